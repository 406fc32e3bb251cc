"""The water fitted to the user's tank: ``sim fit-water``.

The simulator's underwater model (:func:`uwdock.sim.water.apply_water`) gives, per colour
channel ``c``, the linear intensity of a surface point at range ``r``::

    I_c = V(rho) * (J_c * exp(-p beta_D_c r) + B_inf_c * (1 - exp(-beta_B_c r)))

with ``J`` the in-air radiance, ``p = 2`` when a lamp beside the camera lights the scene (the
light travels to the target and back) and 1 under ambient light, and ``V = 1 - s rho**2`` the
vignetting. A known target (a chessboard, or the DS marker board) posed by PnP gives, in every
frame, black and white patches of known geometry: their range ``r``, their distance ``d`` to
the lamp and the cosine of the lamp's incidence. Three lighting models give the in-air radiance
of a patch of albedo class ``k`` (:mod:`datasets.water_fit_model`): ``lamp`` (``a_kc cos /
d**2``), ``both`` (``a_kc (eta + cos / d**2)``: the lamp plus a uniform ambient light ``eta``,
one ratio for the three channels, as the renderer lights a scene) and ``ambient`` (``a_kc``,
``p = 1``: tank or room lights only). The difference white - black carries the direct signal
(``beta_D``), the black level the backscatter (``B_inf``, ``beta_B``), the spread of patch
positions in the image the vignetting; all parameters are fitted jointly by weighted least
squares (:func:`scipy.optimize.least_squares` with the model's analytic Jacobian, 2 % relative
+ 0.002 absolute uncertainty per patch, a few starts).

What the frames can tell (:mod:`datasets.water_fit_judge`): with ``lighting = "auto"`` every
model is fitted and the one with the least error on held-out frames (folds of whole frames,
no random draw) is chosen; the uncertainty is the larger of the Jacobian's standard error and
the spread over a bootstrap of whole frames; and each of ``beta_D``, ``B_inf``, ``beta_B`` per
channel is *determined* unless it sits at a bound, its backscatter is not separable over the
ranges seen (:func:`backscatter_separable`: in clear water only ``B_inf * beta_B`` is), its
uncertainty is large, the modelled contrast misses the frames', or another lighting model that
fits the held-out frames about as well gives a value beyond the uncertainties. The report says
what to film to pin an undetermined value down; the command writes no water file when
``beta_D`` is undetermined.

It lives in ``datasets``: it crosses the sim -> perception seam (the water model of ``sim``,
the detector and PnP of ``perception``); ``sim fit-water`` is its command.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Annotated, Any

import cv2
import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import make_T
from uwdock.calibration.patterns import PatternDetector
from uwdock.datasets import water_fit_model as wm
from uwdock.datasets.water_fit_judge import (
    ModelResult,
    Verdict,
    block_std,
    frame_folds,
    judge,
    lamp_not_seen,
    lamp_share,
)
from uwdock.datasets.water_fit_model import LIGHTINGS, Geometry, expected
from uwdock.datasets.water_fit_report import plot_fit, water_toml, write_water_file
from uwdock.dockcore.config import check_fields, to_dict
from uwdock.dockcore.domains import Interval, Seed
from uwdock.dockcore.errors import DockError
from uwdock.markers.dictionary import bits_per_side
from uwdock.markers.markerset import MarkerSet
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.sim.water import PRESETS, WaterConfig, decode_lut

__all__ = [
    "FitWaterConfig",
    "PatchSamples",
    "WaterFit",
    "backscatter_separable",
    "contrast_error",
    "estimate_noise",
    "fit_water",
    "plot_fit",
    "sample_frames",
    "water_toml",
    "write_water_file",
]

CHANNELS = ("R", "G", "B")
TARGETS = ("chessboard", "markers")

#: The sensor model (kept under its old name for callers).
_expected = expected


@dataclass(frozen=True)
class FitWaterConfig:
    """Settings of the water fit (the ``[fit_water]`` table).

    Attributes:
        target: ``"chessboard"`` (a printed board, sized by ``cols``, ``rows``,
            ``square_mm``) or ``"markers"`` (the DS marker board of a marker set file).
        cols: chessboard inner corners along a row.
        rows: chessboard inner corners along a column.
        square_mm: chessboard square side (mm).
        gamma: display gamma of the frames (2.2: sRGB-like cameras and the simulator).
        lamp_offset_camcv_m: the lamp's position in the camera frame (m; the Girona's lamp is
            10 cm above the camera, the renderer's default).
        lighting: the lighting model (:data:`water_fit_model.LIGHTINGS`): ``"lamp"`` (a lamp
            beside the camera: fall-off 1 / d**2, direct signal over 2 r), ``"ambient"`` (tank
            or room lights only: uniform, direct signal over r), ``"both"`` (the lamp plus a
            uniform ambient light, as the renderer lights a scene) or ``"auto"``: each is fitted
            and the one with the least error on held-out frames chosen.
        artificial_light: False is the older spelling of ``lighting = "ambient"``.
        patch_fraction: central fraction of a square (or marker cell) that is sampled: away
            from the edges, where blur mixes black and white.
        saturation_level: patches with any sampled channel at or above this 8-bit level are
            dropped (clipped by the camera).
        fit_vignetting: fit the vignetting strength; False: keep ``vignetting``.
        vignetting: vignetting strength when it is not fitted.
        min_range_spread_m: the fit refuses frames whose target ranges span less (m).
        max_frames: at most this many frames are used (evenly spaced over the input).
        base: the preset whose other fields (blur, sensor noise, gamma) the water file keeps.
        cv_folds: folds of frames for the held-out error (frames sorted by range, dealt
            round-robin); 0, or no more frames than folds: leave one frame out.
        plausible_tolerance: a lighting model whose held-out error is within this fraction of
            the best one's is plausible too (its values are compared with the chosen one's).
        bootstrap_resamples: resamples of whole frames for the uncertainty (0: the Jacobian's
            standard errors only).
        bootstrap_seed: seed of the resampling.
        max_rel_std: a value whose relative uncertainty (the larger of the bootstrap's and the
            Jacobian's) exceeds this is not determined.
        disagree_sigmas: a value is not determined when a plausible other lighting model gives
            one more than this many combined uncertainties away.
        max_contrast_error: a channel's attenuation is not determined when the modelled
            contrast misses the measured one by more than this fraction
            (:func:`contrast_error`; rendered films: within 0.01).
    """

    target: str = "chessboard"
    cols: Annotated[int, Interval(ge=2, le=100)] = 8
    rows: Annotated[int, Interval(ge=2, le=100)] = 6
    square_mm: Annotated[float, Interval(gt=0, le=10_000)] = 100.0
    gamma: Annotated[float, Interval(ge=0.2, le=5)] = 2.2
    lamp_offset_camcv_m: tuple[
        Annotated[float, Interval(ge=-5, le=5)],
        Annotated[float, Interval(ge=-5, le=5)],
        Annotated[float, Interval(ge=-5, le=5)],
    ] = (0.0, -0.10, 0.0)
    lighting: str = "auto"
    artificial_light: bool = True
    patch_fraction: Annotated[float, Interval(gt=0, le=0.9)] = 0.5
    saturation_level: Annotated[int, Interval(ge=1, le=255)] = 250
    fit_vignetting: bool = True
    vignetting: Annotated[float, Interval(ge=0, lt=1)] = 0.0
    min_range_spread_m: Annotated[float, Interval(ge=0, le=100)] = 1.0
    max_frames: Annotated[int, Interval(ge=1, le=100_000)] = 400
    base: str = "coastal"
    cv_folds: Annotated[int, Interval(ge=0, le=1000)] = 5
    plausible_tolerance: Annotated[float, Interval(ge=0, le=10)] = 0.10
    bootstrap_resamples: Annotated[int, Interval(ge=0, le=10_000)] = 100
    bootstrap_seed: Seed = 0
    max_rel_std: Annotated[float, Interval(gt=0, le=100)] = 0.25
    disagree_sigmas: Annotated[float, Interval(gt=0, le=100)] = 2.0
    max_contrast_error: Annotated[float, Interval(gt=0, le=100)] = 0.2

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        check_fields(self)
        if self.lighting not in ("auto", *LIGHTINGS):
            raise ValueError(
                f"lighting: must be auto, {', '.join(LIGHTINGS)}, got {self.lighting!r}"
            )
        if not self.artificial_light and self.lighting not in ("auto", "ambient"):
            raise ValueError(
                f"artificial_light: false means lighting 'ambient', not {self.lighting!r}"
            )

    def lightings(self) -> tuple[str, ...]:
        """The lighting models to fit (all of them for ``"auto"``)."""
        if not self.artificial_light:
            return ("ambient",)
        return LIGHTINGS if self.lighting == "auto" else (self.lighting,)
        if self.target not in TARGETS:
            raise ValueError(f"target: must be one of {', '.join(TARGETS)}, got {self.target!r}")
        if self.base not in PRESETS:
            raise ValueError(f"base: unknown water preset {self.base!r}")


@dataclass
class PatchSamples:
    """Black and white patches of a target seen in frames (one row per patch).

    Attributes:
        frame: (N,) index of the frame.
        white: (N,) True for a white patch.
        rgb: (N, 3) mean linear RGB of the patch (white = 1).
        var: (N, 3) variance of the linear values sampled in the patch (the sensor noise).
        range_m: (N,) range of the patch centre from the camera (m).
        lamp_m: (N,) distance from the lamp (m).
        cos_lamp: (N,) cosine between the patch normal and the direction to the lamp.
        rho2: (N,) squared normalised distance of the patch from the image centre (the
            vignetting's ``rho**2``).
        pair: (N,) for a white patch, the id of its group (its black neighbours share it), -1
            when it has none; for a black patch, the ids of the groups it belongs to are in
            ``groups``.
        groups: list of (white row, black rows) pairs for the contrast comparison.
        names: frame names by index.
        frames_read: frames read; ``frames_used``: frames that gave patches.
        dropped_saturated: patches dropped as clipped.
    """

    frame: np.ndarray
    white: np.ndarray
    rgb: np.ndarray
    var: np.ndarray
    range_m: np.ndarray
    lamp_m: np.ndarray
    cos_lamp: np.ndarray
    rho2: np.ndarray
    groups: list[tuple[int, list[int]]] = field(default_factory=list)
    names: dict[int, str] = field(default_factory=dict)
    frames_read: int = 0
    frames_used: int = 0
    frames_corrupt: int = 0
    dropped_saturated: int = 0

    def __len__(self) -> int:
        return int(self.frame.shape[0])


# ----------------------------------------------------------------------------- the target


@dataclass(frozen=True)
class _Patch:
    """A patch of the target in its own frame: centre, sample points, colour, neighbours."""

    points_m: np.ndarray  # (k, 3) sample points in the target frame
    normal: np.ndarray  # (3,) unit normal towards the viewer, target frame
    white: bool | None  # None: decided per frame by brightness (chessboard parity)
    parity: int


class _Target:
    """Finds the target in a frame and gives the patches' pose."""

    def patches(self) -> list[_Patch]:  # pragma: no cover - interface
        raise NotImplementedError

    def neighbours(self) -> list[tuple[int, list[int]]]:  # pragma: no cover - interface
        raise NotImplementedError

    def pose(self, img_bgr: np.ndarray, camera: CameraModel) -> np.ndarray | None:
        raise NotImplementedError  # pragma: no cover - interface

    def usable(self, k: int) -> bool:
        """Whether patch ``k`` is sampled in the frame last posed (all of them by default)."""
        return True


def _grid(fraction: float, n: int = 9) -> np.ndarray:
    """(n*n, 2) offsets in [-fraction/2, fraction/2]^2 (units of the patch side)."""
    t = (np.arange(n) + 0.5) / n - 0.5
    u, v = np.meshgrid(t * fraction, t * fraction)
    return np.stack([u.ravel(), v.ravel()], axis=1)


class _Chessboard(_Target):
    """A chessboard (OpenCV's object frame: origin at the first inner corner, z into it)."""

    def __init__(self, cfg: FitWaterConfig) -> None:
        self.cols, self.rows = cfg.cols, cfg.rows
        self.s = cfg.square_mm / 1000.0
        self.detector = PatternDetector("chessboard", cfg.cols, cfg.rows, self.s)
        offs = _grid(cfg.patch_fraction) * self.s
        self._patches, self._index = [], {}
        for i in range(self.cols + 1):
            for j in range(self.rows + 1):
                c = np.array([(i - 0.5) * self.s, (j - 0.5) * self.s])
                pts = np.zeros((len(offs), 3))
                pts[:, :2] = c + offs
                self._index[(i, j)] = len(self._patches)
                self._patches.append(_Patch(pts, np.array([0.0, 0.0, -1.0]), None, (i + j) % 2))

    def patches(self) -> list[_Patch]:
        return self._patches

    def neighbours(self) -> list[tuple[int, list[int]]]:
        out = []
        for (i, j), k in self._index.items():
            nb = [self._index[q] for q in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1))
                  if q in self._index]  # fmt: skip
            out.append((k, nb))
        return out

    def pose(self, img_bgr: np.ndarray, camera: CameraModel) -> np.ndarray | None:
        det = self.detector.detect(cv2.cvtColor(img_bgr, cv2.COLOR_BGR2GRAY))
        if det is None or det.n_corners < 4:
            return None
        ok, rvec, tvec = cv2.solvePnP(
            det.object_m.astype(np.float64), det.image_px.astype(np.float64),
            camera.K, np.asarray(camera.dist, np.float64), flags=cv2.SOLVEPNP_IPPE,
        )  # fmt: skip
        if not ok:
            return None
        return make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())


