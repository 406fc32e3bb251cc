"""Hostile input to ``rl``: absurd config values, bad policy files, folders of other tools.
Each is one ``error:`` line, exit status 2, no traceback, and nothing written."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from uwdock.rl import cli
from uwdock.rl.policy.policy_format import npz_bytes

SHIPPED = Path(__file__).resolve().parent.parent / "rl" / "policies" / "error_model_ppo"


def _refused(res, out: Path, message: str) -> None:
    assert res.code == 2, (res.code, res.err)
    assert res.out == "" or "error" not in res.out
    errors = [line for line in res.err.splitlines() if line.startswith("error")]
    assert errors == [f"error: {message}"] or (len(errors) == 1 and message in errors[0]), res.err
    assert "Traceback" not in res.err
    assert not out.exists(), f"{out} was written"


_BIG = "[1, 1000000000]"


@pytest.mark.parametrize(
    "toml,message",
    [
        ("checkpoint_every = 0\n", f"checkpoint_every: must be an integer in {_BIG}, got 0"),
        ("eval_every = -5\n", "eval_every: must be an integer in [0, 1000000000], got -5"),
        ("[ppo]\nnet_arch = [0]\n", "ppo.net_arch[0]: must be an integer in [1, 4096], got 0"),
        ("[env]\nwrench_limits = [-280.0, 140.0, 268.0, 0.0, 39.0, 72.0]\n",
         "env.wrench_limits[0]: must be a finite number in [0, 10000], got -280"),
        ("[env]\nepisode_s = nan\n", "env.episode_s: must be a finite number in (0, 3600], got"),
        ("[env]\nepisode_s = 1e-9\n", "env.episode_s: 1e-09 s is shorter than one control step"),
        ("[env]\nspawn_auv_height_m = inf\n", "env.spawn_auv_height_m: must be a finite number"),
        ("[env.world]\ntank_size_m = [19.0, 0.0, 5.0]\n",
         "env.world.tank_size_m[1]: must be a finite number"),
        ("[env]\ntank_size_m = [19.0, 0.0, 5.0]\n",  # the flat layout of old run folders
         "env.world.tank_size_m[1]: must be a finite number"),
        ("[env]\ntank_size_m = [4.0, 9.0, 5.0]\n", "spawn_auv_range_m: the spawn box"),
        ("[ppo]\nlearning_rate = 0.0\n", "ppo.learning_rate: must be a finite number in (0, 1]"),
        ("[ppo]\ngamma = 1.5\n", "ppo.gamma: must be a finite number in [0, 1], got 1.5"),
        ("[ppo]\nbatch_size = 0\n", "ppo.batch_size: must be an integer in [2, 1000000], got 0"),
        ("[ppo]\nn_steps = -1\n", "ppo.n_steps: must be an integer in [1, 1000000], got -1"),
        ("seed = -1\n", "seed: must be an integer in [0, 4294967295], got -1"),
        ("[imitation]\nteacher = 'mpc'\n", "imitation.teacher: must be one of ['pid', 'none']"),
        ("[env.world.vehicle]\nmass_kg = 1.0\nlinear_damping = [1e5, 1e5, 1e5, 1e5, 1e5, 1e5]\n",
         "env.world.vehicle.linear_damping: too stiff for physics_hz 300"),
    ],
)  # fmt: skip
def test_absurd_training_configs_are_one_line(run_cli, tmp_path, toml, message):
    cfg = tmp_path / "c.toml"
    cfg.write_text(toml)
    out = tmp_path / "run"
    _refused(run_cli(cli.main, "train", "--config", cfg, "--out", out), out, message)


@pytest.mark.parametrize(
    "args,message",
    [
        (["--episodes", "0"], "Invalid value for '--episodes': must be an integer in [1, "),
        (
            ["--workers", "0"],
            "Invalid value for '--workers': must be an integer in [1, 256], got 0",
        ),
        (["--videos", "-1"], "--videos: episode -1 is not among the 100 episodes"),
        (["--videos", "0,x"], "--videos must be comma-separated episode numbers, got '0,x'"),
        (["--stress-episodes", "nan"], "Invalid value for '--stress-episodes'"),
    ],
)
def test_absurd_eval_options_are_one_line(run_cli, tmp_path, args, message):
    out = tmp_path / "e"
    res = run_cli(cli.main, "eval", "--policy", "pid", "--obs", "proxy", *args, "--out", out)
    _refused(res, out, message)


def test_fit_error_model_bins_are_bounded(run_cli, tmp_path):
    out = tmp_path / "em.json"
    res = run_cli(cli.main, "fit-error-model", tmp_path, "--range-bin-m", "1e-9", "--out", out)
    _refused(res, out, "range_bin_m: 1e-09 m over 8 m gives 8000000000 bins (at most 1000)")
    res = run_cli(cli.main, "fit-error-model", tmp_path, "--range-bin-m", "nan", "--out", out)
    _refused(res, out, "Invalid value for '--range-bin-m'")


# ----------------------------------------------------------------------------- policy files


def _policy_folder(tmp_path: Path, name: str) -> Path:
    folder = tmp_path / name
    folder.mkdir()
    for f in ("model.json", "weights.npz", "config.toml"):
        shutil.copy(SHIPPED / f, folder / f)
    return folder


def _rewrite_weights(folder: Path, change) -> Path:
    """``folder``'s weights.npz with ``change(arrays)`` applied, its model.json recording the new
    file's SHA-256 (so the loader reads the changed arrays)."""
    arrays = dict(np.load(folder / "weights.npz", allow_pickle=False))
    change(arrays)
    data = npz_bytes(arrays)
    (folder / "weights.npz").write_bytes(data)
    meta = json.loads((folder / "model.json").read_text())
    meta["weights_sha256"] = hashlib.sha256(data).hexdigest()
    (folder / "model.json").write_text(json.dumps(meta))
    return folder


