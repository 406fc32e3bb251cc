"""The water fit's measurements: the black and white patches of a known target (a printed
chessboard or the DS marker board) posed by PnP in each frame, with their range, their geometry
to the lamp and their place in the image (:func:`sample_frames`), and the sensor noise read from
the spread inside them (:func:`estimate_noise`). :mod:`datasets.water_fit` fits the water to
them; ``sim fit-water`` is the command.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import make_T
from uwdock.calibration.patterns import PatternDetector
from uwdock.dockcore.errors import DockError
from uwdock.markers.dictionary import bits_per_side
from uwdock.markers.markerset import MarkerSet
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.sim.water import decode_lut

if TYPE_CHECKING:
    from uwdock.datasets.water_fit_config import FitWaterConfig

__all__ = ["PatchSamples", "estimate_noise", "sample_frames"]


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
    target = _target(cfg, marker_set)
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
        _check_frame(name, img, camera)
        T = target.pose(img, camera)
        if T is None:
            continue
        rows, sat = _sample_frame(img, camera, target, T, cfg, lut)
        saturated += sat
        if not rows or not _decide_white(rows):
            continue
        names[int(index)] = str(name)
        _add_rows(cols, groups, index, rows, neighbours)
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


def _target(cfg: FitWaterConfig, marker_set: MarkerSet | None) -> _Target:
    """The target ``cfg.target`` names: the DS marker board (``marker_set`` needed) or the
    chessboard."""
    if cfg.target == "markers":
        if marker_set is None:
            raise DockError("target 'markers' needs the DS marker set (--marker-set)")
        return _MarkerBoard(cfg, marker_set)
    return _Chessboard(cfg)


def _check_frame(name: str, img: np.ndarray, camera: CameraModel) -> None:
    """Refuse a frame that is not a colour image of the camera's size."""
    if img.ndim != 3 or img.shape[2] != 3:
        raise DockError(f"{name}: the water fit needs colour frames, got shape {img.shape}")
    if (img.shape[1], img.shape[0]) != (camera.width_px, camera.height_px):
        raise DockError(
            f"{name}: frame is {img.shape[1]}x{img.shape[0]} px, the camera file "
            f"{camera.width_px}x{camera.height_px}"
        )


def _decide_white(rows: list[dict[str, Any]]) -> bool:
    """Whether the frame's patches are known white or black: a chessboard's brighter parity is
    made white here; False when it shows one parity only, none clipped (which is not known)."""
    if any(r["white"] is None for r in rows):  # chessboard: the brighter parity is white
        if len({r["parity"] for r in rows}) == 1:
            return False  # one parity only, none clipped: which is white is not known
        lum = {p: np.mean([r["rgb"].sum() for r in rows if r["parity"] == p] or [0.0])
               for p in (0, 1)}  # fmt: skip
        white_parity = 0 if lum[0] > lum[1] else 1
        for r in rows:
            r["white"] = r["parity"] == white_parity
    return True


def _add_rows(
    cols: dict[str, list],
    groups: list[tuple[int, list[int]]],
    index: int,
    rows: list[dict[str, Any]],
    neighbours: list[tuple[int, list[int]]],
) -> None:
    """Append frame ``index``'s patches to the columns, and its white patches with their black
    neighbours to ``groups``."""
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
