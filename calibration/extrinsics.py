"""Camera extrinsics ``T_body_cam`` (``T_bodyfrd_camcv``) in camera files, and the reference camera.

``T_body_cam`` is the OpenCV camera frame (x right, y down, z optical axis) expressed in the
vehicle body frame (FRD: x forward, y starboard, z down), metres. People give it as a position
and roll, pitch, yaw:

    xyz_m:   the camera's optical centre in body FRD (m).
    rpy_deg: the rotation ``R_body_cam = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (Fossen ZYX, as
             :func:`calibration.frames.R_from_rpy`), i.e. the cam_cv axes expressed in body FRD.

With rpy = (0, 0, 0) the cam_cv axes coincide with FRD: the optical axis (z_cv) points down,
the image's x (right) points forward and the image's y (down) points to starboard. The reference
downward camera has rpy = (0, 0, 90) deg: image right to starboard, image top to forward.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import (
    REFERENCE_T_BODYFRD_CAMCV,
    check_T_body_cam,
    load_camera,
    resolve_camera,
    save_camera,
    scaled_to_width,
)
from uwdock.calibration.frames import R_from_rpy, check_T, make_T, rpy_from_R
from uwdock.dockcore.errors import DockError

__all__ = [
    "REFERENCE_RPY_DEG",
    "T_body_cam_from_xyz_rpy",
    "format_extrinsics",
    "read_extrinsics",
    "write_extrinsics",
    "write_reference_camera",
    "xyz_rpy_from_T_body_cam",
]

#: Roll, pitch, yaw (deg) of the reference downward camera (``REFERENCE_T_BODYFRD_CAMCV``).
REFERENCE_RPY_DEG = (0.0, 0.0, 90.0)


def T_body_cam_from_xyz_rpy(xyz_m: ArrayLike, rpy_deg: ArrayLike) -> np.ndarray:
    """``T_bodyfrd_camcv`` from the camera position (m) and roll, pitch, yaw (deg), ZYX.

    Args:
        xyz_m: (3,) optical centre in body FRD (m).
        rpy_deg: (3,) roll, pitch, yaw (deg) of cam_cv relative to body FRD.

    Returns:
        (4, 4) float64 ``T_body_cam``.
    """
    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1)
    rpy = np.asarray(rpy_deg, dtype=np.float64).reshape(-1)
    if xyz.shape != (3,) or rpy.shape != (3,):
        raise DockError(f"need 3 values for xyz and for rpy, got {xyz.size} and {rpy.size}")
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(rpy))):
        raise DockError("xyz and rpy must be finite numbers")
    return make_T(R_from_rpy(*np.radians(rpy)), xyz)


def xyz_rpy_from_T_body_cam(T_body_cam: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`T_body_cam_from_xyz_rpy`: ((3,) xyz_m, (3,) rpy_deg)."""
    T = check_T(T_body_cam, "T_body_cam")
    return T[:3, 3].copy(), np.degrees(np.array(rpy_from_R(T[:3, :3])))


def read_extrinsics(path: str | os.PathLike[str]) -> tuple[np.ndarray, bool]:
    """``T_body_cam`` of a camera file, or the reference default when the file has none.

    Returns:
        ((4, 4) ``T_body_cam``, True when it came from the file).

    Raises:
        DockError: the camera file is missing or malformed.
    """
    _, T = load_camera(path)
    if T is None:
        return np.array(REFERENCE_T_BODYFRD_CAMCV), False
    return T, True


def write_extrinsics(path: str | os.PathLike[str], T_body_cam: ArrayLike) -> tuple[Path, Path]:
    """Store ``T_body_cam`` in an existing camera file (both twins rewritten, intrinsics kept).

    Returns:
        (yaml_path, json_path).

    Raises:
        DockError: the camera file is missing or malformed, or ``T_body_cam`` is not a rigid
            transform.
    """
    cam, _ = load_camera(path)
    try:
        T = check_T_body_cam(T_body_cam)
    except ValueError as exc:
        raise DockError(str(exc)) from None
    return save_camera(path, cam, T)


def write_reference_camera(
    path: str | os.PathLike[str],
    width_px: int | None = None,
    height_px: int | None = None,
) -> tuple[Path, Path]:
    """Write the reference camera (968 x 732 px, 55 deg HFOV) with the reference ``T_body_cam``.

    Args:
        path: camera file (``.yaml`` / ``.yml`` / ``.json``; both twins are written).
        width_px: image width (px); None: 968, or from ``height_px`` keeping the aspect ratio.
        height_px: image height (px); None: 732, or from ``width_px`` keeping the aspect ratio.

    Returns:
        (yaml_path, json_path).
    """
    cam, T_body_cam = resolve_camera()
    if width_px is not None or height_px is not None:
        w = width_px if width_px is not None else round(height_px * cam.width_px / cam.height_px)
        h = height_px if height_px is not None else round(width_px * cam.height_px / cam.width_px)
        if w <= 0 or h <= 0:
            raise DockError(f"image size must be positive, got {w} x {h}")
        if height_px is None:
            cam = scaled_to_width(cam, int(w))  # the world's and the runner's resolution
        else:
            cam = cam.scaled(int(w), int(h))
    return save_camera(path, cam, T_body_cam)


def format_extrinsics(T_body_cam: ArrayLike, source: str, as_json: bool = False) -> str:
    """Human (or JSON) text of ``T_body_cam``: xyz (m), rpy (deg, ZYX) and the matrix."""
    T = check_T(T_body_cam, "T_body_cam")
    xyz, rpy = xyz_rpy_from_T_body_cam(T)
    rpy = np.where(np.abs(rpy) < 5e-7, 0.0, rpy)  # no "-0.000000"
    xyz = np.where(np.abs(xyz) < 5e-10, 0.0, xyz)
    if as_json:
        doc = {
            "source": source,
            "xyz_m": xyz.tolist(),
            "rpy_deg": rpy.tolist(),
            "T_body_cam": T.tolist(),
        }
        return json.dumps(doc, indent=2)
    shown = np.where(np.abs(T) < 5e-13, 0.0, T)
    rows = "\n".join("  [" + " ".join(f"{v: .9f}" for v in row) + "]" for row in shown)
    return (
        f"T_body_cam (camera cv frame in body FRD), {source}\n"
        f"xyz_m   {xyz[0]:.6f} {xyz[1]:.6f} {xyz[2]:.6f}\n"
        f"rpy_deg {rpy[0]:.6f} {rpy[1]:.6f} {rpy[2]:.6f}\n"
        f"{rows}"
    )
