"""The batched docking env (rl.env.batch_env) against the per-env DockingEnv: whole episodes
agree where no per-step noise is drawn, evaluations and worker splits give the per-env rows.
Each batched piece against its scalar twin (rl.env.batch_parts) is tests/test_batch_twins.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uwdock.dockcore.config import replace
from uwdock.rl.env.batch_env import BatchDockingEnv
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.env.task import (
    DockingTaskConfig,
)
from uwdock.rl.evaluate.batched import batched_episodes
from uwdock.rl.evaluate.episodes import run_episodes
from uwdock.sim.usbl import UsblConfig
from uwdock.sim.vehicle import ImuConfig, VehicleConfig
from uwdock.sim.world_config import WorldConfig

MODEL = "rl/models/error_model_clear_tank_480_ar1.json"
TASK = DockingTaskConfig()


def _quiet_cfg(**kw) -> EnvConfig:
    """No per-step draws: IMU without noise (biases drawn at reset), the acoustic source, and
    noise-free acoustic fixes every second (the scalar IMU draws its zero noise from the
    episode's stream, the batch's from its own: any draw after the reset would differ). The
    batch steps PhysX in each vehicle's own scene (bit-equal to the per-env env), unless
    ``batch_contact`` says otherwise."""
    contact = kw.pop("batch_contact", "own")
    vehicle = replace(VehicleConfig(), imu=ImuConfig(0.0, 0.02, 0.0, 0.001, 0.0, 0.0))
    world = replace(WorldConfig(), vehicle=vehicle, randomise_vehicle=True, batch_contact=contact)
    usbl = UsblConfig(sigma_floor_m=0.0, sigma_per_m=0.0)
    base = {"obs_source": "acoustic", "world": world, "usbl": usbl}
    return EnvConfig(**(base | kw))


@pytest.mark.parametrize("terminate_on, contact", [("paper", False), ("strict", True)])
def test_batched_episodes_equal_scalar_episodes(terminate_on, contact):
    cfg = _quiet_cfg(
        terminate_on=terminate_on, episode_s=6.0, obs_frames=2, obs_privileged=True,
        obs_contact=contact,
    )  # fmt: skip
    n, seed = 3, 11
    batch = BatchDockingEnv(cfg, n, seed=seed, privileged=True)
    scalars = [DockingEnv(cfg, privileged=True) for _ in range(n)]
    obs_b = batch.reset()
    obs_s = np.stack([e.reset(seed=seed + i)[0] for i, e in enumerate(scalars)])
    np.testing.assert_allclose(obs_b, obs_s, atol=1e-6)
    rng = np.random.default_rng(0)
    for k in range(30):  # one whole episode (6 s): every env truncates or docks
        a = rng.uniform(-1, 1, (n, 6)).astype(np.float32)
        ob, rb, db, ib = batch.step(a)
        for i, e in enumerate(scalars):
            o, r, term, trunc, info = e.step(a[i])
            assert rb[i] == pytest.approx(r, rel=1e-9, abs=1e-9), (k, i)
            assert db[i] == (term or trunc)
            assert ib[i]["success_strict"] == info["success_strict"]
            np.testing.assert_allclose(ib[i]["T_world_body"], info["T_world_body"], atol=1e-9)
            if term or trunc:
                np.testing.assert_allclose(ib[i]["terminal_observation"], o, atol=1e-6)
                assert ib[i]["TimeLimit.truncated"] == (trunc and not term)
                assert ib[i]["episode"]["l"] == e.steps
                # auto-reset: a fresh spawn (its draws continue the env's own stream, which the
                # scalar env's IMU also draws from: not compared)
                assert batch.steps[i] == 0 and np.isfinite(ob[i]).all()
            else:
                np.testing.assert_allclose(ob[i], o, atol=1e-6, err_msg=f"step {k} env {i}")
    assert db.all()


class _Steer:
    """A fixed deterministic policy with SB3's ``predict`` (batch) and a controller's ``act``
    (one observation): full thrust toward the observed docking station, clipped."""

    def predict(self, obs, deterministic=True):
        a = np.zeros((obs.shape[0], 6), dtype=np.float32)
        a[:, :3] = np.clip(4.0 * obs[:, :3], -1.0, 1.0)
        return a, None

    def reset(self) -> None:
        pass

    def act(self, obs):
        return self.predict(obs[None])[0][0].astype(np.float64)


def test_batched_evaluation_rows_equal_the_per_env_rows():
    """Without per-step draws, the batched evaluation's episode k is the per-env evaluation's
    episode k: the same rows (success, steps, return, collisions, final errors, failure
    mode)."""
    cfg = _quiet_cfg(terminate_on="paper", episode_s=6.0, obs_frames=2)
    pol = _Steer()
    per_env = run_episodes(pol, cfg, 3, 21, record=False).episodes
    batch = batched_episodes(pol, cfg, 3, 21)
    assert [r["episode"] for r in batch] == [0, 1, 2]
    for p, b in zip(per_env, batch, strict=True):
        assert set(p) == set(b)
        for k, v in p.items():
            if isinstance(v, float):
                assert b[k] == pytest.approx(v, rel=1e-6, abs=1e-6), k
            else:
                assert b[k] == v, k


def test_shared_contact_scene_evaluation_rows_match_the_per_env_rows():
    """The training default (every vehicle's DS contact in one PhysX scene): PhysX's contact
    differs from the per-env env's at round-off, so the rows agree in outcome (success, steps,
    collisions, failure mode) and to 0.5 % in return (measured 0.02 %), not to the bit."""
    cfg = _quiet_cfg(terminate_on="paper", episode_s=6.0, obs_frames=2, batch_contact="shared")
    pol = _Steer()
    per_env = run_episodes(pol, cfg, 3, 21, record=False).episodes
    batch = batched_episodes(pol, cfg, 3, 21)
    assert any(r["collisions"] > 0 for r in per_env)  # the DS was touched (PhysX ran)
    for p, b in zip(per_env, batch, strict=True):
        for k in ("success", "success_strict", "steps", "collisions", "failure_mode"):
            assert b[k] == p[k], k
        assert b["return"] == pytest.approx(p["return"], rel=5e-3)


def test_a_kept_batch_evaluates_as_a_new_one_and_shares_are_their_episodes():
    """An evaluation batch kept between evaluations (the training workers') is reseeded: after
    another evaluation it gives a new batch's rows, bit for bit, in the shared contact scene
    too; a share (``first``) is those episodes of the whole (a PhysX scene per vehicle)."""
    pol = _Steer()
    shared = _quiet_cfg(terminate_on="paper", episode_s=6.0, obs_frames=2, batch_contact="shared")
    want = batched_episodes(pol, shared, 3, 21)
    kept = BatchDockingEnv(shared, 3, seed=5)
    try:
        other = batched_episodes(pol, shared, 3, 40, venv=kept)
        assert [r["seed"] for r in other] == [40, 41, 42]
        assert batched_episodes(pol, shared, 3, 21, venv=kept) == want
    finally:
        kept.close()
    own = _quiet_cfg(terminate_on="paper", episode_s=6.0, obs_frames=2)
    whole = batched_episodes(pol, own, 3, 21)
    share = batched_episodes(pol, own, 2, 21, first=1)
    assert [r["episode"] for r in share] == [1, 2] and share == whole[1:]
    with pytest.raises(ValueError, match="n_episodes envs"):
        batched_episodes(pol, own, 2, 21, venv=BatchDockingEnv(own, 3))


def test_training_evaluations_run_in_the_batch_workers():
    """With the batch over worker processes, the training evaluation runs a share of the
    episodes in each (in batches they keep): the rows of one batch of all of them, again at the
    next evaluation. Outcomes equal; returns to round-off (a batch of other size rounds the
    policy's matrix products differently)."""
    from stable_baselines3 import PPO

    from uwdock.rl.policy.policy_format import policy_files
    from uwdock.rl.train.batch_workers import BatchGroup
    from uwdock.rl.train.grouped_vec_env import BatchGroupsVecEnv
    from uwdock.rl.train.vec_envs import EnvWorkers
    from uwdock.rl.train.workers import EvalJob

    cfg = _quiet_cfg(terminate_on="paper", episode_s=4.0, obs_frames=2)
    workers = EnvWorkers(cfg, 4, 7, 2, group_cls=BatchGroup, venv_cls=BatchGroupsVecEnv)
    try:
        model = PPO("MlpPolicy", workers.venv, n_steps=8, batch_size=32, seed=3, device="cpu")
        job = EvalJob(policy_files(model, None), cfg, 5, 31, 2)
        want = batched_episodes(model, cfg, 5, 31)
        for _ in range(2):  # the second time in the kept batches
            got = workers.venv.evaluate(job)
            assert [r["episode"] for r in got] == [0, 1, 2, 3, 4]
            for w, g in zip(want, got, strict=True):
                assert set(w) == set(g)
                for k, v in w.items():
                    if isinstance(v, float) and k != "time_to_dock_s":
                        assert g[k] == pytest.approx(v, rel=1e-4, abs=1e-6), k
                    else:
                        assert g[k] == v, k
    finally:
        workers.close()


def test_shared_contact_scene_steps_after_a_reset_as_a_fresh_batch():
    """A resumed run resets all its envs at the checkpoint and steps a new batch; the run that
    never stopped resets its old batch there: the shared contact scene starts afresh at a full
    reset, so both step alike through DS contact."""
    cfg = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=3.0)
    assert cfg.world.batch_contact == "shared"
    old, new = (BatchDockingEnv(cfg, 6, seed=8, privileged=True) for _ in range(2))
    for venv in (old, new):
        venv.env_method("set_curriculum", 0.02, 0.5, 1.0, (0.03, 0.3, 0.05, 5.0))
    rng = np.random.default_rng(2)
    old.reset()
    for _ in range(60):  # the history the resumed run never saw (without a fresh scene
        # at the reset the two differ after it: checked)
        old.step(rng.uniform(-1, 1, (6, 6)).astype(np.float32))
    for venv in (old, new):
        venv.seed(77)
    o1, o2 = old.reset(), new.reset()
    np.testing.assert_array_equal(o1, o2)
    for _ in range(20):
        a = rng.uniform(-1, 1, (6, 6)).astype(np.float32)
        r1, r2 = old.step(a), new.step(a)
        for x, y in zip(r1[:3], r2[:3], strict=True):
            np.testing.assert_array_equal(x, y)
    assert old.physics.physx_steps > 20 and new.physics.physx_steps > 20
    old.close()
    new.close()


def test_error_model_batch_runs_and_reports_detections():
    cfg = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=4.0)
    env = BatchDockingEnv(cfg, 4, seed=0)
    obs = env.reset()
    assert obs.shape == (4, env.observation_space.shape[0])
    for _ in range(25):
        obs, r, d, infos = env.step(np.zeros((4, 6), dtype=np.float32))
        assert np.isfinite(obs).all() and np.isfinite(r).all()
    assert all("episode" in i for i in infos) or d.sum() == 0


