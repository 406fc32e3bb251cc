"""Reinforcement learning for docking: the Gymnasium env, observation sources, the DS pose
filter, PPO/SAC training, evaluation, the PID baseline and ONNX export.

Importing ``rl`` registers the environment with Gymnasium as ``uwdock/Docking-v0``::

    import gymnasium as gym
    import uwdock.rl  # noqa: F401
    from uwdock.rl.config import EnvConfig
    env = gym.make("uwdock/Docking-v0", config=EnvConfig(obs_source="proxy"))
"""

if __name__ != "uwdock.rl":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.rl: import uwdock.rl "
        "(pip install -e . from the repository puts it there)"
    )
import gymnasium as _gym

ENV_ID = "uwdock/Docking-v0"

if ENV_ID not in _gym.registry:
    _gym.register(id=ENV_ID, entry_point="uwdock.rl.env:DockingEnv", max_episode_steps=None)
