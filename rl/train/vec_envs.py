"""The learner's vectorised training env over local worker processes, one env or several each.

:class:`EnvWorkers` holds ``n_envs`` docking envs: in this process for one env (SB3's
``DummyVecEnv``), else in worker processes (:mod:`rl.train.workers`: failures as one line, no
orphans, the periodic evaluation's shares), one env each (SB3's ``SubprocVecEnv``) or, with
``envs_per_worker = K``, ``K`` each (:class:`rl.train.grouped_vec_env.GroupedVecEnv` over
:class:`PipeHosts`).

Several envs per worker (``rl train --envs-per-worker K``): with one env per worker, every
worker process loads torch, SAPIEN and OpenCV and opens its own render device (on a GPU each
holds its own Vulkan and CUDA context; on a cluster each costs a process's memory; on Ray every
env step is a round trip to one actor). A worker here holds an :class:`EnvGroup` of ``K`` envs
that share the process: its SAPIEN renderer (one render device per process; each env keeps its
own scene), its torch and its imports. A step sends a group all its envs' actions at once and
gets their results back in one message.

Every env is built exactly as the one-env workers build theirs
(:func:`rl.train.workers.make_env_fn`: ``Monitor(DockingEnv)``, first reset with ``seed + i``) and
answers SB3's worker commands with ``SubprocVecEnv``'s semantics (auto-reset with
``terminal_observation``, ``TimeLimit.truncated``, seeds and options used once). The envs share no
random state, so the rollouts, checkpoints and evaluations do not depend on ``K`` or on the backend
(tests). The Ray backend (:mod:`rl.train.ray_envs`) puts the same groups in Ray actors.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import pickle
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from uwdock.dockcore.domains import Interval
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.train.workers import (
    WorkerError,
    error_path,
    failure_reason,
    make_env_fn,
    report_and_exit,
    setup_worker_process,
)

__all__ = [
    "EnvGroup",
    "EnvWorkers",
    "EnvsPerWorker",
    "HereAndPipeHosts",
    "PipeHosts",
    "env_groups",
]

#: The domain of ``envs_per_worker`` (``rl train --envs-per-worker``).
EnvsPerWorker = Annotated[int, Interval(ge=1, le=256)]


def env_groups(n_envs: int, envs_per_worker: int) -> list[list[int]]:
    """The env indices each worker holds: consecutive runs of ``envs_per_worker`` (the last
    one shorter when it does not divide ``n_envs``)."""
    k = max(1, min(int(envs_per_worker), int(n_envs)))
    return [list(range(s, min(s + k, n_envs))) for s in range(0, n_envs, k)]


class EnvGroup:
    """The envs of one worker (see the module docstring); its methods take the envs' *slots*
    (their positions in the group) and return one result per env.

    Args:
        indices: the envs' indices in the whole vectorised env.

    Attributes:
        current: the index of the env being called (a failure names it).
    """

    def __init__(self, indices: Sequence[int]) -> None:
        self.indices = [int(i) for i in indices]
        self.current = self.indices[0]
        self.envs: list[Any] = []

    def build(self, env_cfg: EnvConfig, seed: int) -> None:
        """Build the envs (env ``i`` first reset with ``seed + i``)."""
        for i in self.indices:
            self.current = i
            self.envs.append(make_env_fn(env_cfg, seed + i, i, None, None)())

    def _env(self, slot: int) -> Any:
        self.current = self.indices[slot]
        return self.envs[slot]

    def spaces(self) -> bytes:
        # pickled here and unpickled by the learner: the same bytes whatever the transport
        # (Ray's hands arrays back read-only, which would pickle into checkpoints differently)
        env = self._env(0)
        return pickle.dumps((env.observation_space, env.action_space))

    def step(self, actions: Sequence[np.ndarray]) -> list[tuple[Any, float, bool, dict, dict]]:
        out = []
        for slot, action in enumerate(actions):
            env = self._env(slot)
            obs, reward, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            reset_info: dict = {}
            if done:
                info["terminal_observation"] = obs
                obs, reset_info = env.reset()
            out.append((obs, reward, done, info, reset_info))
        return out

    def reset(self, seeds: Sequence[int | None], options: Sequence[dict | None]) -> list:
        out = []
        for slot, (seed, opts) in enumerate(zip(seeds, options, strict=True)):
            env = self._env(slot)
            out.append(env.reset(seed=seed, **({"options": opts} if opts else {})))
        return out

    def env_method(self, slots: Sequence[int], name: str, args: tuple, kwargs: dict) -> list:
        out = []
        for slot in slots:
            env = self._env(slot)
            if name == "evaluate_share":  # this env's share of the periodic evaluation
                out.append(args[0].rows(self.indices[slot]))
            else:
                out.append(env.get_wrapper_attr(name)(*args, **kwargs))
        return out

    def get_attr(self, slots: Sequence[int], name: str) -> list:
        return [self._env(s).get_wrapper_attr(name) for s in slots]

    def has_attr(self, slots: Sequence[int], name: str) -> list[bool]:
        out = []
        for s in slots:
            try:
                self._env(s).get_wrapper_attr(name)
            except AttributeError:
                out.append(False)
            else:
                out.append(True)
        return out

    def set_attr(self, slots: Sequence[int], name: str, value: Any) -> list[None]:
        for s in slots:
            setattr(self._env(s), name, value)
        return [None] * len(slots)

    def is_wrapped(self, slots: Sequence[int], wrapper_class: type) -> list[bool]:
        from stable_baselines3.common.env_util import is_wrapped

        return [is_wrapped(self._env(s), wrapper_class) for s in slots]

    def render(self, slots: Sequence[int]) -> list:
        return [self._env(s).render() for s in slots]

    def close(self) -> None:
        for slot in range(len(self.envs)):
            self._env(slot).close()


# ----------------------------------------------------------------------------- local processes


def _group_worker(
    conn: Any, parent_end: Any, env_cfg: EnvConfig, seed: int, indices: list[int],
    error_dir: str, parent: int, group_cls: type = EnvGroup,
) -> None:  # fmt: skip
    """A local worker process: build the group, then answer the learner's calls until
    ``close``. A failure writes ``env{i}.err`` (its one-line reason) and ends the process; the
    learner, finding the pipe closed, reads the reason (:class:`rl.train.workers.EnvWorkers`)."""
    parent_end.close()
    setup_worker_process(parent)
    group = group_cls(indices)
    try:
        group.build(env_cfg, seed)
        gc.freeze()  # the libraries and envs live as long as the worker (training.py: _run)
        while True:
            try:
                method, args = conn.recv()
            except EOFError:  # the learner is gone
                return
            if method == "close":
                group.close()
                conn.send(None)
                return
            conn.send(getattr(group, method)(*args))
    except Exception as exc:
        report_and_exit(error_path(error_dir, group.current), group.current, exc)


class PipeHosts:
    """The groups in forked local processes, one pipe each (the local backend with
    ``envs_per_worker > 1``).

    Args:
        env_cfg: the training env.
        seed: env ``i`` is first reset with ``seed + i``.
        groups: the env indices of each worker (:func:`env_groups`).
        error_dir: where a failing worker writes ``env{i}.err``.
        group_cls: what a worker holds: :class:`EnvGroup` (one docking env per index) or a
            class with its interface (:class:`rl.train.batch_workers.BatchGroup`: the indices' envs
            as one batch).

    Attributes:
        processes: the worker processes.
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        seed: int,
        groups: list[list[int]],
        error_dir: str,
        group_cls: type = EnvGroup,
    ) -> None:
        ctx = multiprocessing.get_context("fork" if os.name == "posix" else "spawn")
        self.conns: list[Any] = []
        self.processes: list[Any] = []
        parent = os.getpid()
        for indices in groups:
            here, there = ctx.Pipe()
            p = ctx.Process(
                target=_group_worker,
                args=(there, here, env_cfg, seed, indices, error_dir, parent, group_cls),
                daemon=True,
            )
            p.start()
            there.close()
            self.conns.append(here)
            self.processes.append(p)

    def submit(self, worker: int, method: str, *args: Any) -> int:
        self.conns[worker].send((method, args))
        return worker

    def gather(self, handles: Sequence[int]) -> list[Any]:
        # a dead worker: EOFError / ConnectionError, which the trainer turns into its reason
        return [self.conns[w].recv() for w in handles]

    def shutdown(self) -> None:
        for c in self.conns:
            c.close()


