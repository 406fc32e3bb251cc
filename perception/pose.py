"""Marker and docking-station pose from detected corners (PnP).

Frames (see :mod:`calibration.frames`): ``cam`` is the OpenCV camera (x right, y down,
z forward); ``marker`` is the OpenCV ArUco marker frame (corners TL, TR, BR, BL at
(-s/2, s/2, 0), (s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0), z out of the face); ``ds`` is
the docking-station frame the board's object points are given in. Poses are 4x4 float64
``T_a_b`` (p_a = T_a_b @ p_b), distances in metres, pixels as OpenCV (integer = pixel centre).

* :func:`solve_marker`: one square marker with ``SOLVEPNP_IPPE_SQUARE``, keeping both IPPE
  solutions (a lone distant marker is ambiguous: its pose "flips"); :func:`choose_candidate`
  resolves the ambiguity with a prior or with the board's pose.
* :func:`solve_board`: all visible markers of the docking station jointly (SQPnP or ITERATIVE,
  then Levenberg-Marquardt), with outlier-marker rejection and a pose covariance. Never EPnP:
  it is unreliable on four coplanar points.

Intrinsics are plain arrays: ``K`` (3, 3) and ``dist`` (OpenCV distortion vector, 4/5/8/12/14
values, or None for none); a ``CameraModel`` gives them as ``.K`` and ``.dist_coeffs``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.frames import (
    R_from_rpy,
    check_T,
    inv_T,
    make_T,
    rotation_angle_deg,
    transform_points,
)
from uwdock.dockcore.config import validated
from uwdock.dockcore.domains import Ge, Interval, Positive
from uwdock.dockcore.errors import DockError
from uwdock.markers.config import MAX_MARKER_ID
from uwdock.markers.markerset import corners_marker_m

__all__ = [
    "BoardPose",
    "BoardPoseConfig",
    "LevelBoardPose",
    "MarkerPose",
    "PoseCandidate",
    "T_body_ds",
    "choose_candidate",
    "marker_frame_from_corners",
    "refine_level_board",
    "reprojection_errors_px",
    "solve_board",
    "solve_marker",
]

_PNP_FLAGS = {"sqpnp": cv2.SOLVEPNP_SQPNP, "iterative": cv2.SOLVEPNP_ITERATIVE}


# --------------------------------------------------------------------------- helpers


def _intrinsics(K: ArrayLike, dist: ArrayLike | None) -> tuple[np.ndarray, np.ndarray]:
    """Validated (3, 3) float64 K and (N,) float64 distortion (N = 0 allowed: no distortion)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DockError(f"K must be a finite (3, 3) camera matrix with fx, fy > 0, got {K}")
    d = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
    if d.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
        raise DockError(f"dist must hold 0, 4, 5, 8, 12 or 14 finite values, got {d.size}")
    return K, d


def _points(arr: ArrayLike, shape: tuple[int, int], name: str) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise DockError(f"{name}: expected a finite {shape} array, got shape {a.shape}")
    return a


def _T_from_rt(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def _rt_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy()


def reprojection_errors_px(
    T_cam_obj: ArrayLike, obj_pts: ArrayLike, img_pts: ArrayLike, K: ArrayLike, dist: ArrayLike
) -> np.ndarray:
    """Per-point Euclidean reprojection error.

    Args:
        T_cam_obj: (4, 4) object frame in the camera frame.
        obj_pts: (N, 3) points in the object frame (m).
        img_pts: (N, 2) observed pixels.
        K, dist: intrinsics.

    Returns:
        (N,) float64 pixel distances between projected and observed points.
    """
    K, dist = _intrinsics(K, dist)
    rvec, tvec = _rt_from_T(np.asarray(T_cam_obj, np.float64))
    proj = cv2.projectPoints(np.asarray(obj_pts, np.float64), rvec, tvec, K, dist)[0].reshape(-1, 2)
    return np.linalg.norm(proj - np.asarray(img_pts, np.float64).reshape(-1, 2), axis=1)


def _rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(errors)))) if errors.size else 0.0


