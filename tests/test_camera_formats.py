"""Camera files of other tools (``calibration.formats``): ROS camera_info and Kalibr camchain.

Golden files are literal text laid out as the tools write them: ``camera_calibration``'s
``ost.yaml`` (ROS 1 and 2: matrices wrapped over lines by numpy), ``camera_calibration_parsers``
(one line per matrix), ``rostopic echo`` / ``ros2 topic echo`` of a ``CameraInfo`` message, and
a two-camera Kalibr camchain written by PyYAML (block lists at the key's indentation). Imports
are checked number for number, round trips to 1e-12, every malformed file gives one line naming
the file, and the commands are run through the CLI runner.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import CameraModel, load_camera, save_camera
from uwdock.calibration.formats import (
    MAX_FILE_BYTES,
    camera_from_camera_info_msg,
    detect_format,
    import_camera_file,
    read_camera_yaml,
    read_yaml_mapping,
)
from uwdock.calibration.formats_export import (
    export_camera_file,
    kalibr_camchain_yaml,
    ros_camera_info_yaml,
)
from uwdock.dockcore.errors import DockError

# --------------------------------------------------------------------------- golden files

#: ``camera_calibration`` (cameracalibrator.py) output, 1280 x 1024, plumb_bob.
ROS_OST = """\
image_width: 1280
image_height: 1024
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [ 1109.35742,     0.     ,   643.71249,
            0.     ,  1108.62131,   507.20493,
            0.     ,     0.     ,     1.     ]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.337612, 0.128734, 0.000842, -0.000519, -0.023906]
rectification_matrix:
  rows: 3
  cols: 3
  data: [ 1.,  0.,  0.,
          0.,  1.,  0.,
          0.,  0.,  1.]
projection_matrix:
  rows: 3
  cols: 4
  data: [ 1021.68896,     0.     ,   643.19052,     0.     ,
            0.     ,  1052.28918,   506.77712,     0.     ,
            0.     ,     0.     ,     1.     ,     0.     ]
"""
ROS_OST_K = np.array([[1109.35742, 0.0, 643.71249], [0.0, 1108.62131, 507.20493], [0.0, 0.0, 1.0]])
ROS_OST_DIST = (-0.337612, 0.128734, 0.000842, -0.000519, -0.023906)

#: ``camera_calibration_parsers`` (ROS 2) output, 968 x 732, rational_polynomial.
ROS_PARSERS = """\
image_width: 968
image_height: 732
camera_name: downward
camera_matrix:
  rows: 3
  cols: 3
  data: [931.25, 0, 483.75, 0, 930.5, 366.125, 0, 0, 1]
distortion_model: rational_polynomial
distortion_coefficients:
  rows: 1
  cols: 8
  data: [0.51, -0.27, 0.0011, -0.0007, 0.013, 0.82, -0.19, 0.045]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [931.25, 0, 483.75, 0, 0, 930.5, 366.125, 0, 0, 0, 1, 0]
"""

#: A stereo pair's right camera: R is not the identity.
ROS_STEREO_RIGHT = ROS_OST.replace(
    "data: [ 1.,  0.,  0.,\n          0.,  1.,  0.,\n          0.,  0.,  1.]",
    "data: [0.9999, -0.0141, 0.0019, 0.0141, 0.9999, -0.0012, -0.0019, 0.0012, 1.0]",
)

#: ``rostopic echo -n 1 /camera/camera_info`` (ROS 1: upper-case K, D, R, P; quoted strings).
ECHO_ROS1 = """\
header:
  seq: 1842
  stamp:
    secs: 1700000000
    nsecs: 125000000
  frame_id: "downward_cam_optical"
height: 732
width: 968
distortion_model: "plumb_bob"
D: [-0.1, 0.01, 0.0, 0.0, 0.0]
K: [931.25, 0.0, 483.75, 0.0, 930.5, 366.125, 0.0, 0.0, 1.0]
R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
P: [931.25, 0.0, 483.75, 0.0, 0.0, 930.5, 366.125, 0.0, 0.0, 0.0, 1.0, 0.0]
binning_x: 0
binning_y: 0
roi:
  x_offset: 0
  y_offset: 0
  height: 0
  width: 0
  do_rectify: False
---
"""

#: ``ros2 topic echo --once /camera/camera_info`` (ROS 2: lower-case, block lists).
ECHO_ROS2 = """\
header:
  stamp:
    sec: 1700000000
    nanosec: 125000000
  frame_id: downward_cam_optical
