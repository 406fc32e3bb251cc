"""Stereo calibration from pairs of views of a chessboard or ChArUco board (``calibration
stereo``).

Pipeline: read pairs (two image folders paired by file stem, two videos paired by frame index,
or one ROS bag's two image topics paired by header stamp) -> find the pattern in each view
(:class:`calibration.patterns.PatternDetector`) -> keep the pairs where both views show it
(ChArUco: the corners both see) -> intrinsics fixed from each camera's file
(``cv2.CALIB_FIX_INTRINSIC``) or fitted: ``cv2.calibrateCamera`` per camera on every view of it
that shows the board, then refined jointly (``CALIB_USE_INTRINSIC_GUESS``) -> ``cv2.
stereoCalibrate``, rejecting the worst pair while its error is far above the other pairs'
median -> rectification (``cv2.stereoRectify``) -> per-pair epipolar error -> stereo file, camera
files, ROS camera_info pair, Kalibr camchain, JSON report and a per-pair error plot.

Frames and units: ``T_right_left`` maps points of the left ``cam_cv`` frame into the right one
(metres, the board's square size sets the scale); see :mod:`calibration.stereo_rig`.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import sys
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from uwdock.calibration.camera import CameraModel, camera_file_bytes, load_camera, twin_paths
from uwdock.calibration.intrinsics import MIN_VIEWS, IntrinsicsConfig
from uwdock.calibration.patterns import Detection, PatternDetector, blur_px
from uwdock.calibration.stereo_config import StereoConfig
from uwdock.calibration.stereo_formats import (
    kalibr_stereo_camchain_yaml,
    ros_stereo_camera_info_yaml,
)
from uwdock.calibration.stereo_inputs import View, stereo_pairs
from uwdock.calibration.stereo_rig import StereoRig, stereo_file_bytes
from uwdock.dockcore.config import to_dict, validated
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files
from uwdock.dockcore.provenance import provenance

__all__ = [
    "PairRecord",
    "StereoConfig",
    "StereoResult",
    "calibrate_stereo",
    "stereo_output_paths",
    "write_stereo_outputs",
]

#: OpenCV calibration flags of each distortion model (``IntrinsicsConfig.distortion_model``).
_DIST_FLAGS = {
    "k1k2": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
    "k1k2k3": cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "k1k2p1p2k3": 0,
    "rational": cv2.CALIB_RATIONAL_MODEL,
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass
class PairRecord:
    """What happened to one pair of views.

    Attributes:
        name: file stem (folders), ``frame_<index>`` (videos) or ``msg_<left index>`` (bag).
        status: ``used`` or ``rejected``.
        reason: why a pair was rejected (``unreadable``, ``size_mismatch``, ``no_pattern``,
            ``blurred``, ``too_few_common``, ``outlier``), else None.
        detail: which view failed, or for an outlier its error against the others' median.
        n_corners: corners both views see (0 unless both found the pattern).
        error_px: RMS reprojection error over both views of the stereo fit (px), for used
            pairs and outliers.
        epipolar_px: RMS symmetric distance of each undistorted corner to its epipolar line in
            the other view (px), from the final ``T_right_left``.
        rectified_dy_px: RMS vertical disparity of the corners after rectification (px; 0 for
            a perfect calibration).
    """

    name: str
    status: str = "rejected"
    reason: str | None = None
    detail: str | None = None
    n_corners: int = 0
    error_px: float | None = None
    epipolar_px: float | None = None
    rectified_dy_px: float | None = None
    left: Detection | None = field(default=None, repr=False)
    right: Detection | None = field(default=None, repr=False)
    object_m: np.ndarray | None = field(default=None, repr=False)
    image_left_px: np.ndarray | None = field(default=None, repr=False)
    image_right_px: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no arrays)."""
        return {
            "name": self.name,
            "status": self.status,
            "reason": self.reason,
            "detail": self.detail,
            "n_corners": self.n_corners,
            "error_px": _round(self.error_px),
            "epipolar_px": _round(self.epipolar_px),
            "rectified_dy_px": _round(self.rectified_dy_px),
        }


