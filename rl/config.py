"""Configuration of the docking environment (one dataclass, nesting the components it uses)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from rl.estimator import EstimatorConfig
from rl.rewards import RewardConfig
from rl.task import DockingTaskConfig
from sim.vehicle import CurrentConfig, VehicleConfig, VehicleRandomisation

ObsSourceName = Literal["proxy", "error-model", "camera"]


@dataclass(frozen=True)
class EnvConfig:
    """The docking environment (reference.md section 1 and the paper's appendix table).

    Attributes:
        obs_source: how the DS pose is measured: "proxy" (the paper's visibility test +
            Gaussian noise), "error-model" (image-derived noise model) or "camera"
            (render -> detect -> PnP every control step).
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
        randomise_vehicle: draw the vehicle's parameters (and thruster placement) per episode.
        error_model_path: fitted error model file, for ``obs_source = "error-model"``.
        camera_file: camera YAML/JSON for the camera source (None: the reference camera).
        camera_width_px: render width for the camera source (intrinsics scaled from the camera
            file; 0 keeps the file's size). 480 (of the reference 968) keeps the DS markers
            detectable from the approach altitude at a quarter of the render cost (>= 50
            control steps/s on one core); fit the error model from frames of the same camera.
        water_preset: water for the camera source (a ``sim.water`` preset: "clear_tank",
            "coastal", "turbid", "very_turbid").
        marker_set_path: marker set file (None: the default DS set, generated into a cache).
        task: success criteria and docking geometry.
        reward: reward constants.
        estimator: DS pose filter.
        current: ocean current model.
        vehicle: nominal vehicle.
        vehicle_randomisation: ranges used when ``randomise_vehicle``.
    """

    obs_source: ObsSourceName = "proxy"
    control_hz: float = 5.0
    physics_hz: float = 300.0
    episode_s: float = 60.0
    wrench_limits: tuple[float, float, float, float, float, float] = (
        280.0,
        140.0,
        268.0,
        0.0,
        39.0,
        72.0,
    )
    wrench_scale: float = 1.0
    tank_size_m: tuple[float, float, float] = (19.0, 9.0, 5.0)
    spawn_auv_range_m: tuple[float, float, float] = (6.0, 3.0, 1.4)
    spawn_auv_height_m: float = 3.3
    spawn_auv_yaw_deg: float = 180.0
    spawn_ds_range_m: tuple[float, float, float] = (1.0, 2.0, 0.0)
    spawn_ds_yaw_deg: float = 180.0
    terminate_on: Literal["paper", "strict"] = "paper"
    obs_last_action: bool = False
    obs_uncertainty: bool = True
    obs_frames: int = 1
    randomise_vehicle: bool = True
    error_model_path: str | None = None
    camera_file: str | None = None
    camera_width_px: int = 480
    water_preset: str = "clear_tank"
    marker_set_path: str | None = None
    task: DockingTaskConfig = field(default_factory=DockingTaskConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    current: CurrentConfig = field(default_factory=CurrentConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    vehicle_randomisation: VehicleRandomisation = field(default_factory=VehicleRandomisation)

    @property
    def action_limits(self) -> np.ndarray:
        """(6,) wrench of a unit action: ``wrench_limits * wrench_scale`` (N, N m)."""
        return np.asarray(self.wrench_limits, dtype=np.float64) * self.wrench_scale

    def validate(self) -> None:
        ratio = self.physics_hz / self.control_hz
        if self.control_hz <= 0 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("physics_hz: must be a positive multiple of control_hz")
        if self.episode_s <= 0 or self.obs_frames < 1:
            raise ValueError("episode_s must be > 0 and obs_frames >= 1")
        if not 0 < self.wrench_scale <= 1:
            raise ValueError("wrench_scale: must be in (0, 1]")
        if self.spawn_auv_height_m - self.spawn_auv_range_m[2] < 1.5:
            raise ValueError("spawn_auv_height_m: the AUV would spawn inside the DS (< 1.5 m)")
        if self.spawn_auv_height_m + self.spawn_auv_range_m[2] > self.tank_size_m[2] - 0.3:
            raise ValueError("spawn_auv_height_m: the AUV would spawn above the water surface")
        if self.obs_source == "error-model" and not self.error_model_path:
            raise ValueError("error_model_path: required for obs_source 'error-model'")
        from sim.water import PRESET_ORDER

        if self.water_preset not in PRESET_ORDER:
            raise ValueError(
                f"water_preset: unknown {self.water_preset!r} (known: {', '.join(PRESET_ORDER)})"
            )
