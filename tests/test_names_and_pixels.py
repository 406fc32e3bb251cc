"""Any file name and any pixel type through the footage commands (issue 54, part 3), and only the
toolkit's own lines on stderr (part 4: library noise).

A name that is not UTF-8 (``caf\\xe9.png``) crashed ``perception detect`` / ``eval`` (exit 139:
OpenCV's text drawing on the surrogate-escaped name) and was an internal error in
``--no-annotate`` (the CSV writer) and ``calibration intrinsics`` (the plot's labels); 16-bit and
float frames without markers, or with the wrong dictionary, were internal errors (the dictionary
hint handed them to ArUco as they were). Here: random byte names (non-UTF-8, spaces, leading
dashes) and random pixel types (uint8, uint16, float32, float64, NaN, +-inf), in-process, must
give exit 0 (or one line and exit 2), never 1 or a crash, and leave no temporary file; the
outputs are valid UTF-8 and name the file as :func:`dockcore.names.display_name` shows it.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import struct
import sys
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import reference_camera, save_camera
from uwdock.dockcore.cli import run_group
from uwdock.dockcore.io import TEMP_MARK
from uwdock.dockcore.media import (
    AtomicVideoWriter,
    display_name,
    open_video,
    scale_to_uint8,
    silence_opencv_log,
)
from uwdock.perception import cli as perception_cli

W, H = 320, 240
TAG_ID = 13  # in the default DS marker set (DICT_4X4_50)

_SETTINGS = dict(
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _invoke(main_group, args: list) -> tuple[int, str, str]:
    """A command group in-process: (exit status, stdout, stderr). Streams are StringIO (they
    take what a terminal in the C locale would); stderr is checked to be valid UTF-8 text."""
    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = ["prog", *map(str, args)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                run_group(main_group, [str(a) for a in args])
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = argv
    err_text = err.getvalue()
    err_text.encode("utf-8")  # no lone surrogate reaches the user's terminal
    return code, out.getvalue(), err_text


def _temps(root: Path) -> list[bytes]:
    """Names holding the temporary-file mark anywhere under ``root`` (bytes: any name)."""
    mark = TEMP_MARK.encode()
    found = []
    for folder, dirs, files in os.walk(os.fsencode(root)):
        found += [os.path.join(folder, n) for n in dirs + files if mark in n]
    return found


def _tag_frame() -> np.ndarray:
    """(H, W) uint8: one flat DICT_4X4_50 tag (ID 13) on white."""
    tag = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), TAG_ID, 96
    )
    img = np.full((H, W), 255, np.uint8)
    img[70:166, 110:206] = tag
    return img


def _write_image(path: Path, image: np.ndarray) -> Path:
    """Encode by the suffix and write through the file's bytes name (cv2.imwrite would crash on
    a name that is not UTF-8, as the toolkit did)."""
    ok, buf = cv2.imencode(path.suffix, image)
    assert ok, image.dtype
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(os.fsencode(path), "wb") as fh:
        fh.write(buf.tobytes())
    return path


@pytest.fixture(scope="module")
def camera_file(tmp_path_factory) -> Path:
    return save_camera(
        tmp_path_factory.mktemp("cam") / "cam.yaml", reference_camera().scaled(W, H)
    )[0]


# --------------------------------------------------------------------------- names

_STEM = st.binary(min_size=1, max_size=14).map(lambda b: b.replace(b"/", b"_").replace(b"\0", b"_"))
#: random byte names, the non-UTF-8 ones, leading dashes, spaces, and a few named cases
NAMES = st.one_of(
    _STEM,
    _STEM.map(lambda b: b"-" + b),
    _STEM.map(lambda b: b" " + b + b" "),
    st.sampled_from([b"caf\xe9", b"\xff\xfe", b"--help", b"-", b"a b", "日本".encode(), b"\\xe9"]),
)


def _name(stem: bytes, suffix: bytes = b".png") -> str:
    return os.fsdecode(stem + suffix)


def test_display_name_shows_the_bytes_and_keeps_text():
    assert display_name(os.fsdecode(b"caf\xe9.png")) == "caf\\xe9.png"
    assert display_name(b"caf\xe9.png") == "caf\\xe9.png"
    assert display_name("café.png") == "café.png"  # valid UTF-8 is left alone
    assert display_name(Path(os.fsdecode(b"d\xff/x.png"))) == "d\\xff/x.png"


@settings(max_examples=8, **_SETTINGS)
@given(folder=NAMES, name=NAMES, out_name=NAMES)
def test_any_file_or_folder_name_through_detect_and_eval(
    tmp_path_factory, camera_file, folder, name, out_name
):
    """Exit 0 with the tag found, the annotated frame written under the file's own bytes, and
    every output valid UTF-8 naming the frame as display_name shows it."""
    root = tmp_path_factory.mktemp("names")
    frames = root / _name(b"in" + folder, b"")
    file_name = _name(name)
    _write_image(frames / file_name, _tag_frame())
    shown = display_name(file_name)
    for extra in ([], ["--no-annotate"]):
        out = root / _name(b"out" + out_name, b"") / ("n" if extra else "a")
        args = ["detect", frames, "--out", out, *extra]
        code, _, err = _invoke(perception_cli.cli, args)
        assert code == 0, (args, err)
        row = json.loads((out / "detections.jsonl").read_bytes().decode("utf-8"))
        assert row["name"] == shown and row["ids"] == [TAG_ID], row
        table = (out / "detections.csv").read_bytes().decode("utf-8")
        assert list(csv.reader(io.StringIO(table, newline="")))[1][1] == shown, table
        if not extra:
            assert os.listdir(os.fsencode(out / "annotated")) == [os.fsencode(file_name)]
    out = root / _name(b"out" + out_name, b"") / "e"
    code, _, err = _invoke(
        perception_cli.cli, ["eval", frames, "--camera", camera_file, "--out", out]
    )
    assert code == 0, err
    report = json.loads((out / "report.json").read_bytes().decode("utf-8"))
    assert report["detection_rate"] == 1.0, report["detection_rate"]
    row = json.loads((out / "frames.jsonl").read_bytes().decode("utf-8"))
    assert row["name"] == shown and row["ids"] == [TAG_ID], row
    assert _temps(root) == []


# --------------------------------------------------------------------------- pixel types


def _as_dtype(grey: np.ndarray, dtype: str, scale: str, bad: str, rng) -> np.ndarray:
    """``grey`` (uint8) as ``dtype``: ``scale`` "unit" (float in [0, 1] / full-range uint16),
    "raw" (float counts -50 ... 254950 / 16-bit data in 12 bits); ``bad`` non-finite pixels put
    in the top rows (the tag stays whole)."""
    if dtype == "uint8":
        return grey
    if dtype == "uint16":
        return grey.astype(np.uint16) * (257 if scale == "unit" else 16)
    img = grey.astype(dtype) / 255.0
    if scale == "raw":
        img = img * 255_000.0 - 50.0
    if bad != "none":
        values = {
            "nan": [np.nan],
            "inf": [np.inf],
            "-inf": [-np.inf],
            "mixed": [np.nan, np.inf, -np.inf],
        }
        rows = img[:12]
        rows[...] = rng.choice(values[bad], size=rows.shape)
    return img


@settings(max_examples=14, **_SETTINGS)
@given(
    dtype=st.sampled_from(["uint8", "uint16", "float32", "float64"]),
    scale=st.sampled_from(["unit", "raw"]),
    bad=st.sampled_from(["none", "nan", "inf", "-inf", "mixed"]),
    content=st.sampled_from(["tag", "blank", "all-nan"]),
    markers=st.sampled_from(["set", "right", "wrong"]),
    command=st.sampled_from(["detect", "detect-plain", "eval"]),
)
def test_any_pixel_type_through_detect_and_eval(
    tmp_path_factory, camera_file, dtype, scale, bad, content, markers, command
):
    """16-bit, float (unit or raw range), NaN and inf frames, with and without markers, with
    the right or the wrong dictionary: exit 0, the tag found where it is whole and in range."""
    root = tmp_path_factory.mktemp("px")
    grey = _tag_frame() if content == "tag" else np.full((H, W), 128, np.uint8)
    img = _as_dtype(
        grey, dtype, scale, bad if dtype.startswith("float") else "none", np.random.default_rng(0)
    )
    if content == "all-nan":
        img = np.full((H, W), np.nan, np.float32)
    suffix = ".png" if img.dtype in (np.uint8, np.uint16) else ".tif"
    _write_image(root / "f" / f"frame{suffix}", img)
    marker_args = {
        "set": [],
        "right": ["--dictionary", "DICT_4X4_50", "--marker-size-m", "0.1"],
        "wrong": ["--dictionary", "DICT_6X6_50"],
    }[markers]
    out = root / "o"
    args = {
        "detect": ["detect", root / "f", "--out", out],
        "detect-plain": ["detect", root / "f", "--no-annotate", "--out", out],
        "eval": ["eval", root / "f", "--camera", camera_file, "--out", out],
    }[command] + marker_args
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # NaN casts handled, not warned about
        code, _, err = _invoke(perception_cli.cli, args)
    assert code == 0, (args, dtype, scale, bad, content, err)
    rows_file = out / ("frames.jsonl" if command == "eval" else "detections.jsonl")
    row = json.loads(rows_file.read_text(encoding="utf-8"))
    found = content == "tag" and markers != "wrong" and not (dtype == "uint16" and scale == "raw")
    if found:
        assert row["ids"] == [TAG_ID], (dtype, scale, bad, row)
    if content != "tag" or markers == "wrong":
        assert row["ids"] == [] and "warning: no marker of" in err, err
    assert _temps(root) == []


def test_scale_to_uint8_values():
    u16 = np.array([[0, 257, 65535]], np.uint16)
    assert scale_to_uint8(u16).tolist() == [[0, 1, 255]]
    unit = np.array([[0.0, 0.5, 1.0, np.nan, np.inf, -np.inf]], np.float32)
    assert scale_to_uint8(unit).tolist() == [[0, 128, 255, 0, 255, 0]]
    overshoot = np.array([[-0.02, 0.5, 1.04]], np.float32)  # a filter's overshoot: clipped
    assert scale_to_uint8(overshoot).tolist() == [[0, 128, 255]]
    counts = np.array([[0.0, 100.0, 255.0]])  # 8-bit data in a float image: as it is
    assert scale_to_uint8(counts).tolist() == [[0, 100, 255]]
    raw = np.array([[-50.0, 127475.0 - 25.0, 254950.0]])  # another range: min-max
    assert scale_to_uint8(raw).tolist() == [[0, 128, 255]]
    assert scale_to_uint8(np.full((2, 2), np.nan)).tolist() == [[0, 0], [0, 0]]
    assert scale_to_uint8(np.array([[-5, 0, 5]], np.int16)).tolist() == [[0, 128, 255]]
    with pytest.raises(Exception, match="pixel type"):
        scale_to_uint8(np.zeros((2, 2), np.complex64))


# --------------------------------------------------------------------------- calibration


@pytest.fixture(scope="module")
def views() -> list[np.ndarray]:
    """Five 640 x 480 chessboard views (9 x 6 inner corners) of tests/test_calibration.py."""
    from tests.test_calibration import DIST_TRUE, H_PX, K_TRUE, W_PX, chessboard_views

    uv = np.stack(np.meshgrid(np.arange(W_PX), np.arange(H_PX)), -1).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    rays = cv2.undistortPoints(uv.reshape(-1, 1, 2), K_TRUE, DIST_TRUE, criteria=crit)
    return chessboard_views(rays.reshape(H_PX, W_PX, 2), 5, seed=3)


CALIB = ["--cols", "9", "--rows", "6", "--corner-method", "classic", "--cv-folds", "2"]


def _calibrate(root: Path, views, odd: np.ndarray, odd_name: str) -> tuple[int, str, dict | None]:
    folder = root / "views"
    for k, v in enumerate(views[:-1]):
        _write_image(folder / f"v{k}.png", v)
    _write_image(folder / odd_name, odd)
    code, _, err = _invoke(
        calibration_cli.cli, ["intrinsics", folder, *CALIB, "--out", root / "c" / "cam.yaml"]
    )
    report = root / "c" / "cam_report.json"
    data = json.loads(report.read_bytes().decode("utf-8")) if code == 0 else None
    return code, err, data


@settings(max_examples=5, **_SETTINGS)
@given(name=NAMES)
def test_intrinsics_with_any_view_name(tmp_path_factory, views, name):
    """The view's name in the report and the plot's labels: exit 0, all five views used."""
    root = tmp_path_factory.mktemp("cal")
    file_name = _name(name, b"_.png")  # never one of the other views' names
    code, err, report = _calibrate(root, views, views[-1], file_name)
    assert code == 0, err
    assert report["views"]["calibration"] == 5, report["views"]
    assert display_name(file_name) in [v["name"] for v in report["per_view"]]
    assert (root / "c" / "cam_errors.png").stat().st_size > 1000
    assert _temps(root) == []


@pytest.mark.parametrize(
    "dtype, scale, bad",
    [("uint16", "unit", "none"), ("float32", "unit", "none"), ("float64", "raw", "none"),
     ("float32", "unit", "nan"), ("float64", "unit", "mixed")],
)  # fmt: skip
def test_intrinsics_with_16_bit_and_float_views(tmp_path, views, dtype, scale, bad):
    """The view of another pixel type is read as the others (its chessboard found and used)."""
    odd = _as_dtype(views[-1], dtype, scale, bad, np.random.default_rng(1))
    code, err, report = _calibrate(tmp_path, views, odd, "odd.tif")
    assert code == 0, err
    assert report["views"]["calibration"] == 5 and report["views"]["unreadable"] == 0
    assert _temps(tmp_path) == []


# --------------------------------------------------------------------------- videos


def test_videos_with_names_that_are_not_utf8(tmp_path):
    """OpenCV's VideoCapture / VideoWriter crashed on such a path: read and written now."""
    folder = tmp_path / os.fsdecode(b"d\xe9")
    frames = [np.full((48, 64, 3), 40 * k, np.uint8) for k in range(5)]
    for suffix in (".mp4", ".avi"):
        with AtomicVideoWriter(folder / os.fsdecode(b"v\xff" + suffix.encode()), 10.0) as video:
            for f in frames:
                video.write(f)
        cap, first, leading = open_video(video.path)
        n = 1
        while cap.read()[0]:
            n += 1
        cap.release()
        assert (n, leading, first.shape) == (5, 0, (48, 64, 3)), suffix
    mp4 = folder / os.fsdecode(b"v\xff.mp4")
    code, _, err = _invoke(perception_cli.cli, ["detect", mp4, "--out", tmp_path / "o"])
    assert code == 0, err
    assert sum(1 for _ in (tmp_path / "o" / "detections.jsonl").open()) == 5
    assert (tmp_path / "o" / "annotated.mp4").is_file()
    code, _, err = _invoke(calibration_cli.cli, ["intrinsics", mp4, "--out", tmp_path / "c.yaml"])
    assert code == 2 and err.startswith("error: no chessboard"), err
    assert _temps(tmp_path) == []