class HereAndPipeHosts:
    """The first group in this process, the others in local worker processes
    (:class:`PipeHosts`): a batched simulator's groups on 2 cores run in 2 processes, not a
    trainer waiting beside 2 workers.

    A call to the first group waits until :meth:`gather`, so that the calls to the worker
    processes, submitted before it, run while this process runs its own share: a step sends
    the workers their actions, steps the first group here, then collects theirs. The groups
    are built as :class:`PipeHosts` builds them, so the rollouts are the same as with every
    group in a worker (tested). A failure of the first group raises here, as the batch of a
    single process does.

    Args:
        here: the first group, built (``group_cls(groups[0])`` and its ``build``).
        pipes: the other groups' workers; worker ``k`` of ``pipes`` is worker ``k + 1`` here.
    """

    def __init__(self, here: Any, pipes: PipeHosts) -> None:
        self._here = here
        self._pipes = pipes
        self.processes = pipes.processes
        self._calls: dict[int, tuple[str, tuple[Any, ...]]] = {}
        self._next = 0

    def submit(self, worker: int, method: str, *args: Any) -> Any:
        if worker > 0:
            return ("pipe", self._pipes.submit(worker - 1, method, *args))
        self._next += 1
        self._calls[self._next] = (method, args)
        return ("here", self._next)

    def gather(self, handles: Sequence[Any]) -> list[Any]:
        out = []
        for where, h in handles:
            if where == "pipe":
                out.extend(self._pipes.gather([h]))
                continue
            method, args = self._calls.pop(h)
            out.append(getattr(self._here, method)(*args))
        return out

    def shutdown(self) -> None:
        self._calls.clear()
        self._pipes.shutdown()


