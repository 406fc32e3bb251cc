"""Thrusters of the Girona AUV: geometry, allocation, thrust curve and first-order response.

Everything here is in the marine body frame ``body_frd`` (x forward, y starboard, z down) with
moments about the body origin; see ``calibration.frames``. Pure NumPy: no SAPIEN import.

Model (per thruster i):
    * thrust curve: ``thrust_n = max_thrust_n * s * |s|`` for a setpoint ``s`` in [-1, 1]
      (the inverse is ``s = sign(t) * sqrt(|t| / max_thrust_n)``);
    * dynamics: the produced thrust follows the commanded thrust with a first-order lag of time
      constant ``time_constant_s``, discretised exactly: ``t_k+1 = c + (t_k - c) * exp(-dt/tau)``;
    * geometry: the wrench of thrust t is ``t * [axis, position x axis]``, so the allocation
      matrix ``B`` (6, n) has the columns ``[a_i; r_i x a_i]`` and ``wrench = B @ thrust``.

Allocation (``ThrusterArray.allocate``): the weighted pseudo-inverse
``thrust = pinv(W B) W wrench`` with ``W = diag(sqrt(allocation_weights))``. Roll has weight 0
by default: the only roll authority is the sway thruster's 21 mm lever above the origin, so roll
always comes as ``0.021 * F_y`` and is not independently actuated; with weight 0 the other five
axes are reproduced exactly and a roll request is ignored. When a thruster would exceed its limit
the whole thrust vector is scaled down by one common factor, which keeps the direction of the
produced wrench (it is the requested wrench times that factor) instead of distorting it as
per-thruster clipping would.

Example:
    >>> arr = ThrusterArray(ThrusterArrayConfig())
    >>> thrust_n = arr.allocate([100.0, 0, 0, 0, 0, 10.0])
    >>> arr.wrench_from_thrust(thrust_n)  # -> [100, 0, 0, 0, 0, 10]
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.frames import cross3
from uwdock.dockcore.config import check_fields
from uwdock.dockcore.domains import Interval
from uwdock.sim.domains import BodyCoord_m, RelativeRange, validate_each

__all__ = [
    "DEFAULT_THRUSTERS",
    "ThrusterArray",
    "ThrusterArrayConfig",
    "ThrusterConfig",
    "ThrusterRandomisation",
]

#: A component of a thrust direction (-); the axis is normalised on use.
_AxisComponent = Annotated[float, Interval(ge=-1, le=1)]
#: A wrench-axis weight of the least-squares allocation (-).
_Weight = Annotated[float, Interval(ge=0, le=1e6)]


@dataclass(frozen=True)
class ThrusterConfig:
    """One thruster.

    Attributes:
        name: label (e.g. "SurgePort").
        position_m: (3,) thruster centre in body FRD (m).
        axis: (3,) direction of positive thrust in body FRD (unit vector; normalised on use).
        max_thrust_n: thrust at setpoint +1 and, negated, at -1 (N).
        time_constant_s: first-order lag between commanded and produced thrust (s).
    """

    name: str
    position_m: tuple[BodyCoord_m, BodyCoord_m, BodyCoord_m]
    axis: tuple[_AxisComponent, _AxisComponent, _AxisComponent]
    max_thrust_n: Annotated[float, Interval(gt=0, le=1e5)] = 140.0
    time_constant_s: Annotated[float, Interval(ge=0, le=100)] = 0.2

    def validate(self) -> None:
        """Raise ValueError naming the first field outside its declared domain (NaN included)
        or a zero axis."""
        check_fields(self)
        if not float(np.linalg.norm(self.axis)) >= 1e-9:
            raise ValueError(f"axis: must be non-zero (thruster {self.name})")


#: The five thrusters of the reference vehicle (docs/reference-system.md section 3), body FRD.
DEFAULT_THRUSTERS: tuple[ThrusterConfig, ...] = (
    ThrusterConfig("SurgePort", (-0.330, -0.259, -0.021), (1.0, 0.0, 0.0)),
    ThrusterConfig("SurgeStarboard", (-0.330, 0.259, -0.021), (1.0, 0.0, 0.0)),
    ThrusterConfig("Sway", (-0.063, 0.031, -0.021), (0.0, 1.0, 0.0)),
    ThrusterConfig("HeaveBow", (0.535, 0.0, -0.314), (0.0, 0.0, 1.0)),
    ThrusterConfig("HeaveStern", (-0.583, 0.0, -0.314), (0.0, 0.0, 1.0)),
)


@dataclass(frozen=True)
class ThrusterArrayConfig:
    """The vehicle's thrusters and how a wrench is shared among them.

    Attributes:
        thrusters: the thrusters (body FRD geometry), default the reference's five.
        allocation_weights: (6,) non-negative weight of each wrench axis (surge, sway, heave,
            roll, pitch, yaw) in the least-squares allocation; 0 drops the axis (default: roll,
            which these thrusters cannot actuate independently).
    """

    thrusters: tuple[ThrusterConfig, ...] = DEFAULT_THRUSTERS
    allocation_weights: tuple[_Weight, _Weight, _Weight, _Weight, _Weight, _Weight] = (
        1.0,
        1.0,
        1.0,
        0.0,
        1.0,
        1.0,
    )

    def validate(self) -> None:
        """Raise ValueError naming the first field outside its declared domain (NaN included),
        all-zero allocation weights, or an empty array or bad thruster (:class:`ThrusterArray`
        calls it on configs built in Python)."""
        check_fields(self)
        if not max(self.allocation_weights) > 0:
            raise ValueError("allocation_weights: at least one must be > 0")
        if not 1 <= len(self.thrusters) <= 32:
            raise ValueError(f"thrusters: 1 to 32 thrusters, got {len(self.thrusters)}")
        validate_each("thrusters", self.thrusters)


@dataclass(frozen=True)
class ThrusterRandomisation:
    """Per-episode perturbation of the thrusters (uniform draws; all zero = off).

    Attributes:
        position_m: each position coordinate moves by U(-position_m, position_m) (m).
        axis_deg: each axis tilts by an angle U(0, axis_deg) about a random perpendicular (deg).
        max_thrust_rel: each max thrust is scaled by 1 + U(-max_thrust_rel, max_thrust_rel).
        time_constant_rel: each time constant is scaled by 1 + U(-rel, rel).
    """

    position_m: Annotated[float, Interval(ge=0, le=1)] = 0.01
    axis_deg: Annotated[float, Interval(ge=0, le=90)] = 2.0
    max_thrust_rel: RelativeRange = 0.05
    time_constant_rel: RelativeRange = 0.2

    def validate(self) -> None:
        """Raise ValueError on a negative range or a relative range >= 1."""
        ranges = (self.position_m, self.axis_deg, self.max_thrust_rel, self.time_constant_rel)
        if not all(r >= 0 for r in ranges):  # also NaN
            raise ValueError("thruster randomisation ranges must be >= 0")
        if not (self.max_thrust_rel < 1 and self.time_constant_rel < 1):
            raise ValueError("relative thruster randomisation ranges must be < 1")

    def sample(self, base: ThrusterArrayConfig, rng: np.random.Generator) -> ThrusterArrayConfig:
        """Draw a perturbed copy of ``base`` (the allocation weights are kept)."""
        out = []
        for t in base.thrusters:
            pos = np.asarray(t.position_m, float) + rng.uniform(-1, 1, 3) * self.position_m
            axis = _tilt(np.asarray(t.axis, float), math.radians(self.axis_deg), rng)
            out.append(
                replace(
                    t,
                    position_m=tuple(float(x) for x in pos),
                    axis=tuple(float(x) for x in axis),
                    max_thrust_n=t.max_thrust_n * (1 + rng.uniform(-1, 1) * self.max_thrust_rel),
                    time_constant_s=t.time_constant_s
                    * (1 + rng.uniform(-1, 1) * self.time_constant_rel),
                )
            )
        return replace(base, thrusters=tuple(out))


def _tilt(axis: np.ndarray, max_angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Unit ``axis`` tilted by U(0, max_angle_rad) about a random perpendicular direction."""
    a = axis / np.linalg.norm(axis)
    angle = rng.uniform(0.0, max_angle_rad)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = cross3(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = cross3(a, e1)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    perp = math.cos(phi) * e1 + math.sin(phi) * e2
    return math.cos(angle) * a + math.sin(angle) * perp


class ThrusterArray:
    """Allocation matrix, allocation, thrust curve and first-order dynamics of a thruster set.

    Attributes (derived from ``config``; treat as read-only):
        config: the :class:`ThrusterArrayConfig` it was built from.
        B: (6, n) allocation matrix, ``wrench_frd = B @ thrust_n``.
        max_thrust_n: (n,) per-thruster limits (N).
        time_constant_s: (n,) per-thruster lags (s).
    """

    def __init__(self, config: ThrusterArrayConfig | None = None) -> None:
        self.config = config if config is not None else ThrusterArrayConfig()
        self.config.validate()
        ts = self.config.thrusters
        axes = np.array([np.asarray(t.axis, float) / np.linalg.norm(t.axis) for t in ts])
        pos = np.array([t.position_m for t in ts], dtype=float)
        self.B = np.vstack([axes.T, np.cross(pos, axes).T])  # (6, n)
        self.max_thrust_n = np.array([t.max_thrust_n for t in ts], dtype=float)
        self.time_constant_s = np.array([t.time_constant_s for t in ts], dtype=float)
        self._powers_key: tuple[float, int] | None = None
        self._powers = np.empty((0, len(ts)))

    @functools.cached_property
    def _alloc(self) -> np.ndarray:
        """(n, 6) the weighted pseudo-inverse, made at first use: the true thrusters of a
        randomised vehicle (drawn at every reset) need only ``B``; the nominal ones allocate."""
        w = np.sqrt(np.asarray(self.config.allocation_weights, dtype=float))
        return np.linalg.pinv(w[:, None] * self.B) * w[None, :]

    @functools.cached_property
    def _max_wrench(self) -> np.ndarray:
        return self._compute_max_wrench()

    @property
    def names(self) -> tuple[str, ...]:
        """Thruster names, in the column order of ``B``."""
        return tuple(t.name for t in self.config.thrusters)

    @property
    def n(self) -> int:
        """Number of thrusters."""
        return self.B.shape[1]

    def wrench_from_thrust(self, thrust_n: ArrayLike) -> np.ndarray:
        """Body wrench of the given thrusts.

        Args:
            thrust_n: (n,) thrust per thruster (N), or (k, n) for k samples.

        Returns:
            (6,) (or (k, 6)) wrench [Fx, Fy, Fz (N), Mx, My, Mz (N m) about the origin], FRD.
        """
        return np.asarray(thrust_n, dtype=float) @ self.B.T

    @property
    def allocation_matrix(self) -> np.ndarray:
        """(n, 6) weighted pseudo-inverse: unsaturated thrusts = this @ wrench (a copy)."""
        return self._alloc.copy()

    def allocate_unsaturated(self, wrench: ArrayLike) -> np.ndarray:
        """Weighted least-squares thrusts for ``wrench`` (6,), ignoring the limits (N, (n,))."""
        return self._alloc @ np.asarray(wrench, dtype=float)

    def allocate(self, wrench: ArrayLike) -> np.ndarray:
        """Thrusts (n,) in N that produce ``wrench`` (6,), body FRD, moments about the origin.

        The weighted pseudo-inverse solution is scaled down by one common factor when any
        thruster would exceed its limit, so the produced wrench keeps the requested direction.
        """
        thrust = self.allocate_unsaturated(wrench)
        ratio = float(np.max(np.abs(thrust) / self.max_thrust_n))
        return thrust / ratio if ratio > 1.0 else thrust

    def setpoint_from_thrust(self, thrust_n: ArrayLike) -> np.ndarray:
        """Setpoints in [-1, 1] giving ``thrust_n`` (clipped to the limits): sign*sqrt(|t|/max)."""
        t = np.asarray(thrust_n, dtype=float)
        return np.sign(t) * np.sqrt(np.minimum(np.abs(t) / self.max_thrust_n, 1.0))

    def thrust_from_setpoint(self, setpoint: ArrayLike) -> np.ndarray:
        """Thrust (N) of setpoints (clipped to [-1, 1]): ``max_thrust_n * s * |s|``."""
        s = np.clip(np.asarray(setpoint, dtype=float), -1.0, 1.0)
        return self.max_thrust_n * s * np.abs(s)

    def decay(self, dt_s: float) -> np.ndarray:
        """(n,) per-substep factors ``exp(-dt/tau)`` of the first-order response (0 if tau=0)."""
        tau = self.time_constant_s
        with np.errstate(divide="ignore"):
            return np.where(tau > 0, np.exp(-dt_s / np.where(tau > 0, tau, 1.0)), 0.0)

    def response(
        self, thrust_n: ArrayLike, command_n: ArrayLike, dt_s: float, n_steps: int
    ) -> np.ndarray:
        """Exact first-order response to a held command.

        Args:
            thrust_n: (n,) produced thrust now (N).
            command_n: (n,) commanded thrust, held for ``n_steps`` substeps (N).
            dt_s: substep (s).
            n_steps: number of substeps.

        Returns:
            (n_steps, n) produced thrust at the end of each substep k = 1..n_steps (N).
        """
        c = np.asarray(command_n, dtype=float)
        e0 = np.asarray(thrust_n, dtype=float) - c
        return c + e0 * self._decay_powers(dt_s, n_steps)

    def _decay_powers(self, dt_s: float, n_steps: int) -> np.ndarray:
        """(n_steps, n) ``decay(dt_s) ** k`` for k = 1..n_steps, kept for the last (dt, n): every
        control step asks for the same table."""
        key = (float(dt_s), int(n_steps))
        if self._powers_key != key:
            k = np.arange(1, n_steps + 1, dtype=float)[:, None]
            self._powers = self.decay(dt_s)[None, :] ** k
            self._powers_key = key
        return self._powers

    def max_wrench(self) -> np.ndarray:
        """(6,) largest pure wrench per axis (N, N m) the allocation reaches within the limits.

        Axis j's entry is the largest ``a`` for which ``allocate(a * e_j)`` is unsaturated;
        an axis with allocation weight 0 (roll by default) reports 0.
        """
        return self._max_wrench.copy()

    def _compute_max_wrench(self) -> np.ndarray:
        out = np.zeros(6)
        for j in range(6):
            if self.config.allocation_weights[j] <= 0:
                continue
            thrust = self._alloc[:, j]
            peak = float(np.max(np.abs(thrust) / self.max_thrust_n))
            out[j] = 1.0 / peak if peak > 1e-12 else 0.0
        return out
