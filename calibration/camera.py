"""Pinhole camera model (OpenCV conventions) and the camera file read by perception and sim.

Pixel convention: OpenCV's. Pixel (u, v) = (column, row); integer coordinates are pixel centres,
so the image covers u in [-0.5, width - 0.5) and v in [-0.5, height - 0.5). Points are in the
``cam_cv`` frame (x right, y down, z forward; see :mod:`calibration.frames`).

Camera file (format version 1), written by :func:`save_camera` as two twins with one stem:

* ``<stem>.yaml``: OpenCV FileStorage YAML, readable by ``cv2.FileStorage`` in any language.
* ``<stem>.json``: the same values as plain JSON lists and numbers.

Keys (required unless marked optional):
    format_version (int, optional):  1. Files without it (e.g. from OpenCV's calibration
        sample) are read as version 1.
    camera_matrix (3x3):             K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (px).
    distortion_coefficients (1xN):   OpenCV order k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4
        [, tx, ty]]]], N in {4, 5, 8, 12, 14}.
    image_width, image_height (int): image size (px) the intrinsics belong to.
    rms_px (float, optional):        RMS reprojection error of the calibration (px).
    T_body_cam (4x4, optional):      camera extrinsics ``T_bodyfrd_camcv``: the OpenCV camera
        frame expressed in the vehicle body frame (x forward, y starboard, z down), metres.
    name (str, optional):            camera name (default "camera").
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.frames import check_T
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, check_regular_file, read_text
from uwdock.dockcore.media import display_name, quiet_native_stderr

__all__ = [
    "CAMERA_FILE_VERSION",
    "MAX_CAMERA_OFFSET_M",
    "REFERENCE_T_BODYFRD_CAMCV",
    "CameraModel",
    "camera_file_bytes",
    "check_T_body_cam",
    "check_camera",
    "check_plausible",
    "filestorage_yaml_text",
    "load_camera",
    "raw_integer",
    "raw_matrix",
    "read_filestorage_yaml",
    "reference_camera",
    "resolve_camera",
    "save_camera",
    "scaled_to_width",
    "twin_paths",
]

#: Version written into (and accepted from) camera files.
CAMERA_FILE_VERSION = 1

#: Accepted lengths of the OpenCV distortion vector.
_DIST_LENGTHS = (4, 5, 8, 12, 14)
#: Largest image side (px), focal length and principal point coordinate (px, in absolute value;
#: a 100000 px image with a 0.1 deg field of view has f = 5.7e7 px) and distortion coefficient a
#: camera may state: beyond them a file is wrong, and projections overflow.
MAX_IMAGE_PX = 100_000
MAX_FOCAL_PX = 1e8
MAX_DIST_COEFF = 1e6


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics with OpenCV distortion.

    Attributes:
        width_px: image width (px), 1 ... ``MAX_IMAGE_PX``.
        height_px: image height (px), 1 ... ``MAX_IMAGE_PX``.
        fx_px: focal length along u (px), in (0, ``MAX_FOCAL_PX``].
        fy_px: focal length along v (px), in (0, ``MAX_FOCAL_PX``].
        cx_px: principal point u (px; pixel centres at integers), within +-``MAX_FOCAL_PX``.
        cy_px: principal point v (px), within +-``MAX_FOCAL_PX``.
        dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]); length 4, 5, 8, 12 or
            14; dimensionless, within +-``MAX_DIST_COEFF``. Zeros for an ideal pinhole.
        rms_px: RMS reprojection error of the calibration that produced it (px), or None.
        name: a label for files and reports.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    rms_px: float | None = None
    name: str = "camera"

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))
        except (TypeError, ValueError):
            raise ValueError(f"dist: expected a sequence of numbers, got {self.dist!r}") from None
        if isinstance(self.name, str):  # bytes that are not UTF-8 (--name) as \\xNN: no crash
            object.__setattr__(self, "name", display_name(self.name))
        self.validate()

    def validate(self) -> None:
        """Raise ValueError (one line naming the field) if a value is out of range."""
        for key in ("width_px", "height_px"):
            value = getattr(self, key)
            integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
            if not (integer and 1 <= value <= MAX_IMAGE_PX):
                raise ValueError(f"{key}: must be an integer in [1, {MAX_IMAGE_PX}], got {value!r}")
        for key in ("fx_px", "fy_px", "cx_px", "cy_px"):
            value = getattr(self, key)
            if not isinstance(value, (int, float, np.number)) or not math.isfinite(value):
                raise ValueError(f"{key}: must be a finite number, got {value!r}")
            if abs(value) > MAX_FOCAL_PX:
                raise ValueError(f"{key}: must be within +-{MAX_FOCAL_PX:g} px, got {value!r}")
        for key in ("fx_px", "fy_px"):
            if getattr(self, key) <= 0:
                raise ValueError(f"{key}: must be > 0, got {getattr(self, key)!r}")
        if len(self.dist) not in _DIST_LENGTHS:
            raise ValueError(f"dist: length must be one of {_DIST_LENGTHS}, got {len(self.dist)}")
        if not all(math.isfinite(d) and abs(d) <= MAX_DIST_COEFF for d in self.dist):
            raise ValueError(
                f"dist: must be finite and within +-{MAX_DIST_COEFF:g}, got {self.dist}"
            )
        if self.rms_px is not None and not (
            isinstance(self.rms_px, (int, float, np.number))
            and math.isfinite(self.rms_px)
            and 0 <= self.rms_px <= MAX_IMAGE_PX
        ):
            raise ValueError(
                f"rms_px: must be None or a number in [0, {MAX_IMAGE_PX}], got {self.rms_px!r}"
            )
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name: must be a non-empty string, got {self.name!r}")

    # ------------------------------------------------------------------ derived quantities

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (px)."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(N,) float64 distortion coefficients in OpenCV order."""
        return np.array(self.dist, dtype=np.float64)

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view (deg) between the outer pixel edges, pinhole (no distortion)."""
        left = math.atan((self.cx_px + 0.5) / self.fx_px)
        right = math.atan((self.width_px - 0.5 - self.cx_px) / self.fx_px)
        return math.degrees(left + right)

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view (deg) between the outer pixel edges, pinhole (no distortion)."""
        top = math.atan((self.cy_px + 0.5) / self.fy_px)
        bottom = math.atan((self.height_px - 0.5 - self.cy_px) / self.fy_px)
        return math.degrees(top + bottom)

    @classmethod
    def from_hfov(
        cls, width_px: int, height_px: int, hfov_deg: float, name: str = "camera"
    ) -> CameraModel:
        """Ideal pinhole with square pixels and the principal point at the image centre.

        Args:
            width_px: image width (px).
            height_px: image height (px).
            hfov_deg: horizontal field of view between the outer pixel edges (deg), in (0, 180).
            name: camera name.

        Returns:
            A model with f = (width/2) / tan(hfov/2), c = ((w-1)/2, (h-1)/2), zero distortion.
        """
        if not 0.0 < hfov_deg < 180.0:
            raise ValueError(f"hfov_deg: must be in (0, 180), got {hfov_deg!r}")
        f_px = (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(
            width_px=width_px,
            height_px=height_px,
            fx_px=f_px,
            fy_px=f_px,
            cx_px=(width_px - 1) / 2.0,
            cy_px=(height_px - 1) / 2.0,
            name=name,
        )

    def scaled(self, width_px: int, height_px: int) -> CameraModel:
        """The same camera with the image resized to ``width_px`` x ``height_px``.

        Focal lengths scale with the size ratio; the principal point scales about the image
        corner (-0.5, -0.5) so that pixel centres stay consistent. Distortion is unchanged;
        ``rms_px`` is scaled by the mean of the two ratios (an approximation).
        """
        sx = width_px / self.width_px
        sy = height_px / self.height_px
        return dataclasses.replace(
            self,
            width_px=width_px,
            height_px=height_px,
            fx_px=self.fx_px * sx,
            fy_px=self.fy_px * sy,
            cx_px=(self.cx_px + 0.5) * sx - 0.5,
            cy_px=(self.cy_px + 0.5) * sy - 0.5,
            rms_px=None if self.rms_px is None else self.rms_px * (sx + sy) / 2.0,
        )

    def project(self, p_cam_cv: ArrayLike) -> np.ndarray:
        """Project points in the OpenCV camera frame to pixels (with distortion).

        Args:
            p_cam_cv: (N, 3) points (m) in ``cam_cv``; a single (3,) point is also accepted.

        Returns:
            (N, 2) float64 pixels (u, v) ((2,) for a (3,) input). Points with z <= 0 (behind
            the camera) give nan. Points far outside the field of view of a strongly distorted
            model may fold back into the image: combine with a field-of-view test if needed.
        """
        p = np.asarray(p_cam_cv, dtype=np.float64)
        single = p.shape == (3,)
        p = p.reshape(1, 3) if single else p
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"p_cam_cv: expected shape (3,) or (N, 3), got {p.shape}")
        out = np.full((p.shape[0], 2), np.nan)
        ok = np.isfinite(p).all(axis=1) & (p[:, 2] > 0.0)
        if np.any(ok):
            px, _ = cv2.projectPoints(
                p[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist_coeffs
            )
            out[ok] = px.reshape(-1, 2)
        return out[0] if single else out

    def in_image(self, px: ArrayLike, margin_px: float = 0.0) -> np.ndarray:
        """Which pixels lie inside the image.

        Args:
            px: (N, 2) pixels (u, v), or a single (2,) pixel; nan counts as outside.
            margin_px: required distance from the image border (px).

        Returns:
            (N,) bool mask (0-d bool array for a (2,) input):
            ``-0.5 + m <= u < width - 0.5 - m`` and likewise for v.
        """
        uv = np.asarray(px, dtype=np.float64)
        if uv.shape[-1:] != (2,):
            raise ValueError(f"px: expected shape (2,) or (N, 2), got {uv.shape}")
        u, v = uv[..., 0], uv[..., 1]
        lo = -0.5 + margin_px
        with np.errstate(invalid="ignore"):
            return (
                (u >= lo)
                & (u < self.width_px - 0.5 - margin_px)
                & (v >= lo)
                & (v < self.height_px - 0.5 - margin_px)
            )


#: Fields of view (deg, pinhole, between the outer pixel edges) a camera file may state: outside,
#: the focal length does not belong to the image size (fx = 1e-9 px, a 180 deg pinhole).
MIN_FOV_DEG = 1.0
MAX_FOV_DEG = 179.0
#: Range of the radial distortion's scale ``r_d / r`` (distorted over undistorted normalised
#: radius) out to the image corners: a lens that shrinks or stretches its corner rays by more
#: than this is a wrong file (k1 = 1000 scales the reference camera's corners 271 times).
MIN_RADIAL_SCALE = 0.2
MAX_RADIAL_SCALE = 5.0
#: Largest pixel aspect ``fx / fy`` (and its inverse) a camera may state. Sensors have square
#: pixels (1.00 within a percent); the most anamorphic real imaging is a 2x squeeze lens or 2x1
#: binning (2:1), so 4:1 leaves room for any real optics while a 20:1 typo is refused.
MAX_PIXEL_ASPECT = 4.0
#: Largest tangential (decentring) distortion ``|p1|``, ``|p2|``. A decentred lens element or a
#: tilted flat port gives 1e-4 ... 1e-2; at 0.5 a ray at the image corner of a 90 deg camera
#: moves by over half its radius, which no lens does (p1 = 5 found markers whose poses the
#: solver then dropped without a word).
MAX_TANGENTIAL = 0.5
#: Largest |x|, |y| or |z| of the camera in the vehicle body frame (m): a vehicle is a few metres
#: long. ``calibration extrinsics set`` takes positions in this range and every reader of
#: ``T_body_cam`` refuses one beyond it (10^6 m put ``datasets synth``'s vehicle 997 km from the
#: station).
MAX_CAMERA_OFFSET_M = 100.0
#: Radii at which the radial distortion is sampled between the centre and the farthest corner.
_RADIAL_SAMPLES = 1024


def radial_distortion(cam: CameraModel, r: ArrayLike) -> np.ndarray:
    """The distorted normalised radius ``r_d`` of the undistorted normalised radius ``r``.

    OpenCV's radial terms only (tangential and thin-prism terms are small by construction):
    ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``.

    Args:
        cam: the camera model.
        r: undistorted normalised radii ``sqrt(x^2 + y^2)`` with ``x = X / Z`` (-), any shape.

    Returns:
        ``r_d`` of the same shape (-); NaN where the rational model's denominator is <= 0.
    """
    k = list(cam.dist) + [0.0] * (8 - min(len(cam.dist), 8))
    k1, k2, p1, p2, k3, k4, k5, k6 = k[:8]
    del p1, p2
    r = np.asarray(r, dtype=np.float64)
    r2 = r * r
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0.0, r * num / den, np.nan)


