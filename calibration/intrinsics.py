"""Camera intrinsics from views of a chessboard or ChArUco board (``calibration intrinsics``).

Pipeline: read views (an image folder or a sampled video) -> find the pattern with sub-pixel
corners -> reject blurred views and near-duplicates -> keep at most ``max_views`` spread over
pose space -> hold out a seeded fraction -> ``cv2.calibrateCamera`` on the rest -> reprojection
error of the held-out views with the calibrated intrinsics (their pose from PnP) -> camera file,
JSON report and a per-view error plot.

Pattern sizes: ``cols`` x ``rows`` are **inner corners** for a chessboard and **squares** for a
ChArUco board (OpenCV's conventions; see :mod:`calibration.patterns`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import sys
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from tqdm import tqdm

from uwdock.calibration.camera import CameraModel, load_camera, save_camera
from uwdock.calibration.patterns import (
    PATTERNS,
    Detection,
    PatternDetector,
    blur_px,
    normalise_dictionary_name,
    quad_distance_px,
    spread_subset,
    view_quad_px,
)
from uwdock.dockcore.bags import Bag, is_bag
from uwdock.dockcore.config import to_dict, validated
from uwdock.dockcore.domains import Interval, Seed
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_json
from uwdock.dockcore.media import (
    IMAGE_SUFFIXES,
    MAX_CONSECUTIVE_VIDEO_FAILURES,
    open_video,
    quiet_native_stderr,
    read_image,
)
from uwdock.dockcore.provenance import provenance

__all__ = [
    "IMAGE_SUFFIXES",
    "MIN_VIEWS",
    "IntrinsicsConfig",
    "IntrinsicsResult",
    "ViewRecord",
    "calibrate_intrinsics",
    "iter_views",
    "write_outputs",
]

#: Fewest calibration views (held-out views excluded) a calibration accepts.
MIN_VIEWS = 4
#: Views smaller than this on a side (px) are rejected as ``too_small`` (no target fits).
MIN_VIEW_PX = 16
#: Most views one calibration keeps (``max_views``): ``cv2.calibrateCamera`` grows with them.
MAX_VIEWS = 500

#: Inner corners (chessboard) or squares (ChArUco) along one side of a target (OpenCV's
#: chessboard finder needs more than 2).
BoardCount = Annotated[int, Interval(ge=3, le=100)]
#: A square or marker side of a printed target (mm): 0.1 mm ... 1 m.
TargetMm = Annotated[float, Interval(ge=0.1, le=1000.0)]

#: OpenCV calibration flags of each distortion model.
_DIST_FLAGS = {
    "k1k2": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
    "k1k2k3": cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "k1k2p1p2k3": 0,
    "rational": cv2.CALIB_RATIONAL_MODEL,
}


@dataclass(frozen=True)
class IntrinsicsConfig:
    """Intrinsic calibration from views of a planar target.

    Attributes:
        pattern: ``"chessboard"`` or ``"charuco"``.
        cols: chessboard: inner corners per row; charuco: squares per row (3 ... 100).
        rows: chessboard: inner corners per column; charuco: squares per column (3 ... 100).
        square_mm: side of one square (mm, 0.1 ... 1000). Scales the board poses only; K does
            not depend on it.
        marker_mm: ChArUco marker side (mm, 0.1 ... 1000), < ``square_mm``; ``None``: 0.75 x
            ``square_mm``.
        dictionary: ChArUco marker dictionary (``cv2.aruco`` name, e.g. ``DICT_4X4_50``); it
            must hold the board's cols x rows / 2 markers.
        legacy_charuco: the board was printed by OpenCV < 4.6 (matters for an even row count).
        blur_threshold_px: views whose pattern edge width exceeds this are rejected as blurred
            (px, (0, 1000]; a sharp image gives ~2, a Gaussian blur of sigma s gives ~2.5 s).
        duplicate_threshold_frac: a view whose board outline lies closer than this to a kept
            view's (mean corner distance, as a fraction of the image diagonal, [0, 1)) is a
            duplicate.
        max_views: most views used (calibration + hold-out, ``MIN_VIEWS`` ... ``MAX_VIEWS``);
            extra views are dropped so that the kept ones spread over board positions and tilts.
        holdout_fraction: fraction of the kept views held out of the fit to validate it, in
            [0, 0.5]; at least one when there are more than ``MIN_VIEWS`` views, none otherwise.
        seed: seed of the hold-out draw and the spread selection (0 ... 2^32 - 1).
        distortion_model: ``k1k2``, ``k1k2k3``, ``k1k2p1p2``, ``k1k2p1p2k3`` (OpenCV's default)
            or ``rational`` (8 coefficients).
        min_corners: fewest ChArUco corners for a view to count (4 ... the board's inner
            corners; a chessboard is all or nothing).
        subpix_win_px: largest half window of the sub-pixel corner search (px, 2 ... 100).
        video_max_frames: most frames sampled (evenly) from a video input (1 ... 100000).
        corner_method: chessboard corners by ``classic`` (``findChessboardCorners`` +
            ``cornerSubPix``), ``sb`` (``findChessboardCornersSB``) or ``auto``: both, each
            calibrated, and the one with the lower hold-out error kept (the classic one when
            nothing is held out); both errors go into the report. ChArUco has one detector.
        outlier_ratio: after each fit, the calibration view with the largest reprojection
            error is rejected (reason ``outlier``) and the fit repeated while that error exceeds
            this multiple of the median of the other views' (and ``outlier_min_px``), as long
            as ``MIN_VIEWS`` remain; 0 disables. A view with a mis-detected or moved corner
            pulls K toward itself: on real tank frames one view at ~6x the median error moved
            fx by ~8 % and doubled the RMS.
        outlier_min_px: views at or below this error are never outliers (px; sub-pixel
            corners on a sharp board reach ~0.1 px, so a ratio alone would flag noise).
    """

    pattern: str = "chessboard"
    cols: BoardCount = 9
    rows: BoardCount = 6
    square_mm: TargetMm = 25.0
    marker_mm: TargetMm | None = None
    dictionary: str = "DICT_4X4_50"
    legacy_charuco: bool = False
    blur_threshold_px: Annotated[float, Interval(gt=0.0, le=1000.0)] = 6.0
    duplicate_threshold_frac: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.01
    max_views: Annotated[int, Interval(ge=MIN_VIEWS, le=MAX_VIEWS)] = 40
    holdout_fraction: Annotated[float, Interval(ge=0.0, le=0.5)] = 0.2
    seed: Seed = 0
    distortion_model: Literal["k1k2", "k1k2k3", "k1k2p1p2", "k1k2p1p2k3", "rational"] = "k1k2p1p2k3"
    min_corners: Annotated[int, Interval(ge=4, le=100 * 100)] = 8
    corner_method: Literal["auto", "classic", "sb"] = "auto"
    outlier_ratio: Annotated[float, Interval(ge=0.0, le=1000.0)] = 3.0
    outlier_min_px: Annotated[float, Interval(ge=0.0, le=1000.0)] = 0.5
    subpix_win_px: Annotated[int, Interval(ge=2, le=100)] = 11
    video_max_frames: Annotated[int, Interval(ge=1, le=100_000)] = 300

    def validate(self) -> None:
        """Raise ValueError (one line naming the field) for values that do not go together
        (each numeric field's own range is its declared domain)."""
        if self.pattern not in PATTERNS:
            raise ValueError(f"pattern: must be one of {list(PATTERNS)}, got {self.pattern!r}")
        if self.marker_mm is not None and not self.marker_mm < self.square_mm:
            raise ValueError(
                f"marker_mm: must be smaller than square_mm ({self.square_mm:g}), "
                f"got {self.marker_mm:g}"
            )
        try:
            name = normalise_dictionary_name(self.dictionary)
        except ValueError as exc:
            raise ValueError(f"dictionary: {exc}") from None
        if self.pattern == "charuco":
            n_markers = self.cols * self.rows // 2
            n_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
            if n_markers > n_dict:
                raise ValueError(
                    f"dictionary: a {self.cols}x{self.rows} ChArUco board has {n_markers} markers "
                    f"but {name} only {n_dict}"
                )
            inner = (self.cols - 1) * (self.rows - 1)
            if self.min_corners > inner:
                raise ValueError(
                    f"min_corners: {self.min_corners} is more than the {inner} inner corners of "
                    f"a {self.cols}x{self.rows} ChArUco board"
                )

    def detector(self) -> PatternDetector:
        """The pattern detector this configuration describes."""
        return PatternDetector(
            self.pattern,
            self.cols,
            self.rows,
            self.square_mm / 1000.0,
            None if self.marker_mm is None else self.marker_mm / 1000.0,
            self.dictionary,
            legacy_charuco=self.legacy_charuco,
            subpix_win_px=self.subpix_win_px,
            min_corners=self.min_corners,
            corner_method="sb" if self.corner_method == "sb" else "classic",
        )


@dataclass
class ViewRecord:
    """What happened to one input view.

    Attributes:
        name: file name (folder input) or ``frame_<index>`` (video input).
        status: ``calibration``, ``holdout`` or ``rejected``.
        reason: why a view was rejected (``unreadable``, ``too_small``, ``size_mismatch``,
            ``no_pattern``, ``blurred``, ``duplicate``, ``over_cap``, ``outlier``), else None.
        detail: for an outlier, its error against the others' median and the fit's K before
            and after its rejection.
        n_corners: corners found (0 without a detection).
        blur_px: pattern edge width (px), None without a detection.
        error_px: RMS reprojection error of the view (px) for calibration and hold-out views.
    """

    name: str
    status: str = "rejected"
    reason: str | None = None
    n_corners: int = 0
    blur_px: float | None = None
    error_px: float | None = None
    detail: str | None = None
    detection: Detection | None = field(default=None, repr=False)
    quad_px: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no arrays)."""
        return {
            "name": self.name,
            "status": self.status,
            "reason": self.reason,
            "n_corners": self.n_corners,
            "blur_px": _round(self.blur_px),
            "error_px": _round(self.error_px),
            "detail": self.detail,
        }


@dataclass
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`.

    Attributes:
        camera: the calibrated camera (``rms_px`` = RMS over the calibration views).
        holdout_rms_px: RMS reprojection error (px) over the held-out views, None without any.
        views: one record per input view, in input order.
        std_intrinsics: one-sigma uncertainty of fx, fy, cx, cy (px) and each distortion term.
        config: the configuration used.
        source: the input path.
        notes: one-line remarks for the user (e.g. a ChArUco border too thin).
        corner_methods: with ``corner_method = "auto"`` on a chessboard, each method's
            ``{"rms_px", "holdout_rms_px", "views"}`` and which was ``"chosen"``; else None.
    """

    camera: CameraModel
    holdout_rms_px: float | None
    views: list[ViewRecord]
    std_intrinsics: dict[str, float]
    config: IntrinsicsConfig
    source: str
    notes: list[str] = field(default_factory=list)
    corner_methods: dict[str, Any] | None = None

    def counts(self) -> dict[str, Any]:
        """Views read / with the pattern / used / held out / rejected (by reason)."""
        reasons = Counter(v.reason for v in self.views if v.status == "rejected")
        return {
            "read": sum(v.reason != "unreadable" for v in self.views),
            "unreadable": reasons.get("unreadable", 0),
            "pattern_found": sum(v.detection is not None for v in self.views),
            "calibration": sum(v.status == "calibration" for v in self.views),
            "holdout": sum(v.status == "holdout" for v in self.views),
            "rejected": sum(reasons.values()),
            "rejected_by_reason": dict(sorted(reasons.items())),
        }

    def report(self) -> dict[str, Any]:
        """The JSON report written beside the camera file."""
        cam = self.camera
        return {
            "source": self.source,
            "image_size_px": [cam.width_px, cam.height_px],
            "pattern_size_meaning": (
                "inner corners" if self.config.pattern == "chessboard" else "squares"
            ),
            "views": self.counts(),
            "rms_px": _round(cam.rms_px),
            "holdout_rms_px": _round(self.holdout_rms_px),
            "camera_matrix": cam.K.tolist(),
            "distortion_coefficients": list(cam.dist),
            "std_intrinsics": {k: _round(v) for k, v in self.std_intrinsics.items()},
            "per_view": [v.as_dict() for v in self.views],
            "notes": list(self.notes),
            "corner_methods": self.corner_methods,
            "config": to_dict(self.config),
        }


def _round(x: float | None, digits: int = 6) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


# --------------------------------------------------------------------------- input views


def _video_frames(
    path: Path, max_frames: int
) -> tuple[int, Iterator[tuple[str, np.ndarray | None]]]:
    """(views expected, views) of a video: every ``stride``-th frame, at most ``max_frames``.

    A frame that cannot be decoded is a view ``None`` (counted as unreadable) and reading goes
    on past it; it stops at the end of the stream or after
    ``dockcore.media.MAX_CONSECUTIVE_VIDEO_FAILURES`` failed reads in a row; corrupt leading
    frames are skipped. Decoding is quiet (:func:`dockcore.media.quiet_native_stderr`).
    """
    cap, first, leading = open_video(path)
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    stride = max(1, math.ceil(count / max_frames)) if count > 0 else 1
    total = min(max_frames, math.ceil(count / stride)) if count > 0 else max_frames

    def read() -> np.ndarray | None:
        with quiet_native_stderr():
            for _ in range(stride - 1):
                cap.grab()
            ok, frame = cap.read()
        return frame if ok else None

    def frames() -> Iterator[tuple[str, np.ndarray | None]]:
        try:
            index, frame, n, failures = leading, first, 0, 0
            while n < max_frames and failures < MAX_CONSECUTIVE_VIDEO_FAILURES:
                if count > 0 and index >= count:
                    break
                if frame is None:
                    failures += 1
                else:
                    failures = 0
                    frame = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
                yield f"frame_{index:06d}", frame
                n += 1
                index += stride
                frame = read()
        finally:
            cap.release()

    return total, frames()


def _bag_frames(
    path: Path, topic: str, max_frames: int
) -> tuple[int, Iterator[tuple[str, np.ndarray | None]]]:
    """(views expected, views) of a bag's image topic: every ``stride``-th message, at most
    ``max_frames``, greyscale; an undecodable message is a view None."""
    with Bag(path) as bag:
        count = bag.topic(topic, ("image",)).count
    stride = max(1, math.ceil(count / max_frames))
    total = min(max_frames, math.ceil(count / stride))

    def frames() -> Iterator[tuple[str, np.ndarray | None]]:
        with Bag(path) as bag:
            n = 0
            for k, (_, image) in enumerate(bag.images(topic)):
                if k % stride or n >= total:
                    continue
                if image is not None:
                    if image.dtype == np.uint16:  # as imread's GRAYSCALE flag does
                        image = (image >> 8).astype(np.uint8)
                    if image.ndim == 3:
                        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                yield f"frame_{k:06d}", image
                n += 1

    return total, frames()


def iter_views(
    source: str | os.PathLike[str], video_max_frames: int = 300, topic: str | None = None
) -> tuple[int, Iterator[tuple[str, np.ndarray | None]]]:
    """The views of an input: an image folder (sorted by name), a video file (sampled) or a
    ROS bag's image topic (sampled, :mod:`dockcore.bags`).

    Args:
        source: folder of images (``IMAGE_SUFFIXES``), a video file ``cv2.VideoCapture`` reads,
            or a bag (``.bag``, ``.db3``, ``.mcap``, ROS 2 folder).
        video_max_frames: most frames taken from a video or bag, evenly spaced over its length.
        topic: a bag's image topic (required for a bag: see
            :func:`dockcore.bags.resolve_image_topic`).

    Returns:
        (expected number of views, iterator of (name, greyscale uint8 image or None for a file
        that cannot be decoded)).

    Raises:
        DockError: missing input, a folder without images, an unreadable video.
    """
    path = Path(source)
    if path.exists() and is_bag(path):
        if topic is None:
            raise DockError(f"{path} is a bag: name its image topic (--topic)")
        return _bag_frames(path, topic, video_max_frames)
    if path.is_dir():
        files = sorted(
            p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not files:
            raise DockError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder {path}")
        return len(files), ((p.name, read_image(p, grey=True)) for p in files)
    if path.is_file():
        return _video_frames(path, video_max_frames)
    raise DockError(f"input not found: {path}")


# --------------------------------------------------------------------------- view selection


def _image_blur_px(gray: np.ndarray) -> float:
    """Whole-image edge width (px), used only to label a view without a detection."""
    img = gray.astype(np.float32)
    lo, hi = np.percentile(img, [1.0, 99.0])
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    peak = float(np.percentile(np.hypot(gx, gy), 99.5))
    return float(hi - lo) / max(peak, 1e-6)


def _inspect(
    views: Iterator[tuple[str, np.ndarray | None]],
    total: int,
    cfg: IntrinsicsConfig,
    detector: PatternDetector,
    progress: bool | None,
) -> tuple[list[ViewRecord], tuple[int, int] | None]:
    """Detect, measure blur and reject duplicates view by view (input order)."""
    records: list[ViewRecord] = []
    kept_quads: list[np.ndarray] = []
    size: tuple[int, int] | None = None
    dup_px = 0.0
    show = sys.stderr.isatty() if progress is None else bool(progress)
    bar = tqdm(views, total=total, desc="views", unit="view", disable=not show)
    for name, gray in bar:
        rec = ViewRecord(name)
        records.append(rec)
        if gray is None:
            rec.reason = "unreadable"
            continue
        if min(gray.shape[:2]) < MIN_VIEW_PX:
            rec.reason = "too_small"
            continue
        if size is None:
            size = (gray.shape[1], gray.shape[0])
            dup_px = cfg.duplicate_threshold_frac * math.hypot(*size)
        if (gray.shape[1], gray.shape[0]) != size:
            rec.reason = "size_mismatch"
            continue
        det = detector.detect(gray)
        if det is None:
            blurred = _image_blur_px(gray) > cfg.blur_threshold_px
            rec.reason = "blurred" if blurred else "no_pattern"
            continue
        rec.detection, rec.n_corners = det, det.n_corners
        rec.blur_px = blur_px(gray, det)
        rec.quad_px = view_quad_px(det, detector.outline_m)
        if rec.blur_px > cfg.blur_threshold_px:
            rec.reason = "blurred"
        elif rec.quad_px is None:
            rec.reason = "no_pattern"
        elif any(quad_distance_px(rec.quad_px, q) < dup_px for q in kept_quads):
            rec.reason = "duplicate"
        else:
            rec.status = "candidate"
            kept_quads.append(rec.quad_px)
    bar.close()
    return records, size


def _select(records: list[ViewRecord], cfg: IntrinsicsConfig) -> list[ViewRecord]:
    """Cap the candidates at ``max_views`` (spread) and split them into calibration / hold-out."""
    cands = [r for r in records if r.status == "candidate"]
    keep = set(spread_subset([r.quad_px for r in cands], cfg.max_views, cfg.seed))
    for i, rec in enumerate(cands):
        if i not in keep:
            rec.status, rec.reason = "rejected", "over_cap"
    kept = [r for i, r in enumerate(cands) if i in keep]
    n_hold = 0
    if cfg.holdout_fraction > 0 and len(kept) > MIN_VIEWS:
        n_hold = min(max(1, round(cfg.holdout_fraction * len(kept))), len(kept) - MIN_VIEWS)
    hold = set(np.random.default_rng(cfg.seed).choice(len(kept), n_hold, replace=False).tolist())
    for i, rec in enumerate(kept):
        rec.status = "holdout" if i in hold else "calibration"
    return kept


# --------------------------------------------------------------------------- calibration


def _view_rms_px(det: Detection, rvec: np.ndarray, tvec: np.ndarray, K, dist) -> float:
    proj, _ = cv2.projectPoints(det.object_m.astype(np.float64), rvec, tvec, K, dist)
    err = proj.reshape(-1, 2) - det.image_px.astype(np.float64)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _holdout_error(det: Detection, K: np.ndarray, dist: np.ndarray) -> tuple[float, float]:
    """(RMS px, sum of squared px errors) of a held-out view posed by PnP with fixed intrinsics."""
    obj = det.object_m.astype(np.float64)
    img = det.image_px.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    rms = _view_rms_px(det, rvec, tvec, K, dist)
    return rms, rms**2 * det.n_corners


_STD_NAMES = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def calibrate_intrinsics(
    source: str | os.PathLike[str],
    cfg: IntrinsicsConfig | None = None,
    name: str = "camera",
    progress: bool | None = False,
    topic: str | None = None,
) -> IntrinsicsResult:
    """Calibrate a camera from an image folder, a video or a ROS bag of a chessboard / ChArUco
    board.

    Args:
        source: image folder, video file or bag (see :func:`iter_views`).
        cfg: configuration (defaults: 9 x 6 inner-corner chessboard, 25 mm squares).
        name: camera name written into the camera file.
        progress: tqdm progress bar on stderr: True, False, or None (only on a terminal).
        topic: a bag's image topic.

    Returns:
        The calibrated camera, the hold-out error and one record per view.

    Raises:
        DockError: bad input (see :func:`iter_views`), no pattern in any view, fewer than
            ``MIN_VIEWS`` usable views, or a calibration OpenCV rejects.
    """
    cfg = validated(cfg or IntrinsicsConfig())
    if cfg.corner_method == "auto" and cfg.pattern == "chessboard":
        return _best_corner_method(source, cfg, name, progress, topic)
    detector = cfg.detector()
    total, views = iter_views(source, cfg.video_max_frames, topic)
    records, size = _inspect(views, total, cfg, detector, progress)
    if size is None:
        raise DockError(f"none of the {len(records)} images in {source} could be decoded")
    n_found = sum(r.detection is not None for r in records)
    if n_found == 0:
        blurred = sum(r.reason == "blurred" for r in records)
        raise DockError(
            f"no {cfg.pattern} of {cfg.cols}x{cfg.rows} "
            f"{'inner corners' if cfg.pattern == 'chessboard' else 'squares'} found in any of "
            f"{len(records)} views ({blurred} too blurred); check --pattern, --cols and --rows"
            + "".join(f"; {note}" for note in detector.notes)
        )
    kept = _select(records, cfg)
    cal = [r for r in kept if r.status == "calibration"]
    if len(cal) < MIN_VIEWS:
        reasons = Counter(r.reason for r in records if r.status == "rejected")
        detail = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())) or "none"
        raise DockError(
            f"only {len(cal)} usable views of {len(records)}, need at least {MIN_VIEWS} "
            f"(rejected: {detail})"
        )
    rms, K, dist, std_in = _fit_rejecting_outliers(cal, size, cfg)
    sq_sum, n_pts = 0.0, 0
    for rec in (r for r in kept if r.status == "holdout"):
        rec.error_px, sq = _holdout_error(rec.detection, K, dist)
        sq_sum, n_pts = sq_sum + sq, n_pts + rec.n_corners
    holdout = math.sqrt(sq_sum / n_pts) if n_pts else None
    n_dist = 8 if cfg.distortion_model == "rational" else 5
    camera = CameraModel(
        width_px=int(size[0]),
        height_px=int(size[1]),
        fx_px=float(K[0, 0]),
        fy_px=float(K[1, 1]),
        cx_px=float(K[0, 2]),
        cy_px=float(K[1, 2]),
        dist=tuple(float(d) for d in dist[:n_dist]),
        rms_px=float(rms),
        name=name,
    )
    std = std_in.reshape(-1)
    std_named = {k: float(std[i]) for i, k in enumerate(_STD_NAMES[: 4 + n_dist])}
    notes = list(detector.notes)
    for rec in records:
        if rec.reason == "outlier":
            notes.append(f"{rec.name} rejected as an outlier: {rec.detail}")
    if holdout is not None and holdout > HOLDOUT_WARN_RATIO * rms:
        notes.append(
            f"warning: the hold-out error {holdout:.3f} px is {holdout / rms:.1f}x the fit's "
            f"{rms:.3f} px: the model does not generalise (too few or too similar views, or a "
            "distortion model with too many terms)"
        )
    empty = uncovered_corners([r for r in kept if r.status == "calibration"], size)
    if empty:
        notes.append(
            f"warning: no calibration view covers the image's {', '.join(empty)} corner"
            f"{'s' if len(empty) > 1 else ''}: distortion there is extrapolated; add views "
            "with the board in those corners"
        )
    return IntrinsicsResult(camera, holdout, records, std_named, cfg, str(source), notes)