def test_camera_source_and_bad_actions_are_refused():
    with pytest.raises(ValueError, match="cannot be batched"):
        BatchDockingEnv(EnvConfig(obs_source="camera"), 2)
    env = BatchDockingEnv(_quiet_cfg(), 2)
    env.reset()
    with pytest.raises(ValueError, match="env 1"):
        env.step(np.array([[0.0] * 6, [np.nan] + [0.0] * 5]))


def test_curriculum_reaches_every_env():
    env = BatchDockingEnv(_quiet_cfg(terminate_on="strict"), 2)
    env.set_curriculum(0.5, 0.3)
    assert env.task.strict_peg_z_m == 0.5
    assert all(t.strict_peg_z_m == 0.5 for t in env.get_attr("task"))


def _assert_same_infos(a, b) -> None:
    """Two steps' per-env infos hold the same keys, in order, with equal values and types."""
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert list(x) == list(y)
        for k in x:
            if k in ("episode",):  # its "t" is wall-clock seconds
                assert x[k]["r"] == y[k]["r"] and x[k]["l"] == y[k]["l"]
            elif isinstance(x[k], np.ndarray):
                np.testing.assert_array_equal(x[k], y[k])
            else:
                assert type(x[k]) is type(y[k]) and x[k] == y[k], k


