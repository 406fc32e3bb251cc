"""The training envs as Ray actors behind SB3's ``VecEnv`` interface (``rl train --backend ray``).

Each env is a Ray actor (:class:`_EnvHost`) holding one docking env, built exactly as the local
workers build theirs (:func:`rl.workers._make_env_fn`: ``Monitor(DockingEnv)``, reset with
``seed + i``) and answering the commands of SB3's ``SubprocVecEnv`` worker with the same
semantics (auto-reset with ``terminal_observation``, ``TimeLimit.truncated``, seeds and options
used once). The PPO learner, the checkpoints and the resume logic do not know the difference;
the rollouts are the local ones, step for step. The periodic evaluation's share
(``env_method("evaluate_share", job)``) runs on the actors too.

The actors may sit on other machines of a Ray cluster (``--ray-address``); they only exchange
actions, observations and rewards with the learner. An actor that fails (an env error, a lost
node) stops training with one line; ``rl train --resume`` goes on from the newest checkpoint.
"""

from __future__ import annotations

import functools
import pickle
from collections.abc import Sequence
from typing import Any

import numpy as np

from uwdock.dockcore.pool import actor_cpus, import_ray, start_ray
from uwdock.rl.config import EnvConfig
from uwdock.rl.workers import WorkerError, _make_env_fn, _reason

__all__ = ["RayEnvWorkers", "RayVecEnv"]


class _EnvHost:
    """One training env in a Ray actor."""

    def __init__(self, env_cfg: EnvConfig, seed: int, index: int) -> None:
        import torch  # one thread per actor: the actors are the parallelism

        torch.set_num_threads(1)
        self.index = index
        self.env = _make_env_fn(env_cfg, seed, index, None, None)()

    def spaces(self) -> bytes:
        # pickled here and unpickled by the learner: Ray's own transport hands arrays back
        # read-only, which would pickle (into the checkpoints) differently from a local run's
        return pickle.dumps((self.env.observation_space, self.env.action_space))

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, dict, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        done = terminated or truncated
        info["TimeLimit.truncated"] = truncated and not terminated
        reset_info: dict = {}
        if done:
            info["terminal_observation"] = obs
            obs, reset_info = self.env.reset()
        return obs, reward, done, info, reset_info

    def reset(self, seed: int | None, options: dict | None) -> tuple[Any, dict]:
        return self.env.reset(seed=seed, **({"options": options} if options else {}))

    def env_method(self, name: str, args: tuple, kwargs: dict) -> Any:
        if name == "evaluate_share":  # the worker's share of the periodic evaluation
            return args[0].rows(self.index)
        return self.env.get_wrapper_attr(name)(*args, **kwargs)

    def get_attr(self, name: str) -> Any:
        return self.env.get_wrapper_attr(name)

    def has_attr(self, name: str) -> bool:
        try:
            self.env.get_wrapper_attr(name)
        except AttributeError:
            return False
        return True

    def set_attr(self, name: str, value: Any) -> None:
        setattr(self.env, name, value)

    def is_wrapped(self, wrapper_class: type) -> bool:
        from stable_baselines3.common.env_util import is_wrapped

        return is_wrapped(self.env, wrapper_class)

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


