"""Configuration of the simulated world of one docking env (tank, DS, vehicle, currents, camera).

Kept apart from :mod:`uwdock.sim.world` (which needs SAPIEN) so that configs can be built,
loaded and checked without the simulator. The env's config (:class:`uwdock.rl.env.config.EnvConfig`)
nests it as ``EnvConfig.world`` (the TOML table ``[env.world]``). It owns the rules of a world
camera's render width (:func:`camera_width_error`, which ``datasets synth`` applies too).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Annotated, Literal

from uwdock.dockcore.domains import Interval
from uwdock.sim.domains import TANK_SIZE_M, TankSide_m
from uwdock.sim.vehicle import CurrentConfig, Hydrodynamics, VehicleConfig, VehicleRandomisation
from uwdock.sim.water import Water, water_spec_error

__all__ = ["MIN_CAMERA_WIDTH_PX", "WorldConfig", "camera_width_error"]

#: Narrowest render width (px) a world camera may have (0 = the camera file's own width).
MIN_CAMERA_WIDTH_PX = 16


def camera_width_error(width_px: int) -> str | None:
    """Why ``width_px`` cannot be a render width (the camera's intrinsics scaled to it), or None:
    it must be 0 (the camera file's own size) or at least :data:`MIN_CAMERA_WIDTH_PX`. Its upper
    bound is the field's declared domain. The one rule for every config with such a width
    (:class:`WorldConfig`, ``datasets.synth.SynthConfig``)."""
    if width_px and width_px < MIN_CAMERA_WIDTH_PX:
        return f"must be 0 or >= {MIN_CAMERA_WIDTH_PX}, got {width_px}"
    return None


@dataclass(frozen=True)
class WorldConfig:
    """The world of one docking env.

    Attributes:
        physics_hz: physics substep rate (Hz); in a docking env a multiple of its
            ``control_hz``.
        tank_size_m: tank length, width, depth (m); the world origin is at the surface above
            the tank centre (NED), the floor at z = depth.
        marker_set_path: marker set file (None: the default DS set, generated into a cache).
        camera_file: camera YAML/JSON (None: the reference camera and mounting).
        camera_width_px: render width (px): the camera's intrinsics are scaled to it
            (:func:`uwdock.calibration.camera.resolve_camera`); 0 keeps the file's size. 480
            (of the reference 968) keeps the DS markers detectable from the approach altitude
            at a quarter of the render cost (>= 50 control steps/s on one core); fit an error
            model from frames of the same camera and width.
        water_preset: water between the camera and the scene: a :mod:`uwdock.sim.water` preset
            name or a water file (``*.toml`` with a ``[water]`` table, e.g. from
            ``sim fit-water``).
        water_device: None: the water model in numpy/OpenCV on the CPU; a torch device
            ("cuda", "cpu"): :func:`uwdock.sim.water_torch.apply_water_torch` there;
            "auto": on the CUDA GPU SAPIEN renders with, where it renders on one (else None).
        randomise_vehicle: draw the vehicle's parameters (and thruster placement) per episode.
        camera_mount_error_m: the camera's true mounting differs from its calibration by a
            translation drawn per episode, each camera axis uniform within +- this (m); the
            frames are rendered from the true mounting, perception keeps the calibrated one.
        camera_mount_error_deg: likewise a rotation, roll, pitch and yaw of the camera each
            uniform within +- this (deg).
        current: ocean current model.
        vehicle: nominal vehicle.
        vehicle_randomisation: ranges used when ``randomise_vehicle``.
        batch_contact: in the batched simulator (:class:`uwdock.sim.batch.BatchVehicles`),
            where the vehicles that may touch the docking station are stepped: ``"shared"``,
            all in one PhysX scene (faster; trajectories within PhysX's own sensitivity of the
            per-env ones), ``"own"``, each in its own scene (bit-equal to the per-env env), or
            ``"kernel"``, no PhysX: the kernel's own contact model against the station's shapes
            (:mod:`uwdock.sim.kernel_contact`; a different model). A per-env env ignores it.
    """

    physics_hz: Annotated[float, Interval(gt=0, le=5000)] = 300.0
    tank_size_m: tuple[TankSide_m, TankSide_m, TankSide_m] = TANK_SIZE_M
    marker_set_path: str | None = None
    camera_file: str | None = None
    camera_width_px: Annotated[int, Interval(ge=0, le=8192)] = 480
    water_preset: str = "clear_tank"
    water_device: str | None = None
    randomise_vehicle: bool = True
    camera_mount_error_m: Annotated[float, Interval(ge=0, le=0.5)] = 0.0
    camera_mount_error_deg: Annotated[float, Interval(ge=0, le=45)] = 0.0
    current: CurrentConfig = field(default_factory=CurrentConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    vehicle_randomisation: VehicleRandomisation = field(default_factory=VehicleRandomisation)
    batch_contact: Literal["shared", "own", "kernel"] = "shared"

    @property
    def water(self) -> Water:
        """The water :attr:`water_preset` names, as an object (a water file read)."""
        return Water.named(self.water_preset, allow_none=False)

    def validate(self) -> None:
        """Raise ValueError naming the first field that breaks a rule across fields or a name
        (each field's own range is its declared domain)."""
        why = camera_width_error(self.camera_width_px)
        if why is not None:
            raise ValueError(f"camera_width_px: {why}")
        if self.water_device is not None and not re.fullmatch(
            r"(auto|cpu|cuda(:\d+)?|mps)", str(self.water_device)
        ):
            raise ValueError(
                f"water_device: must be None, 'auto', 'cpu', 'cuda', 'cuda:N' or 'mps', got "
                f"{str(self.water_device)[:40]!r}"
            )
        why = water_spec_error(self.water_preset, allow_none=False)
        if why is not None:
            raise ValueError(f"water_preset: {why}")
        # the physics substep must keep the damping stable for every vehicle the world may draw
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