def T_body_ds(T_body_cam: ArrayLike, T_cam_ds: ArrayLike) -> np.ndarray:
    """Docking station in the vehicle body frame: ``T_body_cam @ T_cam_ds`` (both validated)."""
    return check_T(T_body_cam, "T_body_cam") @ check_T(T_cam_ds, "T_cam_ds")


# --------------------------------------------------------------------------- single marker


@dataclass(frozen=True)
class PoseCandidate:
    """One PnP solution.

    Attributes:
        T_cam_marker: (4, 4) marker (or board) frame in the camera frame.
        reprojection_rms_px: RMS over the corners of the pixel reprojection error.
    """

    T_cam_marker: np.ndarray
    reprojection_rms_px: float


@dataclass(frozen=True)
class MarkerPose:
    """Both IPPE solutions for one square marker.

    Attributes:
        candidates: solutions sorted by reprojection error, best first (1 or 2).
        marker_id: the marker's ID when known, else None.
        side_m: marker side used (m).
    """

    candidates: tuple[PoseCandidate, ...]
    marker_id: int | None = None
    side_m: float = 0.0

    @property
    def best(self) -> PoseCandidate:
        """The candidate with the lowest reprojection error."""
        return self.candidates[0]

    @property
    def T_cam_marker(self) -> np.ndarray:
        """(4, 4) pose of the best candidate."""
        return self.candidates[0].T_cam_marker

    @property
    def ambiguity_ratio(self) -> float:
        """Best / second-best reprojection error in [0, 1]: near 0 the choice is clear, near 1
        both solutions explain the corners equally well (a flip is likely). 1 when both errors
        are 0, 0 when there is a single candidate."""
        if len(self.candidates) < 2:
            return 0.0
        e1, e2 = self.candidates[0].reprojection_rms_px, self.candidates[1].reprojection_rms_px
        return 1.0 if e2 <= 0.0 else float(min(e1 / e2, 1.0))


def solve_marker(
    corners_px: ArrayLike,
    marker_size_m: float,
    K: ArrayLike,
    dist: ArrayLike | None,
    marker_id: int | None = None,
) -> MarkerPose:
    """Pose of one square marker with ``cv2.SOLVEPNP_IPPE_SQUARE``, both solutions kept.

    Args:
        corners_px: (4, 2) pixel corners TL, TR, BR, BL (as in a detector ``Detection``).
        marker_size_m: marker side (outer edge of the border), metres, > 0.
        K: (3, 3) camera matrix; dist: distortion coefficients or None.
        marker_id: stored in the result.

    Returns:
        A :class:`MarkerPose`; candidates in front of the camera only, best first.

    Raises:
        DockError: bad shapes, a non-positive size, or no solution in front of the camera.
    """
    K, dist = _intrinsics(K, dist)
    img = _points(corners_px, (4, 2), "corners_px")
    if not (marker_size_m > 0 and math.isfinite(marker_size_m)):
        raise DockError(f"marker_size_m must be > 0, got {marker_size_m}")
    obj = corners_marker_m(marker_size_m)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error as exc:
        raise DockError(f"IPPE_SQUARE failed on these corners: {exc.err}") from None
    cands = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n], strict=True):
        T = _T_from_rt(rvec, tvec)
        if np.all(transform_points(T, obj)[:, 2] > 0):
            cands.append(PoseCandidate(T, _rms(reprojection_errors_px(T, obj, img, K, dist))))
    if not cands:
        raise DockError("no marker pose in front of the camera fits these corners")
    cands.sort(key=lambda c: c.reprojection_rms_px)
    return MarkerPose(tuple(cands), marker_id, float(marker_size_m))


def choose_candidate(pose: MarkerPose, T_cam_marker_ref: ArrayLike) -> PoseCandidate:
    """The candidate whose rotation is closest to a reference pose.

    Use a prediction from the previous frame (temporal consistency) or the board's estimate
    ``T_cam_ds @ T_ds_marker`` (board agreement) to undo a flip.

    Args:
        pose: both solutions of :func:`solve_marker`.
        T_cam_marker_ref: (4, 4) reference pose of the same marker.

    Returns:
        The candidate with the smallest geodesic rotation angle to the reference.
    """
    ref = np.asarray(T_cam_marker_ref, np.float64)
    return min(pose.candidates, key=lambda c: rotation_angle_deg(c.T_cam_marker, ref))


