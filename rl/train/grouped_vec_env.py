"""The learner's side of the env groups: :class:`GroupedVecEnv`, SB3's ``VecEnv`` over the groups
of envs that worker processes (:class:`rl.train.vec_envs.PipeHosts`) or Ray actors
(:class:`rl.train.ray_envs.RayHosts`) hold (see :mod:`rl.train.vec_envs` for the groups).

This module subclasses Stable-Baselines3's ``VecEnv``, so it imports SB3 (and torch under it) at
module level: it is imported only inside the functions that build a vectorised env, never by a
module that a light command imports (``tests/test_architecture.py``: heavy modules of the tree).
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from uwdock.rl.env.batch_env import StepColumns, info_rows

if TYPE_CHECKING:
    from uwdock.rl.env.config import EnvConfig
    from uwdock.rl.train.workers import EvalJob

__all__ = ["BatchGroupsVecEnv", "GroupedVecEnv", "Hosts", "SplitBatch", "stack_observations"]


class Hosts(Protocol):
    """Where the groups live: call a group's method without waiting, then wait for results."""

    def submit(self, worker: int, method: str, *args: Any) -> Any:
        """Start ``group.<method>(*args)`` on ``worker``; returns a handle for :meth:`gather`."""

    def gather(self, handles: Sequence[Any]) -> list[Any]:
        """The results of the handles' calls, in order (a failure raises)."""

    def shutdown(self) -> None:
        """Stop the workers (after their groups were closed, or when they cannot answer)."""


def stack_observations(obs: Sequence[Any], space: spaces.Space) -> Any:
    """The per-env observations ``obs`` as one batch, as SB3's ``VecEnv`` returns it: for a
    ``Dict`` space a dict of arrays (each ``(n_envs, *shape)``), for a ``Tuple`` space a tuple of
    them, else one array ``(n_envs, *shape)`` (the docking env's ``Box``).

    Args:
        obs: one observation per env, in env order (at least one).
        space: the envs' observation space.
    """
    if isinstance(space, spaces.Dict):
        return {key: np.stack([o[key] for o in obs]) for key in space.spaces}
    if isinstance(space, spaces.Tuple):
        return tuple(np.stack([o[i] for o in obs]) for i in range(len(space.spaces)))
    return np.stack(obs)


