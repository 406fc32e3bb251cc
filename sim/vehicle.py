"""Girona AUV model: parameters, per-episode randomisation, hydrodynamics, ocean current, IMU.

Marine convention throughout (Fossen): world ``world_ned`` (x north, y east, z down), body
``body_frd`` (x forward, y starboard, z down), body velocity ``nu = [u, v, w, p, q, r]`` of the
body origin in FRD (m/s, rad/s), generalised forces ``tau = [X, Y, Z, K, M, N]`` about the
origin (N, N m). SAPIEN's z-up world and FLU actor appear only in ``sim.physics``. NumPy; the
compiled scalar twin of the model used by the 300 Hz loop lives in ``sim.fastpath``.

Equations of motion (Fossen 2011, irrotational current ``v_c`` constant in NED)::

    (M_RB + M_A) nu_dot + C_RB(nu) nu + C_A(nu_r) nu_r + D(nu_r) nu_r + g(R) = tau + M_A nu_c_dot
    nu_r = nu - nu_c,   nu_c = [R^T v_c, 0, 0, 0],   nu_c_dot = [-omega x R^T v_c, 0, 0, 0]

with ``M_RB`` the rigid body (mass at the CG ``r_g``), ``M_A`` the diagonal added mass about the
origin, ``D(nu_r) = diag(linear) + diag(quadratic) |nu_r|`` and ``g`` the weight (``m g`` at
``r_g``) and buoyancy (``B`` at ``r_b``). :class:`Hydrodynamics` evaluates the right-hand side
and returns ``nu_dot``; ``sim.physics`` hands that acceleration to PhysX (see its docstring for
why this keeps added mass exact and stable at 300 Hz). The time derivative of a slowly varying
current (below 1e-3 m/s^2 for the default drift) is not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Annotated, Literal

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.frames import check_R
from uwdock.dockcore.config import check_fields
from uwdock.dockcore.domains import Interval
from uwdock.sim.domains import BodyCoord_m, Friction, RelativeRange, validate_each
from uwdock.sim.thrusters import ThrusterArrayConfig, ThrusterRandomisation

__all__ = [
    "CollisionShape",
    "Current",
    "CurrentConfig",
    "Hydrodynamics",
    "Imu",
    "ImuConfig",
    "ImuReading",
    "VehicleConfig",
    "VehicleRandomisation",
]

#: A point in body FRD (m).
_BodyPoint = tuple[BodyCoord_m, BodyCoord_m, BodyCoord_m]
#: A half-extent or radius of a hull shape (m).
_ShapeSize = Annotated[float, Interval(ge=0, le=10)]
#: A moment of inertia (kg m^2).
_Inertia = Annotated[float, Interval(ge=0.01, le=1e5)]
#: A diagonal added-mass or damping coefficient (kg, kg m^2, N s/m, N m s/rad, ...).
_Coefficient = Annotated[float, Interval(ge=0, le=1e5)]
_Coefficients6 = tuple[
    _Coefficient, _Coefficient, _Coefficient, _Coefficient, _Coefficient, _Coefficient
]
#: A water velocity component (m/s); the fastest tidal races run at about 5 m/s.
_CurrentSpeed = Annotated[float, Interval(ge=-10, le=10)]
_CurrentRange = tuple[_CurrentSpeed, _CurrentSpeed]


def _skew(a: np.ndarray) -> np.ndarray:
    """(3, 3) matrix S(a) with S(a) @ b = a x b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


@dataclass(frozen=True)
class CollisionShape:
    """A primitive collision shape of the hull, in body FRD.

    Attributes:
        kind: "box" or "capsule".
        center_m: (3,) shape centre in body FRD (m).
        size_m: box: (3,) half-extents along body x, y, z (m); capsule: (radius, half-length of
            the cylindrical part, unused) (m).
        axis: capsule axis, "x", "y" or "z" (ignored for boxes).
    """

    kind: Literal["box", "capsule"]
    center_m: _BodyPoint
    size_m: tuple[_ShapeSize, _ShapeSize, _ShapeSize]
    axis: Literal["x", "y", "z"] = "x"

    def validate(self) -> None:
        """Raise ValueError on non-positive sizes."""
        n = 3 if self.kind == "box" else 2
        if not all(v > 0 for v in self.size_m[:n]):  # also NaN
            raise ValueError(f"size_m: the first {n} values must be > 0, got {self.size_m}")