@dataclass
class StereoResult:
    """Outcome of :func:`calibrate_stereo`.

    Attributes:
        rig: cameras, ``T_right_left``, rectification; ``rig.rms_px`` is the stereo fit's RMS
            reprojection error over the used pairs (px).
        pairs: one record per pair read, in input order.
        config: the configuration used.
        sources: the inputs (``left``, ``right``, ``left_topic``, ``right_topic``,
            ``left_camera``, ``right_camera``), as given.
        intrinsics_fitted: True when the intrinsics were fitted here, False when they came
            fixed from the camera files.
        per_camera: per camera (``left``, ``right``): views with the pattern and, when fitted,
            the single-camera ``calibrateCamera`` RMS before the joint refinement (px).
        epipolar_rms_px: RMS of the per-corner epipolar distances over the used pairs (px).
        rectified_dy_rms_px: RMS vertical disparity after rectification, used pairs (px).
        rectification_roi: valid pixel rectangles (x, y, w, h) of the rectified left and right
            images.
        notes: one-line remarks for the user.
        camera_T_body_cam: ``T_body_cam`` of each input camera file (fixed intrinsics), or None.
    """

    rig: StereoRig
    pairs: list[PairRecord]
    config: StereoConfig
    sources: dict[str, str | None]
    intrinsics_fitted: bool
    per_camera: dict[str, dict[str, Any]]
    epipolar_rms_px: float
    rectified_dy_rms_px: float
    rectification_roi: tuple[list[int], list[int]]
    notes: list[str] = field(default_factory=list)
    camera_T_body_cam: dict[str, np.ndarray | None] = field(default_factory=dict)

    def counts(self) -> dict[str, Any]:
        """Pairs read / used / rejected (by reason)."""
        reasons = Counter(p.reason for p in self.pairs if p.status == "rejected")
        return {
            "pairs": len(self.pairs),
            "used": sum(p.status == "used" for p in self.pairs),
            "rejected": sum(reasons.values()),
            "rejected_by_reason": dict(sorted(reasons.items())),
        }

    def report(self) -> dict[str, Any]:
        """The JSON report written beside the stereo file."""
        rig = self.rig
        T = rig.T_right_left
        centre = -T[:3, :3].T @ T[:3, 3]

        def cam(c: CameraModel, side: str) -> dict[str, Any]:
            return {
                "name": c.name,
                "camera_matrix": c.K.tolist(),
                "distortion_coefficients": list(c.dist),
                **{
                    k: _round(v) if isinstance(v, float) else v
                    for k, v in self.per_camera[side].items()
                },
            }

        return {
            "sources": dict(self.sources),
            "image_size_px": list(rig.image_size),
            "intrinsics": "fitted jointly" if self.intrinsics_fitted else "fixed (camera files)",
            "pairs": self.counts(),
            "T_right_left": T.tolist(),
            "T_right_left_meaning": "maps points of the left cam_cv frame into the right one (m)",
            "baseline_m": _round(rig.baseline_m, 9),
            "rotation_deg": _round(rig.rotation_deg),
            "right_camera_centre_in_left_m": [_round(float(v), 9) for v in centre],
            "rms_px": _round(rig.rms_px),
            "epipolar_rms_px": _round(self.epipolar_rms_px),
            "rectified_dy_rms_px": _round(self.rectified_dy_rms_px),
            "left_camera": cam(rig.left, "left"),
            "right_camera": cam(rig.right, "right"),
            "rectification": {
                "R1": rig.R1.tolist(),
                "R2": rig.R2.tolist(),
                "P1": rig.P1.tolist(),
                "P2": rig.P2.tolist(),
                "Q": rig.Q.tolist(),
                "alpha": rig.rectification_alpha,
                "flags": "CALIB_ZERO_DISPARITY",
                "roi_left_px": self.rectification_roi[0],
                "roi_right_px": self.rectification_roi[1],
                "maps": {
                    "function": "cv2.initUndistortRectifyMap(K, D, R, P, size, cv2.CV_32FC1)",
                    "size_px": list(rig.image_size),
                    "left": "K, D of the left camera with R1, P1",
                    "right": "K, D of the right camera with R2, P2",
                },
            },
            "per_pair": [p.as_dict() for p in self.pairs],
            "notes": list(self.notes),
            "config": to_dict(self.config),
        }


