"""Evaluation episodes on the batched simulator (:class:`rl.env.batch_env.BatchDockingEnv`): every
episode at once, one env each, with the rows :func:`rl.evaluate.episodes.run_episodes` gives."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.evaluate.episodes import as_controller, episode_row
from uwdock.rl.evaluate.failures import FailureTracker

if TYPE_CHECKING:
    from uwdock.rl.env.batch_env import BatchDockingEnv

__all__ = ["batched_episodes"]


def batched_episodes(
    policy,
    env_cfg: EnvConfig,
    n_episodes: int,
    seed: int,
    vecnorm=None,
    first: int = 0,
    venv: BatchDockingEnv | None = None,
) -> list[dict[str, Any]]:
    """Episodes ``0 .. n_episodes - 1`` of a policy (deterministic) on the batched
    simulator, all at once: episode ``k`` is env ``k`` of one :class:`BatchDockingEnv`, first
    reset with ``seed + k`` (the spawn, vehicle, current and prior of
    :func:`rl.evaluate.episodes.run_episodes`'s episode ``k``; the per-step noise is the batch's
    own).

    Rows as :func:`rl.evaluate.episodes.run_episodes` gives them
    (:func:`rl.evaluate.episodes.episode_row`). An env whose episode ended flies on with zero thrust
    until the last one ends, so it costs the numba kernel, not PhysX.

    Args:
        policy: an SB3 model (with ``vecnorm``, its observation normalisation, or None), or a
            stateless controller (``act_batch`` for all envs at once, else ``act`` per env).
        env_cfg: the evaluation env (its ``obs_source`` must be batchable).
        n_episodes: how many episodes (envs); seed: seed of episode 0.
        first: the first episode's number: the episodes are ``first .. first + n_episodes -
            1`` (a share of a larger evaluation), env ``i`` is episode ``first + i``.
        venv: a batch of ``n_episodes`` envs of ``env_cfg`` to run them in, kept open
            (reseeded: the rows are those of a new one, tested); default a new one, closed.
    """
    from uwdock.rl.env.batch_env import BatchDockingEnv  # SB3 at module level

    ctrl = as_controller(policy, vecnorm)
    own = venv is None
    if venv is None:
        venv = BatchDockingEnv(env_cfg, n_episodes, seed=seed + first)
    elif venv.num_envs != n_episodes or venv.cfg != env_cfg:
        raise ValueError("batched_episodes: venv must hold n_episodes envs of env_cfg")
    else:
        venv.seed(seed + first)  # as a new batch: each env's reset and noise from seed + k
    n = venv.num_envs
    rows: list[dict[str, Any] | None] = [None] * n
    trackers = [FailureTracker() for _ in range(n)]
    steps = np.zeros(n, dtype=np.int64)
    ret = np.zeros(n)
    coll = np.zeros(n, dtype=np.int64)
    dock: list[float | None] = [None] * n
    live = np.ones(n, dtype=bool)
    try:
        obs = venv.reset()
        while live.any():
            if hasattr(ctrl, "act_batch"):
                acts = np.asarray(ctrl.act_batch(obs), dtype=np.float64)
            else:
                acts = np.stack([np.asarray(ctrl.act(x), dtype=np.float64) for x in obs])
            acts = acts.reshape(n, 6)
            acts[~live] = 0.0
            if not np.all(np.isfinite(acts)):
                raise DockError("the policy gave a non-finite action: its weights are broken")
            obs, rew, done, infos = venv.step(acts)
            for i in np.flatnonzero(live):
                info = infos[i]
                steps[i] += 1
                ret[i] += rew[i]
                coll[i] += int(info["collided"])
                trackers[i].update(
                    info["time_s"], info["T_world_body"][:3, 3], info["e_true"], acts[i]
                )
                if info["success_paper"] and dock[i] is None:
                    dock[i] = info["time_s"]
                if done[i]:
                    rows[i] = episode_row(
                        first + i, seed, info, dock[i], steps[i], ret[i], coll[i], trackers[i]
                    )
                    live[i] = False
    finally:
        if own:
            venv.close()
    return [r for r in rows if r is not None]