class _MarkerBoard(_Target):
    """The DS marker board: white border cells of each marker (the 3DBM insert) and the black
    enclosure ring around it; posed by the DS pose estimator (detector + board PnP)."""

    def __init__(self, cfg: FitWaterConfig, marker_set: MarkerSet) -> None:
        self.ms = marker_set
        self.estimator = DSPoseEstimator.from_marker_set(marker_set)
        self._patches: list[_Patch] = []
        self._groups: list[tuple[int, list[int]]] = []
        self._by_marker: dict[int, list[int]] = {}
        ratio = float(marker_set.geometry.get("enclosure_side_mm", 0.0) or 0.0)
        for spec in marker_set.markers:
            side = spec.side_m
            n = _cells_per_side(spec.dictionary)
            cell = side / n
            enclosure = ratio / 1000.0 if ratio else 1.26 * side
            R, t = spec.T_ds_marker[:3, :3], spec.T_ds_marker[:3, 3]
            normal = R @ np.array([0.0, 0.0, 1.0])  # marker z: out of the face
            rows = []
            offs = _grid(cfg.patch_fraction, 5) * cell
            whites = []
            for i in range(n):
                for j in range(n):
                    if 0 < i < n - 1 and 0 < j < n - 1:
                        continue  # only the border cells are white for sure
                    c = (np.array([i, j]) + 0.5) * cell - side / 2
                    whites.append(c + offs)
            ring = (side / 2 + enclosure / 2) / 2  # middle of the black ring
            width = max((enclosure - side) / 2, 1e-6)
            roffs = _grid(cfg.patch_fraction, 5) * width
            blacks = []
            for sx, sy in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                for along in (-0.5, 0.5):
                    c = np.array([sx * ring + sy * along * side * 0.5,
                                  sy * ring + sx * along * side * 0.5])  # fmt: skip
                    blacks.append(c + roffs)
            for pts2, white in [(p, True) for p in whites] + [(p, False) for p in blacks]:
                pts = np.zeros((len(pts2), 3))
                pts[:, :2] = pts2
                rows.append(len(self._patches))
                self._patches.append(_Patch((R @ pts.T).T + t, normal, white, 0))
            self._by_marker[spec.marker_id] = rows
            w = [k for k in rows if self._patches[k].white]
            b = [k for k in rows if not self._patches[k].white]
            self._groups.extend((k, b) for k in w)
        self._seen: set[int] = set()

    def patches(self) -> list[_Patch]:
        return self._patches

    def neighbours(self) -> list[tuple[int, list[int]]]:
        return self._groups

    def pose(self, img_bgr: np.ndarray, camera: CameraModel) -> np.ndarray | None:
        est = self.estimator.estimate(img_bgr, camera)
        self._seen = {d.marker_id for d in est.detections}
        return est.T_cam_ds

    def usable(self, k: int) -> bool:
        """Only the patches of markers decoded in the frame last posed are sampled."""
        return any(k in self._by_marker[m] for m in self._seen)


