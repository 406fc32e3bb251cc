"""Configuration of the docking environment (one dataclass, nesting the components it uses)."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Any, ClassVar, Literal

import numpy as np

from uwdock.calibration.camera import load_camera
from uwdock.dockcore.config import field_path, replace_at, value_at
from uwdock.dockcore.domains import Interval
from uwdock.markers.markerset import load_marker_set, marker_set_files
from uwdock.rl.env.error_model import load_error_model
from uwdock.rl.env.estimator import EstimatorConfig
from uwdock.rl.env.rewards import RewardConfig
from uwdock.rl.env.task import DockingTaskConfig
from uwdock.sim.navigation import NavConfig
from uwdock.sim.usbl import USBL_PRESETS, UsblConfig
from uwdock.sim.water import is_water_file
from uwdock.sim.world_config import WorldConfig

ObsSourceName = Literal["proxy", "error-model", "camera", "acoustic"]

_Wrench = Annotated[float, Interval(ge=0, le=10_000)]  # N or N m at action +-1
_Range = Annotated[float, Interval(ge=0, le=1000)]  # m, half-width of a spawn box
_HalfTurn = Annotated[float, Interval(ge=0, le=180)]  # deg

#: The :class:`WorldConfig` fields that ``[env]`` tables held flat before ``[env.world]``
#: existed (every run folder and shipped policy of that time); frozen: a field added to the
#: world later is only ever read from ``[env.world]``.
LEGACY_WORLD_KEYS = (
    "physics_hz",
    "tank_size_m",
    "marker_set_path",
    "camera_file",
    "camera_width_px",
    "water_preset",
    "water_device",
    "randomise_vehicle",
    "camera_mount_error_m",
    "camera_mount_error_deg",
    "current",
    "vehicle",
    "vehicle_randomisation",
)

#: ``[estimator]`` keys of configs written before ``[usbl]`` existed, where they held the "ideal"
#: acoustic model's numbers, and the :class:`UsblConfig` field each one is.
LEGACY_IDEAL_USBL_KEYS: Mapping[str, str] = MappingProxyType(
    {
        "usbl_period_s": "period_s",
        "usbl_sigma_floor_m": "sigma_floor_m",
        "usbl_sigma_per_m": "sigma_per_m",
    }
)


@dataclass(frozen=True)
class EnvConfig:
    """The docking environment (docs/reference-system.md section 1 and the paper's appendix table).

    The simulated world (tank, DS markers, camera, water, vehicle, currents) is one nested
    config, :attr:`world` (:class:`~uwdock.sim.world_config.WorldConfig`, the TOML table
    ``[env.world]``), the one config :class:`uwdock.sim.world.DockingWorld` reads. Run folders
    and policies written before it existed keep the world's keys flat in ``[env]``
    (``physics_hz``, ``camera_width_px``, ``[env.vehicle]``, ...): the loader lifts those
    (:data:`LEGACY_WORLD_KEYS`) into ``world``, so they load unchanged; a key given both flat
    and in ``[env.world]`` is refused.

    Attributes:
        obs_source: how the DS pose is measured: "proxy" (the paper's visibility test +
            Gaussian noise), "error-model" (image-derived noise model), "camera"
            (render -> detect -> PnP every control step) or "acoustic" (no camera: the
            acoustic fixes alone, the camera-off ablation).
        control_hz: policy (and camera) rate (Hz).
        episode_s: truncation time (s).
        wrench_limits: body wrench at action +-1 [Fx, Fy, Fz (N), Mx, My, Mz (N m)]. Defaults:
            the reference's generalised limits (surge 280 N, sway 140 N, pitch 39 N m, yaw 72 N m)
            with heave at the 268 N the heave pair reaches; roll is not actuated (0).
        wrench_scale: safety factor on the limits (the tank trials clipped to 0.25-0.5).
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
        obs_contact: append what the vehicle can tell of its contacts from its own sensors:
            a trace of the IMU-detected collisions and how long it has been at rest
            (:class:`rl.env.observation.ContactMemory`; ours, not in the paper's observation), so
            a policy can tell it is wedged or has landed off the seat.
        obs_fine_error: append the estimated error to the docking point again as tanh(e /
            0.1 m) (3 values; :data:`rl.env.observation.FINE_ERROR_SCALE_M`): the error's first
            entries are scaled by 5 m, so the seat's last centimetres are a few hundredths of
            them; these resolve them (ours, not in the paper's observation).
        obs_frames: stack this many observation frames (1 = no history).
        obs_privileged: asymmetric actor-critic: the observation ends with privileged state
            (true errors, the estimate's error, time left) that only the critic reads and only
            training envs fill (:mod:`rl.env.observation`, :mod:`rl.policy.asymmetric`).
        error_model_path: fitted error model file, for ``obs_source = "error-model"``.
        error_model_memory: sample the error model's fitted memory (the AR(1) correlation of
            consecutive steps' pose errors, ``rl.env.error_model``); False: every step's error is
            drawn independently. Models without memory (version 1) are memoryless either way.
        task: success criteria and docking geometry.
        reward: reward constants.
        estimator: DS pose filter.
        usbl: the acoustic (USBL) positioning of the DS that sources with
            ``needs.acoustic_fixes`` receive (:mod:`uwdock.sim.usbl`; the approach is
            acoustic, the final servoing visual; the paper's proxy takes none): a preset name
            plus any field overriding it; :attr:`usbl_model` is the model the env simulates.
            Configs written before this table held the "ideal" model's numbers in
            ``[estimator]`` (:data:`LEGACY_IDEAL_USBL_KEYS`); the loader moves them here
            (:meth:`upgrade_layout`).
        nav: the vehicle's navigation (:mod:`uwdock.sim.navigation`): a preset name ("ideal":
            the vehicle knows its true pose; "mems-ahrs-dvl": dead reckoning over a DVL, an AHRS
            and a depth sensor that drifts) plus any field overriding it. Measurements of the
            DS are turned into the world with the navigation pose and the policy sees the
            docking point relative to it.
        world: the simulated world: tank, DS marker set, camera (file, render width, mounting
            error), water, vehicle (nominal and randomised) and ocean current.
    """

    #: Keys of :attr:`world` that an ``[env]`` table written before it existed holds flat; the
    #: loader lifts them into ``world`` (:func:`uwdock.dockcore.config.current_layout`).
    MOVED_KEYS: ClassVar[Mapping[str, str]] = MappingProxyType(
        dict.fromkeys(LEGACY_WORLD_KEYS, "world")
    )

    obs_source: ObsSourceName = "proxy"
    control_hz: Annotated[float, Interval(gt=0, le=100)] = 5.0
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
    spawn_auv_range_m: tuple[_Range, _Range, _Range] = (6.0, 3.0, 1.4)
    spawn_auv_height_m: Annotated[float, Interval(gt=0, le=100)] = 3.3
    spawn_auv_yaw_deg: _HalfTurn = 180.0
    spawn_ds_range_m: tuple[_Range, _Range, _Range] = (1.0, 2.0, 0.0)
    spawn_ds_yaw_deg: _HalfTurn = 180.0
    spawn_horizontal_range_m: tuple[_Range, _Range] = (0.0, 1000.0)
    terminate_on: Literal["paper", "strict"] = "paper"
    obs_last_action: bool = False
    obs_uncertainty: bool = True
    obs_contact: bool = False
    obs_fine_error: bool = False
    obs_frames: Annotated[int, Interval(ge=1, le=64)] = 1
    obs_privileged: bool = False
    error_model_path: str | None = None
    error_model_memory: bool = True
    task: DockingTaskConfig = field(default_factory=DockingTaskConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    usbl: UsblConfig = field(default_factory=UsblConfig)
    nav: NavConfig = field(default_factory=NavConfig)
    world: WorldConfig = field(default_factory=WorldConfig)

    @classmethod
    def upgrade_layout(cls, data: Mapping[str, Any]) -> Mapping[str, Any]:
        """Plain ``[env]`` data with the "ideal" USBL numbers of an older ``[estimator]``
        (:data:`LEGACY_IDEAL_USBL_KEYS`) moved into ``[usbl]``: where its ``[usbl]`` names no
        other preset, each one that differs from the ideal preset's and that ``[usbl]`` does
        not set itself becomes that ``[usbl]`` field (the model such a file ran); the others
        described nothing the env simulated and are dropped."""
        est = data.get("estimator")
        if not isinstance(est, Mapping) or not any(k in est for k in LEGACY_IDEAL_USBL_KEYS):
            return data
        out = dict(data)
        est = dict(est)
        moved = {new: est.pop(old) for old, new in LEGACY_IDEAL_USBL_KEYS.items() if old in est}
        out["estimator"] = est
        usbl = out.get("usbl", {})
        if isinstance(usbl, Mapping) and usbl.get("preset", "ideal") == "ideal":
            ideal = USBL_PRESETS["ideal"]
            own = {k: v for k, v in moved.items() if usbl.get(k) is None and v != getattr(ideal, k)}
            if own:
                out["usbl"] = {**usbl, **own}
        return out

    @property
    def usbl_model(self) -> UsblConfig:
        """The acoustic model the env simulates, every field set: :attr:`usbl`'s preset, then
        its own fields."""
        return self.usbl.resolved()

    @property
    def action_limits(self) -> np.ndarray:
        """(6,) wrench of a unit action: ``wrench_limits * wrench_scale`` (N, N m)."""
        return np.asarray(self.wrench_limits, dtype=np.float64) * self.wrench_scale

    def validate(self) -> None:
        """Raise ValueError naming the first field that breaks a rule across fields (the world's
        own rules are :meth:`WorldConfig.validate`'s, reported under ``world.``)."""
        w = self.world
        ratio = w.physics_hz / self.control_hz  # inf for a control_hz of 5e-324
        if self.control_hz <= 0 or not np.isfinite(ratio) or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("world.physics_hz: must be a positive multiple of control_hz")
        if round(self.episode_s * self.control_hz) < 1:
            raise ValueError(
                f"episode_s: {self.episode_s:g} s is shorter than one control step "
                f"({1 / self.control_hz:g} s)"
            )
        try:
            w.validate()  # camera width, water, the physics substep against the vehicle
        except ValueError as exc:
            text = str(exc)
            keyed = re.match(r"[A-Za-z_][\w.\[\]]*: ", text)
            raise ValueError(f"world.{text}" if keyed else f"world: {text}") from None
        length_m, width_m, depth_m = w.tank_size_m
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
        if self.spawn_auv_height_m + self.spawn_auv_range_m[2] > depth_m - 0.3:
            raise ValueError("spawn_auv_height_m: the AUV would spawn above the water surface")
        if self.obs_source == "error-model" and not self.error_model_path:
            raise ValueError(
                "error_model_path: required for obs_source 'error-model' (rl train/eval: "
                "--error-model FILE, e.g. rl/models/error_model_clear_tank_480.json)"
            )


#: The fields of an env config that may name an input file, as typed selectors' paths.
INPUT_FILE_FIELDS: tuple[tuple[str, ...], ...] = (
    field_path(EnvConfig, lambda c: c.error_model_path),
    field_path(EnvConfig, lambda c: c.world.camera_file),
    field_path(EnvConfig, lambda c: c.world.marker_set_path),
    field_path(EnvConfig, lambda c: c.world.water_preset),
)


def env_input_files(cfg: EnvConfig) -> dict[tuple[str, ...], str]:
    """The files an env of ``cfg`` reads, by config field path (``("world", "camera_file")``,
    ...; :data:`INPUT_FILE_FIELDS`): the error model (for the error-model source), the camera,
    the marker set and a water file."""
    out: dict[tuple[str, ...], str] = {}
    for path in INPUT_FILE_FIELDS:
        value = value_at(cfg, path)
        if not value:
            continue
        if path == ("error_model_path",) and cfg.obs_source != "error-model":
            continue
        if path == ("world", "water_preset") and not is_water_file(value):
            continue  # a preset's name
        out[path] = value
    return out


def with_input_files(cfg: EnvConfig, where: Callable[[str], str]) -> EnvConfig:
    """``cfg`` with each input file (:func:`env_input_files`) replaced by ``where(file)``."""
    for path, value in env_input_files(cfg).items():
        cfg = replace_at(cfg, path, where(value))
    return cfg


def with_absolute_inputs(cfg: EnvConfig) -> EnvConfig:
    """``cfg`` with its input files (:func:`env_input_files`) as absolute paths from this
    process's working directory: what a worker elsewhere (another folder, another node that
    mounts the same storage) opens is then what this process meant."""
    return with_input_files(cfg, lambda p: str(Path(p).expanduser().resolve()))


def absolute_inputs(cfg: EnvConfig) -> tuple[EnvConfig, list[str]]:
    """:func:`with_absolute_inputs` and the absolute input files it names, with the render
    meshes its marker set names: what a job whose workers may start elsewhere sends them
    (``dockcore.pool.PoolConfig.inputs``) or checks on every node."""
    cfg = with_absolute_inputs(cfg)
    files = list(env_input_files(cfg).values())
    if cfg.world.marker_set_path:
        files += [f for f in marker_set_files(cfg.world.marker_set_path) if f not in files]
    return cfg, files


def check_env_files(cfg: EnvConfig) -> None:
    """Read the files an env of ``cfg`` will read (error model, camera, marker set), so a
    missing or broken one is a one-line DockError in the calling process, before worker
    processes start or any output is written."""
    if cfg.obs_source == "error-model":
        load_error_model(cfg.error_model_path)
    if cfg.world.camera_file:
        load_camera(cfg.world.camera_file)
    if cfg.world.marker_set_path:
        load_marker_set(cfg.world.marker_set_path)