def _nan_weights(folder: Path) -> Path:
    def poison(arrays):
        arrays["policy/action_net.weight"][0, 0] = np.nan

    return _rewrite_weights(folder, poison)


def _eval(run_cli, policy, out, *extra):
    return run_cli(
        cli.main, "eval", "--policy", policy, "--obs", "proxy", "--episodes", "1", *extra,
        "--out", out,
    )  # fmt: skip


def test_garbage_weights_file(run_cli, tmp_path):
    folder = _policy_folder(tmp_path, "p")
    garbage = b"PK\x03\x04garbage" * 9
    (folder / "weights.npz").write_bytes(garbage)
    meta = json.loads((folder / "model.json").read_text())
    meta["weights_sha256"] = hashlib.sha256(garbage).hexdigest()
    (folder / "model.json").write_text(json.dumps(meta))
    out = tmp_path / "e"
    _refused(_eval(run_cli, folder, out), out, f"cannot read policy weights {folder}/weights.npz")


def test_replaced_weights_differ_from_the_recorded_digest(run_cli, tmp_path):
    folder = _policy_folder(tmp_path, "p")
    arrays = dict(np.load(folder / "weights.npz", allow_pickle=False))
    arrays["policy/action_net.bias"] = arrays["policy/action_net.bias"] + 1.0
    (folder / "weights.npz").write_bytes(npz_bytes(arrays))
    out = tmp_path / "e"
    message = "differ from the SHA-256 its model.json records"
    _refused(_eval(run_cli, folder, out), out, message)


def test_corrupt_normalisation_statistics(run_cli, tmp_path):
    def poison(arrays):
        arrays["obs_rms/var"] = -np.ones_like(arrays["obs_rms/var"])

    folder = _rewrite_weights(_policy_folder(tmp_path, "p"), poison)
    out = tmp_path / "e"
    message = "obs_rms statistics hold NaN, infinity or a negative variance"
    _refused(_eval(run_cli, folder, out), out, message)


def test_truncated_onnx(run_cli, tmp_path):
    onnx = tmp_path / "p.onnx"
    assert run_cli(cli.main, "export", "--policy", SHIPPED, "--out", onnx).code == 0
    onnx.write_bytes(onnx.read_bytes()[:300])
    out = tmp_path / "e"
    _refused(_eval(run_cli, onnx, out), out, f"cannot read ONNX policy {onnx}")