def marker_frame_from_corners(corners_obj_m: ArrayLike) -> tuple[np.ndarray, float]:
    """Marker frame and side from its four corners given in another frame (e.g. the DS).

    Args:
        corners_obj_m: (4, 3) corners TL, TR, BR, BL in frame ``obj`` (m).

    Returns:
        ``(T_obj_marker, side_m)``: the (4, 4) ArUco marker frame in ``obj`` (nearest rotation
        to the corners' axes) and the mean edge length.

    Raises:
        DockError: the corners are not (close to) a square (edges within 2 %, planar).
    """
    c = _points(corners_obj_m, (4, 3), "corners_obj_m")
    edges = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)
    side = float(edges.mean())
    x = 0.5 * ((c[1] - c[0]) + (c[2] - c[3]))
    y = 0.5 * ((c[0] - c[3]) + (c[1] - c[2]))
    M = np.stack([x / side, y / side, np.cross(x, y) / side**2], axis=1)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    T = make_T(R, c.mean(axis=0))
    fit = transform_points(T, corners_marker_m(side))
    if (
        side <= 0
        or np.max(np.abs(edges - side)) > 0.02 * side
        or np.max(np.abs(fit - c)) > 0.02 * side
    ):
        raise DockError(f"marker corners are not a square (edges {np.round(edges, 4).tolist()} m)")
    return T, side


# --------------------------------------------------------------------------- board


@dataclass(frozen=True)
class BoardPoseConfig:
    """Docking-station (marker board) pose estimation.

    Attributes:
        method: initial solver, "sqpnp" (global, any point layout) or "iterative" (OpenCV's
            DLT/homography + LM). Never EPnP.
        lm_refine: refine the initial solution with ``cv2.solvePnPRefineLM``.
        outlier_threshold_px: outlier rejection runs while some marker's RMS corner
            reprojection error exceeds this (px). The board is then re-solved without each
            marker in turn; the marker whose removal leaves the most consistent board is
            dropped if, against that pose, its own error exceeds this threshold (> 0)...
        outlier_ratio: ...and this many times the RMS error of the remaining markers (-, >= 1:
            a marker no worse than the rest is never the outlier).
            (Leave-one-out, because a joint least-squares fit spreads one bad marker's error
            over the good ones: a 20 px shift shows as ~13 px on it and ~5 px on the rest.)
        min_markers: fewest markers to return a pose (1 uses IPPE_SQUARE on a lone marker;
            1 ... 2320, the largest dictionary).
        min_markers_for_rejection: outlier rejection runs only with at least this many markers
            (>= 3: with two, neither can be blamed; default 4, because three markers minus one
            leave 8 points for 6 unknowns, which fit anything and reject clean markers at 1 px
            corner noise).
        max_rms_px: no pose (None) when the final RMS reprojection error exceeds this (px, > 0).
        sigma_floor_px: lower bound on the corner noise used for the covariance (px, 0 ... 100),
            so that noise-free input does not claim a zero covariance.
    """

    method: str = "sqpnp"
    lm_refine: bool = True
    outlier_threshold_px: Positive = 2.0
    outlier_ratio: Annotated[float, Ge(1.0)] = 4.0
    min_markers: Annotated[int, Interval(ge=1, le=MAX_MARKER_ID + 1)] = 1
    min_markers_for_rejection: Annotated[int, Interval(ge=3, le=MAX_MARKER_ID + 1)] = 4
    max_rms_px: Positive = 10.0
    sigma_floor_px: Annotated[float, Interval(ge=0.0, le=100.0)] = 0.05

    def validate(self) -> None:
        """Raise ValueError naming the field of an unknown ``method`` (each numeric field's
        range is its declared domain)."""
        if self.method not in _PNP_FLAGS:
            raise ValueError(f"method: {self.method!r} is not one of {', '.join(_PNP_FLAGS)}")


@functools.lru_cache(maxsize=64)
def _checked(cfg: BoardPoseConfig) -> BoardPoseConfig:
    """``cfg`` through :func:`dockcore.config.validated`, once per distinct config (the board
    is solved on every frame)."""
    return validated(cfg)