def corner_radius(cam: CameraModel) -> float:
    """The largest normalised pinhole radius of the four image corners (pixel edges) (-)."""
    u = np.array([-0.5, cam.width_px - 0.5])
    v = np.array([-0.5, cam.height_px - 0.5])
    x = (u - cam.cx_px) / cam.fx_px
    y = (v - cam.cy_px) / cam.fy_px
    return float(np.sqrt(np.max(x * x) + np.max(y * y)))


def check_plausible(cam: CameraModel) -> None:
    """Check that ``cam`` can be a physical camera (on top of :meth:`CameraModel.validate`).

    * the principal point lies inside the image (pixel edges: ``-0.5 <= cx <= width - 0.5``);
    * the focal lengths give a pinhole field of view of ``MIN_FOV_DEG`` ... ``MAX_FOV_DEG``
      across the image, horizontally (fx) and vertically (fy);
    * the pixel aspect ``fx / fy`` lies within 1 / ``MAX_PIXEL_ASPECT`` ... ``MAX_PIXEL_ASPECT``;
    * the tangential distortion ``|p1|``, ``|p2|`` is at most ``MAX_TANGENTIAL``;
    * the radial distortion is monotonic: the distorted radius grows strictly with the
      undistorted one from the centre out to the farthest image corner (taken at the corner's
      pinhole radius), and its scale ``r_d / r`` stays within ``MIN_RADIAL_SCALE`` ...
      ``MAX_RADIAL_SCALE`` there.

    Called by every reader of a camera (:func:`check_camera`: :func:`load_camera`, the imports
    of other tools' files, bags' camera_info, stereo files, error models, the vehicle node's
    camera_info), not by the constructor: a model built in code may be anything ``validate``
    allows.

    Raises:
        ValueError: one line naming the field and its value.
    """
    for key, size in (("cx_px", cam.width_px), ("cy_px", cam.height_px)):
        c = getattr(cam, key)
        if not -0.5 <= c <= size - 0.5:
            raise ValueError(
                f"{key}: the principal point must lie inside the image (-0.5 ... "
                f"{size - 0.5:g} px), got {c:g}"
            )
    for key, size, fov in (
        ("fx_px", cam.width_px, cam.hfov_deg),
        ("fy_px", cam.height_px, cam.vfov_deg),
    ):
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise ValueError(
                f"{key}: {getattr(cam, key):g} px gives a field of view of {fov:.4g} deg across "
                f"{size} px (a pinhole camera sees {MIN_FOV_DEG:g} ... {MAX_FOV_DEG:g} deg)"
            )
    aspect = cam.fx_px / cam.fy_px
    if not 1.0 / MAX_PIXEL_ASPECT <= aspect <= MAX_PIXEL_ASPECT:
        raise ValueError(
            f"fx_px / fy_px: the pixel aspect {cam.fx_px:g} / {cam.fy_px:g} = {aspect:.4g} is "
            f"outside 1/{MAX_PIXEL_ASPECT:g} ... {MAX_PIXEL_ASPECT:g} (pixels are square, "
            "anamorphic optics reach 2:1)"
        )
    for key, value in zip(("p1", "p2"), cam.dist[2:4], strict=True):
        if abs(value) > MAX_TANGENTIAL:
            raise ValueError(
                f"dist: tangential distortion {key} = {value:g} is beyond +-{MAX_TANGENTIAL:g} "
                "(decentred lenses and tilted ports give at most about 0.01)"
            )
    if not any(cam.dist):
        return
    r_max = corner_radius(cam)
    r = np.linspace(0.0, r_max, _RADIAL_SAMPLES + 1)
    r_d = radial_distortion(cam, r)
    shown = ", ".join(f"{d:g}" for d in cam.dist)
    step = np.diff(r_d)
    if not np.all(step > 0.0):  # NaN (a pole of the rational model) fails too
        k = int(np.argmax(~(step > 0.0)))  # the first step that does not grow
        raise ValueError(
            f"dist: ({shown}) is not monotonic over the image: the distorted radius stops "
            f"growing at normalised radius {r[k]:.3g} ({100 * r[k] / r_max:.0f} % of the way "
            "to the image corner)"
        )
    scale = r_d[1:] / r[1:]
    worst = int(np.argmax(np.abs(np.log(scale))))
    if not MIN_RADIAL_SCALE <= scale[worst] <= MAX_RADIAL_SCALE:
        raise ValueError(
            f"dist: ({shown}) scales the radius by {scale[worst]:.3g} at normalised radius "
            f"{r[worst + 1]:.3g} (a lens stays within {MIN_RADIAL_SCALE:g} ... "
            f"{MAX_RADIAL_SCALE:g} out to the image corners)"
        )


