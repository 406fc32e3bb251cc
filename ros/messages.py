"""ROS 2 messages as ROS 2 Jazzy defines them, without a ROS installation.

The definitions, the CDR serialiser and the ``ros2msg`` schema text come from one place: the
ROS 2 Jazzy type store of ``rosbags`` (:func:`typestore`). A message is an instance of the type
store's dataclass for its type (``msg_class("geometry_msgs/msg/WrenchStamped")``); its wire
bytes are :func:`serialize`'s (the 4-byte CDR encapsulation header, little endian, then the
body), the same bytes a ROS 2 node's ``rmw`` hands to DDS and ``ros2 bag`` stores.

The builders below turn the toolkit's values into messages and back: times in integer
nanoseconds (``stamp_ns``), poses as (4, 4) ``T_a_b`` arrays, covariances as (6, 6) arrays in
the message's row-major order (x, y, z, rotation about x, y, z), images as OpenCV arrays.
Readers validate what they return (finite numbers, a unit quaternion) and raise ``ValueError``
with one line on anything else, so a hostile message never becomes a pose.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import cv2
import numpy as np

from uwdock.calibration.frames import R_from_quat_wxyz, quat_wxyz_from_R

__all__ = [
    "camera_info_msg",
    "clock_msg",
    "compressed_image_msg",
    "dds_type_name",
    "deserialize",
    "diagnostic_array_msg",
    "header_msg",
    "image_msg",
    "imu_msg",
    "msg_class",
    "msgdef",
    "odometry_msg",
    "pose_cov_stamped_msg",
    "serialize",
    "stamp_ns",
    "tf_message_msg",
    "type_hash",
    "typestore",
    "wrench_stamped_msg",
]


@functools.cache
def typestore() -> Any:
    """The ROS 2 Jazzy message definitions (``rosbags``' type store, built once)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


#: Largest time a ``builtin_interfaces/Time`` holds (int32 seconds).
_MAX_SEC = 2**31 - 1


def msg_class(typename: str) -> type:
    """The dataclass of a ROS 2 type (``"sensor_msgs/msg/Image"``).

    Raises:
        KeyError: a type the Jazzy store does not define.
    """
    return typestore().types[typename]


def serialize(msg: Any, typename: str) -> bytes:
    """The CDR bytes of ``msg`` (encapsulation header included), as ROS 2 sends them."""
    return bytes(typestore().serialize_cdr(msg, typename))


def deserialize(data: bytes | memoryview, typename: str) -> Any:
    """The message of CDR bytes (encapsulation header included).

    Raises:
        ValueError: bytes that are not a message of this type (truncated, garbage), one line.
    """
    try:
        return typestore().deserialize_cdr(bytes(data), typename)
    except Exception as exc:  # rosbags raises struct.error, IndexError, its own errors
        raise ValueError(
            f"not a {typename} message ({type(exc).__name__}: {' '.join(str(exc).split())[:80]})"
        ) from None


@functools.cache
def msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text of a type (its definition, then each nested one), as
    ``ros2 bag`` writes it into MCAP files."""
    return typestore().generate_msgdef(typename, ros_version=2)[0]


@functools.cache
def type_hash(typename: str) -> str:
    """The ROS 2 type hash (``RIHS01_<sha256>``) that Jazzy nodes advertise in USER_DATA."""
    return typestore().hash_rihs01(typename)


def dds_type_name(typename: str) -> str:
    """The DDS type name of a ROS 2 type: ``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_``."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


# --------------------------------------------------------------------------- time and header


def time_msg(stamp_ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` of a time in nanoseconds (0 ... 2^31 s)."""
    ns = int(stamp_ns)
    if not 0 <= ns <= _MAX_SEC * 1_000_000_000:
        raise ValueError(f"time {ns} ns is outside a ROS time (0 ... 2^31 s)")
    sec, nanosec = divmod(ns, 1_000_000_000)
    return msg_class("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def stamp_ns(msg: Any) -> int:
    """The time of a ``Time`` message, or of a message's ``header.stamp`` (ns).

    Raises:
        ValueError: a negative time or nanoseconds past one second.
    """
    t = msg.header.stamp if hasattr(msg, "header") else msg
    sec, nanosec = int(t.sec), int(t.nanosec)
    if sec < 0 or not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"invalid stamp {sec} s {nanosec} ns")
    return sec * 1_000_000_000 + nanosec


def header_msg(stamp_ns: int, frame_id: str) -> Any:
    """``std_msgs/msg/Header``."""
    return msg_class("std_msgs/msg/Header")(stamp=time_msg(stamp_ns), frame_id=str(frame_id))


def clock_msg(stamp_ns: int) -> Any:
    """``rosgraph_msgs/msg/Clock`` (the ``/clock`` topic of simulated time)."""
    return msg_class("rosgraph_msgs/msg/Clock")(clock=time_msg(stamp_ns))


# --------------------------------------------------------------------------- geometry


def _vector3(v: np.ndarray) -> Any:
    x, y, z = (float(a) for a in v)
    return msg_class("geometry_msgs/msg/Vector3")(x=x, y=y, z=z)


def vector3(msg: Any) -> np.ndarray:
    """(3,) of a ``Vector3`` / ``Point`` message, checked finite."""
    v = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError("vector holds NaN or infinity")
    return v


def _quaternion(R: np.ndarray) -> Any:
    w, x, y, z = (float(a) for a in quat_wxyz_from_R(R))
    return msg_class("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)


def rotation(q: Any, tolerance: float = 1e-3) -> np.ndarray:
    """(3, 3) rotation of a ``Quaternion`` message.

    Raises:
        ValueError: non-finite values or a norm off 1 by more than ``tolerance`` (a zero
            quaternion is not "no rotation": it is a bug upstream).
    """
    wxyz = np.array([q.w, q.x, q.y, q.z], dtype=np.float64)
    if not np.all(np.isfinite(wxyz)):
        raise ValueError("quaternion holds NaN or infinity")
    norm = float(np.linalg.norm(wxyz))
    if abs(norm - 1.0) > tolerance:
        raise ValueError(f"quaternion norm {norm:.4g} is not 1")
    return R_from_quat_wxyz(wxyz)


def pose_msg(T_a_b: np.ndarray) -> Any:
    """``geometry_msgs/msg/Pose`` of ``T_a_b`` (frame b in frame a)."""
    T = np.asarray(T_a_b, dtype=np.float64)
    x, y, z = (float(a) for a in T[:3, 3])
    return msg_class("geometry_msgs/msg/Pose")(
        position=msg_class("geometry_msgs/msg/Point")(x=x, y=y, z=z),
        orientation=_quaternion(T[:3, :3]),
    )


def pose_T(pose: Any) -> np.ndarray:
    """(4, 4) ``T_a_b`` of a ``Pose`` message (``ValueError`` on a bad one)."""
    T = np.eye(4)
    T[:3, :3] = rotation(pose.orientation)
    T[:3, 3] = vector3(pose.position)
    return T


def _cov36(cov6: np.ndarray | None) -> np.ndarray:
    if cov6 is None:
        return np.zeros(36)
    c = np.asarray(cov6, dtype=np.float64)
    if c.shape != (6, 6):
        raise ValueError(f"covariance must be (6, 6), got {c.shape}")
    return c.reshape(36).copy()


def covariance6(flat: Any) -> np.ndarray:
    """(6, 6) of a message's 36-value covariance, checked finite and symmetric."""
    c = np.asarray(flat, dtype=np.float64).reshape(6, 6)
    if not np.all(np.isfinite(c)):
        raise ValueError("covariance holds NaN or infinity")
    if not np.allclose(c, c.T, rtol=1e-6, atol=1e-12):
        raise ValueError("covariance is not symmetric")
    return c


def pose_cov_stamped_msg(
    T_a_b: np.ndarray, cov6: np.ndarray | None, stamp_ns: int, frame_id: str
) -> Any:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` of ``T_a_b`` in ``frame_id`` (a)."""
    cls = msg_class("geometry_msgs/msg/PoseWithCovariance")
    return msg_class("geometry_msgs/msg/PoseWithCovarianceStamped")(
        header=header_msg(stamp_ns, frame_id),
        pose=cls(pose=pose_msg(T_a_b), covariance=_cov36(cov6)),
    )


def wrench_stamped_msg(wrench_6: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """``geometry_msgs/msg/WrenchStamped``: (6,) [Fx, Fy, Fz (N), Mx, My, Mz (N m)]."""
    w = np.asarray(wrench_6, dtype=np.float64)
    return msg_class("geometry_msgs/msg/WrenchStamped")(
        header=header_msg(stamp_ns, frame_id),
        wrench=msg_class("geometry_msgs/msg/Wrench")(force=_vector3(w[:3]), torque=_vector3(w[3:])),
    )


def wrench6(msg: Any) -> np.ndarray:
    """(6,) of a ``WrenchStamped`` (``ValueError`` on non-finite values)."""
    return np.concatenate([vector3(msg.wrench.force), vector3(msg.wrench.torque)])


def twist_stamped_msg(v_3: np.ndarray, w_3: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """``geometry_msgs/msg/TwistStamped`` (linear m/s, angular rad/s)."""
    return msg_class("geometry_msgs/msg/TwistStamped")(
        header=header_msg(stamp_ns, frame_id),
        twist=msg_class("geometry_msgs/msg/Twist")(linear=_vector3(v_3), angular=_vector3(w_3)),
    )


def odometry_msg(
    T_world_body: np.ndarray,
    velocity_body_mps: np.ndarray,
    angular_velocity_body_radps: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    child_frame_id: str,
    pose_cov6: np.ndarray | None = None,
    twist_cov6: np.ndarray | None = None,
) -> Any:
    """``nav_msgs/msg/Odometry``: the pose in ``frame_id``, the twist in ``child_frame_id``
    (the body), as REP 105 and COLA2's navigator publish it."""
    twist = msg_class("geometry_msgs/msg/Twist")(
        linear=_vector3(velocity_body_mps), angular=_vector3(angular_velocity_body_radps)
    )
    return msg_class("nav_msgs/msg/Odometry")(
        header=header_msg(stamp_ns, frame_id),
        child_frame_id=str(child_frame_id),
        pose=msg_class("geometry_msgs/msg/PoseWithCovariance")(
            pose=pose_msg(T_world_body), covariance=_cov36(pose_cov6)
        ),
        twist=msg_class("geometry_msgs/msg/TwistWithCovariance")(
            twist=twist, covariance=_cov36(twist_cov6)
        ),
    )


def imu_msg(
    R_world_body: np.ndarray,
    angular_velocity_body_radps: np.ndarray,
    linear_acceleration_body_mps2: np.ndarray,
    stamp_ns: int,
    frame_id: str,
) -> Any:
    """``sensor_msgs/msg/Imu`` (covariances unknown: zeros, as many drivers send)."""
    zeros9 = np.zeros(9)
    return msg_class("sensor_msgs/msg/Imu")(
        header=header_msg(stamp_ns, frame_id),
        orientation=_quaternion(np.asarray(R_world_body, dtype=np.float64)),
        orientation_covariance=zeros9,
        angular_velocity=_vector3(angular_velocity_body_radps),
        angular_velocity_covariance=zeros9.copy(),
        linear_acceleration=_vector3(linear_acceleration_body_mps2),
        linear_acceleration_covariance=zeros9.copy(),
    )


def accel_stamped_msg(acceleration_body_mps2: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """``geometry_msgs/msg/AccelWithCovarianceStamped`` of a gravity-free linear acceleration
    in the body frame (the angular part zero), as ``robot_localization`` publishes its
    ``accel/filtered``."""
    accel = msg_class("geometry_msgs/msg/Accel")(
        linear=_vector3(acceleration_body_mps2), angular=_vector3(np.zeros(3))
    )
    return msg_class("geometry_msgs/msg/AccelWithCovarianceStamped")(
        header=header_msg(stamp_ns, frame_id),
        accel=msg_class("geometry_msgs/msg/AccelWithCovariance")(
            accel=accel, covariance=np.zeros(36)
        ),
    )


def tf_message_msg(transforms: list[tuple[np.ndarray, str, str, int]]) -> Any:
    """``tf2_msgs/msg/TFMessage`` of ``(T_parent_child, parent, child, stamp_ns)`` entries."""
    out = []
    for T, parent, child, stamp in transforms:
        T = np.asarray(T, dtype=np.float64)
        x, y, z = (float(a) for a in T[:3, 3])
        tf = msg_class("geometry_msgs/msg/Transform")(
            translation=msg_class("geometry_msgs/msg/Vector3")(x=x, y=y, z=z),
            rotation=_quaternion(T[:3, :3]),
        )
        out.append(
            msg_class("geometry_msgs/msg/TransformStamped")(
                header=header_msg(stamp, parent), child_frame_id=str(child), transform=tf
            )
        )
    return msg_class("tf2_msgs/msg/TFMessage")(transforms=out)


# --------------------------------------------------------------------------- images


def image_msg(img: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "bgr8") -> Any:
    """``sensor_msgs/msg/Image`` of an 8-bit image: (H, W, 3) in ``encoding``'s channel
    order (``bgr8`` / ``rgb8``) or (H, W) ``mono8``."""
    a = np.ascontiguousarray(img)
    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise ValueError(f"image must be 8-bit (H, W) or (H, W, 3), got {a.dtype} {a.shape}")
    channels = 1 if a.ndim == 2 else a.shape[2]
    want = {"mono8": 1, "bgr8": 3, "rgb8": 3}
    if want.get(encoding) != channels:
        raise ValueError(f"encoding {encoding!r} does not fit an image of {channels} channels")
    h, w = a.shape[:2]
    return msg_class("sensor_msgs/msg/Image")(
        header=header_msg(stamp_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * channels,
        data=a.reshape(-1),
    )


def compressed_image_msg(
    img_bgr: np.ndarray, stamp_ns: int, frame_id: str, jpeg_quality: int = 90
) -> Any:
    """``sensor_msgs/msg/CompressedImage`` (JPEG) of a BGR or grey 8-bit image."""
    ok, buf = cv2.imencode(".jpg", img_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise ValueError("the image cannot be encoded as JPEG")
    return msg_class("sensor_msgs/msg/CompressedImage")(
        header=header_msg(stamp_ns, frame_id),
        format="bgr8; jpeg compressed bgr8" if np.ndim(img_bgr) == 3 else "mono8; jpeg",
        data=buf.reshape(-1),
    )


def camera_info_msg(
    K: np.ndarray, dist: tuple[float, ...], width_px: int, height_px: int, stamp_ns: int, frame: str
) -> Any:
    """``sensor_msgs/msg/CameraInfo`` of a pinhole camera with OpenCV distortion
    (``plumb_bob`` for 5 coefficients or fewer, ``rational_polynomial`` for 8)."""
    d = np.asarray(dist, dtype=np.float64).ravel()
    model = "plumb_bob" if d.size <= 5 else "rational_polynomial"
    K = np.asarray(K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return msg_class("sensor_msgs/msg/CameraInfo")(
        header=header_msg(stamp_ns, frame),
        height=int(height_px),
        width=int(width_px),
        distortion_model=model,
        d=d,
        k=K.reshape(9).copy(),
        r=np.eye(3).reshape(9),
        p=P.reshape(12),
        binning_x=0,
        binning_y=0,
        roi=msg_class("sensor_msgs/msg/RegionOfInterest")(
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


# --------------------------------------------------------------------------- diagnostics

#: ``diagnostic_msgs/DiagnosticStatus`` levels.
DIAG_OK, DIAG_WARN, DIAG_ERROR, DIAG_STALE = 0, 1, 2, 3


def diagnostic_array_msg(
    stamp_ns: int, statuses: list[tuple[int, str, str, str, dict[str, str]]]
) -> Any:
    """``diagnostic_msgs/msg/DiagnosticArray`` of ``(level, name, message, hardware_id,
    {key: value})`` entries."""
    kv = msg_class("diagnostic_msgs/msg/KeyValue")
    status = msg_class("diagnostic_msgs/msg/DiagnosticStatus")
    return msg_class("diagnostic_msgs/msg/DiagnosticArray")(
        header=header_msg(stamp_ns, ""),
        status=[
            status(
                level=int(level),
                name=name,
                message=message,
                hardware_id=hw,
                values=[kv(key=k, value=str(v)) for k, v in values.items()],
            )
            for level, name, message, hw, values in statuses
        ],
    )


def diagnostic_values(msg: Any, index: int = 0) -> dict[str, str]:
    """The key/value pairs of one status of a ``DiagnosticArray``."""
    return {kv.key: kv.value for kv in msg.status[index].values}


def finite_or_nan(x: float) -> float:
    """``x`` as a float, NaN for anything that is not a finite number."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v if math.isfinite(v) else math.nan