def test_step_columns_make_the_per_env_infos_sb3_reads():
    from uwdock.rl.env.batch_env import StepColumns, info_rows

    def part(n, off, done):
        return StepColumns(
            terms={"r_dist": np.arange(n, dtype=np.float32) + off},
            values={
                "success_paper": np.arange(n) % 2 == 0,
                "time_s": np.arange(n) * 0.2 + off,
                "e_true": np.arange(3 * n, dtype=float).reshape(n, 3) + off,
            },
            ends={done: {"TimeLimit.truncated": True, "terminal_observation": np.ones(2)}},
        )

    rows = info_rows(StepColumns.concat([part(2, 0, 1), part(3, 10, 0)]))
    assert len(rows) == 5
    assert list(rows[0]) == ["reward_terms", "success_paper", "time_s", "e_true"]
    assert (
        rows[3]["reward_terms"] == {"r_dist": 11.0}
        and type(rows[3]["reward_terms"]["r_dist"]) is float
    )
    assert rows[3]["success_paper"] is False and rows[2]["success_paper"] is True
    assert rows[4]["time_s"] == pytest.approx(10.4) and type(rows[4]["time_s"]) is float
    np.testing.assert_array_equal(rows[4]["e_true"], [16.0, 17.0, 18.0])
    # the done envs (1 of the first group, 0 of the second: env 2) carry the episode's end
    assert [i for i, r in enumerate(rows) if "terminal_observation" in r] == [1, 2]
    assert rows[2]["TimeLimit.truncated"] is True and "TimeLimit.truncated" not in rows[0]


