"""The water fitted to the user's tank: ``sim fit-water``.

The simulator's underwater model (:func:`uwdock.sim.water.apply_water`) gives, per colour
channel ``c``, the linear intensity of a surface point at range ``r`` lit by the lamp beside the
camera::

    I_c = V(rho) * (J_c * exp(-2 beta_D_c r) + B_inf_c * (1 - exp(-beta_B_c r)))

with ``J`` the in-air radiance and ``V = 1 - s rho**2`` the vignetting. A known target (a
chessboard, or the DS marker board) posed by PnP gives, in every frame, black and white patches
of known geometry: their range ``r``, their distance ``d`` to the lamp and the cosine of the
lamp's incidence. The in-air radiance of a patch of albedo class ``k`` (black or white) is
modelled as ``J = a_kc * (eta + cos / d**2)``: a point lamp (``1 / d**2``, Lambert) plus a
uniform ambient light ``eta`` (the renderer's ambient light, or a tank's room lights), one ratio
for the three channels (the ambient light taken to have the lamp's colour: a ratio per channel
trades off against the attenuation, and in turbid water moved green's by 20 %). The
difference white - black then carries the direct signal alone (``beta_D``), the black level the
backscatter (``B_inf``, ``beta_B``), and the spread of patch positions in the image the
vignetting; all 17 parameters are fitted jointly by weighted least squares
(:func:`scipy.optimize.least_squares`, 2 % relative + 0.002 absolute uncertainty per patch, a
few starts). Their standard errors come from the Jacobian.

Needs ranges: the target must be seen at several ranges (a spread of 1 m or more), and the
backscatter coefficient of a channel is only separable from its veiling light when
the backscatter changes and bends over the ranges seen (:func:`backscatter_separable`): in clear
water only the product ``B_inf * beta_B`` is determined, and the report says so in a warning
(there the Jacobian's standard errors understate the error several times).

It lives in ``datasets``: it crosses the sim -> perception seam (the water model of ``sim``,
the detector and PnP of ``perception``); ``sim fit-water`` is its command.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import make_T
from uwdock.calibration.patterns import PatternDetector
from uwdock.dockcore.config import check_fields, dumps_toml, to_dict
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_text
from uwdock.markers.dictionary import bits_per_side
from uwdock.markers.markerset import MarkerSet
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.sim.water import PRESETS, WaterConfig, _decode_lut

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

#: Parameter blocks of the fit (each per channel), in the order of the parameter vector.
_BLOCKS = ("a_white", "a_black", "ambient", "beta_D", "B_inf", "beta_B")
#: Values per block: the ambient-to-lamp ratio is one (one lighting), the rest per channel.
_SIZES = {b: 1 if b == "ambient" else 3 for b in _BLOCKS}
#: Where each block sits in the parameter vector; the vignetting strength comes last.
_SLICES = {
    b: slice(sum(_SIZES[q] for q in _BLOCKS[:i]), sum(_SIZES[q] for q in _BLOCKS[: i + 1]))
    for i, b in enumerate(_BLOCKS)
}
_N_PARAMS = sum(_SIZES.values()) + 1
#: log bounds of each block (the values are exp of the parameters).
_LOG_BOUNDS = {
    "a_white": (-12.0, 6.0),
    "a_black": (-14.0, 6.0),
    "ambient": (-14.0, 4.0),
    "beta_D": (-9.0, math.log(100.0)),
    "B_inf": (-14.0, 0.0),
    "beta_B": (-9.0, math.log(100.0)),
}
#: Per-patch uncertainty of the fit: relative and absolute (linear units, white = 1).
_SIGMA_REL, _SIGMA_ABS = 0.02, 0.002


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
        artificial_light: the target is lit by the vehicle's lamp (direct signal over 2 r,
            fall-off 1 / d**2); False: by daylight or tank lights only (direct signal over r,
            uniform lighting).
        patch_fraction: central fraction of a square (or marker cell) that is sampled: away
            from the edges, where blur mixes black and white.
        saturation_level: patches with any sampled channel at or above this 8-bit level are
            dropped (clipped by the camera).
        fit_vignetting: fit the vignetting strength; False: keep ``vignetting``.
        vignetting: vignetting strength when it is not fitted.
        min_range_spread_m: the fit refuses frames whose target ranges span less (m).
        max_frames: at most this many frames are used (evenly spaced over the input).
        base: the preset whose other fields (blur, sensor noise, gamma) the water file keeps.
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
    artificial_light: bool = True
    patch_fraction: Annotated[float, Interval(gt=0, le=0.9)] = 0.5
    saturation_level: Annotated[int, Interval(ge=1, le=255)] = 250
    fit_vignetting: bool = True
    vignetting: Annotated[float, Interval(ge=0, lt=1)] = 0.0
    min_range_spread_m: Annotated[float, Interval(ge=0, le=100)] = 1.0
    max_frames: Annotated[int, Interval(ge=1, le=100_000)] = 400
    base: str = "coastal"

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        check_fields(self)
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
    lut = _decode_lut(float(cfg.gamma))  # the water model's own uint8 -> linear table
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


def _expected(m: np.ndarray, photons: float | None, read: float) -> np.ndarray:
    """The mean of a value ``m`` seen through the sensor's noise and clipped at 0 (the camera
    cannot record negative light: dark patches read brighter than their signal)."""
    from scipy.special import ndtr  # scipy costs 0.5 s to import: only for the fit

    var = read * read + (np.maximum(m, 0.0) / photons if photons else 0.0)
    sd = np.sqrt(np.maximum(var, 1e-18))
    z = m / sd
    return m * ndtr(z) + sd * np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


# ----------------------------------------------------------------------------- the fit


@dataclass
class WaterFit:
    """The fitted water and how well it explains the frames.

    Attributes:
        water: the fitted model as a :class:`WaterConfig` (the base preset's other fields).
        params: block -> (R, G, B) fitted values (``a_white``, ``a_black``, ``ambient``,
            ``beta_D``, ``B_inf``, ``beta_B``).
        rel_std: block -> (R, G, B) relative standard errors (from the Jacobian).
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
    _x: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def model(self, s: PatchSamples | None = None) -> np.ndarray:
        """(N, 3) modelled linear RGB of the patches as the camera records them (mean of the
        noisy values clipped at 0)."""
        noise = (self.water.photons_at_white, self.water.read_noise)
        return _expected(_model(self._x, s or self.samples, self.config), *noise)

    def contrast_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(range_m (G,), measured (G, 3), modelled (G, 3)) white - mean(black neighbours)."""
        return _contrast(self.samples, self.model())

    def summary(self) -> dict[str, Any]:
        """What the report JSON holds (no per-patch arrays)."""
        s = self.samples
        return {
            "water": to_dict(self.water),
            "params": {k: list(v) for k, v in self.params.items()},
            "rel_std": {k: list(v) for k, v in self.rel_std.items()},
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


def _unpack(x: np.ndarray) -> tuple[dict[str, np.ndarray], float]:
    p = {b: np.broadcast_to(np.exp(x[_SLICES[b]]), (3,)) for b in _BLOCKS}
    return p, float(x[-1])


def _model(x: np.ndarray, s: PatchSamples, cfg: FitWaterConfig) -> np.ndarray:
    p, vig = _unpack(x)
    r = s.range_m[:, None]
    a = np.where(s.white[:, None], p["a_white"], p["a_black"])
    if cfg.artificial_light:
        light = p["ambient"] + (s.cos_lamp / s.lamp_m**2)[:, None]
        direct = a * light * np.exp(-2.0 * p["beta_D"] * r)
    else:
        direct = a * np.exp(-p["beta_D"] * r)
    back = p["B_inf"] * (1.0 - np.exp(-p["beta_B"] * r))
    return (1.0 - vig * s.rho2)[:, None] * (direct + back)


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


def _start(s: PatchSamples, water: WaterConfig, vig: float) -> np.ndarray:
    """A starting point: the preset's water, albedo scales from the nearest patches."""
    near = s.range_m <= np.quantile(s.range_m, 0.2)
    light = 1.0 / np.maximum(s.lamp_m, 0.1) ** 2
    x = np.zeros(_N_PARAMS)

    def scale(mask: np.ndarray) -> np.ndarray:
        m = mask & near
        if not m.any():
            m = mask
        decay = np.exp(-2.0 * np.asarray(water.beta_D_rgb) * s.range_m[m, None])
        v = s.rgb[m] / (light[m, None] * decay)
        return np.log(np.clip(np.median(v, axis=0), 1e-5, 1e2))

    x[_SLICES["a_white"]] = scale(s.white)
    x[_SLICES["a_black"]] = scale(~s.white) if (~s.white).any() else x[_SLICES["a_white"]] - 3
    x[_SLICES["ambient"]] = math.log(0.05)
    x[_SLICES["beta_D"]] = np.log(np.clip(water.beta_D_rgb, 1e-3, 50))
    x[_SLICES["B_inf"]] = np.log(np.clip(water.B_inf_rgb, 1e-3, 1))
    x[_SLICES["beta_B"]] = np.log(np.clip(water.beta_B_rgb, 1e-3, 50))
    x[-1] = vig
    return x


def fit_water(samples: PatchSamples, cfg: FitWaterConfig | None = None) -> WaterFit:
    """Fit the water model to the patches (see the module docstring).

    Raises:
        DockError: too few patches, no white or no black patch, ranges spanning less than
            ``cfg.min_range_spread_m``.
    """
    from scipy.optimize import least_squares  # scipy costs 0.5 s to import: only for the fit

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
    lo = np.concatenate([np.repeat(_LOG_BOUNDS[b][0], _SIZES[b]) for b in _BLOCKS] + [[0.0]])
    hi = np.concatenate([np.repeat(_LOG_BOUNDS[b][1], _SIZES[b]) for b in _BLOCKS] + [[0.95]])
    if not cfg.fit_vignetting:
        lo[-1], hi[-1] = cfg.vignetting - 1e-9, cfg.vignetting + 1e-9
    obs = s.rgb
    sigma = _SIGMA_REL * obs + _SIGMA_ABS
    photons, read = estimate_noise(s, cfg.gamma)

    def residual(x: np.ndarray) -> np.ndarray:
        return ((_expected(_model(x, s, cfg), photons, read) - obs) / sigma).ravel()

    best = None
    for name in ("clear_tank", "coastal", "turbid", "very_turbid"):
        x0 = np.clip(_start(s, PRESETS[name], cfg.vignetting if not cfg.fit_vignetting else 0.1),
                     lo + 1e-6, hi - 1e-6)  # fmt: skip
        res = least_squares(residual, x0, bounds=(lo, hi), x_scale="jac", max_nfev=400)
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None
    x = best.x
    p, vig = _unpack(x)
    n_res, n_par = best.fun.size, _N_PARAMS - (0 if cfg.fit_vignetting else 1)
    sd = _log_std(best.jac, 2.0 * best.cost / max(n_res - n_par, 1))
    rel_std = {b: tuple(float(v) for v in np.broadcast_to(sd[_SLICES[b]], (3,))) for b in _BLOCKS}
    params = {b: tuple(float(v) for v in p[b]) for b in _BLOCKS}
    model = _expected(_model(x, s, cfg), photons, read)
    resid = model - obs
    disp = 255.0 * (np.clip(obs, 1e-6, None) ** (1.0 / cfg.gamma))
    disp_m = 255.0 * (np.clip(model, 1e-6, None) ** (1.0 / cfg.gamma))
    cerr = contrast_error(*_contrast(s, model))
    warnings = []
    r_lo, r_hi = float(s.range_m.min()), float(s.range_m.max())
    separable = backscatter_separable(p["B_inf"], p["beta_B"], r_lo, r_hi)
    for c, ch in enumerate(CHANNELS):
        b_inf, beta_b = params["B_inf"][c], params["beta_B"][c]
        if b_inf >= 0.01 and not separable[c]:
            why = (
                "is saturated already at the nearest range: film nearer"
                if beta_b * r_lo > 2.0
                else "hardly bends: film farther"
            )
            warnings.append(
                f"B_inf and beta_B of {ch} are not separable over {r_lo:.2f}-{r_hi:.2f} m (the "
                f"backscatter {why}); only its curve over these ranges is determined "
                f"(B_inf * beta_B = {b_inf * beta_b:.3g}/m)"
            )
        for b in ("beta_D", "beta_B", "B_inf"):
            if b != "beta_D" and (b_inf < 0.01 or not separable[c]):
                continue  # no backscatter to speak of, or said above
            if rel_std[b][c] > 0.25:
                warnings.append(
                    f"{b} {ch} = {params[b][c]:.3g} is poorly determined by these frames "
                    f"(+-{100 * rel_std[b][c]:.0f} %): film over a wider range of distances"
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
        artificial_light=cfg.artificial_light,
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
        residual_rms_8bit=float(np.sqrt(np.mean((disp_m - disp) ** 2))),
        contrast_error=cerr,  # type: ignore[arg-type]
        range_m=(float(s.range_m.min()), float(s.range_m.max())),
        samples=s,
        config=cfg,
        separable=tuple(separable),  # type: ignore[arg-type]
        warnings=warnings,
        _x=x,
    )


def _log_std(J: np.ndarray, scale: float) -> np.ndarray:
    """Standard errors of the (log) parameters from the Jacobian of the weighted residuals: a
    parameter the residuals do not depend on (a backscatter already saturated at the nearest
    range) gets a huge one, not the zero a pseudo-inverse would give it."""
    JtJ = J.T @ J
    ridge = 1e-12 * max(float(np.abs(np.diag(JtJ)).max()), 1e-300)
    try:
        cov = np.linalg.inv(JtJ + ridge * np.eye(len(JtJ))) * scale
    except np.linalg.LinAlgError:  # pragma: no cover - the ridge keeps it invertible
        return np.full(len(JtJ), np.inf)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _rgb(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


# ----------------------------------------------------------------------------- outputs


def water_toml(fit: WaterFit, source: str = "") -> str:
    """The fitted water as a ``[water]`` TOML file (read by every ``--water`` option)."""
    head = [
        "# Water fitted by `sim fit-water`" + (f" to {source}" if source else ""),
        f"# {len(fit.samples)} patches in {fit.samples.frames_used} frames, ranges "
        f"{fit.range_m[0]:.2f}-{fit.range_m[1]:.2f} m; residual RMS {fit.residual_rms_8bit:.2f} "
        "grey levels; contrast error R/G/B "
        + "/".join(f"{100 * e:.1f} %" for e in fit.contrast_error),
        f"# blur and sensor noise from the '{fit.config.base}' preset",
        "",
        "[water]",
    ]
    return "\n".join(head) + "\n" + dumps_toml(fit.water)


def write_water_file(fit: WaterFit, path: str | Path, source: str = "") -> Path:
    """Write :func:`water_toml` atomically."""
    return atomic_write_text(path, water_toml(fit, source))


def plot_fit(fit: WaterFit, path: str | Path) -> None:
    """Measured vs modelled contrast (white - black) and black level against range, per
    channel; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = fit.samples
    model = fit.model()
    r_pairs, meas, mod = fit.contrast_pairs()
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.2), sharex=True)
    colours = ("tab:red", "tab:green", "tab:blue")
    for c, ch in enumerate(CHANNELS):
        ax = axes[0, c]
        ax.scatter(r_pairs, meas[:, c], s=4, color=colours[c], alpha=0.35, label="frames")
        order = np.argsort(r_pairs)
        ax.plot(r_pairs[order], mod[order, c], ".", ms=2, color="k", label="model")
        ax.set_yscale("log")
        ax.set_title(f"{ch}: contrast white - black (error {100 * fit.contrast_error[c]:.1f} %)",
                     fontsize=9)  # fmt: skip
        black = ~s.white
        ax = axes[1, c]
        ax.scatter(s.range_m[black], s.rgb[black, c], s=4, color=colours[c], alpha=0.35,
                   label="frames")  # fmt: skip
        ax.plot(s.range_m[black], model[black, c], ".", ms=2, color="k", label="model")
        ax.set_title(f"{ch}: black level (B_inf {fit.params['B_inf'][c]:.3f}, beta_B "
                     f"{fit.params['beta_B'][c]:.3f}/m)", fontsize=9)  # fmt: skip
        ax.set_xlabel("range (m)")
    axes[0, 0].set_ylabel("linear intensity")
    axes[1, 0].set_ylabel("linear intensity")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        "Water fit: beta_D " + ", ".join(f"{v:.3f}" for v in fit.params["beta_D"]) + " /m; "
        f"residual {fit.residual_rms_8bit:.2f} grey levels",
        fontsize=10,
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
