"""Many vehicles stepped as arrays in one process: the training simulator's physics.

:class:`BatchVehicles` advances ``N`` vehicles, each the :class:`~uwdock.sim.physics.VehicleBody`
of its own physics scene (tank, docking station, vehicle), by one control step in one call:

* thruster allocation (the nominal vehicle), setpoints, the true thrusters' first-order
  response and the thrust wrench per substep, as NumPy arrays over all vehicles;
* the step of every vehicle in one numba kernel call (:func:`uwdock.sim.fastpath.
  free_flight_all`, a loop over ``free_flight``: the same Fossen model and free surface, the
  tank planes' contact, the same integration as PhysX's), as far as its swept hull cannot touch
  the docking station;
* PhysX only for the rest of the steps of the vehicles that may touch the docking station,
  all of them in one shared scene (``contact="shared"``, the default:
  :class:`uwdock.sim.contact_scene.SharedContactScene`, one PhysX step per substep for all),
  or each in its own body's scene (``contact="own"``: the body is given the batch's state,
  stepped by ``VehicleBody``'s own PhysX loop, and read back);
* or no PhysX at all (``contact="kernel"``): the docking station's contact is the tank
  planes' model against its shapes as prisms, in the same kernel call
  (:mod:`uwdock.sim.kernel_contact`; a different contact model from PhysX's).

The state is kept as PhysX keeps it (float32 pose and velocities, written back after every
step). With ``contact="own"`` a vehicle's trajectory here is the one ``VehicleBody.step`` gives
for the same wrenches, in free flight and in contact, to the last bit; with ``"shared"`` it
agrees within stated tolerances (``tests/test_batch_physics.py``: the shared scene offsets
positions and keeps PhysX's contact cache across episodes). What differs from ``N``
``VehicleBody.step`` calls is the cost: the per-vehicle Python work of a step (allocation,
response, state reads and writes) is done once for all vehicles, and with ``"shared"`` PhysX's
per-scene cost of a substep is paid once for all vehicles in contact.

A slot is (re)loaded from its body with :meth:`BatchVehicles.load` after the body was reset by
the scalar code (spawn, randomised vehicle, IMU biases, current): resets are rare and keep
one implementation. The IMU is sampled for all vehicles by :meth:`BatchVehicles.read_imu`.

Frames as in :mod:`uwdock.sim.physics`: state in the SAPIEN z-up world with the body FLU
(entity position, quaternion w x y z, CoM velocity, angular velocity); poses handed out in world
NED / body FRD.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from uwdock.calibration.frames import T_WORLDZUP_WORLDNED
from uwdock.sim.contact_scene import SharedContactScene
from uwdock.sim.fastpath import (
    HYDRO_PARAMS,
    OBSTACLE_COLS,
    PRISM_COLS,
    free_flight_all,
    kernel_flight_all,
)
from uwdock.sim.kernel_contact import StaticPrisms, hull_contact_spheres
from uwdock.sim.physics import FREE_FLIGHT_MARGIN_M, VehicleBody

Contact = Literal["shared", "own", "kernel"]

__all__ = ["BatchImu", "BatchVehicles"]

_S_BODY = np.array([1.0, -1.0, -1.0])  # FRD <-> FLU component signs
_R_ZUP_NED = np.array(T_WORLDZUP_WORLDNED[:3, :3])


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-by-row cross product of (N, 3) arrays (either may be (N, 3) or (3,)): ``np.cross``'s
    arithmetic, bit for bit, without its axis handling (a third of the cost for N = 32)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


@dataclass(frozen=True)
class BatchImu:
    """The navigation sensors of every vehicle at one instant (body FRD, at the origin): the
    fields of :class:`uwdock.sim.vehicle.ImuReading`, each with a leading vehicle axis."""

    specific_force_frd_mps2: np.ndarray  # (N, 3)
    acceleration_frd_mps2: np.ndarray  # (N, 3)
    angular_velocity_frd_radps: np.ndarray  # (N, 3)
    velocity_frd_mps: np.ndarray  # (N, 3)
    depth_m: np.ndarray  # (N,)


def _put_rows(table: np.ndarray, i: int, rows: np.ndarray) -> np.ndarray:
    """``table`` (N, m, cols) with vehicle ``i``'s first rows set to ``rows``, grown (zeros)
    when it holds fewer rows per vehicle."""
    m = rows.shape[0]
    if m > table.shape[1]:
        grown = np.zeros((table.shape[0], m, table.shape[2]))
        grown[:, : table.shape[1]] = table
        table = grown
    table[i, :m] = rows
    return table


def _f32(a: np.ndarray) -> np.ndarray:
    """What PhysX stores of a float64 value (float32), back as float64."""
    return a.astype(np.float32).astype(np.float64)


class BatchVehicles:
    """``N`` vehicles, one per physics scene, stepped together (module docstring).

    Args:
        bodies: one :class:`VehicleBody` per vehicle, each alone (the only dynamic body) in its
            own scene; all with the same substep, thruster count and collision shapes. Call
            :meth:`load` for a slot after resetting its body.
        contact: where the vehicles that may touch the docking station are stepped: one
            shared PhysX scene (``"shared"``), each body's own scene (``"own"``; bit-equal
            to ``VehicleBody.step``, slower), or none: the kernel's own contact model
            (``"kernel"``, :mod:`uwdock.sim.kernel_contact`).
        slot_ids: with ``"shared"``, each vehicle's id in the whole training batch (where it
            sits in the shared scene, the same whichever process holds it); default 0, 1, ...

    Attributes:
        last_physx: (N,) bool, the vehicles the last step sent through PhysX.
        physx_steps: how many vehicle-steps went through PhysX since construction.
    """

    def __init__(
        self,
        bodies: Sequence[VehicleBody],
        contact: Contact = "shared",
        slot_ids: Sequence[int] | None = None,
    ) -> None:
        if not bodies:
            raise ValueError("BatchVehicles: no vehicles")
        if contact not in ("shared", "own", "kernel"):
            raise ValueError(f"contact: 'shared', 'own' or 'kernel', got {contact!r}")
        self.contact_mode = contact
        self.bodies = list(bodies)
        b0 = self.bodies[0]
        n, k = len(self.bodies), b0.thrusters.n
        self.n = n
        self.dt_s = b0.dt_s
        self.hull = np.ascontiguousarray(b0.hull)
        self.spheres, self.planes, _ = b0.plane_params
        for b in self.bodies:
            spheres, planes, _ = b.plane_params
            same = (
                b.dt_s == self.dt_s
                and b.thrusters.n == k
                and b.hull.shape == self.hull.shape
                and np.array_equal(spheres, self.spheres)
                and np.array_equal(planes, self.planes)
            )
            if not same:
                raise ValueError(
                    "BatchVehicles: every body needs the same substep, hull and tank planes"
                )
        self.contact = np.zeros((n, 5))
        self.state = np.zeros((n, 13))
        self._R_cache: tuple[bytes, np.ndarray] | None = None  # (quaternions' bits, R_zup_flu)
        self.P = np.zeros((n, HYDRO_PARAMS))
        self.B = np.zeros((n, 9))
        self.alloc = np.zeros((n, k, 6))  # nominal allocation matrix (thrust = alloc @ wrench)
        self.max_nominal_n = np.ones((n, k))
        self.max_true_n = np.ones((n, k))
        self.decay = np.zeros((n, k))  # per-substep factor of the true thrusters' response
        self.B_T = np.zeros((n, k, 6))  # true thrust -> wrench
        self.thrust_n = np.zeros((n, k))
        self.time_s = np.zeros(n)
        self.cg_m = np.zeros((n, 3))
        self.obstacles = np.zeros((n, 0, OBSTACLE_COLS))
        self.n_obstacles = np.full(n, -1, dtype=np.int64)
        self.current_ned = np.zeros((n, 3))  # the constant currents; None rows: see _varying
        self._varying = np.zeros(n, dtype=bool)
        self.acc_mean_zup = np.zeros((n, 6))
        self.last_physx = np.zeros(n, dtype=bool)
        self.physx_steps = 0
        # the body holds the batch state already (its last step was PhysX's): writing it
        # again would teleport it and lose PhysX's contact cache between the two steps
        self._held = np.zeros(n, dtype=bool)
        # IMU: per-episode biases and the noise levels (ImuConfig), and g
        self.accel_bias = np.zeros((n, 3))
        self.gyro_bias = np.zeros((n, 3))
        self.imu_std = np.zeros((n, 4))  # accel, gyro, velocity, depth noise
        self.gravity_mps2 = np.zeros(n)
        self._powers_key: tuple[float, int] | None = None
        self._powers = np.zeros((n, 0, k))
        self._shared = None
        self._slot_ids = slot_ids
        self._prisms: list[StaticPrisms] = []
        self.prisms = np.zeros((n, 0, PRISM_COLS))
        self.n_prisms = np.zeros(n, dtype=np.int64)
        if contact == "kernel":
            self.kernel_spheres, self.kernel_chunks, self.kernel_shapes = hull_contact_spheres(
                b0.config.collision
            )
            for b in self.bodies:
                if b.config.collision != b0.config.collision:
                    raise ValueError("BatchVehicles: every body needs the same collision shapes")
            self._prisms = [StaticPrisms(b, b.config.friction) for b in self.bodies]
        for i in range(n):
            self.load(i)
        if contact == "shared":
            self._shared = SharedContactScene(self.bodies, slot_ids)
            self._held[:] = False

    # ------------------------------------------------------------------ slots

    def load(self, i: int) -> None:
        """Copy vehicle ``i``'s state, parameters, thrusters, current, IMU biases and obstacles
        from its body (after the scalar code reset it)."""
        b = self.bodies[i]
        self.state[i] = b.state_zup()
        self.P[i], self.B[i] = b.kernel_params
        self.contact[i] = b.plane_params[2]
        self.alloc[i] = b.allocator.allocation_matrix
        self.max_nominal_n[i] = b.allocator.max_thrust_n
        self.max_true_n[i] = b.thrusters.max_thrust_n
        self.decay[i] = b.thrusters.decay(self.dt_s)
        self.B_T[i] = b.thrust_wrench_matrix
        self.thrust_n[i] = b.thrust_n
        self.time_s[i] = b.time_s
        self.cg_m[i] = b.config.cg_m
        self._varying[i] = not b.current.is_constant
        self.current_ned[i] = b.current.mean_ned
        self.acc_mean_zup[i] = b.acc_mean_zup
        if self._shared is not None:
            self._shared.load(i)
        # the body holding the state PhysX steps: its own (own), or a twin placed at its start
        self._held[i] = self._shared is None
        self._powers_key = None
        if self._prisms:
            self._prisms[i].hull_friction = float(b.config.friction)
            rows = self._prisms[i].rows()
            self.prisms = _put_rows(self.prisms, i, rows)
            self.n_prisms[i] = rows.shape[0]
        boxes = b.obstacle_boxes()
        if boxes is None:
            self.n_obstacles[i] = -1
        else:
            self.obstacles = _put_rows(self.obstacles, i, boxes)
            self.n_obstacles[i] = boxes.shape[0]
        imu = b.imu
        self.accel_bias[i] = imu.accel_bias
        self.gyro_bias[i] = imu.gyro_bias
        c = imu.config
        self.imu_std[i] = (
            c.accel_noise_std_mps2,
            c.gyro_noise_std_radps,
            c.velocity_noise_std_mps,
            c.depth_noise_std_m,
        )
        self.gravity_mps2[i] = imu.gravity_mps2

    def fresh_contact_scene(self) -> None:
        """With ``contact="shared"``, replace the shared PhysX scene by a new one built from
        the bodies as they are now (no contact state, no history), as a per-env world's reset
        does for its own scene; e.g. after resetting every slot."""
        if self._shared is None:
            return
        self._shared = SharedContactScene(self.bodies, self._slot_ids)
        self._held[:] = False

    def store(self, i: int) -> None:
        """Write vehicle ``i``'s batch state into its PhysX body (pose and velocities), e.g.
        before the scalar code reads or renders it."""
        self.bodies[i].set_state_zup(self.state[i], self.thrust_n[i], self.time_s[i])
        if self._shared is None:
            self._held[i] = True

    # ------------------------------------------------------------------ stepping

    def _decay_powers(self, n_sub: int) -> np.ndarray:
        key = (self.dt_s, n_sub)
        if self._powers_key != key:
            k = np.arange(1, n_sub + 1, dtype=float)[None, :, None]
            self._powers = self.decay[:, None, :] ** k  # (N, n_sub, k)
            self._powers_key = key
        return self._powers

    def step(self, wrench_frd: np.ndarray, duration_s: float) -> None:
        """One control step of every vehicle: the body wrench (N, 6) [N, N m, FRD about the
        origin] allocated by the nominal thrusters, produced by the true ones, held for
        ``duration_s`` (a multiple of the substep), as :meth:`VehicleBody.step` does."""
        wrench = np.asarray(wrench_frd, dtype=np.float64)
        if wrench.shape != (self.n, 6):
            raise ValueError(f"wrench_frd: expected shape ({self.n}, 6), got {wrench.shape}")
        n_sub = self.bodies[0].substeps(duration_s)
        dt = self.dt_s
        # allocation (nominal vehicle): weighted least squares, one common saturation factor
        thrust = np.einsum("nkj,nj->nk", self.alloc, wrench)
        ratio = np.max(np.abs(thrust) / self.max_nominal_n, axis=1, keepdims=True)
        thrust = np.where(ratio > 1.0, thrust / np.maximum(ratio, 1e-300), thrust)
        setpoint = np.sign(thrust) * np.sqrt(np.minimum(np.abs(thrust) / self.max_nominal_n, 1.0))
        # the true thrusters: command, then the exact first-order response per substep
        s = np.clip(setpoint, -1.0, 1.0)
        cmd = self.max_true_n * s * np.abs(s)
        response = cmd[:, None, :] + (self.thrust_n - cmd)[:, None, :] * self._decay_powers(n_sub)
        wrenches = np.ascontiguousarray(np.einsum("nsk,nkj->nsj", response, self.B_T))
        currents = np.ascontiguousarray(self._currents_zup(n_sub))
        v0 = self.state[:, 7:13].copy()
        acc = np.zeros((self.n, 6))
        if self.contact_mode == "kernel":
            kernel_flight_all(
                self.P, self.B, self.state, wrenches, currents, dt, acc, self.spheres,
                self.planes, self.contact, self.kernel_spheres, self.kernel_chunks,
                self.kernel_shapes, self.prisms, self.n_prisms,
            )  # fmt: skip
            self.state[:] = _f32(self.state)  # kept as PhysX keeps a state, as the others
            self._held[:] = False
            self.last_physx = np.zeros(self.n, dtype=bool)
        else:
            self._flight_then_physx(wrenches, currents, acc, n_sub)
        self.physx_steps += int(self.last_physx.sum())
        self.thrust_n = response[:, -1, :].copy()
        self.time_s = self.time_s + n_sub * dt
        self.acc_mean_zup = (self.state[:, 7:13] - v0) / (n_sub * dt)

    def _flight_then_physx(
        self, wrenches: np.ndarray, currents: np.ndarray, acc: np.ndarray, n_sub: int
    ) -> None:
        """The PhysX contact modes' step: the kernel's free flight as far as no contact is
        possible, then PhysX for the rest of the vehicles that may touch the station."""
        done = free_flight_all(
            self.P, self.B, self.state, wrenches, currents, self.dt_s,
            self.hull, self.obstacles, self.n_obstacles, FREE_FLIGHT_MARGIN_M, acc,
            self.spheres, self.planes, self.contact,
        )  # fmt: skip
        moved = done > 0
        self.state[moved] = _f32(self.state[moved])  # what PhysX keeps of it
        self._held[moved] = False
        self.last_physx = done < n_sub
        physx = np.flatnonzero(self.last_physx)
        if self._shared is not None and len(physx):
            self._shared.step(
                physx, done[physx], self._held, self.state, self.P, self.B, self.contact,
                wrenches, currents, self.spheres, self.planes,
            )  # fmt: skip
            self._held[physx] = True
        elif self._shared is None:
            for i in physx:
                k = int(done[i])  # PhysX from the first substep that may touch
                self._physx_step(i, wrenches[i, k:], currents[i, k:])

    def _currents_zup(self, n_sub: int) -> np.ndarray:
        """(N, n_sub, 3) water velocity at the step's substeps, z-up world."""
        out = np.broadcast_to((self.current_ned @ _R_ZUP_NED.T)[:, None, :], (self.n, n_sub, 3))
        if not self._varying.any():
            return out
        out = out.copy()
        for i in np.flatnonzero(self._varying):
            times = self.time_s[i] + self.dt_s * np.arange(n_sub)
            out[i] = self.bodies[i].current.velocity_ned_at(times) @ _R_ZUP_NED.T
        return out

    def _physx_step(self, i: int, wrenches: np.ndarray, currents: np.ndarray) -> None:
        """Vehicle ``i``'s step through PhysX (its body's own loop), state read back."""
        if not self._held[i]:
            self.store(i)
        b = self.bodies[i]
        b.run_physx(wrenches, currents)
        self.state[i] = b.state_zup()

    # ------------------------------------------------------------------ reading

    def R_zup_flu(self) -> np.ndarray:
        """(N, 3, 3) attitude of body FLU in the z-up world."""
        key = self.state[:, 3:7].tobytes()
        cached = self._R_cache
        if cached is not None and cached[0] == key:  # the same bits: a step reads it 5 times
            return cached[1].copy()
        R = self._R_of(self.state[:, 3:7])
        self._R_cache = (key, R)
        return R.copy()

    def _R_of(self, q: np.ndarray) -> np.ndarray:
        """(N, 3, 3) the rotations of quaternions ``q`` (N, 4) (w, x, y, z), normalised."""
        w, x, y, z = (q[:, j] for j in range(4))
        # the quaternion as SAPIEN returns it (float32, unit to its precision): normalise
        inv = 1.0 / np.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w * inv, x * inv, y * inv, z * inv
        R = np.empty((self.n, 3, 3))
        R[:, 0, 0] = 1 - 2 * (y * y + z * z)
        R[:, 0, 1] = 2 * (x * y - w * z)
        R[:, 0, 2] = 2 * (x * z + w * y)
        R[:, 1, 0] = 2 * (x * y + w * z)
        R[:, 1, 1] = 1 - 2 * (x * x + z * z)
        R[:, 1, 2] = 2 * (y * z - w * x)
        R[:, 2, 0] = 2 * (x * z - w * y)
        R[:, 2, 1] = 2 * (y * z + w * x)
        R[:, 2, 2] = 1 - 2 * (x * x + y * y)
        return R

    def T_world_body(self) -> np.ndarray:
        """(N, 4, 4) pose of body FRD in world NED."""
        T = np.zeros((self.n, 4, 4))
        T[:, :3, :3] = self.R_zup_flu()
        T[:, :3, 3] = self.state[:, :3]
        T[:, 3, 3] = 1.0
        # T_ned_frd = F T_zup_flu F, F = diag(1, -1, -1, 1)
        T[:, 1:3, :] *= -1.0
        T[:, :, 1:3] *= -1.0
        return T

    def _body(self, R_t: np.ndarray, v_zup: np.ndarray) -> np.ndarray:
        """World z-up vectors (N, 3) in body FRD."""
        return np.einsum("nij,nj->ni", R_t, v_zup) * _S_BODY

    def nu(self) -> np.ndarray:
        """(N, 6) body velocity [u, v, w, p, q, r] of the origin, FRD (m/s, rad/s)."""
        R_t = np.swapaxes(self.R_zup_flu(), 1, 2)
        w = self._body(R_t, self.state[:, 10:13])
        v_cg = self._body(R_t, self.state[:, 7:10])
        return np.concatenate([v_cg - _cross_rows(w, self.cg_m), w], axis=1)

    def nu_dot_mean(self) -> np.ndarray:
        """(N, 6) acceleration of the origin and angular acceleration over the last control
        step, body FRD (:attr:`VehicleBody.nu_dot_mean`)."""
        R_t = np.swapaxes(self.R_zup_flu(), 1, 2)
        a_cg = self._body(R_t, self.acc_mean_zup[:, :3])
        alpha = self._body(R_t, self.acc_mean_zup[:, 3:])
        w = self._body(R_t, self.state[:, 10:13])
        c = self.cg_m
        a_o = a_cg - _cross_rows(alpha, c) - _cross_rows(w, _cross_rows(w, c))
        return np.concatenate([a_o, alpha], axis=1)

    def read_imu(self, normals: np.ndarray) -> BatchImu:
        """Sample every vehicle's navigation sensors now (:meth:`uwdock.sim.vehicle.Imu.measure`
        for all), the noise made of ``normals`` (N, 10) standard normal draws (accelerometer 3,
        gyro 3, velocity 3, depth 1)."""
        T = self.T_world_body()
        R = T[:, :3, :3]
        nu = self.nu()
        g_body = R[:, 2, :] * self.gravity_mps2[:, None]  # R^T (0, 0, g)
        noise = np.asarray(normals, dtype=np.float64)
        if noise.shape != (self.n, 10):
            raise ValueError(f"normals: expected shape ({self.n}, 10), got {noise.shape}")
        s = self.imu_std
        acc = self.nu_dot_mean()[:, :3] + self.accel_bias + s[:, 0:1] * noise[:, 0:3]
        return BatchImu(
            specific_force_frd_mps2=acc - g_body,
            acceleration_frd_mps2=acc,
            angular_velocity_frd_radps=nu[:, 3:] + self.gyro_bias + s[:, 1:2] * noise[:, 3:6],
            velocity_frd_mps=nu[:, :3] + s[:, 2:3] * noise[:, 6:9],
            depth_m=T[:, 2, 3] + s[:, 3] * noise[:, 9],
        )
