"""What a sweep trial reserves on a Ray cluster (``rl sweep --cpus-per-trial / --gpus-per-trial``),
the check that every trial can be placed before anything is written, and a batched-simulator
trial run through the sweep equal to the plain ``rl train`` run."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.hostile_runs import run_digest
from uwdock.dockcore.config import from_dict
from uwdock.dockcore.errors import DockError
from uwdock.rl.train.sweep import check_fits, trial_resources
from uwdock.rl.train.training import TrainConfig

MODEL = "rl/models/error_model_clear_tank_480_ar1.json"


def _cfg(**fields) -> TrainConfig:
    data = {"total_steps": 1024, **fields}
    if data.get("simulator") == "batched":
        data["env"] = {"obs_source": "error-model", "error_model_path": MODEL}
    return from_dict(TrainConfig, data)


def test_per_env_trials_reserve_a_learner_and_their_env_actors() -> None:
    r = trial_resources(_cfg(n_envs=4))
    assert (r.backend, r.cpus, len(r.bundles), r.envs_per_worker) == ("ray", 5.0, 5, 1)
    # 3 CPUs: the learner and two actors of two envs each
    r = trial_resources(_cfg(n_envs=4), cpus_per_trial=3)
    assert (r.backend, r.cpus, len(r.bundles), r.envs_per_worker) == ("ray", 3.0, 3, 2)
    # 4 CPUs for 4 envs: 3 actors cannot share 4 envs evenly -> 2 of 2 (ceil), 3 CPUs reserved
    r = trial_resources(_cfg(n_envs=4), cpus_per_trial=4)
    assert (r.cpus, r.envs_per_worker) == (3.0, 2)
    # more CPUs than envs: one actor per env
    r = trial_resources(_cfg(n_envs=2), cpus_per_trial=16)
    assert (r.cpus, r.envs_per_worker) == (3.0, 1)
    with pytest.raises(DockError, match="needs 2 CPUs at least"):
        trial_resources(_cfg(n_envs=4), cpus_per_trial=1)
    r = trial_resources(_cfg(n_envs=1), gpus_per_trial=0.5)
    assert (r.backend, r.bundles) == ("local", ({"CPU": 1.0, "GPU": 0.5},))


def test_batched_trials_run_in_the_learner_process_or_its_batch_processes() -> None:
    r = trial_resources(_cfg(n_envs=64, simulator="batched"))
    assert (r.backend, r.bundles, r.batch_workers) == ("local", ({"CPU": 1.0},), 1)
    r = trial_resources(_cfg(n_envs=64, simulator="batched"), cpus_per_trial=4, gpus_per_trial=1)
    assert (r.backend, r.bundles, r.batch_workers) == ("local", ({"CPU": 4.0, "GPU": 1.0},), 4)
    r = trial_resources(_cfg(n_envs=2, simulator="batched"), cpus_per_trial=8)
    assert r.batch_workers == 2  # never more processes than vehicles


def test_a_trial_that_can_never_be_placed_is_one_line() -> None:
    two_nodes = [{"CPU": 2.0}, {"CPU": 2.0, "GPU": 1.0}]
    check_fits(trial_resources(_cfg(n_envs=3)), two_nodes, "t")  # 4 CPUs over the two nodes
    check_fits(trial_resources(_cfg(n_envs=1), gpus_per_trial=1), two_nodes, "t")
    with pytest.raises(DockError, match=r"needs 5 CPUs \(1 learner \+ 4 env actors.*has 4"):
        check_fits(trial_resources(_cfg(n_envs=4)), two_nodes, "t")
    with pytest.raises(DockError, match="needs 2 GPUs but the cluster has 1"):
        check_fits(trial_resources(_cfg(n_envs=1), gpus_per_trial=2), two_nodes, "t")
    # 3 batch processes fit the cluster's 4 CPUs but no single node
    batched = trial_resources(_cfg(n_envs=8, simulator="batched"), cpus_per_trial=3)
    with pytest.raises(DockError, match="on one node but no node has that much"):
        check_fits(batched, two_nodes, "t")


class _FakeRay:
    """Enough of ``ray`` for :func:`check_inputs_on_nodes`: two nodes, each task run here on
    the node's own view of the files (``views``: node -> path rewrite)."""

    from ray import exceptions  # its GetTimeoutError

    def __init__(self, views):
        self.views = views

    def nodes(self):
        return [{"NodeID": f"{k + 1:02x}" * 28, "Alive": True, "NodeManagerAddress": ip}
                for k, ip in enumerate(self.views)]  # fmt: skip

    def remote(self, **_kw):
        views = self.views

        def wrap(fn):
            class Task:
                def options(self, scheduling_strategy):
                    ip = list(views)[int(scheduling_strategy.node_id[:2], 16) - 1]

                    class Bound:
                        @staticmethod
                        def remote(paths):
                            return fn([views[ip](p) for p in paths])

                    return Bound

            return Task()

        return wrap

    def get(self, refs, timeout=None):
        return refs