def _round(x: float | None, digits: int = 6) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


# --------------------------------------------------------------------------- detection


def _look(
    gray: View, detector: PatternDetector, cfg: IntrinsicsConfig
) -> tuple[Detection | None, str | None]:
    """(detection, None) of a usable view, else (None or the detection, reason)."""
    if gray is None:
        return None, "unreadable"
    det = detector.detect(gray)
    if det is None:
        return None, "no_pattern"
    if blur_px(gray, det) > cfg.blur_threshold_px:
        return det, "blurred"
    return det, None


def _inspect(
    pairs: Iterator[tuple[str, View, View]],
    total: int,
    cfg: StereoConfig,
    detector: PatternDetector,
    cameras: tuple[CameraModel | None, CameraModel | None],
    progress: bool | None,
) -> tuple[list[PairRecord], tuple[int, int]]:
    """Detect in every pair; check the image sizes against each other and the camera files."""
    records: list[PairRecord] = []
    size: tuple[int, int] | None = None
    show = sys.stderr.isatty() if progress is None else bool(progress)
    bar = tqdm(pairs, total=total, desc="pairs", unit="pair", disable=not show)
    for name, gl, gr in bar:
        rec = PairRecord(name)
        records.append(rec)
        sizes = [None if g is None else (g.shape[1], g.shape[0]) for g in (gl, gr)]
        if size is None and sizes[0] is not None and sizes[1] is not None:
            if sizes[0] != sizes[1]:
                raise DockError(
                    f"the left images are {sizes[0][0]}x{sizes[0][1]} px and the right ones "
                    f"{sizes[1][0]}x{sizes[1][1]} px (pair {name}): stereo calibration needs "
                    "one image size"
                )
            size = sizes[0]
            for side, cam in zip(("left", "right"), cameras, strict=True):
                if cam is not None and (cam.width_px, cam.height_px) != size:
                    raise DockError(
                        f"the {side} camera file is {cam.width_px}x{cam.height_px} px but the "
                        f"{side} images are {size[0]}x{size[1]} px"
                    )
        if size is not None and any(s is not None and s != size for s in sizes):
            rec.reason, rec.detail = "size_mismatch", f"not {size[0]}x{size[1]} px"
            continue
        (dl, why_l), (dr, why_r) = (_look(g, detector, cfg.intrinsics) for g in (gl, gr))
        rec.left = dl if why_l is None else None  # a camera's own fit takes its good views
        rec.right = dr if why_r is None else None
        if why_l or why_r:
            for reason in ("unreadable", "no_pattern", "blurred"):
                sides = [s for s, w in (("left", why_l), ("right", why_r)) if w == reason]
                if sides:
                    rec.reason, rec.detail = reason, " and ".join(sides)
                    break
            continue
        assert dl is not None and dr is not None
        if cfg.intrinsics.pattern == "chessboard" and _flipped(dl, dr):
            # a chessboard's corner order is defined up to a half turn: the two views of one
            # pair (cameras turned little about their axes) must agree on it
            dr = Detection(dr.image_px[::-1].copy(), dr.object_m, dr.ids)
            rec.right = dr
            rec.detail = "right corners reordered (board found half a turn apart)"
        common, il, ir = np.intersect1d(dl.ids, dr.ids, assume_unique=True, return_indices=True)
        need = max(6, cfg.intrinsics.min_corners) if cfg.intrinsics.pattern == "charuco" else 1
        if common.size < need:
            rec.reason = "too_few_common"
            rec.detail = f"{common.size} corners seen by both views, need {need}"
            continue
        rec.status, rec.n_corners = "used", int(common.size)
        rec.object_m = dl.object_m[il].astype(np.float64)
        rec.image_left_px = dl.image_px[il].astype(np.float64)
        rec.image_right_px = dr.image_px[ir].astype(np.float64)
    bar.close()
    if size is None:
        raise DockError(f"no pair of the {len(records)} read has two decodable images")
    return records, size


def _flipped(dl: Detection, dr: Detection) -> bool:
    """Whether two chessboard detections of one board list its corners half a turn apart (the
    first-to-last corner directions point opposite ways)."""
    a = dl.image_px[-1] - dl.image_px[0]
    b = dr.image_px[-1] - dr.image_px[0]
    return float(np.dot(a, b)) < 0.0


