"""ROS 2 on the wire without ROS (``uwdock.ros``): the bytes the node sends are the bytes a ROS 2
node sends, the names are ROS 2's, the axis conventions convert exactly, hostile messages are
refused in one line, and samples cross a real Cyclone DDS domain on loopback unchanged.

Byte identity is checked three ways for every message type the node publishes or reads: the
bytes read off a DDS reader, ``rosbags``' serialisation of a message built with ``rosbags``' own
classes (not the toolkit's builders), and Cyclone DDS's own serialiser of the DDS type
(:func:`uwdock.ros.dds.idl_type`), an implementation independent of ``rosbags``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="Cyclone DDS's binding (x86-64 wheels on PyPI only)")

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.rl.deploy import inputs
from uwdock.ros import conventions as conv
from uwdock.ros import messages as rm
from uwdock.ros.dds import DdsGraph, idl_type, loopback_config
from uwdock.ros.names import check_topic, dds_topic_name
from uwdock.ros.qos import QosProfile

T = make_T(R_from_rpy(0.1, -0.2, 2.5), [12.5, -3.25, 7.0])
STAMP = 1_733_500_000_123_456_789


def _idl_value(value, node):
    """A ``rosbags`` field value as the Cyclone IDL type wants it (nested dataclasses,
    lists)."""
    from rosbags.typesys.base import Nodetype

    kind, arg = node
    if kind == Nodetype.NAME:
        return _to_idl(value, arg)
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        sub = arg[0]
        return [_idl_value(v, sub) for v in (value.tolist() if hasattr(value, "tolist") else value)]
    return value.item() if hasattr(value, "item") else value


def _to_idl(msg, typename: str):
    """The same message as an instance of the Cyclone IDL type (an independent serialiser)."""
    _, fields = rm.typestore().fielddefs[typename]
    cls = idl_type(typename)
    return cls(**{name: _idl_value(getattr(msg, name), node) for name, node in fields})


def _ros(typename: str):
    return rm.typestore().types[typename]


def _time():
    return _ros("builtin_interfaces/msg/Time")(sec=STAMP // 10**9, nanosec=STAMP % 10**9)


def _header(frame: str):
    return _ros("std_msgs/msg/Header")(stamp=_time(), frame_id=frame)


def _reference_wrench():
    """A WrenchStamped built with rosbags' classes alone."""
    v3 = _ros("geometry_msgs/msg/Vector3")
    return _ros("geometry_msgs/msg/WrenchStamped")(
        header=_header("girona500/base_link"),
        wrench=_ros("geometry_msgs/msg/Wrench")(
            force=v3(x=140.0, y=-70.5, z=12.25), torque=v3(x=0.0, y=-3.5, z=36.0)
        ),
    )


def _node_messages() -> dict[str, object]:
    """One message of every type the node and the simulated vehicle put on the wire."""
    img = np.arange(363 * 480 * 3, dtype=np.uint32).astype(np.uint8).reshape(363, 480, 3)
    cov = np.diag([0.01, 0.02, 0.03, 0.0, 0.0, 0.004])
    return {
        "geometry_msgs/msg/WrenchStamped": rm.wrench_stamped_msg(
            np.array([140.0, -70.5, 12.25, 0.0, -3.5, 36.0]), STAMP, "girona500/base_link"
        ),
        "geometry_msgs/msg/PoseWithCovarianceStamped": rm.pose_cov_stamped_msg(
            T, cov, STAMP, "world_ned"
        ),
        "nav_msgs/msg/Odometry": rm.odometry_msg(
            T, np.array([0.3, 0.0, -0.1]), np.array([0.0, 0.01, -0.2]), STAMP, "w", "b"
        ),
        "sensor_msgs/msg/Imu": rm.imu_msg(
            T[:3, :3], np.array([0.0, 0.01, -0.2]), np.array([0.1, 0.2, -9.8]), STAMP, "b"
        ),
        "geometry_msgs/msg/AccelWithCovarianceStamped": rm.accel_stamped_msg(
            np.array([0.1, 0.2, 0.3]), STAMP, "b"
        ),
        "sensor_msgs/msg/Image": rm.image_msg(img, STAMP, "camera"),
        "sensor_msgs/msg/CompressedImage": rm.compressed_image_msg(img, STAMP, "camera", 25),
        "sensor_msgs/msg/CameraInfo": rm.camera_info_msg(
            np.array([[461.0, 0, 239.5], [0, 461.1, 181.0], [0, 0, 1]]),
            (0.01, -0.02, 0.0, 0.0, 0.001),
            480,
            363,
            STAMP,
            "camera",
        ),
        "tf2_msgs/msg/TFMessage": rm.tf_message_msg([(T, "world_ned", "docking_station", STAMP)]),
        "diagnostic_msgs/msg/DiagnosticArray": rm.diagnostic_array_msg(
            STAMP, [(rm.DIAG_ERROR, "uwdock_docking", "camera stale", "b", {"state": "holding"})]
        ),
        "rosgraph_msgs/msg/Clock": rm.clock_msg(STAMP),
    }