def _cells_per_side(dictionary: str) -> int:
    return bits_per_side(dictionary) + 2


# ----------------------------------------------------------------------------- sampling


def _sample_frame(
    img_bgr: np.ndarray,
    camera: CameraModel,
    target: _Target,
    T_cam_target: np.ndarray,
    cfg: FitWaterConfig,
    lut: np.ndarray,
) -> tuple[list[dict[str, Any]], int]:
    """The target's patches in one frame (those wholly inside the image, unclipped)."""
    h, w = img_bgr.shape[:2]
    R, t = T_cam_target[:3, :3], T_cam_target[:3, 3]
    lamp = np.asarray(cfg.lamp_offset_camcv_m, float)
    patches = [(k, p) for k, p in enumerate(target.patches()) if target.usable(k)]
    rows: list[dict[str, Any]] = []
    if not patches:
        return rows, 0
    # every sample point of the frame projected in one call, then split per patch
    points = np.concatenate([p.points_m for _, p in patches])
    projected, _ = cv2.projectPoints(
        points, cv2.Rodrigues(R)[0], t, camera.K, np.asarray(camera.dist, np.float64)
    )
    per_patch = np.split(
        projected.reshape(-1, 2), np.cumsum([len(p.points_m) for _, p in patches])[:-1]
    )
    saturated = 0
    clipped_parity: list[int] = []
    for (k, p), px in zip(patches, per_patch, strict=True):
        pts_cam = (R @ p.points_m.T).T + t
        if (pts_cam[:, 2] <= 0.05).any():
            continue
        inside = (px[:, 0] >= 1) & (px[:, 0] <= w - 2) & (px[:, 1] >= 1) & (px[:, 1] <= h - 2)
        if not inside.all():
            continue
        uv = np.unique(np.rint(px).astype(int), axis=0)  # each pixel once (far patches)
        if len(uv) < 4:
            continue
        raw = img_bgr[uv[:, 1], uv[:, 0], ::-1]  # (k, 3) RGB uint8
        if (raw >= cfg.saturation_level).any():
            saturated += 1
            clipped_parity.append(p.parity)
            continue
        centre = pts_cam.mean(axis=0)
        n_cam = R @ p.normal
        to_lamp = lamp - centre
        d = float(np.linalg.norm(to_lamp))
        cos = float(np.dot(n_cam, to_lamp) / d)
        if cos <= 0.05:
            continue  # seen edge-on or from behind
        c_px = px.mean(axis=0)
        u = (c_px[0] - (w - 1) / 2) / ((w - 1) / 2)
        v = (c_px[1] - (h - 1) / 2) / ((h - 1) / 2)
        rows.append(
            {
                "k": k,
                "rgb": lut[raw].mean(axis=0),
                "var": lut[raw].var(axis=0, ddof=1),
                "range_m": float(np.linalg.norm(centre)),
                "lamp_m": d,
                "cos": cos,
                "rho2": float((u * u + v * v) / 2.0),
                "parity": p.parity,
                "white": p.white,
            }
        )
    if rows and clipped_parity and len({r["parity"] for r in rows}) == 1:
        # one parity left: the other was dropped as clipped, so it is the white one (without
        # this a frame whose white squares all clip would call its black squares white)
        white_parity = max(set(clipped_parity), key=clipped_parity.count)
        for r in rows:
            if r["white"] is None:
                r["white"] = r["parity"] == white_parity
    return rows, saturated


