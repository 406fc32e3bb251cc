"""Training: ``rl train`` (PPO or SAC in a resumable run folder), its env workers, checkpoints,
evaluations and callbacks, the warm starts, recipes and sweeps. Imports ``rl.env``,
``rl.policy`` and ``rl.evaluate``; ``rl.deploy`` is its peer (neither imports the other).

Modules:
    training:        ``rl train``: the configs, the run folder, the learner.
    session:         one run's state between rollouts: schedule, evaluations, ``best/``.
    checkpoint:      checkpoints as transactions (data, no pickles).
    callbacks:       the rollout boundaries and TensorBoard charts (SB3 at module level).
    imitation:       DAgger from the PID baseline, before PPO.
    widen:           a policy fine-tuned on a wider observation.
    workers:         what runs in an env worker; a worker's failure in one line.
    vec_envs:        the learner's vectorised env over local worker processes.
    grouped_vec_env: SB3's ``VecEnv`` over groups of envs on workers (SB3 at module level).
    ray_envs:        the env groups as Ray actors.
    batch_workers:   the batched simulator split over worker processes.
    recipe:          a policy trained in stages by one command.
    sweep:           multi-seed and hyper-parameter sweeps through Ray Tune.
"""
