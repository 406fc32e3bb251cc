"""Which DS markers a camera sees: the one geometric in-view test shared by sim, perception, rl.

A marker is *in view* when all four of its corners are in front of the camera (``z`` in the
OpenCV camera frame above ``min_depth_m``) and project, with the camera's lens distortion, inside
the image (OpenCV's pixel convention: ``-0.5 <= u < width - 0.5``, likewise for v). Occlusion is
not tested here (the renderer's range image does that, :func:`uwdock.sim.render.project_markers`).

Example:
    >>> mask = markers_in_view(camera, T_cam_ds, corners_ds)   # (M,) bool
    >>> n_in_view = int(mask.sum())
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import CameraModel

__all__ = ["markers_in_view", "project_corners"]


def project_corners(
    camera: CameraModel, T_cam_ds: ArrayLike, corners_ds: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Project marker corners given in the DS frame into the image.

    Args:
        camera: intrinsics and distortion.
        T_cam_ds: (4, 4) float64 DS pose in the OpenCV camera frame (m).
        corners_ds: (M, 4, 3) corners in the DS frame (m) (``MarkerSet.corners_ds()`` stacked).

    Returns:
        ``(px, z_m)``: (M, 4, 2) float64 pixels (u, v) with distortion (nan behind the camera)
        and (M, 4) float64 depths ``z`` of the corners in the camera frame (m).
    """
    T = np.asarray(T_cam_ds, dtype=np.float64)
    c = np.asarray(corners_ds, dtype=np.float64)
    if c.ndim != 3 or c.shape[1:] != (4, 3):
        raise ValueError(f"corners_ds: expected shape (M, 4, 3), got {c.shape}")
    p = c.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    if any(camera.dist):
        px = camera.project(p)
    else:  # the pinhole formula, what projectPoints computes without distortion (faster)
        px = np.full((p.shape[0], 2), np.nan)
        ok = np.isfinite(p).all(axis=1) & (z > 0.0)
        px[ok, 0] = camera.fx_px * p[ok, 0] / z[ok] + camera.cx_px
        px[ok, 1] = camera.fy_px * p[ok, 1] / z[ok] + camera.cy_px
    return px.reshape(-1, 4, 2), z.reshape(-1, 4)


def markers_in_view(
    camera: CameraModel,
    T_cam_ds: ArrayLike,
    corners_ds: ArrayLike,
    min_depth_m: float = 0.0,
) -> np.ndarray:
    """Which markers have all four corners in front of the camera and inside the image.

    Args:
        camera: intrinsics and distortion (distortion applied).
        T_cam_ds: (4, 4) float64 DS pose in the OpenCV camera frame (m).
        corners_ds: (M, 4, 3) corners in the DS frame (m).
        min_depth_m: a corner counts as in front when its camera-frame ``z`` exceeds this (m).

    Returns:
        (M,) bool mask, in the order of ``corners_ds``.
    """
    px, z = project_corners(camera, T_cam_ds, corners_ds)
    inside = camera.in_image(px.reshape(-1, 2)).reshape(z.shape)
    return np.all(inside & (z > min_depth_m), axis=1)
