"""The settings of a synthetic dataset (``datasets synth``, :mod:`datasets.synth`): how poses
are drawn and what is rendered; below the renderer and its output folder
(:mod:`datasets.synth_folder`), which both read them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated

from uwdock.dockcore.domains import Fraction, Interval, Seed
from uwdock.sim.docking_station import DockingStationConfig
from uwdock.sim.render import RenderConfig
from uwdock.sim.water import WaterRandomisation, water_spec_error
from uwdock.sim.world_config import camera_width_error

__all__ = ["PoseSamplingConfig", "SynthConfig", "station_config"]

#: Frames of a dataset: a million full-size frames are about 600 GB.
_Frames = Annotated[int, Interval(ge=1, le=10**6)]
#: A distance of the pose sampler (m).
_Distance_m = Annotated[float, Interval(ge=0, le=100)]
#: A camera-to-DS range of aimed frames (m).
_Range_m = Annotated[float, Interval(gt=0, le=100)]
#: A tilt from straight down (deg).
_Tilt_deg = Annotated[float, Interval(ge=0, lt=90)]


@dataclass(frozen=True)
class PoseSamplingConfig:
    """How vehicle poses are drawn (module docstring).

    Attributes:
        aimed_fraction: probability that a frame is aimed at the DS (-), in [0, 1].
        aimed_range_m: (lo, hi) uniform distance camera -> DS origin of aimed frames (m).
        aimed_tilt_max_deg: largest tilt of the optical axis from straight down (deg); the tilt
            is uniform over the spherical cap (vehicle roll/pitch).
        aimed_image_margin: the DS origin's pixel is uniform over the image shrunk by this
            fraction of its width/height on every side (-), in [0, 0.5).
        uniform_range_m: (x, y, z) half-widths of the box around the nominal AUV position (m).
        uniform_height_m: nominal height of the AUV origin above the DS floor (m).
        uniform_tilt_max_deg: largest roll/pitch tilt of uniform frames (deg).
        min_depth_m: the camera stays at least this deep below the water surface (m).
        min_height_m: the camera stays at least this high above the DS floor (m).
        tank_margin_m: the AUV origin stays this far inside the tank walls (m).
    """

    aimed_fraction: Fraction = 0.8
    aimed_range_m: tuple[_Range_m, _Range_m] = (1.0, 6.0)
    aimed_tilt_max_deg: _Tilt_deg = 25.0
    aimed_image_margin: Annotated[float, Interval(ge=0, lt=0.5)] = 0.1
    uniform_range_m: tuple[_Distance_m, _Distance_m, _Distance_m] = (6.0, 3.0, 1.4)
    uniform_height_m: _Distance_m = 3.3
    uniform_tilt_max_deg: _Tilt_deg = 5.0
    min_depth_m: _Distance_m = 0.3
    min_height_m: _Distance_m = 0.3
    tank_margin_m: _Distance_m = 0.8

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field (comparisons fail on NaN)."""
        lo, hi = self.aimed_range_m
        if not 0.0 < lo <= hi:
            raise ValueError(f"aimed_range_m: need 0 < lo <= hi, got {self.aimed_range_m}")

    def check_tank(self, ds: DockingStationConfig) -> None:
        """Raise ValueError when no pose can satisfy the limits in the tank of ``ds`` (the
        sampler would give up after its draws and keep a pose outside them)."""
        floor_m = ds.tank_depth_m - ds.floor_thickness_m  # water above the DS floor
        half_m = min(ds.tank_length_m, ds.tank_width_m) / 2
        if not self.min_depth_m + self.min_height_m < floor_m:
            raise ValueError(
                f"min_depth_m: with min_height_m, must be < {floor_m:g} m (the water above the "
                f"DS floor), got {self.min_depth_m:g} + {self.min_height_m:g}"
            )
        if not self.tank_margin_m < half_m:
            raise ValueError(
                f"tank_margin_m: must be < {half_m:g} m (half the tank's width), "
                f"got {self.tank_margin_m:g}"
            )
        if not self.uniform_height_m < floor_m:
            raise ValueError(
                f"uniform_height_m: must be < {floor_m:g} m (the water above the DS floor), "
                f"got {self.uniform_height_m:g}"
            )
        reach_m = math.hypot(  # the farthest a camera in the tank gets from the DS origin
            ds.tank_length_m / 2 - self.tank_margin_m,
            ds.tank_width_m / 2 - self.tank_margin_m,
            floor_m - self.min_depth_m,
        )
        if self.aimed_fraction > 0 and not self.aimed_range_m[0] < reach_m:
            raise ValueError(
                f"aimed_range_m: the shortest range must be < {reach_m:.1f} m (no camera in the "
                f"tank is farther from the DS), got {self.aimed_range_m[0]:g}"
            )


@dataclass(frozen=True)
class SynthConfig:
    """A synthetic labelled dataset.

    Attributes:
        n_frames: number of frames (1 ... 10^6).
        seed: base seed (0 ... 2^32 - 1); frame k uses ``SeedSequence([seed, k])``.
        water: a water preset name (``sim.water.PRESETS``), a water file (``*.toml`` with a
            ``[water]`` table, e.g. from ``sim fit-water``), "random" (a fresh
            :class:`WaterRandomisation` draw per frame) or "none" (the clean render).
        water_randomisation: ranges of the per-frame draw when ``water = "random"``.
        camera_file: camera YAML/JSON (intrinsics and ``T_body_cam``; a file without
            ``T_body_cam`` gets the reference extrinsics); None: the reference downward camera.
        width_px: render width (px, 16 ... 8192; the height keeps the aspect ratio,
            intrinsics scaled); 0 keeps the camera's size.
        marker_set_path: marker set file (with render meshes); None: the default DS set.
        occlusion_tol_m: a marker corner is occluded when the rendered surface along its ray is
            nearer than the corner by more than this (m).
        poses: how poses are drawn.
        render: renderer and lamp.
    """

    n_frames: _Frames = 100
    seed: Seed = 0
    water: str = "random"
    water_randomisation: WaterRandomisation = field(default_factory=WaterRandomisation)
    camera_file: str | None = None
    width_px: Annotated[int, Interval(ge=0, le=8192)] = 0
    marker_set_path: str | None = None
    occlusion_tol_m: Annotated[float, Interval(ge=0, le=10)] = 0.03
    poses: PoseSamplingConfig = field(default_factory=PoseSamplingConfig)
    render: RenderConfig = field(default_factory=RenderConfig)

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        why = water_spec_error(self.water, allow_random=True)
        if why is not None:
            raise ValueError(f"water: {why}")
        why = camera_width_error(self.width_px)
        if why is not None:
            raise ValueError(f"width_px: {why}")
        try:
            self.poses.check_tank(station_config(self))
        except ValueError as exc:
            raise ValueError(f"poses.{exc}") from None


def station_config(cfg: SynthConfig) -> DockingStationConfig:
    """The docking station (and tank) of a dataset's scenes."""
    return DockingStationConfig(marker_set_path=cfg.marker_set_path)
