"""Camera intrinsics from views of a chessboard or ChArUco board (``calibration intrinsics``).

Pipeline: read views (an image folder, a sampled video or a bag topic, each turned grey the same
way) -> find the pattern with sub-pixel corners -> reject blurred views (edge width on the board)
and near-duplicates -> keep at most ``max_views`` spread over pose space (deterministically) ->
cross-validate over the views (:mod:`calibration.crossval`: leave-one-view-out or k folds, no
random draw), rejecting views whose held-out error the others' consensus does not explain ->
``cv2.calibrateCamera`` on every accepted view -> camera file, JSON report (the folds' spread of
fx, fy, cx, cy as the uncertainty) and a per-view error plot.

Pattern sizes: ``cols`` x ``rows`` are **inner corners** for a chessboard and **squares** for a
ChArUco board (OpenCV's conventions; see :mod:`calibration.patterns`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from tqdm import tqdm

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.crossval import (
    INTRINSIC_NAMES,
    CrossValidation,
    Fit,
    cross_validate,
    fit_views,
)
from uwdock.calibration.intrinsics_inputs import iter_views, to_grey
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
from uwdock.dockcore.config import to_dict, validated
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import (
    IMAGE_SUFFIXES,
)

__all__ = [
    "IMAGE_SUFFIXES",
    "MIN_VIEWS",
    "IntrinsicsConfig",
    "IntrinsicsResult",
    "ViewRecord",
    "calibrate_intrinsics",
    "iter_views",
    "to_grey",
]

#: Fewest calibration views a calibration accepts.
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
        max_views: most views used (``MIN_VIEWS`` ... ``MAX_VIEWS``); extra views are dropped
            so that the kept ones spread over board positions and tilts (farthest-point
            sampling from the medoid view: no random draw).
        cv_folds: cross-validation folds (0 ... 100): 0 = leave-one-view-out up to 40 views
            and 10 folds above; ``k >= 2``: ``k`` folds, view ``i`` in fold ``i mod k``. The
            final intrinsics are fitted on every accepted view; the folds give the held-out
            error and the uncertainty (see :mod:`calibration.crossval`).
        uncertainty_warn_frac: warn when the folds' jackknife standard deviation of fx, fy, cx
            or cy exceeds this fraction of its value ((0, 1]; 0.01 = 1 %).
        distortion_model: ``k1k2``, ``k1k2k3``, ``k1k2p1p2``, ``k1k2p1p2k3`` (OpenCV's default)
            or ``rational`` (8 coefficients).
        min_corners: fewest ChArUco corners for a view to count (4 ... the board's inner
            corners; a chessboard is all or nothing).
        subpix_win_px: largest half window of the sub-pixel corner search (px, 2 ... 100).
        video_max_frames: most frames sampled (evenly) from a video input (1 ... 100000).
        corner_method: chessboard corners by ``classic`` (``findChessboardCorners`` +
            ``cornerSubPix``), ``sb`` (``findChessboardCornersSB``) or ``auto``: both, each
            calibrated, and the one with the lower cross-validated error *on the views both
            accept* kept (the one with more accepted views when fewer than ``MIN_VIEWS + 1``
            views are common; classic on a tie); the comparison goes into the report.
            ChArUco has one detector.
        outlier_ratio: the view with the largest held-out error (posed with the intrinsics the
            other views give) is rejected (reason ``outlier``) and the cross-validation
            repeated while that error exceeds this multiple of the median of the other views'
            (and ``outlier_min_px``), as long as ``MIN_VIEWS`` remain; 0 disables. A
            view with a mis-detected or moved corner pulls K toward itself, so its in-fit error
            understates it: on real tank frames one such view moved fx by ~8 %.
        outlier_min_px: views at or below this held-out error are never outliers (px;
            sub-pixel corners on a sharp board reach ~0.1 px, so a ratio alone would flag
            noise).
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
    cv_folds: Annotated[int, Interval(ge=0, le=100)] = 0
    uncertainty_warn_frac: Annotated[float, Interval(gt=0.0, le=1.0)] = 0.01
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
        if self.cv_folds == 1:
            raise ValueError("cv_folds: must be 0 (leave-one-view-out) or at least 2, got 1")
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
        status: ``calibration`` or ``rejected`` (``candidate`` while being selected).
        reason: why a view was rejected (``unreadable``, ``too_small``, ``size_mismatch``,
            ``no_pattern``, ``blurred``, ``duplicate``, ``over_cap``, ``outlier``), else None.
            ``blurred`` is judged on the board's own edges only: a view where the pattern is
            not found is ``no_pattern`` (the detail gives the whole image's edge width).
        detail: for an outlier, its held-out error against the others' median and the fit's
            fx before and after its rejection; for ``no_pattern``, the image's edge width.
        n_corners: corners found (0 without a detection).
        blur_px: pattern edge width (px), None without a detection.
        error_px: RMS reprojection error of a calibration view in the final fit (px).
        cv_error_px: its held-out error (px): posed by PnP with the intrinsics fitted without
            its fold (for an outlier: at its rejection).
    """

    name: str
    status: str = "rejected"
    reason: str | None = None
    n_corners: int = 0
    blur_px: float | None = None
    error_px: float | None = None
    cv_error_px: float | None = None
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
            "cv_error_px": _round(self.cv_error_px),
            "detail": self.detail,
        }