def test_other_observation_layout_without_its_config(run_cli, tmp_path):
    folder = tmp_path / "bare"
    folder.mkdir()
    for f in ("model.json", "weights.npz"):  # no config.toml beside them
        shutil.copy(SHIPPED / f, folder / f)
    env = tmp_path / "env.toml"
    env.write_text("obs_frames = 2\n")
    out = tmp_path / "e"
    res = _eval(run_cli, folder, out, "--config", env)
    _refused(res, out, f"policy {folder} takes 13 observation values, the env gives 26")


def test_nan_policy_is_refused_by_eval_export_and_init_policy(run_cli, tmp_path):
    folder = _nan_weights(_policy_folder(tmp_path, "nan"))
    message = "holds NaN or infinity"
    out = tmp_path / "e"
    _refused(_eval(run_cli, folder, out), out, message)
    onnx = tmp_path / "nan.onnx"
    _refused(run_cli(cli.main, "export", "--policy", folder, "--out", onnx), onnx, message)
    run = tmp_path / "run"
    res = run_cli(cli.main, "train", "--init-policy", folder, "--out", run)
    _refused(res, run, message)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_policy_with_finite_weights_but_nan_outputs(run_cli, tmp_path):
    """Finite weights too large for float32 arithmetic: NaN or infinite actions. Export refuses;
    eval stops at the first such action with one line."""

    def blow_up(arrays):
        for key in ("policy/mlp_extractor.policy_net.0.weight", "policy/action_net.weight"):
            arrays[key] = np.full_like(arrays[key], 3e38)

    folder = _rewrite_weights(_policy_folder(tmp_path, "big"), blow_up)
    onnx = tmp_path / "big.onnx"
    res = run_cli(cli.main, "export", "--policy", folder, "--out", onnx)
    _refused(res, onnx, "outputs NaN or infinity: refusing to export it")
    out = tmp_path / "e"
    res = _eval(run_cli, folder, out)
    assert res.code == 2 and "NaN" in res.err, res.err
    assert res.err.count("error:") == 1 and "Traceback" not in res.err


def test_commands_do_not_write_into_another_tools_folder(run_cli, tmp_path):
    ev = tmp_path / "eval"
    res = _eval(run_cli, "pid", ev, "--config", _short_env(tmp_path), "--videos", "")
    assert res.code == 0, res.err
    before = (ev / "summary.json").read_bytes()
    res = run_cli(cli.main, "train", "--out", ev)
    assert res.code == 2 and "holds the output of `rl eval`; `rl train` will not" in res.err
    assert (ev / "summary.json").read_bytes() == before and not (ev / "config.toml").exists()
    run = tmp_path / "run"
    (run).mkdir()
    shutil.copy(SHIPPED / "provenance.json", run / "provenance.json")  # a legacy rl train folder
    res = _eval(run_cli, "pid", run)
    assert res.code == 2 and "holds the output of `rl train`; `rl eval` will not" in res.err


def _short_env(tmp_path: Path) -> Path:
    env = tmp_path / "short.toml"
    env.write_text("episode_s = 2.0\n")
    return env