# --------------------------------------------------------------------------- calibration


def _fit_camera(
    dets: list[Detection], size: tuple[int, int], cfg: IntrinsicsConfig, side: str
) -> tuple[float, np.ndarray, np.ndarray]:
    """``cv2.calibrateCamera`` of one camera on its views that show the board."""
    if len(dets) < MIN_VIEWS:
        raise DockError(
            f"the {side} camera shows the board in {len(dets)} views, need at least "
            f"{MIN_VIEWS} to fit its intrinsics (or give --{side}-camera)"
        )
    obj = [d.object_m.reshape(-1, 1, 3).astype(np.float32) for d in dets]
    img = [d.image_px.reshape(-1, 1, 2).astype(np.float32) for d in dets]
    try:
        rms, K, dist, _, _ = cv2.calibrateCamera(
            obj, img, size, None, None, flags=_DIST_FLAGS[cfg.distortion_model]
        )
    except cv2.error as exc:
        raise DockError(f"{side} camera calibration failed: {_cv_text(exc)}") from None
    return float(rms), K, dist.reshape(-1)


def _cv_text(exc: cv2.error) -> str:
    return " ".join(str(exc).split()).split(" error: ", 1)[-1]


def _stereo_fit(
    used: list[PairRecord],
    size: tuple[int, int],
    cams: list[tuple[np.ndarray, np.ndarray]],
    flags: int,
):
    """``cv2.stereoCalibrateExtended``: (rms, K1, D1, K2, D2, R, T, per-pair RMS)."""
    obj = [p.object_m.reshape(-1, 1, 3).astype(np.float32) for p in used]  # type: ignore[union-attr]
    il = [p.image_left_px.reshape(-1, 1, 2).astype(np.float32) for p in used]  # type: ignore[union-attr]
    ir = [p.image_right_px.reshape(-1, 1, 2).astype(np.float32) for p in used]  # type: ignore[union-attr]
    (K1, D1), (K2, D2) = cams
    try:
        rms, K1, D1, K2, D2, R, T, _, _, _, _, per_view = cv2.stereoCalibrateExtended(
            obj, il, ir, K1.copy(), D1.copy(), K2.copy(), D2.copy(), size, None, None,
            flags=flags, criteria=_CRITERIA,
        )  # fmt: skip
    except cv2.error as exc:
        raise DockError(f"stereo calibration failed: {_cv_text(exc)}") from None
    per_view = np.asarray(per_view, dtype=np.float64).reshape(-1, 2)
    pair_rms = np.sqrt(np.mean(per_view**2, axis=1))
    return float(rms), K1, D1.reshape(-1), K2, D2.reshape(-1), R, T.reshape(3), pair_rms


def _fit_rejecting_outliers(used, size, cams, flags, cfg: StereoConfig):
    """Fit; reject the worst pair while it is an outlier (``cfg.outlier_ratio``)."""
    pending: tuple[PairRecord, str, float, float] | None = None
    while True:
        fit = _stereo_fit(used, size, cams, flags)
        rms, T, pair_rms = fit[0], fit[6], fit[7]
        for rec, err in zip(used, pair_rms, strict=True):
            rec.error_px = float(err)
        if pending is not None:
            rec_out, text, base_before, rms_before = pending
            rec_out.detail = (
                f"{text}; without it baseline {base_before:.4f} -> {np.linalg.norm(T):.4f} m, "
                f"RMS {rms_before:.3f} -> {rms:.3f} px"
            )
            pending = None
        if cfg.outlier_ratio <= 0 or len(used) <= MIN_VIEWS:
            return fit
        worst = int(np.argmax(pair_rms))
        others = float(np.median(np.delete(pair_rms, worst)))
        err = float(pair_rms[worst])
        if err <= cfg.outlier_min_px or err <= cfg.outlier_ratio * others:
            return fit
        rec = used.pop(worst)
        rec.status, rec.reason = "rejected", "outlier"
        text = (
            f"{err:.2f} px, {err / max(others, 1e-12):.1f}x the other pairs' median {others:.2f} px"
        )
        rec.detail = text
        pending = (rec, text, float(np.linalg.norm(T)), rms)


