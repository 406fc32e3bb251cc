"""Configuration of the docking environment (one dataclass, nesting the components it uses)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np

from uwdock.calibration.camera import load_camera
from uwdock.dockcore.domains import Interval
from uwdock.markers.markerset import load_marker_set
from uwdock.rl.error_model import load_error_model
from uwdock.rl.estimator import EstimatorConfig
from uwdock.rl.rewards import RewardConfig
from uwdock.rl.task import DockingTaskConfig
from uwdock.sim.domains import TANK_SIZE_M
from uwdock.sim.usbl import UsblConfig
from uwdock.sim.vehicle import CurrentConfig, Hydrodynamics, VehicleConfig, VehicleRandomisation
from uwdock.sim.world_config import WorldConfig

ObsSourceName = Literal["proxy", "error-model", "camera", "acoustic"]

_Wrench = Annotated[float, Interval(ge=0, le=10_000)]  # N or N m at action +-1
_TankSide = Annotated[float, Interval(gt=0, le=1000)]  # m
_Range = Annotated[float, Interval(ge=0, le=1000)]  # m, half-width of a spawn box
_HalfTurn = Annotated[float, Interval(ge=0, le=180)]  # deg


@dataclass(frozen=True)
class EnvConfig:
    """The docking environment (reference.md section 1 and the paper's appendix table).

    The world's fields (``physics_hz``, ``tank_size_m``, ``marker_set_path``, ``camera_file``,
    ``camera_width_px``, ``water_preset``, ``randomise_vehicle``, ``camera_mount_error_m``,
    ``camera_mount_error_deg``, ``current``, ``vehicle``, ``vehicle_randomisation``) are kept
    as flat keys, the layout of every run folder and exported policy; :attr:`world` is the
    :class:`~uwdock.sim.world_config.WorldConfig` built from them, the one config the simulated
    world (:class:`uwdock.sim.world.DockingWorld`) reads.

    Attributes:
        obs_source: how the DS pose is measured: "proxy" (the paper's visibility test +
            Gaussian noise), "error-model" (image-derived noise model), "camera"
            (render -> detect -> PnP every control step) or "acoustic" (no camera: the
            acoustic fixes alone, the camera-off ablation).
        control_hz: policy (and camera) rate (Hz).
        physics_hz: physics substep rate (Hz); a multiple of ``control_hz``.
        episode_s: truncation time (s).
        wrench_limits: body wrench at action +-1 [Fx, Fy, Fz (N), Mx, My, Mz (N m)]. Defaults:
            the reference's generalised limits (surge 280 N, sway 140 N, pitch 39 N m, yaw 72 N m)
            with heave at the 268 N the heave pair reaches; roll is not actuated (0).
        wrench_scale: safety factor on the limits (the tank trials clipped to 0.25-0.5).
        tank_size_m: tank length, width, depth (m); the world origin is at the surface above
            the tank centre (NED), the floor at z = depth.
        spawn_auv_range_m: AUV origin uniform within +- this of (tank centre, nominal height).
        spawn_auv_height_m: nominal height of the AUV origin above the DS floor at spawn (m);
            3.3 +- 1.4 keeps the paper's range inside the 5 m tank (spawns that would touch the
            DS are redrawn).
        spawn_auv_yaw_deg: AUV yaw uniform within +- this (deg).
        spawn_ds_range_m: DS origin uniform within +- this of the tank centre on the floor (m).
        spawn_ds_yaw_deg: DS yaw uniform within +- this (deg).
        spawn_horizontal_range_m: the AUV's horizontal distance from the DS at spawn, (min,
            max): spawns outside are redrawn (m); e.g. (8, 10) with a wider spawn box for a
            long approach. The default accepts every spawn of the box.
        terminate_on: "paper" (the paper's docking condition ends the episode, +p_s) or
            "strict" (pegs seated in the notches, held ``task.strict_hold_s``).
        obs_last_action: append the previous action to the observation (the paper's reference
            code does). Off by default: a policy imitated from a teacher with it learns to copy
            its previous action, so sampled exploration noise snowballs (measured: 0 % docking
            with sampled actions against 50-88 % without it) and PPO fine-tuning collapses.
        obs_uncertainty: append the filter's horizontal standard deviation (m, clipped to 2)
            and whether the DS was detected this step (0/1), so a policy can tell a fresh
            camera fix from a stale or acoustic estimate (not in the paper's observation).
        obs_frames: stack this many observation frames (1 = no history).
        obs_privileged: asymmetric actor-critic: the observation ends with privileged state
            (true errors, the estimate's error, time left) that only the critic reads and only
            training envs fill (:mod:`rl.observation`, :mod:`rl.asymmetric`).
        randomise_vehicle: draw the vehicle's parameters (and thruster placement) per episode.
        camera_mount_error_m: per-episode error of the camera's true mounting against its
            calibration, each axis within +- this (m) (the camera source only).
        camera_mount_error_deg: likewise in roll, pitch and yaw (deg).
        error_model_path: fitted error model file, for ``obs_source = "error-model"``.
        error_model_memory: sample the error model's fitted memory (the AR(1) correlation of
            consecutive steps' pose errors, ``rl.error_model``); False: every step's error is
            drawn independently. Models without memory (version 1) are memoryless either way.
        camera_file: camera YAML/JSON for the camera source (None: the reference camera).
        camera_width_px: render width for the camera source (intrinsics scaled from the camera
            file; 0 keeps the file's size). 480 (of the reference 968) keeps the DS markers
            detectable from the approach altitude at a quarter of the render cost (>= 50
            control steps/s on one core); fit the error model from frames of the same camera.
        water_preset: water for the camera source (a ``sim.water`` preset: "clear_tank",
            "coastal", "turbid", "very_turbid", or a water file ``*.toml`` from
            ``sim fit-water``).
        water_device: None runs the water model with numpy/OpenCV on the CPU (the default);
            a torch device ("cuda", "cuda:1", "cpu") runs it with torch there
            (:mod:`uwdock.sim.water_torch`: the same image within one grey level); "auto" on
            the CUDA GPU SAPIEN renders with, where it renders on one (else numpy).
        marker_set_path: marker set file (None: the default DS set, generated into a cache).
        task: success criteria and docking geometry.
        reward: reward constants.
        estimator: DS pose filter. Its ``usbl_*`` fields are the period and noise of the
            "ideal" acoustic model (kept there so run folders written before :attr:`usbl`
            existed load and run unchanged); other presets carry their own.
        usbl: the acoustic (USBL) positioning of the DS that sources with
            ``needs.acoustic_fixes`` receive (:mod:`uwdock.sim.usbl`): a preset name plus any
            field overriding it; :attr:`usbl_model` is the model the env simulates.
        current: ocean current model.
        vehicle: nominal vehicle.
        vehicle_randomisation: ranges used when ``randomise_vehicle``.
    """

    obs_source: ObsSourceName = "proxy"
    control_hz: Annotated[float, Interval(gt=0, le=100)] = 5.0
    physics_hz: Annotated[float, Interval(gt=0, le=5000)] = 300.0
    episode_s: Annotated[float, Interval(gt=0, le=3600)] = 60.0
    wrench_limits: tuple[_Wrench, _Wrench, _Wrench, _Wrench, _Wrench, _Wrench] = (
        280.0,
        140.0,
        268.0,
        0.0,
        39.0,
        72.0,
    )
    wrench_scale: Annotated[float, Interval(gt=0, le=1)] = 1.0
    tank_size_m: tuple[_TankSide, _TankSide, _TankSide] = TANK_SIZE_M
    spawn_auv_range_m: tuple[_Range, _Range, _Range] = (6.0, 3.0, 1.4)
    spawn_auv_height_m: Annotated[float, Interval(gt=0, le=100)] = 3.3
    spawn_auv_yaw_deg: _HalfTurn = 180.0
    spawn_ds_range_m: tuple[_Range, _Range, _Range] = (1.0, 2.0, 0.0)
    spawn_ds_yaw_deg: _HalfTurn = 180.0
    spawn_horizontal_range_m: tuple[_Range, _Range] = (0.0, 1000.0)
    terminate_on: Literal["paper", "strict"] = "paper"
    obs_last_action: bool = False
    obs_uncertainty: bool = True
    obs_frames: Annotated[int, Interval(ge=1, le=64)] = 1
    obs_privileged: bool = False
    randomise_vehicle: bool = True
    camera_mount_error_m: Annotated[float, Interval(ge=0, le=0.5)] = 0.0
    camera_mount_error_deg: Annotated[float, Interval(ge=0, le=45)] = 0.0
    error_model_path: str | None = None
    error_model_memory: bool = True
    camera_file: str | None = None
    camera_width_px: Annotated[int, Interval(ge=0, le=8192)] = 480
    water_preset: str = "clear_tank"
    water_device: str | None = None
    marker_set_path: str | None = None
    task: DockingTaskConfig = field(default_factory=DockingTaskConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    usbl: UsblConfig = field(default_factory=UsblConfig)
    current: CurrentConfig = field(default_factory=CurrentConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    vehicle_randomisation: VehicleRandomisation = field(default_factory=VehicleRandomisation)

    @property
    def world(self) -> WorldConfig:
        """The simulated world's config, built from this config's world fields."""
        return WorldConfig(
            physics_hz=self.physics_hz,
            tank_size_m=self.tank_size_m,
            marker_set_path=self.marker_set_path,
            camera_file=self.camera_file,
            camera_width_px=self.camera_width_px,
            water_preset=self.water_preset,
            water_device=self.water_device,
            randomise_vehicle=self.randomise_vehicle,
            camera_mount_error_m=self.camera_mount_error_m,
            camera_mount_error_deg=self.camera_mount_error_deg,
            current=self.current,
            vehicle=self.vehicle,
            vehicle_randomisation=self.vehicle_randomisation,
        )

    @property
    def usbl_model(self) -> UsblConfig:
        """The acoustic model the env simulates, every field set: :attr:`usbl`'s preset, for
        "ideal" with the period and noise of ``estimator.usbl_*``, then :attr:`usbl`'s own
        fields."""
        base: dict[str, float] = {}
        if self.usbl.preset == "ideal":
            e = self.estimator
            base = {
                "period_s": e.usbl_period_s,
                "sigma_floor_m": e.usbl_sigma_floor_m,
                "sigma_per_m": e.usbl_sigma_per_m,
            }
        return self.usbl.resolved(**base)

    @property
    def action_limits(self) -> np.ndarray:
        """(6,) wrench of a unit action: ``wrench_limits * wrench_scale`` (N, N m)."""
        return np.asarray(self.wrench_limits, dtype=np.float64) * self.wrench_scale

    def validate(self) -> None:
        ratio = self.physics_hz / self.control_hz
        if self.control_hz <= 0 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("physics_hz: must be a positive multiple of control_hz")
        if round(self.episode_s * self.control_hz) < 1:
            raise ValueError(
                f"episode_s: {self.episode_s:g} s is shorter than one control step "
                f"({1 / self.control_hz:g} s)"
            )
        self.world.validate()  # camera width, water preset
        length_m, width_m, _ = self.tank_size_m
        if self.spawn_auv_range_m[0] >= length_m / 2 or self.spawn_auv_range_m[1] >= width_m / 2:
            raise ValueError(
                f"spawn_auv_range_m: the spawn box {self.spawn_auv_range_m[:2]} m reaches the "
                f"walls of a {length_m:g} x {width_m:g} m tank"
            )
        lo_m, hi_m = self.spawn_horizontal_range_m
        if not lo_m < hi_m:
            raise ValueError(
                f"spawn_horizontal_range_m: min {lo_m:g} m must be below max {hi_m:g} m"
            )
        if self.spawn_ds_range_m[0] >= length_m / 2 or self.spawn_ds_range_m[1] >= width_m / 2:
            raise ValueError(
                f"spawn_ds_range_m: {self.spawn_ds_range_m[:2]} m reaches the tank walls"
            )
        if self.spawn_auv_height_m - self.spawn_auv_range_m[2] < 1.5:
            raise ValueError("spawn_auv_height_m: the AUV would spawn inside the DS (< 1.5 m)")
        if self.spawn_auv_height_m + self.spawn_auv_range_m[2] > self.tank_size_m[2] - 0.3:
            raise ValueError("spawn_auv_height_m: the AUV would spawn above the water surface")
        if self.obs_source == "error-model" and not self.error_model_path:
            raise ValueError(
                "error_model_path: required for obs_source 'error-model' (rl train/eval: "
                "--error-model FILE, e.g. rl/models/error_model_clear_tank_480.json)"
            )
        # the physics substep must keep the damping stable for every vehicle the env may draw
        limit_s = Hydrodynamics(self.vehicle).stable_substep_s()
        if self.randomise_vehicle:
            r = self.vehicle_randomisation
            shrink = 1 - max(r.mass_rel, r.inertia_rel, r.added_mass_rel)
            limit_s *= shrink / (1 + r.damping_rel)
        if not 1.0 / self.physics_hz < limit_s:
            raise ValueError(
                f"vehicle.linear_damping: too stiff for physics_hz {self.physics_hz:g} (the "
                f"vehicle's damping and mass need a substep < {limit_s:.3g} s, randomised draws "
                "included): lower the damping, raise the mass or physics_hz"
            )


def check_env_files(cfg: EnvConfig) -> None:
    """Read the files an env of ``cfg`` will read (error model, camera, marker set), so a
    missing or broken one is a one-line DockError in the calling process, before worker
    processes start or any output is written."""
    if cfg.obs_source == "error-model":
        load_error_model(cfg.error_model_path)
    if cfg.camera_file:
        load_camera(cfg.camera_file)
    if cfg.marker_set_path:
        load_marker_set(cfg.marker_set_path)