#: Three hulls (bottom, port top, starboard top), two frame plates and the four docking pegs
#: (D 40 mm at x = +-0.42 m, |y| = 0.52..0.62 m, 0.195 m above the origin). Overall about
#: 1.5 x 1.0 x 0.9 m; the camera (0.45 m below the origin) sits at the bottom hull's skin.
DEFAULT_COLLISION: tuple[CollisionShape, ...] = (
    CollisionShape("capsule", (0.0, 0.0, 0.30), (0.15, 0.60, 0.0), "x"),
    CollisionShape("capsule", (0.0, -0.32, -0.30), (0.13, 0.58, 0.0), "x"),
    CollisionShape("capsule", (0.0, 0.32, -0.30), (0.13, 0.58, 0.0), "x"),
    CollisionShape("box", (0.42, 0.0, 0.0), (0.02, 0.45, 0.25), "x"),
    CollisionShape("box", (-0.42, 0.0, 0.0), (0.02, 0.45, 0.25), "x"),
    *(
        CollisionShape("capsule", (x, s * 0.57, -0.195), (0.02, 0.05, 0.0), "y")
        for x in (0.42, -0.42)
        for s in (-1.0, 1.0)
    ),
)


@dataclass(frozen=True)
class ImuConfig:
    """Navigation sensors: IMU, DVL-like velocity and depth, all at the body origin.

    Attributes:
        accel_noise_std_mps2: white noise on each accelerometer axis per sample (m/s^2).
        accel_bias_std_mps2: per-episode constant accelerometer bias, std per axis (m/s^2).
        gyro_noise_std_radps: white noise on each gyro axis per sample (rad/s).
        gyro_bias_std_radps: per-episode constant gyro bias, std per axis (rad/s).
        velocity_noise_std_mps: white noise on the body velocity (DVL) per axis (m/s).
        depth_noise_std_m: white noise on the depth (m).
    """

    accel_noise_std_mps2: Annotated[float, Interval(ge=0, le=10)] = 0.05
    accel_bias_std_mps2: Annotated[float, Interval(ge=0, le=10)] = 0.02
    gyro_noise_std_radps: Annotated[float, Interval(ge=0, le=1)] = 0.002
    gyro_bias_std_radps: Annotated[float, Interval(ge=0, le=1)] = 0.0005
    velocity_noise_std_mps: Annotated[float, Interval(ge=0, le=1)] = 0.01
    depth_noise_std_m: Annotated[float, Interval(ge=0, le=5)] = 0.02

    def validate(self) -> None:
        """Raise ValueError on a negative standard deviation."""
        if not all(v >= 0 for v in vars(self).values()):  # also NaN
            raise ValueError("imu noise standard deviations must be >= 0")