def _pair_errors(rec: PairRecord, rig: StereoRig) -> None:
    """Epipolar distance (undistorted px, symmetric) and rectified vertical disparity."""
    pl = rec.image_left_px.reshape(-1, 1, 2)  # type: ignore[union-attr]
    pr = rec.image_right_px.reshape(-1, 1, 2)  # type: ignore[union-attr]
    L, Rt = rig.left, rig.right
    ul = cv2.undistortPoints(pl, L.K, L.dist_coeffs, P=L.K, criteria=_CRITERIA).reshape(-1, 2)
    ur = cv2.undistortPoints(pr, Rt.K, Rt.dist_coeffs, P=Rt.K, criteria=_CRITERIA).reshape(-1, 2)
    xl = np.column_stack([ul, np.ones(len(ul))])
    xr = np.column_stack([ur, np.ones(len(ur))])
    F = rig.F
    lines_r = xl @ F.T  # epipolar lines in the right image
    lines_l = xr @ F  # in the left image
    alg = np.sum(xr * lines_r, axis=1)
    d_r = alg / np.hypot(lines_r[:, 0], lines_r[:, 1])
    d_l = alg / np.hypot(lines_l[:, 0], lines_l[:, 1])
    rec.epipolar_px = float(np.sqrt(np.mean((d_r**2 + d_l**2) / 2.0)))
    yl = cv2.undistortPoints(pl, L.K, L.dist_coeffs, R=rig.R1, P=rig.P1, criteria=_CRITERIA)
    yr = cv2.undistortPoints(pr, Rt.K, Rt.dist_coeffs, R=rig.R2, P=rig.P2, criteria=_CRITERIA)
    axis = 1 if abs(rig.P2[0, 3]) >= abs(rig.P2[1, 3]) else 0  # vertical rig: x disparity
    dy = yl.reshape(-1, 2)[:, axis] - yr.reshape(-1, 2)[:, axis]
    rec.rectified_dy_px = float(np.sqrt(np.mean(dy**2)))


def calibrate_stereo(
    left: str | os.PathLike[str],
    right: str | os.PathLike[str] | None = None,
    cfg: StereoConfig | None = None,
    left_camera: str | os.PathLike[str] | None = None,
    right_camera: str | os.PathLike[str] | None = None,
    left_topic: str | None = None,
    right_topic: str | None = None,
    progress: bool | None = False,
) -> StereoResult:
    """Calibrate a stereo pair from views of one planar target seen by both cameras.

    Args:
        left: the left camera's image folder or video, or a ROS bag holding both cameras.
        right: the right camera's image folder (paired by file stem) or video (paired by frame
            index); None for a bag.
        cfg: configuration (default: 9 x 6 inner-corner chessboard, 25 mm squares).
        left_camera: the left camera's file: its intrinsics are kept fixed. Give both camera
            files or neither (then both cameras' intrinsics are fitted).
        right_camera: the right camera's file.
        left_topic: bag: the left camera's image topic.
        right_topic: bag: the right camera's image topic (paired by header stamp within
            ``cfg.pair_tolerance_ms``).
        progress: tqdm progress bar on stderr: True, False or None (only on a terminal).

    Returns:
        The rig, one record per pair, the epipolar errors and notes.

    Raises:
        DockError: one line: missing or unpaired inputs, different image sizes (between the
            cameras, or against a camera file), fewer than ``MIN_VIEWS`` usable pairs, or a
            fit OpenCV rejects.
    """
    cfg = validated(cfg or StereoConfig())
    files, T_body = _camera_files(left_camera, right_camera)
    notes: list[str] = []
    detector = cfg.intrinsics.detector()
    total, pairs = stereo_pairs(
        Path(left), None if right is None else Path(right), (left_topic, right_topic), cfg, notes
    )
    records, size = _inspect(pairs, total, cfg, detector, (files[0], files[1]), progress)
    used = [r for r in records if r.status == "used"]
    _require_pairs(used, records, detector)
    rig, per_camera = _fit_rig(records, used, size, cfg, files, (left_topic, right_topic))
    epipolar_rms_px, rectified_dy_rms_px = _rig_errors(records, rig)
    notes += _notes(rig, records, detector)
    sources = {
        "left": str(left),
        "right": None if right is None else str(right),
        "left_topic": left_topic,
        "right_topic": right_topic,
        "left_camera": None if left_camera is None else str(left_camera),
        "right_camera": None if right_camera is None else str(right_camera),
    }
    roi = ([int(v) for v in rig.roi[0]], [int(v) for v in rig.roi[1]]) if rig.roi else ([], [])
    return StereoResult(rig, records, cfg, sources, files[0] is None, per_camera,
                        epipolar_rms_px, rectified_dy_rms_px, roi, notes, T_body)  # fmt: skip


