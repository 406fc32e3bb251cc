"""The jobs on Ray (``--backend ray``, :mod:`uwdock.dockcore.pool`) against the local pool, on a
local Ray instance with 2 CPUs: byte-identical datasets, identical evaluation rows and summary, a
killed Ray worker replaced with nothing lost or duplicated, a killed driver resumed."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import tomllib

from uwdock.dockcore.config import replace
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.pool import PoolConfig, actor_death, worker_pool

ray = pytest.importorskip("ray")
psutil = pytest.importorskip("psutil")

from tests.hostile_runs import ROOT, SMALL_RUN, run_digest  # noqa: E402
from uwdock import cli as uwdock_cli  # noqa: E402 - after the skips
from uwdock.datasets.synth import SynthConfig, generate  # noqa: E402
from uwdock.rl.env.config import EnvConfig  # noqa: E402
from uwdock.rl.evaluate.episodes import run_episodes_parallel  # noqa: E402

#: Files a run writes about itself (its owner's pid, its own timing): not part of the data.
RUN_FILES = {".uwdock-owner.json", "provenance.json"}
CFG = SynthConfig(n_frames=8, water="coastal", width_px=160, seed=5)


def _files(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name not in RUN_FILES
    }


@pytest.fixture(scope="module")
def local_dataset(tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("local") / "ds"
    generate(out, CFG, workers=2, progress=False)
    return _files(out)


def _host_pids() -> list[int]:
    """The processes of this machine's Ray actors hosting pool workers."""
    pids = []
    for p in psutil.process_iter(["pid", "cmdline"]):
        cmd = " ".join(p.info["cmdline"] or ())
        if "ray::_Host" in cmd:
            pids.append(p.info["pid"])
    return pids


@pytest.mark.render
@pytest.mark.slow  # ~29 s on 2 cores: in the slow set (CI runs it)
def test_ray_dataset_equals_the_local_one_file_by_file(local_dataset, tmp_path):
    out = tmp_path / "ray"
    res = generate(out, CFG, workers=2, progress=False, backend="ray")
    assert sorted(res.rendered) == list(range(CFG.n_frames))
    # where the frames ran: every frame counted once (one node here), no worker replaced
    assert sum(res.ray["tasks_by_node"].values()) == CFG.n_frames
    assert res.ray["workers_replaced"] == 0
    got = _files(out)
    assert sorted(got) == sorted(local_dataset)
    assert [k for k in got if got[k] != local_dataset[k]] == []


