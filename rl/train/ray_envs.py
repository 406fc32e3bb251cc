"""The training envs as Ray actors behind SB3's ``VecEnv`` interface (``rl train --backend ray``).

Each actor (:class:`_RayGroup`) holds a group of envs (:class:`rl.train.vec_envs.EnvGroup`: one by
default, ``K`` with ``--envs-per-worker K``), built exactly as the local workers build theirs
and answering SB3's worker commands with ``SubprocVecEnv``'s semantics; the learner reaches
them through :class:`rl.train.grouped_vec_env.GroupedVecEnv`, the same vectorised env as the local
groups. The PPO learner, the checkpoints and the resume logic do not know the difference: the
rollouts are the local ones, step for step. The periodic evaluation's share
(``env_method("evaluate_share", job)``) runs on the actors too.

The actors may sit on other machines of a Ray cluster (``--ray-address``): the env's input files
(error model, camera, marker set and meshes, water file) travel to them as content, so no node
needs the driver's paths; they only exchange actions, observations and rewards with the
learner, one round trip per group and step (so ``K`` envs per actor cut the round trips
``K``-fold). An actor that fails (an env error, a lost
node) stops training with one line; ``rl train --resume`` goes on from the newest checkpoint.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from uwdock.dockcore.pool import (
    actor_cpus,
    import_ray,
    input_mapping,
    kill_actors,
    materialize_inputs,
    read_inputs,
    relocate,
    start_ray,
)
from uwdock.rl.env.config import EnvConfig, absolute_inputs, env_input_files
from uwdock.rl.train.vec_envs import EnvGroup, env_groups
from uwdock.rl.train.workers import WorkerError, failure_reason

__all__ = ["RayEnvWorkers", "RayHosts", "RayVecEnv"]


class _RayGroup(EnvGroup):
    """A group of training envs in a Ray actor. The env's input files come as content
    (``files``: absolute path -> bytes, through the object store), written on this node
    (:func:`dockcore.pool.materialize_inputs`); the env config, and the evaluation jobs' (which
    may name them as the driver's config did, ``aliases``: that name -> absolute path), are
    pointed at the copies, so no node needs the driver's paths."""

    def __init__(
        self,
        env_cfg: EnvConfig,
        seed: int,
        indices: Sequence[int],
        files: dict[str, bytes] | None = None,
        aliases: dict[str, str] | None = None,
    ) -> None:
        import torch  # one thread per actor: the actors are the parallelism

        torch.set_num_threads(1)
        super().__init__(indices)
        self._mapping: dict[str, str] = {}
        if files:
            copies = input_mapping(files, materialize_inputs(files))
            named = {a: copies[b] for a, b in (aliases or {}).items() if b in copies}
            self._mapping = {**named, **copies}
            env_cfg = relocate(env_cfg, self._mapping)
        self.build(env_cfg, seed)

    def env_method(self, slots: Sequence[int], name: str, args: tuple, kwargs: dict) -> list:
        if name == "evaluate_share" and self._mapping:
            args = (relocate(args[0], self._mapping), *args[1:])
        return super().env_method(slots, name, args, kwargs)


class RayHosts:
    """The env groups as Ray actors (:class:`rl.train.grouped_vec_env.Hosts`); a failure is a
    one-line :class:`WorkerError`.

    Args:
        env_cfg: the training env.
        seed: env ``i`` is first reset with ``seed + i``.
        groups: the env indices of each actor (:func:`rl.train.vec_envs.env_groups`).
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        seed: int,
        groups: list[list[int]],
        files: Any = None,
        aliases: dict[str, str] | None = None,
    ) -> None:
        import ray

        self._ray = ray
        actor = ray.remote(num_cpus=actor_cpus(ray, len(groups)))(_RayGroup)
        self.actors = [actor.remote(env_cfg, seed, g, files, aliases) for g in groups]

    def submit(self, worker: int, method: str, *args: Any) -> Any:
        return getattr(self.actors[worker], method).remote(*args)

    def gather(self, handles: Sequence[Any]) -> list[Any]:
        ray = self._ray
        try:
            return ray.get(list(handles))
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            why = failure_reason(cause) if isinstance(cause, BaseException) else failure_reason(exc)
            raise WorkerError(f"environment worker failed: {why}") from None
        except ray.exceptions.RayActorError as exc:
            what = " ".join(str(exc).split()[:12])
            raise WorkerError(
                f"environment worker failed: a Ray actor was lost ({what} ...); "
                "`rl train --resume` goes on from the newest checkpoint"
            ) from None

    def shutdown(self) -> None:
        kill_actors(self._ray, self.actors)


def RayVecEnv(
    env_cfg: EnvConfig,
    n_envs: int,
    seed: int,
    envs_per_worker: int = 1,
    files: Any = None,
    aliases: dict[str, str] | None = None,
) -> Any:
    """``n_envs`` docking envs in Ray actors (``envs_per_worker`` each) behind SB3's ``VecEnv``
    (see the module docstring); env i is reset first with ``seed + i``; ``files`` and
    ``aliases`` as for :class:`_RayGroup` (``files`` an object-store reference)."""
    from uwdock.rl.train.grouped_vec_env import GroupedVecEnv  # SB3 at module level

    groups = env_groups(n_envs, envs_per_worker)
    return GroupedVecEnv(RayHosts(env_cfg, seed, groups, files, aliases), groups)


class RayEnvWorkers:
    """:class:`rl.train.vec_envs.EnvWorkers`' interface over a :class:`RayVecEnv` (a local Ray
    instance with a CPU per actor, or the cluster at ``ray_address``)."""

    def __init__(
        self,
        env_cfg: EnvConfig,
        n_envs: int,
        seed: int,
        ray_address: str | None = None,
        envs_per_worker: int = 1,
    ) -> None:
        ray = import_ray(ray_address)
        start_ray(ray, len(env_groups(n_envs, envs_per_worker)), ray_address)
        # the actors may start in another folder or on another node: the env's input files
        # travel to them as content, once through the object store
        given = env_input_files(env_cfg)
        env_cfg, inputs = absolute_inputs(env_cfg)
        absolute = env_input_files(env_cfg)
        aliases = {given[k]: absolute[k] for k in given if given[k] != absolute[k]}
        files = ray.put(read_inputs(inputs)) if inputs else None
        self.venv = RayVecEnv(env_cfg, n_envs, seed, envs_per_worker, files, aliases)

    def worker_errors(self) -> list[str]:
        return []

    def raise_worker_error(self, exc: BaseException) -> None:
        self.close(force=True)
        raise WorkerError(f"environment worker failed: {failure_reason(exc)}") from None

    def close(self, force: bool = False) -> None:
        venv = getattr(self, "venv", None)
        if venv is not None:
            venv.close()
