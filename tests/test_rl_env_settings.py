"""Honest defaults (issue 30 point 5): `rl eval`, `rl episode`, `rl export` and the deployment
runner run a policy in its training env (USBL, water, camera width, termination) unless a flag
or --config says otherwise, and say where each setting came from; the shipped weights match
their recorded checksums."""

from __future__ import annotations

import csv
import hashlib
import json
import shutil
from pathlib import Path

import pytest

from uwdock.rl import cli

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "rl" / "policies" / "scratch_error_model_ppo"


@pytest.fixture
def policy_dir(tmp_path: Path) -> Path:
    """The shipped weights in a run folder whose config says settings no command defaults to:
    the Cerulean USBL, a drifting navigation, coastal water, 320 px, the paper's termination."""
    folder = tmp_path / "policy"
    folder.mkdir()
    for name in ("model.json", "weights.npz"):
        shutil.copy(SHIPPED / name, folder / name)
    text = (SHIPPED / "config.toml").read_text()
    swaps = (
        ('preset = "evologics-s2cr"', 'preset = "cerulean-rovl"'),
        ('water_preset = "clear_tank"', 'water_preset = "coastal"'),
        ("camera_width_px = 480", "camera_width_px = 320"),
        ('terminate_on = "strict"', 'terminate_on = "paper"'),
    )
    for old, new in swaps:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    assert "[train.env.nav]" not in text
    text += '\n[train.env.nav]\npreset = "mems-ahrs-dvl"\n'
    (folder / "config.toml").write_text(text)
    return folder


@pytest.fixture
def short(tmp_path: Path) -> Path:
    cfg = tmp_path / "short.toml"
    cfg.write_text("episode_s = 2.0\n")
    return cfg


def _eval(run_cli, out: Path, short: Path, *args):
    res = run_cli(
        cli.main, "eval", "--episodes", "1", "--obs", "acoustic", "--config", short,
        "--videos", "", "--out", out, *args,
    )  # fmt: skip
    assert res.code == 0, res.err
    summary = json.loads((out / "summary.json").read_text())
    with (out / "episodes.csv").open() as fh:
        row = next(csv.DictReader(fh))
    return res.out.splitlines()[0], summary, row


def test_eval_runs_the_policys_training_env_unless_a_flag_overrides_it(
    run_cli, tmp_path, policy_dir, short
):
    line, summary, row = _eval(run_cli, tmp_path / "e", short, "--policy", policy_dir)
    assert f"[policy: {policy_dir / 'config.toml'}]" in line
    for said in (
        "usbl cerulean-rovl (policy config)",
        "nav mems-ahrs-dvl (policy config)",
        "water coastal (policy config)",
        "camera_width_px 320 (policy config)",
        "terminate_on paper (policy config)",
        "obs acoustic (flag)",
        "episode_s 2 (--config)",
    ):
        assert said in line, line
    cfg = summary["config"]
    assert (summary["usbl_preset"], summary["nav_preset"]) == ("cerulean-rovl", "mems-ahrs-dvl")
    assert summary["env_settings"]["nav"] == {"value": "mems-ahrs-dvl", "from": "policy config"}
    assert cfg["usbl"]["preset"] == "cerulean-rovl" and cfg["terminate_on"] == "paper"
    assert (cfg["world"]["water_preset"], cfg["world"]["camera_width_px"]) == ("coastal", 320)
    assert summary["env_settings"]["usbl"] == {"value": "cerulean-rovl", "from": "policy config"}

    # explicit flags win, and the acoustic model reaches the simulation: another trajectory
    line2, summary2, row2 = _eval(
        run_cli, tmp_path / "e2", short, "--policy", policy_dir, "--usbl", "ideal",
        "--nav", "ideal", "--terminate-on", "strict", "--width", "480",
    )  # fmt: skip
    assert "usbl ideal (flag)" in line2 and "terminate_on strict (flag)" in line2
    assert "nav ideal (flag)" in line2 and summary2["nav_preset"] == "ideal"
    assert "camera_width_px 480 (flag)" in line2 and "water coastal (policy config)" in line2
    assert summary2["usbl_preset"] == "ideal" and summary2["config"]["terminate_on"] == "strict"
    assert summary2["env_settings"]["usbl"]["from"] == "flag"
    assert row["seed"] == row2["seed"]
    assert float(row["final_e_xy_m"]) != pytest.approx(float(row2["final_e_xy_m"]), abs=1e-9)


def test_pid_runs_under_a_policys_settings_with_env_from(run_cli, tmp_path, policy_dir, short):
    line, summary, _ = _eval(run_cli, tmp_path / "plain", short, "--policy", "pid")
    assert "usbl ideal (default)" in line and "terminate_on strict (default)" in line
    assert "[policy:" not in line and summary["usbl_preset"] == "ideal"
    line, summary, _ = _eval(
        run_cli, tmp_path / "from", short, "--policy", "pid", "--env-from", policy_dir
    )
    assert (
        "usbl cerulean-rovl (policy config)" in line
        and "camera_width_px 320 (policy config)" in line
    )
    assert summary["policy"] == "pid" and summary["usbl_preset"] == "cerulean-rovl"
    assert summary["config"]["world"]["water_preset"] == "coastal"
    # the film of a PID episode takes the same settings
    out = tmp_path / "film"
    res = run_cli(
        cli.main, "episode", "--out", out, "--seconds", "0.4", "--width", "96",
        "--outside-width", "96", "--env-from", policy_dir, "--quiet",
    )  # fmt: skip
    assert res.code == 0, res.err
    assert (
        "usbl cerulean-rovl (policy config)" in res.err and "camera_width_px 96 (flag)" in res.err
    )
    film = json.loads((out / "summary.json").read_text())
    assert film["water"] == "coastal"


def test_export_carries_the_training_env_to_eval_and_the_runner(run_cli, tmp_path, policy_dir):
    onnx = tmp_path / "policy.onnx"
    res = run_cli(cli.main, "export", "--policy", policy_dir, "--out", onnx)
    assert res.code == 0, res.err
    assert "rl export env" in res.out and "usbl cerulean-rovl (policy config)" in res.out
    env = json.loads(onnx.with_suffix(".json").read_text())["env"]
    assert env["usbl"]["preset"] == "cerulean-rovl" and env["world"]["camera_width_px"] == 320
    from uwdock.rl.deploy.runner import DockingRunner

    runner = DockingRunner(str(onnx))
    assert runner.cfg.usbl.preset == "cerulean-rovl" and runner.cfg.world.camera_width_px == 320
    assert runner.cfg.terminate_on == "paper" and runner.env_from == str(onnx.with_suffix(".json"))
    short = tmp_path / "short.toml"
    short.write_text("episode_s = 1.0\n")
    line, summary, _ = _eval(run_cli, tmp_path / "e", short, "--policy", onnx)
    assert "usbl cerulean-rovl (policy config)" in line
    assert summary["usbl_preset"] == "cerulean-rovl"


def test_shipped_policy_matches_its_recorded_checksums():
    lines = (SHIPPED / "checksums.sha256").read_text().splitlines()
    recorded = dict(reversed(line.split("  ", 1)) for line in lines if line.strip())
    assert set(recorded) == {"model.json", "weights.npz"}
    for name, digest in recorded.items():
        assert hashlib.sha256((SHIPPED / name).read_bytes()).hexdigest() == digest, name