def sample_frames(
    frames: Iterable[tuple[int, str, np.ndarray | None]],
    camera: CameraModel,
    cfg: FitWaterConfig,
    marker_set: MarkerSet | None = None,
    progress: Callable[[int], None] | None = None,
) -> PatchSamples:
    """Find the target in each frame and sample its black and white patches.

    Args:
        frames: ``(index, name, BGR image | None)`` (:func:`perception.video.open_frames`).
        camera: the camera's intrinsics (frames of another size are an error).
        cfg: the fit's settings.
        marker_set: the DS marker set (``target = "markers"``).
        progress: called with the number of frames read so far.
    """
    cfg.validate()
    if cfg.target == "markers":
        if marker_set is None:
            raise DockError("target 'markers' needs the DS marker set (--marker-set)")
        target: _Target = _MarkerBoard(cfg, marker_set)
    else:
        target = _Chessboard(cfg)
    lut = decode_lut(float(cfg.gamma))  # the water model's own uint8 -> linear table
    cols: dict[str, list] = {k: [] for k in ("frame", "white", "rgb", "var", "range_m",
                                             "lamp_m", "cos", "rho2")}  # fmt: skip
    groups: list[tuple[int, list[int]]] = []
    names: dict[int, str] = {}
    read = corrupt = saturated = 0
    neighbours = target.neighbours()
    for index, name, img in frames:
        read += 1
        if progress is not None:
            progress(read)
        if img is None:
            corrupt += 1
            continue
        if img.ndim != 3 or img.shape[2] != 3:
            raise DockError(f"{name}: the water fit needs colour frames, got shape {img.shape}")
        if (img.shape[1], img.shape[0]) != (camera.width_px, camera.height_px):
            raise DockError(
                f"{name}: frame is {img.shape[1]}x{img.shape[0]} px, the camera file "
                f"{camera.width_px}x{camera.height_px}"
            )
        T = target.pose(img, camera)
        if T is None:
            continue
        rows, sat = _sample_frame(img, camera, target, T, cfg, lut)
        saturated += sat
        if not rows:
            continue
        if any(r["white"] is None for r in rows):  # chessboard: the brighter parity is white
            if len({r["parity"] for r in rows}) == 1:
                continue  # one parity only, none clipped: which is white is not known
            lum = {p: np.mean([r["rgb"].sum() for r in rows if r["parity"] == p] or [0.0])
                   for p in (0, 1)}  # fmt: skip
            white_parity = 0 if lum[0] > lum[1] else 1
            for r in rows:
                r["white"] = r["parity"] == white_parity
        names[int(index)] = str(name)
        base = len(cols["frame"])
        row_of = {r["k"]: base + n for n, r in enumerate(rows)}
        for r in rows:
            cols["frame"].append(int(index))
            cols["white"].append(bool(r["white"]))
            for key in ("rgb", "var", "range_m", "lamp_m", "cos", "rho2"):
                cols[key].append(r[key])
        for k, nb in neighbours:
            if k in row_of and cols["white"][row_of[k]]:
                blacks = [row_of[q] for q in nb if q in row_of and not cols["white"][row_of[q]]]
                if blacks:
                    groups.append((row_of[k], blacks))
    return PatchSamples(
        frame=np.asarray(cols["frame"], int),
        white=np.asarray(cols["white"], bool),
        rgb=np.asarray(cols["rgb"], float).reshape(-1, 3),
        var=np.asarray(cols["var"], float).reshape(-1, 3),
        range_m=np.asarray(cols["range_m"], float),
        lamp_m=np.asarray(cols["lamp_m"], float),
        cos_lamp=np.asarray(cols["cos"], float),
        rho2=np.asarray(cols["rho2"], float),
        groups=groups,
        names=names,
        frames_read=read,
        frames_used=len(names),
        frames_corrupt=corrupt,
        dropped_saturated=saturated,
    )