def _best_corner_method(
    source: str | os.PathLike[str],
    cfg: IntrinsicsConfig,
    name: str,
    progress: bool | None,
    topic: str | None,
) -> IntrinsicsResult:
    """Calibrate with the classic and the sector-based chessboard corners; keep the one with
    the lower hold-out error (classic when nothing is held out or only it succeeds)."""
    results: dict[str, IntrinsicsResult] = {}
    failures: dict[str, str] = {}
    for method in ("classic", "sb"):
        try:
            results[method] = calibrate_intrinsics(
                source, dataclasses.replace(cfg, corner_method=method), name, progress, topic
            )
        except DockError as exc:
            failures[method] = str(exc)
    if not results:
        raise DockError(failures["classic"])
    held = {m: r.holdout_rms_px for m, r in results.items() if r.holdout_rms_px is not None}
    chosen = min(held, key=lambda m: held[m]) if len(held) == 2 else next(iter(results))
    best = results[chosen]
    table: dict[str, Any] = {"chosen": chosen}
    for m in ("classic", "sb"):
        r = results.get(m)
        table[m] = (
            {"failed": failures[m]}
            if r is None
            else {
                "rms_px": _round(r.camera.rms_px),
                "holdout_rms_px": _round(r.holdout_rms_px),
                "views": r.counts()["calibration"],
            }
        )
    why = (
        f"lower hold-out error: {held[chosen]:.3f} against {max(held.values()):.3f} px"
        if len(held) == 2
        else "the only one"
        if len(results) == 1
        else "nothing held out to compare"
    )
    best.notes.insert(0, f"chessboard corners: {chosen} ({why})")
    best.corner_methods = table
    best.config = cfg
    return best