@dataclass(frozen=True)
class VehicleConfig:
    """Rigid body, hydrodynamic and actuator parameters of the Girona AUV (body FRD, origin O).

    Sources (docs/reference-system.md section 3): mass ~150 kg, CG ~0.11 m below and CB
    ~0.18 m above the origin, ~+3 kg net buoyancy; damping, translational added mass and
    thruster lag from the published G500 dynamics file. Inertia and rotational added mass are
    our estimates from a three-hull mass model (not published); all of it is randomised per
    episode.

    Attributes:
        mass_kg: dry rigid-body mass m (kg); the weight m*g acts at ``cg_m``.
        inertia_kgm2: (3,) principal moments of inertia about the CG, body axes (kg m^2).
        cg_m: (3,) centre of gravity in body FRD (m); +z is below the origin.
        cb_m: (3,) centre of buoyancy in body FRD (m); -z is above the origin.
        net_buoyancy_kg: buoyancy minus weight as an equivalent mass (kg); buoyancy force
            B = (mass_kg + net_buoyancy_kg) * g. Positive floats up.
        added_mass: (6,) diagonal added mass about the origin [X_udot, Y_vdot, Z_wdot (kg),
            K_pdot, M_qdot, N_rdot (kg m^2)], as positive magnitudes.
        linear_damping: (6,) linear damping (N s/m; N m s/rad), positive.
        quadratic_damping: (6,) quadratic damping (N s^2/m^2; N m s^2/rad^2), positive.
        gravity_mps2: gravitational acceleration g (m/s^2).
        surface_band_m: the free surface (m): buoyancy fades linearly from all to none as the
            centre of buoyancy rises through a band of this height centred on the water
            surface (the hull above water displaces nothing), so a positively buoyant vehicle
            floats at the surface with part of its top hulls out, as a surfaced Girona does.
            The default is the top hulls' diameter (they carry the buoyancy: section 3 of
            docs/reference-system.md). 0: buoyancy never fades (the model before, whose tank
            needs a lid to keep the vehicle in the water).
        collision: primitive collision shapes (body FRD) for PhysX contacts.
        friction: static = dynamic friction coefficient of the hull (-).
        thrusters: thruster geometry, limits, lags and allocation weights.
        imu: navigation sensor noise.
    """

    mass_kg: Annotated[float, Interval(ge=1, le=1e4)] = 150.0
    inertia_kgm2: tuple[_Inertia, _Inertia, _Inertia] = (14.0, 25.0, 22.0)
    cg_m: _BodyPoint = (0.0, 0.0, 0.11)
    cb_m: _BodyPoint = (0.0, 0.0, -0.18)
    net_buoyancy_kg: Annotated[float, Interval(ge=-1e4, le=1e4)] = 3.0
    added_mass: _Coefficients6 = (49.0, 49.0, 49.0, 4.0, 8.0, 6.0)
    linear_damping: _Coefficients6 = (20.0, 20.0, 20.0, 130.0, 130.0, 130.0)
    quadratic_damping: _Coefficients6 = (148.0, 148.0, 148.0, 180.0, 180.0, 180.0)
    gravity_mps2: Annotated[float, Interval(gt=0, le=100)] = 9.81
    surface_band_m: Annotated[float, Interval(ge=0, le=10)] = 0.26
    collision: tuple[CollisionShape, ...] = DEFAULT_COLLISION
    friction: Friction = 0.3
    thrusters: ThrusterArrayConfig = field(default_factory=ThrusterArrayConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)

    def validate(self) -> None:
        """Raise ValueError naming the first field outside its declared domain (NaN included;
        :class:`Hydrodynamics` calls it on configs built in Python), negative buoyancy or a bad
        collision shape."""
        check_fields(self)
        if not self.mass_kg + self.net_buoyancy_kg >= 0:
            raise ValueError("net_buoyancy_kg: buoyancy must be >= 0")
        if not 1 <= len(self.collision) <= 64:
            raise ValueError(f"collision: 1 to 64 shapes, got {len(self.collision)}")
        validate_each("collision", self.collision)

    @property
    def weight_n(self) -> float:
        """Weight m*g (N)."""
        return self.mass_kg * self.gravity_mps2

    @property
    def buoyancy_n(self) -> float:
        """Buoyancy force (m + net_buoyancy_kg) * g (N)."""
        return (self.mass_kg + self.net_buoyancy_kg) * self.gravity_mps2


def _scaled(values: tuple[float, ...], rel: float, rng: np.random.Generator) -> tuple[float, ...]:
    """Each value times 1 + U(-rel, rel)."""
    return tuple(float(v) * (1.0 + rng.uniform(-rel, rel)) for v in values)


def _shifted(values: tuple[float, ...], amp: float, rng: np.random.Generator) -> tuple[float, ...]:
    """Each value plus U(-amp, amp)."""
    return tuple(float(v) + rng.uniform(-amp, amp) for v in values)