def _camera_files(
    left_camera: str | os.PathLike[str] | None, right_camera: str | os.PathLike[str] | None
) -> tuple[list[CameraModel | None], dict[str, np.ndarray | None]]:
    """The two fixed-intrinsics camera files (both or neither) and their ``T_body_cam``."""
    if (left_camera is None) != (right_camera is None):
        raise DockError(
            "give both --left-camera and --right-camera (intrinsics fixed), or neither "
            "(intrinsics fitted)"
        )
    files: list[CameraModel | None] = [None, None]
    T_body: dict[str, np.ndarray | None] = {}
    if left_camera is not None and right_camera is not None:
        for i, (side, path) in enumerate((("left", left_camera), ("right", right_camera))):
            files[i], T_body[side] = load_camera(path)
    return files, T_body


def _require_pairs(
    used: list[PairRecord], records: list[PairRecord], detector: PatternDetector
) -> None:
    """Refuse fewer than ``MIN_VIEWS`` usable pairs, with the rejections counted by reason."""
    if len(used) >= MIN_VIEWS:
        return
    reasons = Counter(
        f"{r.reason} ({r.detail})" if r.detail and r.reason != "too_few_common" else r.reason
        for r in records
        if r.status == "rejected"
    )
    detail = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())) or "none"
    raise DockError(
        f"only {len(used)} usable pairs of {len(records)}, need at least {MIN_VIEWS} "
        f"(rejected: {detail})" + "".join(f"; {n}" for n in detector.notes)
    )


def _fit_rig(
    records: list[PairRecord],
    used: list[PairRecord],
    size: tuple[int, int],
    cfg: StereoConfig,
    files: list[CameraModel | None],
    topics: tuple[str | None, str | None],
) -> tuple[StereoRig, dict[str, dict[str, Any]]]:
    """The stereo fit (outlier pairs rejected from ``used``) as a rectified rig, and per camera
    its views with the pattern and single-camera RMS (fitted intrinsics)."""
    per_camera: dict[str, dict[str, Any]] = {
        "left": {"views_with_pattern": sum(r.left is not None for r in records)},
        "right": {"views_with_pattern": sum(r.right is not None for r in records)},
    }
    cams, flags = _start_intrinsics(records, size, cfg, files, per_camera)
    rms, K1, D1, K2, D2, R, T, _ = _fit_rejecting_outliers(used, size, cams, flags, cfg)
    models = _camera_models(((K1, D1), (K2, D2)), files, size, cfg)
    Tm = np.eye(4)
    Tm[:3, :3], Tm[:3, 3] = R, T
    try:
        rig = StereoRig.from_cameras(
            models[0], models[1], Tm, cfg.rectify_alpha, rms_px=rms,
            left_topic=topics[0], right_topic=topics[1],
        )  # fmt: skip
    except ValueError as exc:
        raise DockError(f"stereo calibration: {exc}") from None
    return rig, per_camera


def _start_intrinsics(
    records: list[PairRecord],
    size: tuple[int, int],
    cfg: StereoConfig,
    files: list[CameraModel | None],
    per_camera: dict[str, dict[str, Any]],
) -> tuple[list[tuple[np.ndarray, np.ndarray]], int]:
    """The stereo fit's starting (K, D) per camera and its flags: fixed from the camera files,
    or fitted per camera (its RMS noted in ``per_camera``) and refined jointly."""
    if files[0] is not None:
        return [(c.K, c.dist_coeffs) for c in files if c is not None], cv2.CALIB_FIX_INTRINSIC
    cams = []
    for side in ("left", "right"):
        dets = [getattr(r, side) for r in records if getattr(r, side) is not None]
        rms, K, D = _fit_camera(dets, size, cfg.intrinsics, side)
        per_camera[side]["single_camera_rms_px"] = rms
        cams.append((K, D))
    return cams, cv2.CALIB_USE_INTRINSIC_GUESS | _DIST_FLAGS[cfg.intrinsics.distortion_model]