def check_T_body_cam(T_body_cam: ArrayLike, name: str = "T_body_cam") -> np.ndarray:
    """Check a camera mounting ``T_bodyfrd_camcv``: a rigid transform
    (:func:`calibration.frames.check_T`) whose translation lies within
    +-``MAX_CAMERA_OFFSET_M`` on each axis (the range ``calibration extrinsics set`` takes).

    Returns:
        A float64 (4, 4) copy.

    Raises:
        ValueError: one line naming ``name`` and the value.
    """
    T = check_T(T_body_cam, name)
    t = T[:3, 3]
    if np.any(np.abs(t) > MAX_CAMERA_OFFSET_M):
        shown = ", ".join(f"{v:g}" for v in t)
        raise ValueError(
            f"{name}: the camera is at ({shown}) m in the body frame; each of x, y, z must be "
            f"within +-{MAX_CAMERA_OFFSET_M:g} m (a vehicle is a few metres long)"
        )
    return T


def check_camera(
    cam: CameraModel, T_body_cam: ArrayLike | None = None
) -> tuple[CameraModel, np.ndarray | None]:
    """The one check of a camera read from anywhere (a camera file, another tool's file, a
    bag's or the wire's camera_info, a stereo file, an error model): its values
    (:meth:`CameraModel.validate`), that it can be a physical camera (:func:`check_plausible`:
    principal point, field of view, pixel aspect, tangential and radial distortion) and its
    mounting (:func:`check_T_body_cam`), when given.

    Returns:
        ``(cam, T_body_cam as a float64 copy or None)``.

    Raises:
        ValueError: one line naming the field and its value.
    """
    cam.validate()
    check_plausible(cam)
    return cam, None if T_body_cam is None else check_T_body_cam(T_body_cam)