def test_batched_workers_send_arrays_and_give_the_per_env_calls_results():
    """The columnar step of :class:`BatchGroupsVecEnv` gives what the generic per-env pipe
    protocol (:class:`rl.train.grouped_vec_env.GroupedVecEnv` over the same groups) gives: the same
    observations, float32 rewards, dones and infos, through an auto-reset."""
    from uwdock.rl.train.batch_workers import BatchGroup
    from uwdock.rl.train.grouped_vec_env import BatchGroupsVecEnv, GroupedVecEnv
    from uwdock.rl.train.vec_envs import EnvWorkers

    cfg = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=2.0)
    fast = EnvWorkers(cfg, 3, 7, 2, group_cls=BatchGroup, venv_cls=BatchGroupsVecEnv)
    slow = EnvWorkers(cfg, 3, 7, 2, group_cls=BatchGroup)
    try:
        assert type(fast.venv) is BatchGroupsVecEnv and type(slow.venv) is GroupedVecEnv
        np.testing.assert_array_equal(fast.venv.reset(), slow.venv.reset())
        rng = np.random.default_rng(3)
        dones = 0
        for _ in range(14):  # 10 steps per episode
            a = rng.uniform(-1, 1, (3, 6)).astype(np.float32)
            r1, r2 = fast.venv.step(a), slow.venv.step(a)
            for x, y in zip(r1[:3], r2[:3], strict=True):
                np.testing.assert_array_equal(x, y)
                assert x.dtype == y.dtype
            _assert_same_infos(r1[3], r2[3])
            dones += int(r1[2].sum())
        assert dones == 3
    finally:
        fast.close()
        slow.close()


@pytest.mark.parametrize(
    "near_share, contact, workers, here",
    [
        (0.0, "shared", 2, False),
        (1.0, "own", 2, True),
        (1.0, "kernel", 2, True),
        (1.0, "shared", 1, True),
        (1.0, "shared", (2, True), False),
    ],
)
def test_batch_split_over_worker_processes_gives_the_same_rollouts(
    near_share, contact, workers, here
):
    """Two envs in each of two processes step exactly as one batch of four (free flight, and
    with every vehicle starting just above the seat, ``near_share`` 1, in contact with each
    vehicle in its own PhysX scene or in the numba kernel, the recipe's), whether the first
    half runs in this process (``here``) or in a worker process too. In the shared contact
    scene a split rounds contacts differently (sim.contact_scene), so there the same batch run
    twice is compared (runs are deterministic), and the split of two worker processes against
    the same split with its first half here (``(2, True)`` beside 2 worker processes)."""
    from uwdock.rl.train.batch_workers import BatchWorkers

    world = replace(WorldConfig(), batch_contact=contact)
    cfg = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=3.0, world=world)
    if isinstance(workers, tuple):
        one = BatchWorkers(cfg, 4, seed=5, workers=workers[0], first_here=workers[1])
        workers = workers[0]
    else:
        one = BatchWorkers(cfg, 4, seed=5, workers=1)
    two = BatchWorkers(cfg, 4, seed=5, workers=workers, first_here=here)
    try:
        for venv in (one.venv, two.venv):
            venv.seed(40)
            venv.env_method("set_curriculum", 0.02, 0.5, near_share, (0.03, 0.3, 0.05, 5.0))
        o1, o2 = one.venv.reset(), two.venv.reset()
        np.testing.assert_array_equal(o1, o2)
        rng = np.random.default_rng(1)
        resets = collisions = 0
        for _ in range(20):  # through an auto-reset (15 steps per episode)
            a = rng.uniform(-1, 1, (4, 6)).astype(np.float32)
            r1, r2 = one.venv.step(a), two.venv.step(a)
            collisions += sum(bool(info["collided"]) for info in r1[3])
            np.testing.assert_array_equal(r1[0], r2[0])
            np.testing.assert_array_equal(r1[1], r2[1])
            assert r1[1].dtype == r2[1].dtype == np.float32  # VecNormalize keeps this dtype
            np.testing.assert_array_equal(r1[2], r2[2])
            _assert_same_infos(r1[3], r2[3])
            resets += int(r1[2].sum())
        assert resets >= 4
        if near_share > 0 and contact == "kernel":
            assert collisions > 0  # the vehicles touched the station in the kernel
        elif near_share > 0 and hasattr(one.venv, "physics"):
            assert one.venv.physics.physx_steps > 40  # the contact scene did the work
    finally:
        one.close()
        two.close()


