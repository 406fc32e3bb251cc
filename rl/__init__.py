"""Reinforcement learning for docking: the Gymnasium env, observation sources, the DS pose
filter, PPO/SAC training, evaluation, the PID baseline and ONNX export.

Its rooms, each importing only those below it (``uwdock.ROOMS``; ``tests/test_architecture.py``):

=================  ===============================================================  ====
room               what it holds                                                    rank
=================  ===============================================================  ====
``rl.env``         the task, observation sources, filter, reward, the env, batched  0
``rl.policy``      policy files, controllers, the PID baseline, the policy's env     1
``rl.evaluate``    seeded episodes, their rows, failures, reports, videos            2
``rl.train``       ``rl train``: workers, checkpoints, resume, recipes, sweeps       3
``rl.deploy``      the runner, the docking node, replay, the simulated vehicle       3
``rl.cli``         the ``rl`` command                                                4
=================  ===============================================================  ====

Importing ``rl`` registers the environment with Gymnasium as ``uwdock/Docking-v0`` (where
Gymnasium is installed: the vehicle install runs the node without it)::

    import gymnasium as gym
    import uwdock.rl  # noqa: F401
    from uwdock.rl.env.config import EnvConfig
    env = gym.make("uwdock/Docking-v0", config=EnvConfig(obs_source="proxy"))
"""

if __name__ != "uwdock.rl":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.rl: import uwdock.rl "
        "(pip install -e . from the repository puts it there)"
    )
ENV_ID = "uwdock/Docking-v0"

try:  # the vehicle install (``uwdock[vehicle]``: the node and replay) has no Gymnasium
    import gymnasium as _gym
except ModuleNotFoundError:  # pragma: no cover - exercised by the vehicle-install test
    _gym = None
if _gym is not None and ENV_ID not in _gym.registry:
    _gym.register(
        id=ENV_ID, entry_point="uwdock.rl.env.docking_env:DockingEnv", max_episode_steps=None
    )
