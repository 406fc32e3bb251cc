"""Training runs as transactions: a run killed at any moment (SIGKILL, SIGTERM, SIGINT; before
its first checkpoint, during a rollout, while starting) and resumed equals an uninterrupted run
file by file (checkpoints bit-identical, same evaluation history, same best/, same final
policy); damaged checkpoints are skipped; a resume keeps the run's config; worker processes
never outlive the command."""

from __future__ import annotations

import json
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from tests.hostile_runs import run_digest
from uwdock.dockcore.config import load_config
from uwdock.rl import cli
from uwdock.rl.train.training import TrainConfig, train

# Two envs in worker processes, a DAgger warm start, a critic warm-up that spans a checkpoint,
# evaluations between checkpoints, a curriculum and an asymmetric critic: everything a resume
# has to restore.
CONFIG = """\
n_envs = 2
total_steps = 512
checkpoint_every = 128
eval_every = 192
eval_episodes = 2
[env]
episode_s = 4.0
obs_privileged = true
[curriculum]
steps = 384
spawn_scale_start = 0.3
[ppo]
n_steps = 32
batch_size = 64
n_epochs = 2
[imitation]
teacher = "pid"
iterations = 1
episodes_per_iteration = 1
epochs = 2
critic_warmup_steps = 200
"""


def _rl(*args: str) -> list[str]:
    # the console script's path: `rl` imports its group inside the error handling, so a signal
    # that lands while it imports is one line too
    return [sys.executable, "-c", "from uwdock.cli import rl; rl()", *map(str, args)]


