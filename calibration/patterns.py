"""Calibration targets: chessboard and ChArUco detection with sub-pixel corners, view geometry.

Pattern size conventions (they differ between the two OpenCV targets, as in OpenCV):
    chessboard: ``cols`` x ``rows`` counts **inner corners** (where four squares meet); the
        printed board has (cols + 1) x (rows + 1) squares. Board frame: origin at the first
        inner corner, x along a row of ``cols`` corners, y along the ``rows``, z = 0 on the board.
    charuco: ``cols`` x ``rows`` counts **squares** (``cv2.aruco.CharucoBoard((cols, rows), ...)``);
        it has (cols - 1) x (rows - 1) inner corners. Board frame: OpenCV's (origin at the board's
        outer top-left corner, x right, y down in the generated image).

All image points are pixels (u, v) with integer pixel centres (OpenCV convention); object points
are metres in the board frame.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import quiet_native_stderr

__all__ = [
    "PATTERNS",
    "Detection",
    "PatternDetector",
    "blur_px",
    "normalise_dictionary_name",
    "quad_distance_px",
    "spread_subset",
    "view_quad_px",
]

#: Supported calibration targets.
PATTERNS = ("chessboard", "charuco")

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


def normalise_dictionary_name(name: str) -> str:
    """Canonical ``cv2.aruco`` dictionary name (``DICT_4X4_50``) of ``name`` (``4x4_50`` works).

    Raises:
        ValueError: no such predefined dictionary.
    """
    key = str(name).strip().upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    names = {n.upper(): n for n in dir(cv2.aruco) if n.startswith("DICT_")}
    if key not in names:
        raise ValueError(f"unknown ArUco dictionary {name!r} (e.g. DICT_4X4_50, DICT_5X5_100)")
    return names[key]


@dataclass(frozen=True)
class Detection:
    """Pattern corners found in one view.

    Attributes:
        image_px: (N, 2) float32 sub-pixel corner positions (u, v) in px.
        object_m: (N, 3) float32 matching corner positions in the board frame (m), z = 0.
        ids: (N,) int32 corner indices in the board (row-major; ChArUco corner ids).
    """

    image_px: np.ndarray
    object_m: np.ndarray
    ids: np.ndarray

    @property
    def n_corners(self) -> int:
        """Number of corners found."""
        return int(self.image_px.shape[0])


class PatternDetector:
    """Finds a chessboard or ChArUco board in greyscale images.

    Args:
        pattern: ``"chessboard"`` or ``"charuco"``.
        cols: inner corners per row (chessboard) or squares per row (charuco).
        rows: inner corners per column (chessboard) or squares per column (charuco).
        square_m: square side (m).
        marker_m: ChArUco marker side (m); ignored for a chessboard.
        dictionary: ChArUco marker dictionary name; ignored for a chessboard.
        legacy_charuco: use the pre-4.6 OpenCV ChArUco layout (boards printed with old OpenCV
            with an even number of rows).
        subpix_win_px: largest half window of ``cv2.cornerSubPix`` (px); it shrinks for small
            squares to stay inside one square.
        sb_fallback: try ``cv2.findChessboardCornersSB`` when the classic chessboard finder fails.
        corner_method: chessboard corners from ``"classic"`` (``findChessboardCorners`` +
            ``cornerSubPix``, with the SB fallback) or ``"sb"`` (``findChessboardCornersSB``
            alone, OpenCV's sector-based finder, sub-pixel by itself).
        min_corners: ChArUco views with fewer corners count as "pattern not found".

    Attributes:
        notes: one-line remarks about the target (a ChArUco marker border too thin for
            reliable detection), for the caller to show.

    Raises:
        DockError: unknown pattern or dictionary, or a board OpenCV cannot build.
    """

    def __init__(
        self,
        pattern: str,
        cols: int,
        rows: int,
        square_m: float,
        marker_m: float | None = None,
        dictionary: str = "DICT_4X4_50",
        legacy_charuco: bool = False,
        subpix_win_px: int = 11,
        sb_fallback: bool = True,
        min_corners: int = 6,
        corner_method: str = "classic",
    ) -> None:
        if pattern not in PATTERNS:
            raise DockError(f"unknown pattern {pattern!r} (use one of: {', '.join(PATTERNS)})")
        self.pattern = pattern
        self.notes: list[str] = []
        self.cols, self.rows = int(cols), int(rows)
        self.square_m = float(square_m)
        self.subpix_win_px = int(subpix_win_px)
        self.sb_fallback = bool(sb_fallback)
        if corner_method not in ("classic", "sb"):
            raise DockError(f"unknown corner method {corner_method!r} (use classic or sb)")
        self.corner_method = corner_method
        self.min_corners = int(min_corners)
        if pattern == "chessboard":
            grid = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2)  # row-major
            self._objects = np.zeros((grid.shape[0], 3), np.float32)
            self._objects[:, :2] = grid * self.square_m
            # Board outline (m) used for view descriptors: one square beyond the inner corners.
            lo, hi = -self.square_m, np.array([self.cols, self.rows]) * self.square_m
        else:
            try:
                dict_name = normalise_dictionary_name(dictionary)
            except ValueError as exc:
                raise DockError(str(exc)) from None
            marker = 0.75 * self.square_m if marker_m is None else float(marker_m)
            self._gap_frac = (self.square_m - marker) / (2.0 * self.square_m)
            try:
                aruco_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dict_name))
                cell_m = marker / (int(aruco_dict.markerSize) + 2)
                border_m = (self.square_m - marker) / 2.0
                if border_m < 0.7 * cell_m:  # what OpenCV would warn about on stderr
                    self.notes.append(
                        f"the ChArUco markers ({1e3 * marker:g} mm in {1e3 * self.square_m:g} mm "
                        f"squares) leave a {1e3 * border_m:.3g} mm white border, less than 70 % "
                        f"of a marker cell ({1e3 * cell_m:.3g} mm): detection may be unreliable"
                    )
                with quiet_native_stderr():
                    self._board = cv2.aruco.CharucoBoard(
                        (self.cols, self.rows), self.square_m, marker, aruco_dict
                    )
                self._board.setLegacyPattern(bool(legacy_charuco))
                self._charuco = cv2.aruco.CharucoDetector(self._board)
            except cv2.error as exc:
                text = " ".join(str(exc).split()).split(" error: ", 1)[-1]
                raise DockError(f"cannot build the ChArUco board: {text}") from None
            self._objects = np.asarray(self._board.getChessboardCorners(), np.float32)
            lo, hi = 0.0, np.array([self.cols, self.rows]) * self.square_m
        self.outline_m = np.array(
            [[lo, lo], [hi[0], lo], [hi[0], hi[1]], [lo, hi[1]]], dtype=np.float64
        )

    @property
    def n_corners_max(self) -> int:
        """Number of corners of the full board."""
        return int(self._objects.shape[0])

    def detect(self, gray: np.ndarray) -> Detection | None:
        """Find the pattern in one greyscale uint8 image (H, W); None when it is not found."""
        if self.pattern == "chessboard":
            return self._detect_chessboard(gray)
        return self._detect_charuco(gray)

    def _refine(self, gray: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """cornerSubPix with a half window that stays inside the corner's own squares.

        The half window is at most 0.4 of the smallest corner spacing (chessboard) or half the
        gap between a corner and the nearest marker edge (ChArUco: marker edges inside the
        window bias the corner by tenths of a pixel), and at most ``subpix_win_px``.
        """
        pts = corners.reshape(-1, 1, 2).astype(np.float32)
        if pts.shape[0] >= 2:
            d = np.linalg.norm(pts[:, None, 0] - pts[None, :, 0], axis=-1)
            np.fill_diagonal(d, np.inf)
            spacing = float(np.min(d))
        else:
            spacing = 2.0 * self.subpix_win_px
        limit = 0.4 * spacing if self.pattern == "chessboard" else 0.5 * spacing * self._gap_frac
        win = int(np.clip(np.floor(limit), 2, self.subpix_win_px))
        pts = cv2.cornerSubPix(gray, pts, (win, win), (-1, -1), _SUBPIX_CRITERIA)
        return pts.reshape(-1, 2)

    def _detect_chessboard(self, gray: np.ndarray) -> Detection | None:
        size = (self.cols, self.rows)
        flags = (
            cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
        )
        found, corners = False, None
        if self.corner_method == "classic":
            found, corners = cv2.findChessboardCorners(gray, size, flags=flags)
        if found:
            corners = self._refine(gray, corners)
        elif self.sb_fallback or self.corner_method == "sb":
            found, corners = _find_sb(gray, size)
            if not found:
                return None
            corners = corners.reshape(-1, 2)  # already sub-pixel accurate
        else:
            return None
        ids = np.arange(self.n_corners_max, dtype=np.int32)
        return Detection(corners.astype(np.float32), self._objects.copy(), ids)

    def _detect_charuco(self, gray: np.ndarray) -> Detection | None:
        corners, ids, _, _ = self._charuco.detectBoard(gray)
        if ids is None or corners is None or len(ids) < self.min_corners:
            return None
        ids = np.asarray(ids, np.int32).reshape(-1)
        obj = self._objects[ids]
        # Corners on one line (a single row of markers) cannot constrain a homography.
        centred = obj[:, :2] - obj[:, :2].mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        if sv[1] < 0.5 * self.square_m:
            return None
        image = self._refine(gray, np.asarray(corners, np.float32))
        return Detection(image.astype(np.float32), obj.astype(np.float32), ids)


#: Flags of the sector-based finder: image normalisation and sub-pixel accuracy (its corners
#: come from a finer sampling: on a real tank set the calibration RMS fell from 0.24 to 0.16 px).
_SB_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY


def _find_sb(gray: np.ndarray, size: tuple[int, int]) -> tuple[bool, np.ndarray | None]:
    """``findChessboardCornersSB`` with :data:`_SB_FLAGS`, retried with the exhaustive search
    where the quick one finds nothing (on a real murky tank set the quick search missed 5 of
    11 views the exhaustive one finds)."""
    found, corners = cv2.findChessboardCornersSB(gray, size, flags=_SB_FLAGS)
    if not found:
        found, corners = cv2.findChessboardCornersSB(
            gray, size, flags=_SB_FLAGS | cv2.CALIB_CB_EXHAUSTIVE
        )
    return bool(found), corners


def _homography(det: Detection) -> np.ndarray | None:
    """(3, 3) board-plane (m) -> image (px) homography of a detection, or None."""
    if det.n_corners < 4:
        return None
    H, _ = cv2.findHomography(
        det.object_m[:, :2].astype(np.float64), det.image_px.astype(np.float64)
    )
    return H


def view_quad_px(det: Detection, outline_m: np.ndarray) -> np.ndarray | None:
    """Where the board outline lands in the image: (4, 2) px, via the detection's homography.

    A compact descriptor of a view's pose (position, size, tilt and roll of the board in the
    image), used to spot near-duplicate views and to spread the kept views.
    """
    H = _homography(det)
    if H is None:
        return None
    pts = cv2.perspectiveTransform(outline_m.reshape(-1, 1, 2).astype(np.float64), H)
    return pts.reshape(4, 2)


#: Corner orders of a quad under the board's symmetries (4 rotations x 2 reflections).
_QUAD_ORDERS = tuple(
    tuple(np.roll(order, k)) for order in ((0, 1, 2, 3), (3, 2, 1, 0)) for k in range(4)
)


def quad_distance_px(a: np.ndarray, b: np.ndarray) -> float:
    """Mean corner distance (px) between two view quads, minimised over the quad's symmetries.

    A chessboard detector may number the corners from either end, so the same board pose can
    come back relabelled; the minimum over the 8 corner orders removes that ambiguity.
    """
    return float(min(np.linalg.norm(a - b[list(o)], axis=1).mean() for o in _QUAD_ORDERS))


def blur_px(gray: np.ndarray, det: Detection) -> float:
    """Edge width (px) of the pattern: a blur measure that does not depend on scale or contrast.

    Inside the convex hull of the detected corners, edge width = contrast / peak gradient, with
    contrast the 1-99 % intensity range and the peak gradient the 99th percentile of the Sobel
    gradient magnitude. Pixels are split by gradient direction into the two families of board
    edges (along the board's x and y axes, from the homography) and the wider family is
    returned, so motion blur across one family is caught. A sharp image gives about 2 px; a
    Gaussian blur of sigma s gives about 2.5 s.

    Args:
        gray: (H, W) uint8 image.
        det: the detection in that image.

    Returns:
        Edge width (px); ``inf`` where the pattern shows no contrast.
    """
    hull = cv2.convexHull(det.image_px.reshape(-1, 1, 2).astype(np.float32))
    mask = np.zeros(gray.shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, hull.astype(np.int32).reshape(-1, 2), 1)
    inside = mask.astype(bool)
    if inside.sum() < 64:
        return float("inf")
    img = gray.astype(np.float32)
    lo, hi = np.percentile(img[inside], [1.0, 99.0])
    contrast = float(hi - lo)
    if contrast < 8.0:
        return float("inf")
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    gx, gy = gx[inside], gy[inside]
    mag = np.hypot(gx, gy)
    families = _edge_normals(det)
    if families is None:
        return contrast / max(float(np.percentile(mag, 99.0)), 1e-6)
    # |cos| between each gradient and each family's image normal; assign to the closer one.
    score = np.abs(np.stack([gx * n[0] + gy * n[1] for n in families]))
    label = np.argmax(score, axis=0)
    widths = []
    for k in range(2):
        sel = mag[label == k]
        if sel.size >= 32:
            widths.append(contrast / max(float(np.percentile(sel, 99.0)), 1e-6))
    return max(widths) if widths else float("inf")


def _edge_normals(det: Detection) -> tuple[np.ndarray, np.ndarray] | None:
    """Unit image normals of the board's x-parallel and y-parallel edges at the board centre."""
    H = _homography(det)
    if H is None:
        return None
    c = det.object_m[:, :2].astype(np.float64).mean(axis=0)
    step = 1e-3
    pts = np.array([c, c + np.array([step, 0.0]), c + np.array([0.0, step])]).reshape(-1, 1, 2)
    img = cv2.perspectiveTransform(pts, H).reshape(3, 2)
    normals = []
    for d in (img[1] - img[0], img[2] - img[0]):
        n = np.array([-d[1], d[0]])
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm < 1e-12:
            return None
        normals.append(n / norm)
    return normals[0], normals[1]


def spread_subset(quads: list[np.ndarray], k: int) -> list[int]:
    """Indices of ``k`` views spread over pose space (farthest-point sampling on view quads).

    Deterministic: sampling starts at the medoid view (least summed distance to the others), so
    the same views always give the same subset.

    Args:
        quads: (4, 2) view quads (px), one per candidate view.
        k: how many to keep (all when ``k >= len(quads)``).

    Returns:
        Sorted indices into ``quads``.
    """
    n = len(quads)
    if k >= n:
        return list(range(n))
    pair = np.array([[quad_distance_px(a, b) for b in quads] for a in quads])
    chosen = [int(np.argmin(pair.sum(axis=1)))]
    dist = pair[chosen[0]].copy()
    for _ in itertools.repeat(None, k - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, pair[nxt])
    return sorted(chosen)