@dataclass(frozen=True)
class VehicleRandomisation:
    """Per-episode domain randomisation of :class:`VehicleConfig` (uniform draws; zeros = off).

    Attributes:
        mass_rel: mass scaled by 1 + U(-mass_rel, mass_rel) (-).
        inertia_rel: each principal inertia scaled likewise (-).
        added_mass_rel: each added-mass term scaled likewise (-).
        damping_rel: each linear and quadratic damping term scaled likewise (-).
        cg_offset_m: each CG coordinate shifted by U(-cg_offset_m, cg_offset_m) (m).
        cb_offset_m: each CB coordinate shifted likewise (m).
        net_buoyancy_kg: net buoyancy shifted by U(-net_buoyancy_kg, net_buoyancy_kg) (kg).
        thrusters: thruster placement, axis, limit and lag perturbation.
    """

    mass_rel: RelativeRange = 0.05
    inertia_rel: RelativeRange = 0.15
    added_mass_rel: RelativeRange = 0.25
    damping_rel: RelativeRange = 0.25
    cg_offset_m: Annotated[float, Interval(ge=0, le=1)] = 0.01
    cb_offset_m: Annotated[float, Interval(ge=0, le=1)] = 0.01
    net_buoyancy_kg: Annotated[float, Interval(ge=0, le=1e3)] = 2.0
    thrusters: ThrusterRandomisation = field(default_factory=ThrusterRandomisation)

    def validate(self) -> None:
        """Raise ValueError on a negative range or a relative range >= 1."""
        rels = (self.mass_rel, self.inertia_rel, self.added_mass_rel, self.damping_rel)
        if not all(0 <= r < 1 for r in rels):  # also NaN
            raise ValueError("relative randomisation ranges must lie in [0, 1)")
        if not all(v >= 0 for v in (self.cg_offset_m, self.cb_offset_m, self.net_buoyancy_kg)):
            raise ValueError("randomisation offsets must be >= 0")

    def sample(self, base: VehicleConfig, rng: np.random.Generator) -> VehicleConfig:
        """Draw one vehicle: ``base`` with every randomised parameter perturbed.

        The net buoyancy is kept >= ``-mass_kg`` (buoyancy >= 0), so any draw is a valid
        vehicle whatever the ranges."""
        mass_kg = base.mass_kg * (1.0 + rng.uniform(-self.mass_rel, self.mass_rel))
        return replace(
            base,
            mass_kg=mass_kg,
            inertia_kgm2=_scaled(base.inertia_kgm2, self.inertia_rel, rng),
            added_mass=_scaled(base.added_mass, self.added_mass_rel, rng),
            linear_damping=_scaled(base.linear_damping, self.damping_rel, rng),
            quadratic_damping=_scaled(base.quadratic_damping, self.damping_rel, rng),
            cg_m=_shifted(base.cg_m, self.cg_offset_m, rng),
            cb_m=_shifted(base.cb_m, self.cb_offset_m, rng),
            net_buoyancy_kg=max(
                base.net_buoyancy_kg + rng.uniform(-self.net_buoyancy_kg, self.net_buoyancy_kg),
                -mass_kg,
            ),
            thrusters=self.thrusters.sample(base.thrusters, rng),
        )


# --------------------------------------------------------------------------- hydrodynamics


