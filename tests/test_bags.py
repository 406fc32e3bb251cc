"""ROS bags as footage (``dockcore.bags``): a rendered dataset written into ROS 1 ``.bag`` and
ROS 2 ``.db3`` / ``.mcap`` recordings (raw and compressed images, camera_info, the DS pose) must
evaluate exactly as the same frames in a folder with the same camera and a pose CSV.

The bags are written with ``rosbags``' own writers and type stores (Noetic for ROS 1, Humble
for ROS 2), as a recorder would write them: header stamps 100 ms apart, recorded 3 ms later.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from uwdock.calibration.camera import load_camera
from uwdock.calibration.frames import pos_quat_from_T
from uwdock.dockcore.bags import Bag, camera_info_topic_for, decode_image_msg, format_topics
from uwdock.dockcore.errors import DockError
from uwdock.perception import cli as perception_cli
from uwdock.perception.groundtruth import load_dataset, truth_from_bag, write_pose_csv

N_FRAMES = 30
T0_NS = 1_700_000_000_000_000_000
STEP_NS = 100_000_000  # 10 Hz
RECORD_DELAY_NS = 3_000_000
RAW, COMPRESSED, INFO, POSE = (
    "/cam/image_raw",
    "/cam/image_raw/compressed",
    "/cam/camera_info",
    "/ds_pose",
)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    """30 frames rendered by SAPIEN (``datasets synth``, 480 px, clear tank)."""
    from uwdock.datasets.synth import SynthConfig, generate

    out = tmp_path_factory.mktemp("bags") / "synth"
    generate(out, SynthConfig(n_frames=N_FRAMES, seed=3, water="clear_tank", width_px=480),
             workers=1, progress=False)  # fmt: skip
    return out


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def _messages(ts, ros1: bool, root: Path):
    """(topic, msgtype, stamp ns, message) of the dataset in recording order."""
    ds = load_dataset(root)
    cam, _ = load_camera(ds.camera_path)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]

    def header(ns: int):
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return Header(seq=0, stamp=stamp, frame_id="cam") if ros1 else Header(stamp, "cam")

    k = [cam.fx_px, 0.0, cam.cx_px, 0.0, cam.fy_px, cam.cy_px, 0.0, 0.0, 1.0]
    p = [cam.fx_px, 0.0, cam.cx_px, 0.0, 0.0, cam.fy_px, cam.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0]
    info_fields = {
        "header": header(T0_NS),
        "height": cam.height_px,
        "width": cam.width_px,
        "distortion_model": "plumb_bob",
        ("D" if ros1 else "d"): np.array(cam.dist, np.float64),
        ("K" if ros1 else "k"): np.array(k),
        ("R" if ros1 else "r"): np.eye(3).ravel(),
        ("P" if ros1 else "p"): np.array(p),
        "binning_x": 0,
        "binning_y": 0,
        "roi": T["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False),
    }
    yield INFO, "sensor_msgs/msg/CameraInfo", T0_NS, T["sensor_msgs/msg/CameraInfo"](**info_fields)
    for frame in sorted(ds.frames):
        ft = ds.frames[frame]
        stamp = T0_NS + frame * STEP_NS
        bgr = cv2.imread(str(root / ft.image), cv2.IMREAD_COLOR)
        rgb = np.ascontiguousarray(bgr[:, :, ::-1])
        h, w = rgb.shape[:2]
        yield RAW, "sensor_msgs/msg/Image", stamp, T["sensor_msgs/msg/Image"](
            header=header(stamp), height=h, width=w, encoding="rgb8", is_bigendian=0,
            step=3 * w, data=rgb.ravel())  # fmt: skip
        png = cv2.imencode(".png", bgr)[1].ravel()
        yield (
            COMPRESSED,
            "sensor_msgs/msg/CompressedImage",
            stamp,
            T["sensor_msgs/msg/CompressedImage"](
                header=header(stamp), format="rgb8; png compressed bgr8", data=png
            ),
        )
        pos, quat_wxyz = pos_quat_from_T(ft.T_cam_ds)
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](*map(float, pos)),
            orientation=T["geometry_msgs/msg/Quaternion"](
                x=float(quat_wxyz[1]),
                y=float(quat_wxyz[2]),
                z=float(quat_wxyz[3]),
                w=float(quat_wxyz[0]),
            ),
        )
        yield (
            POSE,
            "geometry_msgs/msg/PoseStamped",
            stamp,
            T["geometry_msgs/msg/PoseStamped"](header=header(stamp), pose=pose),
        )


def write_bag(root: Path, path: Path) -> Path:
    """The dataset as a ``.bag`` (ROS 1) or a ROS 2 recording with ``.db3`` / ``.mcap`` storage;
    returns what a user would pass (the ``.bag`` file, or the ROS 2 storage file)."""
    ros1 = path.suffix == ".bag"
    ts = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        serialize = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if path.suffix == ".mcap" else StoragePlugin.SQLITE3
        writer = Writer(path.with_suffix(""), version=9, storage_plugin=plugin)
        serialize = ts.serialize_cdr
    conns: dict[str, object] = {}
    with writer:
        for topic, msgtype, stamp, msg in _messages(ts, ros1, root):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], stamp + RECORD_DELAY_NS, serialize(msg, msgtype))
    if ros1:
        return path
    (storage,) = sorted(path.with_suffix("").glob(f"*{path.suffix}"))
    return storage


@pytest.fixture(scope="module")
def folder_report(rendered, tmp_path_factory) -> tuple[list[dict], dict]:
    """The frames as a folder, the dataset's camera and a pose CSV of T_cam_ds."""
    from click.testing import CliRunner

    ds = load_dataset(rendered)
    tmp = tmp_path_factory.mktemp("folder")
    csv_path = write_pose_csv(tmp / "poses.csv", {k: ft.T_cam_ds for k, ft in ds.frames.items()})
    out = tmp / "eval"
    res = CliRunner().invoke(
        perception_cli.cli,
        [
            "eval",
            str(ds.images_dir),
            "--camera",
            str(ds.camera_path),
            "--ground-truth",
            str(csv_path),
            "--out",
            str(out),
            "--quiet",
        ],
    )
    assert res.exit_code == 0, res.output
    return _frames(out), json.loads((out / "report.json").read_text())


