"""Files the toolkit reads are checked before use (issue 32, "nothing accepted silently"):
error models with NaN or out-of-domain values, a policy folder that disagrees with its own run
config, physically impossible camera files. Each is one line naming the key and the value."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.error_models import synthetic_model
from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import (
    check_plausible,
    load_camera,
    radial_distortion,
    reference_camera,
    save_camera,
)
from uwdock.dockcore.errors import DockError
from uwdock.rl import cli as rl_cli
from uwdock.rl.env.error_model import load_error_model

ROOT = Path(__file__).resolve().parent.parent
SHIPPED_POLICY = ROOT / "rl" / "policies" / "error_model_ppo"


def _one_line(res) -> str:
    """The single ``error:`` line of a refused command (exit status 2)."""
    assert res.code == 2, (res.code, res.out, res.err)
    assert "Traceback" not in res.err, res.err
    errors = [line for line in res.err.splitlines() if line.startswith("error")]
    assert len(errors) == 1, res.err
    return errors[0]


# ----------------------------------------------------------------------------- error models

_SD = np.array([0.02, 0.02, 0.05, 0.01, 0.01, 0.02])


def _model(**edit) -> dict:
    data = synthetic_model(0.8, np.zeros(6), np.diag(_SD**2))
    table = data["tables"]["all"]
    for key, value in edit.items():
        if key == "p_detect":
            table["p_detect"][3][1] = value
        elif key == "p_outlier":
            table["bins"][2]["p_outlier"] = value
        elif key == "bias":
            table["bins"][5]["bias"][0] = value
        elif key == "variance":
            table["bins"][1]["cov"][2][2] = value
        elif key == "outliers":
            table["bins"][0]["outliers"] = [[value, 0, 0, 0, 0, 0]]
        elif key == "range_bin_m":
            data["config"]["range_bin_m"] = value
        elif key == "fx_px":
            data["camera"]["fx_px"] = value
        elif key == "corners":
            data["board_corners_ds_m"][0][0][0] = value
    return data


@pytest.mark.parametrize(
    "edit, key",
    [
        ({"p_detect": float("nan")}, "tables.all.p_detect[3][1]"),
        ({"p_detect": 1.5}, "tables.all.p_detect[3][1]"),
        ({"p_detect": -0.1}, "tables.all.p_detect[3][1]"),
        ({"p_outlier": float("inf")}, "tables.all.bins[2].p_outlier"),
        ({"p_outlier": 2.0}, "tables.all.bins[2].p_outlier"),
        ({"bias": float("nan")}, "tables.all.bins[5].bias[0]"),
        ({"variance": -1e-4}, "tables.all.bins[1].cov diagonal (variances)[2]"),
        ({"variance": float("-inf")}, "tables.all.bins[1].cov[2][2]"),
        ({"outliers": float("nan")}, "tables.all.bins[0].outliers[0][0]"),
        ({"range_bin_m": -0.5}, "config.range_bin_m"),
        ({"range_bin_m": float("nan")}, "config.range_bin_m"),
        ({"fx_px": 1e-9}, "camera.fx_px"),
        ({"corners": float("inf")}, "board_corners_ds_m[0][0][0]"),
    ],
)
def test_error_model_values_out_of_their_domain_are_refused(tmp_path, edit, key):
    """NaN detection probabilities gave exit 0 and 0 % strict success instead of 100 %."""
    path = tmp_path / "em.json"
    path.write_text(json.dumps(_model(**edit)))  # NaN and inf as JSON's NaN / Infinity
    with pytest.raises(DockError) as exc:
        load_error_model(path)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg and f"({key}: " in msg, msg


def test_error_model_in_domain_loads_and_its_sampler_agrees(tmp_path):
    """The checks do not refuse a valid model: p = 0 and p = 1, zero variances."""
    data = _model(p_detect=1.0, p_outlier=0.0, variance=0.0)
    path = tmp_path / "em.json"
    path.write_text(json.dumps(data))
    model = load_error_model(path)
    assert model.table("all")["p"][3, 1] == 1.0 and model.table("all")["cov"][1, 2, 2] == 0.0
    for shipped in sorted((ROOT / "rl" / "models").glob("*.json")):
        load_error_model(shipped)


@pytest.mark.parametrize("command", ["eval", "trajectories"])
def test_nan_error_model_stops_rl_commands_with_one_line(run_cli, tmp_path, command):
    path = tmp_path / "em.json"
    path.write_text(json.dumps(_model(p_detect=float("nan"))))
    out = tmp_path / "o"
    args = ["--obs", "error-model", "--error-model", path, "--episodes", "1", "--out", out]
    if command == "eval":
        args = ["--policy", "pid", *args]
    msg = _one_line(run_cli(rl_cli.main, command, *args))
    assert "tables.all.p_detect[3][1]: must be a finite number in [0, 1], got nan" in msg
    assert not out.exists()


def test_nan_error_model_stops_rl_train_with_one_line(run_cli, tmp_path):
    path = tmp_path / "em.json"
    path.write_text(json.dumps(_model(p_outlier=float("nan"))))
    out = tmp_path / "run"
    res = run_cli(
        rl_cli.main, "train", "--obs", "error-model", "--error-model", path, "--steps", "64",
        "--envs", "1", "--out", out,
    )  # fmt: skip
    assert "tables.all.bins[2].p_outlier: must be" in _one_line(res)
    assert not out.exists()


# ----------------------------------------------------------------------------- policy folders


def _policy_without_normalisation(tmp_path: Path) -> Path:
    """The shipped policy written again without its normalisation (its config says
    normalize_obs = true)."""
    from uwdock.rl.policy.policy_format import write_policy
    from uwdock.rl.policy.policy_io import load_policy

    folder = tmp_path / "policy"
    model, _ = load_policy(SHIPPED_POLICY)
    write_policy(folder, model, None)
    shutil.copy(SHIPPED_POLICY / "config.toml", folder / "config.toml")
    return folder


def test_policy_folder_missing_its_normalisation_is_refused(run_cli, tmp_path):
    """``rl eval`` gave 0 % strict success instead of 100 %; ``rl export`` wrote an ONNX
    without the normalisation."""
    from uwdock.rl.policy.policy_io import load_policy

    assert "normalize_obs = true" in (SHIPPED_POLICY / "config.toml").read_text()
    folder = _policy_without_normalisation(tmp_path)
    expected = "says normalize_obs = true but its model.json has no observation normalisation"
    with pytest.raises(DockError, match=expected):
        load_policy(folder)
    out = tmp_path / "e"
    res = run_cli(
        rl_cli.main, "eval", "--policy", folder, "--obs", "proxy", "--episodes", "1",
        "--out", out,
    )  # fmt: skip
    assert expected in _one_line(res) and not out.exists()
    onnx = tmp_path / "p.onnx"
    res = run_cli(rl_cli.main, "export", "--policy", folder, "--out", onnx)
    assert expected in _one_line(res)
    assert not onnx.exists() and not onnx.with_suffix(".json").exists()
    # best/ reads the run config one level up
    best = folder / "best"
    best.mkdir()
    for name in ("model.json", "weights.npz"):
        shutil.copy(folder / name, best / name)
    with pytest.raises(DockError, match=expected):
        load_policy(best)
    # the shipped folder, complete, loads
    _, vecnorm = load_policy(SHIPPED_POLICY)
    assert vecnorm is not None and vecnorm.norm_obs


# ----------------------------------------------------------------------------- camera files


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"fx_px": 1e-9}, "fx_px: 1e-09 px gives a field of view of 180 deg across 968 px"),
        ({"fy_px": 1e7}, "fy_px: 1e+07 px gives a field of view of"),
        ({"cx_px": -1e6}, "cx_px: the principal point must lie inside the image"),
        ({"cy_px": 900.0}, "cy_px: the principal point must lie inside the image"),
        ({"dist": (1000.0, 0.0, 0.0, 0.0, 0.0)}, "dist: (1000, 0, 0, 0, 0) scales the radius by"),
        ({"dist": (0.0, 0.0, 0.0, 0.0, 1e5)}, "scales the radius by"),
        ({"dist": (-0.9, 0.0, 0.0, 0.0, 0.0)}, "is not monotonic over the image"),
        ({"dist": (0.0,) * 5 + (-5.0, 0.0, 0.0)}, "is not monotonic over the image"),  # a pole
    ],
)
def test_physically_impossible_camera_files_are_refused(run_cli, tmp_path, change, fragment):
    """fx = 1e-9 px, cx = -1e6, k1 = 1000 or k3 = 1e5 gave poses of 0.26 m for 1.43 m,
    x = 1216 m, or silently none."""
    cam = dataclasses.replace(reference_camera(), **change)  # the constructor accepts them
    for suffix in (".yaml", ".json"):
        path = tmp_path / f"bad{suffix}"
        save_camera(path, cam)
        path.with_suffix(".json" if suffix == ".yaml" else ".yaml").unlink()
        with pytest.raises(DockError) as exc:
            load_camera(path)
        msg = str(exc.value)
        assert msg.startswith(f"{path}: ") and fragment in msg and "\n" not in msg, msg
    msg = _one_line(run_cli(calibration_cli.main, "extrinsics", "show", path))
    assert fragment in msg


def test_monotonic_check_measures_the_distortion_it_names():
    """The fold is where d(r_d)/dr = 0: for r_d = r (1 + k1 r^2), r = sqrt(-1 / (3 k1))."""
    cam = dataclasses.replace(reference_camera(), dist=(-0.9, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"stops growing at normalised radius 0\.60"):
        check_plausible(cam)
    assert np.sqrt(1 / 2.7) == pytest.approx(0.6086, abs=1e-4)
    r = np.array([0.0, 0.5, 1.0])
    np.testing.assert_allclose(radial_distortion(cam, r), r * (1 - 0.9 * r**2))


def test_reference_shipped_and_real_cameras_pass():
    check_plausible(reference_camera())
    for width in (320, 480, 640, 1920):
        check_plausible(reference_camera().scaled(width, round(width * 732 / 968)))
    # the real calibration of the tank frames (strong barrel distortion, k3 < 0)
    real, _ = load_camera(ROOT / "bench" / "results" / "water_fit_real" / "camera.yaml")
    assert real.dist[0] < -0.3
    # a lens with ordinary distortion, and the widest and narrowest pinholes allowed
    for cam in (
        dataclasses.replace(reference_camera(), dist=(-0.35, 0.1, 0.001, -0.001, 0.0)),
        reference_camera().from_hfov(968, 732, 170.0),
        reference_camera().from_hfov(968, 732, 1.5),
    ):
        check_plausible(cam)


# ----------------------------------------------------------------------------- dictionaries


def _tag_frames(folder: Path, dictionary: str, marker_id: int, n: int = 3) -> Path:
    """``n`` 320 x 240 frames of one flat tag of ``dictionary`` on white (a plain print)."""
    import cv2

    folder.mkdir()
    tag = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), marker_id, 96
    )
    for k in range(n):
        img = np.full((240, 320), 255, np.uint8)
        x = 40 + 30 * k
        img[60:156, x : x + 96] = tag
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    return folder


@pytest.mark.parametrize("command", ["eval", "detect"])
def test_wrong_dictionary_is_warned_naming_the_right_one(run_cli, tmp_path, command):
    """``perception eval`` with the wrong dictionary: detection rate 0 and no word."""
    from uwdock.perception import cli as perception_cli

    frames = _tag_frames(tmp_path / "f", "DICT_6X6_250", 7)
    cam = tmp_path / "cam.yaml"
    save_camera(cam, reference_camera().scaled(320, 240))
    args = ["--dictionary", "DICT_4X4_50", "--marker-size-m", "0.1", "--camera", cam]
    res = run_cli(perception_cli.main, command, frames, *args, "--out", tmp_path / "o")
    assert res.code == 0, res.err
    warnings = [line for line in res.err.splitlines() if line.startswith("warning: ")]
    assert warnings == [
        "warning: no marker of DICT_4X4_50 found in 3 frame(s); DICT_6X6_50 finds markers "
        "(IDs 7) in 3 of 3 sampled frame(s): pass --dictionary DICT_6X6_50 or a marker set of "
        "that dictionary"
    ], res.err
    # the right dictionary finds the tag and says nothing
    args[1] = "DICT_6X6_50"
    res = run_cli(perception_cli.main, command, frames, *args, "--out", tmp_path / "o2")
    assert res.code == 0 and "warning" not in res.err, res.err


def test_no_marker_in_any_dictionary_is_warned(run_cli, tmp_path):
    import cv2

    from uwdock.perception import cli as perception_cli

    frames = tmp_path / "f"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for k in range(7):
        cv2.imwrite(str(frames / f"{k}.png"), rng.integers(90, 160, (240, 320), dtype=np.uint8))
    cam = tmp_path / "cam.yaml"
    save_camera(cam, reference_camera().scaled(320, 240))
    res = run_cli(
        perception_cli.main, "eval", frames, "--dictionary", "DICT_4X4_50", "--marker-size-m",
        "0.1", "--camera", cam, "--out", tmp_path / "o",
    )  # fmt: skip
    assert res.code == 0, res.err
    warnings = [line for line in res.err.splitlines() if line.startswith("warning: ")]
    assert len(warnings) == 1 and "found in 7 frame(s), and none with the other" in warnings[0]
    assert "DICT_6X6" in warnings[0] and "DICT_4X4" not in warnings[0].split("(")[1]


def test_frame_sampler_spreads_over_the_stream():
    from uwdock.perception.dictionary_hint import FrameSampler

    s = FrameSampler(cap=4)
    for k in range(100):
        s.offer(np.full((1, 1), k, np.uint8))
    kept = [int(f[0, 0]) for f in s.frames]
    assert len(kept) <= 4 and kept[0] == 0 and kept[-1] >= 50, kept
    assert np.all(np.diff(kept) == s.stride)


# ----------------------------------------------------------------------------- marker sets


def test_marker_set_with_every_marker_at_one_pose_is_refused(run_cli, tmp_path):
    from uwdock.markers.config import MarkerConfig
    from uwdock.markers.markerset import load_marker_set, marker_set_from_config, save_marker_set
    from uwdock.perception import cli as perception_cli

    good = marker_set_from_config(MarkerConfig())
    one_pose = dataclasses.replace(
        good,
        markers=tuple(
            dataclasses.replace(m, T_ds_marker=good.markers[0].T_ds_marker) for m in good.markers
        ),
    )
    for suffix in (".toml", ".json"):
        path = save_marker_set(tmp_path / f"set{suffix}", one_pose)
        with pytest.raises(DockError) as exc:
            load_marker_set(path)
        msg = str(exc.value)
        assert "5 markers, 13 and 14 among them, overlap: centres 0 m apart" in msg, msg
    frames = _tag_frames(tmp_path / "f", "DICT_4X4_50", 13, n=1)
    cam = tmp_path / "cam.yaml"
    save_camera(cam, reference_camera().scaled(320, 240))
    out = tmp_path / "o"
    res = run_cli(perception_cli.main, "eval", frames, "--markers", path, "--camera", cam,
                  "--out", out)  # fmt: skip
    assert "overlap: centres 0 m apart" in _one_line(res) and not out.exists()
    # two markers 60 mm apart overlap (side 100 mm); 110 mm apart they do not
    for dx, refused in ((0.06, True), (0.11, False)):
        T = good.markers[1].T_ds_marker.copy()
        T[:3, 3] = good.markers[0].T_ds_marker[:3, 3] + [dx, 0.0, 0.0]
        near = dataclasses.replace(
            good, markers=(good.markers[0], dataclasses.replace(good.markers[1], T_ds_marker=T))
        )
        path = save_marker_set(tmp_path / "near.toml", near)
        if refused:
            with pytest.raises(
                DockError, match=r"markers 13 and 14 overlap: centres 0\.06 m apart"
            ):
                load_marker_set(path)
        else:
            assert load_marker_set(path).ids == (13, 14)


def test_marker_layout_for_ids_not_generated_is_refused(run_cli, tmp_path):
    from uwdock.markers import cli as markers_cli

    cfg = tmp_path / "m.toml"
    cfg.write_text(
        "ids = [13, 14]\n[layout]\n13 = [0.87, -1.05, -1.756, 0.0]\n"
        "41 = [0.0, 0.5, -0.26, 0.0]\n99 = [0.0, 0.0, -0.26, 0.0]\n"
    )
    out = tmp_path / "g"
    msg = _one_line(run_cli(markers_cli.main, "generate", "--config", cfg, "--out", out))
    assert "layout: entries for marker ID(s) 41, 99 that are not generated" in msg
    assert not out.exists()
    # layout poses that overlap: one line too
    cfg.write_text("ids = [13, 14]\n[layout]\n13 = [0.0, 0.0, -0.26, 0.0]\n"
                   "14 = [0.0, 0.05, -0.26, 45.0]\n")  # fmt: skip
    msg = _one_line(run_cli(markers_cli.main, "generate", "--config", cfg, "--out", out))
    assert "layout: markers 13 and 14 overlap: centres 0.05 m apart" in msg


def test_grid_placement_avoids_the_layout_and_the_default_layout_stays_quiet():
    from uwdock.markers.config import MarkerConfig
    from uwdock.markers.markerset import marker_set_from_config, overlap_complaint

    # the default layout beside other ids places nothing and is not an error
    ms = marker_set_from_config(MarkerConfig(ids=(1, 2, 3)))
    assert ms.ids == (1, 2, 3) and overlap_complaint(ms.markers) is None
    # 45 grid markers around the 5 laid-out ones: none lands on a laid-out marker
    ms = marker_set_from_config(MarkerConfig(ids=tuple(range(50))))
    assert overlap_complaint(ms.markers) is None
    np.testing.assert_allclose(ms[14].T_ds_marker[:3, 3], [0.0, -0.30, -0.26])


# ----------------------------------------------------------------------------- pose CSVs


@pytest.mark.parametrize(
    "header, row, fragment",
    [
        ("x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg", "0,0,3,0,0,1e300",
         "line 3: column 'yaw_deg' is 1e+300, outside [-100000, 100000]"),
        ("x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg", "0,0,3,nan,0,0",
         "line 3: column 'roll_deg' is not finite ('nan')"),
        ("x_m,y_m,z_m,qw,qx,qy,qz", "1e300,0,3,1,0,0,0",
         "line 3: column 'x_m' is 1e+300, outside [-1e+06, 1e+06]"),
        ("x_m,y_m,z_m,qw,qx,qy,qz", "0,0,3,1e300,1e300,0,0",
         "line 3: quaternion (qw, qx, qy, qz) has norm inf"),
        ("x_m,y_m,z_m,qw,qx,qy,qz", "0,0,3,1,0,0,x",
         "line 3: column 'qz' is not a number ('x')"),
        ("x_m,y_m,z_m,qw,qx,qy,qz,sequence,step,time_s", "0,0,3,1,0,0,0,0,1,1e300",
         "line 3: column 'time_s' is 1e+300, outside"),
    ],
)  # fmt: skip
def test_absurd_vehicle_pose_csv_is_refused_naming_row_and_column(
    run_cli, tmp_path, header, row, fragment
):
    """A yaw of 1e300 deg was rendered (its sine is noise)."""
    from uwdock.datasets import cli as datasets_cli

    first = "0,0,3," + ("1,0,0,0" if "qw" in header else "0,0,0")
    first += ",0,0,0" if "sequence" in header else ""
    poses = tmp_path / "poses.csv"
    poses.write_text(f"{header}\n{first}\n{row}\n")
    out = tmp_path / "r"
    msg = _one_line(run_cli(datasets_cli.main, "render", "--poses", poses, "--out", out))
    assert f"{poses} {fragment}" in msg, msg
    assert not out.exists()


@pytest.mark.parametrize(
    "row, fragment",
    [
        ("1,1e300,0,2,1,0,0,0", "line 3: column 'x_m' is 1e+300, outside [-1e+06, 1e+06]"),
        ("1e300,0,0,2,1,0,0,0", "line 3: column 'frame' is 1e+300, outside"),
        ("1,0,0,-inf,1,0,0,0", "line 3: column 'z_m' is not finite ('-inf')"),
    ],
)
def test_absurd_ground_truth_csv_is_refused_naming_row_and_column(tmp_path, row, fragment):
    from uwdock.perception.groundtruth import load_pose_csv

    path = tmp_path / "truth.csv"
    path.write_text(f"frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,0,0,2,1,0,0,0\n{row}\n")
    with pytest.raises(DockError) as exc:
        load_pose_csv(path)
    assert str(exc.value).startswith(f"{path} {fragment}"), exc.value


# ----------------------------------------------------------------------------- camera twins


def test_camera_twins_that_disagree_are_refused_not_rewritten(run_cli, tmp_path):
    """``extrinsics set cam.yaml`` silently rewrote a cam.json that said something else."""
    from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV

    cam_yaml, cam_json = save_camera(tmp_path / "cam.yaml", reference_camera())
    assert load_camera(cam_yaml)[0] == load_camera(cam_json)[0]  # agreeing twins load
    doc = json.loads(cam_json.read_text())
    doc["camera_matrix"][0][0] = 500.0
    cam_json.write_text(json.dumps(doc))
    before = {p: p.read_bytes() for p in (cam_yaml, cam_json)}
    for path, other in ((cam_yaml, "cam.json"), (cam_json, "cam.yaml")):
        with pytest.raises(DockError) as exc:
            load_camera(path)
        assert f"camera file {path} and its twin {other} disagree on fx_px (" in str(exc.value)
    args = ("extrinsics", "set", cam_yaml, "--xyz-m", 1, 2, 3, "--rpy-deg", 0, 0, 0)
    msg = _one_line(run_cli(calibration_cli.main, *args))
    assert "disagree on fx_px (929.7" in msg and "vs 500)" in msg
    assert {p: p.read_bytes() for p in before} == before
    # extrinsics in one twin only
    save_camera(tmp_path / "cam.yaml", reference_camera(), REFERENCE_T_BODYFRD_CAMCV)
    doc = json.loads(cam_json.read_text())
    del doc["T_body_cam"]
    cam_json.write_text(json.dumps(doc))
    with pytest.raises(DockError, match="disagree on T_body_cam"):
        load_camera(cam_yaml)
    # a broken twin is named
    cam_json.write_text("{")
    with pytest.raises(DockError, match=r"the twin of camera file .*cam\.yaml is unusable"):
        load_camera(cam_yaml)
    cam_json.unlink()  # one file alone loads
    assert load_camera(cam_yaml)[1] is not None


# ----------------------------------------------------------------------------- YAML and FIFOs

_LAUGHS = 'a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n' + "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("a: &a [*a]\n", "line 1: YAML anchors and aliases (&a) are not accepted"),
        (_LAUGHS, "line 1: YAML anchors and aliases (&a) are not accepted"),
        ("image_width: 640\nimage_height: *h\n", "line 2: YAML anchors and aliases (*h)"),
        ("camera_matrix:\n  rows: 3\n  data: &d [1, 0, 0]\n", "line 3: YAML anchors and aliases"),
    ],
)
def test_yaml_anchors_are_refused_before_any_expansion(run_cli, tmp_path, text, fragment):
    """A billion-laughs camera file hung `calibration import` (1 GB and growing); `a: &a [*a]`
    was "internal error (RecursionError)"."""
    import time

    src = tmp_path / "cam_info.yaml"
    src.write_text(text)
    out = tmp_path / "cam.yaml"
    t0 = time.perf_counter()
    msg = _one_line(run_cli(calibration_cli.main, "import", src, "--out", out))
    assert f"{src}: {fragment}" in msg and time.perf_counter() - t0 < 5.0
    assert not out.exists()


@pytest.fixture
def alarm():
    """Fail (instead of hanging the suite) when a read blocks for 20 s."""
    import signal

    def hung(signum, frame):
        raise TimeoutError("blocked on a special file")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def _fifo(path: Path) -> Path:
    import os

    os.mkfifo(path)
    return path


@pytest.mark.usefixtures("alarm")
def test_special_files_are_refused_before_reading(run_cli, tmp_path):
    """A FIFO given as an image hung; a folder or FIFO where a file is expected is one line."""
    from uwdock.perception import cli as perception_cli

    frames = _tag_frames(tmp_path / "f", "DICT_4X4_50", 13, n=1)
    cam = tmp_path / "cam.yaml"
    save_camera(cam, reference_camera().scaled(320, 240))
    out = tmp_path / "o"
    image = _fifo(tmp_path / "frame.png")
    msg = _one_line(run_cli(perception_cli.main, "detect", image, "--out", out))
    assert f"input {image} is a FIFO (named pipe), not a regular file" in msg
    video = _fifo(tmp_path / "dive.mp4")
    msg = _one_line(
        run_cli(calibration_cli.main, "intrinsics", video, "--out", tmp_path / "c.yaml")
    )
    assert f"input {video} is a FIFO" in msg
    for option, name, what in (
        ("--camera", "fifo_cam.yaml", "camera file"),
        ("--config", "fifo.toml", "config file"),
        ("--markers", "fifo_set.toml", "marker set file"),
    ):
        fifo = _fifo(tmp_path / name)
        args = ["detect", frames, "--camera", cam, option, fifo, "--out", out]
        if option == "--camera":
            args = ["detect", frames, option, fifo, "--out", out]
        msg = _one_line(run_cli(perception_cli.main, *args))
        assert f"{what} {fifo} is a FIFO (named pipe), not a regular file" in msg, msg
    msg = _one_line(run_cli(calibration_cli.main, "import", tmp_path / "fifo_cam.yaml",
                            "--out", tmp_path / "c.yaml"))  # fmt: skip
    assert "is a FIFO" in msg
    em = _fifo(tmp_path / "em.json")
    args = ["eval", "--policy", "pid", "--obs", "error-model", "--error-model", em, "--out", out]
    assert f"error model file {em} is a FIFO" in _one_line(run_cli(rl_cli.main, *args))
    # a folder where a file is expected (the CLI's own check, and the readers')
    msg = _one_line(run_cli(perception_cli.main, "detect", frames, "--camera", frames,
                            "--out", out))  # fmt: skip
    assert "is a directory" in msg
    folder = tmp_path / "cam_dir.yaml"
    folder.mkdir()
    with pytest.raises(DockError, match=f"camera file is a folder, not a file: {folder}"):
        load_camera(folder)
    assert not out.exists()


@pytest.mark.usefixtures("alarm")
def test_a_fifo_among_the_frames_of_a_folder_is_a_corrupt_frame(tmp_path):
    """A FIFO named as an image in a frame folder was left out without a word: it is a frame
    that cannot be read (None, counted in ``corrupt``), and reading it does not block."""
    from uwdock.perception.video import open_frames

    frames = _tag_frames(tmp_path / "f", "DICT_4X4_50", 13, n=2)
    _fifo(frames / "001b.png")
    source = open_frames(frames)
    got = [img is None for _index, _name, img in source]
    assert source.total == 3 and got == [False, False, True] and source.corrupt == 1


def test_an_empty_water_file_is_refused_not_rendered_as_the_default(tmp_path):
    """An empty water file (or a bare [water], or comments only) was the default water,
    rendered as coastal without a word."""
    from uwdock.sim.water import load_water_file, water_spec_error

    for text in ("", "# only a comment\n", "[water]\n"):
        path = tmp_path / "empty_water.toml"
        path.write_text(text)
        with pytest.raises(DockError, match="sets no water value"):
            load_water_file(path)
        assert "sets no water value" in water_spec_error(str(path))
    path.write_text("[water]\nbeta_D_rgb = [0.4, 0.2, 0.3]\n")  # one value: the rest default
    assert load_water_file(path).beta_D_rgb == (0.4, 0.2, 0.3)


@pytest.mark.render
@pytest.mark.usefixtures("alarm")
def test_synth_resume_over_a_fifo_in_images_is_refused_then_completes(tmp_path):
    """A FIFO where a frame's image was hung the resume (it opened the FIFO to check the PNG).
    A special file is never replaced: the resume stops in one line naming it, the FIFO left as
    it was; once it is removed, the rerun completes the dataset."""
    import stat

    from tests.hostile_runs import dataset
    from uwdock.datasets.synth import SynthConfig, generate

    cfg = SynthConfig(n_frames=3, seed=4, width_px=64)
    out, reference = tmp_path / "ds", tmp_path / "ref"
    generate(out, cfg, progress=False)
    fifo = out / "images" / "000001.png"
    fifo.unlink()
    _fifo(fifo)
    with pytest.raises(DockError, match=r"000001\.png is a FIFO"):
        generate(out, cfg, progress=False)
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    fifo.unlink()
    assert generate(out, cfg, progress=False).rendered == (1,)
    generate(reference, cfg, progress=False)
    assert dataset(out) == dataset(reference)
