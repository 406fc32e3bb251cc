"""Asymmetric actor-critic: the critic sees privileged state in training only; the actor, the
export, ``rl eval`` and the deployment runner never do."""

from __future__ import annotations

import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.env.observation import PRIVILEGED_DIM, actor_observation_size, observation_size
from uwdock.rl.train.training import TrainConfig

ENV = replace(EnvConfig(), episode_s=4.0, obs_privileged=True)


def _model(env_cfg: EnvConfig = ENV):
    from stable_baselines3.common.vec_env import DummyVecEnv

    from uwdock.rl.train.training import build_model

    cfg = replace(TrainConfig(), env=env_cfg)
    venv = DummyVecEnv([lambda: DockingEnv(env_cfg, privileged=True)])
    return build_model(cfg, venv, tb_dir=Path(tempfile.mkdtemp()))


def test_layout_and_only_training_envs_fill_the_block():
    n_actor = actor_observation_size(ENV)
    assert observation_size(ENV) == n_actor + PRIVILEGED_DIM
    assert observation_size(replace(ENV, obs_privileged=False)) == n_actor
    train_env, eval_env = DockingEnv(ENV, privileged=True), DockingEnv(ENV)
    try:
        for env in (train_env, eval_env):
            obs, _ = env.reset(seed=3)
            assert obs.shape == (n_actor + PRIVILEGED_DIM,)
        rng = np.random.default_rng(0)
        for _ in range(5):
            a = rng.uniform(-1, 1, 6)
            obs_t, _, _, _, info_t = train_env.step(a)
            obs_e, *_ = eval_env.step(a)
            # the same episode: identical actor inputs, the block only in the training env
            np.testing.assert_array_equal(obs_t[:n_actor], obs_e[:n_actor])
            assert not np.any(obs_e[n_actor:])
            block = obs_t[n_actor:]
            np.testing.assert_allclose(block[:3] * 5.0, info_t["e_true"], atol=1e-5)
            assert block[3] == pytest.approx(info_t["e_psi_true"] / np.pi, abs=1e-6)
            assert block[7] == pytest.approx(1 - train_env.steps / train_env.max_steps)
    finally:
        train_env.close()
        eval_env.close()


def test_actor_ignores_the_block_the_critic_reads_it_and_it_survives_save_and_export(tmp_path):
    from stable_baselines3 import PPO

    from uwdock.rl.policy.asymmetric import AsymmetricPolicy

    model = _model()
    pol = model.policy
    assert isinstance(pol, AsymmetricPolicy)
    n_actor = actor_observation_size(ENV)
    obs = torch.as_tensor(np.random.default_rng(1).normal(size=(8, observation_size(ENV))))
    other = obs.clone()
    other[:, n_actor:] += 3.0
    with torch.no_grad():
        a1 = pol.get_distribution(obs.float()).distribution.mean
        a2 = pol.get_distribution(other.float()).distribution.mean
        v1, v2 = pol.predict_values(obs.float()), pol.predict_values(other.float())
    torch.testing.assert_close(a1, a2)
    assert not torch.allclose(v1, v2)

    buf = io.BytesIO()
    model.save(buf)
    buf.seek(0)
    loaded = PPO.load(buf, device="cpu")
    assert isinstance(loaded.policy, AsymmetricPolicy)
    assert loaded.policy.actor_obs_dim == n_actor

    from uwdock.rl.policy.export import _actor_module

    actor = _actor_module(loaded, None)
    with torch.no_grad():
        torch.testing.assert_close(actor(obs.float()), actor(other.float()))
        torch.testing.assert_close(actor(obs.float()), torch.clamp(a1, -1, 1))


def test_rl_eval_and_the_runner_never_see_privileged_state(monkeypatch):
    from uwdock.rl.deploy.runner import DockingRunner, Odometry
    from uwdock.rl.evaluate import episodes as evaluate
    from uwdock.rl.policy.baselines import PIDController

    seen = []

    class Spy(DockingEnv):
        def _obs(self, *args):
            obs = super()._obs(*args)
            seen.append((self.privileged, obs[actor_observation_size(self.cfg) :].copy()))
            return obs

    monkeypatch.setattr(evaluate, "DockingEnv", Spy)
    evaluate.run_episodes(PIDController.for_env(ENV), ENV, 1, seed=5, record=False)
    assert seen and not any(p for p, _ in seen)
    assert not any(np.any(b) for _, b in seen)

    got = []

    class Recorder:
        def act(self, obs):
            got.append(np.asarray(obs))
            return np.zeros(6)

    runner = DockingRunner(Recorder(), env_cfg=ENV)
    runner.reset(np.eye(4))
    odom = Odometry(np.eye(4), np.zeros(3), 0.0, np.zeros(3))
    runner.step(None, odom)
    assert got[0].shape == (observation_size(ENV),)
    assert not np.any(got[0][actor_observation_size(ENV) :])


def test_sac_refuses_the_asymmetric_critic():
    from uwdock.dockcore.config import validated

    with pytest.raises(ValueError, match="PPO only"):
        validated(replace(TrainConfig(), algo="sac", env=ENV))
