"""The vehicle's own navigation: where it *thinks* it is, from its DVL, AHRS and depth sensor.

A hovering AUV of the Girona class has no position sensor under water: its navigation filter
integrates the Doppler velocity log's body velocity, turned into the world by the attitude and
heading reference system (AHRS), and takes its depth from a pressure sensor. The pose it reports
drifts: the DVL's scale-factor error and the AHRS's heading error turn into a horizontal position
error that grows with the distance run, and the attitude it reports is off by the AHRS's error.

The docking env measures the DS *relative* to the vehicle (camera, USBL) and turns each
measurement into the world frame with this navigation pose, as the vehicle's software does, so
the DS estimate and the vehicle's own pose live in the same drifting frame: what the policy sees
(the docking point relative to the vehicle) is off by the drift since the last measurement and
by the attitude error, not by the whole drift.

The model is an error state on top of the true motion, for N vehicles at once (one row each;
the scalar env uses N = 1), so the ``"ideal"`` preset is exactly the true pose and draws
nothing:

* AHRS: roll, pitch and heading errors, each a first-order Gauss-Markov process with a
  stationary standard deviation and a correlation time (``tilt_*``, ``heading_*``); its first
  value is drawn from the stationary distribution at reset.
* DVL: a per-episode scale-factor error on each body axis, ``1 + N(0, dvl_scale_sigma_rel^2)``,
  on the body velocity the IMU model already reports with white noise
  (:class:`uwdock.sim.vehicle.ImuConfig` ``velocity_noise_std_mps``).
* Position: the horizontal error integrates ``R_nav v_dvl - R_true v_true`` over each control
  step (dead reckoning), starting at zero (the vehicle starts from a known position).
* Depth: the pressure sensor's reading (the IMU model's, with its white noise) plus a
  per-episode offset N(0, ``depth_offset_sigma_m^2``) (zero-pressure and density errors).

Presets (:data:`NAV_PRESETS`) name their sources; docs/reference-system.md has the figures.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np

from uwdock.calibration.frames import inv_T_b
from uwdock.dockcore.domains import Interval

__all__ = ["NAV_PRESETS", "NavConfig", "NavErrors"]

_Deg = Annotated[float, Interval(ge=0, le=45)] | None
_Tau_s = Annotated[float, Interval(gt=0, le=1e6)] | None


@dataclass(frozen=True)
class NavConfig:
    """The vehicle's navigation model: a named preset, with any field given here overriding it.

    A field left ``None`` takes the preset's value (:meth:`resolved`), so a TOML ``[env.nav]``
    table reads ``preset = "mems-ahrs-dvl"`` plus only the values that differ.

    Attributes:
        preset: the base model, a key of :data:`NAV_PRESETS` ("ideal": the true pose).
        heading_sigma_deg: AHRS heading error, stationary standard deviation (deg).
        heading_tau_s: its correlation time (s).
        tilt_sigma_deg: AHRS roll and pitch errors, stationary standard deviation (deg).
        tilt_tau_s: their correlation time (s).
        dvl_scale_sigma_rel: per-episode DVL scale-factor error on each body axis (-).
        depth_offset_sigma_m: per-episode offset of the pressure depth (m).
        ds_prior: where the DS estimate starts: "survey" (the DS's surveyed pose with the
            estimator's prior spread, world frame) or "usbl" (the first acoustic fix, converted
            with the vehicle's navigation, when the observation source takes acoustic fixes
            and one arrives at the start; otherwise the survey prior).
    """

    preset: str = "ideal"
    heading_sigma_deg: Annotated[float, Interval(ge=0, le=180)] | None = None
    heading_tau_s: _Tau_s = None
    tilt_sigma_deg: _Deg = None
    tilt_tau_s: _Tau_s = None
    dvl_scale_sigma_rel: Annotated[float, Interval(ge=0, le=0.5)] | None = None
    depth_offset_sigma_m: Annotated[float, Interval(ge=0, le=10)] | None = None
    ds_prior: Literal["survey", "usbl"] | None = None

    def validate(self) -> None:
        """Raise ValueError for an unknown preset name."""
        if self.preset not in NAV_PRESETS:
            raise ValueError(
                f"preset: unknown navigation preset {self.preset[:100]!r} "
                f"(known: {', '.join(NAV_PRESETS)})"
            )

    def resolved(self) -> NavConfig:
        """This model with every field set: the preset's values, then the fields set here."""
        self.validate()
        base = NAV_PRESETS[self.preset]
        values = {n: getattr(base, n) for n in MODEL_FIELDS}
        values.update({n: v for n in MODEL_FIELDS if (v := getattr(self, n)) is not None})
        return NavConfig(preset=self.preset, **values)

    @property
    def is_ideal(self) -> bool:
        """True when every error is zero (the navigation pose is the true pose)."""
        r = self.resolved()
        return not any(
            (r.heading_sigma_deg, r.tilt_sigma_deg, r.dvl_scale_sigma_rel, r.depth_offset_sigma_m)
        )