def _frames(out: Path) -> list[dict]:
    rows = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    for r in rows:
        r.pop("ms"), r.pop("name")
    return rows


_SAME_KEYS = ("frames", "detection_rate", "pose_rate", "markers_detected_total",
              "translation_error_m_median", "translation_error_m_p90",
              "rotation_error_deg_median", "rotation_error_deg_p90")  # fmt: skip


@pytest.mark.render
@pytest.mark.parametrize("suffix", [".bag", ".db3", ".mcap"])
@pytest.mark.parametrize("topic", [RAW, COMPRESSED])
@pytest.mark.slow  # ~18 s on 2 cores: in the slow set (CI runs it)
def test_bag_evaluates_exactly_as_the_same_frames_in_a_folder(
    rendered, folder_report, tmp_path, suffix, topic
):
    from click.testing import CliRunner

    bag = write_bag(rendered, tmp_path / f"run{suffix}")
    out = tmp_path / "eval"
    res = CliRunner().invoke(
        perception_cli.cli,
        ["eval", str(bag), "--topic", topic, "--pose-topic", POSE, "--out", str(out), "--quiet"],
    )
    assert res.exit_code == 0, res.output
    assert "camera from the bag's /cam/camera_info" in res.output
    rows, report = _frames(out), json.loads((out / "report.json").read_text())
    folder_rows, folder = folder_report
    assert folder["markers_detected_total"] > 0 and folder["pose_rate"] > 0  # not vacuous
    stamps = [r.pop("stamp_ns") for r in rows]
    assert stamps == [T0_NS + k * STEP_NS for k in range(N_FRAMES)]  # header stamps, not log
    truth_keys = ("range_m", "view_angle_deg", "translation_error_m", "rotation_error_deg")
    for a, b in zip(rows, folder_rows, strict=True):
        # detections, estimated poses and fit residuals: exactly the folder's
        assert {k: v for k, v in a.items() if k not in truth_keys} == {
            k: v for k, v in b.items() if k not in truth_keys
        }
        # the truth went through the CSV's 9 significant digits on the folder's side
        for k in truth_keys:
            assert (a.get(k) is None) == (b.get(k) is None)
            if a.get(k) is not None:
                assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-7), k
    for key in _SAME_KEYS:
        assert report[key] == pytest.approx(folder[key], rel=1e-6, abs=1e-7), key
    assert report["input"]["kind"] == "bag"


@pytest.mark.render
def test_topics_are_listed_and_ros_conventions_followed(rendered, tmp_path, run_cli):
    bag = write_bag(rendered, tmp_path / "run.mcap")
    with Bag(bag) as b:
        topics = b.topics()
        listing = format_topics(topics)
        assert {t.name: t.count for t in topics} == {RAW: 30, COMPRESSED: 30, INFO: 1, POSE: 30}
        assert "[frames]" in listing and "[camera]" in listing and "[ground truth]" in listing
        assert camera_info_topic_for(COMPRESSED, topics) == INFO
        assert camera_info_topic_for(RAW, topics) == INFO
        info = b.camera_info(INFO)
    cam, _ = load_camera(load_dataset(rendered).camera_path)
    assert info["k"][0] == cam.fx_px and info["width"] == cam.width_px
    # two image topics and no --topic: the listing, then a one-line error naming both
    res = run_cli(perception_cli.main, "detect", str(bag), "--out", str(tmp_path / "d"))
    assert res.code != 0
    last = res.err.strip().splitlines()[-1]
    assert "choose one with --topic" in last and RAW in last
    assert f"note: {POSE}" in res.err  # the listing came first
    # the ROS 2 folder itself reads the same
    with Bag(bag.parent) as b:
        assert len(b.topics()) == 4


