"""Fine-tuning on a wider observation (rl.train.widen): a policy trained without ``obs_fine_error``
starts a run with it as exactly itself, and layouts that are not a widening are refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uwdock.dockcore.config import replace
from uwdock.dockcore.errors import DockError
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.observation import frame_dim, observation_size
from uwdock.rl.train.widen import widen_obs_rms, widen_state_dict, widening_index
from uwdock.sim.world_config import WorldConfig

MODEL = "rl/models/error_model_clear_tank_480_ar1.json"


def _env(**kw) -> EnvConfig:
    world = replace(WorldConfig(), batch_contact="own")
    base = {"obs_source": "error-model", "error_model_path": MODEL, "episode_s": 2.0}
    return EnvConfig(**(base | {"world": world, "obs_contact": True} | kw))


def test_the_index_maps_every_old_entry_to_its_place_in_each_wider_frame():
    old, new = _env(), _env(obs_fine_error=True)
    index = widening_index(old, new)
    fo, fn = frame_dim(old), frame_dim(new)
    assert fn == fo + 3
    np.testing.assert_array_equal(index, np.arange(fo))
    three = widening_index(replace(old, obs_frames=3), replace(new, obs_frames=3))
    want = np.concatenate([np.arange(fo) + k * fn for k in range(3)])
    np.testing.assert_array_equal(three, want)
    assert widening_index(new, new) is None and widening_index(old, old) is None
    with pytest.raises(ValueError, match="obs_contact"):
        widening_index(replace(old, obs_contact=False), new)
    with pytest.raises(ValueError, match="on in the init policy"):
        widening_index(new, old)
    with pytest.raises(ValueError, match="privileged"):
        widening_index(replace(old, obs_privileged=True), replace(new, obs_privileged=True))


def test_the_widened_model_acts_and_values_as_the_old_one_whatever_the_new_inputs_read():
    """Actions (the Gaussian's mean) and values of the widened PPO policy on observations whose
    fine-error entries hold anything equal the old policy's on the same observations without
    them; the normalisation maps the old entries as before and leaves the new ones as they are."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.running_mean_std import RunningMeanStd

    from uwdock.rl.env.batch_env import BatchDockingEnv

    old_env, new_env = _env(), _env(obs_fine_error=True)
    kw = {"n_steps": 8, "batch_size": 16, "seed": 3, "device": "cpu"}
    old = PPO("MlpPolicy", BatchDockingEnv(old_env, 2), **kw)
    new = PPO("MlpPolicy", BatchDockingEnv(new_env, 2), **kw | {"seed": 4})
    with torch.no_grad():  # an old policy whose input weights are not the initial ones
        for p in old.policy.parameters():
            p.add_(0.1 * torch.randn_like(p))
    index = widening_index(old_env, new_env)
    od, nd = observation_size(old_env), observation_size(new_env)
    new.policy.load_state_dict(
        widen_state_dict(old.policy.state_dict(), new.policy.state_dict(), index, od, nd)
    )
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (50, nd)).astype(np.float32)
    with torch.no_grad():
        a_old = old.policy.get_distribution(torch.as_tensor(x[:, index])).distribution.mean
        a_new = new.policy.get_distribution(torch.as_tensor(x)).distribution.mean
        v_old = old.policy.predict_values(torch.as_tensor(x[:, index]))
        v_new = new.policy.predict_values(torch.as_tensor(x))
    np.testing.assert_allclose(a_new.numpy(), a_old.numpy(), atol=1e-6)
    np.testing.assert_allclose(v_new.numpy(), v_old.numpy(), atol=1e-6)
    assert np.abs(a_old.numpy()).max() > 1e-3  # the comparison is not of zeros
    # a new input does reach the network once its weights move off 0
    with torch.no_grad():
        first = new.policy.mlp_extractor.policy_net[0].weight
        assert torch.all(first[:, od:] == 0)
        first[:, od:] = 0.5
        moved = new.policy.get_distribution(torch.as_tensor(x)).distribution.mean
    assert not np.allclose(moved.numpy(), a_old.numpy(), atol=1e-3)
    rms = RunningMeanStd(shape=(od,))
    rms.update(rng.normal(3.0, 2.0, (200, od)))
    wide = widen_obs_rms(rms, index, nd)
    np.testing.assert_array_equal(wide.mean[index], rms.mean)
    np.testing.assert_array_equal(wide.var[index], rms.var)
    np.testing.assert_array_equal(wide.mean[od:], 0.0)
    np.testing.assert_array_equal(wide.var[od:], 1.0)
    assert wide.count == rms.count and rms.mean.shape == (od,)  # the source is untouched
    bad = {k: v for k, v in old.policy.state_dict().items()}
    key = next(k for k in bad if k.endswith("policy_net.0.weight"))
    bad[key] = bad[key][:, :-1]
    with pytest.raises(ValueError, match="does not widen"):
        widen_state_dict(bad, new.policy.state_dict(), index, od, nd)


def test_a_run_with_the_fine_error_starts_from_a_policy_trained_without_it(tmp_path):
    """rl train --init-policy: a policy of the narrower layout is widened (the run says so); one
    whose layout differs otherwise is refused with the one-line dimension error."""
    from uwdock.rl.train.training import PPOConfig, TrainConfig, train

    ppo = PPOConfig(n_steps=8, batch_size=16, n_epochs=1)
    base = {"total_steps": 32, "n_envs": 2, "seed": 3, "checkpoint_every": 32, "eval_every": 32}
    base |= {"eval_episodes": 2, "simulator": "batched", "ppo": ppo}
    train(TrainConfig(**base, env=_env()), tmp_path / "a", progress=False, note=lambda m: None)
    notes: list[str] = []
    wide = TrainConfig(**base, env=_env(obs_fine_error=True))
    train(wide, tmp_path / "b", progress=False, note=notes.append,
          init_policy=str(tmp_path / "a"))  # fmt: skip
    od, nd = observation_size(_env()), observation_size(_env(obs_fine_error=True))
    assert f"--init-policy: widened from {od} to {nd} observation values" in notes
    other = TrainConfig(**base, env=_env(obs_contact=False, obs_fine_error=True))
    with pytest.raises(DockError, match=r"observation values.*differs in obs_contact"):
        train(other, tmp_path / "c", progress=False, note=lambda m: None,
              init_policy=str(tmp_path / "a"))  # fmt: skip
