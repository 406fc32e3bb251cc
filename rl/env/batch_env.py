"""A vectorised docking env that steps N envs as arrays in one process: SB3 uses it directly.

:class:`BatchDockingEnv` is a Stable-Baselines3 ``VecEnv`` of ``n_envs`` docking envs of one
:class:`~uwdock.rl.env.config.EnvConfig`. A control step of all of them is one batched physics call
(:class:`uwdock.sim.batch.BatchVehicles`: numba free flight with the tank's planes, PhysX only
for the vehicles at the docking station) and NumPy over the env axis for the rest
(:mod:`rl.env.batch_parts`: IMU, collision test, error-model or proxy measurement, DS filter,
success tests, reward, observation). Resets are rare and run the scalar
:class:`rl.env.docking_env.DockingEnv` of the slot (spawn, randomised vehicle, current, the filter's
prior, the USBL's biases), whose state the batch then takes over; the acoustic fixes are the slot's
own :class:`uwdock.sim.usbl.UsblSensor` (one call per env and step: it keeps the latency's pose
history).

What equals the scalar env and what does not:

* the physics: identical (the batch is the same kernels and the same PhysX bodies; tested);
* the maths of every step (errors, tests, filter, reward, observation): the scalar functions'
  on the same inputs (tested);
* the random draws: each env's reset draws from the env's own stream exactly as the scalar
  env (``seed + i``, then continuing); its per-step noise (IMU, error model, proxy) comes from a
  second generator of its own (seeded from ``seed + i`` too) in a fixed number of draws per
  step, so an episode is a different sample of the same distributions than the scalar env's,
  and the same whether the envs run in one batch or split over worker processes.

The camera source cannot be batched (one render per env and step): ``obs_source = "camera"``
is refused. Auto-reset, ``terminal_observation``, ``TimeLimit.truncated`` and Monitor's
``episode`` entry follow ``SubprocVecEnv`` + ``Monitor``, so the learner, ``VecNormalize`` and
the callbacks see what the per-env workers give them.

Split over worker processes, the batch is :mod:`rl.train.batch_workers`; evaluation episodes
on it are :func:`rl.evaluate.batched.batched_episodes`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from uwdock.rl.env.batch_parts import (
    BATCH_SOURCES,
    BatchErrorModel,
    BatchFilter,
    docking_errors_b,
    ds_visible_b,
    inv_T_b,
    observation_frames_b,
    pegs_seated_b,
    proxy_measure_b,
    reward_terms_b,
    yaw_b,
)
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv, SimulationError
from uwdock.rl.env.error_model import ErrorModelSource
from uwdock.rl.env.observation import (
    OBS_BOUND,
    POS_SCALE_M,
    PRIVILEGED_DIM,
    ContactMemory,
    frame_dim,
)
from uwdock.rl.env.task import paper_success_b
from uwdock.sim.batch import BatchVehicles
from uwdock.sim.navigation import NavErrors, correction

__all__ = ["BatchDockingEnv", "StepColumns", "info_rows"]


@dataclass
class StepColumns:
    """One batched step's infos as arrays over the env axis: what :func:`info_rows` turns into
    SB3's per-env info dicts.

    Attributes:
        terms: the reward terms, each (n,) (an info's ``reward_terms``).
        values: the other entries of every env's info, each (n, ...): a 1-D column gives a
            Python scalar per env, a wider one the env's row.
        ends: the entries only a done env's info has (``TimeLimit.truncated``,
            ``terminal_observation``, ``episode``), by env index.
    """

    terms: dict[str, np.ndarray]
    values: dict[str, np.ndarray]
    ends: dict[int, dict[str, Any]]

    @property
    def n(self) -> int:
        """How many envs."""
        return len(next(iter(self.values.values())))

    @staticmethod
    def concat(parts: Sequence[StepColumns]) -> StepColumns:
        """The columns of consecutive env groups as one (env indices offset in order)."""
        if len(parts) == 1:
            return parts[0]
        ends: dict[int, dict[str, Any]] = {}
        off = 0
        for p in parts:
            ends.update({off + i: e for i, e in p.ends.items()})
            off += p.n
        return StepColumns(
            {k: np.concatenate([p.terms[k] for p in parts]) for k in parts[0].terms},
            {k: np.concatenate([p.values[k] for p in parts]) for k in parts[0].values},
            ends,
        )


def info_rows(cols: StepColumns) -> list[dict[str, Any]]:
    """SB3's per-env info dicts of one step (:class:`StepColumns`), keys in a fixed order:
    ``reward_terms``, the columns, then a done env's ``ends``."""
    terms = {k: v.tolist() for k, v in cols.terms.items()}
    values = {k: v.tolist() if v.ndim == 1 else v for k, v in cols.values.items()}
    rows = []
    for i in range(cols.n):
        info: dict[str, Any] = {"reward_terms": {k: v[i] for k, v in terms.items()}}
        for k, v in values.items():
            info[k] = v[i]
        end = cols.ends.get(i)
        if end is not None:
            info.update(end)
        rows.append(info)
    return rows