#: NavConfig fields that describe the model (every field but ``preset``).
MODEL_FIELDS = tuple(f.name for f in dataclasses.fields(NavConfig) if f.name != "preset")

NAV_PRESETS: dict[str, NavConfig] = {
    # The vehicle knows its true pose: the env before navigation existed, and what the paper's
    # simulator gave its policy.
    "ideal": NavConfig(
        preset="ideal",
        heading_sigma_deg=0.0,
        heading_tau_s=60.0,
        tilt_sigma_deg=0.0,
        tilt_tau_s=10.0,
        dvl_scale_sigma_rel=0.0,
        depth_offset_sigma_m=0.0,
        ds_prior="survey",
    ),
    # A MEMS AHRS and a compact DVL, the sensor class a hovering Girona-type AUV carries.
    # AHRS: Xsens MTi-300 (MTi User Manual MT0605P, section 4.3 "Orientation performance
    # specification"): roll/pitch 0.3 deg RMS dynamic (0.2 static), heading 1.0 deg RMS with a
    # magnetic reference. DVL: Water Linked DVL-A50 long-term velocity accuracy 1 % (standard
    # firmware; 0.1 % for the performance one), taken here as the per-episode scale error's
    # standard deviation. The correlation times (60 s heading, 10 s tilt) and the 2 cm depth
    # offset are assumptions of this toolkit, not datasheet figures.
    "mems-ahrs-dvl": NavConfig(
        preset="mems-ahrs-dvl",
        heading_sigma_deg=1.0,
        heading_tau_s=60.0,
        tilt_sigma_deg=0.3,
        tilt_tau_s=10.0,
        dvl_scale_sigma_rel=0.01,
        depth_offset_sigma_m=0.02,
        ds_prior="usbl",
    ),
}

#: Standard normals one vehicle draws per control step (roll, pitch, heading), 0 when ideal.
STEP_DRAWS = 3
#: Standard normals one vehicle draws at reset (3 attitude errors, 3 DVL scales, 1 depth offset).
RESET_DRAWS = 7