def reference_camera() -> CameraModel:
    """The Girona AUV downward camera of the reference: 968 x 732 px, HFOV 55 deg, no distortion.

    f is about 929.7 px and the VFOV about 43.0 deg (docs/reference-system.md, section 3).
    """
    return CameraModel.from_hfov(968, 732, 55.0, name="girona_downward")


def _reference_extrinsics() -> np.ndarray:
    T = np.eye(4)
    # Columns: the cam_cv axes in body FRD. x_cv -> starboard, y_cv -> aft, z_cv -> down,
    # so the image top (-y_cv) points to the vehicle's forward.
    T[:3, :3] = np.column_stack([(0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)])
    T[:3, 3] = (0.535, 0.0, 0.45)
    T.setflags(write=False)
    return T


#: ``T_bodyfrd_camcv`` of the reference: camera at (0.535, 0, 0.45) m in body FRD, optical axis
#: straight down (+z body), image top toward the vehicle's forward. Read-only.
REFERENCE_T_BODYFRD_CAMCV = _reference_extrinsics()


# ---------------------------------------------------------------------------- camera file


def twin_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """(yaml_path, json_path) for a camera file path ending in .yaml, .yml or .json."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return path, path.with_suffix(".json")
    if suffix == ".json":
        return path.with_suffix(".yaml"), path
    raise DockError(f"camera file must end in .yaml, .yml or .json: {path}")


def filestorage_yaml_text(items: list[tuple[str, Any]]) -> str:
    """OpenCV FileStorage YAML of ``(key, value)`` pairs (ints, floats, strings, 2-D arrays),
    built in memory.

    Written to disk by the caller with a Python write (``dockcore.io.atomic_write_files``):
    FileStorage's own file writer does not report a failed write, so on a full disk it left an
    empty temporary file that the atomic rename then put over the user's camera file.
    """
    fs = cv2.FileStorage(
        "camera.yaml",
        cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML,
    )
    for key, value in items:
        fs.write(key, value)
    return fs.releaseAndGetString()


def save_camera(
    path: str | os.PathLike[str], cam: CameraModel, T_body_cam: ArrayLike | None = None
) -> tuple[Path, Path]:
    """Write a camera file as OpenCV YAML plus a JSON twin with the same stem, atomically.

    Args:
        path: ``<stem>.yaml`` (or ``.yml`` / ``.json``: the other twin gets the other suffix).
        cam: intrinsics (validated).
        T_body_cam: optional (4, 4) extrinsics ``T_bodyfrd_camcv`` (validated with check_T).

    Returns:
        (yaml_path, json_path) as written.

    Raises:
        ValueError: ``cam`` or ``T_body_cam`` is invalid.
        DockError: the path has an unsupported suffix, or a twin is not a regular file.
    """
    files = camera_file_bytes(path, cam, T_body_cam)
    # the twins as one unit: both new or both as they were (twins that disagree are refused)
    atomic_write_files(files)
    yaml_path, json_path = files
    return yaml_path, json_path


def camera_file_bytes(
    path: str | os.PathLike[str], cam: CameraModel, T_body_cam: ArrayLike | None = None
) -> dict[Path, bytes]:
    """What :func:`save_camera` writes: ``{yaml_path: bytes, json_path: bytes}``, for a caller
    that writes the twins in one unit with other files (``dockcore.io.atomic_write_files``).

    Raises:
        ValueError: ``cam`` or ``T_body_cam`` is invalid.
        DockError: the path has an unsupported suffix.
    """
    cam.validate()
    T = None if T_body_cam is None else check_T_body_cam(T_body_cam)  # as every reader checks
    yaml_path, json_path = twin_paths(path)

    items: list[tuple[str, Any]] = [
        ("format_version", CAMERA_FILE_VERSION),
        ("name", cam.name),
        ("image_width", int(cam.width_px)),
        ("image_height", int(cam.height_px)),
        ("camera_matrix", cam.K),
        ("distortion_coefficients", cam.dist_coeffs.reshape(1, -1)),
    ]
    if cam.rms_px is not None:
        items.append(("rms_px", float(cam.rms_px)))
    if T is not None:
        items.append(("T_body_cam", T))
    yaml_text = filestorage_yaml_text(items)

    doc: dict[str, Any] = {
        "format_version": CAMERA_FILE_VERSION,
        "name": cam.name,
        "image_width": int(cam.width_px),
        "image_height": int(cam.height_px),
        "camera_matrix": cam.K.tolist(),
        "distortion_coefficients": list(cam.dist),
    }
    if cam.rms_px is not None:
        doc["rms_px"] = float(cam.rms_px)
    if T is not None:
        doc["T_body_cam"] = T.tolist()
    return {
        yaml_path: yaml_text.encode("utf-8"),
        json_path: (json.dumps(doc, indent=2) + "\n").encode("utf-8"),
    }


def _one_line(exc: BaseException) -> str:
    """The exception text on one line, without OpenCV's "OpenCV(x) file.cpp:N: error: " prefix."""
    text = " ".join(str(exc).split())
    return text.split(" error: ", 1)[-1] if isinstance(exc, cv2.error) else text