# --------------------------------------------------------------------------- library noise


def _png_with_bad_icc(image: np.ndarray) -> bytes:
    """A PNG whose iCCP chunk holds a profile too short to be one: libpng warns on fd 2."""
    png = cv2.imencode(".png", image)[1].tobytes()
    data = b"bad\x00\x00" + zlib.compress(struct.pack(">I", 200) + bytes(196))
    chunk = struct.pack(">I", len(data)) + b"iCCP" + data
    chunk += struct.pack(">I", zlib.crc32(b"iCCP" + data) & 0xFFFFFFFF)
    return png[:33] + chunk + png[33:]  # after the signature and IHDR


def _bag_of(path: Path, payloads: list[bytes]) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    with Writer(path) as writer:
        conn = writer.add_connection(
            "/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts
        )
        for k, data in enumerate(payloads):
            ns = 1_000_000_000 + k * 100_000_000
            stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
            header = T["std_msgs/msg/Header"](seq=k, stamp=stamp, frame_id="cam")
            msg = T["sensor_msgs/msg/CompressedImage"](
                header=header, format="png", data=np.frombuffer(data, np.uint8)
            )
            writer.write(conn, ns, ts.serialize_ros1(msg, "sensor_msgs/msg/CompressedImage"))
    return path


def test_library_lines_do_not_reach_the_user(tmp_path, capfd):
    """libpng's "iCCP" warnings (a bag's PNG frames, a folder's PNG) and OpenCV's own
    ``[ WARN:0@...]`` log: the footage commands print their own lines only."""
    payload = _png_with_bad_icc(cv2.cvtColor(_tag_frame(), cv2.COLOR_GRAY2BGR))
    bag = _bag_of(tmp_path / "dive.bag", [payload] * 3)
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "a.png").write_bytes(payload)
    level = cv2.utils.logging.getLogLevel()
    try:
        for group, args in (
            (perception_cli.cli, ["detect", bag, "--out", tmp_path / "o1"]),
            (perception_cli.cli, ["detect", tmp_path / "f", "--out", tmp_path / "o2"]),
            (calibration_cli.cli, ["intrinsics", bag, "--out", tmp_path / "c.yaml"]),
        ):
            capfd.readouterr()
            code, _, err = _invoke(group, args)
            fd = capfd.readouterr()
            assert code in (0, 2), err
            assert "libpng" not in fd.err + err, fd.err + err
            assert all(
                line.startswith(("note: ", "warning: ", "error: ")) for line in err.splitlines()
            ), err
        # the groups turned OpenCV's log off: a warning OpenCV would print says nothing
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_SILENT
        capfd.readouterr()
        cv2.imread(str(tmp_path / "missing.png"))
        assert "WARN" not in capfd.readouterr().err
    finally:
        cv2.utils.logging.setLogLevel(level)


def test_a_users_opencv_log_level_is_kept(monkeypatch):
    level = cv2.utils.logging.getLogLevel()
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_WARNING)
        monkeypatch.setenv("OPENCV_LOG_LEVEL", "WARNING")
        silence_opencv_log()
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_WARNING
        monkeypatch.delenv("OPENCV_LOG_LEVEL")
        silence_opencv_log()
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_SILENT
    finally:
        cv2.utils.logging.setLogLevel(level)
