"""What the node reads off the wire, checked and in the toolkit's frames.

Each reader takes a ROS 2 message (a ``rosbags`` dataclass: from DDS or from a bag, the same
objects) and returns the values the docking chain uses, in the toolkit's axes (NED world, FRD
body: :mod:`uwdock.ros.conventions` converts from ``axes = "enu"``), or raises ``ValueError``
with one line saying what is wrong (NaN, infinity, a quaternion that is not one, a negative
variance, a position further than ``MAX_RANGE_M`` from the world origin, a frame that does not
decode). The node counts and logs the refusal and holds; it never exits on a message.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from uwdock.calibration.camera import CameraModel, check_camera
from uwdock.dockcore.bags import decode_image_msg
from uwdock.dockcore.errors import DockError
from uwdock.ros import conventions as conv
from uwdock.ros import messages as rm

__all__ = [
    "MAX_RANGE_M",
    "NavSample",
    "read_accel",
    "read_camera_info",
    "read_ds_prior",
    "read_image",
    "read_imu",
    "read_odometry",
    "read_usbl",
]

#: Largest distance from the navigation's origin that a position may have (m): a docking
#: mission's local frame spans kilometres at most; beyond that a value is a unit or frame bug.
MAX_RANGE_M = 100_000.0
#: Largest speed (m/s), rate (rad/s) and acceleration (m/s^2) an AUV's navigation may report.
MAX_SPEED_MPS = 20.0
MAX_RATE_RADPS = 20.0
MAX_ACCEL_MPS2 = 1000.0
#: Largest standard deviation a fix or prior may carry (m).
MAX_SIGMA_M = 10_000.0


@dataclass(frozen=True)
class NavSample:
    """One navigation solution in the toolkit's frames.

    Attributes:
        stamp_ns: its header stamp (ns).
        T_world_body: (4, 4) body FRD pose in the NED world.
        velocity_frd_mps: (3,) body velocity (the DVL's).
        angular_velocity_frd_radps: (3,) body rates (the gyro's).
    """

    stamp_ns: int
    T_world_body: np.ndarray
    velocity_frd_mps: np.ndarray
    angular_velocity_frd_radps: np.ndarray


def _bounded(v: np.ndarray, limit: float, what: str) -> np.ndarray:
    if float(np.max(np.abs(v))) > limit:
        raise ValueError(f"{what} {np.round(v, 3).tolist()} is out of range (|x| <= {limit:g})")
    return v


def read_odometry(msg: Any, axes: conv.Convention) -> NavSample:
    """``nav_msgs/Odometry`` -> :class:`NavSample` (pose in the world, twist in the body)."""
    T_wire = rm.pose_T(msg.pose.pose)
    _bounded(T_wire[:3, 3], MAX_RANGE_M, "position")
    v = _bounded(rm.vector3(msg.twist.twist.linear), MAX_SPEED_MPS, "velocity")
    w = _bounded(rm.vector3(msg.twist.twist.angular), MAX_RATE_RADPS, "angular velocity")
    return NavSample(
        rm.stamp_ns(msg),
        conv.pose_from_wire(T_wire, axes),
        conv.body_vector_from_wire(v, axes),
        conv.body_vector_from_wire(w, axes),
    )


def read_imu(msg: Any, axes: conv.Convention) -> np.ndarray:
    """``sensor_msgs/Imu`` -> (3,) specific force in FRD (m/s^2, gravity included)."""
    a = _bounded(rm.vector3(msg.linear_acceleration), MAX_ACCEL_MPS2, "linear acceleration")
    return conv.body_vector_from_wire(a, axes)


def read_accel(msg: Any, axes: conv.Convention) -> np.ndarray:
    """``geometry_msgs/AccelWithCovarianceStamped`` -> (3,) gravity-free body acceleration."""
    a = _bounded(rm.vector3(msg.accel.accel.linear), MAX_ACCEL_MPS2, "linear acceleration")
    return conv.body_vector_from_wire(a, axes)


def _variances(cov6: np.ndarray, idx: list[int], what: str) -> np.ndarray:
    var = np.array([cov6[i, i] for i in idx])
    if np.any(var < 0):
        raise ValueError(f"{what} covariance has a negative variance {var.tolist()}")
    if np.any(var > MAX_SIGMA_M**2):
        raise ValueError(f"{what} standard deviation is out of range (> {MAX_SIGMA_M:g})")
    return var


def read_usbl(msg: Any, axes: conv.Convention) -> tuple[np.ndarray, float]:
    """``PoseWithCovarianceStamped`` fix -> ((3,) DS position in the NED world (m), its
    variance on each axis (m^2): the largest of x, y, z, so the filter is never told more
    than the fix says)."""
    p = _bounded(rm.vector3(msg.pose.pose.position), MAX_RANGE_M, "USBL position")
    cov = conv.covariance_from_wire(rm.covariance6(msg.pose.covariance), axes, body=False)
    var = _variances(cov, [0, 1, 2], "USBL")
    if float(var.max()) <= 0:
        raise ValueError("USBL fix has no variance (a fix is never exact)")
    return conv.world_vector_from_wire(p, axes), float(var.max())


def read_ds_prior(msg: Any, axes: conv.Convention) -> tuple[np.ndarray, np.ndarray]:
    """``PoseWithCovarianceStamped`` -> ((4, 4) ``T_world_ds`` in NED, (4,) variances of x,
    y, z (m^2) and yaw (rad^2)); a zero variance takes the filter's configured prior."""
    T = conv.frame_pose_from_wire(rm.pose_T(msg.pose.pose), axes)
    _bounded(T[:3, 3], MAX_RANGE_M, "DS position")
    cov = conv.covariance_from_wire(rm.covariance6(msg.pose.covariance), axes, body=False)
    var = _variances(cov, [0, 1, 2, 5], "DS prior")
    return T, var


def read_image(msg: Any) -> np.ndarray:
    """``Image`` / ``CompressedImage`` -> an 8-bit BGR or grey image.

    Raises:
        ValueError: an image that does not decode, an encoding the toolkit does not read, a
            16-bit or float image (the detector's frames are 8-bit here).
    """
    try:
        img = decode_image_msg(msg, "image")
    except DockError as exc:
        raise ValueError(str(exc)) from None
    if img is None:
        raise ValueError("image data does not decode (truncated or damaged)")
    if img.dtype != np.uint8:
        img = (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else None
        if img is None:
            raise ValueError("image is neither 8- nor 16-bit")
    return img


def read_camera_info(msg: Any) -> CameraModel:
    """``CameraInfo`` -> the camera model (K and distortion; validated)."""
    k_raw = msg.k if hasattr(msg, "k") else msg.K  # ROS 2 / ROS 1 field names
    d_raw = msg.d if hasattr(msg, "d") else msg.D
    k = np.asarray(k_raw, dtype=np.float64).reshape(3, 3)
    d = tuple(float(v) for v in np.asarray(d_raw, dtype=np.float64).ravel())
    if not np.all(np.isfinite(k)) or not all(np.isfinite(d)):
        raise ValueError("camera_info holds NaN or infinity")
    if len(d) not in (0, 4, 5, 8, 12, 14):
        raise ValueError(f"camera_info has {len(d)} distortion coefficients")
    try:
        cam = CameraModel(
            width_px=int(msg.width),
            height_px=int(msg.height),
            fx_px=float(k[0, 0]),
            fy_px=float(k[1, 1]),
            cx_px=float(k[0, 2]),
            cy_px=float(k[1, 2]),
            dist=d or (0.0, 0.0, 0.0, 0.0, 0.0),
            name="camera_info",
        )
        check_camera(cam)  # the check of every camera the toolkit reads
    except ValueError as exc:
        raise ValueError(f"camera_info: {exc}") from None
    return cam
