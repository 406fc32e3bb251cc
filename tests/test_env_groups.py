"""Several training envs per worker process (``rl train --envs-per-worker K``,
:mod:`rl.train.vec_envs`): the same run file by file as one env per worker (checkpoints, evaluation
history, best/, the final policy), with the proxy source and with the camera (the envs of a worker
sharing its SAPIEN renderer); a failing env in a group is one line naming it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import psutil
import pytest

from tests.hostile_runs import SMALL_RUN, run_digest
from uwdock.rl import cli
from uwdock.rl.train.vec_envs import env_groups

# 4 envs, periodic evaluations (their shares run in the workers) and a checkpoint in between
CONFIG = SMALL_RUN.format(n_envs=4, eval_episodes=3)
CAMERA = """\
n_envs = 2
total_steps = 96
checkpoint_every = 64
eval_every = 64
eval_episodes = 2
[env]
episode_s = 3.0
obs_source = "camera"
camera_width_px = 240
[ppo]
n_steps = 24
batch_size = 48
n_epochs = 1
"""


def _train(run_cli, cfg: Path, out: Path, *extra) -> dict[str, str]:
    res = run_cli(cli.main, "train", "--config", cfg, "--out", out, *extra)
    assert res.code == 0, res.err[-2000:]
    return run_digest(out)


def _same(a: dict[str, str], b: dict[str, str]) -> None:
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []
    assert any(k.startswith("checkpoints/") for k in a) and "eval_history.jsonl" in a


def test_env_groups_cover_every_env_once():
    assert env_groups(4, 1) == [[0], [1], [2], [3]]
    assert env_groups(4, 2) == [[0, 1], [2, 3]]
    assert env_groups(5, 2) == [[0, 1], [2, 3], [4]]
    assert env_groups(3, 8) == [[0, 1, 2]]


def test_several_envs_per_worker_train_the_same_run(run_cli, tmp_path):
    """4 envs in 4 workers (SB3's SubprocVecEnv), 2 workers of 2, and uneven groups (3 + 1):
    the same run file by file."""
    cfg = tmp_path / "train.toml"
    cfg.write_text(CONFIG)
    one = _train(run_cli, cfg, tmp_path / "k1")
    _same(one, _train(run_cli, cfg, tmp_path / "k2", "--envs-per-worker", "2"))
    _same(one, _train(run_cli, cfg, tmp_path / "k3", "--envs-per-worker", "3"))


def test_worker_processes_hold_their_share_of_the_envs(tmp_path):
    """``K`` envs per worker: ``n_envs / K`` worker processes, all gone after close."""
    from uwdock.rl.env.config import EnvConfig
    from uwdock.rl.train.vec_envs import EnvWorkers

    workers = EnvWorkers(EnvConfig(episode_s=2.0), 4, seed=0, envs_per_worker=2)
    try:
        procs = workers._processes()
        assert len(procs) == 2 and all(p.is_alive() for p in procs)
        assert workers.venv.num_envs == 4
        obs = workers.venv.reset()
        assert obs.shape[0] == 4 and len({o.tobytes() for o in obs}) == 4  # four seeds
        venv = workers.venv
        venv.set_attr("tag", "x", indices=[2])  # env 2 is worker 1's first, env 1 worker 0's
        venv.set_attr("tag", "y", indices=[1])
        assert venv.get_attr("tag", [2, 1]) == ["x", "y"]  # in the order asked for
        assert not venv.has_attr("tag")  # envs 0 and 3 have none
        from stable_baselines3.common.monitor import Monitor

        assert venv.env_is_wrapped(Monitor) == [True] * 4
    finally:
        workers.close()
    assert not any(psutil.pid_exists(p.pid) and p.is_alive() for p in procs)


def _train_process(cfg: Path, out: Path, *extra) -> dict[str, str]:
    """``rl train`` as a process of its own, as a user runs it: the workers are forked from a
    process that has not rendered (a process that has, like this test process after the
    rendering tests, must not fork its Vulkan state)."""
    cmd = [sys.executable, "-c", "from uwdock.cli import rl; rl()", "train", "--config", str(cfg),
           "--out", str(out), *extra]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return run_digest(out)


@pytest.mark.slow  # 40 s; test_several_envs_per_worker_train_the_same_run covers the groups
@pytest.mark.render
def test_camera_envs_sharing_a_renderer_train_the_same_run(tmp_path):
    """Two camera envs (render -> water -> detector -> PnP) in one worker, sharing its SAPIEN
    renderer: the same run as one env per worker."""
    cfg = tmp_path / "camera.toml"
    cfg.write_text(CAMERA)
    _same(
        _train_process(cfg, tmp_path / "k1"),
        _train_process(cfg, tmp_path / "k2", "--envs-per-worker", "2"),
    )


def test_a_failing_env_in_a_group_is_one_line_naming_it(run_cli, tmp_path, monkeypatch):
    """An env that fails while stepping, 4 envs in 2 workers: one line with each worker's
    reason, naming the env that failed (the first of each group)."""
    import uwdock.rl.env.docking_env

    def broken_step(self, action):
        raise uwdock.rl.env.docking_env.SimulationError("simulator blew up at t=0.10 s (test)")

    monkeypatch.setattr(uwdock.rl.env.docking_env.DockingEnv, "step", broken_step)
    res = run_cli(cli.main, "train", "--envs", "4", "--envs-per-worker", "2", "--steps", "64",
                  "--out", tmp_path / "r")  # fmt: skip
    assert res.code == 2, res.err
    errors = [line for line in res.err.splitlines(keepends=True) if line.startswith("error")]
    assert "Traceback" not in res.err and errors == [
        "error: environment worker failed: env 0: simulator blew up at t=0.10 s (test); "
        "env 2: simulator blew up at t=0.10 s (test)\n"
    ]


def test_envs_per_worker_is_checked(run_cli, tmp_path):
    for bad in ("0", "-1", "nan", "1e9", "two"):
        out = tmp_path / f"r{bad}"
        res = run_cli(cli.main, "train", "--envs-per-worker", bad, "--out", out)
        assert res.code == 2 and res.err.strip().count("\n") == 0, res.err
        assert "envs-per-worker" in res.err
        assert not out.exists()
