"""Reinforcement learning for docking: the Gymnasium env, observation sources, the DS pose
filter, PPO/SAC training, evaluation, the PID baseline and ONNX export.

Importing ``rl`` registers the environment with Gymnasium as ``uwdock/Docking-v0``::

    import gymnasium as gym
    import rl  # noqa: F401
    env = gym.make("uwdock/Docking-v0", config=rl.config.EnvConfig(obs_source="proxy"))
"""

import gymnasium as _gym

ENV_ID = "uwdock/Docking-v0"

if ENV_ID not in _gym.registry:
    _gym.register(id=ENV_ID, entry_point="rl.env:DockingEnv", max_episode_steps=None)