@dataclass(frozen=True)
class BoardPose:
    """Docking-station pose from the marker board.

    Attributes:
        T_cam_ds: (4, 4) DS frame in the camera frame.
        reprojection_rms_px: RMS corner reprojection error over the used markers (px).
        marker_errors_px: marker ID -> RMS corner reprojection error (px), used markers and
            rejected ones (the latter measured against the final pose).
        used_ids: markers the pose was solved from, ascending.
        rejected_ids: markers dropped as outliers, in rejection order.
        covariance: (6, 6) first-order covariance of (rvec [rad], tvec [m]) of ``T_cam_ds`` as
            ``cv2.projectPoints`` parametrises it: sigma^2 (J^T J)^-1, sigma^2 the residual
            variance (floored by ``sigma_floor_px``).
        method: "sqpnp", "iterative" (+ "+lm" when refined) or "ippe_square" (one marker).
        ambiguity_ratio: when the used markers are coplanar, best / second-best RMS error of
            the two planar solutions (near 1: a flip is likely; see
            :attr:`MarkerPose.ambiguity_ratio`); None for markers spanning 3D.
    """

    T_cam_ds: np.ndarray
    reprojection_rms_px: float
    marker_errors_px: dict[int, float]
    used_ids: tuple[int, ...]
    rejected_ids: tuple[int, ...] = ()
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    method: str = ""
    ambiguity_ratio: float | None = None

    @property
    def translation_std_m(self) -> np.ndarray:
        """(3,) standard deviation of the DS origin in the camera frame (m), from the covariance."""
        return np.sqrt(np.clip(np.diag(self.covariance)[3:], 0.0, None))

    @property
    def rotation_std_deg(self) -> np.ndarray:
        """(3,) standard deviation of the rotation vector components (deg), from the covariance."""
        return np.degrees(np.sqrt(np.clip(np.diag(self.covariance)[:3], 0.0, None)))


def _match(
    detections: Iterable[Any] | Mapping[int, ArrayLike], object_points: Mapping[int, ArrayLike]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """ID -> (obj (4, 3), img (4, 2)) for detections of board markers; duplicated IDs dropped."""
    if isinstance(detections, Mapping):
        pairs = [(int(k), v) for k, v in detections.items()]
    else:
        pairs = [(int(d.marker_id), d.corners_px) for d in detections]
    counts: dict[int, int] = {}
    for k, _ in pairs:
        counts[k] = counts.get(k, 0) + 1
    out = {}
    for k, img in pairs:
        if k in object_points and counts[k] == 1:
            out[k] = (
                _points(object_points[k], (4, 3), f"object_points[{k}]"),
                _points(img, (4, 2), f"corners of marker {k}"),
            )
    return out


def _stack(obs: Mapping[int, tuple[np.ndarray, np.ndarray]], ids: Iterable[int]):
    ids = list(ids)
    return np.vstack([obs[i][0] for i in ids]), np.vstack([obs[i][1] for i in ids])


def _is_coplanar(obj: np.ndarray, rel_tol: float = 1e-3) -> bool:
    """True when the (N, 3) points lie on one plane (smallest/largest singular value < tol)."""
    s = np.linalg.svd(obj - obj.mean(axis=0), compute_uv=False)
    return bool(s[2] <= rel_tol * s[0])


def _refined(obj, img, K, dist, rvec, tvec, lm: bool) -> np.ndarray | None:
    if lm:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    T = _T_from_rt(rvec, tvec)
    return T if np.all(transform_points(T, obj)[:, 2] > 0) else None


def _solve_joint(
    obj, img, K, dist, cfg: BoardPoseConfig, prior: np.ndarray | None
) -> tuple[np.ndarray | None, float | None]:
    """Joint PnP; for coplanar markers also both IPPE solutions (the planar ambiguity).

    Returns the chosen ``T_cam_ds`` (lowest error, or closest to ``prior`` in rotation when
    the markers are coplanar) and, for coplanar markers, the ambiguity ratio (else None).
    """
    cands = []
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=_PNP_FLAGS[cfg.method])
        if ok:
            cands.append(_refined(obj, img, K, dist, rvec, tvec, cfg.lm_refine))
        if not _is_coplanar(obj):
            return cands[0] if cands else None, None
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        for rv, tv in zip(rvecs[:n], tvecs[:n], strict=True):
            cands.append(_refined(obj, img, K, dist, rv, tv, cfg.lm_refine))
    except cv2.error:  # degenerate input (e.g. all corners on a line)
        if not cands:
            return None, None
    scored = []  # (rms, T), distinct rotations only
    for T in cands:
        if T is not None and all(rotation_angle_deg(T, U) > 0.5 for _, U in scored):
            scored.append((_rms(reprojection_errors_px(T, obj, img, K, dist)), T))
    if not scored:
        return None, None
    scored.sort(key=lambda c: c[0])
    ratio = 0.0 if len(scored) < 2 else (1.0 if scored[1][0] <= 0 else scored[0][0] / scored[1][0])
    if prior is not None:
        return min(scored, key=lambda c: rotation_angle_deg(c[1], prior))[1], ratio
    return scored[0][1], ratio