@pytest.mark.render
@pytest.mark.slow  # ~20 s on 2 cores: in the slow set (CI runs it)
def test_a_killed_ray_worker_is_replaced_and_nothing_is_lost_or_duplicated(local_dataset, tmp_path):
    # Frames of 160 px render at ~200 per second once the workers are up, so a run of a few
    # dozen frames can finish between two polls (it did on CI): 400 frames leave a window of
    # about two seconds, the worker pids are taken while SAPIEN starts, and the first image is
    # watched for every 5 ms, so the kill lands while both workers hold tasks.
    n_frames = 400
    cfg = replace(CFG, n_frames=n_frames)
    out = tmp_path / "killed"
    result: dict[str, object] = {}

    def run() -> None:
        try:
            result["res"] = generate(out, cfg, workers=2, progress=False, backend="ray")
        except BaseException as exc:  # reported by the assertion below
            result["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    pids: list[int] = []
    deadline = time.monotonic() + 240  # Ray and SAPIEN start slowly on a loaded machine
    while time.monotonic() < deadline and thread.is_alive() and len(pids) < 2:
        pids = _host_pids()
        time.sleep(0.05)
    killed = None
    images = out / "images"
    while pids and time.monotonic() < deadline and thread.is_alive():
        if images.is_dir() and any(images.glob("*.png")):
            # a host taken while Ray started may be an earlier test's actor that has since
            # exited (CI once killed a pid that was gone): the kill goes to a live one
            for pid in _host_pids():
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    continue
                killed = pid
                break
            if killed is not None:
                break
        time.sleep(0.005)
    thread.join(300)
    assert killed is not None, "the run ended before a worker could be killed"
    assert "error" not in result, result.get("error")
    labels = (out / "labels.jsonl").read_text().splitlines()
    assert [json.loads(line)["frame"] for line in labels] == list(range(n_frames))  # once each
    assert result["res"].ray["workers_replaced"] >= 1
    assert sum(result["res"].ray["tasks_by_node"].values()) == n_frames
    # the first 8 frames are the 8-frame dataset's: same seed, same bytes
    got = _files(out)
    for name, data in local_dataset.items():
        if name.startswith("images/"):
            assert got[name] == data, name
    assert killed not in _host_pids()


@pytest.mark.slow  # 23 s; the killed-worker test covers Ray's replacement of lost work
@pytest.mark.render
def test_a_killed_driver_resumes_without_redoing_finished_frames(local_dataset, tmp_path):
    out = tmp_path / "resumed"
    code = (
        "from uwdock.datasets.synth import SynthConfig, generate\n"
        "if __name__ == '__main__':\n"
        f"    generate({str(out)!r}, SynthConfig(n_frames=8, water='coastal', width_px=160, "
        "seed=5), workers=2, progress=False, backend='ray')\n"
    )
    log = tmp_path / "first.err"
    with log.open("w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code], stderr=err)
    deadline = time.monotonic() + 300  # Ray and SAPIEN start slowly on a loaded machine
    while time.monotonic() < deadline and proc.poll() is None:
        partial = list((out / ".partial").glob("*.json")) if (out / ".partial").exists() else []
        if len(partial) >= 2:
            break
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    # a frame is finished once its partial label is written (after its image)
    done_before = {int(p.stem) for p in (out / ".partial").glob("*.json")}
    assert done_before, log.read_text()[-2000:]
    res = generate(out, CFG, workers=2, progress=False, backend="ray")
    assert set(res.rendered).isdisjoint(done_before)
    assert set(res.rendered) | done_before == set(range(CFG.n_frames))
    assert _files(out) == local_dataset


@pytest.mark.render
@pytest.mark.slow  # ~8 s on 2 cores: in the slow set (CI runs it)
def test_ray_evaluation_gives_the_local_rows_and_summary(tmp_path, run_cli):
    env = tmp_path / "env.toml"
    env.write_text("episode_s = 15.0\n")
    common = ["eval", "--policy", "pid", "--episodes", "4", "--obs", "proxy", "--videos", "",
              "--workers", "2", "--config", env]  # fmt: skip
    a = run_cli(uwdock_cli.rl, *common, "--out", tmp_path / "local")
    b = run_cli(uwdock_cli.rl, *common, "--backend", "ray", "--out", tmp_path / "ray")
    assert a.code == 0 and b.code == 0, (a.err, b.err)
    sa = json.loads((tmp_path / "local/summary.json").read_text())
    sb = json.loads((tmp_path / "ray/summary.json").read_text())
    timing = {"wall_clock_s", "control_steps_per_s", "backend", "provenance", "ray"}  # its own
    assert {k: v for k, v in sa.items() if k not in timing} == {
        k: v for k, v in sb.items() if k not in timing
    }
    assert sb["backend"] == "ray" and sa["backend"] == "local"
    assert sum(sb["ray"]["tasks_by_node"].values()) == 4 and "ray" not in sa
    csv = [(tmp_path / f"{b}/episodes.csv").read_bytes() for b in ("local", "ray")]
    assert csv[0] == csv[1]


def test_evaluation_rows_do_not_depend_on_the_number_of_workers():
    """Episodes are handed out one at a time (no static split): any worker count, same rows."""
    cfg = replace(EnvConfig(), obs_source="proxy", episode_s=10.0)
    one = run_episodes_parallel("pid", cfg, 5, 7, workers=1, record=False)
    three = run_episodes_parallel("pid", cfg, 5, 7, workers=3, record=False)
    assert one.episodes == three.episodes and one.summary == three.summary


def test_without_ray_the_backend_is_a_one_line_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ModuleNotFoundError
    with pytest.raises(DockError, match=r"uwdock\[ray\]"):
        with worker_pool(PoolConfig("ray", 2), dict):
            pass


@pytest.mark.slow  # ~11 s on 2 cores: in the slow set (CI runs it)
def test_a_ray_worker_that_cannot_start_stops_the_job_in_one_line():
    """A worker whose constructor fails on its node (here: an input file missing there) stops
    the job at once, naming the node and the worker's error, instead of being replaced
    (issue 54: a node that cannot run a worker, its work silently done elsewhere) or respawned
    forever (issue 32). In its own process: a Ray instance of its own, whatever earlier tests
    did to theirs."""
    script = (
        "from uwdock.dockcore.pool import PoolConfig, worker_pool\n"
        "from uwdock.dockcore.errors import DockError\n"
        "try:\n"
        "    with worker_pool(PoolConfig('ray', 1), open, ('/nonexistent/missing-policy.zip',))"
        " as p:\n"
        "        list(p.imap_unordered('read', range(3)))\n"
        "except DockError as exc:\n"
        "    print('ERROR', exc)\n"
    )
    t0 = time.monotonic()
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=180, check=False
    )
    assert res.returncode == 0, res.stderr[-2000:]
    lines = [line for line in res.stdout.splitlines() if line.startswith("ERROR ")]
    assert len(lines) == 1, res.stdout
    text = lines[0]
    assert "cannot run a worker: FileNotFoundError" in text and "missing-policy.zip" in text
    assert "Ray node 127.0.0.1 (node " in text, text  # its IP and node ID
    assert "lost Ray worker(s) replaced" not in res.stderr
    assert time.monotonic() - t0 < 120


@pytest.mark.slow  # ~10 s on 2 cores: in the slow set (CI runs it)
def test_a_local_ray_instance_listens_on_loopback_only():
    """The Ray instance a job starts for itself takes 127.0.0.1 and listens on no other
    interface (in its own process: the choice is made when ``ray`` is imported)."""
    script = (
        "import psutil\n"
        "from uwdock.dockcore.pool import PoolConfig, worker_pool\n"
        "with worker_pool(PoolConfig('ray', 1), dict) as p:\n"
        "    import ray\n"
        "    print('NODE', ray.util.get_node_ip_address())\n"
        "    session = ray._private.worker._global_node.get_session_dir_path()\n"
        "    pids = {q.pid for q in psutil.process_iter(['cmdline'])\n"
        "            if session in ' '.join(q.info['cmdline'] or ())}\n"
        "    for c in psutil.net_connections('inet'):\n"
        "        if c.status == 'LISTEN' and c.pid in pids:\n"
        "            print('LISTEN', c.laddr.ip)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"}
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=180,
        check=False, env=env,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert "NODE 127.0.0.1" in res.stdout, res.stdout
    listening = {line.split()[1] for line in res.stdout.splitlines() if line.startswith("LISTEN")}
    assert listening, res.stdout  # the GCS, the raylet, the object manager at least
    assert listening <= {"127.0.0.1", "::ffff:127.0.0.1", "::1"}, listening


def test_actor_death_reads_node_and_cause_from_rays_message():
    msg = (
        "The actor died because of an error raised in its creation task, "
        "ray::_Host.__init__() (pid=16122, ip=192.0.2.2, actor_id=803f, repr=<_Host>)\n"
        '  File "/work/main/rl/env/docking_env.py", line 109, in __init__\n'
        "    self.nav = NavErrors(c.nav, 1)\n"
        "AttributeError: 'EnvConfig' object has no attribute 'nav'"
    )
    assert actor_death(RuntimeError(msg)) == (
        "192.0.2.2",
        "AttributeError: 'EnvConfig' object has no attribute 'nav'",
    )
    assert actor_death(RuntimeError("node lost")) == ("unknown", "node lost")


def test_pool_config_is_checked():
    for bad in (PoolConfig("spark", 2), PoolConfig("local", 0), PoolConfig("local", 2, "auto")):
        with pytest.raises(ValueError):
            bad.validate()


TRAIN = SMALL_RUN.format(n_envs=2, eval_episodes=2)


def _rl(*args) -> list[str]:
    return [sys.executable, "-c", "from uwdock.cli import rl; rl()", *map(str, args)]


@pytest.mark.slow  # 42 s; Ray evaluation and datasets equal local ones in the default suite
@pytest.mark.render
def test_training_on_ray_env_workers_resumes_and_equals_the_local_run(tmp_path):
    """Env workers as Ray actors behind SB3's VecEnv: killed after its first checkpoint and
    resumed (on Ray, now both envs in one actor), the run equals an uninterrupted local run file
    by file (checkpoints, evaluation history, best/, the final policy)."""
    cfg = tmp_path / "train.toml"
    cfg.write_text(TRAIN)
    local = tmp_path / "local"
    done = subprocess.run(_rl("train", "--config", cfg, "--out", local), capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    run = tmp_path / "ray"
    proc = subprocess.Popen(
        _rl("train", "--config", cfg, "--out", run, "--backend", "ray"),
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if (run / "checkpoints" / "step_0000000128").exists():
            break
        time.sleep(0.05)
    proc.kill()
    _, err = proc.communicate(timeout=60)
    assert "Traceback" not in err, err[-2000:]
    resumed = subprocess.run(_rl("train", "--out", run, "--resume", "--backend", "ray",
                                 "--envs-per-worker", 2),
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    log = [json.loads(line) for line in (run / "resume_log.jsonl").read_text().splitlines()]
    assert log and log[-1]["from_step"] >= 128  # it went on from a checkpoint
    a, b = run_digest(local), run_digest(run)
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []


SWEEP = """\
n_envs = 1
total_steps = 128
checkpoint_every = 64
eval_every = 64
eval_episodes = 1
[env]
episode_s = 3.0
[ppo]
n_steps = 32
batch_size = 32
n_epochs = 1
"""


@pytest.mark.slow  # 30 s
@pytest.mark.render
def test_a_sweep_runs_each_trial_as_its_own_resumable_run(tmp_path, run_cli):
    """``rl sweep`` through Ray Tune: 2 seeds x 2 learning rates, each trial a run folder equal
    to ``rl train`` of the same config; run again, nothing is trained twice."""
    base = tmp_path / "base.toml"
    base.write_text(SWEEP)
    out = tmp_path / "sweep"
    args = ["sweep", "--config", base, "--seeds", "0,1", "--set", "ppo.learning_rate=0.0003,0.001",
            "--out", out]  # fmt: skip
    res = run_cli(uwdock_cli.rl, *args)
    assert res.code == 0, res.err[-2000:]
    summary = json.loads((out / "sweep_summary.json").read_text())
    assert sorted(summary) == sorted(
        f"seed{s}_learning_rate={lr}" for s in (0, 1) for lr in ("0.0003", "0.001")
    )
    assert all(t["done"] and t["steps"] == 128 for t in summary.values())
    # a trial is the plain run of its config
    direct = tmp_path / "direct"
    cfg = tmp_path / "direct.toml"
    cfg.write_text(SWEEP.replace("n_epochs = 1", "n_epochs = 1\nlearning_rate = 0.001") + "")
    res = run_cli(uwdock_cli.rl, "train", "--config", cfg, "--seed", "1", "--out", direct)
    assert res.code == 0, res.err[-2000:]
    a, b = run_digest(direct), run_digest(out / "seed1_learning_rate=0.001")
    assert [k for k in a if a[k] != b.get(k)] == []
    # again: every trial is complete, nothing is trained again
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("weights.npz")}
    res = run_cli(uwdock_cli.rl, *args)
    assert res.code == 0, res.err[-2000:]
    assert stamps and {p: p.stat().st_mtime_ns for p in out.rglob("weights.npz")} == stamps


@pytest.mark.slow  # 15 s
def test_a_sweeps_input_files_travel_in_its_folder(tmp_path, run_cli):
    """Issue 54: the trials' input files (an error model here) are copied once into the sweep
    folder, which every node mounts, and the trials read them there: no node needs the
    driver's paths. The copy is the file's content; the run folders name only the copy."""
    model = tmp_path / "elsewhere" / "model.json"
    model.parent.mkdir()
    shutil.copy(ROOT / "rl/models/error_model_clear_tank_480.json", model)
    base = tmp_path / "base.toml"
    base.write_text(SWEEP.replace("[env]\n", f'[env]\nobs_source = "error-model"\n'
                                  f'error_model_path = "{model}"\n'))  # fmt: skip
    out = tmp_path / "sweep"
    args = ["sweep", "--config", base, "--seeds", "0", "--out", out]
    res = run_cli(uwdock_cli.rl, *args)
    assert res.code == 0, res.err[-2000:]
    run_cfg = tomllib.loads((out / "seed0" / "config.toml").read_text())
    used = Path(run_cfg["train"]["env"]["error_model_path"])
    assert used.is_relative_to(out / "inputs") and used.name == "model.json"
    assert used.read_bytes() == model.read_bytes()
    assert f'"{model}"' not in (out / "sweep.json").read_text()  # only the copy is named
    # run again: the same plan (the same copy), nothing trained twice
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("weights.npz")}
    res = run_cli(uwdock_cli.rl, *args)
    assert res.code == 0, res.err[-2000:]
    assert stamps and {p: p.stat().st_mtime_ns for p in out.rglob("weights.npz")} == stamps
    # other content at the same path is another sweep
    model.write_text(model.read_text() + "\n")
    res = run_cli(uwdock_cli.rl, *args)
    assert res.code == 2 and "another sweep" in res.err


def test_an_unreachable_or_malformed_ray_address_is_refused_before_anything_is_written(
    tmp_path, run_cli
):
    out = tmp_path / "never"
    for address in ("127.0.0.1:1", "no-port-here"):
        res = run_cli(uwdock_cli.datasets, "render", "--n", "2", "--width", "160", "--backend",
                      "ray", "--ray-address", address, "--out", out)  # fmt: skip
        assert res.code == 2 and res.err.strip().count("\n") == 0, res.err
        assert "Ray" in res.err or "ray-address" in res.err
        assert not out.exists()
