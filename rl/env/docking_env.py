"""The docking environment: Girona AUV, docking station, 5 Hz control of a body wrench.

Registered with Gymnasium as ``uwdock/Docking-v0``. One step:

    action [-1, 1]^6 -> body wrench -> thruster allocation -> 60 substeps of hydrodynamics +
    thrusters + PhysX contacts -> IMU/DVL -> the vehicle's navigation pose (dead reckoning,
    :mod:`uwdock.sim.navigation`) -> the observation source measures the DS pose, turned into
    the world with that pose -> shared filter -> observation [e_x, e_y, e_z, e_psi, v_x, v_y,
    v_z, w_psi, acc_x, acc_y, acc_z] (+ last action, + history) -> named reward terms ->
    paper / strict success.

The reward and the success tests use the true state (as the reference code does); the policy
sees only the estimate: the DS filter's, relative to the vehicle's navigation pose. ``info``
carries ``reward_terms``, ``success_paper``, ``success_strict``, ``collided``, ``detected``,
``e_true``, the poses for plotting and ``nav_error_m`` (the navigation's horizontal drift).
"""

from __future__ import annotations

import functools
import math
from typing import Any, ClassVar

import cv2
import gymnasium as gym
import numpy as np

from uwdock.calibration.frames import R_from_rpy, inv_T, make_T
from uwdock.dockcore.config import replace
from uwdock.dockcore.errors import DockError
from uwdock.rl.env.camera_source import CameraSource
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.curriculum import curriculum_z_field
from uwdock.rl.env.error_model import ErrorModelSource, load_error_model
from uwdock.rl.env.estimator import DSPoseFilter
from uwdock.rl.env.obs_sources import (
    AcousticSource,
    ObservationSource,
    ProxySource,
    SourceNeeds,
    StepContext,
)
from uwdock.rl.env.observation import (
    OBS_BOUND,
    PRIVILEGED_DIM,
    ContactMemory,
    observation_frame,
    observation_size,
    privileged_block,
)
from uwdock.rl.env.rewards import DockingReward
from uwdock.rl.env.task import (
    DockingTaskConfig,
    docking_errors,
    ds_visible,
    paper_success,
    pegs_seated,
)
from uwdock.sim.navigation import RESET_DRAWS as RESET_NAV_DRAWS
from uwdock.sim.navigation import STEP_DRAWS, NavErrors, correction
from uwdock.sim.usbl import UsblSensor
from uwdock.sim.world import DockingWorld

#: ``EnvConfig.obs_source`` -> the source class (its ``needs`` say what the env provides it)
SOURCE_CLASSES: dict[str, type] = {
    "proxy": ProxySource,
    "error-model": ErrorModelSource,
    "camera": CameraSource,
    "acoustic": AcousticSource,
}


class SimulationError(DockError):
    """The physics produced a non-finite or impossible state."""


@functools.lru_cache(maxsize=256)
def _relaxed_task(task: DockingTaskConfig, field: str, z_m: float) -> DockingTaskConfig:
    """``task`` with the curriculum's z tolerance (a validated copy, made once per level: the
    curriculum moves every rollout, and a batch's envs share the task)."""
    return replace(task, **{field: z_m})


