"""``rl replay`` on recordings written here: a ROS 1 ``.bag`` and a ROS 2 ``.mcap`` of the same
mission give the same track; the node's topics are found or refused in one line; the output
MCAP reads back with ``rosbags`` (ROS 2 types). The replay of a ``sim vehicle`` recording, and
its equality with the live node, is ``tests/test_vehicle_wire.py``'s."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.dockcore.bags import Bag
from uwdock.ros import messages as rm
from uwdock.ros.mcap import McapRecorder

T0 = 50_000_000_000
T_DS = make_T(R_from_rpy(0, 0, 0.5), [1.0, 0.0, 8.0])
COV = np.diag([1.0, 1.0, 0.09, 0, 0, 0.07])


def _poses(k: int) -> np.ndarray:
    return make_T(R_from_rpy(0.0, 0.0, 0.2 + 0.01 * k), [0.1 * k, 0.0, 4.0])


def _frame(k: int) -> np.ndarray:
    return np.full((363, 480, 3), 60 + k, np.uint8)


def _ros2(path: Path, n: int = 12) -> None:
    rec = McapRecorder(path)
    rec.write("/uwdock/ds_prior", "geometry_msgs/msg/PoseWithCovarianceStamped",
              rm.pose_cov_stamped_msg(T_DS, COV, T0, "world_ned"), T0)  # fmt: skip
    for k in range(n):
        t = T0 + k * 200_000_000
        odom = rm.odometry_msg(_poses(k), np.array([0.5, 0, 0]), np.zeros(3), t, "w", "b")
        rec.write("/girona500/navigator/odometry", "nav_msgs/msg/Odometry", odom, t)
        rec.write("/girona500/down_camera/image_raw", "sensor_msgs/msg/Image",
                  rm.image_msg(_frame(k), t, "camera"), t)  # fmt: skip
    rec.close()


def _ros1(path: Path, n: int = 12) -> None:
    """The same mission as a ROS 1 bag (Noetic types: headers carry ``seq``)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    M = ts.types

    def header(t: int, frame: str):
        stamp = M["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
        return M["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

    def pose(T: np.ndarray):
        m = rm.pose_msg(T)  # a ROS 2 Pose: same fields in ROS 1
        p, q = m.position, m.orientation
        return M["geometry_msgs/msg/Pose"](
            position=M["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=p.z),
            orientation=M["geometry_msgs/msg/Quaternion"](x=q.x, y=q.y, z=q.z, w=q.w),
        )

    def vec(v):
        return M["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    with Writer(path) as w:
        c_prior = w.add_connection(
            "/uwdock/ds_prior", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=ts
        )
        c_odom = w.add_connection(
            "/girona500/navigator/odometry", "nav_msgs/msg/Odometry", typestore=ts
        )
        c_img = w.add_connection(
            "/girona500/down_camera/image_raw", "sensor_msgs/msg/Image", typestore=ts
        )
        prior = M["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=header(T0, "world_ned"),
            pose=M["geometry_msgs/msg/PoseWithCovariance"](pose=pose(T_DS), covariance=COV.ravel()),
        )
        w.write(c_prior, T0, ts.serialize_ros1(prior, c_prior.msgtype))
        for k in range(n):
            t = T0 + k * 200_000_000
            odom = M["nav_msgs/msg/Odometry"](
                header=header(t, "w"),
                child_frame_id="b",
                pose=M["geometry_msgs/msg/PoseWithCovariance"](
                    pose=pose(_poses(k)), covariance=np.zeros(36)
                ),
                twist=M["geometry_msgs/msg/TwistWithCovariance"](
                    twist=M["geometry_msgs/msg/Twist"](
                        linear=vec([0.5, 0, 0]), angular=vec([0, 0, 0])
                    ),
                    covariance=np.zeros(36),
                ),
            )
            w.write(c_odom, t, ts.serialize_ros1(odom, c_odom.msgtype))
            img = _frame(k)
            im = M["sensor_msgs/msg/Image"](
                header=header(t, "camera"), height=363, width=480, encoding="bgr8",
                is_bigendian=0, step=480 * 3, data=img.reshape(-1),
            )  # fmt: skip
            w.write(c_img, t, ts.serialize_ros1(im, c_img.msgtype))


def _replay(bag: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "uwdock.cli", "rl", "replay", str(bag), "--out", str(out), *extra],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip


def test_ros1_and_ros2_recordings_of_one_mission_replay_the_same(tmp_path):
    _ros2(tmp_path / "m.mcap")
    _ros1(tmp_path / "m.bag")
    a = _replay(tmp_path / "m.mcap", tmp_path / "a")
    b = _replay(tmp_path / "m.bag", tmp_path / "b")
    assert a.returncode == 0, a.stderr
    assert b.returncode == 0, b.stderr
    sa = json.loads((tmp_path / "a" / "summary.json").read_text())
    sb = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert sa["frames"]["used"] == sb["frames"]["used"] == 12
    assert sa["ticks"] == sb["ticks"] >= 12
    assert sa["track"] == sb["track"]
    # no frame shows a marker and no fix arrives: the estimate stays the DS prior
    est = np.array([r["ds_estimate_xyz_m"] for r in sa["track"]])
    assert np.allclose(est, T_DS[:3, 3])
    with Bag(tmp_path / "b" / "replay.mcap") as bag:
        types = {t.name: t.msgtype for t in bag.topics()}
        ours = {t: m for t, _, _, m, _, _ in bag.messages(["/uwdock/ds_estimate"])}
    assert types["/girona500/navigator/odometry"] == "nav_msgs/msg/Odometry"
    assert types["/uwdock/ds_estimate"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert types["/diagnostics"] == "diagnostic_msgs/msg/DiagnosticArray"
    # Foxglove's own reader (its ros2msg parser and CDR decoder) reads every channel
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    seen = {}
    with open(tmp_path / "b" / "replay.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, _, decoded in reader.iter_decoded_messages():
            assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
            seen[channel.topic] = decoded
    assert set(seen) == set(types)
    est = seen["/uwdock/ds_estimate"].pose.pose.position
    mine = ours["/uwdock/ds_estimate"].pose.pose.position
    assert (est.x, est.y, est.z) == (mine.x, mine.y, mine.z)


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        ("missing", "not found"),
        ("no_camera", "has no camera topic"),
        ("not_a_bag", "not a ROS bag"),
        ("fifo", "FIFO"),
    ],
)
def test_bad_recordings_are_one_line(tmp_path, setup, message):
    bag = tmp_path / "x.mcap"
    if setup == "no_camera":
        rec = McapRecorder(bag)
        odom = rm.odometry_msg(_poses(0), np.zeros(3), np.zeros(3), T0, "w", "b")
        rec.write("/girona500/navigator/odometry", "nav_msgs/msg/Odometry", odom, T0)
        rec.close()
    elif setup == "not_a_bag":
        bag = tmp_path / "x.txt"
        bag.write_text("hello")
    elif setup == "fifo":
        os.mkfifo(bag)
    res = _replay(bag, tmp_path / "out")
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and message in res.stderr, res.stderr
    assert not (tmp_path / "out" / "summary.json").exists()


def test_record_refuses_special_files(tmp_path):
    from uwdock.dockcore.errors import DockError

    with pytest.raises(DockError, match="folder"):
        McapRecorder(tmp_path)
    null = tmp_path / "null.mcap"  # a character device of its own, as /dev/null is
    os.mknod(null, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    with pytest.raises(DockError, match="character device"):
        McapRecorder(null)
    with pytest.raises(DockError, match=r"\.mcap"):
        McapRecorder(tmp_path / "x.bag")
    rec = McapRecorder(tmp_path / "r.mcap")
    rec.write("/clock", "rosgraph_msgs/msg/Clock", rm.clock_msg(5), 5)
    rec.discard()  # an interrupted recording leaves nothing
    assert list(tmp_path.iterdir()) == [null]  # nothing else, the device left as it was
    assert stat.S_ISCHR(null.lstat().st_mode)