#: Hold-out error above this multiple of the fit's RMS is warned about.
HOLDOUT_WARN_RATIO = 2.0

#: Image corners checked for coverage: a corner region is this fraction of each side.
CORNER_REGION_FRAC = 0.2


def uncovered_corners(views: list[ViewRecord], size: tuple[int, int]) -> list[str]:
    """Image corners (``top-left`` ...) where no calibration view has a detected pattern corner
    within ``CORNER_REGION_FRAC`` of both sides."""
    w, h = size
    pts = [r.detection.image_px.reshape(-1, 2) for r in views if r.detection is not None]
    if not pts:
        return []
    p = np.concatenate(pts)
    fx, fy = CORNER_REGION_FRAC * w, CORNER_REGION_FRAC * h
    left, right = p[:, 0] < fx, p[:, 0] > w - fx
    top, bottom = p[:, 1] < fy, p[:, 1] > h - fy
    regions = {
        "top-left": top & left,
        "top-right": top & right,
        "bottom-left": bottom & left,
        "bottom-right": bottom & right,
    }
    return [name for name, inside in regions.items() if not inside.any()]


def _calibrate(cal: list[ViewRecord], size: tuple[int, int], cfg: IntrinsicsConfig):
    obj = [r.detection.object_m.reshape(-1, 1, 3) for r in cal]  # type: ignore[union-attr]
    img = [r.detection.image_px.reshape(-1, 1, 2) for r in cal]  # type: ignore[union-attr]
    try:
        rms, K, dist, _, _, std_in, _, per_view = cv2.calibrateCameraExtended(
            obj, img, size, None, None, flags=_DIST_FLAGS[cfg.distortion_model]
        )
    except cv2.error as exc:
        text = " ".join(str(exc).split()).split(" error: ", 1)[-1]
        raise DockError(f"calibration failed: {text}") from None
    return float(rms), K, dist.reshape(-1), std_in, per_view.reshape(-1)


