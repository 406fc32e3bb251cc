"""A calibrated stereo pair and its file: two cameras, ``T_right_left`` and the rectification.

Frames: both cameras in ``cam_cv`` (x right, y down, z forward). ``T_right_left`` (4 x 4, metres)
is the left camera frame expressed in the right camera frame: it maps a point p_left to
p_right = T_right_left @ p_left (OpenCV ``stereoCalibrate``'s ``R``, ``T``; Kalibr's
``T_cn_cnm1`` of cam1 when cam0 is the left camera). For cameras side by side with the right
one to the right of the left one, its translation is about (-baseline, 0, 0).

Rectification (OpenCV ``stereoRectify``, the same matrices ROS's ``camera_calibration`` writes
into a stereo pair's camera_info): ``R1`` / ``R2`` (3 x 3) rotate the left / right raw camera
frame into its rectified frame, ``P1`` / ``P2`` (3 x 4) project rectified-frame points of the
left camera into each rectified image (``P2[0, 3] = -fx' * baseline``, ROS's ``Tx``), and ``Q``
(4 x 4) reprojects (u, v, disparity, 1) of the left rectified image to 3D.

Stereo file (format version 1), written by :func:`save_stereo` as two twins with one stem, as
camera files are (:mod:`calibration.camera`): ``<stem>.yaml`` (OpenCV FileStorage) and
``<stem>.json`` (plain JSON). Keys:
    format_version (int):            1.
    kind (str):                      ``stereo`` (tells the file from a camera file).
    image_width, image_height (int): image size of both cameras (px).
    left_name, right_name (str):     camera names.
    left_camera_matrix, right_camera_matrix (3x3): K of each raw image (px).
    left_distortion_coefficients, right_distortion_coefficients (1xN): OpenCV order.
    T_right_left (4x4):              see above (m).
    R1, R2 (3x3), P1, P2 (3x4), Q (4x4): the rectification.
    rectification_alpha (float, optional): ``stereoRectify``'s alpha the matrices were made
        with; absent when R and P were imported as read (a ROS camera_info pair).
    rms_px (float, optional):        RMS reprojection error of the stereo calibration (px).
    left_topic, right_topic (str, optional): the image topics (a bag's, or a camchain's
        ``rostopic``), written into an exported Kalibr camchain.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import (
    CameraModel,
    check_camera,
    filestorage_yaml_text,
    raw_integer,
    raw_matrix,
    read_filestorage_yaml,
    twin_paths,
)
from uwdock.calibration.frames import check_T
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, read_text

__all__ = [
    "STEREO_FILE_VERSION",
    "StereoRig",
    "is_stereo_file",
    "load_stereo",
    "rectification",
    "save_stereo",
    "stereo_file_bytes",
]

#: Version written into (and accepted from) stereo files.
STEREO_FILE_VERSION = 1


def rectification(
    left: CameraModel, right: CameraModel, T_right_left: np.ndarray, alpha: float = 0.0
) -> dict[str, Any]:
    """``cv2.stereoRectify`` of a pair (``CALIB_ZERO_DISPARITY``: both rectified principal
    points at the same pixel).

    Args:
        left: left camera.
        right: right camera (same image size).
        T_right_left: (4, 4) left camera frame in the right camera frame (m).
        alpha: 0 keeps only valid pixels in the rectified images, 1 keeps every source pixel
            (black borders), in between scales.

    Returns:
        ``R1``, ``R2`` (3, 3), ``P1``, ``P2`` (3, 4), ``Q`` (4, 4) float64 and ``roi1``,
        ``roi2``: the valid pixel rectangles (x, y, w, h) of each rectified image.
    """
    size = (left.width_px, left.height_px)
    R1, R2, P1, P2, Q, roi1, roi2 = cv2.stereoRectify(
        left.K,
        left.dist_coeffs,
        right.K,
        right.dist_coeffs,
        size,
        np.ascontiguousarray(T_right_left[:3, :3]),
        np.ascontiguousarray(T_right_left[:3, 3]).reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=float(alpha),
    )
    return {
        "R1": R1,
        "R2": R2,
        "P1": P1,
        "P2": P2,
        "Q": Q,
        "roi1": [int(v) for v in roi1],
        "roi2": [int(v) for v in roi2],
    }


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Two calibrated cameras of one image size, their relative pose and rectification.

    Attributes:
        left: the left camera (raw image intrinsics).
        right: the right camera.
        T_right_left: (4, 4) float64, the left camera frame in the right camera frame (m).
        R1: (3, 3) left raw -> left rectified rotation.
        R2: (3, 3) right raw -> right rectified rotation.
        P1: (3, 4) left rectified projection.
        P2: (3, 4) right rectified projection, ``P2[0, 3] = -fx' * baseline`` (ROS's Tx).
        Q: (4, 4) disparity-to-depth matrix of the left rectified image.
        rectification_alpha: ``stereoRectify``'s alpha, None when R and P were imported.
        rms_px: RMS reprojection error of the stereo calibration (px), or None.
        left_topic: image topic of the left camera, or None.
        right_topic: image topic of the right camera, or None.
    """

    left: CameraModel
    right: CameraModel
    T_right_left: np.ndarray
    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    rectification_alpha: float | None = 0.0
    rms_px: float | None = None
    left_topic: str | None = None
    right_topic: str | None = None
    roi: tuple[tuple[int, ...], tuple[int, ...]] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if (self.left.width_px, self.left.height_px) != (
            self.right.width_px,
            self.right.height_px,
        ):
            raise ValueError(
                f"the cameras differ in size: left {self.left.width_px}x{self.left.height_px}, "
                f"right {self.right.width_px}x{self.right.height_px} px"
            )
        object.__setattr__(self, "T_right_left", check_T(self.T_right_left, "T_right_left"))
        for key, shape in (("R1", (3, 3)), ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4))):
            arr = np.array(getattr(self, key), dtype=np.float64)
            if arr.shape != shape or not np.all(np.isfinite(arr)):
                raise ValueError(f"{key}: must be a finite {shape[0]}x{shape[1]} matrix")
            object.__setattr__(self, key, arr)
        Q = np.array(self.Q, dtype=np.float64)
        if Q.shape != (4, 4) or not np.all(np.isfinite(Q)):
            raise ValueError("Q: must be a finite 4x4 matrix")
        object.__setattr__(self, "Q", Q)
        if self.baseline_m <= 0.0:
            raise ValueError("T_right_left: the cameras are at the same place (baseline 0 m)")

    @classmethod
    def from_cameras(
        cls,
        left: CameraModel,
        right: CameraModel,
        T_right_left: ArrayLike,
        alpha: float = 0.0,
        **extra: Any,
    ) -> StereoRig:
        """A rig whose rectification is computed here (:func:`rectification`).

        Args:
            left: left camera.
            right: right camera (same image size).
            T_right_left: (4, 4) left camera frame in the right camera frame (m).
            alpha: ``stereoRectify``'s alpha in [0, 1].
            extra: ``rms_px``, ``left_topic``, ``right_topic``.

        Raises:
            ValueError: different image sizes, an invalid transform, a zero baseline.
        """
        T = check_T(T_right_left, "T_right_left")
        if (left.width_px, left.height_px) != (right.width_px, right.height_px):
            raise ValueError(
                f"the cameras differ in size: left {left.width_px}x{left.height_px}, "
                f"right {right.width_px}x{right.height_px} px"
            )
        if not np.linalg.norm(T[:3, 3]) > 0.0:
            raise ValueError("T_right_left: the cameras are at the same place (baseline 0 m)")
        rect = rectification(left, right, T, alpha)
        return cls(
            left,
            right,
            T,
            rect["R1"],
            rect["R2"],
            rect["P1"],
            rect["P2"],
            rect["Q"],
            rectification_alpha=float(alpha),
            roi=(tuple(rect["roi1"]), tuple(rect["roi2"])),
            **extra,
        )

    @classmethod
    def from_rectified(
        cls,
        left: CameraModel,
        right: CameraModel,
        R1: ArrayLike,
        R2: ArrayLike,
        P1: ArrayLike,
        P2: ArrayLike,
        **extra: Any,
    ) -> StereoRig:
        """A rig from the rectification of a ROS camera_info pair, kept as read.

        The pose follows from the rectified frames: they share one orientation, and the left
        one's origin sits at ``t' = (P2[0, 3] / P2[0, 0], P2[1, 3] / P2[1, 1], 0)`` in the right
        one's, so ``T_right_left = [R2^T R1 | R2^T t']``.

        Raises:
            ValueError: R1 or R2 not a rotation, P2 without a baseline, different image sizes.
        """
        R1, R2 = (np.array(r, dtype=np.float64).reshape(3, 3) for r in (R1, R2))
        P1, P2 = (np.array(p, dtype=np.float64).reshape(3, 4) for p in (P1, P2))
        for key, R in (("R1", R1), ("R2", R2)):
            if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
                raise ValueError(f"{key}: the rectification matrix is not a rotation")
        if P2[0, 0] <= 0.0 or P2[1, 1] <= 0.0:
            raise ValueError("P2: the focal lengths must be > 0")
        t_rect = np.array([P2[0, 3] / P2[0, 0], P2[1, 3] / P2[1, 1], 0.0])
        if not np.linalg.norm(t_rect) > 0.0:
            raise ValueError(
                "P2: no baseline (Tx = Ty = 0): not the right camera of a rectified pair"
            )
        T = np.eye(4)
        T[:3, :3] = R2.T @ R1
        T[:3, 3] = R2.T @ t_rect
        # the disparity-to-depth matrix of stereoRectify, from P1 and P2
        horizontal = abs(t_rect[0]) >= abs(t_rect[1])
        f, cx1, cy1 = P1[0, 0], P1[0, 2], P1[1, 2]
        if horizontal:
            tx = t_rect[0]
            Q = np.array(
                [
                    [1.0, 0.0, 0.0, -cx1],
                    [0.0, 1.0, 0.0, -cy1],
                    [0.0, 0.0, 0.0, f],
                    [0.0, 0.0, -1.0 / tx, (cx1 - P2[0, 2]) / tx],
                ]
            )
        else:
            ty = t_rect[1]
            Q = np.array(
                [
                    [1.0, 0.0, 0.0, -cx1],
                    [0.0, 1.0, 0.0, -cy1],
                    [0.0, 0.0, 0.0, P1[1, 1]],
                    [0.0, 0.0, -1.0 / ty, (cy1 - P2[1, 2]) / ty],
                ]
            )
        return cls(left, right, T, R1, R2, P1, P2, Q, rectification_alpha=None, **extra)

    # ------------------------------------------------------------------ derived

    @property
    def baseline_m(self) -> float:
        """Distance between the two camera centres (m)."""
        return float(np.linalg.norm(self.T_right_left[:3, 3]))

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation between the two camera frames (deg)."""
        c = (np.trace(self.T_right_left[:3, :3]) - 1.0) / 2.0
        return math.degrees(math.acos(min(1.0, max(-1.0, c))))

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) of both images (px)."""
        return self.left.width_px, self.left.height_px

    @property
    def E(self) -> np.ndarray:
        """(3, 3) essential matrix ``[t]x R`` of ``T_right_left`` (p_right^T E p_left = 0)."""
        t = self.T_right_left[:3, 3]
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        return tx @ self.T_right_left[:3, :3]

    @property
    def F(self) -> np.ndarray:
        """(3, 3) fundamental matrix between the undistorted pixels of the two cameras
        (x_right^T F x_left = 0, homogeneous px)."""
        return np.linalg.inv(self.right.K).T @ self.E @ np.linalg.inv(self.left.K)

    def rectify_maps(
        self, m1type: int = cv2.CV_32FC1
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``cv2.initUndistortRectifyMap`` of both cameras at the image size:
        (left_x, left_y, right_x, right_y), each (H, W) float32 source pixel coordinates for
        ``cv2.remap``."""
        size = self.image_size
        lx, ly = cv2.initUndistortRectifyMap(
            self.left.K, self.left.dist_coeffs, self.R1, self.P1, size, m1type
        )
        rx, ry = cv2.initUndistortRectifyMap(
            self.right.K, self.right.dist_coeffs, self.R2, self.P2, size, m1type
        )
        return lx, ly, rx, ry


# ---------------------------------------------------------------------------- file


def _matrices(rig: StereoRig) -> dict[str, np.ndarray]:
    return {
        "left_camera_matrix": rig.left.K,
        "left_distortion_coefficients": rig.left.dist_coeffs.reshape(1, -1),
        "right_camera_matrix": rig.right.K,
        "right_distortion_coefficients": rig.right.dist_coeffs.reshape(1, -1),
        "T_right_left": rig.T_right_left,
        "R1": rig.R1,
        "R2": rig.R2,
        "P1": rig.P1,
        "P2": rig.P2,
        "Q": rig.Q,
    }


def _scalars(rig: StereoRig) -> dict[str, Any]:
    out: dict[str, Any] = {
        "format_version": STEREO_FILE_VERSION,
        "kind": "stereo",
        "image_width": int(rig.left.width_px),
        "image_height": int(rig.left.height_px),
        "left_name": rig.left.name,
        "right_name": rig.right.name,
    }
    optional = {
        "rectification_alpha": rig.rectification_alpha,
        "rms_px": rig.rms_px,
        "left_topic": rig.left_topic,
        "right_topic": rig.right_topic,
    }
    out.update({k: v for k, v in optional.items() if v is not None})
    return out


def save_stereo(path: str | os.PathLike[str], rig: StereoRig) -> tuple[Path, Path]:
    """Write a stereo file as OpenCV YAML plus a JSON twin with one stem, atomically.

    Args:
        path: ``<stem>.yaml`` (or ``.yml`` / ``.json``: the other twin gets the other suffix).
        rig: the stereo pair.

    Returns:
        (yaml_path, json_path) as written, as one unit (both new or both as they were).
    """
    files = stereo_file_bytes(path, rig)
    atomic_write_files(files)
    yaml_path, json_path = files
    return yaml_path, json_path


def stereo_file_bytes(path: str | os.PathLike[str], rig: StereoRig) -> dict[Path, bytes]:
    """What :func:`save_stereo` writes: ``{yaml_path: bytes, json_path: bytes}``, for a caller
    that writes the twins in one unit with other files (``dockcore.io.atomic_write_files``)."""
    yaml_path, json_path = twin_paths(path)
    scalars, matrices = _scalars(rig), _matrices(rig)
    items = [(k, float(v) if isinstance(v, float) else v) for k, v in scalars.items()]
    items += [(k, np.ascontiguousarray(v, dtype=np.float64)) for k, v in matrices.items()]
    yaml_text = filestorage_yaml_text(items)
    doc = dict(scalars)
    doc.update({k: v.tolist() for k, v in matrices.items()})
    doc["left_distortion_coefficients"] = list(rig.left.dist)
    doc["right_distortion_coefficients"] = list(rig.right.dist)
    return {
        yaml_path: yaml_text.encode("utf-8"),
        json_path: (json.dumps(doc, indent=2, sort_keys=False) + "\n").encode("utf-8"),
    }


def _read_raw(path: Path) -> dict[str, Any]:
    suffix = path.suffix.lower()
    if suffix not in (".yaml", ".yml", ".json"):
        raise DockError(f"stereo file must end in .yaml, .yml or .json: {path}")
    if not path.is_file():
        raise DockError(f"stereo file not found: {path}")
    try:
        if suffix != ".json":
            return read_filestorage_yaml(path)
        raw = json.loads(read_text(path, "stereo file"))
    except json.JSONDecodeError as exc:
        raise DockError(f"malformed stereo file {path}: {' '.join(str(exc).split())}") from None
    except OSError as exc:
        raise DockError(f"cannot read stereo file {path}: {exc.strerror or exc}") from None
    if not isinstance(raw, dict):
        raise DockError(f"malformed stereo file {path}: top level is not an object")
    return raw


def is_stereo_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a readable stereo file (``kind: stereo``), not a camera file."""
    try:
        return _read_raw(Path(path)).get("kind") == "stereo"
    except DockError:
        return False


def load_stereo(path: str | os.PathLike[str]) -> StereoRig:
    """Read a stereo file (``.yaml`` / ``.yml`` via cv2.FileStorage, or ``.json``).

    Raises:
        DockError: one line naming the file (and the key at fault) when it is missing,
            malformed, of another version, or holds invalid values.
    """
    path = Path(path)
    raw = _read_raw(path)
    if raw.get("kind") != "stereo":
        raise DockError(f"{path}: not a stereo file (no 'kind: stereo'; a camera file?)")

    def matrix(key: str, shape: tuple[int, ...] | None) -> np.ndarray:
        return raw_matrix(raw, key, path, shape)

    def integer(key: str) -> int:
        return raw_integer(raw, key, path)

    def optional(key: str, kind: type) -> Any:
        value = raw.get(key)
        if value is None:
            return None
        if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if kind is str and isinstance(value, str):
            return value
        raise DockError(f"{path}: key '{key}' must be a {kind.__name__}, got {value!r}")

    version = integer("format_version")
    if version != STEREO_FILE_VERSION:
        raise DockError(
            f"{path}: key 'format_version' is {version}, this toolkit reads {STEREO_FILE_VERSION}"
        )
    size = (integer("image_width"), integer("image_height"))
    cams = []
    for side in ("left", "right"):
        K = matrix(f"{side}_camera_matrix", (3, 3))
        if K[0, 1] != 0.0 or K[1, 0] != 0.0 or not np.array_equal(K[2], (0.0, 0.0, 1.0)):
            raise DockError(
                f"{path}: key '{side}_camera_matrix' must be [[fx,0,cx],[0,fy,cy],[0,0,1]]"
            )
        dist = matrix(f"{side}_distortion_coefficients", None).reshape(-1)
        name = raw.get(f"{side}_name", side)
        try:
            cams.append(
                CameraModel(
                    size[0],
                    size[1],
                    float(K[0, 0]),
                    float(K[1, 1]),
                    float(K[0, 2]),
                    float(K[1, 2]),
                    tuple(float(d) for d in dist),
                    name=name if isinstance(name, str) and name else side,
                )
            )
            check_camera(cams[-1])
        except ValueError as exc:
            raise DockError(f"{path}: {side} camera: {exc}") from None
    try:
        return StereoRig(
            cams[0],
            cams[1],
            matrix("T_right_left", (4, 4)),
            matrix("R1", (3, 3)),
            matrix("R2", (3, 3)),
            matrix("P1", (3, 4)),
            matrix("P2", (3, 4)),
            matrix("Q", (4, 4)),
            rectification_alpha=optional("rectification_alpha", float),
            rms_px=optional("rms_px", float),
            left_topic=optional("left_topic", str),
            right_topic=optional("right_topic", str),
        )
    except ValueError as exc:
        raise DockError(f"{path}: {exc}") from None