def test_inputs_are_checked_on_every_node_before_work_starts(tmp_path) -> None:
    from uwdock.dockcore.pool import check_inputs_on_nodes

    model = tmp_path / "model.json"
    model.write_text("{}")
    other = tmp_path / "elsewhere.json"
    other.write_text('{"stale": 1}')
    same = {"10.0.0.1": str, "10.0.0.2": str}
    assert check_inputs_on_nodes(_FakeRay(same), [model]) == 2
    missing = {"10.0.0.1": str, "10.0.0.2": lambda p: p + ".absent"}
    with pytest.raises(DockError, match=r"model.json is not on Ray node 10.0.0.2: put it on"):
        check_inputs_on_nodes(_FakeRay(missing), [model])
    stale = {"10.0.0.1": str, "10.0.0.2": lambda p: str(other)}
    with pytest.raises(DockError, match=r"on Ray node 10\.0\.0\.2 differs from this machine's"):
        check_inputs_on_nodes(_FakeRay(stale), [model])


def test_relative_input_paths_become_absolute_from_the_working_directory(
    tmp_path, monkeypatch
) -> None:
    from uwdock.rl.env.config import env_input_files, with_absolute_inputs

    (tmp_path / "my_water.toml").write_text("[water]\nbeta_D_rgb = [0.1, 0.05, 0.2]\n")
    monkeypatch.chdir(tmp_path)

    model = str(Path(__file__).resolve().parents[1] / MODEL)
    env = _cfg(n_envs=1, env={"obs_source": "error-model", "error_model_path": model,
                              "world": {"water_preset": "my_water.toml"}}).env  # fmt: skip
    got = env_input_files(with_absolute_inputs(env))
    water = str(tmp_path.resolve() / "my_water.toml")
    assert got == {("error_model_path",): model, ("world", "water_preset"): water}
    assert with_absolute_inputs(with_absolute_inputs(env)) == with_absolute_inputs(env)


def _rl(*args) -> list[str]:
    return [sys.executable, "-c", "from uwdock.rl.cli import main; main()", *map(str, args)]


