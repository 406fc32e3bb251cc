"""The docking chain's messages: which topics it reads (and of what type), how each message
reaches the chain, and the messages a tick publishes. Shared by the live node (DDS) and the
replay of a recording (a bag), so both read and write exactly the same things.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwdock.rl.deploy.chain import DockingChain, Tick
from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.inputs import (
    read_accel,
    read_camera_info,
    read_ds_prior,
    read_image,
    read_imu,
    read_odometry,
    read_usbl,
)
from uwdock.ros import conventions as conv
from uwdock.ros import messages as rm
from uwdock.ros.qos import QosProfile

__all__ = [
    "Dispatcher",
    "InputTopic",
    "input_topics",
    "output_types",
    "steady_velocity",
    "tick_messages",
]

#: the ROS 2 type of each output (``NodeTopics`` field -> type)
OUTPUT_TYPES = {
    "ds_pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "ds_estimate": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "command": "geometry_msgs/msg/WrenchStamped",
    "velocity_command": "geometry_msgs/msg/TwistStamped",
    "tf": "tf2_msgs/msg/TFMessage",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


@dataclass(frozen=True)
class InputTopic:
    """One input: its kind (a ``NodeTopics`` field), ROS 2 type and QoS."""

    kind: str
    typename: str
    qos: QosProfile


def input_topics(cfg: NodeConfig, sim_clock: bool = False) -> dict[str, InputTopic]:
    """Topic name -> :class:`InputTopic` of every input the config turns on (``clock`` only
    with ``sim_clock``; every QoS reliable then: lock-step needs every sample)."""
    t, q = cfg.topics, cfg.qos
    image_type = (
        "sensor_msgs/msg/CompressedImage"
        if t.image_format == "compressed"
        else "sensor_msgs/msg/Image"
    )
    table = [
        ("image", image_type, q.image),
        ("camera_info", "sensor_msgs/msg/CameraInfo", q.camera_info),
        ("odometry", "nav_msgs/msg/Odometry", q.navigation),
        ("imu", "sensor_msgs/msg/Imu", q.navigation),
        ("accel", "geometry_msgs/msg/AccelWithCovarianceStamped", q.navigation),
        ("usbl", "geometry_msgs/msg/PoseWithCovarianceStamped", q.usbl),
        ("ds_prior", "geometry_msgs/msg/PoseWithCovarianceStamped", q.mission),
        ("enable", "std_msgs/msg/Bool", q.mission),
        ("abort", "std_msgs/msg/Empty", q.mission),
    ]
    if sim_clock:
        table.append(("clock", "rosgraph_msgs/msg/Clock", q.clock))
    out = {}
    for kind, typename, qos in table:
        name = getattr(t, kind)
        if not name:
            continue
        if sim_clock:
            qos = QosProfile("reliable", max(qos.depth, 4), qos.durability)
        out[name] = InputTopic(kind, typename, qos)
    return out


def output_types(cfg: NodeConfig) -> dict[str, tuple[str, str]]:
    """Output kind -> (topic, ROS 2 type) for the outputs the config turns on."""
    return {
        k: (getattr(cfg.topics, k), ty) for k, ty in OUTPUT_TYPES.items() if getattr(cfg.topics, k)
    }


class Dispatcher:
    """Hands each input message to the chain, read and checked (:mod:`rl.deploy.inputs`);
    a message that cannot be read is refused (counted, logged, held on), never raised.

    Args:
        chain: the docking chain.
        cfg: the node's settings (topics, axes).
        camera_file_given: intrinsics came from a camera file, so ``camera_info`` is only
            recorded, not used.
        check_future: refuse messages stamped ``safety.max_future_s`` ahead of the node's
            clock (clocks out of step); off on simulated time, where the vehicle's sensors
            for a step arrive before ``/clock`` moves to it.
    """

    def __init__(
        self,
        chain: DockingChain,
        cfg: NodeConfig,
        camera_file_given: bool,
        check_future: bool = True,
    ) -> None:
        self.chain, self.cfg = chain, cfg
        self.check_future = check_future
        self.use_camera_info = not camera_file_given
        self.clock_ns: int | None = None
        self._handlers: dict[str, Callable[[Any, int], None]] = {
            "image": self._image,
            "camera_info": self._camera_info,
            "odometry": self._odometry,
            "imu": self._imu,
            "accel": self._accel,
            "usbl": self._usbl,
            "ds_prior": self._ds_prior,
            "enable": self._enable,
            "abort": self._abort,
            "clock": self._clock,
        }

    def feed(self, kind: str, msg: Any, now_ns: int, error: str = "") -> None:
        """One message of input ``kind`` received at ``now_ns`` (``msg`` None: its bytes did
        not deserialise, ``error`` says why)."""
        if msg is None:
            self.chain.reject(kind, error or "not a message of its type", now_ns)
            return
        try:
            self._check_stamp(kind, msg, now_ns)
            self._handlers[kind](msg, now_ns)
        except ValueError as exc:
            self.chain.reject(kind, " ".join(str(exc).split())[:200], now_ns)

    def _check_stamp(self, kind: str, msg: Any, now_ns: int) -> None:
        if not self.check_future or not hasattr(msg, "header") or kind == "camera_info":
            return
        ahead = (rm.stamp_ns(msg) - now_ns) / 1e9
        if ahead > self.cfg.safety.max_future_s:
            raise ValueError(f"stamped {ahead:.3f} s ahead of the node's clock")

    def _image(self, msg: Any, now_ns: int) -> None:
        jpeg = hasattr(msg, "format") and "jpeg" in str(msg.format).lower()  # CompressedImage
        self.chain.on_frame(rm.stamp_ns(msg), lambda: read_image(msg), True if jpeg else None)

    def _camera_info(self, msg: Any, now_ns: int) -> None:
        if self.use_camera_info and not self.chain.camera_from_info:
            self.chain.on_camera_model(read_camera_info(msg))

    def _odometry(self, msg: Any, now_ns: int) -> None:
        self.chain.on_nav(read_odometry(msg, self.cfg.axes))

    def _imu(self, msg: Any, now_ns: int) -> None:
        self.chain.on_imu(rm.stamp_ns(msg), read_imu(msg, self.cfg.axes))

    def _accel(self, msg: Any, now_ns: int) -> None:
        self.chain.on_accel(rm.stamp_ns(msg), read_accel(msg, self.cfg.axes))

    def _usbl(self, msg: Any, now_ns: int) -> None:
        p, var = read_usbl(msg, self.cfg.axes)
        self.chain.on_usbl(rm.stamp_ns(msg), p, var)

    def _ds_prior(self, msg: Any, now_ns: int) -> None:
        T, var = read_ds_prior(msg, self.cfg.axes)
        self.chain.on_ds_prior(rm.stamp_ns(msg), T, var)

    def _enable(self, msg: Any, now_ns: int) -> None:
        self.chain.on_enable(bool(msg.data))

    def _abort(self, msg: Any, now_ns: int) -> None:
        self.chain.on_abort()

    def _clock(self, msg: Any, now_ns: int) -> None:
        t = rm.stamp_ns(msg.clock)
        self.clock_ns = t if self.clock_ns is None else max(self.clock_ns, t)


def steady_velocity(
    wrench_6: np.ndarray, linear_damping: np.ndarray, quadratic_damping: np.ndarray
) -> np.ndarray:
    """(6,) body velocity at which the vehicle's damping balances ``wrench_6`` on each axis
    (``d_l v + d_q |v| v = F``; restoring forces and coupling ignored): the policy's wrench as
    a body velocity request, for vehicles whose controller takes velocities (m/s, rad/s)."""
    F = np.asarray(wrench_6, dtype=np.float64)
    dl = np.asarray(linear_damping, dtype=np.float64)
    dq = np.asarray(quadratic_damping, dtype=np.float64)
    a = np.abs(F)
    with np.errstate(divide="ignore", invalid="ignore"):
        quad = (-dl + np.sqrt(dl * dl + 4.0 * dq * a)) / (2.0 * dq)
        lin = np.where(dl > 0, a / dl, 0.0)
    return np.sign(F) * np.where(dq > 0, quad, lin)


def _cov6(cov_xyzyaw: np.ndarray) -> np.ndarray:
    """(6, 6) pose covariance of an [x, y, z, yaw] one (roll and pitch: not estimated, 0)."""
    c = np.zeros((6, 6))
    idx = [0, 1, 2, 5]
    c[np.ix_(idx, idx)] = cov_xyzyaw
    return c


def tick_messages(
    tick: Tick, cfg: NodeConfig, damping: tuple[np.ndarray, np.ndarray] | None = None
) -> list[tuple[str, str, str, Any]]:
    """The messages one tick publishes, in order: ``(kind, topic, type, message)``. The
    command comes before the diagnostics (a lock-step vehicle waits for the diagnostics, then
    reads the command). ``damping``: the vehicle's (linear, quadratic) damping, for the body
    velocity request (:func:`steady_velocity`) when ``topics.velocity_command`` is set."""
    axes, f, t = cfg.axes, cfg.frames, tick.stamp_ns
    outs = output_types(cfg)
    msgs: list[tuple[str, str, str, Any]] = []

    def add(kind: str, msg: Any) -> None:
        if kind in outs:
            msgs.append((kind, *outs[kind], msg))

    if tick.measurement is not None and tick.frame_stamp_ns is not None:
        m = tick.measurement
        T = conv.frame_pose_to_wire(m.T_world_ds, axes)
        cov = conv.covariance_to_wire(_cov6(m.cov_xyzyaw), axes, body=False)
        add("ds_pose", rm.pose_cov_stamped_msg(T, cov, tick.frame_stamp_ns, f.world))
    T_est = conv.frame_pose_to_wire(tick.T_world_ds, axes)
    cov_est = conv.covariance_to_wire(_cov6(tick.cov_xyzyaw), axes, body=False)
    add("ds_estimate", rm.pose_cov_stamped_msg(T_est, cov_est, t, f.world))
    add("tf", rm.tf_message_msg([(T_est, f.world, f.docking_station, t)]))
    if tick.command is not None:
        w = np.concatenate(
            [conv.body_vector_to_wire(tick.command[:3], axes),
             conv.body_vector_to_wire(tick.command[3:], axes)]
        )  # fmt: skip
        add("command", rm.wrench_stamped_msg(w, t, f.body))
        if damping is not None:
            v = steady_velocity(tick.command, *damping)
            v_wire = [conv.body_vector_to_wire(v[:3], axes), conv.body_vector_to_wire(v[3:], axes)]
            add("velocity_command", rm.twist_stamped_msg(*v_wire, t, f.body))
    level = rm.DIAG_OK if tick.state == "armed" else rm.DIAG_WARN
    if tick.state == "holding":
        level = rm.DIAG_ERROR
    message = "; ".join(tick.reasons) or tick.state
    add(
        "diagnostics",
        rm.diagnostic_array_msg(t, [(level, cfg.name, message, cfg.frames.body, tick.values)]),
    )
    return msgs