def _units(run: Path) -> list[str]:
    return sorted(p.name for p in (run / "checkpoints").glob("step_*"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run (started in the background; waited for on first use)."""
    root = tmp_path_factory.mktemp("resume")
    (root / "train.toml").write_text(CONFIG)
    ref = root / "ref"
    proc = subprocess.Popen(
        _rl("train", "--config", root / "train.toml", "--out", ref),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    state = {"proc": proc, "root": root, "ref": ref}
    yield state
    if proc.poll() is None:
        proc.kill()


def _finished(reference) -> Path:
    proc = reference["proc"]
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-2000:]
    return reference["ref"]


def _run_until(cmd: list[str], event, sig: int, delay_s: float, timeout_s: float = 120):
    """Start ``cmd``; once ``event()`` holds, wait ``delay_s`` and send ``sig``. Returns the
    return code, stderr and the pids of the children it had just before the signal."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not event() and proc.poll() is None and time.monotonic() - t0 < timeout_s:
        time.sleep(0.05)
    time.sleep(delay_s)
    children = []
    if proc.poll() is None:
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=timeout_s)
    return proc.returncode, err, children


def _assert_gone(children: list[psutil.Process]) -> None:
    deadline = time.monotonic() + 5.0
    alive = children
    while alive and time.monotonic() < deadline:
        alive = [c for c in alive if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
        time.sleep(0.1)
    assert not alive, f"worker processes outlived the command: {[c.pid for c in alive]}"


@pytest.mark.slow  # ~41 s on 2 cores: in the slow set (CI runs it)
def test_killed_and_resumed_training_equals_uninterrupted(reference):
    root = reference["root"]
    run = root / "killed"
    rng = random.Random(20261123)
    first = _rl("train", "--config", root / "train.toml", "--out", run)
    resume = _rl("train", "--out", run, "--resume")
    ckpt = run / "checkpoints"
    kills = [
        # before the first checkpoint (during start-up or the DAgger warm start), once the run
        # folder holds its config (a kill before that leaves nothing a --resume could go on from)
        (first, lambda: (run / "config.toml").exists(), signal.SIGKILL, rng.uniform(0.0, 2.0)),
        # mid-run, each signal once, a random moment after a given checkpoint (within 0.3 s: on
        # an idle machine the rest of the run can take under a second, and a resume that ran
        # to the end left the later ones nothing to resume)
        (resume, lambda: (ckpt / "step_0000000128").exists(), signal.SIGKILL, rng.uniform(0, 0.3)),
        (resume, lambda: (ckpt / "step_0000000256").exists(), signal.SIGTERM, rng.uniform(0, 0.3)),
        (resume, lambda: True, signal.SIGINT, rng.uniform(4.0, 6.0)),
        # while starting (loading the checkpoint, forking workers)
        (resume, lambda: True, signal.SIGKILL, rng.uniform(0.5, 2.0)),
    ]
    for cmd, event, sig, delay in kills:
        code, err, children = _run_until(cmd, event, sig, delay)
        assert "Traceback" not in err, err[-3000:]
        if code != 0:  # it finished before the signal otherwise
            assert code in (-signal.SIGKILL, 128 + signal.SIGTERM, 130), (code, err[-2000:])
        if sig != signal.SIGKILL and code != 0:
            assert err.strip().splitlines()[-1].startswith("error: interrupted"), err[-500:]
        _assert_gone(children)
    done = subprocess.run(resume, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]

    ref = _finished(reference)
    assert _units(run) == _units(ref) == [f"step_{n:010d}" for n in range(0, 513, 128)]
    a, b = run_digest(ref), run_digest(run)
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []
    history = [json.loads(line) for line in (run / "eval_history.jsonl").read_text().splitlines()]
    assert [h["step"] for h in history] == [0, 192, 384]  # the warm start, then every 192
    assert (run / "best" / "model.json").is_file() and (run / "best" / "weights.npz").is_file()
    log = [json.loads(line) for line in (run / "resume_log.jsonl").read_text().splitlines()]
    assert 2 <= len(log) <= len(kills) and all(r["config_changed"] == [] for r in log)
    assert log[-1]["from_step"] >= 256


@pytest.mark.slow  # waits for the uninterrupted run (~20 s), shared with the test above
def test_resume_falls_back_past_a_damaged_checkpoint(reference, tmp_path):
    ref = _finished(reference)
    run = tmp_path / "damaged"
    shutil.copytree(ref, run)
    for name in ("DONE", "model.json", "weights.npz"):
        (run / name).unlink()
    newest = run / "checkpoints" / "step_0000000512"
    with (newest / "training.npz").open("r+b") as fh:  # a torn write
        fh.truncate(1000)
    (run / "checkpoints" / "step_0000000384" / "manifest.json").unlink()  # never completed
    notes: list[str] = []
    cfg = load_config(TrainConfig, run / "config.toml", section="train")
    train(cfg, run, resume=True, progress=False, note=notes.append)
    assert any("step_0000000512 is damaged" in n and "checksum" in n for n in notes), notes
    assert any("step_0000000384 is damaged" in n and "manifest" in n for n in notes), notes
    a, b = run_digest(ref), run_digest(run)
    assert [k for k in a if a[k] != b.get(k)] == []


def test_resume_keeps_the_runs_config(run_cli, tmp_path):
    run = tmp_path / "run"
    res = run_cli(cli.main, "train", "--out", run, "--resume")
    assert res.code == 2 and "has no config.toml: not a run folder of `rl train`" in res.err
    cfg = tmp_path / "small.toml"
    cfg.write_text(
        "n_envs = 1\ntotal_steps = 64\ncheckpoint_every = 64\neval_every = 0\n"
        "[env]\nepisode_s = 2.0\n[ppo]\nn_steps = 32\nbatch_size = 32\nn_epochs = 1\n"
    )
    assert run_cli(cli.main, "train", "--config", cfg, "--out", run).code == 0
    other = tmp_path / "other.toml"
    other.write_text("seed = 5\n[ppo]\nlearning_rate = 0.1\n")
    before = (run / "config.toml").read_text()
    res = run_cli(cli.main, "train", "--config", other, "--out", run, "--resume")
    assert res.code == 2 and res.err.count("\n") == 1
    assert "differs from the run's config.toml in ppo.learning_rate, seed" in res.err
    assert (run / "config.toml").read_text() == before  # nothing overwritten
    # the run's own config: nothing to do, it is complete
    res = run_cli(cli.main, "train", "--out", run, "--resume")
    assert res.code == 0 and "is complete" in res.err
    res = run_cli(cli.main, "train", "--config", cfg, "--out", run, "--init-policy", run)
    assert res.code == 2 and "already holds a run" in res.err


def test_a_failing_worker_is_one_line(run_cli, tmp_path, monkeypatch):
    """An env that fails in a worker process (2 envs): one line with the worker's reason."""
    import uwdock.rl.env.docking_env

    def broken_init(self, *a, **kw):
        raise uwdock.rl.env.docking_env.SimulationError("simulator blew up at t=0.00 s (test)")

    monkeypatch.setattr(uwdock.rl.env.docking_env.DockingEnv, "__init__", broken_init)
    res = run_cli(cli.main, "train", "--envs", "2", "--steps", "64", "--out", tmp_path / "r")
    assert res.code == 2, res.err
    errors = [line for line in res.err.splitlines(keepends=True) if line.startswith("error")]
    assert "Traceback" not in res.err and errors == [
        "error: environment worker failed: env 0: simulator blew up at t=0.00 s (test); "
        "env 1: simulator blew up at t=0.00 s (test)\n"
    ]


def test_missing_error_model_is_refused_before_anything_is_written(run_cli, tmp_path):
    out = tmp_path / "r"
    res = run_cli(
        cli.main, "train", "--envs", "2", "--obs", "error-model", "--error-model",
        tmp_path / "nope.json", "--out", out,
    )  # fmt: skip
    assert res.code == 2 and res.err == f"error: error model file not found: {tmp_path}/nope.json\n"
    assert not out.exists()


def test_steps_rounded_up_to_whole_rollouts_says_so(run_cli, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "n_envs = 1\neval_every = 0\n[env]\nepisode_s = 2.0\n"
        "[ppo]\nn_steps = 32\nbatch_size = 32\nn_epochs = 1\n"
    )
    res = run_cli(cli.main, "train", "--config", cfg, "--steps", "10", "--out", tmp_path / "r")
    assert res.code == 0, res.err
    assert "training 32 steps: PPO steps in rollouts of 32" in res.err
    assert json.loads((tmp_path / "r" / "DONE").read_text())["steps"] == 32
