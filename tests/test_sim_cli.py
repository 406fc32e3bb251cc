"""``datasets render`` and ``rl episode`` through the CLI runner, and their input errors.

Rendering tests are marked ``render`` (SAPIEN on lavapipe or a GPU).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV
from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.datasets import cli as datasets_cli
from uwdock.rl import cli as rl_cli
from uwdock.sim import cli as sim_cli
from uwdock.sim.water import PRESET_ORDER, PRESETS

T_WD = make_T(t=[0.0, 0.0, 4.98])  # default DS pose: tank floor (5 m deep) at the tank centre


def _one_line_error(res) -> None:
    assert res.code != 0
    lines = res.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.err


def test_bad_inputs(run_cli, tmp_path):
    out = tmp_path / "out"
    res = run_cli(datasets_cli.main, "render", "--out", out, "--n", "1", "--water", "lagoon")
    _one_line_error(res)
    assert "lagoon" in res.err
    _one_line_error(run_cli(datasets_cli.main, "render", "--out", out, "--n", "0"))
    poses = tmp_path / "poses.csv"
    poses.write_text("x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg\n0,0,2,0,0,0\n")
    res = run_cli(datasets_cli.main, "render", "--out", out, "--n", "1", "--poses", poses)
    _one_line_error(res)
    assert "either" in res.err
    poses.write_text("x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg\n0,0,2,0,zero,0\n")
    res = run_cli(datasets_cli.main, "render", "--out", out, "--poses", poses)
    _one_line_error(res)
    assert "line 2" in res.err
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    _one_line_error(run_cli(datasets_cli.main, "render", "--out", blocker / "sub", "--n", "1"))
    res = run_cli(rl_cli.main, "episode", "--out", out, "--water", "lagoon")
    _one_line_error(res)
    _one_line_error(run_cli(rl_cli.main, "episode", "--out", out, "--seconds", "0"))
    _one_line_error(run_cli(rl_cli.main, "episode", "--out", blocker / "sub", "--seconds", "1"))
    cfg = tmp_path / "env.toml"
    cfg.write_text("episode_s = [\n")
    _one_line_error(run_cli(rl_cli.main, "episode", "--out", out, "--config", cfg))
    cfg.write_text("spawn_auv_height_m = 0.5\n")  # inside the DS: EnvConfig.validate refuses
    res = run_cli(rl_cli.main, "episode", "--out", out, "--config", cfg)
    _one_line_error(res)
    assert "spawn_auv_height_m" in res.err
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.render
def test_render_random_and_given_poses(run_cli, tmp_path):
    out = tmp_path / "random"
    res = run_cli(datasets_cli.main, "render", "--out", out, "--n", "3", "--width", "96", "--quiet")
    assert res.code == 0, res.err
    labels = [json.loads(s) for s in (out / "labels.jsonl").read_text().splitlines()]
    assert [lab["frame"] for lab in labels] == [0, 1, 2]
    assert all(lab["water"] is None for lab in labels)  # datasets render default: the clean render
    assert cv2.imread(str(out / "images" / "000002.png")).shape == (73, 96, 3)

    # given poses: 2 m and 3 m above the DS floor, level, yawed
    poses = tmp_path / "poses.csv"
    poses.write_text(
        "x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg,note\n0.2,-0.1,2.98,0,0,30,a\n-0.5,0.3,1.98,0,0,-90,b\n"
    )
    out = tmp_path / "given"
    res = run_cli(
        datasets_cli.main, "render", "--out", out, "--poses", poses, "--width", "120",
        "--water", "coastal", "--quiet",
    )  # fmt: skip
    assert res.code == 0, res.err
    labels = [json.loads(s) for s in (out / "labels.jsonl").read_text().splitlines()]
    given = [
        make_T(R_from_rpy(0, 0, np.radians(30)), [0.2, -0.1, 2.98]),
        make_T(R_from_rpy(0, 0, np.radians(-90)), [-0.5, 0.3, 1.98]),
    ]
    for lab, T_wb in zip(labels, given, strict=True):
        np.testing.assert_allclose(lab["T_world_body"], T_wb, atol=1e-12)
        p_cam = (T_wb @ REFERENCE_T_BODYFRD_CAMCV)[:3, 3]  # camera 0.45 m below the origin
        assert lab["range_m"] == pytest.approx(np.linalg.norm(T_WD[:3, 3] - p_cam), abs=1e-9)
        assert lab["water"]["preset"] == "coastal"
    # the level camera looks straight down: view angle = atan(horizontal / vertical offset)
    p_cam = (given[0] @ REFERENCE_T_BODYFRD_CAMCV)[:3, 3]
    d = T_WD[:3, 3] - p_cam
    expected_deg = np.degrees(np.arctan2(np.hypot(d[0], d[1]), d[2]))
    assert labels[0]["view_angle_deg"] == pytest.approx(expected_deg)


@pytest.mark.render
def test_episode_video(run_cli, tmp_path):
    out = tmp_path / "ep"
    res = run_cli(
        rl_cli.main, "episode", "--out", out, "--seconds", "2", "--width", "96",
        "--outside-width", "96", "--seed", "1", "--water", "turbid", "--quiet",
    )  # fmt: skip
    assert res.code == 0, res.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 10 and summary["frames"] == 11  # 5 Hz for 2 s + the reset frame
    assert summary["sim_time_s"] == pytest.approx(2.0, abs=1e-6)
    assert summary["truncated"] and summary["controller"] == "pid"
    cap = cv2.VideoCapture(str(out / "episode.mp4"))
    assert cap.isOpened()
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 11
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(5.0)
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    assert len(frames) == 11
    h, w = frames[0].shape[:2]
    assert [w, h] == summary["size_px"] and h == 72  # panels scaled to 3/4 of 96, even
    # the two panels differ (downward water view vs outside view)
    left, right = frames[-1][:, : w // 2].astype(float), frames[-1][:, w // 2 :].astype(float)
    assert np.abs(left.mean(axis=(0, 1)) - right.mean(axis=(0, 1))).max() > 3.0
    assert (out / "config.toml").is_file() and (out / "provenance.json").is_file()


def test_sim_water_lists_the_presets(run_cli):
    """``sim water``: every preset, clearest first, with the numbers of its WaterConfig."""
    res = run_cli(sim_cli.main, "water", "--json")
    assert res.code == 0, res.err
    data = json.loads(res.out)
    assert list(data) == list(PRESET_ORDER)
    for name in PRESET_ORDER:
        assert data[name]["beta_D_rgb"] == pytest.approx(list(PRESETS[name].beta_D_rgb))
        assert data[name]["blur_sigma_per_m"] == PRESETS[name].blur_sigma_per_m
    res = run_cli(sim_cli.main, "water")
    assert res.code == 0
    lines = res.out.strip().splitlines()
    assert [line.split()[0] for line in lines] == list(PRESET_ORDER)
    beta_d = [float(v) for v in lines[1].split("beta_D ")[1].split()[:3]]
    assert beta_d == pytest.approx(PRESETS["coastal"].beta_D_rgb, abs=5e-4)
