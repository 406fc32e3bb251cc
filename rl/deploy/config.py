"""The vehicle node's settings: topics, frames, QoS, axis convention, clock and safety limits.

One typed config (:class:`NodeConfig`), defaults in code, overridden by a TOML file
(``rl node --config vehicle.toml``; unknown keys are errors). The defaults follow COLA2, the
Girona vehicles' software: its navigator publishes ``nav_msgs/Odometry`` in a NED world with an
FRD body under ``/<robot>/navigator/``, and its controller takes body force requests under
``/<robot>/controller/``. ``docs/guides/vehicle.md`` has the mapping table for COLA2 and for a
plain ROS 2 vehicle (REP 103: ENU world, FLU body; ``axes = "enu"``), and
``rl/deploy/profiles/`` holds both as files.

The node publishes ROS 2 types only (``geometry_msgs/WrenchStamped`` for the command): on a
COLA2 vehicle a relay turns it into ``cola2_msgs/BodyForceReq`` (COLA2's own message type,
which the Jazzy store does not define).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from uwdock.dockcore.config import load_config
from uwdock.dockcore.domains import Interval
from uwdock.ros.names import check_topic
from uwdock.ros.qos import RELIABLE, SENSOR_DATA, QosProfile

__all__ = ["NodeConfig", "NodeFrames", "NodeQos", "NodeSafety", "NodeTopics", "load_node_config"]

_Age_s = Annotated[float, Interval(gt=0, le=3600)]


@dataclass(frozen=True)
class NodeTopics:
    """ROS 2 topic names (absolute). An empty name turns that input or output off.

    Attributes:
        image: the downward camera, ``sensor_msgs/Image`` (``image_format = "raw"``) or
            ``sensor_msgs/CompressedImage`` (``"compressed"``).
        image_format: ``"raw"`` or ``"compressed"`` (JPEG/PNG).
        camera_info: ``sensor_msgs/CameraInfo``: the intrinsics, when no camera file is given
            (the first message is taken; ``T_body_cam`` then comes from the camera file or the
            reference mounting).
        odometry: ``nav_msgs/Odometry``: the navigation's pose (world frame) and body twist.
        imu: ``sensor_msgs/Imu``: the accelerometer's specific force (REP 145: gravity
            included) for the contact sense; empty: the specific force is derived from
            ``accel`` (or not sensed).
        accel: ``geometry_msgs/AccelWithCovarianceStamped``: the navigation's gravity-free body
            acceleration (``robot_localization``'s ``accel/filtered``); empty: derived from
            ``imu`` with the navigation's attitude.
        usbl: ``geometry_msgs/PoseWithCovarianceStamped``: acoustic fixes of the DS position
            in the world frame (orientation ignored), placed by the vehicle's navigator.
        ds_prior: ``geometry_msgs/PoseWithCovarianceStamped``: the DS pose the mission starts
            from (a survey, the mission plan); each message starts a new docking run.
        enable: ``std_msgs/Bool``: true arms the node (commands are published), false disarms.
        abort: ``std_msgs/Empty``: hold with a zero wrench until the next enable.
        clock: ``rosgraph_msgs/Clock``: simulated time (``use_sim_time``), read with
            ``--clock sim``.
        ds_pose: output, ``PoseWithCovarianceStamped``: each camera measurement of the DS
            (world frame), with the estimator's covariance.
        ds_estimate: output, ``PoseWithCovarianceStamped``: the filtered DS estimate, each tick.
        command: output, ``geometry_msgs/WrenchStamped``: the body wrench (N, N m).
        velocity_command: output, ``geometry_msgs/TwistStamped``: the wrench as a body velocity
            request (the velocity at which the vehicle's damping balances it on each axis:
            for a controller that takes velocities, e.g. COLA2's body velocity requests through
            a relay); empty: not published.
        tf: output, ``tf2_msgs/TFMessage``: world -> DS (estimate) each tick.
        diagnostics: output, ``diagnostic_msgs/DiagnosticArray``: state, rates, latency, why
            it holds, each tick.
    """

    image: str = "/girona500/down_camera/image_raw"
    image_format: Literal["raw", "compressed"] = "raw"
    camera_info: str = "/girona500/down_camera/camera_info"
    odometry: str = "/girona500/navigator/odometry"
    imu: str = "/girona500/navigator/imu"
    accel: str = ""
    usbl: str = "/girona500/navigator/usbl_ds"
    ds_prior: str = "/uwdock/ds_prior"
    enable: str = "/uwdock/enable"
    abort: str = "/uwdock/abort"
    clock: str = "/clock"
    ds_pose: str = "/uwdock/ds_pose"
    ds_estimate: str = "/uwdock/ds_estimate"
    command: str = "/girona500/controller/body_wrench_req"
    velocity_command: str = ""
    tf: str = "/tf"
    diagnostics: str = "/diagnostics"

    def validate(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if name != "image_format" and value:
                check_topic(value, name)


@dataclass(frozen=True)
class NodeFrames:
    """TF frame names.

    Attributes:
        world: the navigation's world frame (``header.frame_id`` of poses it publishes).
        body: the vehicle's body frame (the wrench's frame).
        docking_station: the DS frame the node publishes on ``/tf``.
    """

    world: str = "world_ned"
    body: str = "girona500/base_link"
    docking_station: str = "docking_station"


#: camera_info: latched (a late subscriber gets the last one).
_LATCHED = QosProfile("reliable", 1, "transient_local")
#: navigation: best effort, a short history (odometry, IMU, acceleration at 10-50 Hz).
_NAVIGATION = QosProfile("best_effort", 10, "volatile")
#: /clock as ROS 2 publishes it (best effort, keep last 1).
_CLOCK = QosProfile("best_effort", 1, "volatile")
#: the command: only the newest counts, and it must arrive.
_COMMAND = QosProfile("reliable", 1, "volatile")
#: /tf as tf2 publishes it.
_TF = QosProfile("reliable", 100, "volatile")


@dataclass(frozen=True)
class NodeQos:
    """QoS per topic group (ROS 2 names). Sensor data is best effort, keep last 1: only the
    newest frame counts, and a late one is worth less than none. ``--clock sim`` makes every
    topic reliable (lock-step needs every sample delivered)."""

    image: QosProfile = SENSOR_DATA
    camera_info: QosProfile = _LATCHED
    navigation: QosProfile = _NAVIGATION
    usbl: QosProfile = RELIABLE
    mission: QosProfile = RELIABLE
    clock: QosProfile = _CLOCK
    outputs: QosProfile = RELIABLE
    command: QosProfile = _COMMAND
    tf: QosProfile = _TF


@dataclass(frozen=True)
class NodeSafety:
    """When the node holds (a zero wrench, the reason in diagnostics).

    Attributes:
        camera_timeout_s: hold when the newest frame is older than this (s).
        nav_timeout_s: hold when the newest navigation solution is older than this (s).
        nav_buffer_s: navigation history kept to place frames at their own stamp (s); a frame
            older than the buffer is refused (counted).
        bad_input_hold_s: after an input is refused (NaN, out of its domain, undecodable),
            hold this long (s).
        max_ds_sigma_m: hold while the DS estimate's horizontal standard deviation exceeds
            this (m).
        max_future_s: a message stamped further ahead of the node's clock than this is refused
            (s): clocks out of step.
    """

    camera_timeout_s: _Age_s = 1.0
    nav_timeout_s: _Age_s = 0.5
    nav_buffer_s: _Age_s = 5.0
    bad_input_hold_s: Annotated[float, Interval(ge=0, le=3600)] = 1.0
    max_ds_sigma_m: Annotated[float, Interval(gt=0, le=1000)] = 3.0
    max_future_s: _Age_s = 0.5


@dataclass(frozen=True)
class NodeConfig:
    """The vehicle node (module docstring).

    Attributes:
        name: the node's name (diagnostics' status name, the ROS 2 graph's node name).
        axes: the axis convention of every pose, twist and wrench on the wire: ``"ned"``
            (NED world, FRD body: COLA2) or ``"enu"`` (ENU world, FLU body: REP 103).
        control_hz: the control tick (Hz); 0: the policy's own rate (5 Hz for the shipped
            policy). Another rate than the policy's is refused.
        flat_markers: also decode flat (printed) markers, not only 3D Binary Markers (the
            detector's OpenCV pass); off for the simulator's renders, which show only 3DBMs.
        topics: topic names.
        frames: TF frame names.
        qos: QoS per topic group.
        safety: hold conditions.
    """

    name: str = "uwdock_docking"
    axes: Literal["ned", "enu"] = "ned"
    control_hz: Annotated[float, Interval(ge=0, le=100)] = 0.0
    flat_markers: bool = True
    topics: NodeTopics = field(default_factory=NodeTopics)
    frames: NodeFrames = field(default_factory=NodeFrames)
    qos: NodeQos = field(default_factory=NodeQos)
    safety: NodeSafety = field(default_factory=NodeSafety)

    def validate(self) -> None:
        if not self.topics.odometry:
            raise ValueError("topics.odometry: the node needs the vehicle's navigation")
        if not self.topics.image:
            raise ValueError("topics.image: the node needs the downward camera")
        if not self.topics.command:
            raise ValueError("topics.command: the node must have a command output")
        if self.safety.nav_buffer_s < self.safety.camera_timeout_s:
            raise ValueError(
                "safety.nav_buffer_s must cover safety.camera_timeout_s (frames are placed "
                "with the navigation at their own stamp)"
            )


def load_node_config(path: str | None = None) -> NodeConfig:
    """The defaults, then the TOML file at ``path`` (a ``[node]`` table or the keys at top
    level). Raises ConfigError with one line on an unknown key or a bad value."""
    return load_config(NodeConfig, path, section="node")