def _solve_single(obj, img, K, dist, prior: np.ndarray | None) -> tuple[np.ndarray | None, float]:
    try:
        T_ds_marker, side = marker_frame_from_corners(obj)
        mp = solve_marker(img, side, K, dist)
    except DockError:
        return None, 1.0
    if prior is not None:
        cand = choose_candidate(mp, prior @ T_ds_marker)
    else:
        cand = mp.best
    return cand.T_cam_marker @ inv_T(T_ds_marker), mp.ambiguity_ratio


def _solve_set(obs, ids, K, dist, cfg: BoardPoseConfig, prior):
    """(T_cam_ds or None, ambiguity ratio or None, method name) from the markers ``ids``."""
    obj, img = _stack(obs, ids)
    if len(ids) == 1:
        T, ambiguity = _solve_single(obj, img, K, dist, prior)
        return T, ambiguity, "ippe_square"
    T, ambiguity = _solve_joint(obj, img, K, dist, cfg, prior)
    return T, ambiguity, cfg.method + ("+lm" if cfg.lm_refine else "")


def _leave_one_out(obs, ids, K, dist, cfg: BoardPoseConfig, prior):
    """Solve the board without each marker in turn; keep the split whose remaining markers agree
    best. Returns (RMS of the rest, left-out ID, its RMS error, solution) or None."""
    best = None
    for out in ids:
        rest = [i for i in ids if i != out]
        solution = _solve_set(obs, rest, K, dist, cfg, prior)
        T = solution[0]
        if T is None:
            continue
        rest_rms = _rms(np.concatenate([reprojection_errors_px(T, *obs[i], K, dist) for i in rest]))
        if best is None or rest_rms < best[0]:
            error_out = _rms(reprojection_errors_px(T, *obs[out], K, dist))
            best = (rest_rms, out, error_out, solution)
    return best


def _covariance(T, obj, img, K, dist, sigma_floor_px: float) -> np.ndarray:
    rvec, tvec = _rt_from_T(T)
    proj, jac = cv2.projectPoints(obj, rvec, tvec, K, dist)
    res = (proj.reshape(-1, 2) - img).ravel()
    J = jac[:, :6]
    dof = max(res.size - 6, 1)
    sigma2 = max(float(res @ res) / dof, sigma_floor_px**2)
    try:
        return sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.nan)


def _marker_errors(T, obs, ids, K, dist) -> dict[int, float]:
    """RMS corner error per marker, from one projection of all their corners."""
    if not ids:
        return {}
    obj, img = _stack(obs, ids)
    e = reprojection_errors_px(T, obj, img, K, dist).reshape(len(ids), -1)
    return {i: _rms(e[k]) for k, i in enumerate(ids)}


