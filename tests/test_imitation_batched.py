"""The warm start on the batched simulator: an iteration's episodes all at once, each what the
teacher flies in a batch of its own (checked against the batched evaluation), its labels the
teacher's, and a student that imitates."""

from __future__ import annotations

import numpy as np
import pytest
from tqdm import tqdm

from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.evaluate.batched import batched_episodes
from uwdock.rl.policy.baselines import PIDController
from uwdock.rl.train.imitation import ImitationConfig, _BatchRollouts, _discounted, warm_start

# starts above the seat: the teacher docks most in 11-16 s; a 20 s cap ends some undocked
CFG = replace(
    EnvConfig(),
    episode_s=20.0,
    spawn_auv_range_m=(0.6, 0.6, 0.2),
    spawn_ds_range_m=(0.2, 0.2, 0.0),
    terminate_on="strict",
)


class PIDs:
    """One PID per env, as the warm start's teachers: ``act_batch`` for the batched evaluation."""

    def __init__(self, n: int) -> None:
        self.pids = [PIDController.for_env(CFG) for _ in range(n)]

    def act(self, obs: np.ndarray) -> np.ndarray:  # a controller; the batch calls act_batch
        raise AssertionError("one PID per env: act_batch")

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        return np.stack([p.act(o) for p, o in zip(self.pids, obs, strict=True)])


def test_batched_teacher_episodes_are_those_of_the_batched_evaluation():
    n, seed = 6, 500_000
    icfg = ImitationConfig(episodes_per_iteration=n)
    bar = tqdm(total=n, disable=True)
    roll = _BatchRollouts(CFG, "success_strict", None, None, icfg, 0.99, bar, ep_seed=seed)
    try:
        frac, O, A, G = roll.collect(student=False)
    finally:
        roll.close()
    rows = batched_episodes(PIDs(n), CFG, n, seed)
    assert [len(o) for o in O] == [r["steps"] for r in rows]
    assert roll.steps == sum(r["steps"] for r in rows)
    assert frac == pytest.approx(np.mean([r["success_strict"] for r in rows]))
    assert 0 < frac < 1  # most dock, not all (the 20 s cap)
    for o, a, g in zip(O, A, G, strict=True):
        # the labels are the teacher's own actions on the observations kept
        pid = PIDController.for_env(CFG)
        assert np.array_equal(a, np.stack([pid.act(x) for x in o]))
        assert g.shape == (len(o),)
    # gamma 1: G[0] is the episode's return the evaluation counted
    roll = _BatchRollouts(CFG, "success_strict", None, None, icfg, 1.0, bar, ep_seed=seed)
    try:
        _, _, _, G1 = roll.collect(student=False)
    finally:
        roll.close()
    assert [g[0] for g in G1] == pytest.approx([r["return"] for r in rows], rel=1e-9)
    assert roll.ep_seed == seed + n  # the next iteration's episodes are new ones


def test_discounted_return_is_the_backward_sum():
    r = np.array([1.0, 2.0, 4.0])
    assert _discounted(r, 0.5) == pytest.approx([1 + 0.5 * 2 + 0.25 * 4, 2 + 0.5 * 4, 4.0])


def test_batched_warm_start_imitates_the_teacher(tmp_path):
    import torch
    from stable_baselines3.common.vec_env import VecNormalize

    from uwdock.rl.env.batch_env import BatchDockingEnv
    from uwdock.rl.train.training import PPOConfig, TrainConfig, build_model

    cfg = replace(TrainConfig(), n_envs=4, env=CFG, ppo=replace(PPOConfig(), batch_size=64))
    venv = VecNormalize(BatchDockingEnv(CFG, 4))
    model = build_model(cfg, venv, tmp_path / "tb")
    untrained = batched_episodes(model, CFG, 8, 700_000, vecnorm=venv)
    icfg = ImitationConfig(iterations=2, episodes_per_iteration=8, epochs=40, log_std=-1.5)
    hist = warm_start(model, venv, CFG, icfg, seed=0, gamma=0.99, progress=False, batched=True)
    assert len(hist["loss"]) == 2 and hist["loss"][-1] < 0.08
    assert torch.allclose(model.policy.log_std, torch.full((6,), -1.5))
    sel = hist["selected_iteration"][0]
    assert venv.obs_rms.count == pytest.approx(1e-4 + sum(hist["samples"][: sel + 1]))
    # every transition of the three batches (two iterations and the final score) is counted
    assert hist["env_steps"][0] > sum(hist["samples"])

    # the student flies like the teacher (0.875 and 0.75 of 8 held-out starts), the network
    # before the warm start docked none
    def docked(rows):
        return np.mean([r["success_strict"] for r in rows])

    student = docked(batched_episodes(model, CFG, 8, 700_000, vecnorm=venv))
    teacher = docked(batched_episodes(PIDs(8), CFG, 8, 700_000))
    assert docked(untrained) == 0 and student >= teacher - 0.25 and student >= 0.5
    venv.close()


def test_the_warm_start_split_over_the_batch_workers_is_the_one_process_warm_start(tmp_path):
    """The warm start's batch split over the training's two batch processes (the trainer's and
    a worker's, 3 and 2 episodes) is the batch of one process: the same episodes, the same
    fitted weights and normalisation to the bit (with the kernel's station contact, the
    recipe's: the shared PhysX scene rounds contacts by how the batch is split)."""
    import hashlib

    from stable_baselines3.common.vec_env import VecNormalize

    from uwdock.rl.env.batch_env import BatchDockingEnv
    from uwdock.rl.train.batch_workers import BatchWorkers
    from uwdock.rl.train.training import PPOConfig, TrainConfig, build_model

    env = replace(CFG, world=replace(CFG.world, batch_contact="kernel"))
    cfg = replace(TrainConfig(), n_envs=4, env=env, ppo=replace(PPOConfig(), batch_size=64))
    icfg = ImitationConfig(iterations=2, episodes_per_iteration=5, epochs=3)
    out = {}
    for split in (False, True):
        workers = BatchWorkers(env, 4, seed=0, workers=2) if split else None
        venv = VecNormalize(workers.venv if split else BatchDockingEnv(env, 4))
        try:
            model = build_model(cfg, venv, tmp_path / f"tb{split}")
            hist = warm_start(
                model, venv, env, icfg, seed=0, gamma=0.99, progress=False, batched=True,
                workers=workers.venv if split else None,
            )  # fmt: skip
            weights = b"".join(p.detach().numpy().tobytes() for p in model.policy.parameters())
            rms = venv.obs_rms.mean.tobytes() + venv.obs_rms.var.tobytes()
            out[split] = (hist, hashlib.sha256(weights + rms).hexdigest())
        finally:
            venv.close() if workers is None else workers.close()
    assert out[True][0]["env_steps"] == out[False][0]["env_steps"]
    assert out[True] == out[False]
