"""The batched simulator split over worker processes, where the trainer expects its env workers:
:class:`BatchGroup` (a worker's share of the envs as one :class:`rl.env.batch_env.BatchDockingEnv`)
and :class:`BatchWorkers` (the groups behind :class:`rl.train.vec_envs.EnvWorkers`'s interface,
stepped by :class:`rl.train.grouped_vec_env.BatchGroupsVecEnv`).
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from uwdock.rl.env.config import EnvConfig
from uwdock.rl.evaluate.batched import batched_episodes
from uwdock.rl.train.vec_envs import EnvWorkers
from uwdock.rl.train.workers import EvalJob

if TYPE_CHECKING:
    from uwdock.rl.env.batch_env import BatchDockingEnv, StepColumns

__all__ = ["BatchGroup", "BatchWorkers"]


class BatchGroup:
    """A worker process's share of a batched training env: the envs of ``indices`` as one
    :class:`BatchDockingEnv`, behind :class:`rl.train.vec_envs.EnvGroup`'s interface (slots in, one
    result per env out) so that :class:`rl.train.vec_envs.PipeHosts` and
    :class:`rl.train.grouped_vec_env.GroupedVecEnv` carry it unchanged. Env ``i`` is seeded with
    ``seed + i`` and sits at slot ``i`` of the shared contact scene whatever group holds it, so
    the rollouts do not depend on the split, except for the shared scene's contact round-off
    (:mod:`uwdock.sim.contact_scene`; ``batch_contact = "own"`` has none)."""

    def __init__(self, indices: Sequence[int]) -> None:
        self.indices = [int(i) for i in indices]
        self.current = self.indices[0]
        self.venv: BatchDockingEnv | None = None
        self._eval: tuple[tuple, BatchDockingEnv] | None = None  # kept between evaluations
        self._side: tuple[int, BatchDockingEnv] | None = None  # a share of a SplitBatch

    def build(self, env_cfg: EnvConfig, seed: int) -> None:
        from uwdock.rl.env.batch_env import BatchDockingEnv  # SB3 at module level

        self.venv = BatchDockingEnv(
            env_cfg,
            len(self.indices),
            seed=seed + self.indices[0],
            privileged=True,
            slot_ids=self.indices,
        )

    def _batch(self) -> BatchDockingEnv:
        if self.venv is None:
            raise RuntimeError("BatchGroup: build() first")
        return self.venv

    def spaces(self) -> bytes:
        v = self._batch()
        return pickle.dumps((v.observation_space, v.action_space))

    def step(self, actions: Sequence[np.ndarray]) -> list[tuple[Any, float, bool, dict, dict]]:
        obs, rew, done, infos = self._batch().step(np.stack(actions))
        # rewards stay float32 scalars: stacked, the batch's float32 rewards, as in one process
        return [(obs[k], rew[k], bool(done[k]), infos[k], {}) for k in range(len(obs))]

    def step_batch(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, StepColumns]:
        """One step of the group's envs as arrays (:meth:`BatchDockingEnv.step_columns`): what
        :class:`BatchGroupsVecEnv` asks for, a few arrays to pickle instead of a dict per env."""
        v = self._batch()
        v.step_async(actions)
        return v.step_columns()

    def reset(self, seeds: Sequence[int | None], options: Sequence[dict | None]) -> list:
        v = self._batch()
        if seeds and seeds[0] is not None:
            v.seed(int(seeds[0]))  # the learner's seeds are consecutive: seed + index
        obs = v.reset()
        return [(obs[k], {}) for k in range(len(obs))]

    def evaluate_batch(self, job: EvalJob, lo: int, hi: int) -> list[dict[str, Any]]:
        """Episodes ``lo .. hi - 1`` of ``job`` (:func:`batched_episodes`' rows) in a batch of
        this worker's, built at the first evaluation and kept for the next ones (building one
        costs about a quarter of an evaluation)."""
        key = (job.env_cfg, lo, hi)
        if self._eval is None or self._eval[0] != key:
            if self._eval is not None:
                self._eval[1].close()
            self._eval = (key, _share(job.env_cfg, lo, hi, job.seed))
        model, vecnorm = job.policy()
        return batched_episodes(
            model, job.env_cfg, hi - lo, job.seed, vecnorm, first=lo, venv=self._eval[1]
        )

    # ------------------------------------------------------------------ a share of a SplitBatch
    def side_open(self, env_cfg: EnvConfig, lo: int, hi: int, seed: int) -> None:
        """Hold envs ``lo .. hi - 1`` of a batch of ``env_cfg`` beside the training envs
        (:class:`rl.train.grouped_vec_env.SplitBatch`): env ``k`` seeded with ``seed + k`` and
        at slot ``k``, as in one batch of them all."""
        self.side_close()
        self._side = (lo, _share(env_cfg, lo, hi, seed))

    def _side_batch(self) -> tuple[int, BatchDockingEnv]:
        if self._side is None:
            raise RuntimeError("BatchGroup: side_open() first")
        return self._side

    def side_reset(self, seed: int | None) -> np.ndarray:
        """Reset the share (``seed``: the whole batch's, as :meth:`BatchDockingEnv.seed`); its
        first observations."""
        lo, v = self._side_batch()
        if seed is not None:
            v.seed(seed + lo)
        return v.reset()

    def side_step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, StepColumns]:
        """One step of the share with its rows of the actions (:meth:`step_batch`'s arrays)."""
        _, v = self._side_batch()
        v.step_async(actions)
        return v.step_columns()

    def side_close(self) -> None:
        if self._side is not None:
            self._side[1].close()
            self._side = None

    def env_method(self, slots: Sequence[int], name: str, args: tuple, kwargs: dict) -> list:
        return self._batch().env_method(name, *args, indices=list(slots), **kwargs)

    def get_attr(self, slots: Sequence[int], name: str) -> list:
        return self._batch().get_attr(name, list(slots))

    def has_attr(self, slots: Sequence[int], name: str) -> list[bool]:
        return [hasattr(self._batch().envs[s], name) for s in slots]

    def set_attr(self, slots: Sequence[int], name: str, value: Any) -> list[None]:
        self._batch().set_attr(name, value, list(slots))
        return [None] * len(slots)

    def is_wrapped(self, slots: Sequence[int], wrapper_class: type) -> list[bool]:
        return [False] * len(slots)

    def render(self, slots: Sequence[int]) -> list:
        return [None] * len(slots)

    def close(self) -> None:
        if self.venv is not None:
            self.venv.close()
        if self._eval is not None:
            self._eval[1].close()
        self.side_close()


def _share(env_cfg: EnvConfig, lo: int, hi: int, seed: int) -> BatchDockingEnv:
    """Envs ``lo .. hi - 1`` of a batch whose env ``k`` is seeded with ``seed + k`` and sits at
    slot ``k``: a worker's consecutive share of it, the same episodes as in one batch."""
    from uwdock.rl.env.batch_env import BatchDockingEnv  # SB3 at module level

    return BatchDockingEnv(env_cfg, hi - lo, seed=seed + lo, slot_ids=range(lo, hi))


class BatchWorkers:
    """The batched simulator where the trainer expects its env workers (:class:`rl.train.vec_envs.
    EnvWorkers`'s interface): with one worker, one :class:`BatchDockingEnv` in this process;
    with more, the envs split into that many consecutive groups, each a batch
    (:class:`BatchGroup`), to use more cores: the first in this process and the others in
    worker processes (``first_here``, :class:`rl.train.vec_envs.HereAndPipeHosts`), or each in a
    worker process of its own. The rollouts are the same for a given split, wherever its
    groups run (tested); another split rounds the shared contact scene's contacts off
    differently (:mod:`uwdock.sim.contact_scene`).

    On the 2-core development machine the first group in the trainer's process stepped 64
    envs 11-23 % faster than two worker processes beside a waiting trainer (3,650-4,050
    against 3,280-3,520 env steps/s, random actions): two processes on two cores, one pipe
    round trip a step instead of two.

    Args:
        env_cfg: the training env.
        n_envs: envs in all.
        seed: env ``i`` first resets with ``seed + i``.
        workers: processes to step the envs in (1: this one).
        first_here: with ``workers > 1``, step the first group in this process.
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        n_envs: int,
        seed: int,
        workers: int = 1,
        first_here: bool = True,
    ) -> None:
        from uwdock.rl.env.batch_env import BatchDockingEnv  # SB3 at module level
        from uwdock.rl.train.grouped_vec_env import BatchGroupsVecEnv  # SB3 at module level

        self._pool = None
        if workers <= 1:
            self.venv: Any = BatchDockingEnv(env_cfg, n_envs, seed=seed, privileged=True)
            return
        per = -(-n_envs // min(workers, n_envs))  # ceil
        # an evaluation in a worker builds the policy, whose optimizer imports torch's compiler
        # stack at its first construction (1.4-2 s, once) while the trainer waits for the
        # worker's share; the trainer's model builds one anyway, so build one before the workers
        # fork off and they inherit the import
        import torch

        torch.optim.Adam([torch.zeros(1, requires_grad=True)])

        self._pool = EnvWorkers(
            env_cfg, n_envs, seed, per, group_cls=BatchGroup, venv_cls=BatchGroupsVecEnv,
            first_here=first_here,
        )  # fmt: skip
        self.venv = self._pool.venv

    def worker_errors(self) -> list[str]:
        return self._pool.worker_errors() if self._pool is not None else []

    def raise_worker_error(self, exc: BaseException) -> None:
        if self._pool is not None:
            self._pool.raise_worker_error(exc)
        raise exc

    def close(self, force: bool = False) -> None:
        if self._pool is not None:
            self._pool.close(force)
        else:
            self.venv.close()