def test_a_batched_run_over_two_processes_keeps_the_evaluation_its_workers_ran(
    tmp_path, monkeypatch
):
    """A real batched training run over two batch processes (the trainer's, holding the first
    half, and a worker process) evaluates in both (each runs its share: they leave their pid
    and episodes here): its history holds each evaluation, and best/ is a policy whose
    evaluation, run again as one batch here, gives the recorded success rates and collisions
    (returns to round-off)."""
    import os

    from uwdock.rl.evaluate.episodes import summarise
    from uwdock.rl.policy.policy_io import load_policy
    from uwdock.rl.train.batch_workers import BatchGroup
    from uwdock.rl.train.session import EVAL_SEED
    from uwdock.rl.train.training import PPOConfig, TrainConfig, train

    world = replace(WorldConfig(), batch_contact="own")
    env = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=2.0, world=world)
    cfg = TrainConfig(
        total_steps=64, n_envs=4, seed=3, checkpoint_every=32, eval_every=32, eval_episodes=5,
        env=env, simulator="batched", ppo=PPOConfig(n_steps=8, batch_size=16, n_epochs=1),
    )  # fmt: skip
    run, marks = tmp_path / "run", tmp_path / "marks"
    marks.mkdir()
    share = BatchGroup.evaluate_batch

    def marked(self, job, lo, hi):  # the workers are forked after this: they run it
        (marks / f"{os.getpid()}_{lo}_{hi}_{len(list(marks.iterdir()))}").touch()
        return share(self, job, lo, hi)

    monkeypatch.setattr(BatchGroup, "evaluate_batch", marked)
    train(cfg, run, progress=False, note=lambda m: None, batch_workers=2)
    ran = [m.name.split("_") for m in marks.iterdir()]
    assert len(ran) == 4
    where = {(int(r[1]), int(r[2])): int(r[0]) for r in ran}
    assert sorted(where) == [(0, 2), (2, 5)]
    assert where[(0, 2)] == os.getpid() != where[(2, 5)]  # the first share here, one there
    history = [json.loads(line) for line in (run / "eval_history.jsonl").open()]
    assert [h["step"] for h in history] == [32, 64] and all(h["episodes"] == 5 for h in history)
    kept = [h for h in history if h.get("best")][-1]
    model, vecnorm = load_policy(run / "best")
    again = summarise(batched_episodes(model, env, 5, EVAL_SEED, vecnorm))
    for k in ("success_rate", "success_rate_strict", "mean_collisions"):
        assert again[k] == kept[k], k
    assert again["mean_return"] == pytest.approx(kept["mean_return"], rel=1e-4)


def test_loading_an_evaluation_snapshot_leaves_the_global_generators_alone():
    """SB3's load reseeds Python's, NumPy's and torch's global generators with the saved seed;
    an evaluation share run in the trainer's process (the first batch group is there) would
    then change the training's own draws (its minibatches, its action noise)."""
    import random

    import torch
    from stable_baselines3 import PPO

    from uwdock.rl.policy.policy_format import policy_files
    from uwdock.rl.train.workers import EvalJob

    cfg = _quiet_cfg(episode_s=2.0)
    model = PPO("MlpPolicy", BatchDockingEnv(cfg, 2), n_steps=8, batch_size=16, seed=3)
    job = EvalJob(policy_files(model, None), cfg, 2, 31, 1)
    np.random.seed(123)  # noqa: NPY002
    random.seed(123)
    torch.manual_seed(123)
    want = (np.random.random(), random.random(), torch.rand(1).item())  # noqa: NPY002
    np.random.seed(123)  # noqa: NPY002
    random.seed(123)
    torch.manual_seed(123)
    loaded, _ = job.policy()
    assert loaded.num_timesteps == 0
    assert (np.random.random(), random.random(), torch.rand(1).item()) == want  # noqa: NPY002