class BatchDockingEnv(VecEnv):
    """``n_envs`` docking envs stepped as arrays (module docstring).

    Args:
        config: every env's config; ``obs_source`` one of :data:`BATCH_SOURCES`.
        n_envs: how many envs.
        seed: env ``i`` first resets with ``seed + i`` (as the per-env workers); the per-step
            noise generator is seeded from ``seed`` too.
        privileged: fill the observation's privileged block (training envs).
        slot_ids: each env's index in the whole training batch when this is a worker's share
            of it (where its vehicle sits in the shared contact scene, :mod:`uwdock.sim.
            contact_scene`, the same whichever worker holds it); default 0, 1, ...
    """

    def __init__(
        self,
        config: EnvConfig,
        n_envs: int,
        seed: int = 0,
        privileged: bool = False,
        slot_ids: Sequence[int] | None = None,
    ) -> None:
        if config.obs_source not in BATCH_SOURCES:
            raise ValueError(
                f"obs_source: '{config.obs_source}' cannot be batched (one render per env and "
                f"step); the batched simulator runs {', '.join(BATCH_SOURCES)}"
            )
        if not 1 <= int(n_envs) <= 4096:
            raise ValueError(f"n_envs: must be 1-4096, got {n_envs!r}")
        n = int(n_envs)
        self.cfg = config
        self.envs = [DockingEnv(config, privileged=privileged) for _ in range(n)]
        e0 = self.envs[0]
        super().__init__(n, e0.observation_space, e0.action_space)
        self.privileged = bool(privileged)
        self.seed_base = int(seed)
        self._gens = [self._noise(self.seed_base + i) for i in range(n)]
        self.dt_s = e0.dt_s
        self.max_steps = e0.max_steps
        self.limits = e0.action_limits
        self.physics = BatchVehicles(
            [e.world.vehicle for e in self.envs],
            contact=config.world.batch_contact,
            slot_ids=slot_ids,
        )
        if config.world.batch_contact != "own":  # the slots' own PhysX never steps
            for e in self.envs:
                e.world.fresh_physics = False
        est = e0.filter.cfg
        q = np.array(
            [est.drift_xyz_m_per_sqrt_s] * 3 + [math.radians(est.drift_yaw_deg_per_sqrt_s)]
        )
        self.filter = BatchFilter(n, est.fuse, est.gate_sigma, q**2)
        src = e0.source
        self.model = (
            BatchErrorModel(src.model, src.water, src.temporal, n)
            if isinstance(src, ErrorModelSource)
            else None
        )
        self.acoustic = e0.source.needs.acoustic_fixes
        self.nav = NavErrors(config.nav, n)
        self.T_nav = np.tile(np.eye(4), (n, 1, 1))
        self.frame_dim = frame_dim(config)
        self.contact = ContactMemory(n, self.dt_s)  # obs_contact's values
        self.frames = np.zeros((n, config.obs_frames, self.frame_dim), dtype=np.float32)
        self.T_world_ds = np.tile(np.eye(4), (n, 1, 1))
        self.steps = np.zeros(n, dtype=np.int64)
        self.prev_action = np.zeros((n, 6))
        self.prev_sf = np.zeros((n, 3))
        self.prev_e_xy = np.full(n, np.nan)  # r_stall's memory (NaN: no step since the reset)
        self.gamma = np.zeros(n)
        self.seated = np.zeros(n, dtype=np.int64)
        self.success_paper = np.zeros(n, dtype=bool)
        self.success_strict = np.zeros(n, dtype=bool)
        self.detected = np.zeros(n, dtype=bool)
        self.ep_return = np.zeros(n)
        self.ep_start = np.zeros(n)
        self._first_reset = [True] * n
        self._actions = np.zeros((n, 6))
        self._refresh_task()
        r = e0.reward_fn
        self._reward_cfg, self._weights, self._smooth = r.cfg, r.weights, r.smooth_mask

    @staticmethod
    def _noise(seed: int) -> np.random.Generator:
        """An env's per-step noise generator for its seed."""
        return np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xBA7C])

    def seed(self, seed: int | None = None):
        """Seed the next reset (env ``i``: ``seed + i``) and each env's per-step noise, so a
        run reset at a checkpoint boundary goes on exactly as it went before."""
        if seed is not None:
            self._gens = [self._noise(int(seed) + i) for i in range(self.num_envs)]
        return super().seed(seed)

    def _draws(self) -> tuple[np.ndarray, np.ndarray | None]:
        """This step's draws of every env from its own generator: (N, 16 + k) standard normals
        (IMU 10, the source's 6, then the navigation's k: 0 when ideal) and (N, 3) uniforms
        (the error model's)."""
        k = 16 + self.nav.step_draws
        normals = np.stack([g.standard_normal(k) for g in self._gens])
        uniforms = np.stack([g.random(3) for g in self._gens]) if self.model else None
        return normals, uniforms

    def _refresh_task(self) -> None:
        e0 = self.envs[0]
        self.task = e0.task
        self.hold_steps = e0.hold_steps

    # ------------------------------------------------------------------ slots
    def _reset_slot(self, i: int, seed: int | None = None) -> np.ndarray:
        """Reset env ``i`` with the scalar code and take its state over; its first obs."""
        env = self.envs[i]
        if seed is None and self._first_reset[i]:
            seed = self.seed_base + i
        self._first_reset[i] = False
        obs, _ = env.reset(seed=seed)
        self.physics.load(i)
        self.T_world_ds[i] = env.world.T_world_ds
        self.nav.copy_row(i, env.nav)
        self.T_nav[i] = env.T_nav
        self.filter.x[i], self.filter.P[i] = env.filter.x, env.filter.P
        if self.model is not None:
            self.model.reset(i)
        self.steps[i] = 0
        self.prev_action[i] = 0.0
        self.prev_e_xy[i] = np.nan
        self.contact.reset(i)
        self.prev_sf[i] = env.prev_specific_force
        self.gamma[i] = env.reward_fn.gamma_mps2
        self.seated[i] = 0
        self.success_paper[i] = self.success_strict[i] = False
        self.detected[i] = env.last_measurement is not None and env.last_measurement.detected
        self.frames[i] = obs[: self.frames.shape[1] * self.frame_dim].reshape(-1, self.frame_dim)
        self.ep_return[i] = 0.0
        self.ep_start[i] = time.time()
        return obs

    # ------------------------------------------------------------------ VecEnv API
    def reset(self) -> np.ndarray:
        seeds = list(self._seeds) if self._seeds else [None] * self.num_envs
        obs = np.stack([self._reset_slot(i, seeds[i]) for i in range(self.num_envs)])
        # every env starts afresh: so does the shared contact scene (a run resumed from a
        # checkpoint, whose envs are all reset, then steps as the run never stopped)
        self.physics.fresh_contact_scene()
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        a = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, -1)
        if a.shape[1] != 6 or not np.all(np.isfinite(a)):
            bad = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0]) if a.shape[1] == 6 else 0
            raise ValueError(f"actions: env {bad} must be 6 finite numbers, got {a[bad].tolist()}")
        self._actions = np.clip(a, -1.0, 1.0)

    def step_wait(self):
        obs, reward, dones, cols = self.step_columns()
        return obs, reward, dones, info_rows(cols)

    def step_columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, StepColumns]:
        """Step every env with the actions of :meth:`step_async`: observations (auto-reset
        where done), float32 rewards, dones, and the infos as columns (:class:`StepColumns`,
        :func:`info_rows` makes SB3's per-env dicts of them; a worker process sends these
        arrays rather than the dicts, whose pickling cost more than the step's physics)."""
        a = self._actions
        ph = self.physics
        ph.step(a * self.limits, self.dt_s)
        self.steps += 1
        T = ph.T_world_body()
        bad = ~np.isfinite(T).all(axis=(1, 2)) | (np.abs(T[:, :3, 3]).max(axis=1) > 1e3)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SimulationError(
                f"simulator blew up in env {i} at t={ph.time_s[i]:.2f} s "
                "(vehicle pose not finite/bounded)"
            )
        normals, uniforms = self._draws()
        imu = ph.read_imu(normals[:, :10])
        sf = imu.specific_force_frd_mps2
        collided = np.linalg.norm(sf - self.prev_sf, axis=1) > self.gamma
        g0 = self._reward_cfg.gamma_set_mps2
        self.gamma = np.where(collided, self.gamma * 2.0, np.maximum(g0, self.gamma / 2.0))
        self.prev_sf = sf
        nav = self.nav
        if not nav.ideal:
            nav.step(self.dt_s, T, ph.nu()[:, :3], imu.velocity_frd_mps, normals[:, 16:])
        self.T_nav = nav.T_nav(T, imu.depth_m)
        self._measure_and_filter(T, normals[:, 10:16], uniforms)
        e_true, psi_true = docking_errors_b(T, self.T_world_ds, self.cfg.task)
        visible = ds_visible_b(inv_T_b(T) @ self.T_world_ds, self.cfg.task)
        paper = paper_success_b(e_true, psi_true, visible, self.task)
        seated = pegs_seated_b(T, self.T_world_ds, self.task)
        self.seated = np.where(seated, self.seated + 1, 0)
        strict = self.seated >= self.hold_steps
        self.success_paper |= paper
        self.success_strict |= strict
        docked = paper if self.cfg.terminate_on == "paper" else strict
        truncated = ~docked & (self.steps >= self.max_steps)
        terms = reward_terms_b(
            self._reward_cfg, self._weights, self._smooth, e_true, psi_true, a,
            self.prev_action, collided, docked, truncated, self.prev_e_xy,
        )  # fmt: skip
        reward = sum(terms.values())
        self.prev_action = a.copy()
        v_dvl = nav.dvl_velocity(imu.velocity_frd_mps)
        if self.cfg.obs_contact:
            self.contact.update(collided, v_dvl)
        frame = observation_frames_b(
            self.cfg, self.T_nav, self.filter.T_world_ds(), self.filter.sigma_xy_m(),
            v_dvl, imu.angular_velocity_frd_radps[:, 2], imu.acceleration_frd_mps2,
            self.prev_action, self.detected,
            self.contact.features() if self.cfg.obs_contact else None,
        )  # fmt: skip
        self.frames = np.concatenate([self.frames[:, 1:], frame[:, None]], axis=1)
        obs = self._obs(e_true, psi_true)
        self.ep_return += reward
        dones = docked | truncated
        sigma = np.sqrt(np.diagonal(self.filter.P, axis1=1, axis2=2)[:, :3])
        nav_err = nav.error_m()
        cols = StepColumns(
            terms={k: np.asarray(v) for k, v in terms.items()},
            values={
                "success_paper": self.success_paper.copy(),
                "success_strict": self.success_strict.copy(),
                "collided": collided,
                "detected": self.detected.copy(),
                "e_true": e_true,
                "e_psi_true": psi_true,
                "time_s": ph.time_s.copy(),
                "T_world_body": T,
                "T_world_ds": self.T_world_ds.copy(),
                "estimate_sigma_m": sigma,
                "nav_error_m": nav_err,
            },
            ends={},
        )
        now = time.time()
        for i in np.flatnonzero(dones):
            cols.ends[int(i)] = {
                "TimeLimit.truncated": bool(truncated[i]),
                "terminal_observation": obs[i].copy(),
                "episode": {
                    "r": round(float(self.ep_return[i]), 6),
                    "l": int(self.steps[i]),
                    "t": round(now - self.ep_start[i], 6),
                },
            }
            obs[i] = self._reset_slot(int(i))
        return obs, reward.astype(np.float32), dones, cols

    def _measure_and_filter(
        self, T: np.ndarray, normals: np.ndarray, uniforms: np.ndarray | None
    ) -> None:
        """Predict, fuse the acoustic fixes due, then the source's measurements (made of this
        step's draws), each moved from the true pose's frame into the navigation's
        (:func:`uwdock.sim.navigation.correction`; neither source here is ``nav_frame``)."""
        f = self.filter
        f.predict(self.dt_s)
        n = self.num_envs
        t = self.physics.time_s
        C = None if self.nav.ideal else correction(self.T_nav, T)
        if self.acoustic:
            mask = np.zeros(n, dtype=bool)
            p = np.zeros((n, 3))
            sig = np.ones(n)
            for i, env in enumerate(self.envs):
                fix = env.usbl.fix(float(t[i]), T[i], self.T_world_ds[i, :3, 3], env.np_random)
                if fix is not None:
                    mask[i], p[i], sig[i] = True, fix.p_world_ds_m, fix.sigma_m
            if mask.any():
                if C is not None:
                    p = np.einsum("nij,nj->ni", C[:, :3, :3], p) + C[:, :3, 3]
                f.update_position(mask, p, sig)
        if self.model is not None:
            det, T_meas, cov = self.model.measure(T, self.T_world_ds, t, uniforms, normals)
        elif self.cfg.obs_source == "proxy":
            det, T_meas, cov = proxy_measure_b(T, self.T_world_ds, self.cfg.task, normals)
            if C is not None:
                T_meas = C @ T_meas
            f.update(np.ones(n, dtype=bool), self._z(T_meas), cov)
            self.detected = det
            return
        else:  # acoustic: no measurement
            self.detected = np.zeros(n, dtype=bool)
            return
        if C is not None:
            T_meas = C @ T_meas
        f.update(det, self._z(T_meas), cov)
        self.detected = det

    @staticmethod
    def _z(T: np.ndarray) -> np.ndarray:
        return np.concatenate([T[:, :3, 3], yaw_b(T)[:, None]], axis=1)

    def _obs(self, e_true: np.ndarray, psi_true: np.ndarray) -> np.ndarray:
        obs = self.frames.reshape(self.num_envs, -1)
        if not self.cfg.obs_privileged:
            return obs.copy()
        block = np.zeros((self.num_envs, PRIVILEGED_DIM), dtype=np.float32)
        if self.privileged:
            e_hat, _ = docking_errors_b(self.T_nav, self.filter.T_world_ds(), self.cfg.task)
            s = POS_SCALE_M
            parts = [
                np.clip(e_true, -s, s) / s,
                (psi_true / math.pi)[:, None],
                np.clip(e_hat - e_true, -s, s) / s,
                (1.0 - self.steps / self.max_steps)[:, None],
                (self.seated / self.hold_steps)[:, None],
            ]
            block = np.clip(np.concatenate(parts, axis=1), -OBS_BOUND, OBS_BOUND).astype(np.float32)
        return np.concatenate([obs, block], axis=1)

    # ------------------------------------------------------------------ the rest of VecEnv
    def close(self) -> None:
        for env in self.envs:
            env.close()

    def _slots(self, indices) -> list[int]:
        return list(self._get_indices(indices))

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self.envs[i], attr_name) for i in self._slots(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        for i in self._slots(indices):
            setattr(self.envs[i], attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        out = [
            getattr(self.envs[i], method_name)(*method_args, **method_kwargs)
            for i in self._slots(indices)
        ]
        self._refresh_task()  # e.g. set_curriculum changed the success test's tolerance
        return out

    def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
        return [False for _ in self._slots(indices)]

    def set_curriculum(
        self, z_tolerance_m: float, spawn_scale: float, near_share: float = 0.0, near_box=None
    ) -> None:
        """The curriculum level for every env
        (:meth:`rl.env.docking_env.DockingEnv.set_curriculum`)."""
        extra = () if near_box is None else (near_box,)
        self.env_method("set_curriculum", z_tolerance_m, spawn_scale, near_share, *extra)