def _camera_models(
    fits: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    files: list[CameraModel | None],
    size: tuple[int, int],
    cfg: StereoConfig,
) -> list[CameraModel]:
    """The left and right cameras: the given files, else models of the fitted (K, D)."""
    n_dist = 8 if cfg.intrinsics.distortion_model == "rational" else 5
    models = []
    for side, (K, D), given in zip(("left", "right"), fits, files, strict=True):
        if given is not None:
            models.append(given)
            continue
        models.append(
            CameraModel(
                size[0], size[1], float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                tuple(float(d) for d in D[:n_dist]), name=side,
            )
        )  # fmt: skip
    return models


def _rig_errors(records: list[PairRecord], rig: StereoRig) -> tuple[float, float]:
    """Each pair's errors against the rig; (epipolar, rectified dy) RMS over the used pairs'
    corners (px)."""
    sq_epi, sq_dy, n_pts = 0.0, 0.0, 0
    for rec in records:
        if rec.object_m is not None:
            _pair_errors(rec, rig)
        if rec.status == "used":
            sq_epi += rec.epipolar_px**2 * rec.n_corners  # type: ignore[operator]
            sq_dy += rec.rectified_dy_px**2 * rec.n_corners  # type: ignore[operator]
            n_pts += rec.n_corners
    return math.sqrt(sq_epi / n_pts), math.sqrt(sq_dy / n_pts)


def _notes(rig: StereoRig, records: list[PairRecord], detector: PatternDetector) -> list[str]:
    notes = list(detector.notes)
    for rec in records:
        if rec.reason == "outlier":
            notes.append(f"pair {rec.name} rejected as an outlier: {rec.detail}")
    T = rig.T_right_left
    centre = -T[:3, :3].T @ T[:3, 3]
    if abs(centre[0]) >= abs(centre[1]) and centre[0] < 0:
        notes.append(
            f"warning: the right camera sits {-centre[0]:.3f} m to the LEFT of the left one "
            "(x of its centre in the left frame < 0): are the inputs swapped?"
        )
    if abs(centre[1]) > abs(centre[0]):
        notes.append("the cameras are one above the other: the rectification is vertical")
    return notes


# --------------------------------------------------------------------------- outputs