def _node_value(node: Any) -> Any:
    """Python value of a FileStorage node: ndarray (opencv-matrix), str, float or list."""
    if node.isMap():
        return node.mat()
    if node.isString():
        return node.string()
    if node.isInt() or node.isReal():
        return node.real()
    if node.isSeq():
        return [_node_value(node.at(i)) for i in range(node.size())]
    return node  # unsupported type: reported by the key checks in _model_from_raw


def read_filestorage_yaml(path: Path) -> dict[str, Any]:
    """Raw key -> value (ndarray, float or str) of an OpenCV FileStorage YAML file."""
    text = read_text(path, "camera file")
    if not text.strip():
        raise DockError(f"malformed camera file {path}: the file is empty")
    try:
        with quiet_native_stderr():
            fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:
        cause = exc.__cause__ or exc.__context__ or exc
        raise DockError(f"malformed camera file {path}: {_one_line(cause)}") from None
    if not fs.isOpened():
        raise DockError(f"cannot read camera file {path}")
    raw: dict[str, Any] = {}
    try:
        root = fs.root()
        if not root.isMap():
            raise DockError(f"malformed camera file {path}: top level is not a mapping")
        for key in root.keys():
            try:
                raw[key] = _node_value(fs.getNode(key))
            except cv2.error as exc:
                raise DockError(f"{path}: key '{key}': {_one_line(exc)}") from None
    finally:
        fs.release()
    return raw