@pytest.mark.slow  # ~11 s on 2 cores: in the slow set (CI runs it)
def test_a_sweep_whose_trial_can_never_fit_is_refused_before_writing(tmp_path) -> None:
    """On a local Ray instance (no GPU asked of this machine's 64), one line, exit 2, no
    folder. A subprocess: Ray's local instance stays out of the test process."""
    cfg = tmp_path / "sweep.toml"
    cfg.write_text("total_steps = 2048\nn_envs = 1\n")
    out = tmp_path / "sw"
    t0 = time.monotonic()
    res = subprocess.run(
        _rl("sweep", "--config", cfg, "--seeds", "0", "--gpus-per-trial", 64, "--out", out),
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert res.returncode == 2, res.stderr[-2000:]
    assert res.stderr.strip().count("\n") == 0, res.stderr[-2000:]
    assert "needs 64 GPUs" in res.stderr and "could never start" in res.stderr
    assert not out.exists()
    assert time.monotonic() - t0 < 120


BATCHED = """\
n_envs = 4
simulator = "batched"
total_steps = 128
checkpoint_every = 64
eval_every = 64
eval_episodes = 1
[env]
obs_source = "error-model"
error_model_path = "rl/models/error_model_clear_tank_480_ar1.json"
episode_s = 3.0
[ppo]
n_steps = 32
batch_size = 64
n_epochs = 1
"""


# ~20-30 s: Ray Tune's start and a second batch process
@pytest.mark.slow  # ~31 s on 2 cores: in the slow set (CI runs it)
def test_a_batched_trial_runs_through_the_sweep_as_plain_rl_train(tmp_path) -> None:
    """A batched-simulator trial (before: refused, "use --backend local") with 2 CPUs: its
    batch over 2 processes, and its run folder equal to ``rl train`` in one process. The
    error model is named by a relative path (before: "not found" in the trial's own folder);
    the trial's config records the sweep folder's copy of it, as the direct run is given it."""
    cfg = tmp_path / "base.toml"
    cfg.write_text(BATCHED)
    out = tmp_path / "sweep"
    res = subprocess.run(
        _rl("sweep", "--config", cfg, "--seeds", "3", "--cpus-per-trial", 2, "--out", out),
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    plan = json.loads((out / "sweep.json").read_text())
    assert plan["resources"]["seed3"]["batch_workers"] == 2
    assert plan["resources"]["seed3"]["bundles"] == [{"CPU": 2.0}]
    copy = plan["trials"]["seed3"]["config"]["env"]["error_model_path"]
    assert Path(copy).is_relative_to(out / "inputs")
    assert Path(copy).read_bytes() == Path(MODEL).read_bytes()
    absolute = tmp_path / "absolute.toml"
    absolute.write_text(BATCHED.replace(MODEL, copy))
    direct = tmp_path / "direct"
    res = subprocess.run(
        _rl("train", "--config", absolute, "--seed", 3, "--out", direct),
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    a, b = run_digest(direct), run_digest(out / "seed3")
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []


def test_policy_input_files_are_what_loading_the_policy_reads(tmp_path) -> None:
    """The files a Ray job checks on every node for ``--policy``: a policy folder's model.json,
    weights.npz and run config; an .onnx and its sidecar; nothing for the PID."""
    from uwdock.rl.policy.policy_io import policy_input_files

    assert policy_input_files("pid") == []
    shipped = Path(__file__).resolve().parents[1] / "rl/policies/scratch_error_model_ppo"
    got = policy_input_files(str(shipped))
    assert got == [shipped / "model.json", shipped / "weights.npz", shipped / "config.toml"]
    assert policy_input_files(str(shipped / "model.json")) == got
    onnx = tmp_path / "p.onnx"
    onnx.write_bytes(b"x")
    (tmp_path / "p.json").write_text("{}")
    assert policy_input_files(str(onnx)) == [onnx.resolve(), (tmp_path / "p.json").resolve()]


def test_a_sweep_folder_every_node_cannot_see_is_refused_and_removed(tmp_path) -> None:
    """Trials write their run folders on the node that runs them: ``--out`` must be storage
    every node mounts; a folder one node cannot see is one line, and removed again."""
    from uwdock.rl.train.sweep import _check_shared

    out = tmp_path / "sw"
    out.mkdir()
    _check_shared(_FakeRay({"10.0.0.1": str, "10.0.0.2": str}), out, created=True)
    assert out.is_dir() and list(out.iterdir()) == []  # the probe is gone, the folder kept
    elsewhere = {"10.0.0.1": str, "10.0.0.2": lambda p: p + ".not-mounted"}
    with pytest.raises(DockError, match=r"not on storage every Ray node mounts.*10\.0\.0\.2"):
        _check_shared(_FakeRay(elsewhere), out, created=True)
    assert not out.exists()