def test_bytes_equal_rosbags_for_a_message_built_with_its_own_classes():
    ours = rm.serialize(
        rm.wrench_stamped_msg(
            np.array([140.0, -70.5, 12.25, 0.0, -3.5, 36.0]), STAMP, "girona500/base_link"
        ),
        "geometry_msgs/msg/WrenchStamped",
    )
    ref = bytes(
        rm.typestore().serialize_cdr(_reference_wrench(), "geometry_msgs/msg/WrenchStamped")
    )
    assert ours == ref
    # little-endian CDR encapsulation, then the stamp (int32 sec, uint32 nanosec)
    assert ours[:4] == b"\x00\x01\x00\x00"
    assert int.from_bytes(ours[4:8], "little") == STAMP // 10**9
    assert int.from_bytes(ours[8:12], "little") == STAMP % 10**9


@pytest.mark.parametrize("typename", sorted(_node_messages()))
def test_bytes_equal_cyclone_dds_own_serialiser(typename):
    msg = _node_messages()[typename]
    ours = rm.serialize(msg, typename)
    theirs = _to_idl(msg, typename).serialize()
    assert ours == theirs
    # and read back to the same values
    assert rm.serialize(rm.deserialize(ours, typename), typename) == ours


def test_names_and_definitions_are_ros2_jazzy():
    assert rm.dds_type_name("geometry_msgs/msg/WrenchStamped") == (
        "geometry_msgs::msg::dds_::WrenchStamped_"
    )
    assert idl_type("sensor_msgs/msg/Image").__idl_typename__ == "sensor_msgs::msg::dds_::Image_"
    assert dds_topic_name("/girona500/navigator/odometry") == "rt/girona500/navigator/odometry"
    for bad in ("relative", "/a//b", "/a/", "/9a", "/a b", "", "/é"):
        with pytest.raises(ValueError):
            check_topic(bad)
    text = rm.msgdef("geometry_msgs/msg/WrenchStamped")
    assert text.startswith("std_msgs/Header header\ngeometry_msgs/Wrench wrench\n")
    assert "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec" in text
    assert rm.type_hash("geometry_msgs/msg/WrenchStamped").startswith("RIHS01_")
    # Jazzy's Gid is 16 bytes (it was 24 before Iron): the store is Jazzy's
    _, fields = rm.typestore().fielddefs["rmw_dds_common/msg/Gid"]
    assert fields[0][1][1][1] == 16