def consecutive_spans(n: int, workers: int) -> list[tuple[int, int]]:
    """``n`` items in ``workers`` consecutive shares as even as they go: ``(lo, hi)`` each."""
    cuts = [n * k // workers for k in range(workers + 1)]
    return [(cuts[k], cuts[k + 1]) for k in range(workers)]


def joined_steps(parts: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
    """The shares' :meth:`BatchGroup.step_batch` arrays as one step of all their envs:
    observations, rewards, dones and SB3's per-env infos."""
    return (
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
        info_rows(StepColumns.concat([p[3] for p in parts])),
    )


class GroupedVecEnv(VecEnv):
    """``n_envs`` envs in groups on workers behind SB3's ``VecEnv`` (:mod:`rl.train.vec_envs`).

    Args:
        hosts: the workers (:class:`rl.train.vec_envs.PipeHosts` or
        :class:`rl.train.ray_envs.RayHosts`).
        groups: the env indices each worker holds (:func:`rl.train.vec_envs.env_groups`).
    """

    def __init__(self, hosts: Hosts, groups: list[list[int]]) -> None:
        self.hosts = hosts
        self.groups = groups
        self._where = [(w, s) for w, g in enumerate(groups) for s in range(len(g))]
        self.waiting = False
        self.closed = False
        self._pending: list[Any] = []
        packed = hosts.gather([hosts.submit(0, "spaces")])[0]
        obs_space, act_space = pickle.loads(packed)
        super().__init__(len(self._where), obs_space, act_space)

    @property
    def processes(self) -> list[Any]:
        """The local worker processes (none on Ray)."""
        return list(getattr(self.hosts, "processes", []))

    def _by_group(self, method: str, *per_env: Sequence[Any]) -> list[Any]:
        """Call ``method`` once per group with its envs' share of each ``per_env`` list;
        returns the handles."""
        return [
            self.hosts.submit(w, method, *([seq[i] for i in g] for seq in per_env))
            for w, g in enumerate(self.groups)
        ]

    def _flat(self, handles: Sequence[Any]) -> list[Any]:
        """The groups' per-env results, in env order."""
        return [r for rs in self.hosts.gather(handles) for r in rs]

    def _per_env(self, method: str, indices: Any, *args: Any) -> list[Any]:
        """``group.<method>(slots, *args)`` for the given envs, results in their order."""
        idx = list(self._get_indices(indices))
        by_worker: dict[int, list[int]] = {}
        for i in idx:
            by_worker.setdefault(self._where[i][0], []).append(i)
        handles = [
            self.hosts.submit(w, method, [self._where[i][1] for i in envs], *args)
            for w, envs in by_worker.items()
        ]
        found: dict[int, Any] = {}
        for envs, res in zip(by_worker.values(), self.hosts.gather(handles), strict=True):
            found.update(zip(envs, res, strict=True))
        return [found[i] for i in idx]

    def step_async(self, actions: np.ndarray) -> None:
        self._pending = self._by_group("step", actions)
        self.waiting = True

    def step_wait(self):
        results = self._flat(self._pending)
        self.waiting = False
        obs, rews, dones, infos, self.reset_infos = zip(*results, strict=True)
        return (
            stack_observations(obs, self.observation_space),
            np.stack(rews),
            np.stack(dones),
            infos,
        )

    def reset(self):
        results = self._flat(self._by_group("reset", self._seeds, self._options))
        obs, self.reset_infos = zip(*results, strict=True)
        self._reset_seeds()
        self._reset_options()
        return stack_observations(obs, self.observation_space)

    def close(self) -> None:
        if self.closed:
            return
        try:
            if self.waiting:
                self.hosts.gather(self._pending)
            self.hosts.gather(self._by_group("close"))
        except Exception:  # a worker already gone: nothing to flush
            pass
        self.hosts.shutdown()
        self.closed = True

    def get_images(self) -> Sequence[np.ndarray | None]:
        return self._per_env("render", None)

    def has_attr(self, attr_name: str) -> bool:
        return all(self._per_env("has_attr", None, attr_name))

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return self._per_env("get_attr", indices, attr_name)

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        self._per_env("set_attr", indices, attr_name, value)

    def env_method(
        self, method_name: str, *method_args, indices=None, **method_kwargs
    ) -> list[Any]:
        return self._per_env("env_method", indices, method_name, method_args, method_kwargs)

    def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
        return self._per_env("is_wrapped", indices, wrapper_class)


class BatchGroupsVecEnv(GroupedVecEnv):
    """:class:`rl.train.grouped_vec_env.GroupedVecEnv` over :class:`BatchGroup` workers holding
    consecutive envs: a step sends each worker its rows of the action array and takes back its
    arrays (:meth:`BatchGroup.step_batch`), then makes the per-env infos here; the results are
    those of the per-env calls (tested), at a fraction of the pipes' pickling."""

    def __init__(self, hosts, groups: list[list[int]]) -> None:
        flat = [i for g in groups for i in g]
        if flat != list(range(len(flat))) or any(
            g != list(range(g[0], g[0] + len(g))) for g in groups
        ):
            raise ValueError("BatchGroupsVecEnv: the groups must hold consecutive envs in order")
        super().__init__(hosts, groups)
        self._spans = [(g[0], g[0] + len(g)) for g in groups]

    def step_async(self, actions: np.ndarray) -> None:
        a = np.asarray(actions)
        self._pending = [
            self.hosts.submit(w, "step_batch", a[lo:hi]) for w, (lo, hi) in enumerate(self._spans)
        ]
        self.waiting = True

    def evaluate(self, job: EvalJob) -> list[dict[str, Any]]:
        """``job``'s episodes split in consecutive shares over the workers, run at once
        (:meth:`BatchGroup.evaluate_batch`); their rows in episode order."""
        spans = consecutive_spans(job.n_episodes, min(len(self.groups), job.n_episodes))
        handles = [
            self.hosts.submit(k, "evaluate_batch", job, lo, hi) for k, (lo, hi) in enumerate(spans)
        ]
        return [r for rows in self.hosts.gather(handles) for r in rows]

    def split_batch(self, env_cfg: EnvConfig, n_envs: int, seed: int) -> SplitBatch:
        """A batch of ``n_envs`` envs of ``env_cfg`` beside the training envs, split in
        consecutive shares over the same workers (:class:`SplitBatch`)."""
        return SplitBatch(self.hosts, min(len(self.groups), n_envs), env_cfg, n_envs, seed)

    def step_wait(self):
        parts = self.hosts.gather(self._pending)
        self.waiting = False
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return joined_steps(parts)


class SplitBatch:
    """``n_envs`` envs of one config as one batch (:class:`rl.env.batch_env.BatchDockingEnv`'s
    ``seed``, ``reset``, ``step``), held in consecutive shares by the training's batch workers
    (:meth:`rl.train.batch_workers.BatchGroup.side_open`) and stepped in all of them at once, so
    that a batch the trainer drives alone (the warm start's episodes, :mod:`rl.train.imitation`)
    uses every core. Env ``k`` is seeded with ``seed + k`` and draws from its own generators:
    the episodes are those of one batch of all the envs (tested).

    Args:
        hosts: the batch workers' hosts (:class:`Hosts`); workers: how many take a share.
        env_cfg: the envs' config; n_envs: how many; seed: env ``k`` first resets with
            ``seed + k``.
    """

    def __init__(self, hosts: Hosts, workers: int, env_cfg: EnvConfig, n_envs: int, seed: int):
        self.hosts = hosts
        self.num_envs = int(n_envs)
        self._spans = consecutive_spans(self.num_envs, workers)
        self._seed: int | None = None
        self._all("side_open", *[(env_cfg, lo, hi, int(seed)) for lo, hi in self._spans])

    def _all(self, method: str, *per_worker: tuple) -> list[Any]:
        handles = [self.hosts.submit(w, method, *args) for w, args in enumerate(per_worker)]
        return self.hosts.gather(handles)

    def seed(self, seed: int | None = None) -> None:
        """Seed the next reset (env ``k``: ``seed + k``) and each env's per-step noise."""
        self._seed = None if seed is None else int(seed)

    def reset(self) -> np.ndarray:
        seed, self._seed = self._seed, None
        return np.concatenate(self._all("side_reset", *[(seed,)] * len(self._spans)))

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
        """Step every env (auto-reset where done): observations, rewards, dones, infos."""
        a = np.asarray(actions)
        return joined_steps(self._all("side_step", *[(a[lo:hi],) for lo, hi in self._spans]))

    def close(self) -> None:
        self._all("side_close", *[()] * len(self._spans))
