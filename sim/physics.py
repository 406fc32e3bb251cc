"""The vehicle as one SAPIEN (PhysX) rigid body driven by our hydrodynamics and thrusters.

Frames: the model (``sim.vehicle``, ``sim.thrusters``) is written in world NED / body FRD; SAPIEN
uses a z-up world and FLU actors (``calibration.frames``: both conversions are 180 deg about x).
This module is the only place where the two meet: poses go through ``ned_pose_to_zup`` /
``zup_pose_to_ned``; inside the 300 Hz loop body vectors are converted by negating their y and z
components (FLU <-> FRD) and the current by ``R_zup_ned`` once per control step.

How added mass is made stable (and exact) at 300 Hz:
    Applying ``-M_A nu_dot`` as a force with the previous substep's acceleration is an explicit
    algebraic loop that oscillates or diverges once ``M_A`` nears the rigid mass. Folding ``M_A``
    into PhysX's mass is the usual cure, but PhysX has one scalar mass and a diagonal inertia at
    the CoM, while ``M_A`` is anisotropic, lives at the origin and gravity must act on ``m`` only.
    So we solve the full 6x6 Fossen equation ourselves for ``nu_dot`` (``Hydrodynamics``: constant
    mass matrix ``M_RB + M_A``, every other term from the current state, no acceleration
    feedback) and hand PhysX the force and torque that make *its* body (mass ``m_e``, inertia
    ``I_e`` at the CG) reach exactly that acceleration:
    ``F = m_e a_cg``, ``T = I_e omega_dot + omega x I_e omega`` (PhysX integrates the gyroscopic
    term itself). The integration is then plain semi-implicit Euler of a smooth ODE, stable for
    any added mass. ``m_e = m + mean(M_A[:3])`` and ``I_e = I + M_A[3:]`` ("folded" added mass)
    matter only for contacts, so a collision feels the water that moves with the hull.

Speed: NumPy costs ~1 us per call on 3-vectors, so the per-substep work is one call of a numba
kernel (``sim.fastpath.physx_wrench``: state -> hydrodynamics -> force and torque) between the
PhysX calls; thruster responses and the varying current are computed per control step with
NumPy. While no PhysX contact is possible during a control step (the hull's swept boxes stay
clear of every static PhysX shape's box: the docking station; a docking world's tank floor and
walls are planes of the kernel's own contact model, :meth:`VehicleBody.set_tank_planes`), the
**free-flight fast path** integrates the whole step in one kernel call
(``sim.fastpath.free_flight``: the same maths, then what PhysX does with the force and torque)
and writes pose and velocities back into PhysX: ~40 us instead of ~0.55 ms per 0.2 s control
step. It needs the vehicle to be the scene's only dynamic body (the docking station and tank are
static) and the component's damping left at 0; the two paths agree to PhysX's float32 round-off.
A step that may touch is integrated in the kernel up to the first six-substep chunk that may,
PhysX runs the rest. ``fast_path=False`` turns it off.

Example:
    >>> scene = make_physics_scene()
    >>> auv = VehicleBody(scene, VehicleConfig(), Current(CurrentConfig(mode="constant")))
    >>> auv.reset(make_T(t=[0, 0, 5.0]))          # 5 m deep, level, heading north
    >>> auv.step([50.0, 0, 0, 0, 0, 0], 0.2)      # one 5 Hz control step (60 substeps)
    >>> auv.nu                                      # body velocity, FRD
"""

from __future__ import annotations

import math

import numpy as np
import sapien
from numpy.typing import ArrayLike

from uwdock.calibration.frames import (
    T_BODYFLU_BODYFRD,
    T_WORLDZUP_WORLDNED,
    R_from_quat_wxyz,
    T_from_pos_quat,
    check_T,
    cross3,
    ned_pose_to_zup,
    pos_quat_from_T,
)
from uwdock.dockcore.errors import ConfigError
from uwdock.sim.fastpath import (
    StaticObstacles,
    body_params,
    free_flight,
    hull_boxes,
    hydro_params,
    physx_wrench,
)
from uwdock.sim.scene import new_scene
from uwdock.sim.thrusters import ThrusterArray
from uwdock.sim.vehicle import Current, CurrentConfig, Hydrodynamics, Imu, ImuReading, VehicleConfig