def test_conventions_convert_exactly():
    # a vehicle 10 m north, 2 m east, 3 m deep, heading east (yaw 90 deg in NED)
    T_ned = make_T(R_from_rpy(0.0, 0.0, math.pi / 2), [10.0, 2.0, 3.0])
    T_enu = conv.pose_to_wire(T_ned, "enu")
    assert np.allclose(T_enu[:3, 3], [2.0, 10.0, -3.0])  # east, north, up
    forward_enu = T_enu[:3, :3] @ np.array([1.0, 0.0, 0.0])
    assert np.allclose(forward_enu, [1.0, 0.0, 0.0])  # FLU x points east
    assert np.allclose(conv.pose_from_wire(T_enu, "enu"), T_ned, atol=1e-15)
    v = np.array([1.0, 2.0, 3.0])  # forward, starboard, down
    assert np.array_equal(conv.body_vector_to_wire(v, "enu"), [1.0, -2.0, -3.0])
    assert np.array_equal(conv.body_vector_from_wire(conv.body_vector_to_wire(v, "enu"), "enu"), v)
    assert np.array_equal(conv.world_vector_to_wire(v, "enu"), [2.0, 1.0, -3.0])
    assert np.array_equal(conv.pose_to_wire(T_ned, "ned"), T_ned)
    cov = np.diag([1.0, 4.0, 9.0, 0.1, 0.2, 0.3])
    back = conv.covariance_from_wire(conv.covariance_to_wire(cov, "enu", False), "enu", False)
    assert np.allclose(back, cov)
    assert np.allclose(
        np.diag(conv.covariance_to_wire(cov, "enu", False)), [4, 1, 9, 0.2, 0.1, 0.3]
    )
    with pytest.raises(ValueError):
        conv.pose_from_wire(T_ned, "nwu")


def test_odometry_in_enu_reads_as_the_same_ned_pose():
    T_ned = make_T(R_from_rpy(0.05, -0.02, 1.2), [4.0, -1.0, 5.0])
    v_frd = np.array([0.4, -0.1, 0.05])
    w_frd = np.array([0.0, 0.01, 0.2])
    msg = rm.odometry_msg(
        conv.pose_to_wire(T_ned, "enu"),
        conv.body_vector_to_wire(v_frd, "enu"),
        conv.body_vector_to_wire(w_frd, "enu"),
        STAMP, "odom", "base_link",
    )  # fmt: skip
    s = inputs.read_odometry(msg, "enu")
    assert s.stamp_ns == STAMP
    assert np.allclose(s.T_world_body, T_ned, atol=1e-12)
    assert np.allclose(s.velocity_frd_mps, v_frd) and np.allclose(
        s.angular_velocity_frd_radps, w_frd
    )


def test_hostile_messages_are_refused_in_one_line():
    good = rm.pose_cov_stamped_msg(T, np.eye(6) * 0.01, STAMP, "w")
    bad_cov = dataclasses.replace(good.pose, covariance=-np.eye(6).reshape(36))
    with pytest.raises(ValueError, match="negative variance"):
        inputs.read_usbl(dataclasses.replace(good, pose=bad_cov), "ned")
    nan_cov = dataclasses.replace(good.pose, covariance=np.full(36, np.nan))
    with pytest.raises(ValueError, match="NaN"):
        inputs.read_ds_prior(dataclasses.replace(good, pose=nan_cov), "ned")
    asym = np.eye(6) * 0.01
    asym[0, 1] = 0.5
    with pytest.raises(ValueError, match="symmetric"):
        inputs.read_usbl(
            dataclasses.replace(good, pose=dataclasses.replace(good.pose, covariance=asym.ravel())),
            "ned",
        )
    zero = rm.pose_cov_stamped_msg(T, np.zeros((6, 6)), STAMP, "w")
    with pytest.raises(ValueError, match="no variance"):
        inputs.read_usbl(zero, "ned")
    with pytest.raises(ValueError, match="not a nav_msgs/msg/Odometry"):
        rm.deserialize(b"\x00\x01\x00\x00garbage", "nav_msgs/msg/Odometry")
    with pytest.raises(ValueError, match="not a"):
        rm.deserialize(b"", "sensor_msgs/msg/Image")
    img = rm.image_msg(np.zeros((4, 4), np.uint8), STAMP, "c", "mono8")
    img.encoding = "32FC1"
    with pytest.raises(ValueError, match="encoding"):
        inputs.read_image(img)
    info = rm.camera_info_msg(np.eye(3) * 0, (0.0,) * 5, 480, 363, STAMP, "c")
    with pytest.raises(ValueError, match="camera_info"):
        inputs.read_camera_info(info)
    with pytest.raises(ValueError, match="outside a ROS time"):
        rm.time_msg(-1)