def _read_json(path: Path) -> dict[str, Any]:
    try:
        raw = json.loads(read_text(path, "camera file"))
    except json.JSONDecodeError as exc:
        raise DockError(f"malformed camera file {path}: {_one_line(exc)}") from None
    if not isinstance(raw, dict):
        raise DockError(f"malformed camera file {path}: top level is not an object")
    return raw


def raw_matrix(
    raw: dict[str, Any], key: str, path: Path, shape: tuple[int, ...] | None
) -> np.ndarray:
    """``raw[key]`` of a camera-like file as a finite float64 array of ``shape`` (any shape
    when None).

    Raises:
        DockError: one line naming ``path`` and ``key``: missing, not numeric, another shape,
            or non-finite.
    """
    if key not in raw:
        raise DockError(f"{path}: missing key '{key}'")
    value = raw[key]
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DockError(f"{path}: key '{key}' must be a numeric matrix") from None
    if shape is not None and arr.shape != shape:
        raise DockError(f"{path}: key '{key}' must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DockError(f"{path}: key '{key}' contains non-finite values")
    return arr


def raw_integer(raw: dict[str, Any], key: str, path: Path) -> int:
    """``raw[key]`` of a camera-like file as an int (an integral float is accepted).

    Raises:
        DockError: one line naming ``path`` and ``key``: missing or not an integer.
    """
    if key not in raw:
        raise DockError(f"{path}: missing key '{key}'")
    value = raw[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DockError(f"{path}: key '{key}' must be an integer, got {value!r}")
    if not float(value).is_integer():
        raise DockError(f"{path}: key '{key}' must be an integer, got {value!r}")
    return int(value)


def _model_from_raw(raw: dict[str, Any], path: Path) -> tuple[CameraModel, np.ndarray | None]:
    for key in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
        if key not in raw:
            raise DockError(f"{path}: missing key '{key}'")
    if "format_version" in raw:
        version = raw_integer(raw, "format_version", path)
        if version != CAMERA_FILE_VERSION:
            raise DockError(
                f"{path}: key 'format_version' is {version}, this toolkit reads "
                f"{CAMERA_FILE_VERSION}"
            )
    K = raw_matrix(raw, "camera_matrix", path, (3, 3))
    if K[0, 1] != 0.0 or K[1, 0] != 0.0 or not np.array_equal(K[2], (0.0, 0.0, 1.0)):
        raise DockError(f"{path}: key 'camera_matrix' must be [[fx,0,cx],[0,fy,cy],[0,0,1]]")
    dist = raw_matrix(raw, "distortion_coefficients", path, None).reshape(-1)
    rms = None
    if "rms_px" in raw:
        rms_value = raw["rms_px"]
        if isinstance(rms_value, bool) or not isinstance(rms_value, (int, float, type(None))):
            raise DockError(f"{path}: key 'rms_px' must be a number, got {rms_value!r}")
        rms = None if rms_value is None else float(rms_value)
    name = raw.get("name", "camera")
    if not isinstance(name, str):
        raise DockError(f"{path}: key 'name' must be a string, got {name!r}")
    try:
        cam = CameraModel(
            width_px=raw_integer(raw, "image_width", path),
            height_px=raw_integer(raw, "image_height", path),
            fx_px=float(K[0, 0]),
            fy_px=float(K[1, 1]),
            cx_px=float(K[0, 2]),
            cy_px=float(K[1, 2]),
            dist=tuple(float(d) for d in dist),
            rms_px=rms,
            name=name,
        )
        check_camera(cam)
    except ValueError as exc:
        raise DockError(f"{path}: {exc}") from None
    T = None
    if raw.get("T_body_cam") is not None:
        try:
            T = check_camera(cam, raw_matrix(raw, "T_body_cam", path, (4, 4)))[1]
        except ValueError as exc:
            raise DockError(f"{path}: key {exc}") from None
    return cam, T


def load_camera(path: str | os.PathLike[str]) -> tuple[CameraModel, np.ndarray | None]:
    """Read a camera file (``.yaml`` / ``.yml`` via cv2.FileStorage, or ``.json``).

    Args:
        path: the camera file.

    Returns:
        (camera model, ``T_bodyfrd_camcv`` (4, 4) or None when the file has no extrinsics).

    Raises:
        DockError: one line naming the file (and the key, where one is at fault) when the file
            is missing, unreadable or malformed, a required key is missing, a value is invalid
            or physically impossible (:func:`check_plausible`), or when its twin (the same stem
            with the other suffix, :func:`save_camera`) exists and is unusable or disagrees
            with it: a command that rewrites the camera would otherwise overwrite one of them
            silently.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".yaml", ".yml", ".json"):
        raise DockError(f"camera file must end in .yaml, .yml or .json: {path}")
    check_regular_file(path, "camera file")
    cam, T = _load_one(path)
    twin = twin_paths(path)[1 if suffix != ".json" else 0]
    if twin.exists():
        if not twin.is_file():
            raise DockError(f"{twin}, the twin of camera file {path}, is not a file")
        try:
            twin_cam, twin_T = _load_one(twin)
        except DockError as exc:
            raise DockError(
                f"the twin of camera file {path} is unusable ({' '.join(str(exc).split())}): "
                "fix or delete it"
            ) from None
        diff = _twin_difference((cam, T), (twin_cam, twin_T))
        if diff:
            raise DockError(
                f"camera file {path} and its twin {twin.name} disagree on {diff}: edit both "
                "the same way or delete the stale one (the toolkit writes both)"
            )
    return cam, T


def _load_one(path: Path) -> tuple[CameraModel, np.ndarray | None]:
    """One camera file, without its twin (:func:`load_camera`)."""
    try:
        raw = _read_json(path) if path.suffix.lower() == ".json" else read_filestorage_yaml(path)
    except OSError as exc:
        raise DockError(f"cannot read camera file {path}: {exc.strerror or exc}") from None
    return _model_from_raw(raw, path)


def _twin_difference(
    a: tuple[CameraModel, np.ndarray | None], b: tuple[CameraModel, np.ndarray | None]
) -> str | None:
    """The first field on which two twins' contents differ (``"fx_px (500 vs 501)"``), or None.

    Numbers agree within 1e-9 relative (both twins are written at full precision)."""
    (ca, Ta), (cb, Tb) = a, b
    for f in dataclasses.fields(CameraModel):
        va, vb = getattr(ca, f.name), getattr(cb, f.name)
        if isinstance(va, str) or va is None or vb is None:
            same = va == vb
        else:
            x, y = np.atleast_1d(np.asarray(va, float)), np.atleast_1d(np.asarray(vb, float))
            same = x.shape == y.shape and np.allclose(x, y, rtol=1e-9, atol=1e-12)
        if not same:
            return f"{f.name} ({_short(va)} vs {_short(vb)})"
    if (Ta is None) != (Tb is None):
        return "T_body_cam (present in one only)"
    if Ta is not None and not np.allclose(Ta, Tb, rtol=1e-9, atol=1e-12):
        return "T_body_cam"
    return None


def _short(value: Any) -> str:
    if isinstance(value, tuple):
        return "(" + ", ".join(f"{v:g}" for v in value) + ")"
    return f"{value:g}" if isinstance(value, float) else repr(value)


# ---------------------------------------------------------------------------- resolution


def scaled_to_width(cam: CameraModel, width_px: int) -> CameraModel:
    """``cam`` resized to ``width_px`` wide, the height keeping the aspect ratio (rounded).

    Args:
        cam: the camera model.
        width_px: the new width (px); 0 or ``cam.width_px`` returns ``cam`` unchanged.

    Returns:
        The scaled model (:meth:`CameraModel.scaled`).
    """
    if not width_px or int(width_px) == cam.width_px:
        return cam
    height_px = max(1, round(cam.height_px * int(width_px) / cam.width_px))
    return cam.scaled(int(width_px), height_px)


def resolve_camera(
    camera_file: str | os.PathLike[str] | None = None, width_px: int = 0
) -> tuple[CameraModel, np.ndarray]:
    """The one way to turn (camera file, width) into a camera and its mounting.

    Args:
        camera_file: camera YAML/JSON; None: :func:`reference_camera`.
        width_px: image width to scale the intrinsics to (:func:`scaled_to_width`); 0 keeps
            the file's (or the reference's) size.

    Returns:
        ``(camera, T_body_cam)``: the (scaled) model and the (4, 4) float64 extrinsics
        ``T_bodyfrd_camcv`` from the file, or ``REFERENCE_T_BODYFRD_CAMCV`` when the file has
        none or no file is given (a fresh, writable copy).

    Raises:
        DockError: the camera file is missing or malformed.
    """
    T_body_cam = None
    if camera_file is not None:
        cam, T_body_cam = load_camera(camera_file)
    else:
        cam = reference_camera()
    if T_body_cam is None:
        T_body_cam = REFERENCE_T_BODYFRD_CAMCV
    return scaled_to_width(cam, width_px), np.array(T_body_cam, dtype=np.float64)