def test_a_killed_evaluation_leaves_no_worker_processes(tmp_path):
    """SIGKILL to `rl eval --workers 2`: its workers (and the queue's helpers) die with it."""
    import signal
    import subprocess
    import sys
    import time

    import psutil

    cmd = [sys.executable, "-c", "from uwdock.rl.cli import main; main()",
           "eval", "--policy", "pid", "--obs", "proxy", "--episodes", "40", "--workers", "2",
           "--videos", "",
           "--out", str(tmp_path / "e")]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (tmp_path / "e" / ".uwdock-owner.json").exists():
            time.sleep(0.1)
        time.sleep(2.0)  # the workers are running episodes
        children = psutil.Process(proc.pid).children(recursive=True)
        assert len(children) >= 2
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    deadline = time.monotonic() + 5
    alive = children
    while alive and time.monotonic() < deadline:
        alive = [c for c in alive if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
        time.sleep(0.1)
    assert not alive, [c.cmdline()[-1][:60] for c in alive]


@pytest.mark.parametrize("after_s", [0.5, 1.0, 1.5])
@pytest.mark.slow  # ~14 s on 2 cores: in the slow set (CI runs it)
def test_sigterm_during_an_episode_film_is_one_line_not_a_crash(tmp_path, after_s):
    """SIGTERM ``after_s`` after `rl episode` has claimed its output folder (building the scene,
    the first frames): "error: interrupted (SIGTERM)", exit 143, no video left. Before, the
    renderer objects the film adds to the env's scene outlived it into the interpreter's
    shutdown and segfaulted (exit 139 in 4 of 8 tries at 2.5-4 s from the start, all three
    delays here). The signal is timed from the folder, not from the start: on a loaded machine
    the imports alone can take longer than the old fixed delays, and the signal then killed
    the program before it had installed its handler (-15, nothing said)."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "ep"
    cmd = [sys.executable, "-c", "from uwdock.rl.cli import main; main()",
           "episode", "--out", str(out), "--seconds", "30", "--width", "320",
           "--outside-width", "320"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not out.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert out.exists(), "rl episode never claimed its output folder"
    time.sleep(after_s)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, (proc.returncode, err[-1500:])
    assert err.strip().splitlines()[-1] == "error: interrupted (SIGTERM)"
    assert not (out / "episode.mp4").exists()


@pytest.mark.parametrize(
    "sig",
    ["SIGTERM", pytest.param("SIGINT", marks=pytest.mark.slow)],  # 18-21 s each
)
@pytest.mark.slow  # ~19 s on 2 cores: in the slow set (CI runs it)
def test_a_signal_to_rl_sweep_is_one_line(tmp_path, sig):
    """SIGTERM or Ctrl-C to a running `rl sweep` (a local Ray instance, two trials): one line,
    exit 143 / 130. Before, ray.init's native handler turned SIGTERM into a crash dump and an
    abort (exit 134), and Tune caught Ctrl-C to print its Tuner.restore advice and exit 0."""
    import signal
    import subprocess
    import sys
    import time

    cfg = tmp_path / "sweep.toml"
    cfg.write_text(
        "total_steps = 200000\nn_envs = 1\neval_every = 0\ncheckpoint_every = 1024\n"
        "[ppo]\nn_steps = 512\nbatch_size = 256\n"
    )
    out = tmp_path / "sw"
    cmd = [sys.executable, "-c", "from uwdock.rl.cli import main; main()", "sweep",
           "--config", str(cfg), "--seeds", "0,1", "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not list(out.glob("seed*/checkpoints/*")):
        if proc.poll() is not None:
            break
        time.sleep(0.1)  # the trials are training
    time.sleep(1.0)
    signum = getattr(signal, sig)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == (143 if sig == "SIGTERM" else 130), (proc.returncode, err[-1500:])
    assert err.strip().splitlines()[-1].startswith("error: interrupted"), err[-800:]
    for crash in ("SIGTERM received", "Traceback", "Tuner.restore", "Aborted"):
        assert crash not in err, err[-1500:]


def test_rl_sweep_at_a_refused_address_is_one_line_and_writes_nothing(tmp_path, run_cli):
    """`rl sweep --ray-address` at a port nobody listens on: one line, exit 2, within seconds,
    and no sweep folder (before: sweep.json written, then a hang of more than 9 minutes)."""
    import socket
    import time

    with socket.socket() as s:  # a free port, closed again: connecting is refused
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = tmp_path / "sweep.toml"
    cfg.write_text("total_steps = 2048\nn_envs = 1\n")
    out = tmp_path / "sw"
    t0 = time.monotonic()
    res = run_cli(
        cli.main, "sweep", "--config", cfg, "--seeds", "0", "--ray-address",
        f"127.0.0.1:{port}", "--out", out,
    )  # fmt: skip
    assert res.code == 2 and res.err.count("\n") == 1, res.err
    assert "cannot reach Ray at" in res.err
    assert not out.exists()
    assert time.monotonic() - t0 < 30