# ----------------------------------------------------------------------------- the trainer's handle


class EnvWorkers:
    """The vectorised training env and the files its workers report failures in.

    Args:
        env_cfg: the training env.
        n_envs: number of envs.
        seed: env ``i`` is first reset with ``seed + i``.
        envs_per_worker: envs each worker process holds (module docstring).
        group_cls: what each worker holds (:class:`PipeHosts`); not :class:`EnvGroup` means
            worker processes even for one env per worker.
        venv_cls: the VecEnv over the workers' groups (default
            :class:`rl.train.grouped_vec_env.GroupedVecEnv`;
            :class:`rl.train.grouped_vec_env.BatchGroupsVecEnv` for batched groups).
        first_here: hold the first group in this process (:class:`HereAndPipeHosts`), the
            others in worker processes.

    Attributes:
        venv: the SB3 VecEnv (``DummyVecEnv`` for one env, ``SubprocVecEnv`` for one env per
            worker, else :class:`rl.train.grouped_vec_env.GroupedVecEnv`).
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        n_envs: int,
        seed: int,
        envs_per_worker: int = 1,
        group_cls: type = EnvGroup,
        venv_cls: type | None = None,
        first_here: bool = False,
    ) -> None:
        from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

        from uwdock.rl.train.grouped_vec_env import GroupedVecEnv  # SB3 at module level

        self._dir = None
        if n_envs == 1 and group_cls is EnvGroup:
            self.venv = DummyVecEnv([make_env_fn(env_cfg, seed, 0, None, None)])
            return
        self._dir = tempfile.TemporaryDirectory(prefix="uwdock-workers-")
        groups = env_groups(n_envs, envs_per_worker)
        if len(groups) < n_envs or group_cls is not EnvGroup:
            if first_here and len(groups) > 1:
                self._hosts = self._here_and_pipes(env_cfg, seed, groups, group_cls)
            else:
                self._hosts = PipeHosts(env_cfg, seed, groups, self._dir.name, group_cls)
            try:
                self.venv = (venv_cls or GroupedVecEnv)(self._hosts, groups)
            except (EOFError, ConnectionError) as exc:
                self.raise_worker_error(exc)
            return
        parent = os.getpid()
        fns = [
            make_env_fn(env_cfg, seed + i, i, error_path(self._dir.name, i), parent)
            for i in range(n_envs)
        ]
        before = set(multiprocessing.active_children())
        try:
            self.venv = SubprocVecEnv(fns, start_method="fork" if os.name == "posix" else "spawn")
        except (EOFError, ConnectionError) as exc:
            # the half-built VecEnv is gone: find its workers among this process's children
            self._orphans = [p for p in multiprocessing.active_children() if p not in before]
            self.raise_worker_error(exc)

    def _here_and_pipes(
        self, env_cfg: EnvConfig, seed: int, groups: list[list[int]], group_cls: type
    ) -> HereAndPipeHosts:
        """Workers for ``groups[1:]``, then ``groups[0]`` built here (its failure stops them)."""
        pipes = PipeHosts(env_cfg, seed, groups[1:], self._dir.name, group_cls)
        here = group_cls(groups[0])
        try:
            here.build(env_cfg, seed)
        except BaseException:
            pipes.shutdown()
            raise
        return HereAndPipeHosts(here, pipes)

    def _processes(self) -> list:
        venv = getattr(self, "venv", None)
        hosts = getattr(self, "_hosts", None)
        procs = hosts.processes if hosts is not None else getattr(venv, "processes", None)
        return list(procs or []) + list(getattr(self, "_orphans", []))

    def worker_errors(self) -> list[str]:
        """The reasons written by failed workers so far."""
        if self._dir is None:
            return []
        out = []
        for p in sorted(Path(self._dir.name).glob("env*.err")):
            text = p.read_text(encoding="utf-8", errors="replace").strip()
            if text:
                out.append(text)
        return out

    def raise_worker_error(self, exc: BaseException) -> None:
        """Raise a :class:`WorkerError` with the workers' reasons (``exc``: what the parent
        saw, used when no worker left a reason)."""
        deadline = time.monotonic() + 3.0  # let the other failing workers write their reason
        for p in self._processes():
            p.join(timeout=max(0.0, deadline - time.monotonic()))
        reasons = self.worker_errors()
        self.close(force=True)
        what = "; ".join(reasons) if reasons else f"a worker process died ({failure_reason(exc)})"
        raise WorkerError(f"environment worker failed: {what}") from None

    def close(self, force: bool = False) -> None:
        """Close the envs; with ``force`` (or if they do not answer), terminate the workers."""
        venv = getattr(self, "venv", None)
        procs = self._processes()
        if venv is not None and not force:
            try:
                venv.close()
            except Exception:
                force = True
        for p in procs:  # workers hold nothing worth flushing: SIGKILL the ones still there
            if not force:
                p.join(timeout=2.0)
            if p.is_alive():
                p.kill()
                p.join(timeout=2.0)
        if self._dir is not None:
            self._dir.cleanup()
            self._dir = None
