"""``calibration stereo``: T_right_left, rectification and epipolar error from synthetic pairs of a
chessboard seen by two cameras of known intrinsics, distortion and relative pose.

Each view is synthesised exactly through its camera's model: 3 x 3 sample points inside every
pixel are undistorted (``cv2.undistortPoints`` to 1e-12) into normalised rays, intersected with
the board plane through the inverse plane homography ``[r1 r2 t]`` of the board pose, the board
texture (32 px per square) sampled there and the samples averaged per pixel; then a mild blur
and noise. The right camera sees the board at ``T_right_left @ T_left_board``. (The project's
SAPIEN renderer would do, but renders on the CPU here at seconds per frame; this takes
milliseconds and approximates nothing of the geometry. Without the per-pixel averaging the
aliased edges bias the corners by ~0.1 px and the principal points by several px.)
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import CameraModel, load_camera, save_camera
from uwdock.calibration.frames import rotation_angle_deg
from uwdock.calibration.intrinsics import MIN_VIEWS, IntrinsicsConfig
from uwdock.calibration.stereo import StereoConfig, calibrate_stereo
from uwdock.calibration.stereo_rig import StereoRig, load_stereo, save_stereo

W_PX, H_PX = 640, 480
LEFT = CameraModel(
    W_PX, H_PX, 800.0, 800.0, 319.5, 239.5, (-0.08, 0.02, 0.0, 0.0, 0.0), name="left"
)
RIGHT = CameraModel(
    W_PX, H_PX, 820.0, 818.0, 325.0, 236.0, (-0.06, 0.015, 0.0004, -0.0003, 0.0), name="right"
)
#: The right camera 0.12 m to the right of the left one, turned by a few degrees.
R_RIGHT_LEFT = Rotation.from_euler("xyz", [0.8, -3.0, 1.2], degrees=True).as_matrix()
CENTRE_RIGHT_IN_LEFT_M = np.array([0.12, 0.004, -0.003])
T_RIGHT_LEFT = np.eye(4)
T_RIGHT_LEFT[:3, :3] = R_RIGHT_LEFT
T_RIGHT_LEFT[:3, 3] = -R_RIGHT_LEFT @ CENTRE_RIGHT_IN_LEFT_M
BASELINE_M = float(np.linalg.norm(CENTRE_RIGHT_IN_LEFT_M))

COLS, ROWS, SQUARE_M = 9, 6, 0.02  # inner corners
TARGET = IntrinsicsConfig(cols=COLS, rows=ROWS, square_mm=SQUARE_M * 1000)
CFG = StereoConfig(intrinsics=TARGET)
N_PAIRS = 12
TILT, Z_MIN = 0.5, 0.5  # board tilt about x and y (rad), nearest board centre (m)
BAD_PAIR = "pair_005"  # its right image shows the board moved (not taken at the same moment)


# --------------------------------------------------------------------------- rendering


#: Samples per pixel side: each pixel is the mean of SS x SS samples of the board.
SS = 3


@functools.cache
def _rays(cam: CameraModel) -> np.ndarray:
    """(SS H, SS W, 2) undistorted normalised coordinates of SS x SS sample points inside every
    pixel of ``cam`` (pixel centres at integers)."""
    sub = (np.arange(SS) + 0.5) / SS - 0.5
    u = (np.arange(W_PX)[:, None] + sub).ravel()
    v = (np.arange(H_PX)[:, None] + sub).ravel()
    uv = np.stack(np.meshgrid(u, v), -1).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    xn = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs, criteria=crit)
    return xn.reshape(SS * H_PX, SS * W_PX, 2).astype(np.float32)


def _texture(sq_px: int, margin_px: int) -> np.ndarray:
    """(cols+1) x (rows+1) squares, black top-left, white margin; uint8."""
    cells = (np.add.outer(np.arange(ROWS + 1), np.arange(COLS + 1)) % 2) == 0
    board = np.where(np.kron(cells, np.ones((sq_px, sq_px), bool)), 0, 255)
    return np.pad(board.astype(np.uint8), margin_px, constant_values=255)


SQ_PX, MARGIN_PX = 32, 32
TEXTURE = _texture(SQ_PX, MARGIN_PX)
ORIGIN_PX = (MARGIN_PX + SQ_PX - 0.5, MARGIN_PX + SQ_PX - 0.5)  # first inner corner = (0, 0)
W_M, H_M = (COLS - 1) * SQUARE_M, (ROWS - 1) * SQUARE_M
OUTLINE_M = np.array(
    [[-2 * SQUARE_M, -2 * SQUARE_M, 0], [W_M + 2 * SQUARE_M, -2 * SQUARE_M, 0],
     [W_M + 2 * SQUARE_M, H_M + 2 * SQUARE_M, 0], [-2 * SQUARE_M, H_M + 2 * SQUARE_M, 0]]
)  # fmt: skip


def _render(rays, T_cam_board: np.ndarray, rng) -> np.ndarray:
    """The board seen from ``T_cam_board`` by the camera of ``rays``, (H, W) uint8."""
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    H_inv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))  # normalised -> board m
    to_texture = np.diag([SQ_PX / SQUARE_M, SQ_PX / SQUARE_M, 1.0])
    to_texture[:2, 2] = ORIGIN_PX
    maps = cv2.perspectiveTransform(rays, to_texture @ H_inv)
    map_x, map_y = maps[..., 0], maps[..., 1]
    img = cv2.remap(TEXTURE, map_x, map_y, cv2.INTER_LINEAR, borderValue=110).astype(np.float32)
    img = cv2.resize(img, (W_PX, H_PX), interpolation=cv2.INTER_AREA)  # the pixels' mean
    img = cv2.GaussianBlur(img, (0, 0), 0.7) + rng.normal(0.0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _inside(cam: CameraModel, T_cam_board: np.ndarray, margin_px: float = 8.0) -> bool:
    p = (T_cam_board[:3, :3] @ OUTLINE_M.T).T + T_cam_board[:3, 3]
    if (p[:, 2] <= 0.1).any():
        return False
    return bool(cam.in_image(cam.project(p), margin_px).all())


def _board_pose(rng) -> np.ndarray:
    """``T_left_board`` with the whole board (and margin) in both images."""
    while True:
        R = Rotation.from_rotvec(
            [rng.uniform(-TILT, TILT), rng.uniform(-TILT, TILT), rng.uniform(-0.35, 0.35)]
        ).as_matrix()
        centre = np.array(
            [rng.uniform(-0.02, 0.14), rng.uniform(-0.06, 0.06), rng.uniform(Z_MIN, 0.85)]
        )
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, centre - R @ np.array([W_M / 2, H_M / 2, 0.0])
        if _inside(LEFT, T) and _inside(RIGHT, T_RIGHT_LEFT @ T):
            return T


def render_pairs(n: int, seed: int, bad: set[int] = frozenset()):
    """n (left, right) image pairs; in the pairs of ``bad`` the board moved by 2 cm and 1.5 deg
    between the two exposures."""
    rng = np.random.default_rng(seed)
    rays = (_rays(LEFT), _rays(RIGHT))
    out = []
    for i in range(n):
        T = _board_pose(rng)
        T_right = T_RIGHT_LEFT @ T
        if i in bad:
            move = np.eye(4)
            move[:3, :3] = Rotation.from_euler("z", 1.5, degrees=True).as_matrix()
            move[:3, 3] = (0.0, 0.02, 0.0)
            T_right = T_RIGHT_LEFT @ T @ move
        out.append((_render(rays[0], T, rng), _render(rays[1], T_right, rng)))
    return out


def write_pair_folders(root: Path, pairs, names=None) -> tuple[Path, Path]:
    left, right = root / "left", root / "right"
    left.mkdir(parents=True, exist_ok=True)
    right.mkdir(parents=True, exist_ok=True)
    for i, (a, b) in enumerate(pairs):
        name = names[i] if names else f"pair_{i:03d}"
        cv2.imwrite(str(left / f"{name}.png"), a)
        cv2.imwrite(str(right / f"{name}.png"), b)
    return left, right


@pytest.fixture(scope="module")
def pairs():
    return render_pairs(N_PAIRS, seed=7, bad={int(BAD_PAIR[-3:])})


@pytest.fixture(scope="module")
def folders(pairs, tmp_path_factory) -> tuple[Path, Path]:
    return write_pair_folders(tmp_path_factory.mktemp("stereo"), pairs)


@pytest.fixture(scope="module")
def camera_files(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("cams")
    return save_camera(root / "left.yaml", LEFT)[0], save_camera(root / "right.yaml", RIGHT)[0]


def _pose_errors(rig: StereoRig) -> tuple[float, float]:
    """(relative baseline error, rotation error in deg) against the truth."""
    base = abs(rig.baseline_m - BASELINE_M) / BASELINE_M
    rot = rotation_angle_deg(rig.T_right_left[:3, :3], R_RIGHT_LEFT)
    return base, rot


# --------------------------------------------------------------------------- calibration


def test_fixed_intrinsics_recover_T_right_left_and_reject_the_planted_pair(folders, camera_files):
    result = calibrate_stereo(*folders, CFG, *camera_files)
    rig = result.rig
    base, rot = _pose_errors(rig)
    print(f"fixed: baseline {rig.baseline_m:.5f} m ({base:.3%}), rotation error {rot:.4f} deg, "
          f"rms {rig.rms_px:.3f} px, epipolar {result.epipolar_rms_px:.4f} px")  # fmt: skip
    assert base < 0.01 and rot < 0.2
    np.testing.assert_allclose(rig.T_right_left[:3, 3], T_RIGHT_LEFT[:3, 3], atol=2e-3)
    assert result.epipolar_rms_px < 0.15 and result.rectified_dy_rms_px < 0.2
    bad = {p.name: p for p in result.pairs}[BAD_PAIR]
    assert (bad.status, bad.reason) == ("rejected", "outlier"), bad
    assert "median" in bad.detail and "without it baseline" in bad.detail
    assert bad.epipolar_px > 5 * result.epipolar_rms_px  # the reason is visible in its error
    used = [p for p in result.pairs if p.status == "used"]
    assert len(used) == N_PAIRS - 1
    assert all(p.epipolar_px < 0.5 and p.error_px < 0.5 for p in used)
    assert rig.left == LEFT and rig.right == RIGHT  # fixed: CALIB_FIX_INTRINSIC
    # rectified: the right P carries Tx = -fx' * baseline (ROS's stereo convention)
    assert rig.P2[0, 3] == pytest.approx(-rig.P2[0, 0] * rig.baseline_m, rel=1e-3)
    assert any(BAD_PAIR in n and "outlier" in n for n in result.notes)


def test_joint_intrinsics_recover_K_and_T_right_left(folders):
    cfg = StereoConfig(intrinsics=IntrinsicsConfig(cols=COLS, rows=ROWS, square_mm=20.0,
                                                   distortion_model="k1k2p1p2"))  # fmt: skip
    result = calibrate_stereo(*folders, cfg)
    rig = result.rig
    base, rot = _pose_errors(rig)
    print(f"joint: baseline {rig.baseline_m:.5f} m ({base:.3%}), rotation error {rot:.4f} deg, "
          f"fx {rig.left.fx_px:.2f}/{rig.right.fx_px:.2f} px, rms {rig.rms_px:.3f} px")  # fmt: skip
    assert base < 0.01 and rot < 0.2
    for got, truth in ((rig.left, LEFT), (rig.right, RIGHT)):
        assert abs(got.fx_px - truth.fx_px) / truth.fx_px < 0.01
        assert abs(got.cx_px - truth.cx_px) < 5.0 and abs(got.cy_px - truth.cy_px) < 5.0
    assert result.intrinsics_fitted
    assert {p.name: p for p in result.pairs}[BAD_PAIR].reason == "outlier"
    assert result.per_camera["left"]["views_with_pattern"] == N_PAIRS


# --------------------------------------------------------------------------- CLI


@dataclasses.dataclass
class _Run:
    exit_code: int
    output: str


@pytest.fixture
def invoke(run_cli):
    """Run ``calibration ARGS`` through the console entry point (errors as a user sees them)."""

    def run(args) -> _Run:
        r = run_cli(calibration_cli.main, *args)
        return _Run(r.code, r.out + r.err)

    return run


TARGET_ARGS = ("--cols", COLS, "--rows", ROWS, "--square-mm", 20)


def test_cli_end_to_end_on_folders(invoke, folders, tmp_path):
    out = tmp_path / "rig" / "stereo.yaml"
    out.parent.mkdir()
    res = invoke(["stereo", *folders, *TARGET_ARGS, "--distortion-model", "k1k2p1p2",
                   "--maps", "--out", out])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "pairs: 12 read, 11 used; rejected: outlier 1" in res.output
    assert f"pair {BAD_PAIR} rejected as an outlier" in res.output
    rig = load_stereo(out)
    assert load_stereo(out.with_suffix(".json")).T_right_left.tolist() == rig.T_right_left.tolist()
    base, rot = _pose_errors(rig)
    assert base < 0.01 and rot < 0.2
    report = json.loads((tmp_path / "rig" / "stereo_report.json").read_text())
    assert report["pairs"]["used"] == 11
    assert report["baseline_m"] == pytest.approx(BASELINE_M, rel=0.01)
    assert report["epipolar_rms_px"] < 0.1
    assert report["config"]["intrinsics"]["cols"] == COLS and "git" in report["provenance"]
    assert {p["name"]: p["reason"] for p in report["per_pair"]}[BAD_PAIR] == "outlier"
    assert report["rectification"]["maps"]["file"] == "stereo_rectify_maps.npz"
    maps = np.load(tmp_path / "rig" / "stereo_rectify_maps.npz")
    assert maps["left_x"].shape == (H_PX, W_PX)
    assert (tmp_path / "rig" / "stereo_errors.png").stat().st_size > 1000
    # the camera files, the ROS camera_info pair and the Kalibr camchain agree with the rig
    assert load_camera(tmp_path / "rig" / "stereo_left.yaml")[0] == rig.left
    from uwdock.calibration.formats import read_camera_yaml, read_yaml_mapping
    from uwdock.calibration.stereo_formats import stereo_from_ros_pair

    ros = stereo_from_ros_pair(tmp_path / "rig" / "stereo_left_camera_info.yaml",
                               tmp_path / "rig" / "stereo_right_camera_info.yaml")  # fmt: skip
    right_info = read_camera_yaml(tmp_path / "rig" / "stereo_right_camera_info.yaml")
    assert right_info.P[0, 3] == pytest.approx(-right_info.P[0, 0] * rig.baseline_m, rel=1e-9)
    np.testing.assert_allclose(ros.T_right_left, rig.T_right_left, atol=1e-9)
    chain = read_yaml_mapping(tmp_path / "rig" / "stereo_camchain.yaml")
    assert np.array(chain["cam1"]["T_cn_cnm1"]).tolist() == rig.T_right_left.tolist()
    assert all(maps[k].dtype == np.float32 for k in ("left_x", "left_y", "right_x", "right_y"))


def test_cli_round_trips_are_bit_identical(invoke, tmp_path):
    rig = StereoRig.from_cameras(
        dataclasses.replace(LEFT, dist=(-0.08, 0.02, 0.001, -0.0005)), RIGHT, T_RIGHT_LEFT,
        rms_px=0.1, left_topic="/stereo/left/image_raw", right_topic="/stereo/right/image_raw",
    )  # fmt: skip
    save_stereo(tmp_path / "a.yaml", rig)
    for fmt in ("kalibr", "ros"):
        first = [tmp_path / f"{fmt}1_{s}.yaml" for s in ("l", "r")]
        second = [tmp_path / f"{fmt}2_{s}.yaml" for s in ("l", "r")]
        right1 = ["--right-out", first[1]] if fmt == "ros" else []
        res = invoke(["export", tmp_path / "a.yaml", "--format", fmt, "--out", first[0], *right1])
        assert res.exit_code == 0, res.output
        back = tmp_path / f"{fmt}_back.yaml"
        right_in = ["--right", first[1]] if fmt == "ros" else []
        res = invoke(["import", first[0], "--format", fmt, "--out", tmp_path / f"{fmt}_cam.yaml",
                       "--stereo-out", back, *right_in])  # fmt: skip
        assert res.exit_code == 0, res.output
        assert "stereo pair" in res.output
        right2 = ["--right-out", second[1]] if fmt == "ros" else []
        res = invoke(["export", back, "--format", fmt, "--out", second[0], *right2])
        assert res.exit_code == 0, res.output
        n = 2 if fmt == "ros" else 1
        for a, b in zip(first[:n], second[:n], strict=True):
            assert a.read_bytes() == b.read_bytes(), fmt
        got = load_stereo(back)
        assert got.left.dist[:4] == rig.left.dist and got.right.K.tolist() == rig.right.K.tolist()
        np.testing.assert_allclose(got.T_right_left, rig.T_right_left, atol=1e-12)
    kalibr_rig = load_stereo(tmp_path / "kalibr_back.yaml")
    assert kalibr_rig.T_right_left.tolist() == rig.T_right_left.tolist()  # as read, exactly
    assert kalibr_rig.left_topic == "/stereo/left/image_raw"


# --------------------------------------------------------------------------- refusals


def _one_line(res, *fragments: str) -> str:
    assert res.exit_code != 0, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1, res.output
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def test_one_line_errors(invoke, pairs, folders, camera_files, tmp_path):
    left, right = folders
    out = ["--out", tmp_path / "s.yaml", *TARGET_ARGS]
    # pairs are matched by name
    other = write_pair_folders(tmp_path / "other", pairs[:3], names=["a", "b", "c"])[1]
    _one_line(invoke(["stereo", left, other, *out]), "no image of", "same name")
    short = write_pair_folders(tmp_path / "short", pairs[:11])[1]
    _one_line(invoke(["stereo", left, short, *out]), "12 images", "11 in", "--skip-unpaired")
    # different image sizes
    small = tmp_path / "small"
    small.mkdir()
    for p in sorted(right.iterdir()):
        cv2.imwrite(str(small / p.name), cv2.resize(cv2.imread(str(p)), (320, 240)))
    _one_line(invoke(["stereo", left, small, *out]), "640x480", "320x240", "one image size")
    # a camera file of another size
    big = save_camera(tmp_path / "big.yaml", LEFT.scaled(1280, 960))[0]
    res = invoke(["stereo", left, right, "--left-camera", big, "--right-camera",
                   camera_files[1], *out])  # fmt: skip
    _one_line(res, "left camera file is 1280x960", "640x480")
    _one_line(invoke(["stereo", left, right, "--left-camera", camera_files[0], *out]),
              "both --left-camera and --right-camera")  # fmt: skip
    # fewer than MIN_VIEWS usable pairs
    few_l, few_r = write_pair_folders(tmp_path / "few", pairs[: MIN_VIEWS - 1])
    _one_line(invoke(["stereo", few_l, few_r, *out]), f"only {MIN_VIEWS - 1} usable pairs",
              f"at least {MIN_VIEWS}")  # fmt: skip
    _one_line(invoke(["stereo", left, *out]), "give the right camera's input")
    assert not (tmp_path / "s.yaml").exists()


def test_skip_unpaired_goes_on_with_a_note(invoke, pairs, folders, camera_files, tmp_path):
    short = write_pair_folders(tmp_path / "short", pairs[:10])[1]
    res = invoke(["stereo", folders[0], short, "--skip-unpaired", "--left-camera",
                   camera_files[0], "--right-camera", camera_files[1], "--out",
                   tmp_path / "s.yaml", *TARGET_ARGS])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "2 without a partner" in res.output and "pairs: 10 read" in res.output


# --------------------------------------------------------------------------- bag


def _write_bag(path: Path, pairs, stamp_offset_ns: int = 1_000_000) -> Path:
    """Two mono8 image topics, 100 ms apart, the right ones ``stamp_offset_ns`` later, plus a
    left frame without a partner."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header, Image = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"], T[
        "sensor_msgs/msg/Image"]  # fmt: skip

    def msg(img, ns, frame):
        h, w = img.shape
        header = Header(Time(sec=ns // 10**9, nanosec=ns % 10**9), frame)
        return Image(header=header, height=h, width=w, encoding="mono8", is_bigendian=0,
                     step=w, data=img.ravel())  # fmt: skip

    t0 = 1_700_000_000 * 10**9
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {t: writer.add_connection(t, "sensor_msgs/msg/Image", typestore=ts)
                 for t in ("/stereo/left/image_raw", "/stereo/right/image_raw")}  # fmt: skip
        for i, (a, b) in enumerate(pairs):
            ns = t0 + i * 100_000_000
            for topic, img, dt in (("/stereo/left/image_raw", a, 0),
                                   ("/stereo/right/image_raw", b, stamp_offset_ns)):  # fmt: skip
                writer.write(
                    conns[topic],
                    ns + dt,
                    ts.serialize_cdr(msg(img, ns + dt, "cam"), "sensor_msgs/msg/Image"),
                )
        ns = t0 + len(pairs) * 100_000_000
        writer.write(
            conns["/stereo/left/image_raw"],
            ns,
            ts.serialize_cdr(msg(pairs[0][0], ns, "cam"), "sensor_msgs/msg/Image"),
        )
    (storage,) = sorted(path.glob("*.mcap"))
    return storage


def test_bag_with_two_topics_pairs_by_stamp(invoke, pairs, camera_files, tmp_path):
    bag = _write_bag(tmp_path / "rig", pairs[:8])
    res = invoke(["stereo", bag, "--left-topic", "/stereo/left/image_raw", "--right-topic",
                   "/stereo/right/image_raw", "--left-camera", camera_files[0],
                   "--right-camera", camera_files[1], "--out", tmp_path / "s.yaml",
                   *TARGET_ARGS])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "1 of 17 messages have no partner within 5 ms" in res.output
    assert "pairs: 8 read, 7 used; rejected: outlier 1" in res.output
    rig = load_stereo(tmp_path / "s.yaml")
    base, rot = _pose_errors(rig)
    assert base < 0.01 and rot < 0.2
    assert rig.left_topic == "/stereo/left/image_raw"
    text = (tmp_path / "s_camchain.yaml").read_text()
    assert "rostopic: /stereo/right/image_raw" in text
    # stamps 1 ms apart do not pair within 0.5 ms; no topics: the bag's image topics are named
    _one_line(invoke(["stereo", bag, "--left-topic", "/stereo/left/image_raw", "--right-topic",
                       "/stereo/right/image_raw", "--pair-tolerance-ms", 0.5, "--out",
                       tmp_path / "t.yaml", *TARGET_ARGS]), "within 0.5 ms")  # fmt: skip
    _one_line(invoke(["stereo", bag, "--out", tmp_path / "t.yaml"]),
              "/stereo/left/image_raw, /stereo/right/image_raw")  # fmt: skip


def test_videos_pair_by_frame_index(invoke, pairs, camera_files, tmp_path):
    paths = [tmp_path / "left.avi", tmp_path / "right.avi"]
    for side, path in enumerate(paths):
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (W_PX, H_PX), False
        )
        for pair in pairs[:8]:
            writer.write(pair[side])
        writer.release()
    res = invoke(["stereo", *paths, "--left-camera", camera_files[0], "--right-camera",
                  camera_files[1], "--out", tmp_path / "s.yaml", *TARGET_ARGS])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "pairs: 8 read, 7 used; rejected: outlier 1" in res.output
    base, rot = _pose_errors(load_stereo(tmp_path / "s.yaml"))
    assert base < 0.01 and rot < 0.2
    report = json.loads((tmp_path / "s_report.json").read_text())
    assert {p["name"]: p["reason"] for p in report["per_pair"]}["frame_000005"] == "outlier"
