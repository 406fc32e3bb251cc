"""What runs in a training env worker: the env, built once, and the report of its failure.

The learner's side (the vectorised env over the workers) is :mod:`rl.train.vec_envs` (local
processes) and :mod:`rl.train.ray_envs` (Ray actors). What a worker adds to SB3's own:

* **one line for a worker's failure**: an env that cannot be built (a typo in a file name, a
  damaged error model) or fails during a step (a simulator blow-up) writes its one-line reason
  to a file the parent reads, and the parent raises a :class:`DockError` with it (instead of
  the worker's traceback and ``Connection reset by peer``);
* **no orphans**: workers die with the parent, whatever killed it
  (:func:`dockcore.procs.die_with_parent`), ignore SIGINT (the parent decides), and are
  terminated if they do not close in time;
* **the periodic evaluation on the workers**: ``evaluate_share`` runs a share of the evaluation
  episodes in each worker (on an evaluation env of its own, never the training env), so the
  evaluation takes the cores the rollouts use instead of one core while the workers wait. Every
  episode has a fixed seed and a fresh PhysX system, so the rows equal one process's.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.procs import die_with_parent
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.evaluate.episodes import SB3Controller, run_episodes
from uwdock.rl.policy.policy_format import policy_from_files
from uwdock.rl.train.checkpoint import global_rng_kept


class WorkerError(DockError):
    """An environment worker process failed (its one-line reason)."""


def failure_reason(exc: BaseException) -> str:
    """``exc`` as one line: its message for a :class:`DockError` (already written for the user),
    else ``<ExceptionType>: <message>``; whitespace collapsed."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, DockError) else f"{type(exc).__name__}: {text}"


def report_and_exit(error_file: str, index: int, exc: BaseException) -> None:
    """End this worker process (exit status 3, no clean-up: the parent decides) after writing
    ``env <index>: <reason>`` to ``error_file`` (:func:`error_path`), where the parent reads it."""
    try:
        Path(error_file).write_text(f"env {index}: {failure_reason(exc)}\n", encoding="utf-8")
    finally:
        os._exit(3)


class GuardedEnv(gym.Wrapper):
    """A worker's env: an exception in ``reset``, ``step`` or ``evaluate_share`` ends the worker
    process with its reason written down (:func:`report_and_exit`).

    Args:
        env: the env (``Monitor(DockingEnv)``).
        error_file: where the reason goes (:func:`error_path`).
        index: the env's index in the vectorised env (the reason names it).
    """

    def __init__(self, env: gym.Env, error_file: str, index: int) -> None:
        super().__init__(env)
        self._error_file = error_file
        self._index = index

    def reset(self, **kwargs):
        try:
            return self.env.reset(**kwargs)
        except Exception as exc:
            report_and_exit(self._error_file, self._index, exc)

    def step(self, action):
        try:
            return self.env.step(action)
        except Exception as exc:
            report_and_exit(self._error_file, self._index, exc)

    def evaluate_share(self, job: EvalJob) -> list[dict]:
        """This worker's share of ``job``'s episodes (their rows)."""
        try:
            return job.rows(self._index)
        except Exception as exc:
            report_and_exit(self._error_file, self._index, exc)


@dataclass(frozen=True)
class EvalJob:
    """Evaluation episodes of a policy snapshot, split between the env workers.

    Attributes:
        policy_files: the snapshot in the policy format
            (:func:`rl.policy.policy_format.policy_files`: ``model.json`` and ``weights.npz``,
            normalisation included).
        env_cfg: the evaluation env.
        n_episodes: episodes in all (episode k has seed ``seed + k``).
        seed: seed of episode 0.
        n_workers: how many workers share them (worker i runs i, i + n, ...).
    """

    policy_files: dict[str, bytes]
    env_cfg: EnvConfig
    n_episodes: int
    seed: int
    n_workers: int

    def policy(self) -> tuple:
        """The snapshot's policy and its observation normalisation (None without one); the
        process's global generators are left as they were (:func:`rl.train.checkpoint.
        global_rng_kept`: building the network draws its initial weights)."""
        with global_rng_kept():
            return policy_from_files(self.policy_files)

    def rows(self, index: int) -> list[dict]:
        """The rows of worker ``index``'s episodes."""
        model, vecnorm = self.policy()
        share = list(range(index, self.n_episodes, self.n_workers))
        res = run_episodes(
            SB3Controller(model, vecnorm), self.env_cfg, self.n_episodes, self.seed,
            record=False, episodes=share,
        )  # fmt: skip
        return res.episodes


def error_path(folder: str, index: int) -> str:
    """Where env ``index``'s worker writes its one-line reason (in the trainer's ``folder``)."""
    return str(Path(folder) / f"env{index}.err")


def setup_worker_process(parent: int) -> None:
    """What every env worker process does first: leave signals to the parent (which decides),
    die with it, and run torch on one thread."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    die_with_parent(parent)
    # one thread per worker, and never the thread pool the parent had when it forked: a forked
    # child that enters the inherited OpenMP pool waits on it forever (seen: both eval workers
    # stuck in torch's orthogonal_ while loading the policy, after the parent had run
    # multi-threaded torch ops)
    import torch

    torch.set_num_threads(1)


def make_env_fn(
    env_cfg: EnvConfig, seed: int, index: int, error_file: str | None, parent: int | None
) -> Callable[[], gym.Env]:
    """The function that builds env ``index`` of a training vectorised env (what SB3's
    ``DummyVecEnv`` / ``SubprocVecEnv`` and :class:`rl.train.vec_envs.EnvGroup` call):
    ``Monitor(DockingEnv(env_cfg, privileged=True))``, first reset with ``seed``.

    Args:
        env_cfg: the training env.
        seed: the first reset's seed.
        index: the env's index in the vectorised env.
        error_file: in a worker process, where a failure's reason goes (the env is then a
            :class:`GuardedEnv`); None: failures raise.
        parent: in a worker process of its own, the parent's pid
            (:func:`setup_worker_process`); else None.
    """

    def make() -> gym.Env:
        if parent is not None:  # a worker process of its own
            setup_worker_process(parent)
        from stable_baselines3.common.monitor import Monitor

        try:
            env = Monitor(
                DockingEnv(env_cfg, privileged=True),  # the critic's state, when configured
                info_keywords=("success_paper", "success_strict"),
            )
            env.reset(seed=seed)
        except Exception as exc:
            if error_file is None:
                raise
            report_and_exit(error_file, index, exc)
        return env if error_file is None else GuardedEnv(env, error_file, index)

    return make