def solve_board(
    detections: Iterable[Any] | Mapping[int, ArrayLike],
    object_points: Mapping[int, ArrayLike],
    K: ArrayLike,
    dist: ArrayLike | None,
    cfg: BoardPoseConfig | None = None,
    T_cam_ds_prior: ArrayLike | None = None,
) -> BoardPose | None:
    """Docking-station pose from all visible board markers, solved jointly.

    Args:
        detections: :class:`~perception.detector.Detection` objects (``marker_id``,
            ``corners_px``) or a mapping ID -> (4, 2) corners. IDs not on the board are
            ignored; an ID detected twice is ignored (it cannot be attributed).
        object_points: ID -> (4, 3) corners TL, TR, BR, BL in the DS frame (m), e.g.
            ``MarkerSet.corners_ds()``.
        K: (3, 3) camera matrix; dist: distortion coefficients or None.
        cfg: solver settings (defaults if None).
        T_cam_ds_prior: optional (4, 4) predicted pose (e.g. the filter's prediction). When the
            used markers are coplanar (a lone marker, or only the floor markers) their pose is
            two-fold ambiguous; the prior picks the solution closest in rotation. Without it
            the lower reprojection error wins, which flips when the noise favours the mirror
            solution.

    Returns:
        A :class:`BoardPose`, or None with fewer than ``cfg.min_markers`` usable markers, no
        solution in front of the camera, or a final RMS error above ``cfg.max_rms_px``.
    """
    cfg = _checked(BoardPoseConfig() if cfg is None else cfg)
    K, dist = _intrinsics(K, dist)
    prior = None if T_cam_ds_prior is None else check_T(T_cam_ds_prior, "T_cam_ds_prior")
    obs = _match(detections, object_points)
    ids = sorted(obs)
    rejected: list[int] = []
    if len(ids) < cfg.min_markers:
        return None
    T, ambiguity, method = _solve_set(obs, ids, K, dist, cfg, prior)
    if T is None:
        return None
    errors = _marker_errors(T, obs, ids, K, dist)
    while (
        len(ids) >= cfg.min_markers_for_rejection
        and max(errors.values()) > cfg.outlier_threshold_px
    ):
        loo = _leave_one_out(obs, ids, K, dist, cfg, prior)
        if loo is None:
            break
        rest_rms, worst, error_out, solution = loo
        if error_out <= cfg.outlier_threshold_px or error_out <= cfg.outlier_ratio * rest_rms:
            break
        ids.remove(worst)
        rejected.append(worst)
        T, ambiguity, method = solution
        errors = _marker_errors(T, obs, ids, K, dist)
    # every marker has four corners: the board RMS is the RMS of the per-marker RMS errors
    rms = _rms(np.array([errors[i] for i in ids]))
    if rms > cfg.max_rms_px or len(ids) < cfg.min_markers:
        return None
    errors.update(_marker_errors(T, obs, rejected, K, dist))
    obj, img = _stack(obs, ids)
    return BoardPose(
        T_cam_ds=T,
        reprojection_rms_px=rms,
        marker_errors_px=errors,
        used_ids=tuple(ids),
        rejected_ids=tuple(rejected),
        covariance=_covariance(T, obj, img, K, dist, cfg.sigma_floor_px),
        method=method,
        ambiguity_ratio=ambiguity,
    )


# --------------------------------------------------------------------------- level DS


@dataclass(frozen=True)
class LevelBoardPose:
    """DS pose constrained to be level, in a gravity-aligned world frame.

    Attributes:
        T_world_ds: (4, 4) DS pose in the world (roll = pitch = 0 by construction).
        covariance: (4, 4) covariance of [x, y, z (m), yaw (rad)] from the fit's Jacobian.
        reprojection_rms_px: RMS corner reprojection error of the fit (px).
        used_ids: markers used.
    """

    T_world_ds: np.ndarray
    covariance: np.ndarray
    reprojection_rms_px: float
    used_ids: tuple[int, ...]