height: 732
width: 968
distortion_model: plumb_bob
d:
- -0.1
- 0.01
- 0.0
- 0.0
- 0.0
k:
- 931.25
- 0.0
- 483.75
- 0.0
- 930.5
- 366.125
- 0.0
- 0.0
- 1.0
r:
- 1.0
- 0.0
- 0.0
- 0.0
- 1.0
- 0.0
- 0.0
- 0.0
- 1.0
p:
- 931.25
- 0.0
- 483.75
- 0.0
- 0.0
- 930.5
- 366.125
- 0.0
- 0.0
- 0.0
- 1.0
- 0.0
binning_x: 0
binning_y: 0
roi:
  x_offset: 0
  y_offset: 0
  height: 0
  width: 0
  do_rectify: false
---
"""
ECHO_CAMERA = CameraModel(
    968, 732, 931.25, 930.5, 483.75, 366.125, (-0.1, 0.01, 0.0, 0.0, 0.0),
    name="downward_cam_optical",
)  # fmt: skip

#: ``kalibr_calibrate_imu_camera`` camchain (PyYAML's layout), two cameras, 1280 x 1024.
KALIBR = """\
cam0:
  T_cam_imu:
  - [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
  - [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768]
  - [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.2834081105, 0.0739590700, 0.0001935939, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [1116.5402, 1115.9118, 638.2177, 514.3864]
  resolution: [1280, 1024]
  rostopic: /cam0/image_raw
  timeshift_cam_imu: -0.00265
cam1:
  T_cam_imu:
  - [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556]
  - [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024]
  - [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038]
  - [0.0, 0.0, 0.0, 1.0]
  T_cn_cnm1:
  - [0.999997256477, 0.00231206719, 0.000376008102, -0.110073808127]
  - [-0.002317135723, 0.999898048506, 0.014089835846, 0.000399121813]
  - [-0.000343393121, -0.014090668452, 0.999900662638, -0.000853702043]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [0]
  camera_model: pinhole
  distortion_coeffs: [-0.2836836, 0.0745128, -0.0001047, -3.5559e-05]
  distortion_model: radtan
  intrinsics: [1114.9870, 1114.1301, 645.8452, 519.2170]
  resolution: [1280, 1024]
  rostopic: /cam1/image_raw
  timeshift_cam_imu: -0.00262
"""
KALIBR_T_CAM0_IMU = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def _write(tmp_path: Path, text: str | bytes, name: str = "in.yaml") -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def _assert_same(a: CameraModel, b: CameraModel, names: bool = True) -> None:
    """Same size, K and distortion (coefficient lists zero-padded) to 1e-12."""
    assert (a.width_px, a.height_px) == (b.width_px, b.height_px)
    np.testing.assert_allclose(a.K, b.K, rtol=0.0, atol=1e-12)
    pad = [np.pad(c.dist_coeffs, (0, 14 - len(c.dist))) for c in (a, b)]
    np.testing.assert_allclose(pad[0], pad[1], rtol=0.0, atol=1e-12)
    if names:
        assert a.name == b.name


# --------------------------------------------------------------------------- import


def test_ros_ost_yaml_imports_exactly(tmp_path):
    got = read_camera_yaml(_write(tmp_path, ROS_OST))
    cam = got.camera
    assert got.source_format == "ros" and got.T_cam_imu is None and got.notes == ()
    assert (cam.width_px, cam.height_px, cam.name) == (1280, 1024, "narrow_stereo")
    assert np.array_equal(cam.K, ROS_OST_K)
    assert cam.dist == ROS_OST_DIST
    assert cam.rms_px is None


def test_ros_parsers_yaml_rational_polynomial_imports_exactly(tmp_path):
    cam = read_camera_yaml(_write(tmp_path, ROS_PARSERS), fmt="ros").camera
    assert (cam.width_px, cam.height_px, cam.name) == (968, 732, "downward")
    assert (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px) == (931.25, 930.5, 483.75, 366.125)
    assert cam.dist == (0.51, -0.27, 0.0011, -0.0007, 0.013, 0.82, -0.19, 0.045)


def test_stereo_rectification_is_noted_not_applied(tmp_path):
    got = read_camera_yaml(_write(tmp_path, ROS_STEREO_RIGHT))
    assert np.array_equal(got.camera.K, ROS_OST_K)  # the raw image's K, not P's
    assert len(got.notes) == 1 and "rectification" in got.notes[0]


def test_kalibr_camchain_imports_exactly_with_T_cam_imu(tmp_path):
    path = _write(tmp_path, KALIBR)
    got = read_camera_yaml(path)
    cam = got.camera
    assert got.source_format == "kalibr" and cam.name == "cam0"
    assert (cam.width_px, cam.height_px) == (1280, 1024)
    assert (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px) == (
        1116.5402, 1115.9118, 638.2177, 514.3864
    )  # fmt: skip
    assert cam.dist == (-0.2834081105, 0.07395907, 0.0001935939, 1.76187114e-05)
    assert np.array_equal(got.T_cam_imu, KALIBR_T_CAM0_IMU)
    assert got.notes == ("the camchain holds cam0, cam1; imported cam0",)
    cam1 = read_camera_yaml(path, fmt="kalibr", cam_key="cam1")
    assert cam1.camera.name == "cam1" and cam1.camera.fx_px == 1114.9870
    assert cam1.camera.dist == (-0.2836836, 0.0745128, -0.0001047, -3.5559e-05)
    assert cam1.T_cam_imu[0, 3] == -0.0198435579556


@pytest.mark.parametrize("text", [ECHO_ROS1, ECHO_ROS2], ids=["ros1", "ros2"])
def test_saved_camera_info_message_imports(tmp_path, text):
    path = _write(tmp_path, text)
    got = read_camera_yaml(path)
    assert got.source_format == "camera_info"
    assert got.camera == ECHO_CAMERA
    assert read_camera_yaml(path, fmt="ros").camera == ECHO_CAMERA


def test_camera_info_message_object_and_mapping():
    K = [931.25, 0.0, 483.75, 0.0, 930.5, 366.125, 0.0, 0.0, 1.0]
    D = [-0.1, 0.01, 0.0, 0.0, 0.0]
    ros1 = SimpleNamespace(
        header=SimpleNamespace(frame_id="/downward_cam_optical"),
        height=732, width=968, distortion_model="plumb_bob", D=D, K=K, R=list(np.eye(3).flat),
        P=[*K[:3], 0.0, *K[3:6], 0.0, *K[6:], 0.0],
    )  # fmt: skip
    assert camera_from_camera_info_msg(ros1) == ECHO_CAMERA
    # what dockcore.bags hands over: lower-case keys, numpy arrays, no header
    bag = {
        "width": np.uint32(968), "height": np.uint32(732), "distortion_model": "plumb_bob",
        "d": np.array(D), "k": np.array(K), "r": np.eye(3).ravel(), "p": np.zeros(12),
    }  # fmt: skip
    assert camera_from_camera_info_msg(bag) == dataclasses.replace(ECHO_CAMERA, name="camera")
    # an uncalibrated camera has no distortion model and an empty D; K must still be real
    plain = dict(bag, distortion_model="", d=[])
    assert camera_from_camera_info_msg(plain).dist == (0.0,) * 5


def test_detect_format_from_keys(tmp_path):
    for text, kind in ((ROS_OST, "ros"), (ECHO_ROS2, "camera_info"), (KALIBR, "kalibr")):
        assert detect_format(read_yaml_mapping(_write(tmp_path, text))) == kind


# --------------------------------------------------------------------------- round trips

MODELS = {
    "plumb_bob": CameraModel(
        1280, 1024, 1109.357421875, 1108.6213, 643.71249, 507.20493,
        (-0.337612, 0.128734, 0.000842, -0.000519, -0.023906), name="narrow_stereo",
    ),
    "four_coeffs_tiny": CameraModel(
        968, 732, 929.7282381749, 929.7282381749, 483.5, 365.5, (1e-05, -3e-07, 1e-16, 0.0),
        name="girona downward: #1",
    ),
    "rational": CameraModel(
        968, 732, 931.25, 930.5, 483.75, 366.125,
        (0.51, -0.27, 0.0011, -0.0007, 0.013, 0.82, -0.19, 0.045), name="yes",
    ),
    "tilted_zero": CameraModel(
        640, 480, 800.0, 800.0, 319.5, 239.5, (-0.05, 0.0, 0.0, 0.0, 0.0) + (0.0,) * 9,
        name="kamera_ü",
    ),
    "ideal": CameraModel.from_hfov(1280, 1024, 55.0),
}  # fmt: skip
RADTAN_MODELS = ("four_coeffs_tiny", "tilted_zero", "ideal")


@pytest.mark.parametrize("key", sorted(MODELS))
def test_ros_round_trip(tmp_path, key):
    cam = MODELS[key]
    got = read_camera_yaml(_write(tmp_path, ros_camera_info_yaml(cam)), fmt="ros")
    assert got.notes == ()
    _assert_same(got.camera, cam)


@pytest.mark.parametrize("key", RADTAN_MODELS)
def test_kalibr_round_trip(tmp_path, key):
    cam = MODELS[key]
    got = read_camera_yaml(_write(tmp_path, kalibr_camchain_yaml(cam)), fmt="kalibr")
    assert got.camera.name == "cam0" and got.T_cam_imu is None
    _assert_same(got.camera, cam, names=False)
    T = KALIBR_T_CAM0_IMU
    text = kalibr_camchain_yaml(cam, T_cam_imu=T, rostopic="/auv/down cam/image")
    got = read_camera_yaml(_write(tmp_path, text))
    assert np.array_equal(got.T_cam_imu, T)
    assert read_yaml_mapping(tmp_path / "in.yaml")["cam0"]["rostopic"] == "/auv/down cam/image"


def test_exported_floats_read_as_floats_by_yaml_1_1():
    """PyYAML (Kalibr) resolves ``1e-05`` as a string: every float written has a '.' and a
    signed exponent."""
    cam = MODELS["four_coeffs_tiny"]
    yaml11_float = re.compile(r"[-+]?[0-9]+\.[0-9]*(?:[eE][-+][0-9]+)?")
    for text in (ros_camera_info_yaml(cam), kalibr_camchain_yaml(cam)):
        for flow in re.findall(r"\[([^\]]*)\]", text):
            for item in filter(None, (s.strip() for s in flow.split(","))):
                assert yaml11_float.fullmatch(item) or item.isdigit(), (item, text)
    assert "1.0e-05" in kalibr_camchain_yaml(cam)


# --------------------------------------------------------------------------- refusals


def _one_line(exc: pytest.ExceptionInfo, *fragments: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and msg.strip() == msg, msg
    for fragment in fragments:
        assert fragment in msg, msg
    return msg


def test_kalibr_export_refuses_k3_and_higher():
    cam = MODELS["plumb_bob"]
    with pytest.raises(DockError) as exc:
        kalibr_camchain_yaml(cam)
    _one_line(exc, "k3 = -0.023906", "radtan")
    with pytest.raises(DockError) as exc:
        kalibr_camchain_yaml(MODELS["rational"])
    _one_line(exc, "k3 = 0.013", "k4 = 0.82", "k6 = 0.045")


def test_ros_export_refuses_thin_prism_terms():
    cam = dataclasses.replace(MODELS["tilted_zero"], dist=(0.0,) * 8 + (1e-3,) + (0.0,) * 5)
    with pytest.raises(DockError) as exc:
        ros_camera_info_yaml(cam)
    _one_line(exc, "thin-prism")


def _ros(**changes: str) -> str:
    """ROS_OST with each old text (which must occur) replaced: {'old': 'new'}."""
    text = ROS_OST
    for old, new in changes.items():
        assert old in text, old
        text = text.replace(old, new)
    return text


K_DATA = ROS_OST.split("camera_matrix:\n")[1].split("distortion_model")[0]
KALIBR_CAM0 = KALIBR.split("cam1:")[0]

#: (id, file text, format, fragments the one-line message must hold)
HOSTILE = [
    ("missing_width", _ros(**{"image_width: 1280\n": ""}), "auto", "missing key 'image_width'"),
    ("missing_data", ROS_OST.replace(K_DATA, "  rows: 3\n  cols: 3\n"), "ros",
     "missing key 'camera_matrix.data'"),
    ("K_2x3", ROS_OST.replace(K_DATA, "  rows: 2\n  cols: 3\n  data: [1, 0, 2, 0, 1, 2]\n"),
     "ros", "'camera_matrix' must be 3 x 3"),
    ("K_count", ROS_OST.replace(K_DATA, "  rows: 3\n  cols: 3\n  data: [1, 0, 2, 0, 1]\n"),
     "ros", "data holds 5 numbers"),
    ("K_text", ROS_OST.replace("1109.35742", "abc"), "ros", "numbers only", "'abc'"),
    ("K_nan", ROS_OST.replace("1109.35742", ".nan"), "ros", "non-finite"),
    ("D_inf", ROS_OST.replace("-0.337612", "-.inf"), "ros", "distortion_coefficients.data",
     "non-finite"),
    ("fx_negative", ROS_OST.replace("1109.35742", "-1109.35742"), "ros", "fx must be > 0"),
    ("fy_zero", ROS_OST.replace("1108.62131", "0.0"), "ros", "fy must be > 0"),
    ("width_zero", _ros(**{"image_width: 1280": "image_width: 0"}), "ros", "image_width"),
    ("height_negative", _ros(**{"image_height: 1024": "image_height: -1024"}), "ros",
     "image_height"),
    ("width_fraction", _ros(**{"image_width: 1280": "image_width: 1280.5"}), "ros",
     "image_width"),
    ("width_huge", _ros(**{"image_width: 1280": "image_width: " + "9" * 5000}), "ros",
     "not YAML"),
    ("width_text", _ros(**{"image_width: 1280": "image_width: wide"}), "ros", "'wide'"),
    ("skew", ROS_OST.replace("  0.     ,   643.71249", "  0.5    ,   643.71249"), "ros",
     "skew"),
    ("equidistant", _ros(**{"model: plumb_bob": "model: equidistant"}), "ros",
     "'equidistant' (fisheye)"),
    ("unknown_model", _ros(**{"model: plumb_bob": "model: pinhole_fancy"}), "ros",
     "unknown distortion model 'pinhole_fancy'"),
    ("plumb_bob_6", _ros(**{"cols: 5": "cols: 6", "-0.023906]": "-0.023906, 0.1]"}), "ros",
     "takes 0 or 4 or 5 coefficients"),
    ("kalibr_equidistant", KALIBR.replace("radtan", "equidistant", 1), "kalibr",
     "'equidistant'"),
    ("kalibr_omni", KALIBR.replace("pinhole", "omni", 1), "kalibr", "'omni'", "pinhole only"),
    ("kalibr_radtan_5", KALIBR.replace("1.76187114e-05]", "1.76187114e-05, 0.01]"), "kalibr",
     "must hold 4 numbers, got 5"),
    ("kalibr_intrinsics_3", KALIBR.replace(", 514.3864]", "]"), "kalibr",
     "'cam0.intrinsics' must hold 4 numbers"),
    ("kalibr_resolution", KALIBR.replace("[1280, 1024]", "[1280]", 1), "auto",
     "'cam0.resolution' must be [width, height]"),
    ("kalibr_no_intrinsics", KALIBR_CAM0.replace("  intrinsics:", "  intrinsic:"), "auto",
     "missing key 'cam0.intrinsics'"),
    ("kalibr_T_not_rigid", KALIBR.replace("0.0148655429818", "0.5", 1), "kalibr",
     "cam0.T_cam_imu"),
    ("kalibr_T_rows", KALIBR.replace("  - [0.0, 0.0, 0.0, 1.0]\n", "", 1), "kalibr",
     "4 rows of 4 numbers"),
    ("kalibr_as_ros", KALIBR, "ros", "--format ros", "Kalibr camchain"),
    ("ros_as_kalibr", ROS_OST, "kalibr", "--format kalibr", "ROS camera_info"),
    ("top_list", "- 1\n- 2\n", "auto", "top level must be a mapping"),
    ("top_scalar", "just some words\n", "auto", "top level must be a mapping"),
    ("empty", "", "auto", "no YAML content"),
    ("comments_only", "# nothing here\n\n   # really\n", "auto", "no YAML content"),
    ("unknown_keys", "width_px: 1280\nfocal: 900\n", "auto", "not a ROS camera_info file"),
    ("tab_indent", ROS_OST.replace("  rows: 3\n  cols: 3", "\trows: 3\n\tcols: 3", 1), "ros",
     "line 5", "cannot start any token"),
    ("unclosed_bracket", _ros(**{"1.     ,     0.     ]\n": "1.     ,     0.\n"}), "ros",
     "expected ',' or ']'"),
    ("unclosed_quote", _ros(**{"narrow_stereo": '"narrow_stereo'}), "ros", "end of stream"),
    ("duplicate_key", ROS_OST + "image_width: 640\n", "ros", 'duplicate key "image_width"'),
    ("two_documents", ROS_OST + "---\n" + ROS_OST, "ros", "2 YAML documents"),
    ("bad_indent", _ros(**{"  cols: 3\n": "   cols: 3\n"}), "ros", "line 6",
     "mapping values are not allowed"),
    ("nested_deep", "a: " + "[" * 200 + "]" * 200 + "\n", "auto", "not a ROS camera_info"),
    ("nested_block", "".join(" " * i + f"k{i}:\n" for i in range(60)), "auto",
     "not a ROS camera_info"),
    ("opencv_file", "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n", "auto",
     "OpenCV FileStorage"),
    ("bad_escape", _ros(**{"camera_name: narrow_stereo": 'camera_name: "a\\qb"'}), "ros",
     "unknown escape"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("text", "fmt", "fragments"),
    [pytest.param(h[1], h[2], h[3:], id=h[0]) for h in HOSTILE],
)
def test_hostile_files_fail_with_one_line_naming_the_file(tmp_path, text, fmt, fragments):
    path = _write(tmp_path, text)
    with pytest.raises(DockError) as exc:
        read_camera_yaml(path, fmt=fmt)
    assert _one_line(exc, *fragments).startswith(str(path))


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        pytest.param(lambda p: p.write_bytes(b"image_width: 1280\ncamera_name: \xff\xfe\n"),
                     "not UTF-8", id="not_utf8"),
        pytest.param(lambda p: p.write_bytes(b"a: 1\n" + b"#" * MAX_FILE_BYTES), "larger than",
                     id="too_large"),
        pytest.param(lambda p: None, "not found", id="missing"),
        pytest.param(lambda p: p.mkdir(), "is a folder", id="folder"),
    ],
)  # fmt: skip
def test_unreadable_files_fail_with_one_line_naming_the_file(tmp_path, make, fragment):
    path = tmp_path / "in.yaml"
    make(path)
    with pytest.raises(DockError) as exc:
        read_camera_yaml(path)
    _one_line(exc, fragment, str(path))


def test_unknown_kalibr_camera_and_bad_cam_key(tmp_path):
    path = _write(tmp_path, KALIBR)
    with pytest.raises(DockError) as exc:
        read_camera_yaml(path, cam_key="cam2")
    _one_line(exc, str(path), "no 'cam2'", "cam0, cam1")
    with pytest.raises(DockError) as exc:
        read_camera_yaml(path, cam_key="left")
    _one_line(exc, "cam0, cam1, ...", "'left'")


MSG = {
    "width": 968, "height": 732, "distortion_model": "plumb_bob",
    "d": [-0.1, 0.01, 0.0, 0.0, 0.0], "k": [931.25, 0.0, 483.75, 0.0, 930.5, 366.125, 0, 0, 1],
}  # fmt: skip


@pytest.mark.parametrize(
    ("msg", "fragment"),
    [
        pytest.param({k: v for k, v in MSG.items() if k != "k"}, "missing field 'k'", id="no_k"),
        pytest.param(dict(MSG, k=MSG["k"][:8]), "must hold 9 numbers", id="k_8"),
        pytest.param(dict(MSG, k=[0.0] * 9), "not calibrated", id="uncalibrated"),
        pytest.param(dict(MSG, k=np.full(9, np.nan)), "non-finite", id="k_nan"),
        pytest.param(dict(MSG, d="0 0 0 0 0"), "'d' must be a list", id="d_text"),
        pytest.param(dict(MSG, d=[0.1, True, 0, 0, 0]), "numbers only", id="d_bool"),
        pytest.param(dict(MSG, distortion_model="equidistant", d=[0.1] * 4), "fisheye",
                     id="fisheye"),
        pytest.param(dict(MSG, distortion_model=None), "must be a string", id="model_none"),
        pytest.param(dict(MSG, width=-968), "'width'", id="width_negative"),
        pytest.param(dict(MSG, height=0), "'height'", id="height_zero"),
        pytest.param(dict(MSG, r=[1.0] * 8), "must hold 0 or 9 numbers", id="r_8"),
        pytest.param([1, 2, 3], "missing field 'width'", id="not_a_message"),
    ],
)  # fmt: skip
def test_hostile_camera_info_messages_fail_with_one_line(msg, fragment):
    with pytest.raises(DockError) as exc:
        camera_from_camera_info_msg(msg, where="bag.mcap /cam/camera_info")
    _one_line(exc, "bag.mcap /cam/camera_info", fragment)


# --------------------------------------------------------------------------- files and CLI


def test_import_keeps_extrinsics_and_refuses_to_overwrite_its_source(tmp_path):
    out = tmp_path / "camera.yaml"
    T = np.eye(4)
    T[:3, 3] = (0.5, 0.0, 0.4)
    save_camera(out, CameraModel.from_hfov(968, 732, 55.0), T)
    imported, _, kept = import_camera_file(_write(tmp_path, KALIBR), out)
    cam, T_read = load_camera(out)
    assert kept and np.array_equal(T_read, T)  # T_cam_imu is never written as T_body_cam
    assert cam == imported.camera
    src = _write(tmp_path, ROS_OST, "ost.yaml")
    with pytest.raises(DockError) as exc:
        import_camera_file(src, tmp_path / "ost.json")  # its YAML twin is the source
    _one_line(exc, "would overwrite")
    assert src.read_text(encoding="utf-8") == ROS_OST


def test_export_refuses_its_own_camera_file_and_other_suffixes(tmp_path):
    camera = tmp_path / "camera.yaml"
    save_camera(camera, MODELS["ideal"])
    for out, fragment in ((camera, "would overwrite"), (tmp_path / "c.txt", ".yaml or .yml")):
        with pytest.raises(DockError) as exc:
            export_camera_file(camera, out, "ros")
        _one_line(exc, fragment)
    assert load_camera(camera)[0] == MODELS["ideal"]


@pytest.mark.parametrize(
    ("text", "fmt", "cam_key", "label"),
    [(ROS_OST, "auto", "cam0", "ROS camera_info"), (ECHO_ROS2, "ros", "cam0", "CameraInfo"),
     (KALIBR, "kalibr", "cam1", "Kalibr")],
    ids=["ros", "camera_info", "kalibr"],
)  # fmt: skip
def test_cli_import_writes_a_camera_file(run_cli, tmp_path, text, fmt, cam_key, label):
    src, out = _write(tmp_path, text), tmp_path / "cam" / "camera.yaml"
    args = ("--format", fmt, "--cam", cam_key)
    r = run_cli(calibration_cli.main, "import", src, "--out", out, *args)
    assert r.code == 0, r.err
    assert label in r.out and f"wrote {out}" in r.out
    cam, T = load_camera(out)
    assert T is None and cam == read_camera_yaml(src, fmt, cam_key).camera
    assert load_camera(out.with_suffix(".json"))[0] == cam
    if label == "Kalibr":
        assert "T_cam_imu" in r.out and "not written" in r.out
        assert "cam0, cam1; imported cam1" in r.err


@pytest.mark.parametrize("fmt", ["ros", "kalibr"])
def test_cli_export_round_trips_through_import(run_cli, tmp_path, fmt):
    cam = MODELS["four_coeffs_tiny"]
    camera, exported, back = (tmp_path / n for n in ("cam.yaml", f"{fmt}.yaml", "back.yaml"))
    save_camera(camera, cam)
    r = run_cli(calibration_cli.main, "export", camera, "--format", fmt, "--out", exported)
    assert r.code == 0, r.err
    assert f"wrote {exported}" in r.out
    r = run_cli(calibration_cli.main, "import", exported, "--out", back)
    assert r.code == 0, r.err
    _assert_same(load_camera(back)[0], cam, names=fmt == "ros")


def test_cli_bad_files_fail_with_one_line(run_cli, tmp_path):
    out = tmp_path / "camera.yaml"
    bad = _write(tmp_path, ROS_OST.replace("1109.35742", "-1109.35742"))
    r = run_cli(calibration_cli.main, "import", bad, "--out", out)
    assert r.code != 0 and not out.exists()
    assert r.err.count("\n") == 1 and str(bad) in r.err and "fx must be > 0" in r.err
    camera = tmp_path / "k3.yaml"
    save_camera(camera, MODELS["plumb_bob"])
    r = run_cli(calibration_cli.main, "export", camera, "--format", "kalibr", "--out", out)
    assert r.code != 0 and not out.exists()
    assert r.err.count("\n") == 1 and "k3 = -0.023906" in r.err
    r = run_cli(calibration_cli.main, "import", _write(tmp_path, KALIBR), "--cam", "cam7")
    assert r.code != 0 and r.err.count("\n") == 1 and "no 'cam7'" in r.err


# --------------------------------------------------------------------------- stereo camchains

KALIBR_T_CN_CNM1 = np.array(
    [
        [0.999997256477, 0.00231206719, 0.000376008102, -0.110073808127],
        [-0.002317135723, 0.999898048506, 0.014089835846, 0.000399121813],
        [-0.000343393121, -0.014090668452, 0.999900662638, -0.000853702043],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


@pytest.mark.parametrize("cam_key", ["cam0", "cam1"])
def test_cli_import_keeps_T_cn_cnm1_as_a_stereo_file(run_cli, tmp_path, cam_key):
    """Either camera of a two-camera camchain: the camera file, and the pair (cam0 left, cam1
    right) with T_right_left = cam1's T_cn_cnm1 exactly, beside it."""
    from uwdock.calibration.stereo_rig import load_stereo

    src, out = _write(tmp_path, KALIBR), tmp_path / "cam.yaml"
    r = run_cli(calibration_cli.main, "import", src, "--cam", cam_key, "--out", out)
    assert r.code == 0, r.err
    assert "stereo pair cam0 -> cam1 (T_cn_cnm1 of cam1)" in r.out
    rig = load_stereo(tmp_path / "cam_stereo.yaml")
    assert np.array_equal(rig.T_right_left, KALIBR_T_CN_CNM1)
    assert rig.left == read_camera_yaml(src, cam_key="cam0").camera
    assert rig.right == read_camera_yaml(src, cam_key="cam1").camera
    assert (rig.left_topic, rig.right_topic) == ("/cam0/image_raw", "/cam1/image_raw")
    assert rig.baseline_m == pytest.approx(0.110078, abs=1e-6)
    # exported again: the same transform, the same numbers, cam1 linked to cam0
    chain = tmp_path / "chain.yaml"
    r = run_cli(calibration_cli.main, "export", tmp_path / "cam_stereo.yaml", "--format",
                "kalibr", "--out", chain)  # fmt: skip
    assert r.code == 0, r.err
    doc = read_yaml_mapping(chain)
    assert np.array_equal(np.array(doc["cam1"]["T_cn_cnm1"]), KALIBR_T_CN_CNM1)
    assert doc["cam0"]["cam_overlaps"] == [1] and doc["cam1"]["cam_overlaps"] == [0]
    assert doc["cam1"]["intrinsics"] == [1114.9870, 1114.1301, 645.8452, 519.2170]


def test_cli_import_no_stereo_and_refusals(run_cli, tmp_path):
    src, out = _write(tmp_path, KALIBR), tmp_path / "cam.yaml"
    r = run_cli(calibration_cli.main, "import", src, "--cam", "cam1", "--no-stereo", "--out", out)
    assert r.code == 0, r.err
    assert "T_cn_cnm1 of cam1 not kept (--no-stereo)" in r.err
    assert not (tmp_path / "cam_stereo.yaml").exists()
    # a partner the camera model cannot hold: refused in one line, nothing written
    fisheye = _write(tmp_path, KALIBR.replace("radtan", "equidistant", 2).replace(
        "distortion_model: equidistant", "distortion_model: radtan", 1), "fish.yaml")  # fmt: skip
    out2 = tmp_path / "c2.yaml"
    r = run_cli(calibration_cli.main, "import", fisheye, "--out", out2)
    assert r.code != 0 and r.err.count("\n") == 1, r.err
    assert "'cam1'" in r.err and "stereo pair" in r.err and "--no-stereo" in r.err
    assert not out2.exists() and not (tmp_path / "c2_stereo.yaml").exists()
    r = run_cli(calibration_cli.main, "import", fisheye, "--no-stereo", "--out", out2)
    assert r.code == 0 and load_camera(out2)[0].name == "cam0"
    # different image sizes cannot form one stereo file (a size that still holds cam1's
    # principal point: one outside the image is refused first, by check_plausible)
    text = KALIBR.replace("[1280, 1024]\n  rostopic: /cam1", "[1300, 1040]\n  rostopic: /cam1")
    sizes = _write(tmp_path, text, "s.yaml")
    r = run_cli(calibration_cli.main, "import", sizes, "--out", out2)
    assert r.code != 0 and r.err.count("\n") == 1 and "differ in size" in r.err, r.err
    # a one-camera camchain has no pair: --stereo-out is refused, the import alone goes on
    one = _write(tmp_path, kalibr_camchain_yaml(MODELS["ideal"]), "one.yaml")
    r = run_cli(calibration_cli.main, "import", one, "--stereo-out", tmp_path / "x.yaml")
    assert r.code != 0 and "holds no stereo pair" in r.err