__all__ = [
    "FREE_FLIGHT_MARGIN_M",
    "PHYSICS_RATE_HZ",
    "PLANE_STIFFNESS_N_PER_M",
    "VehicleBody",
    "hull_spheres",
    "make_physics_scene",
    "tank_planes",
]

#: Default physics rate (Hz): the reference's 300 Hz.
PHYSICS_RATE_HZ = 300.0
#: The fast path is used only if every hull shape's swept box stays this far (m) from every
#: static shape's box (on top of both shapes' PhysX contact offsets).
FREE_FLIGHT_MARGIN_M = 0.05
#: The tank planes' contact (:func:`uwdock.sim.fastpath.plane_contacts`): stiffness (N/m), about
#: 1 mm of give under full thrust, stiff enough for 300 Hz (sqrt(k / m) * dt ~ 0.1); the damping
#: is critical for the vehicle's folded mass; friction is regularised below this speed (m/s).
PLANE_STIFFNESS_N_PER_M = 2.0e5
PLANE_FRICTION_V_EPS_MPS = 0.01


def hull_spheres(shapes) -> np.ndarray:
    """(s, 4) spheres (centre in body FLU, radius; m) that touch a plane where the hull's
    collision shapes (body FRD :class:`uwdock.sim.vehicle.CollisionShape`) do: a capsule's two
    end spheres, a box's eight corners (radius 0)."""
    rows = []
    for sh in shapes:
        c = np.asarray(sh.center_m, dtype=float)
        if sh.kind == "capsule":
            r, half = float(sh.size_m[0]), float(sh.size_m[1])
            axis = np.zeros(3)
            axis["xyz".index(sh.axis)] = 1.0
            rows += [[*((c + s * half * axis) * _S_BODY), r] for s in (-1.0, 1.0)]
        else:
            h = np.asarray(sh.size_m, dtype=float)
            rows += [
                [*((c + np.array([sx, sy, sz]) * h) * _S_BODY), 0.0]
                for sx in (-1.0, 1.0)
                for sy in (-1.0, 1.0)
                for sz in (-1.0, 1.0)
            ]
    return np.ascontiguousarray(np.array(rows, dtype=float).reshape(-1, 4))


def tank_planes(length_m: float, width_m: float, depth_m: float, lid: bool = False) -> np.ndarray:
    """(5, 4) the tank's floor and walls as planes (normal into the water, z-up world, and
    offset; :func:`uwdock.sim.fastpath.plane_contacts`), plus the water surface as a sixth
    with ``lid`` (a vehicle without a free surface): tank centred on the world origin, the
    floor ``depth_m`` below the surface."""
    hx, hy = 0.5 * length_m, 0.5 * width_m
    planes = [
        [0.0, 0.0, 1.0, -depth_m],
        [1.0, 0.0, 0.0, -hx],
        [-1.0, 0.0, 0.0, -hx],
        [0.0, 1.0, 0.0, -hy],
        [0.0, -1.0, 0.0, -hy],
    ]
    if lid:
        planes.append([0.0, 0.0, -1.0, 0.0])
    return np.array(planes)


# The scalar loop converts body vectors FLU <-> FRD by negating y and z: check that assumption.
if not np.array_equal(T_BODYFLU_BODYFRD[:3, :3], np.diag([1.0, -1.0, -1.0])):  # pragma: no cover
    raise ImportError("sim.physics assumes T_BODYFLU_BODYFRD = diag(1, -1, -1)")
_R_ZUP_NED = np.array(T_WORLDZUP_WORLDNED[:3, :3])
_S_BODY = np.array([1.0, -1.0, -1.0])  # FRD <-> FLU component signs