def test_loopback_config_stays_on_loopback():
    xml = loopback_config(7)
    assert '<NetworkInterface address="127.0.0.1"/>' in xml
    assert "<AllowMulticast>false</AllowMulticast>" in xml
    assert '<Peer address="127.0.0.1"/>' in xml
    with pytest.raises(ValueError):
        DdsGraph(233)


def test_samples_cross_dds_unchanged_and_advertise_the_type_hash():
    """A writer and a reader in two participants of one loopback domain: the bytes a reader
    takes are the bytes rosbags makes of the same values; USER_DATA carries the type hash."""
    a, b = DdsGraph(231), DdsGraph(231)
    q = QosProfile("reliable", 4)
    msgs = _node_messages()
    kinds = ["geometry_msgs/msg/WrenchStamped", "sensor_msgs/msg/Image", "nav_msgs/msg/Odometry"]
    pubs = {k: a.publisher(f"/test/{k.split('/')[-1].lower()}", k, q) for k in kinds}
    subs = {k: b.subscription(f"/test/{k.split('/')[-1].lower()}", k, q) for k in kinds}
    assert a.wait_matched(list(pubs.values()) + list(subs.values()), 10.0)
    for k in kinds:
        pubs[k].publish(msgs[k])
        assert pubs[k].wait_for_acks(5.0)
    got = {}
    for _ in range(50):
        b.wait(0.1)
        for k, sub in subs.items():
            for r in sub.take():
                got[k] = r
        if len(got) == len(kinds):
            break
    assert set(got) == set(kinds)
    ref = bytes(
        rm.typestore().serialize_cdr(_reference_wrench(), "geometry_msgs/msg/WrenchStamped")
    )
    assert got["geometry_msgs/msg/WrenchStamped"].cdr == ref
    for k in kinds:
        assert got[k].cdr == rm.serialize(msgs[k], k)
        assert got[k].error == "" and got[k].msg is not None
    image = got["sensor_msgs/msg/Image"].msg
    assert np.array_equal(
        inputs.read_image(image), inputs.read_image(msgs["sensor_msgs/msg/Image"])
    )
    # what discovery tells the reader's side: the DDS names and Jazzy's USER_DATA type hash
    writer = pubs["geometry_msgs/msg/WrenchStamped"]._writer
    data = writer.get_matched_subscription_data(writer.get_matched_subscriptions()[0])
    assert data.topic_name == "rt/test/wrenchstamped"
    assert data.type_name == "geometry_msgs::msg::dds_::WrenchStamped_"
    hash_ = rm.type_hash("geometry_msgs/msg/WrenchStamped")
    assert f"Policy.Userdata(data=b'typehash={hash_};')" in str(data.qos)


def test_the_node_announces_itself_to_the_ros2_graph():
    """``ros_discovery_info`` (no ``rt/`` prefix, latched) carries the participant's GUID and the
    node's readers and writers, as ROS 2's rmw publishes it for ``ros2 node list``."""
    a, b = DdsGraph(228), DdsGraph(228)
    pub = a.publisher(
        "/uwdock/ds_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", QosProfile()
    )
    sub = a.subscription("/girona500/navigator/odometry", "nav_msgs/msg/Odometry", QosProfile())
    keep = a.announce_node("uwdock_docking", [pub, sub])
    latched = QosProfile("reliable", 1, "transient_local")
    typename = "rmw_dds_common/msg/ParticipantEntitiesInfo"
    reader = b.subscription("ros_discovery_info", typename, latched, raw=True)
    got = []
    for _ in range(50):
        b.wait(0.1)
        got += reader.take()
        if got:
            break
    assert got and keep.matched() >= 1
    info = got[-1].msg
    assert bytes(info.gid.data) == a.participant.guid.bytes
    node = info.node_entities_info_seq[0]
    assert (node.node_namespace, node.node_name) == ("/", "uwdock_docking")
    assert [bytes(x.data) for x in node.writer_gid_seq] == [pub.gid]
    assert [bytes(x.data) for x in node.reader_gid_seq] == [sub.gid]
    data = keep._writer.get_matched_subscription_data(keep._writer.get_matched_subscriptions()[0])
    assert data.topic_name == "ros_discovery_info"
    assert data.type_name == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
