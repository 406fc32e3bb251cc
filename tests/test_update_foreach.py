"""PPO's Adam steps over all tensors at once (``foreach``): the same bits as one tensor at a time,
so the recipe's faster update learns exactly what the per-tensor update would, and SB3's own
``eps`` is kept (SB3 sets it only when no optimizer options are given)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.train import training
from uwdock.rl.train.training import PPOConfig, TrainConfig, train
from uwdock.sim.world_config import WorldConfig

MODEL = str(Path(__file__).resolve().parents[1] / "rl/models/error_model_clear_tank_480_ar1.json")


def _cfg() -> TrainConfig:
    env = EnvConfig(obs_source="error-model", error_model_path=MODEL, episode_s=2.0,
                    world=replace(WorldConfig(), batch_contact="kernel"))  # fmt: skip
    ppo = PPOConfig(n_steps=16, batch_size=64, n_epochs=3, net_arch=(64, 64))
    return TrainConfig(total_steps=384, n_envs=8, seed=6, checkpoint_every=128, eval_every=0,
                       env=env, simulator="batched", ppo=ppo)  # fmt: skip


def _weights(run: Path) -> str:
    return hashlib.sha256((run / "weights.npz").read_bytes()).hexdigest()


def test_the_optimizer_is_adam_over_all_tensors_with_sb3s_eps(tmp_path, monkeypatch):
    seen: dict[str, object] = {}
    build = training.build_model

    def recorded(cfg, venv, tb_dir):
        model = build(cfg, venv, tb_dir)
        group = model.policy.optimizer.param_groups[0]
        seen.update(cls=type(model.policy.optimizer), eps=group["eps"], foreach=group["foreach"])
        return model

    monkeypatch.setattr(training, "build_model", recorded)
    train(replace(_cfg(), total_steps=128), tmp_path / "run", progress=False,
          note=lambda m: None)  # fmt: skip
    assert seen == {"cls": torch.optim.Adam, "eps": 1e-5, "foreach": True}


def test_adam_over_all_tensors_learns_the_same_bits_as_one_at_a_time(tmp_path, monkeypatch):
    """Three PPO updates (3 epochs of 2 minibatches each) with each Adam: the weights agree byte
    for byte, and they moved (the update is not a no-op)."""
    runs, models, first = {}, [], []
    for foreach in (True, False):
        build = training.build_model

        def with_foreach(cfg, venv, tb_dir, foreach=foreach, build=build):
            model = build(cfg, venv, tb_dir)
            for group in model.policy.optimizer.param_groups:
                group["foreach"] = foreach
            models.append(model)
            first.append([t.detach().clone() for t in model.policy.parameters()])
            return model

        monkeypatch.setattr(training, "build_model", with_foreach)
        out = tmp_path / f"foreach_{foreach}"
        train(_cfg(), out, progress=False, note=lambda m: None)
        monkeypatch.undo()
        runs[foreach] = out
    assert _weights(runs[True]) == _weights(runs[False])
    final = list(models[0].policy.parameters())
    moved = [not torch.equal(a, b) for a, b in zip(first[0], final, strict=True)]
    assert sum(moved) >= len(moved) - 1  # all but, at most, the action's log std


def test_the_warm_starts_fit_with_adam_over_all_tensors_is_the_one_at_a_time_fit(monkeypatch):
    """DAgger's supervised fit (rl.train.imitation) asks for Adam over all tensors, and gets
    the bits of the per-tensor Adam: policy and value fitted to random labels, byte for byte."""
    import copy

    import numpy as np

    from uwdock.rl.policy.policy_io import load_policy
    from uwdock.rl.train import imitation

    model, _ = load_policy(str(Path(__file__).resolve().parents[1] / "rl/policies/realistic_ppo"))
    start = copy.deepcopy(model.policy.state_dict())
    rng = np.random.default_rng(3)
    X, A = rng.normal(0, 1, (1500, 18)), rng.uniform(-1.2, 1.2, (1500, 6))
    G = rng.normal(0, 5, 1500)
    cfg = imitation.ImitationConfig(epochs=3)
    adam, asked, out = torch.optim.Adam, [], {}
    for foreach in (True, False):

        def built(*args, _forced=foreach, **kwargs):
            asked.append(kwargs.get("foreach"))
            return adam(*args, **{**kwargs, "foreach": _forced})

        monkeypatch.setattr(torch.optim, "Adam", built)
        model.policy.load_state_dict(start)
        imitation._fit_epochs(model, None, X, A, G, cfg)
        out[foreach] = b"".join(p.detach().numpy().tobytes() for p in model.policy.parameters())
    assert asked == [True, True]  # what the fit asks for
    assert out[True] == out[False]
    moved = b"".join(t.numpy().tobytes() for t in start.values())
    assert out[True] != moved