def make_physics_scene(timestep_s: float = 1.0 / PHYSICS_RATE_HZ) -> sapien.Scene:
    """A SAPIEN scene with a PhysX CPU system only (no render system, so no Vulkan needed).

    Args:
        timestep_s: physics substep (s).
    """
    scene = new_scene([sapien.physx.PhysxCpuSystem()])
    scene.set_timestep(timestep_s)
    return scene


def _shape_pose_flu(center_frd: ArrayLike, axis: str) -> sapien.Pose:
    """Local pose (FLU) of a primitive whose natural axis (x for capsules) must lie on ``axis``."""
    p = (np.asarray(center_frd, dtype=float) * _S_BODY).tolist()
    h = math.sqrt(0.5)
    q = {"x": [1.0, 0.0, 0.0, 0.0], "y": [h, 0.0, 0.0, h], "z": [h, 0.0, h, 0.0]}[axis]
    return sapien.Pose(p, q)


class VehicleBody:
    """The AUV as a dynamic SAPIEN actor with hydrodynamics, thrusters, current and IMU.

    ``step`` advances the whole scene (it calls ``scene.step()`` once per substep), so use one
    ``VehicleBody`` per scene and do not step that scene elsewhere.

    Args:
        scene: the SAPIEN scene (physics-only from :func:`make_physics_scene`, or one with a
            renderer); its timestep is the physics substep.
        config: the true vehicle of this episode (e.g. a randomised draw).
        current: ocean current; default none (still water).
        nominal_config: what the controller believes (used by :meth:`step` for allocation);
            default ``config``.
        rng: generator for the IMU biases and noise.
        name: actor name.
        fast_path: integrate contact-free control steps without PhysX (module docstring);
            False always steps PhysX.

    Attributes:
        last_step_fast: whether the last control step took the free-flight fast path.
    """

    def __init__(
        self,
        scene: sapien.Scene,
        config: VehicleConfig | None = None,
        current: Current | None = None,
        nominal_config: VehicleConfig | None = None,
        rng: np.random.Generator | None = None,
        name: str = "auv",
        fast_path: bool = True,
    ) -> None:
        config = config if config is not None else VehicleConfig()
        self.scene = scene
        self.dt_s = float(scene.get_timestep())
        self.fast_path = fast_path
        self.last_step_fast = False
        self.entity = self._build_actor(scene, config, name)
        self.component = self.entity.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
        comp = self.component
        comp.set_disable_gravity(True)  # gravity is our restoring force, acting on m only
        comp.set_linear_damping(0.0)
        comp.set_angular_damping(0.0)
        comp.set_sleep_threshold(0.0)
        self._hull = hull_boxes(comp)  # (s, 7) body-frame boxes for the contact test
        self._obstacles = StaticObstacles(scene, comp)
        self._spheres = hull_spheres(config.collision)  # the hull against the tank planes
        self._planes = np.zeros((0, 4))
        self._plane_friction = 0.0
        self.current = current if current is not None else Current(CurrentConfig("constant"))
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.allocator: ThrusterArray | None = None
        self.set_config(config, nominal_config)
        self.reset(np.eye(4))

    def rebind(self, scene: sapien.Scene) -> None:
        """Follow the vehicle's entity into ``scene`` (a world that moved its entities into a
        fresh physics system, :meth:`uwdock.sim.world.DockingWorld.reset`); call
        :meth:`reset` afterwards."""
        if self.entity.scene is not scene:
            raise ValueError("rebind: the vehicle's entity is not in that scene")
        if float(scene.get_timestep()) != self.dt_s:
            raise ValueError("rebind: the new scene has another timestep")
        self.scene = scene
        self._obstacles.follow(scene)

    # ------------------------------------------------------------------ construction

    @staticmethod
    def _build_actor(scene: sapien.Scene, config: VehicleConfig, name: str) -> sapien.Entity:
        builder = scene.create_actor_builder()
        material = sapien.physx.PhysxMaterial(config.friction, config.friction, 0.0)
        for shape in config.collision:
            pose = _shape_pose_flu(shape.center_m, shape.axis if shape.kind == "capsule" else "x")
            if shape.kind == "box":
                builder.add_box_collision(pose, half_size=shape.size_m, material=material)
            else:
                builder.add_capsule_collision(
                    pose, radius=shape.size_m[0], half_length=shape.size_m[1], material=material
                )
        return builder.build(name=name)

    def set_config(
        self, config: VehicleConfig, nominal_config: VehicleConfig | None = None
    ) -> None:
        """Switch to another vehicle draw (mass, inertia, CG, hydrodynamics, thrusters, IMU).

        Call :meth:`reset` afterwards (PhysX keeps the CoM velocity, whose point just moved).
        The collision shapes stay those the actor was built with.
        """
        self.config = config
        self.nominal_config = nominal_config if nominal_config is not None else config
        self.hydro = Hydrodynamics(config)
        limit_s = self.hydro.stable_substep_s()
        if not self.dt_s < limit_s:
            raise ConfigError(
                f"linear_damping: too stiff for the physics substep of {self.dt_s:.3g} s "
                f"(this vehicle's damping and mass need a substep < {limit_s:.3g} s): lower "
                "the damping, raise the mass or the physics rate"
            )
        self._P = hydro_params(self.hydro)
        self.thrusters = ThrusterArray(config.thrusters)
        nominal = self.nominal_config.thrusters
        if self.allocator is None or self.allocator.config is not nominal:
            # a new episode's draw keeps the nominal vehicle: its allocation is reused
            self.allocator = ThrusterArray(nominal)
        if self.allocator.n != self.thrusters.n:
            raise ValueError("nominal and true vehicles must have the same number of thrusters")
        self._B_T = self.thrusters.B.T.copy()
        self.imu = Imu(config.imu, config.gravity_mps2, self._rng)
        am = config.added_mass
        self.engine_mass_kg = config.mass_kg + (am[0] + am[1] + am[2]) / 3.0
        self.engine_inertia_kgm2 = tuple(
            i + a for i, a in zip(config.inertia_kgm2, am[3:], strict=True)
        )
        comp = self.component
        comp.set_mass(self.engine_mass_kg)
        comp.set_inertia(np.asarray(self.engine_inertia_kgm2, dtype=np.float32))
        comp.set_cmass_local_pose(sapien.Pose((np.asarray(config.cg_m) * _S_BODY).tolist()))
        self._B = body_params(self.engine_mass_kg, self.engine_inertia_kgm2, comp)
        self._set_contact()

    def _set_contact(self) -> None:
        k = PLANE_STIFFNESS_N_PER_M
        mu = 0.5 * (self.config.friction + self._plane_friction)  # PhysX's "average" combine
        c = 2.0 * math.sqrt(k * self.engine_mass_kg)
        s = self._spheres
        reach = float(np.max(np.linalg.norm(s[:, :3], axis=1) + s[:, 3])) if len(s) else 0.0
        self._contact = np.array([k, c, mu, PLANE_FRICTION_V_EPS_MPS, reach])

    def set_tank_planes(self, planes: np.ndarray, friction: float) -> None:
        """Let the hull touch these planes (:func:`tank_planes`) through our contact model
        instead of PhysX shapes (build the tank without collision shapes then): their contact
        is integrated in free flight, so only the docking station needs PhysX.

        Args:
            planes: (k, 4) unit normal into the water (z-up world) and offset.
            friction: the planes' dynamic friction coefficient (averaged with the hull's).
        """
        p = np.asarray(planes, dtype=float).reshape(-1, 4)
        if not np.all(np.isfinite(p)):
            raise ValueError("planes: must be finite")
        self._planes = np.ascontiguousarray(p)
        self._plane_friction = float(friction)
        self._set_contact()

    # ------------------------------------------------------------------ state

    def reset(
        self,
        T_world_ned_body_frd: ArrayLike,
        nu: ArrayLike | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        """Place the vehicle, set its velocity, stop the thrusters and zero the clock.

        Args:
            T_world_ned_body_frd: (4, 4) pose of body FRD in world NED (z = depth, m).
            nu: (6,) body velocity of the origin, FRD (m/s, rad/s); default at rest.
            rng: if given, the IMU draws new biases from it and keeps it for its noise.
        """
        T_zup_flu = ned_pose_to_zup(check_T(T_world_ned_body_frd, "T_world_ned_body_frd"))
        p, q = pos_quat_from_T(T_zup_flu)
        self.entity.set_pose(sapien.Pose(p.tolist(), q.tolist()))
        nu = np.zeros(6) if nu is None else np.asarray(nu, dtype=float)
        if nu.shape != (6,) or not np.all(np.isfinite(nu)):
            raise ValueError(f"nu: expected 6 finite values, got shape {nu.shape}")
        c = np.asarray(self.config.cg_m, dtype=float)
        v_cg_frd = nu[:3] + cross3(nu[3:], c)
        R = T_zup_flu[:3, :3]
        self.component.set_linear_velocity((R @ (v_cg_frd * _S_BODY)).astype(np.float32))
        self.component.set_angular_velocity((R @ (nu[3:] * _S_BODY)).astype(np.float32))
        self.thrust_n = np.zeros(self.thrusters.n)
        self.thrust_command_n = np.zeros(self.thrusters.n)
        self.time_s = 0.0
        self._acc_zup = (0.0,) * 6  # last substep's CoM and angular acceleration, world
        self._acc_mean_zup = (0.0,) * 6  # the same averaged over the last control step
        self._T_cache = None
        if rng is not None:
            self._rng = rng
            self.imu.reset(rng)

    @property
    def T_world_ned_body_frd(self) -> np.ndarray:
        """(4, 4) pose of body FRD in world NED (cached until the next step or reset)."""
        if self._T_cache is None:
            pose = self.component.get_entity_pose()
            T = T_from_pos_quat(pose.p, pose.q)
            # T_ned_frd = F @ T_zup_flu @ F with F = diag(1, -1, -1, 1) (both 180 deg about x)
            T[1:3, :] *= -1.0
            T[:, 1:3] *= -1.0
            self._T_cache = T
        return self._T_cache.copy()

    def _R_t_zup_flu(self) -> np.ndarray:
        pose = self.component.get_entity_pose()
        return R_from_quat_wxyz(pose.q).T

    @property
    def nu(self) -> np.ndarray:
        """(6,) body velocity [u, v, w, p, q, r] of the origin, FRD (m/s, rad/s)."""
        R_t = self._R_t_zup_flu()
        w = R_t @ self.component.get_angular_velocity().astype(float) * _S_BODY
        v_cg = R_t @ self.component.get_linear_velocity().astype(float) * _S_BODY
        return np.concatenate([v_cg - cross3(w, self.config.cg_m), w])

    @property
    def nu_dot(self) -> np.ndarray:
        """(6,) last substep's acceleration of the origin and angular acceleration, body FRD."""
        return self._origin_acceleration(self._acc_zup)

    @property
    def nu_dot_mean(self) -> np.ndarray:
        """(6,) like :attr:`nu_dot`, averaged over the last control step (velocity change over
        its duration): what a delta-velocity IMU sampled at the control rate reports, so an
        impact inside the step shows even when it is over by the step's end."""
        return self._origin_acceleration(self._acc_mean_zup)

    def _origin_acceleration(self, acc_zup) -> np.ndarray:
        R_t = self._R_t_zup_flu()
        a_cg = R_t @ np.asarray(acc_zup[:3]) * _S_BODY
        alpha = R_t @ np.asarray(acc_zup[3:]) * _S_BODY
        w = R_t @ self.component.get_angular_velocity().astype(float) * _S_BODY
        c = self.config.cg_m
        a_o = a_cg - cross3(alpha, c) - cross3(w, cross3(w, c))
        return np.concatenate([a_o, alpha])

    def read_imu(self) -> ImuReading:
        """Sample the noisy navigation sensors at the current state (the accelerometer reports
        the mean over the last control step, see :attr:`nu_dot_mean`)."""
        T = self.T_world_ned_body_frd
        return self.imu.measure(T[:3, :3], self.nu, self.nu_dot_mean[:3], float(T[2, 3]))

    # ------------------------------------------------------------------ batch access
    # What :class:`uwdock.sim.batch.BatchVehicles` reads to step this body among many.

    @property
    def kernel_params(self) -> tuple[np.ndarray, np.ndarray]:
        """``(P, B)``: the packed hydrodynamic (71,) and PhysX body (9,) parameters of the
        kernels (:func:`uwdock.sim.fastpath.hydro_params`, ``body_params``)."""
        return self._P, self._B

    @property
    def hull(self) -> np.ndarray:
        """(s, 7) the hull's collision shapes as boxes in the body frame (the contact test)."""
        return self._hull

    @property
    def plane_params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(spheres, planes, contact)`` of the tank planes' contact (:meth:`set_tank_planes`)."""
        return self._spheres, self._planes, self._contact

    @property
    def thrust_wrench_matrix(self) -> np.ndarray:
        """(k, 6) true thrusts (N) -> body wrench (N, N m, FRD): ``wrench = thrust @ this``."""
        return self._B_T

    @property
    def acc_mean_zup(self) -> tuple[float, ...]:
        """Last control step's mean CoM and angular acceleration, z-up world (6 values)."""
        return self._acc_mean_zup

    def obstacle_boxes(self) -> np.ndarray | None:
        """(m, 6) world boxes of the scene's static shapes, or None when the fast path cannot
        stand in for PhysX (it is off, or the scene holds other moving bodies)."""
        return self._obstacles.boxes() if self.fast_path else None

    def state_zup(self) -> np.ndarray:
        """(13,) float64: entity position, quaternion (w x y z), CoM velocity and angular
        velocity, z-up world, as PhysX holds them."""
        comp = self.component
        pose = comp.get_entity_pose()
        return np.concatenate(
            [pose.p, pose.q, comp.get_linear_velocity(), comp.get_angular_velocity()]
        ).astype(np.float64)

    def set_state_zup(self, state: np.ndarray, thrust_n: np.ndarray, time_s: float) -> None:
        """Put the body in ``state`` (:meth:`state_zup`'s layout), with the thrusters producing
        ``thrust_n`` at ``time_s`` (s)."""
        self.entity.set_pose(sapien.Pose(state[:3], state[3:7]))
        self.component.set_linear_velocity(np.asarray(state[7:10], dtype=np.float32))
        self.component.set_angular_velocity(np.asarray(state[10:13], dtype=np.float32))
        self.thrust_n = np.array(thrust_n, dtype=float)
        self.time_s = float(time_s)
        self._T_cache = None

    def substeps(self, duration_s: float) -> int:
        """Substeps in ``duration_s`` (ValueError unless a whole multiple of the timestep)."""
        return self._substeps(duration_s)

    def run_physx(self, wrenches: np.ndarray, currents: np.ndarray) -> None:
        """Step PhysX through the given substeps' thrust wrenches (n, 6) (FRD) and currents
        (n, 3) (z-up world), contacts included; the clock and thrusters are the caller's."""
        self._run(np.ascontiguousarray(wrenches), np.ascontiguousarray(currents), len(wrenches))

    # ------------------------------------------------------------------ stepping

    def _substeps(self, duration_s: float) -> int:
        n = round(duration_s / self.dt_s)
        if n < 1 or abs(n * self.dt_s - duration_s) > 1e-6 * max(1.0, duration_s):
            raise ValueError(f"duration_s={duration_s} is not a multiple of dt={self.dt_s}")
        return n

    def step(self, wrench_frd: ArrayLike, duration_s: float = 0.2) -> None:
        """One control step: allocate a body wrench and simulate for ``duration_s``.

        The nominal thruster model turns the wrench (6,) [N, N m, FRD, about the origin] into
        setpoints (saturating by a common factor); the true thrusters turn those setpoints into
        thrust, so thruster randomisation shows up as a wrench error.
        """
        setpoint = self.allocator.setpoint_from_thrust(self.allocator.allocate(wrench_frd))
        self.step_thrust(self.thrusters.thrust_from_setpoint(setpoint), duration_s)

    def step_thrust(self, thrust_command_n: ArrayLike, duration_s: float = 0.2) -> None:
        """Hold a thrust command (n,) (N) for ``duration_s`` (a multiple of the timestep).

        Each substep: the thrusters' first-order response, then hydrodynamics for ``nu_dot``,
        then the PhysX force/torque that realises it, then ``scene.step()`` -- or, when no
        contact is possible during the step, the same in one kernel call (module docstring).
        """
        n = self._substeps(duration_s)
        dt = self.dt_s
        comp = self.component
        v0 = comp.get_linear_velocity().astype(float)
        w0 = comp.get_angular_velocity().astype(float)
        cmd = np.asarray(thrust_command_n, dtype=float)
        thrust = self.thrusters.response(self.thrust_n, cmd, dt, n)  # (n, k)
        wrenches = np.ascontiguousarray(thrust @ self._B_T)
        times = self.time_s + dt * np.arange(n)
        currents = np.ascontiguousarray(self.current.velocity_ned_at(times) @ _R_ZUP_NED.T)
        done = self._run_free(wrenches, currents) if self.fast_path else 0
        self.last_step_fast = done == n
        if done < n:  # PhysX for the substeps that may touch the docking station
            self._run(wrenches[done:], currents[done:], n - done)
        self.thrust_command_n = cmd
        self.thrust_n = thrust[-1].copy()
        self.time_s += n * dt
        self._T_cache = None
        span = n * dt
        self._acc_mean_zup = tuple(
            np.concatenate([comp.get_linear_velocity() - v0, comp.get_angular_velocity() - w0])
            / span
        )

    def _run_free(self, wrenches: np.ndarray, currents: np.ndarray) -> int:
        """Integrate the control step without PhysX as far as no contact is possible; returns
        the substeps done (0: nothing changed, e.g. the scene holds other moving bodies)."""
        obstacles = self._obstacles.boxes()
        if obstacles is None:
            return 0
        comp = self.component
        pose = comp.get_entity_pose()
        state = np.concatenate(
            [pose.p, pose.q, comp.get_linear_velocity(), comp.get_angular_velocity()]
        ).astype(np.float64)
        acc = np.zeros(6)
        done = free_flight(
            self._P, self._B, state, wrenches, currents, self.dt_s,
            self._hull, obstacles, FREE_FLIGHT_MARGIN_M, acc,
            self._spheres, self._planes, self._contact,
        )  # fmt: skip
        if done == 0:
            return 0
        self.entity.set_pose(sapien.Pose(state[:3], state[3:7]))
        comp.set_linear_velocity(state[7:10])
        comp.set_angular_velocity(state[10:13])
        self._acc_zup = tuple(acc.tolist())
        return int(done)

    def _run(self, wrenches: np.ndarray, currents: np.ndarray, n: int) -> None:
        """The PhysX loop: ``n`` substeps with the given per-substep wrench (n, 6) (FRD) and
        current (n, 3) (z-up world); one kernel call per substep (module docstring)."""
        comp = self.component
        get_pose = comp.get_entity_pose
        get_v = comp.get_linear_velocity
        get_w = comp.get_angular_velocity
        add = comp.add_force_torque
        step = self.scene.physx_system.step  # what scene.step() calls, without its Python frame
        P, B = self._P, self._B
        spheres, planes, contact = self._spheres, self._planes, self._contact
        v = w = np.zeros(3)
        for k in range(n):
            v = get_v()  # CoM velocity, z-up world
            w = get_w()
            pose = get_pose()
            force, torque = physx_wrench(
                P, B, pose.p, pose.q, v, w, currents, wrenches, k, spheres, planes, contact
            )
            add(force, torque)
            step()
        if n:
            inv = 1.0 / self.dt_s
            dv = np.concatenate([get_v().astype(float) - v, get_w().astype(float) - w])
            self._acc_zup = tuple((dv * inv).tolist())