def _fit_rejecting_outliers(cal: list[ViewRecord], size: tuple[int, int], cfg: IntrinsicsConfig):
    """Fit, then reject the worst view while it is an outlier (``cfg.outlier_ratio``); the
    rejected records get status ``rejected``, reason ``outlier`` and a detail. Returns (rms,
    K, dist, std) of the last fit; sets ``error_px`` of the views kept."""
    views = list(cal)
    while True:
        rms, K, dist, std_in, per_view = _calibrate(views, size, cfg)
        for rec, err in zip(views, per_view, strict=True):
            rec.error_px = float(err)
        if cfg.outlier_ratio <= 0 or len(views) <= MIN_VIEWS:
            return rms, K, dist, std_in
        worst = int(np.argmax(per_view))
        others = float(np.median(np.delete(per_view, worst)))
        err = float(per_view[worst])
        if err <= cfg.outlier_min_px or err <= cfg.outlier_ratio * others:
            return rms, K, dist, std_in
        rec = views.pop(worst)
        rec.status, rec.reason = "rejected", "outlier"
        rms2, K2, *_ = _calibrate(views, size, cfg)
        rec.detail = (
            f"{err:.2f} px, {err / max(others, 1e-12):.1f}x the other views' median "
            f"{others:.2f} px; without it fx {K[0, 0]:.1f} -> {K2[0, 0]:.1f} px, RMS "
            f"{rms:.3f} -> {rms2:.3f} px"
        )