# ----------------------------------------------------------------------------- the noise


def estimate_noise(s: PatchSamples, gamma: float) -> tuple[float | None, float]:
    """The sensor's Poisson-Gaussian noise from the spread of values inside the patches:
    ``var = mean / photons_at_white + read_noise**2`` (a photon transfer curve), less the
    8-bit quantisation's share, fitted by weighted least squares over the patches between 1 %
    and 80 % of white. Returns ``(photons_at_white or None when no shot noise is seen,
    read_noise)``."""
    m, v = s.rgb.ravel(), s.var.ravel()
    ok = (m > 0.01) & (m < 0.8) & np.isfinite(v)
    if ok.sum() < 10:
        return None, 0.0
    m, v = m[ok], v[ok]
    step = gamma * np.power(m, (gamma - 1.0) / gamma) / 255.0  # d linear / d display level
    y = v - step**2 / 12.0
    A = np.stack([m, np.ones_like(m)], axis=1)
    w = np.ones_like(m)
    coef = np.zeros(2)
    for _ in range(3):  # the variance of a sample variance grows with the variance squared
        coef, *_ = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)
        pred = np.maximum(A @ coef, 1e-9)
        w = 1.0 / pred
    slope, read2 = float(coef[0]), float(coef[1])
    photons = 1.0 / slope if slope > 1e-9 else None
    if photons is not None:
        photons = float(min(max(photons, 1.0), 1e9))
    return photons, float(min(math.sqrt(max(read2, 0.0)), 1.0))


# ----------------------------------------------------------------------------- the fit


