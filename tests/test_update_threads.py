"""``ppo.update_threads``: PPO's update runs on that many torch threads, the rollouts on one,
and the count does not change what is learned (the pinned kernels: the same weights with 1 and
2 update threads, so a recipe may use the cores its env workers leave idle)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch
from stable_baselines3 import PPO

from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.train.callbacks import TrainingCallback
from uwdock.rl.train.training import PPOConfig, TrainConfig, train
from uwdock.sim.world_config import WorldConfig

MODEL = str(Path(__file__).resolve().parents[1] / "rl/models/error_model_clear_tank_480_ar1.json")


def _cfg(threads: int) -> TrainConfig:
    env = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=2.0,
                    world=replace(WorldConfig(), batch_contact="kernel"))  # fmt: skip
    ppo = PPOConfig(n_steps=16, batch_size=64, n_epochs=3, net_arch=(256, 256),
                    update_threads=threads)  # fmt: skip
    return TrainConfig(total_steps=256, n_envs=8, seed=4, checkpoint_every=128, eval_every=0,
                       env=env, simulator="batched", ppo=ppo)  # fmt: skip


def _weights(run: Path) -> str:
    return hashlib.sha256((run / "weights.npz").read_bytes()).hexdigest()


def test_the_update_has_its_threads_the_rollouts_one_and_the_weights_do_not_change(
    tmp_path, monkeypatch
):
    seen: list[tuple[str, int]] = []
    update = PPO.train

    def recorded_update(self):
        seen.append(("update", torch.get_num_threads()))
        return update(self)

    step = TrainingCallback._on_step

    def recorded_step(self):  # each env step of a rollout
        seen.append(("rollout", torch.get_num_threads()))
        return step(self)

    monkeypatch.setattr(PPO, "train", recorded_update)
    monkeypatch.setattr(TrainingCallback, "_on_step", recorded_step)
    before = torch.get_num_threads()
    try:
        train(_cfg(2), tmp_path / "two", progress=False, note=lambda m: None)
        two = list(seen)
        seen.clear()
        train(_cfg(1), tmp_path / "one", progress=False, note=lambda m: None)
    finally:
        torch.set_num_threads(before)
    assert {n for what, n in two if what == "update"} == {2}
    assert {n for what, n in two if what == "rollout"} == {1}
    assert {n for _, n in seen} == {1}
    assert len([w for w, _ in two if w == "update"]) == 2  # 256 steps in rollouts of 128
    assert _weights(tmp_path / "two") == _weights(tmp_path / "one")


def test_update_threads_outside_its_domain_is_refused():
    from uwdock.dockcore.config import from_dict
    from uwdock.dockcore.errors import DockError

    with pytest.raises((DockError, ValueError), match="update_threads"):
        from_dict(TrainConfig, {"ppo": {"update_threads": 0}})