# --------------------------------------------------------------------------- outputs


def _plot_errors(result: IntrinsicsResult, path: Path) -> None:
    """Bar chart of per-view RMS reprojection error (px), calibration vs hold-out views."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    used = [v for v in result.views if v.status in ("calibration", "holdout")]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.22 * len(used) + 2.0), 3.6), dpi=100)
    colours = ["tab:blue" if v.status == "calibration" else "tab:orange" for v in used]
    ax.bar(range(len(used)), [v.error_px or 0.0 for v in used], color=colours)
    ax.axhline(
        result.camera.rms_px or 0.0,
        color="tab:blue",
        ls="--",
        lw=1,
        label=f"calibration RMS {result.camera.rms_px:.3f} px",
    )
    if result.holdout_rms_px is not None:
        ax.axhline(
            result.holdout_rms_px,
            color="tab:orange",
            ls="--",
            lw=1,
            label=f"hold-out RMS {result.holdout_rms_px:.3f} px",
        )
    ax.set_xticks(range(len(used)))
    ax.set_xticklabels([v.name for v in used], rotation=90, fontsize=6)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("Per-view error (blue: calibration, orange: hold-out)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_outputs(
    result: IntrinsicsResult, out: str | os.PathLike[str], keep_extrinsics: bool = True
) -> tuple[list[Path], bool]:
    """Write the camera file twins, ``<stem>_report.json`` and ``<stem>_errors.png``.

    Args:
        result: a calibration.
        out: camera file path (``.yaml``, ``.yml`` or ``.json``).
        keep_extrinsics: when ``out`` already holds a readable camera file with ``T_body_cam``,
            carry it over (intrinsics do not change where the camera is mounted).

    Returns:
        (the paths written, whether ``T_body_cam`` was carried over).
    """
    out = Path(out)
    T = None
    if keep_extrinsics and out.is_file():
        with contextlib.suppress(DockError):
            T = load_camera(out)[1]
    yaml_path, json_path = save_camera(out, result.camera, T)
    report = result.report()
    report["T_body_cam_kept"] = T is not None
    report["provenance"] = provenance()  # code version, packages, machine, command line
    report_path = out.with_name(f"{out.stem}_report.json")
    plot_path = out.with_name(f"{out.stem}_errors.png")
    atomic_write_json(report_path, report)
    _plot_errors(result, plot_path)
    return [yaml_path, json_path, report_path, plot_path], T is not None