@pytest.mark.render
def test_detect_on_a_bag_writes_stamps_and_an_annotated_video(rendered, tmp_path):
    from click.testing import CliRunner

    bag = write_bag(rendered, tmp_path / "run.db3")
    out = tmp_path / "det"
    res = CliRunner().invoke(
        perception_cli.cli, ["detect", str(bag), "--topic", COMPRESSED, "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    rows = [json.loads(x) for x in (out / "detections.jsonl").read_text().splitlines()]
    assert [r["stamp_ns"] for r in rows] == [T0_NS + k * STEP_NS for k in range(N_FRAMES)]
    assert (out / "annotated.mp4").exists() or (out / "annotated.avi").exists()


@pytest.mark.render
def test_pose_matching_uses_the_tolerance(rendered, tmp_path):
    bag = write_bag(rendered, tmp_path / "run.bag")
    assert len(truth_from_bag(bag, RAW, POSE, tolerance_ms=1.0)) == N_FRAMES
    with pytest.raises(DockError, match="positive"):
        truth_from_bag(bag, RAW, POSE, tolerance_ms=float("nan"))
    with pytest.raises(DockError, match="no topic '/nope'"):
        truth_from_bag(bag, RAW, "/nope")
    with pytest.raises(DockError, match="not pose"):
        truth_from_bag(bag, RAW, INFO)


# --------------------------------------------------------------------------- image messages


class _Msg:
    def __init__(self, **kw):
        self.__dict__.update(kw)


def test_image_encodings_decode_to_opencv_order():
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    rgb = bgr[:, :, ::-1].copy()
    padded = np.zeros((6, 8 * 3 + 5), np.uint8)  # a row stride with padding
    padded[:, :24] = rgb.reshape(6, 24)
    got = decode_image_msg(_Msg(encoding="rgb8", height=6, width=8, step=29, is_bigendian=0,
                                data=padded.ravel()))  # fmt: skip
    assert np.array_equal(got, bgr)
    mono16 = rng.integers(0, 65536, (6, 8), dtype=np.uint16)
    big = mono16.astype(">u2").tobytes()
    got = decode_image_msg(_Msg(encoding="mono16", height=6, width=8, step=16, is_bigendian=1,
                                data=np.frombuffer(big, np.uint8)))  # fmt: skip
    assert got.dtype == np.uint16 and np.array_equal(got, mono16)
    # Bayer RGGB: R at (0, 0), B at (1, 1); a flat colour demosaics to itself
    flat = np.zeros((8, 8), np.uint8)
    flat[0::2, 0::2], flat[0::2, 1::2], flat[1::2, 0::2], flat[1::2, 1::2] = 200, 100, 100, 30
    got = decode_image_msg(_Msg(encoding="bayer_rggb8", height=8, width=8, step=8,
                                is_bigendian=0, data=flat.ravel()))  # fmt: skip
    assert tuple(got[4, 4]) == (30, 100, 200)  # B, G, R
    # damaged data: a short buffer is a corrupt frame, an unknown encoding an error
    assert decode_image_msg(_Msg(encoding="bgr8", height=6, width=8, step=24, is_bigendian=0,
                                 data=np.zeros(10, np.uint8))) is None  # fmt: skip
    with pytest.raises(DockError, match=r"32FC1"):
        decode_image_msg(_Msg(encoding="32FC1", height=6, width=8, step=32, is_bigendian=0,
                              data=np.zeros(192, np.uint8)))  # fmt: skip
    assert decode_image_msg(_Msg(format="jpeg", data=np.arange(50, dtype=np.uint8))) is None


def test_not_a_bag_and_damaged_bags_are_one_line_errors(tmp_path):
    with pytest.raises(DockError, match="not found"):
        Bag(tmp_path / "missing.bag")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"\x00\xff not a bag" * 20)
    with pytest.raises(DockError, match="cannot read bag") as exc:
        Bag(junk)
    assert "\n" not in str(exc.value)
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 40)
    with pytest.raises(DockError, match="cannot read bag"):
        Bag(tmp_path / "junk.mcap")
    with pytest.raises(DockError, match="not a ROS bag"):
        Bag(tmp_path)