class DockingEnv(gym.Env):
    """Gymnasium environment of vision-in-the-loop docking (module docstring).

    Args:
        config: the environment; defaults to :class:`EnvConfig` ().
        render_mode: None, or "rgb_array" (the downward camera's view, when a camera exists).
        privileged: fill the observation's privileged block (``obs_privileged``) with the true
            state: training envs only (:func:`rl.train.workers.EnvWorkers`); otherwise it is zeros.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(
        self,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        privileged: bool = False,
    ) -> None:
        self.cfg = config or EnvConfig()
        self.privileged = bool(privileged)
        self.cfg.validate()
        self.render_mode = render_mode
        c = self.cfg
        self.dt_s = 1.0 / c.control_hz
        self.max_steps = round(c.episode_s * c.control_hz)
        needs: SourceNeeds = SOURCE_CLASSES[c.obs_source].needs
        self.world = DockingWorld(c.world, with_camera=needs.camera or render_mode is not None)
        self.source = self._make_source()
        self.usbl = UsblSensor(c.usbl_model)
        est_cfg = c.estimator
        if not needs.fusion and est_cfg.fuse:
            # a memoryless source (the paper's proxy): every step replaces the estimate
            est_cfg = replace(est_cfg, fuse=False)
        self.filter = DSPoseFilter(est_cfg)
        self.nav = NavErrors(c.nav, 1)
        self._usbl_prior = (
            self.nav.cfg.ds_prior == "usbl" and needs.acoustic_fixes and self.usbl.cfg.period_s > 0
        )
        self._usbl_prior_pending = False
        self.last_usbl_fix: tuple[np.ndarray, float] | None = None
        self.ds_prior: tuple[np.ndarray, np.ndarray] | None = None
        self._limits = c.action_limits
        self.reward_fn = DockingReward(c.reward, actuated=self._limits > 0)
        self.contact = ContactMemory(1, self.dt_s)  # obs_contact's values
        self.observation_space = gym.spaces.Box(
            -OBS_BOUND, OBS_BOUND, shape=(observation_size(c),), dtype=np.float32
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(6,), dtype=np.float32)
        self._frames: list[np.ndarray] = []
        self._hold_steps = max(1, round(c.task.strict_hold_s * c.control_hz))
        self._task = c.task  # the success tests' task (a curriculum may relax one z tolerance)
        self._spawn_scale = 1.0
        self._near_share = 0.0  # near-seat starts (set_curriculum)
        self._near_box = (0.03, 0.6, 0.02, 2.0)
        self._curriculum_level: tuple | None = None

    def set_curriculum(
        self,
        z_tolerance_m: float,
        spawn_scale: float,
        near_share: float = 0.0,
        near_box: tuple[float, float, float, float] = (0.03, 0.6, 0.02, 2.0),
    ) -> None:
        """Training curriculum (:mod:`rl.env.curriculum`): from now on the z tolerance (m) of the
        test that ends the episode (``terminate_on``: the paper test's ``success_z_m``, or the
        strict test's ``strict_peg_z_m``, the pegs' height above their seats), and the scale
        (0, 1] of the AUV's horizontal offset from the DS at the next spawns. The task's own
        tolerance and 1.0 restore the env's own test (:func:`rl.env.curriculum.curriculum_z_end`).

        ``near_share`` [0, 1] of the next spawns start near the seat: the docked pose raised
        by a height uniform in ``near_box``'s (min, max) (m), offset horizontally within +-
        its xy (m) along each DS axis and yawed within +- its yaw (deg)
        (:attr:`rl.env.curriculum.CurriculumConfig.near_start_box`). With 0 the spawns draw
        exactly what they drew without it."""
        lo, hi, xy, yaw = (float(v) for v in near_box)
        if not (
            0 < z_tolerance_m <= 10
            and 0 < spawn_scale <= 1
            and 0 <= near_share <= 1
            and 0 < lo <= hi <= 5
            and 0 <= xy <= 0.5
            and 0 <= yaw <= 45
        ):
            raise ValueError(
                f"curriculum level out of range: z {z_tolerance_m!r} m, spawn {spawn_scale!r}, "
                f"near-seat share {near_share!r}, box {near_box!r}"
            )
        level = (float(z_tolerance_m), float(spawn_scale), float(near_share), (lo, hi, xy, yaw))
        if level == self._curriculum_level:
            return  # pushed every rollout: the same level costs nothing
        self._curriculum_level = level
        field = curriculum_z_field(self.cfg)
        self._task = _relaxed_task(self.cfg.task, field, float(z_tolerance_m))
        self._spawn_scale = float(spawn_scale)
        self._near_share = float(near_share)
        self._near_box = (lo, hi, xy, yaw)

    @property
    def task(self) -> DockingTaskConfig:
        """The task the success tests use now (the config's, or a curriculum's easier one)."""
        return self._task

    @property
    def hold_steps(self) -> int:
        """Control steps the pegs must stay seated for strict success."""
        return self._hold_steps

    @property
    def action_limits(self) -> np.ndarray:
        """(6,) body wrench of a unit action (N, N m)."""
        return self._limits.copy()

    # ------------------------------------------------------------------ setup
    def _make_source(self) -> ObservationSource:
        c = self.cfg
        if c.obs_source == "proxy":
            return ProxySource(c.task)
        if c.obs_source == "error-model":
            return ErrorModelSource(
                load_error_model(c.error_model_path),
                c.task,
                c.world.water_preset,
                temporal=c.error_model_memory,
            )
        if c.obs_source == "acoustic":
            return AcousticSource()
        return CameraSource(self.world)

    def _spawn(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Draw T_world_ds and T_world_body (NED) over the spawn ranges."""
        c = self.cfg
        depth = self.world.floor_z_m
        dx, dy, _ = c.spawn_ds_range_m
        ds_yaw = math.radians(c.spawn_ds_yaw_deg) * rng.uniform(-1, 1)
        T_world_ds = make_T(
            R_from_rpy(0.0, 0.0, ds_yaw), [rng.uniform(-dx, dx), rng.uniform(-dy, dy), depth]
        )
        if self._near_share > 0 and rng.uniform() < self._near_share:
            return T_world_ds, self._near_seat(rng, T_world_ds)
        ax, ay, az = c.spawn_auv_range_m
        lo_m, hi_m = c.spawn_horizontal_range_m
        for _ in range(1000):
            p = np.array(
                [
                    rng.uniform(-ax, ax),
                    rng.uniform(-ay, ay),
                    depth - c.spawn_auv_height_m + rng.uniform(-az, az),
                ]
            )
            if self._spawn_scale != 1.0:  # curriculum: closer to the DS, horizontally
                p[:2] = T_world_ds[:2, 3] + self._spawn_scale * (p[:2] - T_world_ds[:2, 3])
            horizontal = np.linalg.norm(p[:2] - T_world_ds[:2, 3])
            clear = depth - p[2] > 2.4 or horizontal > 2.0  # of the DS structure
            if clear and lo_m <= horizontal <= hi_m:
                break
        else:
            raise ValueError(
                f"spawn: no AUV position clear of the DS and {lo_m:g}-{hi_m:g} m from it "
                f"(spawn_horizontal_range_m) in 1000 draws of the box {c.spawn_auv_range_m} m"
            )
        yaw = math.radians(c.spawn_auv_yaw_deg) * rng.uniform(-1, 1)
        return T_world_ds, make_T(R_from_rpy(0.0, 0.0, yaw), p)

    def _near_seat(self, rng: np.random.Generator, T_world_ds: np.ndarray) -> np.ndarray:
        """T_world_body of a near-seat start (:meth:`set_curriculum`): the docked pose raised,
        offset and yawed within the near-seat box."""
        lo, hi, xy, yaw_deg = self._near_box
        h = rng.uniform(lo, hi)
        dx, dy = rng.uniform(-xy, xy, size=2)
        dyaw = math.radians(yaw_deg) * rng.uniform(-1, 1)
        T_ds_body = make_T(t=[dx, dy, -h]) @ self.cfg.task.T_ds_target  # ds z down: up is -z
        return T_world_ds @ T_ds_body @ make_T(R_from_rpy(0.0, 0.0, dyaw))

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        T_world_ds, T_world_body = self._spawn(rng)
        self.world.reset(T_world_ds, T_world_body, rng)
        self.source.reset(rng)
        # spawning a child sequence consumes no draws of the episode's stream
        self._film_rng = np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])
        self.filter.reset(T_world_ds, rng)
        #: the DS pose and variances the run starts from, before any fix or frame: what a
        #: mission message carries to the vehicle's node (``sim vehicle``)
        self.ds_prior = (self.filter.T_world_ds, np.diag(self.filter.P).copy())
        self.usbl.reset(rng)  # after the prior: the acoustic bias draws leave it as it was
        # an ideal navigation draws nothing: the episode's stream is the one it always was
        self.nav.reset(0, None if self.nav.ideal else rng.standard_normal(RESET_NAV_DRAWS))
        self.reward_fn.reset()
        self.contact.reset()
        self.steps = 0
        self.prev_action = np.zeros(6)
        self._seated_steps = 0
        self.success_paper = False
        self.success_strict = False
        imu = self._last_imu = self.world.vehicle.read_imu()
        self.prev_specific_force = imu.specific_force_frd_mps2
        T_world_body = self.world.T_world_body
        self.T_nav = self.nav.T_nav(T_world_body, [imu.depth_m])[0]
        self._usbl_prior_pending = self._usbl_prior
        self._measure_and_filter(T_world_body, predict=False)
        self._usbl_prior_pending = False
        self._frames = [self._frame(imu)] * self.cfg.obs_frames
        e_true, psi_true = docking_errors(T_world_body, T_world_ds, self.cfg.task)
        obs = self._obs(e_true, psi_true)
        return obs, self._info(T_world_body, e_true, psi_true, {}, collided=False)

    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (6,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be 6 finite numbers, got {np.asarray(action).tolist()}")
        a = np.clip(a, -1.0, 1.0)
        return self._advance(a, a * self._limits)

    def step_wrench(self, wrench):
        """:meth:`step` with a body wrench (6,) [N, N m] instead of an action: the vehicle
        simulated over the wire (``sim vehicle``) applies the wrench its controller sent,
        saturated at the action limits, and the reward sees the action it amounts to."""
        w = np.asarray(wrench, dtype=np.float64).reshape(-1)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f"wrench must be 6 finite numbers, got {np.asarray(wrench).tolist()}")
        lim = self._limits
        w = np.clip(w, -lim, lim)
        a = np.divide(w, lim, out=np.zeros(6), where=lim > 0)
        return self._advance(a, w)

    def _advance(self, a: np.ndarray, wrench: np.ndarray):
        """One control step applying ``wrench`` (the action ``a`` for the reward)."""
        world = self.world
        world.step(wrench, self.dt_s)
        self.steps += 1
        T_world_body = world.T_world_body
        if not np.all(np.isfinite(T_world_body)) or np.abs(T_world_body[:3, 3]).max() > 1e3:
            raise SimulationError(
                f"simulator blew up at t={world.time_s:.2f} s (vehicle pose not finite/bounded)"
            )
        imu = self._last_imu = world.vehicle.read_imu()
        collided = self.reward_fn.collision(imu.specific_force_frd_mps2, self.prev_specific_force)
        self.prev_specific_force = imu.specific_force_frd_mps2
        self._navigate(T_world_body, imu)
        if self.cfg.obs_contact:
            self.contact.update([collided], self.nav.dvl_velocity(imu.velocity_frd_mps))
        self._measure_and_filter(T_world_body, predict=True)

        e_true, psi_true = docking_errors(T_world_body, world.T_world_ds, self.cfg.task)
        visible = ds_visible(inv_T(T_world_body) @ world.T_world_ds, self.cfg.task)
        paper = paper_success(e_true, psi_true, visible, self._task)
        seated = pegs_seated(T_world_body, world.T_world_ds, self._task)
        self._seated_steps = self._seated_steps + 1 if seated else 0
        strict = self._seated_steps >= self._hold_steps
        self.success_paper |= paper
        self.success_strict |= strict
        docked = paper if self.cfg.terminate_on == "paper" else strict
        truncated = not docked and self.steps >= self.max_steps
        terms = self.reward_fn(e_true, psi_true, a, self.prev_action, collided, docked, truncated)
        self.prev_action = a
        self._frames = [*self._frames[1:], self._frame(imu)]
        info = self._info(T_world_body, e_true, psi_true, terms, collided)
        obs = self._obs(e_true, psi_true)
        return obs, float(sum(terms.values())), bool(docked), bool(truncated), info

    def navigation_solution(self) -> dict[str, Any]:
        """What the vehicle's own sensors and navigation report now (the values the
        observation is built from): ``T_world_body`` (the navigation pose, NED/FRD),
        ``velocity_frd_mps`` (DVL), ``angular_velocity_frd_radps`` (gyro),
        ``acceleration_frd_mps2`` (gravity-free), ``specific_force_frd_mps2``
        (accelerometer)."""
        imu = self._last_imu
        return {
            "T_world_body": self.T_nav.copy(),
            "velocity_frd_mps": self.nav.dvl_velocity(imu.velocity_frd_mps)[0],
            "angular_velocity_frd_radps": np.asarray(imu.angular_velocity_frd_radps).copy(),
            "acceleration_frd_mps2": np.asarray(imu.acceleration_frd_mps2).copy(),
            "specific_force_frd_mps2": np.asarray(imu.specific_force_frd_mps2).copy(),
        }

    def render(self):
        if self.render_mode == "rgb_array":
            return self.world.render_camera_rgb()
        return None

    def camera_frame(self) -> np.ndarray | None:
        """The downward camera's view now (RGB, water applied), with the detected markers
        outlined and the step's status written on it; None without a camera."""
        frame = getattr(self.source, "last_frame", None)
        dets = getattr(self.source, "last_detections", [])
        if frame is None:
            frame = self.world.capture(self._film_rng)
            if frame is None:
                return None
            dets = []
        out = frame.img_rgb.copy()
        for d in dets:
            pts = np.round(d.corners_px).astype(np.int32)
            cv2.polylines(out, [pts], True, (0, 255, 0), 2)
            cv2.putText(
                out,
                str(d.marker_id),
                tuple(int(v) for v in pts[0]),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.5,
                (0, 255, 0),
                1,
                cv2.LINE_AA,
            )
        e, _ = docking_errors(self.world.T_world_body, self.world.T_world_ds, self.cfg.task)
        text = (
            f"t={self.world.time_s:4.1f}s  e=({e[0]:+.2f},{e[1]:+.2f},{e[2]:+.2f}) m  "
            f"{'DS detected' if self._detected() else 'no fix'}"
        )
        cv2.putText(
            out, text, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA
        )
        return out

    def close(self) -> None:
        self.world.close()

    # ------------------------------------------------------------------ internals
    def _navigate(self, T_world_body: np.ndarray, imu) -> None:
        """Move the navigation errors on over the step just simulated and set :attr:`T_nav`,
        the pose the vehicle believes it has (the true pose for an ideal navigation)."""
        nav = self.nav
        if not nav.ideal:
            normals = self.np_random.standard_normal(STEP_DRAWS)
            v_true = self.world.vehicle.nu[:3]
            nav.step(self.dt_s, T_world_body, v_true, imu.velocity_frd_mps, normals)
        self.T_nav = nav.T_nav(T_world_body, [imu.depth_m])[0]

    def _measure_and_filter(self, T_world_body: np.ndarray, predict: bool) -> None:
        world = self.world
        if predict:
            self.filter.predict(self.dt_s)
        # a measurement made with the true pose -> the one the vehicle makes with its own
        C = None if self.nav.ideal else correction(self.T_nav, T_world_body)
        self._usbl_fix(T_world_body, C)
        nav_pose = None if self.nav.ideal else self.T_nav
        ctx = StepContext(
            T_world_body, world.T_world_ds, world.time_s, self.filter.T_world_ds, nav_pose
        )
        m = self.source.measure(ctx)
        self.last_measurement = m
        if m is not None:
            T_meas = m.T_world_ds
            if C is not None and not self.source.needs.nav_frame:
                T_meas = C @ T_meas
            self.filter.update(T_meas, m.cov_xyzyaw)

    def _usbl_fix(self, T_world_body: np.ndarray, C: np.ndarray | None) -> None:
        """Fuse the position-only acoustic fix the vehicle receives this step, if one arrives
        (:class:`uwdock.sim.usbl.UsblSensor` of ``EnvConfig.usbl_model``), for sources that
        declare ``needs.acoustic_fixes``; placed with the navigation pose (``C``: the
        correction from the true one, None when they are equal). At reset with
        ``nav.ds_prior = "usbl"`` the first fix is the DS prior (its yaw: the survey's)."""
        if not self.source.needs.acoustic_fixes:
            return
        world = self.world
        fix = self.usbl.fix(world.time_s, T_world_body, world.T_world_ds[:3, 3], self.np_random)
        self.last_usbl_fix = None
        if fix is None:
            return
        p = fix.p_world_ds_m if C is None else C[:3, :3] @ fix.p_world_ds_m + C[:3, 3]
        #: this step's fix as the navigator places it: (position (3,), sigma (m)), or None
        self.last_usbl_fix = (p, fix.sigma_m)
        if self._usbl_prior_pending:
            T = self.filter.T_world_ds
            T[:3, 3] = p
            self.filter.set_prior(T, sigma_xy_m=fix.sigma_m, sigma_z_m=fix.sigma_m)
        else:
            self.filter.update_position(p, fix.sigma_m)

    def _detected(self) -> bool:
        """The camera (or its error model) found the DS this step (not a proxy or USBL fix)."""
        m = self.last_measurement
        return m is not None and m.detected

    def _frame(self, imu) -> np.ndarray:
        """One observation frame: the DS estimate relative to the navigation pose, the DVL's
        velocity (with its scale error), the gyro's yaw rate and the acceleration."""
        return observation_frame(
            self.cfg,
            self.T_nav,
            self.filter,
            self.nav.dvl_velocity(imu.velocity_frd_mps)[0],
            float(imu.angular_velocity_frd_radps[2]),
            imu.acceleration_frd_mps2,
            self.prev_action,
            self._detected(),
            self.contact.features()[0] if self.cfg.obs_contact else None,
        )

    def _obs(self, e_true: np.ndarray, psi_true: float) -> np.ndarray:
        """The stacked frames, then (``obs_privileged``) the critic's block from this step's
        true errors: filled in training envs only, zeros elsewhere."""
        obs = np.concatenate(self._frames).astype(np.float32)
        if not self.cfg.obs_privileged:
            return obs
        block = np.zeros(PRIVILEGED_DIM, dtype=np.float32)
        if self.privileged:
            e_hat, _ = docking_errors(self.T_nav, self.filter.T_world_ds, self.cfg.task)
            block = privileged_block(
                e_true,
                psi_true,
                e_hat,
                1.0 - self.steps / self.max_steps,
                self._seated_steps / self._hold_steps,
            )
        return np.concatenate([obs, block])

    def _info(
        self,
        T_world_body: np.ndarray,
        e_true: np.ndarray,
        psi_true: float,
        terms: dict[str, float],
        collided: bool,
    ) -> dict[str, Any]:
        world = self.world
        return {
            "reward_terms": dict(terms),
            "success_paper": self.success_paper,
            "success_strict": self.success_strict,
            "collided": collided,
            "detected": self._detected(),
            "e_true": e_true,
            "e_psi_true": psi_true,
            "time_s": world.time_s,
            "T_world_body": T_world_body,
            "T_world_ds": world.T_world_ds.copy(),
            "estimate_sigma_m": self.filter.sigma_xyz_m,
            "nav_error_m": float(self.nav.error_m()[0]),
        }