@dataclass
class WaterFit:
    """The fitted water, how well it explains the frames and what the frames determine.

    Attributes:
        water: the fitted model as a :class:`WaterConfig` (the base preset's other fields).
        params: block -> (R, G, B) fitted values (``a_white``, ``a_black``, ``ambient``,
            ``beta_D``, ``B_inf``, ``beta_B``) of the chosen lighting model.
        rel_std: block -> (R, G, B) relative uncertainty used in the decisions: the larger of
            the Jacobian's standard error and the bootstrap's spread.
        vignetting: the vignetting strength (fitted or given).
        residual_rms: RMS of the patch residuals (linear units, white = 1).
        residual_rms_8bit: the same in 8-bit display levels at the patches' brightness.
        contrast_error: per channel, the modelled against the measured contrast (white - black
            neighbours) by range (:func:`contrast_error`).
        range_m: (min, max) range of the patches (m).
        samples: the patches used.
        config: the fit's settings.
        separable: per channel, whether B_inf and beta_B are told apart over the ranges seen
            (:func:`backscatter_separable`).
        warnings: one-line remarks (ranges too narrow, parameters not determined).
        lighting: the chosen lighting model.
        models: lighting -> its fit, held-out error and uncertainty (every model fitted).
        verdict: per judged parameter and channel, determined or not, why, what to film.
    """

    water: WaterConfig
    params: dict[str, tuple[float, float, float]]
    rel_std: dict[str, tuple[float, float, float]]
    vignetting: float
    residual_rms: float
    residual_rms_8bit: float
    contrast_error: tuple[float, float, float]
    range_m: tuple[float, float]
    samples: PatchSamples
    config: FitWaterConfig
    separable: tuple[bool, bool, bool] = (True, True, True)
    warnings: list[str] = field(default_factory=list)
    lighting: str = "both"
    models: dict[str, ModelResult] = field(default_factory=dict)
    verdict: Verdict | None = None
    _x: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    @property
    def determined(self) -> dict[str, list[bool]]:
        """Judged block -> (R, G, B) whether the frames determine the value."""
        assert self.verdict is not None
        return self.verdict.determined

    @property
    def beta_D_determined(self) -> bool:
        """Whether the attenuation is determined in every channel."""
        return all(self.determined["beta_D"])

    @property
    def to_film(self) -> list[str]:
        """What to film (or state) to pin the undetermined values down."""
        return list(self.verdict.to_film) if self.verdict else []

    def undetermined_names(self) -> dict[str, list[str]]:
        """Judged block -> channels it is not determined in (blocks with none left out)."""
        return {b: [ch for ch, ok in zip(CHANNELS, v, strict=True) if not ok]
                for b, v in self.determined.items() if not all(v)}  # fmt: skip

    def model(self, s: PatchSamples | None = None) -> np.ndarray:
        """(N, 3) modelled linear RGB of the patches as the camera records them (mean of the
        noisy values clipped at 0)."""
        noise = (self.water.photons_at_white, self.water.read_noise)
        g = Geometry.of(s or self.samples)
        return _expected(wm.model(self._x, g, self.lighting), *noise)

    def contrast_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(range_m (G,), measured (G, 3), modelled (G, 3)) white - mean(black neighbours)."""
        return _contrast(self.samples, self.model())

    def summary(self) -> dict[str, Any]:
        """What the report JSON holds (no per-patch arrays)."""
        s = self.samples
        chosen = self.models[self.lighting]
        boot = chosen.rel_std_bootstrap
        return {
            "water": to_dict(self.water),
            "lighting": {
                "requested": self.config.lighting if self.config.artificial_light else "ambient",
                "chosen": self.lighting,
                "chosen_by": "least error on held-out frames"
                if len(self.models) > 1
                else "requested",
                "cv_folds": _n_folds(s, self.config) if len(self.models) > 1 else 0,
                "plausible_tolerance": self.config.plausible_tolerance,
                "models": {k: m.summary() for k, m in self.models.items()},
            },
            "params": {k: list(v) for k, v in self.params.items()},
            "rel_std": {k: list(v) for k, v in self.rel_std.items()},
            "rel_std_jacobian": {
                k: [float(x) for x in v] for k, v in chosen.rel_std_jacobian.items()
            },
            "rel_std_bootstrap": {k: [float(x) for x in v] for k, v in boot.items()},
            "bootstrap": {
                "resamples": chosen.resamples,
                "seed": self.config.bootstrap_seed,
                "what": "whole frames resampled with replacement; half the 16-84 % interval of "
                "each log parameter",
                "beta_D_q16": [float(v) for v in chosen.quantiles["beta_D"][0]]
                if chosen.quantiles
                else None,
                "beta_D_q84": [float(v) for v in chosen.quantiles["beta_D"][1]]
                if chosen.quantiles
                else None,
            },
            "determined": {
                b: dict(zip(CHANNELS, v, strict=True)) for b, v in self.determined.items()
            },
            "undetermined": self.verdict.undetermined() if self.verdict else [],
            "to_film": self.to_film,
            "vignetting": self.vignetting,
            "backscatter_separable": dict(zip(CHANNELS, self.separable, strict=True)),
            "residual_rms": self.residual_rms,
            "residual_rms_8bit": self.residual_rms_8bit,
            "contrast_error": dict(zip(CHANNELS, self.contrast_error, strict=True)),
            "range_m": list(self.range_m),
            "patches": len(s),
            "white_patches": int(s.white.sum()),
            "contrast_pairs": len(s.groups),
            "frames_read": s.frames_read,
            "frames_used": s.frames_used,
            "frames_corrupt": s.frames_corrupt,
            "patches_dropped_saturated": s.dropped_saturated,
            "warnings": list(self.warnings),
            "config": to_dict(self.config),
        }


def _contrast(s: PatchSamples, model: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not s.groups:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    w = np.array([g[0] for g in s.groups])
    meas = np.array([s.rgb[g[0]] - s.rgb[g[1]].mean(axis=0) for g in s.groups])
    mod = np.array([model[g[0]] - model[g[1]].mean(axis=0) for g in s.groups])
    return s.range_m[w], meas, mod


#: Width of the range bins over which measured and modelled contrast are compared (m).
CONTRAST_BIN_M = 0.25


def contrast_error(
    range_m: np.ndarray, measured: np.ndarray, modelled: np.ndarray
) -> tuple[float, float, float]:
    """Per channel, how far the modelled contrast is from the measured one: the mean contrasts
    of the white/black pairs in each range bin (``CONTRAST_BIN_M``) compared, as
    ``sum_bins n |modelled - measured| / sum_bins n |measured|`` (binning averages out the
    sensor noise of single pairs; what is left is the model's error)."""
    if len(range_m) == 0:
        return (float("nan"),) * 3
    bins = np.floor(range_m / CONTRAST_BIN_M).astype(int)
    num, den = np.zeros(3), np.zeros(3)
    for b in np.unique(bins):
        m = bins == b
        n = m.sum()
        num += n * np.abs(modelled[m].mean(axis=0) - measured[m].mean(axis=0))
        den += n * np.abs(measured[m].mean(axis=0))
    return tuple(float(a / max(d, 1e-12)) for a, d in zip(num, den, strict=True))  # type: ignore[return-value]


#: Change and bend (linear, white = 1) the backscatter must show over the ranges seen for its
#: veiling light and coefficient to be told apart (on rendered films, below it the fit's
#: standard errors understate their error several times).
SEPARABLE_CHANGE = 0.03


def backscatter_separable(
    B_inf: np.ndarray, beta_B: np.ndarray, r_min_m: float, r_max_m: float
) -> list[bool]:
    """Per channel, whether ``B_inf`` and ``beta_B`` are determined separately by patches from
    ``r_min_m`` to ``r_max_m``: the backscatter ``B_inf (1 - exp(-beta_B r))`` must change by
    :data:`SEPARABLE_CHANGE` over those ranges *and* bend by as much away from its initial
    slope ``B_inf beta_B r`` (in clear water only the product is seen; in turbid water a
    backscatter already saturated at the nearest range hides its coefficient)."""
    B_inf, beta_B = np.asarray(B_inf, float), np.asarray(beta_B, float)
    change = B_inf * np.abs(np.exp(-beta_B * r_min_m) - np.exp(-beta_B * r_max_m))
    bend = B_inf * (beta_B * r_max_m - (1.0 - np.exp(-beta_B * r_max_m)))
    return [bool(v) for v in (change >= SEPARABLE_CHANGE) & (bend >= SEPARABLE_CHANGE)]


#: A residual above this (8-bit grey levels) means no lighting model explains the frames (on
#: rendered films, with their noise, the fit leaves 0.3-0.6).
MISFIT_8BIT = 3.0


def _n_folds(s: PatchSamples, cfg: FitWaterConfig) -> int:
    n = len(np.unique(s.frame))
    return n if cfg.cv_folds == 0 else min(cfg.cv_folds, n)


def _to_8bit(v: np.ndarray, gamma: float) -> np.ndarray:
    return 255.0 * (np.clip(v, 1e-6, None) ** (1.0 / gamma))


def _fit_model(
    s: PatchSamples, cfg: FitWaterConfig, lighting: str, photons: float | None, read: float
) -> ModelResult:
    """One lighting model on all frames (four starts), its Jacobian standard errors."""
    vig0 = cfg.vignetting if not cfg.fit_vignetting else 0.1
    lo, hi = wm.bounds(lighting, cfg.fit_vignetting, cfg.vignetting)
    sol = wm.solve(s, lighting, photons, read, lo, hi, vig0)
    n_free = wm.free_parameters(lighting, cfg.fit_vignetting)
    sd = wm.log_std(sol.jac[:, hi - lo > 1e-6], 2.0 * sol.cost / max(sol.fun.size - n_free, 1))
    full = np.zeros(wm.N_PARAMS)
    full[hi - lo > 1e-6] = sd
    rel = {b: np.broadcast_to(full[wm.SLICES[b]], (3,)).astype(float) for b in wm.BLOCKS}
    m = _expected(wm.model(sol.x, Geometry.of(s), lighting), photons, read)
    fit_rms = float(np.sqrt(np.mean((_to_8bit(m, cfg.gamma) - _to_8bit(s.rgb, cfg.gamma)) ** 2)))
    return ModelResult(lighting, sol.x, sol.cost, n_free, rel, fit_rms_8bit=fit_rms,
                       lamp_share=lamp_share(sol.x, s, lighting))  # fmt: skip


def _cross_validate(
    s: PatchSamples, cfg: FitWaterConfig, m: ModelResult, photons: float | None, read: float
) -> None:
    """Held-out error of a model: each fold of frames predicted by a fit to the others."""
    folds = frame_folds(s.frame, s.range_m, cfg.cv_folds)
    lo, hi = wm.bounds(m.lighting, cfg.fit_vignetting, cfg.vignetting)
    pred = np.zeros_like(s.rgb)
    for f in np.unique(folds):
        train, test = np.flatnonzero(folds != f), np.flatnonzero(folds == f)
        sol = wm.solve(s, m.lighting, photons, read, lo, hi, 0.1, rows=train, x0=m.x,
                       max_nfev=100, tol=1e-6)  # fmt: skip
        pred[test] = _expected(wm.model(sol.x, Geometry.of(s, test), m.lighting), photons, read)
    sigma = wm.SIGMA_REL * s.rgb + wm.SIGMA_ABS
    m.heldout_rms = float(np.sqrt(np.mean(((pred - s.rgb) / sigma) ** 2)))
    diff = _to_8bit(pred, cfg.gamma) - _to_8bit(s.rgb, cfg.gamma)
    m.heldout_rms_8bit = float(np.sqrt(np.mean(diff**2)))


def _bootstrap(
    s: PatchSamples, cfg: FitWaterConfig, m: ModelResult, photons: float | None, read: float
) -> None:
    """Resample whole frames with replacement (seeded) and refit: the spread of each log
    parameter (half its 16-84 % interval) and its 16 % and 84 % values."""
    if cfg.bootstrap_resamples <= 0:
        return
    frames = np.unique(s.frame)
    index = np.searchsorted(frames, s.frame)
    lo, hi = wm.bounds(m.lighting, cfg.fit_vignetting, cfg.vignetting)
    rng = np.random.default_rng(cfg.bootstrap_seed)
    draws = []
    for _ in range(cfg.bootstrap_resamples):
        count = np.bincount(rng.integers(0, len(frames), len(frames)), minlength=len(frames))
        w = count[index].astype(float)
        rows = np.flatnonzero(w > 0)
        sol = wm.solve(s, m.lighting, photons, read, lo, hi, 0.1, rows=rows, weights=w[rows],
                       x0=m.x, max_nfev=60, tol=1e-5)  # fmt: skip
        draws.append(sol.x)
    m.rel_std_bootstrap, m.quantiles = block_std(np.asarray(draws))
    m.resamples = len(draws)


def fit_water(samples: PatchSamples, cfg: FitWaterConfig | None = None) -> WaterFit:
    """Fit the water model to the patches under each lighting model asked for, choose one by
    its error on held-out frames, and judge what the frames determine (see the module
    docstring and :mod:`datasets.water_fit_judge`).

    Raises:
        DockError: too few patches, no white or no black patch, ranges spanning less than
            ``cfg.min_range_spread_m``.
    """
    cfg = cfg or FitWaterConfig()
    cfg.validate()
    s = samples
    if len(s) < 20 or s.white.all() or not s.white.any():
        raise DockError(
            f"the water fit needs black and white patches of the target: found {len(s)} "
            f"({int(s.white.sum())} white) in {s.frames_used} of {s.frames_read} frames"
        )
    spread = float(s.range_m.max() - s.range_m.min())
    if spread < cfg.min_range_spread_m:
        raise DockError(
            f"the target was seen from {s.range_m.min():.2f} to {s.range_m.max():.2f} m only: "
            f"the fit needs ranges spanning {cfg.min_range_spread_m:g} m or more (film it from "
            f"near and far)"
        )
    photons, read = estimate_noise(s, cfg.gamma)
    lightings = cfg.lightings()
    models = {L: _fit_model(s, cfg, L, photons, read) for L in lightings}
    auto = len(lightings) > 1
    if auto and len(np.unique(s.frame)) < 3:
        raise DockError(
            f"choosing the lighting needs the target in 3 or more frames (found it in "
            f"{len(np.unique(s.frame))}): film more, or state it with --lighting"
        )
    if auto:
        for m in models.values():
            _cross_validate(s, cfg, m, photons, read)
            m.degenerate = lamp_not_seen(m)
        candidates = [m for m in models.values() if not m.degenerate] or list(models.values())
        best = min(m.heldout_rms for m in candidates)
        for m in models.values():
            m.plausible = not m.degenerate and (
                m.heldout_rms <= best * (1.0 + cfg.plausible_tolerance)
            )
        chosen = min(candidates, key=lambda m: m.heldout_rms)
    else:
        chosen = models[lightings[0]]
    for m in models.values():
        if m.plausible:
            _bootstrap(s, cfg, m, photons, read)
    x = chosen.x
    lighting = chosen.lighting
    p, vig = wm.unpack(x)
    rel = chosen.rel_std()
    rel_std = {b: tuple(float(v) for v in rel[b]) for b in wm.BLOCKS}
    params = {b: tuple(float(v) for v in p[b]) for b in wm.BLOCKS}
    model = _expected(wm.model(x, Geometry.of(s), lighting), photons, read)
    resid = model - s.rgb
    cerr = contrast_error(*_contrast(s, model))
    r_lo, r_hi = float(s.range_m.min()), float(s.range_m.max())
    separable = backscatter_separable(p["B_inf"], p["beta_B"], r_lo, r_hi)
    verdict = judge(chosen, [m for m in models.values() if m is not chosen], (r_lo, r_hi),
                    separable, cfg.max_rel_std, cfg.disagree_sigmas, cerr,
                    cfg.max_contrast_error)  # fmt: skip
    if cfg.target == "markers":  # rendered films: attenuation 18-173 % off, contrast within 3.4 %
        for ch in CHANNELS:
            verdict.reasons.setdefault(("beta_D", ch), []).append(
                "the marker board is an approximate target (on rendered films its attenuation "
                "came out 18-173 % off)"
            )
        verdict.determined["beta_D"] = [False, False, False]
        verdict.to_film.append("film a flat chessboard (--target chessboard) for the water file")
    warnings = []
    for (b, ch), why in verdict.reasons.items():
        warnings.append(f"{b} {ch} = {params[b][CHANNELS.index(ch)]:.3g} is not determined by "
                        f"these frames: {'; '.join(why)}")  # fmt: skip
    if chosen.fit_rms_8bit > MISFIT_8BIT:
        warnings.append(
            f"no lighting model explains these frames well (residual {chosen.fit_rms_8bit:.1f} "
            f"grey levels; rendered films fit within 0.6): uneven or changing light (automatic "
            "exposure, room lights), a board that is not flat or glare; treat every value as "
            "approximate"
        )
    if cfg.target == "markers":
        warnings.append(
            "the marker board is an approximate target (small 3D markers, shaded): on rendered "
            "films its attenuation came out 18-173 % off where a chessboard's was within 10 % "
            "(bench/results/water_fit.json); film a flat chessboard for the water file"
        )
    base = PRESETS[cfg.base]
    water = dataclasses.replace(
        base,
        beta_D_rgb=_rgb(np.clip(p["beta_D"], 0.0, 100.0)),
        beta_B_rgb=_rgb(np.clip(p["beta_B"], 0.0, 100.0)),
        B_inf_rgb=_rgb(np.clip(p["B_inf"], 0.0, 1.0)),
        vignetting=float(min(vig, 0.95)),
        artificial_light=lighting != "ambient",
        gamma=cfg.gamma,
        photons_at_white=photons if photons is not None else base.photons_at_white,
        read_noise=read,
    )
    water.validate()
    return WaterFit(
        water=water,
        params=params,
        rel_std=rel_std,
        vignetting=vig,
        residual_rms=float(np.sqrt(np.mean(resid**2))),
        residual_rms_8bit=float(
            np.sqrt(np.mean((_to_8bit(model, cfg.gamma) - _to_8bit(s.rgb, cfg.gamma)) ** 2))
        ),
        contrast_error=cerr,  # type: ignore[arg-type]
        range_m=(r_lo, r_hi),
        samples=s,
        config=cfg,
        separable=tuple(separable),  # type: ignore[arg-type]
        warnings=warnings,
        lighting=lighting,
        models=models,
        verdict=verdict,
        _x=x,
    )


def _rgb(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))