class Hydrodynamics:
    """Fossen rigid-body + hydrodynamic model of one vehicle (body FRD, moments about O).

    The component methods (NumPy, readable) document the model and serve as the reference;
    :func:`sim.fastpath.accel_fn` gives the same ``nu_dot`` from the compiled scalar kernel that
    the 300 Hz loop runs (numba), where NumPy's per-call overhead on 3-vectors would dominate
    (tested equal).

    Attributes:
        config: the vehicle parameters.
        M: (6, 6) generalised mass ``M_RB + M_A`` about the origin.
        M_inv: (6, 6) its inverse.
    """

    def __init__(self, config: VehicleConfig) -> None:
        config.validate()
        self.config = config
        m = config.mass_kg
        self._rg = np.asarray(config.cg_m, dtype=float)
        self._rb = np.asarray(config.cb_m, dtype=float)
        S = _skew(self._rg)
        self.I_O = np.diag(config.inertia_kgm2) - m * S @ S  # parallel-axis theorem
        M_RB = np.block([[m * np.eye(3), -m * S], [m * S, self.I_O]])
        self.M_A = np.diag(np.asarray(config.added_mass, dtype=float))
        self.M = M_RB + self.M_A
        self.M_inv = np.linalg.inv(self.M)
        self._dl = np.asarray(config.linear_damping, dtype=float)
        self._dq = np.asarray(config.quadratic_damping, dtype=float)

    def stable_substep_s(self) -> float:
        """Longest integration substep (s) for which the linear damping stays stable.

        The damping force is evaluated from the current velocity (semi-implicit Euler), which
        is stable on axis i while ``dt * linear_damping[i] / M[i, i] < 2`` (``M[i, i]``: rigid
        plus added mass or inertia about the origin); a longer substep makes the velocity
        oscillate with growing amplitude until it overflows. ``inf`` without damping.
        """
        with np.errstate(divide="ignore"):
            return float(np.min(2.0 * np.diag(self.M) / self._dl))

    # ----------------------------------------------------------------- reference (NumPy)

    def submerged_fraction(self, depth_cb_m: float) -> float:
        """Fraction (0-1) of the buoyancy acting when the centre of buoyancy is ``depth_cb_m``
        below the surface (NED z, m; ``VehicleConfig.surface_band_m``)."""
        band = self.config.surface_band_m
        if band <= 0 or depth_cb_m >= 0.5 * band:
            return 1.0
        return min(1.0, max(0.0, 0.5 + depth_cb_m / band))

    def restoring_wrench(self, R_ned_body: ArrayLike, depth_cb_m: float = math.inf) -> np.ndarray:
        """Weight at the CG plus buoyancy at the CB, as a body wrench (6,) about O (N, N m),
        with the CB ``depth_cb_m`` below the surface (default: deep, all buoyancy).

        This is ``-g(R)`` in Fossen's notation (the force acting on the vehicle).
        """
        down = np.asarray(R_ned_body, dtype=float)[2, :]  # NED +z in body coordinates
        f_w = self.config.weight_n * down
        f_b = -self.config.buoyancy_n * self.submerged_fraction(depth_cb_m) * down
        return np.concatenate([f_w + f_b, np.cross(self._rg, f_w) + np.cross(self._rb, f_b)])

    def damping_wrench(self, nu_r: ArrayLike) -> np.ndarray:
        """Linear + quadratic damping force (6,) acting on the vehicle: ``-D(nu_r) nu_r``."""
        nu_r = np.asarray(nu_r, dtype=float)
        return -(self._dl + self._dq * np.abs(nu_r)) * nu_r

    def added_mass_coriolis_wrench(self, nu_r: ArrayLike) -> np.ndarray:
        """Added-mass Coriolis/centripetal force (6,) acting on the vehicle: ``-C_A(nu_r) nu_r``.

        With ``p1 = M_A11 v_r`` and ``p2 = M_A22 omega``: ``C_A nu_r = [omega x p1,
        v_r x p1 + omega x p2]`` (the second part holds the Munk moment).
        """
        nu_r = np.asarray(nu_r, dtype=float)
        p1 = self.M_A.diagonal()[:3] * nu_r[:3]
        p2 = self.M_A.diagonal()[3:] * nu_r[3:]
        w = nu_r[3:]
        return -np.concatenate([np.cross(w, p1), np.cross(nu_r[:3], p1) + np.cross(w, p2)])

    def rigid_body_coriolis_wrench(self, nu: ArrayLike) -> np.ndarray:
        """Rigid-body Coriolis/centripetal force (6,): ``-C_RB(nu) nu`` about the origin."""
        nu = np.asarray(nu, dtype=float)
        v, w = nu[:3], nu[3:]
        m = self.config.mass_kg
        f = m * (np.cross(w, v) + np.cross(w, np.cross(w, self._rg)))
        mo = m * np.cross(self._rg, np.cross(w, v)) + np.cross(w, self.I_O @ w)
        return -np.concatenate([f, mo])

    def acceleration(
        self,
        R_ned_body: ArrayLike,
        nu: ArrayLike,
        v_current_ned: ArrayLike,
        tau: ArrayLike,
        depth_cb_m: float = math.inf,
    ) -> np.ndarray:
        """Body acceleration ``nu_dot`` (6,) (m/s^2, rad/s^2) from the full model.

        Args:
            R_ned_body: (3, 3) attitude ``R_ned_frd``.
            nu: (6,) body velocity [u, v, w, p, q, r] (m/s, rad/s), FRD.
            v_current_ned: (3,) water velocity in NED (m/s).
            tau: (6,) applied wrench (thrusters, N, N m about O), FRD.
            depth_cb_m: depth of the centre of buoyancy below the surface (m; the free
                surface, :meth:`submerged_fraction`); default deep.
        """
        R = check_R(R_ned_body, "R_ned_body")
        nu = np.asarray(nu, dtype=float)
        v_c = R.T @ np.asarray(v_current_ned, dtype=float)
        nu_r = nu - np.concatenate([v_c, np.zeros(3)])
        nu_c_dot = np.concatenate([-np.cross(nu[3:], v_c), np.zeros(3)])
        rhs = (
            np.asarray(tau, dtype=float)
            + self.restoring_wrench(R, depth_cb_m)
            + self.damping_wrench(nu_r)
            + self.added_mass_coriolis_wrench(nu_r)
            + self.rigid_body_coriolis_wrench(nu)
            + self.M_A @ nu_c_dot
        )
        return self.M_inv @ rhs