@dataclass
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`.

    Attributes:
        camera: the calibrated camera (``rms_px`` = RMS over the calibration views), fitted on
            every accepted view.
        cv: the cross-validation over the accepted views (held-out errors, folds' intrinsics).
        views: one record per input view, in input order.
        std_intrinsics: Jacobian one-sigma of fx, fy, cx, cy (px) and each distortion term
            (``cv2.calibrateCameraExtended``; assumes independent Gaussian corner errors).
        config: the configuration used.
        source: the input path.
        notes: one-line remarks for the user (e.g. a ChArUco border too thin).
        corner_methods: with ``corner_method = "auto"`` on a chessboard, each method's
            figures, the comparison on the common views and which was ``"chosen"``; else None.
    """

    camera: CameraModel
    cv: CrossValidation
    views: list[ViewRecord]
    std_intrinsics: dict[str, float]
    config: IntrinsicsConfig
    source: str
    notes: list[str] = field(default_factory=list)
    corner_methods: dict[str, Any] | None = None

    @property
    def cv_rms_px(self) -> float:
        """Cross-validated RMS reprojection error over the accepted views' corners (px)."""
        return self.cv.rms_px

    def uncertainty(self) -> dict[str, float]:
        """Grouped-jackknife standard deviation of fx, fy, cx, cy over the folds (px)."""
        return dict(zip(INTRINSIC_NAMES, self.cv.uncertainty().tolist(), strict=True))

    def uncertainty_frac(self) -> dict[str, float]:
        """:meth:`uncertainty` as a fraction of each value."""
        cam = self.camera
        values = (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px)
        unc = self.uncertainty()
        return {k: unc[k] / abs(v) for k, v in zip(INTRINSIC_NAMES, values, strict=True)}

    def counts(self) -> dict[str, Any]:
        """Views read / with the pattern / used / rejected (by reason)."""
        reasons = Counter(v.reason for v in self.views if v.status == "rejected")
        return {
            "read": sum(v.reason != "unreadable" for v in self.views),
            "unreadable": reasons.get("unreadable", 0),
            "pattern_found": sum(v.detection is not None for v in self.views),
            "calibration": sum(v.status == "calibration" for v in self.views),
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
            "cv_rms_px": _round(self.cv_rms_px),
            "camera_matrix": cam.K.tolist(),
            "distortion_coefficients": list(cam.dist),
            "uncertainty_px": {k: _round(v) for k, v in self.uncertainty().items()},
            "uncertainty_frac": {k: _round(v) for k, v in self.uncertainty_frac().items()},
            "cross_validation": {
                "scheme": self.cv.scheme,
                "folds": len(self.cv.folds),
                "rms_px": _round(self.cv_rms_px),
                "fold_spread_px": {
                    k: {kk: _round(vv) for kk, vv in v.items()} for k, v in self.cv.spread().items()
                },
                "fold_intrinsics_px": [[_round(x, 4) for x in row] for row in self.cv.params],
                "failed_folds": list(self.cv.failed_folds),
            },
            "std_intrinsics": {k: _round(v) for k, v in self.std_intrinsics.items()},
            "per_view": [v.as_dict() for v in self.views],
            "notes": list(self.notes),
            "corner_methods": self.corner_methods,
            "config": to_dict(self.config),
        }


def _round(x: float | None, digits: int = 6) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


# --------------------------------------------------------------------------- view selection


def _image_blur_px(gray: np.ndarray) -> float:
    """Whole-image edge width (px), only a hint in the detail of a view without a detection
    (a whole-image measure mixes the board with the background: on a real murky tank it
    called 5 views blurred whose board the classic finder reads)."""
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
            rec.reason = "no_pattern"
            width = _image_blur_px(gray)
            if width > cfg.blur_threshold_px:
                rec.detail = f"image edge width {width:.1f} px (the whole image may be blurred)"
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
    """Cap the candidates at ``max_views`` (spread over poses, deterministic); the kept ones
    become calibration views."""
    cands = [r for r in records if r.status == "candidate"]
    keep = set(spread_subset([r.quad_px for r in cands], cfg.max_views))
    for i, rec in enumerate(cands):
        rec.status, rec.reason = ("calibration", None) if i in keep else ("rejected", "over_cap")
    return [r for r in cands if r.status == "calibration"]


# --------------------------------------------------------------------------- calibration


_STD_NAMES = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")

#: A cross-validated error above this multiple of the fit's RMS is warned about.
CV_WARN_RATIO = 2.0

#: Image corners checked for coverage: a corner region is this fraction of each side.
CORNER_REGION_FRAC = 0.2


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
        The camera fitted on every accepted view, its cross-validation (held-out errors, the
        folds' spread as the uncertainty) and one record per view. Deterministic: the same
        input and configuration give the same result.

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
    if not any(r.detection is not None for r in records):
        raise DockError(
            f"no {cfg.pattern} of {cfg.cols}x{cfg.rows} "
            f"{'inner corners' if cfg.pattern == 'chessboard' else 'squares'} found in any of "
            f"{len(records)} views; check --pattern, --cols and --rows"
            + "".join(f"; {note}" for note in detector.notes)
        )
    cal = _select(records, cfg)
    if len(cal) < MIN_VIEWS:
        reasons = Counter(r.reason for r in records if r.status == "rejected")
        detail = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())) or "none"
        raise DockError(
            f"only {len(cal)} usable views of {len(records)}, need at least {MIN_VIEWS} "
            f"(rejected: {detail})"
        )
    fit, cv = _fit_rejecting_outliers(cal, size, cfg)
    n_dist = 8 if cfg.distortion_model == "rational" else 5
    K, dist = fit.K, fit.dist
    camera = CameraModel(
        width_px=int(size[0]),
        height_px=int(size[1]),
        fx_px=float(K[0, 0]),
        fy_px=float(K[1, 1]),
        cx_px=float(K[0, 2]),
        cy_px=float(K[1, 2]),
        dist=tuple(float(d) for d in dist[:n_dist]),
        rms_px=float(fit.rms_px),
        name=name,
    )
    std_named = {k: float(fit.std[i]) for i, k in enumerate(_STD_NAMES[: 4 + n_dist])}
    result = IntrinsicsResult(camera, cv, records, std_named, cfg, str(source))
    result.notes = list(detector.notes) + _warnings(result, size)
    return result


def _warnings(result: IntrinsicsResult, size: tuple[int, int]) -> list[str]:
    """Outliers rejected, a cross-validated error far above the fit's, intrinsics the folds
    disagree on, image corners no view reaches."""
    notes = [
        f"{rec.name} rejected as an outlier: {rec.detail}"
        for rec in result.views
        if rec.reason == "outlier"
    ]
    rms, cv_rms = result.camera.rms_px or 0.0, result.cv_rms_px
    if cv_rms > CV_WARN_RATIO * rms:
        notes.append(
            f"warning: the cross-validated error {cv_rms:.3f} px is "
            f"{cv_rms / max(rms, 1e-12):.1f}x the fit's {rms:.3f} px: the model does not "
            "generalise (too few or too similar views, or a distortion model with too many terms)"
        )
    frac, unc = result.uncertainty_frac(), result.uncertainty()
    loose = [k for k, v in frac.items() if not v <= result.config.uncertainty_warn_frac]
    if loose:
        detail = ", ".join(f"{k[:2]} +-{unc[k]:.1f} px ({100 * frac[k]:.1f} %)" for k in loose)
        notes.append(
            f"warning: the views disagree on the intrinsics ({result.cv.scheme} jackknife: "
            f"{detail}; limit {100 * result.config.uncertainty_warn_frac:g} %): add views "
            "that tilt the board more and fill the image"
        )
    for msg in result.cv.failed_folds:
        notes.append(f"warning: cross-validation {msg}")
    empty = uncovered_corners([r for r in result.views if r.status == "calibration"], size)
    if empty:
        notes.append(
            f"warning: no calibration view covers the image's {', '.join(empty)} corner"
            f"{'s' if len(empty) > 1 else ''}: distortion there is extrapolated; add views "
            "with the board in those corners"
        )
    return notes


def _best_corner_method(
    source: str | os.PathLike[str],
    cfg: IntrinsicsConfig,
    name: str,
    progress: bool | None,
    topic: str | None,
) -> IntrinsicsResult:
    """Calibrate with the classic and the sector-based chessboard corners and keep the one with
    the lower cross-validated error on the views both accept (compared on the same views,
    since a method that keeps only its easy views would otherwise look better)."""
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
    accepted = {
        m: {v.name: v for v in r.views if v.status == "calibration"} for m, r in results.items()
    }
    common = [n for n in accepted.get("classic", {}) if n in accepted.get("sb", {})]
    table: dict[str, Any] = {"common_views": len(common)}
    common_cv: dict[str, float] = {}
    if len(results) == 2 and len(common) > MIN_VIEWS:
        size = (results["classic"].camera.width_px, results["classic"].camera.height_px)
        for m in results:
            if list(accepted[m]) == common:  # every view it accepts is common: its own CV
                common_cv[m] = results[m].cv_rms_px
                continue
            dets = [accepted[m][n].detection for n in common]
            flags = _DIST_FLAGS[cfg.distortion_model]
            common_cv[m] = cross_validate(dets, size, flags, cfg.cv_folds).rms_px
        chosen = min(common_cv, key=lambda m: (common_cv[m], m != "classic"))
        other = "sb" if chosen == "classic" else "classic"
        why = (
            f"lower cross-validated error on the {len(common)} views both accept: "
            f"{common_cv[chosen]:.3f} against {common_cv[other]:.3f} px"
        )
    elif len(results) == 2:
        chosen = max(results, key=lambda m: (len(accepted[m]), m == "classic"))
        why = (
            f"more accepted views ({len(accepted[chosen])}); only {len(common)} views are "
            "common to both, too few to compare"
        )
    else:
        chosen, why = next(iter(results)), "the only one"
    for m in ("classic", "sb"):
        r = results.get(m)
        table[m] = (
            {"failed": failures[m]}
            if r is None
            else {
                "rms_px": _round(r.camera.rms_px),
                "cv_rms_px": _round(r.cv_rms_px),
                "cv_rms_common_px": _round(common_cv.get(m)),
                "views": r.counts()["calibration"],
                "fx_px": _round(r.camera.fx_px, 3),
            }
        )
    table["chosen"] = chosen
    best = results[chosen]
    best.notes.insert(0, f"chessboard corners: {chosen} ({why})")
    best.corner_methods = table
    best.config = cfg
    return best


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


def _fit_rejecting_outliers(
    cal: list[ViewRecord], size: tuple[int, int], cfg: IntrinsicsConfig
) -> tuple[Fit, CrossValidation]:
    """Cross-validate, then reject the view with the largest held-out error while it is an
    outlier against the others' (``cfg.outlier_ratio``, ``cfg.outlier_min_px``); rejected
    records get status ``rejected``, reason ``outlier`` and a detail. Returns the fit on every
    view kept and its cross-validation; sets ``error_px`` and ``cv_error_px`` of the views
    kept (``cal`` is updated in place)."""
    flags = _DIST_FLAGS[cfg.distortion_model]
    views = list(cal)
    fit = fit_views([r.detection for r in views], size, flags)  # type: ignore[misc]
    while True:
        cv = cross_validate([r.detection for r in views], size, flags, cfg.cv_folds)  # type: ignore[misc]
        for rec, err in zip(views, cv.error_px, strict=True):
            rec.cv_error_px = float(err)
        if cfg.outlier_ratio <= 0 or len(views) <= MIN_VIEWS:
            break
        worst = int(np.argmax(cv.error_px))
        others = float(np.median(np.delete(cv.error_px, worst)))
        err = float(cv.error_px[worst])
        if err <= cfg.outlier_min_px or err <= cfg.outlier_ratio * others:
            break
        rec = views.pop(worst)
        rec.status, rec.reason, rec.error_px = "rejected", "outlier", None
        new_fit = fit_views([r.detection for r in views], size, flags)  # type: ignore[misc]
        rec.detail = (
            f"held-out error {err:.2f} px, {err / max(others, 1e-12):.1f}x the other views' "
            f"median {others:.2f} px; without it fx {fit.K[0, 0]:.1f} -> "
            f"{new_fit.K[0, 0]:.1f} px, RMS {fit.rms_px:.3f} -> {new_fit.rms_px:.3f} px"
        )
        fit = new_fit
    for rec, err in zip(views, fit.per_view_px, strict=True):
        rec.error_px = float(err)
    cal[:] = views
    return fit, cv