def refine_level_board(
    board: BoardPose,
    detections: Iterable[Any] | Mapping[int, ArrayLike],
    object_points: Mapping[int, ArrayLike],
    K: ArrayLike,
    dist: ArrayLike | None,
    T_world_cam: ArrayLike,
    sigma_floor_px: float = 0.3,
) -> LevelBoardPose:
    """Re-solve a board pose with the DS known to be level (4 unknowns: x, y, z, yaw).

    A vehicle knows its roll and pitch well (IMU) and a docking station stands level on the
    floor: with only a few coplanar markers in view the full 6-DoF PnP leaves the tilt poorly
    determined (degrees), and the tilt leaks into yaw and position. Fixing the DS's roll and
    pitch to zero in a gravity-aligned world frame removes that ambiguity.

    Args:
        board: the unconstrained solution (initial guess and the markers to use).
        detections, object_points, K, dist: as for :func:`solve_board`.
        T_world_cam: (4, 4) camera pose (OpenCV frame) in a z-down gravity-aligned world.
        sigma_floor_px: lower bound of the corner noise used for the covariance (px).

    Returns:
        The level pose with its covariance.
    """
    K, dist = _intrinsics(K, dist)
    T_wc = check_T(T_world_cam, "T_world_cam")
    obs = _match(detections, object_points)
    ids = [i for i in board.used_ids if i in obs]
    obj, img = _stack(obs, ids)
    T_cw = inv_T(T_wc)
    R_cw, t_cw = T_cw[:3, :3], T_cw[:3, 3]
    T0 = T_wc @ board.T_cam_ds
    x0 = np.array([*T0[:3, 3], math.atan2(T0[1, 0], T0[0, 0])])

    zero = np.zeros(3)
    last: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def project(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The corners in the camera (p_cam = R_cw (Rz(yaw) obj + xyz) + t_cw), their pixels,
        and OpenCV's Jacobian of the pixels with respect to a shift of all points. The last
        point's result is kept: MINPACK asks for the Jacobian where it has just evaluated
        the residual."""
        key = x.tobytes()
        if key not in last:
            c, s = math.cos(x[3]), math.sin(x[3])
            Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            p_cam = (obj @ Rz.T + x[:3]) @ R_cw.T + t_cw
            proj, jac = cv2.projectPoints(p_cam, zero, zero, K, dist)
            # columns 3-5 of OpenCV's Jacobian: d pixel / d tvec = d pixel / d p_cam of each
            # point
            last.clear()
            last[key] = (p_cam, proj.reshape(-1, 2), jac[:, 3:6])
        return last[key]

    def residual(x: np.ndarray) -> np.ndarray:
        return (project(x)[1] - img).ravel()

    def jacobian(x: np.ndarray) -> np.ndarray:
        """(2N, 4) d residual / d (x, y, z, yaw), from OpenCV's own derivatives."""
        _, _, d_pix_d_p = project(x)
        c, s = math.cos(x[3]), math.sin(x[3])
        dRz = np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 0.0]])
        d_p_d_yaw = (obj @ dRz.T) @ R_cw.T  # (N, 3)
        J = np.empty((len(obj) * 2, 4))
        J[:, :3] = d_pix_d_p @ R_cw
        J[:, 3] = np.einsum("nij,nj->ni", d_pix_d_p.reshape(-1, 2, 3), d_p_d_yaw).ravel()
        return J

    from scipy.optimize import leastsq  # half a second to import, only needed here

    # MINPACK's Levenberg-Marquardt (lmder) through SciPy's thin wrapper, with the settings
    # least_squares(method="lm", x_scale=...) passes it: the same iterates, without
    # least_squares' per-call set-up (~0.5 ms, a third of this function in the camera loop)
    x, _, info, _, _ = leastsq(
        residual, x0, Dfun=jacobian, full_output=True, ftol=1e-8, xtol=1e-8, gtol=1e-8,
        maxfev=400, factor=100.0, diag=1.0 / np.array([0.1, 0.1, 0.1, 0.05]),
    )  # fmt: skip
    r = info["fvec"]
    J = jacobian(x)
    dof = max(r.size - 4, 1)
    sigma2 = max(float(r @ r) / dof, sigma_floor_px**2)
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.diag([0.05**2] * 3 + [math.radians(3.0) ** 2])
    T_world_ds = make_T(R_from_rpy(0.0, 0.0, x[3]), x[:3])
    rms = float(np.sqrt(np.mean(r.reshape(-1, 2) ** 2) * 2))
    return LevelBoardPose(T_world_ds, cov, rms, tuple(ids))