# --------------------------------------------------------------------------- ocean current


@dataclass(frozen=True)
class CurrentConfig:
    """Ocean current (water velocity in world NED), drawn per episode.

    Attributes:
        mode: "constant" (``velocity_ned_mps``), "random" (uniform per episode in the ranges)
            or "varying" (random start, then an Ornstein-Uhlenbeck drift around it).
        velocity_ned_mps: (3,) current for mode "constant" (m/s, NED).
        range_x_mps: (lo, hi) uniform range of the north component (m/s).
        range_y_mps: (lo, hi) uniform range of the east component (m/s).
        range_z_mps: (lo, hi) uniform range of the down component (m/s).
        drift_std_mps: stationary std of the drift about the episode's draw, per axis (m/s).
        drift_time_constant_s: correlation time of the drift (s).
        drift_knot_interval_s: the drift is sampled every this many seconds and linearly
            interpolated between samples, so the velocity is continuous (s).
        max_speed_mps: the drifting current's speed is capped here (m/s).
    """

    mode: Literal["constant", "random", "varying"] = "random"
    velocity_ned_mps: tuple[_CurrentSpeed, _CurrentSpeed, _CurrentSpeed] = (0.0, 0.0, 0.0)
    range_x_mps: _CurrentRange = (-0.2, 0.2)
    range_y_mps: _CurrentRange = (-0.2, 0.2)
    range_z_mps: _CurrentRange = (0.0, 0.0)
    drift_std_mps: Annotated[float, Interval(ge=0, le=10)] = 0.05
    drift_time_constant_s: Annotated[float, Interval(gt=0, le=1e6)] = 30.0
    drift_knot_interval_s: Annotated[float, Interval(ge=0.01, le=3600)] = 1.0
    max_speed_mps: Annotated[float, Interval(gt=0, le=20)] = 0.5

    def validate(self) -> None:
        """Raise ValueError on a field outside its declared domain (NaN included) or an
        inverted range."""
        check_fields(self)
        for name in ("range_x_mps", "range_y_mps", "range_z_mps"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"{name}: lo must be <= hi, got ({lo}, {hi})")