def _plot_errors(result: StereoResult) -> bytes:
    """Bar chart of per-pair errors: stereo reprojection RMS and epipolar distance (px), as PNG
    bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [p for p in result.pairs if p.error_px is not None or p.epipolar_px is not None]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.3 * len(shown) + 2.0), 3.8), dpi=100)
    x = np.arange(len(shown))
    colours = ["tab:blue" if p.status == "used" else "tab:red" for p in shown]
    ax.bar(x - 0.2, [p.error_px or 0.0 for p in shown], 0.4, color=colours,
           label="reprojection RMS (red: rejected)")  # fmt: skip
    ax.bar(x + 0.2, [p.epipolar_px or 0.0 for p in shown], 0.4, color="tab:orange",
           label="epipolar distance RMS")  # fmt: skip
    rms = result.rig.rms_px or 0.0
    ax.axhline(rms, color="tab:blue", ls="--", lw=1, label=f"stereo RMS {rms:.3f} px")
    ax.set_xticks(x)
    ax.set_xticklabels([p.name for p in shown], rotation=90, fontsize=6)
    ax.set_ylabel("error (px)")
    ax.set_title(
        f"Per-pair error; baseline {result.rig.baseline_m:.4f} m, "
        f"epipolar RMS {result.epipolar_rms_px:.3f} px"
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png")
    finally:
        plt.close(fig)
    return buf.getvalue()


def _camera_file(path: Path, cam: CameraModel, T_fallback: np.ndarray | None) -> dict[Path, bytes]:
    """One camera's file twins; an existing file's ``T_body_cam`` (else ``T_fallback``) kept."""
    T = None
    if path.is_file():
        with contextlib.suppress(DockError):
            T = load_camera(path)[1]
    return camera_file_bytes(path, cam, T if T is not None else T_fallback)


def stereo_output_paths(out: str | os.PathLike[str], write_maps: bool = False) -> list[Path]:
    """Every file :func:`write_stereo_outputs` may write for ``out`` (the camchain only when
    radtan holds the distortion), checked by the command before it calibrates
    (``dockcore.io.check_output_path``)."""
    out = Path(out)
    stem, sib = out.stem, out.with_name
    cam_suffix = out.suffix if out.suffix != ".json" else ".yaml"
    paths = list(twin_paths(out))
    for side in ("left", "right"):
        paths += twin_paths(sib(f"{stem}_{side}{cam_suffix}"))
    for name in ("left_camera_info", "right_camera_info", "camchain"):
        paths.append(sib(f"{stem}_{name}.yaml"))
    if write_maps:
        paths.append(sib(f"{stem}_rectify_maps.npz"))
    return [*paths, sib(f"{stem}_report.json"), sib(f"{stem}_errors.png")]


def write_stereo_outputs(
    result: StereoResult, out: str | os.PathLike[str], write_maps: bool = False
) -> tuple[list[Path], list[str]]:
    """Write everything a stereo calibration produces, as one unit
    (``dockcore.io.atomic_write_files``: every file written and verified before any is renamed,
    so a failure leaves the existing files as they were).

    Beside ``out`` (``<stem>.yaml``): the stereo file twins
    (:func:`calibration.stereo_rig.save_stereo`),
    ``<stem>_left.yaml`` / ``<stem>_right.yaml`` camera files (+ JSON twins; an existing
    file's ``T_body_cam``, else the input camera file's, is kept), ``<stem>_left_camera_info.yaml``
    and ``<stem>_right_camera_info.yaml`` (ROS), ``<stem>_camchain.yaml`` (Kalibr, when radtan
    can hold the distortion), ``<stem>_report.json``, ``<stem>_errors.png`` and, with
    ``write_maps``, ``<stem>_rectify_maps.npz`` (float32 ``left_x``, ``left_y``, ``right_x``,
    ``right_y`` for ``cv2.remap``, (H, W) each).

    Returns:
        (the paths written, notes about outputs not written).
    """
    out = Path(out)
    rig = result.rig
    stem = out.stem
    sib = out.with_name
    files = stereo_file_bytes(out, rig)
    for side, cam in (("left", rig.left), ("right", rig.right)):
        files.update(
            _camera_file(
                sib(f"{stem}_{side}{out.suffix if out.suffix != '.json' else '.yaml'}"),
                cam,
                result.camera_T_body_cam.get(side),
            )
        )
    left_text, right_text = ros_stereo_camera_info_yaml(rig)
    files[sib(f"{stem}_left_camera_info.yaml")] = left_text.encode("utf-8")
    files[sib(f"{stem}_right_camera_info.yaml")] = right_text.encode("utf-8")
    skipped: list[str] = []
    try:
        files[sib(f"{stem}_camchain.yaml")] = kalibr_stereo_camchain_yaml(rig).encode("utf-8")
    except DockError as exc:
        skipped.append(f"Kalibr camchain not written: {exc}")
    maps_path = None
    if write_maps:
        maps_path = sib(f"{stem}_rectify_maps.npz")
        lx, ly, rx, ry = rig.rectify_maps()
        buf = io.BytesIO()
        np.savez_compressed(buf, left_x=lx, left_y=ly, right_x=rx, right_y=ry)
        files[maps_path] = buf.getvalue()
    report = result.report()
    report["rectification"]["maps"]["file"] = None if maps_path is None else maps_path.name
    report["notes"] = report["notes"] + skipped
    report["provenance"] = provenance()
    report_path, plot_path = sib(f"{stem}_report.json"), sib(f"{stem}_errors.png")
    files[report_path] = (json.dumps(report, indent=2, sort_keys=False) + "\n").encode("utf-8")
    files[plot_path] = _plot_errors(result)
    return atomic_write_files(files), skipped