@functools.cache
def _ray_vec_env_class() -> type:
    """:class:`RayVecEnv`'s class, made on first use (SB3 is imported only then)."""
    from stable_baselines3.common.vec_env import VecEnv
    from stable_baselines3.common.vec_env.subproc_vec_env import _stack_obs

    class RayVecEnv(VecEnv):
        """``n_envs`` docking envs as Ray actors (see the module docstring).

        Args:
            env_cfg: the training env.
            n_envs: number of envs (actors).
            seed: env i is reset first with ``seed + i``.
        """

        def __init__(self, env_cfg: EnvConfig, n_envs: int, seed: int) -> None:
            import ray

            self._ray = ray
            host = ray.remote(num_cpus=actor_cpus(ray, n_envs))(_EnvHost)
            self.actors = [host.remote(env_cfg, seed + i, i) for i in range(n_envs)]
            self.waiting = False
            self.closed = False
            self._pending: list[Any] = []
            obs_space, act_space = pickle.loads(self._get([self.actors[0].spaces.remote()])[0])
            super().__init__(n_envs, obs_space, act_space)

        def _get(self, refs: Sequence[Any]) -> list[Any]:
            """Results of actor calls; a failure is a one-line :class:`WorkerError`."""
            ray = self._ray
            try:
                return ray.get(list(refs))
            except ray.exceptions.RayTaskError as exc:
                cause = getattr(exc, "cause", None)
                why = _reason(cause) if isinstance(cause, BaseException) else _reason(exc)
                raise WorkerError(f"environment worker failed: {why}") from None
            except ray.exceptions.RayActorError as exc:
                what = " ".join(str(exc).split()[:12])
                raise WorkerError(
                    f"environment worker failed: a Ray actor was lost ({what} ...); "
                    "`rl train --resume` goes on from the newest checkpoint"
                ) from None

        def step_async(self, actions: np.ndarray) -> None:
            self._pending = [
                a.step.remote(act) for a, act in zip(self.actors, actions, strict=True)
            ]
            self.waiting = True

        def step_wait(self):
            results = self._get(self._pending)
            self.waiting = False
            obs, rews, dones, infos, self.reset_infos = zip(*results, strict=True)
            return _stack_obs(obs, self.observation_space), np.stack(rews), np.stack(dones), infos

        def reset(self):
            refs = [
                a.reset.remote(self._seeds[i], self._options[i]) for i, a in enumerate(self.actors)
            ]
            results = self._get(refs)
            obs, self.reset_infos = zip(*results, strict=True)
            self._reset_seeds()
            self._reset_options()
            return _stack_obs(obs, self.observation_space)

        def close(self) -> None:
            if self.closed:
                return
            try:
                if self.waiting:
                    self._ray.get(self._pending)
                self._ray.get([a.close.remote() for a in self.actors])
            except Exception:  # an actor already gone: nothing to flush
                pass
            for a in self.actors:
                self._ray.kill(a, no_restart=True)
            self.closed = True

        def get_images(self) -> Sequence[np.ndarray | None]:
            return self._get([a.render.remote() for a in self.actors])

        def has_attr(self, attr_name: str) -> bool:
            return all(self._get([a.has_attr.remote(attr_name) for a in self.actors]))

        def get_attr(self, attr_name: str, indices=None) -> list[Any]:
            return self._get(
                [self.actors[i].get_attr.remote(attr_name) for i in self._get_indices(indices)]
            )

        def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
            self._get(
                [
                    self.actors[i].set_attr.remote(attr_name, value)
                    for i in self._get_indices(indices)
                ]
            )

        def env_method(
            self, method_name: str, *method_args, indices=None, **method_kwargs
        ) -> list[Any]:
            return self._get(
                [
                    self.actors[i].env_method.remote(method_name, method_args, method_kwargs)
                    for i in self._get_indices(indices)
                ]
            )

        def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
            return self._get(
                [
                    self.actors[i].is_wrapped.remote(wrapper_class)
                    for i in self._get_indices(indices)
                ]
            )

    return RayVecEnv


def RayVecEnv(env_cfg: EnvConfig, n_envs: int, seed: int) -> Any:
    """``n_envs`` docking envs as Ray actors behind SB3's ``VecEnv`` (see the module
    docstring); env i is reset first with ``seed + i``."""
    return _ray_vec_env_class()(env_cfg, n_envs, seed)


class RayEnvWorkers:
    """:class:`rl.workers.EnvWorkers`' interface over a :class:`RayVecEnv` (a local Ray instance
    with ``n_envs`` CPUs, or the cluster at ``ray_address``)."""

    def __init__(
        self, env_cfg: EnvConfig, n_envs: int, seed: int, ray_address: str | None = None
    ) -> None:
        start_ray(import_ray(), n_envs, ray_address)
        self.venv = RayVecEnv(env_cfg, n_envs, seed)

    def worker_errors(self) -> list[str]:
        return []

    def raise_worker_error(self, exc: BaseException) -> None:
        self.close(force=True)
        raise WorkerError(f"environment worker failed: {_reason(exc)}") from None

    def close(self, force: bool = False) -> None:
        venv = getattr(self, "venv", None)
        if venv is not None:
            venv.close()