class Current:
    """One episode's current: ``velocity_ned(t_s)`` (m/s, NED), deterministic given the seed.

    Args:
        config: the current model.
        rng: generator used to draw this episode (the drift gets its own child generator so
            its samples do not depend on when they are queried).
    """

    def __init__(self, config: CurrentConfig | None = None, rng: np.random.Generator | None = None):
        self.config = config if config is not None else CurrentConfig()
        self.config.validate()
        self.reset(rng if rng is not None else np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        """Draw a new episode's current."""
        c = self.config
        if c.mode == "constant":
            self.mean_ned = np.asarray(c.velocity_ned_mps, dtype=float)
        else:
            lo, hi = np.array([c.range_x_mps, c.range_y_mps, c.range_z_mps], dtype=float).T
            self.mean_ned = rng.uniform(lo, hi)
        self._drift_rng = np.random.default_rng(int(rng.integers(2**63)))
        self._knots = [self.mean_ned.copy()]

    @property
    def is_constant(self) -> bool:
        """True unless the mode is "varying"."""
        return self.config.mode != "varying"

    def _extend_knots(self, k_max: int) -> None:
        c = self.config
        phi = math.exp(-c.drift_knot_interval_s / c.drift_time_constant_s)
        sig = c.drift_std_mps * math.sqrt(1.0 - phi * phi)
        while len(self._knots) <= k_max:
            x = self.mean_ned + (self._knots[-1] - self.mean_ned) * phi
            x = x + sig * self._drift_rng.standard_normal(3)
            speed = float(np.linalg.norm(x))
            if speed > c.max_speed_mps:
                x = x * (c.max_speed_mps / speed)
            self._knots.append(x)

    def velocity_ned_at(self, t_s: ArrayLike) -> np.ndarray:
        """Current at times ``t_s`` (k,) (s, >= 0): (k, 3) m/s in NED."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if self.is_constant:
            return np.broadcast_to(self.mean_ned, (t.size, 3)).copy()
        s = np.maximum(t, 0.0) / self.config.drift_knot_interval_s
        k0 = np.floor(s).astype(int)
        self._extend_knots(int(k0.max()) + 1)
        knots = np.asarray(self._knots)
        f = (s - k0)[:, None]
        return knots[k0] * (1.0 - f) + knots[k0 + 1] * f

    def velocity_ned(self, t_s: float) -> np.ndarray:
        """Current at time ``t_s`` (s): (3,) m/s in NED."""
        return self.velocity_ned_at([t_s])[0]


# --------------------------------------------------------------------------- IMU


@dataclass(frozen=True)
class ImuReading:
    """One navigation-sensor sample (body FRD, at the origin).

    Attributes:
        specific_force_frd_mps2: (3,) accelerometer output ``R^T (a - g)``: a level vehicle at
            rest reads (0, 0, -g) (m/s^2).
        acceleration_frd_mps2: (3,) the same measurement with gravity removed using the true
            attitude, i.e. the kinematic acceleration plus noise and bias (m/s^2).
        angular_velocity_frd_radps: (3,) gyro output (rad/s).
        velocity_frd_mps: (3,) body velocity over ground, DVL-like (m/s).
        depth_m: NED z of the origin below the world origin (the surface) (m).
    """

    specific_force_frd_mps2: np.ndarray
    acceleration_frd_mps2: np.ndarray
    angular_velocity_frd_radps: np.ndarray
    velocity_frd_mps: np.ndarray
    depth_m: float


class Imu:
    """Noisy navigation sensors with per-episode constant biases.

    Args:
        config: noise and bias levels.
        gravity_mps2: g used for the specific force (m/s^2).
        rng: generator for the bias draw and the noise (keep it for the episode).
    """

    def __init__(self, config: ImuConfig, gravity_mps2: float, rng: np.random.Generator) -> None:
        config.validate()
        self.config = config
        self.gravity_mps2 = gravity_mps2
        self.reset(rng)

    def reset(self, rng: np.random.Generator) -> None:
        """Draw new biases; later noise comes from ``rng``."""
        self._rng = rng
        self.accel_bias = rng.normal(0.0, self.config.accel_bias_std_mps2, 3)
        self.gyro_bias = rng.normal(0.0, self.config.gyro_bias_std_radps, 3)

    def measure(
        self, R_ned_body: ArrayLike, nu: ArrayLike, accel_frd_mps2: ArrayLike, depth_m: float
    ) -> ImuReading:
        """Sample the sensors.

        Args:
            R_ned_body: (3, 3) true attitude ``R_ned_frd``.
            nu: (6,) true body velocity (m/s, rad/s), FRD.
            accel_frd_mps2: (3,) true acceleration of the origin (time derivative in the world,
                expressed in body FRD) (m/s^2).
            depth_m: true depth (m).
        """
        c, rng = self.config, self._rng
        R = np.asarray(R_ned_body, dtype=float)
        g_body = R.T @ np.array([0.0, 0.0, self.gravity_mps2])
        err = self.accel_bias + rng.normal(0.0, c.accel_noise_std_mps2, 3)
        acc = np.asarray(accel_frd_mps2, dtype=float) + err
        nu = np.asarray(nu, dtype=float)
        return ImuReading(
            specific_force_frd_mps2=acc - g_body,
            acceleration_frd_mps2=acc,
            angular_velocity_frd_radps=nu[3:]
            + self.gyro_bias
            + rng.normal(0.0, c.gyro_noise_std_radps, 3),
            velocity_frd_mps=nu[:3] + rng.normal(0.0, c.velocity_noise_std_mps, 3),
            depth_m=float(depth_m + rng.normal(0.0, c.depth_noise_std_m)),
        )
