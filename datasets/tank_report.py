"""The tank report: how far above the docking station the camera still decodes its markers.

Rendered, not guessed: the camera (the user's intrinsics) looks straight down at the DS origin
(image x along the DS y axis) from a range of altitudes above the DS floor, in a tank deep
enough to keep it under water; each altitude is rendered once by SAPIEN, the water is applied
``draws`` times with different sensor noise (:func:`sim.water.apply_water`), and the default
detector counts the DS markers it decodes. The report gives, per water, the greatest altitude
at which the median number decoded is >= 1 and >= 3, and the count at every altitude (with the
markers in view, from the render's ground truth).

Two of the default DS markers are on the rim, 1.76 m up: below ~2.3 m altitude the camera sees
only the floor markers, so ">= 3" may first hold higher up.

A fitted water (``sim fit-water``'s ``water.toml``) carries its uncertainty in a ``[fit]``
table: the attenuation at -+1 of its relative uncertainty per channel (``beta_D_low_rgb``,
``beta_D_high_rgb``: the larger of the bootstrap over frames and the Jacobian). Such a water is
also rendered at both, all three channels together, the rest of the water kept: the detection
range becomes an interval (the higher attenuation gives its lower end).

``bench/bench_sim.py`` (d) measures the benchmark's detection ranges with this function; it lives in
``datasets`` because it crosses the sim -> perception seam (render, then detect).
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import make_T
from uwdock.dockcore.domains import Interval, Seed
from uwdock.dockcore.io import atomic_path
from uwdock.perception.detector import Detector, rendered_3dbm_config
from uwdock.sim.camera import SimCamera
from uwdock.sim.docking_station import DockingStationConfig
from uwdock.sim.render import make_render_scene
from uwdock.sim.water import WaterConfig

__all__ = ["TankReportConfig", "detection_ranges"]

#: cam_cv axes in the DS frame for a camera looking straight down (DS z is down): x = DS +y.
_R_DS_CAMCV = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class TankReportConfig:
    """Settings of the tank report.

    Attributes:
        altitude_min_m: lowest camera altitude above the DS floor (m).
        altitude_max_m: highest (m); the tank is made deep enough for it.
        altitude_step_m: step between altitudes (m): the resolution of the reported ranges.
        draws: noise draws of the water per altitude; the median count is used.
        seed: seed of the noise draws.
    """

    altitude_min_m: Annotated[float, Interval(gt=0.0, le=100.0)] = 1.0
    altitude_max_m: Annotated[float, Interval(gt=0.0, le=100.0)] = 10.0
    altitude_step_m: Annotated[float, Interval(ge=0.05, le=10.0)] = 0.5
    draws: Annotated[int, Interval(ge=1, le=100)] = 5
    seed: Seed = 0

    def validate(self) -> None:
        """Raise ValueError when the altitudes do not make a range."""
        if self.altitude_max_m < self.altitude_min_m:
            raise ValueError(
                f"altitude_max_m: {self.altitude_max_m} is below altitude_min_m "
                f"{self.altitude_min_m}"
            )

    def altitudes_m(self) -> np.ndarray:
        """The altitudes rendered (m)."""
        return np.arange(
            self.altitude_min_m, self.altitude_max_m + 1e-9, self.altitude_step_m, dtype=float
        )


def detection_ranges(
    camera: CameraModel,
    waters: Mapping[str, WaterConfig],
    cfg: TankReportConfig | None = None,
    marker_set: Any = None,
    progress: Callable[[float], None] | None = None,
    bounds: Mapping[str, tuple[WaterConfig, WaterConfig]] | None = None,
) -> list[dict[str, Any]]:
    """Greatest altitudes at which >= 3 and >= 1 DS markers decode, per water.

    Args:
        camera: the camera's intrinsics (its own resolution).
        waters: water name -> model (presets or fitted water files).
        cfg: altitudes, noise draws, seed.
        marker_set: markers on the DS (object or file); None: the default DS set.
        progress: called with the altitude just rendered (m).
        bounds: water name -> (the water at its higher attenuation, at its lower): rendered
            too, they give the ranges as intervals.

    Returns:
        One row per water (``water``, ``width``, ``max_alt_3_markers_m``,
        ``max_alt_1_marker_m``, ``altitudes_m``, ``decoded_median``; with ``bounds``, also
        ``max_alt_3_markers_interval_m`` and ``max_alt_1_marker_interval_m``, [lower, upper]
        with None where no altitude decoded them) and a last row ``water = "(visible)"`` with
        the markers in view at each altitude.
    """
    bounds = dict(bounds or {})
    cfg = cfg or TankReportConfig()
    cfg.validate()
    altitudes = cfg.altitudes_m()
    counts, visible = _decoded_counts(camera, waters, bounds, altitudes, cfg, marker_set, progress)
    width = f"{camera.width_px}x{camera.height_px}"
    rows = [_water_row(name, width, altitudes, counts, name in bounds) for name in waters]
    rows.append(
        {
            "water": "(visible)",
            "width": width,
            "max_alt_3_markers_m": None,
            "max_alt_1_marker_m": None,
            "altitudes_m": altitudes.tolist(),
            "decoded_median": [float(v) for v in visible],
        }
    )
    return rows


def _decoded_counts(
    camera: CameraModel,
    waters: Mapping[str, WaterConfig],
    bounds: dict[str, tuple[WaterConfig, WaterConfig]],
    altitudes: np.ndarray,
    cfg: TankReportConfig,
    marker_set: Any,
    progress: Callable[[float], None] | None,
) -> tuple[dict[Hashable, list[float]], list[int]]:
    """Render each altitude once and count the markers decoded through each water (and each
    bound, keyed ``(name, "high")`` and ``(name, "low")``); returns the median counts per
    water and the markers in view, both per altitude."""
    tank_depth_m = max(12.0, float(altitudes.max()) + 2.0)
    rs = make_render_scene(
        DockingStationConfig(tank_depth_m=tank_depth_m), marker_set, camera_model=camera
    )
    detector = Detector(rendered_3dbm_config(rs.ds.marker_set.ids))
    sim_camera = SimCamera(rs.rig)  # the water through the camera's one path
    rendered: dict[Hashable, WaterConfig] = dict(waters)
    for name, (high, low) in bounds.items():
        rendered[(name, "high")], rendered[(name, "low")] = high, low
    counts: dict[Hashable, list[float]] = {name: [] for name in rendered}
    visible = []
    for alt in altitudes:
        T_world_cam = rs.ds.T_worldned_ds @ make_T(_R_DS_CAMCV, [0.0, 0.0, -float(alt)])
        res = rs.render(T_worldned_camcv=T_world_cam)
        visible.append(sum(p.visible for p in rs.ground_truth(res).values()))
        for name, water in rendered.items():
            n = []
            for d in range(cfg.draws):
                rng = np.random.default_rng([cfg.seed, d, round(float(alt) * 10)])
                frame = sim_camera.through_water(res, rng, water)
                n.append(len(detector.detect(frame.img_bgr())))
            counts[name].append(float(statistics.median(n)))
        if progress is not None:
            progress(float(alt))
    return counts, visible


def _water_row(
    name: str,
    width: str,
    altitudes: np.ndarray,
    counts: dict[Hashable, list[float]],
    bounded: bool,
) -> dict[str, Any]:
    """Water ``name``'s row of the report; ``bounded``: with the intervals its two bounds give."""
    arr = np.asarray(counts[name])
    row = {
        "water": name,
        "width": width,
        "max_alt_3_markers_m": _greatest(altitudes, arr >= 3),
        "max_alt_1_marker_m": _greatest(altitudes, arr >= 1),
        "altitudes_m": altitudes.tolist(),
        "decoded_median": counts[name],
    }
    if bounded:
        hi, lo = np.asarray(counts[(name, "high")]), np.asarray(counts[(name, "low")])
        for k, key in ((3, "max_alt_3_markers"), (1, "max_alt_1_marker")):
            ends = [_greatest(altitudes, hi >= k), _greatest(altitudes, lo >= k)]
            if None not in ends:  # noise may swap them by a step
                ends = sorted(ends)  # type: ignore[type-var]
            row[f"{key}_interval_m"] = ends
        row["decoded_median_interval"] = [counts[(name, "high")], counts[(name, "low")]]
    return row


def _greatest(altitudes: np.ndarray, ok: np.ndarray) -> float | None:
    return float(altitudes[ok].max()) if ok.any() else None


def plot_ranges(rows: list[dict[str, Any]], path: Any) -> None:
    """Markers decoded (median over noise draws) against altitude, one line per water, the
    markers in view dashed; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.0))
    for r in rows:
        style = {"ls": "--", "color": "0.5"} if r["water"] == "(visible)" else {"marker": "o"}
        ax.plot(r["altitudes_m"], r["decoded_median"], label=r["water"], ms=3, **style)
    for k in (1, 3):
        ax.axhline(k, color="0.8", lw=0.8, zorder=0)
    ax.set_xlabel("camera altitude above the DS floor (m)")
    ax.set_ylabel("DS markers decoded (median)")
    ax.set_title(f"Tank report: detection range, camera {rows[0]['width']}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