class NavErrors:
    """Navigation errors of ``n`` vehicles (module docstring), one row per vehicle.

    Args:
        cfg: the navigation model (resolved here).
        n: how many vehicles.
    """

    def __init__(self, cfg: NavConfig, n: int) -> None:
        self.cfg = cfg.resolved()
        c = self.cfg
        self.ideal = cfg.is_ideal
        self.n = int(n)
        self.sigma_rad = np.radians([c.tilt_sigma_deg, c.tilt_sigma_deg, c.heading_sigma_deg])
        self.tau_s = np.array([c.tilt_tau_s, c.tilt_tau_s, c.heading_tau_s], dtype=np.float64)
        self.att_err_rad = np.zeros((self.n, 3))  # roll, pitch, heading
        self.scale = np.ones((self.n, 3))
        self.depth_offset_m = np.zeros(self.n)
        self.dp_xy_m = np.zeros((self.n, 2))

    @property
    def step_draws(self) -> int:
        """Standard normals each vehicle needs per :meth:`step` (0 for an ideal model)."""
        return 0 if self.ideal else STEP_DRAWS

    def reset(self, i: int, normals: np.ndarray | None) -> None:
        """Start vehicle ``i`` at its true position with new per-episode errors drawn from
        :data:`RESET_DRAWS` standard normals (None, or an ideal model: no errors)."""
        self.dp_xy_m[i] = 0.0
        if self.ideal or normals is None:
            self.att_err_rad[i], self.scale[i], self.depth_offset_m[i] = 0.0, 1.0, 0.0
            return
        z = np.asarray(normals, dtype=np.float64).reshape(RESET_DRAWS)
        self.att_err_rad[i] = self.sigma_rad * z[:3]
        self.scale[i] = 1.0 + self.cfg.dvl_scale_sigma_rel * z[3:6]
        self.depth_offset_m[i] = self.cfg.depth_offset_sigma_m * z[6]

    def copy_row(self, i: int, other: NavErrors, j: int = 0) -> None:
        """Take vehicle ``j`` of ``other`` (the same model) as vehicle ``i``."""
        self.att_err_rad[i] = other.att_err_rad[j]
        self.scale[i] = other.scale[j]
        self.depth_offset_m[i] = other.depth_offset_m[j]
        self.dp_xy_m[i] = other.dp_xy_m[j]

    def dvl_velocity(self, v_meas_frd_mps: np.ndarray) -> np.ndarray:
        """(n, 3) the DVL's body velocity: the measured one with each vehicle's scale error."""
        return np.asarray(v_meas_frd_mps, dtype=np.float64).reshape(self.n, 3) * self.scale

    def R_nav(self, R_true: np.ndarray) -> np.ndarray:
        """(n, 3, 3) the AHRS attitude: the true roll, pitch and yaw plus each error."""
        R = np.asarray(R_true, dtype=np.float64).reshape(self.n, 3, 3)
        if self.ideal:
            return R.copy()
        return _R_zyx_plus(R, self.att_err_rad)

    def step(
        self,
        dt_s: float,
        T_true: np.ndarray,
        v_true_frd_mps: np.ndarray,
        v_meas_frd_mps: np.ndarray,
        normals: np.ndarray | None,
    ) -> None:
        """Advance every vehicle's errors over one control step of ``dt_s``: dead-reckon the
        horizontal position error with the attitude and velocity at the step's start (``T_true``
        and the velocities of the previous step's end), then move the attitude errors on with
        :attr:`step_draws` standard normals per vehicle."""
        if self.ideal:
            return
        T = np.asarray(T_true, dtype=np.float64).reshape(self.n, 4, 4)
        R = T[:, :3, :3]
        v_nav = np.einsum("nij,nj->ni", self.R_nav(R), self.dvl_velocity(v_meas_frd_mps))
        v_world = np.einsum("nij,nj->ni", R, np.asarray(v_true_frd_mps).reshape(self.n, 3))
        self.dp_xy_m += (v_nav - v_world)[:, :2] * dt_s
        a = np.exp(-dt_s / self.tau_s)
        z = np.asarray(normals, dtype=np.float64).reshape(self.n, STEP_DRAWS)
        self.att_err_rad = a * self.att_err_rad + np.sqrt(1.0 - a**2) * self.sigma_rad * z

    def T_nav(self, T_true: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """(n, 4, 4) the navigation pose ``T_world_body`` each vehicle believes: its true
        position plus the dead-reckoning error, its pressure depth ``depth_m`` (n,) (the IMU
        model's reading) plus the offset, and the AHRS attitude. Ideal: ``T_true``."""
        T = np.asarray(T_true, dtype=np.float64).reshape(self.n, 4, 4)
        if self.ideal:
            return T.copy()
        out = T.copy()
        out[:, :3, :3] = self.R_nav(T[:, :3, :3])
        out[:, :2, 3] += self.dp_xy_m
        out[:, 2, 3] = np.asarray(depth_m, dtype=np.float64).reshape(self.n) + self.depth_offset_m
        return out

    def error_m(self) -> np.ndarray:
        """(n,) horizontal dead-reckoning error of each vehicle (m)."""
        return np.hypot(self.dp_xy_m[:, 0], self.dp_xy_m[:, 1])


def _R_zyx_plus(R: np.ndarray, d_rpy_rad: np.ndarray) -> np.ndarray:
    """(n, 3, 3) the attitudes of ``R`` (n, 3, 3) with roll, pitch and yaw (Fossen's ZYX angles,
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``, :func:`uwdock.calibration.frames.R_from_rpy`) each moved
    by ``d_rpy_rad`` (n, 3). Closed form in NumPy (SciPy's ``Rotation`` round trip gives the same
    to ~1e-16 at ~10x the cost, a tenth of a batch worker's step)."""
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2]) + d_rpy_rad[:, 0]
    pitch = np.arctan2(-R[:, 2, 0], np.hypot(R[:, 0, 0], R[:, 1, 0])) + d_rpy_rad[:, 1]
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0]) + d_rpy_rad[:, 2]
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    out = np.empty_like(R)
    out[:, 0, 0] = cy * cp
    out[:, 0, 1] = cy * sp * sr - sy * cr
    out[:, 0, 2] = cy * sp * cr + sy * sr
    out[:, 1, 0] = sy * cp
    out[:, 1, 1] = sy * sp * sr + cy * cr
    out[:, 1, 2] = sy * sp * cr - cy * sr
    out[:, 2, 0] = -sp
    out[:, 2, 1] = cp * sr
    out[:, 2, 2] = cp * cr
    return out


def correction(T_nav: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """``T_nav @ inv(T_true)``: maps a pose the sources compute with the true vehicle pose
    (``T_true @ T_body_x``) to the one the vehicle computes with its navigation
    (``T_nav @ T_body_x``); (4, 4) or (n, 4, 4)."""
    T = np.asarray(T_true, dtype=np.float64)
    return T_nav @ inv_T_b(T.reshape(-1, 4, 4)).reshape(T.shape)
