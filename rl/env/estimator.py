"""The DS pose filter shared by every observation source.

The docking station is static, so the filter tracks its pose in the world frame (NED): the state
is ``[x_m, y_m, z_m, yaw_rad]`` of ``T_world_ds`` with a 4x4 covariance. The vehicle's own pose
comes from its navigation (odometry); between measurements the DS estimate is held while its
uncertainty grows with time (odometry drift), which is the same as propagating the relative pose
with the vehicle's velocities. Before the first detection the estimate is a USBL-like prior.

Observation sources differ only in how they make a measurement (``T_world_ds`` + covariance):
render -> detect -> PnP (camera), a fitted error model, or the paper's visibility proxy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from uwdock.calibration.frames import R_from_rpy, make_T, rpy_from_R, wrap_angle_rad
from uwdock.dockcore.domains import Interval

_Sigma = Annotated[float, Interval(ge=0, le=100)]  # m


@dataclass(frozen=True)
class EstimatorConfig:
    """DS pose filter.

    Attributes:
        prior_sigma_xy_m: USBL-like prior, horizontal standard deviation (m).
        prior_sigma_z_m: prior, vertical standard deviation (m).
        prior_sigma_yaw_deg: prior, DS heading standard deviation (deg).
        drift_xyz_m_per_sqrt_s: growth of the position uncertainty between measurements
            (random-walk density of the odometry drift, m / sqrt(s)).
        drift_yaw_deg_per_sqrt_s: same for yaw (deg / sqrt(s)).
        fuse: True: Kalman update; False: a measurement replaces the estimate (the paper's
            proxy observation, which is memoryless).
        gate_sigma: measurements further than this many standard deviations (Mahalanobis) from
            the estimate are rejected as outliers (0 disables gating).

    The acoustic fixes the filter fuses are ``EnvConfig.usbl``'s (:mod:`uwdock.sim.usbl`);
    configs written before that table existed held the "ideal" model's period and noise here
    (``usbl_period_s``, ``usbl_sigma_floor_m``, ``usbl_sigma_per_m``): the loader moves them
    into ``[usbl]`` (``EnvConfig.upgrade_layout``).
    """

    prior_sigma_xy_m: _Sigma = 1.0
    prior_sigma_z_m: _Sigma = 0.3
    prior_sigma_yaw_deg: Annotated[float, Interval(ge=0, le=180)] = 15.0
    drift_xyz_m_per_sqrt_s: Annotated[float, Interval(ge=0, le=10)] = 0.02
    drift_yaw_deg_per_sqrt_s: Annotated[float, Interval(ge=0, le=180)] = 0.2
    fuse: bool = True
    gate_sigma: Annotated[float, Interval(ge=0, le=1000)] = 0.0


class DSPoseFilter:
    """Kalman filter on the static DS pose ``[x, y, z, yaw]`` in the world frame."""

    def __init__(self, cfg: EstimatorConfig | None = None) -> None:
        self.cfg = cfg or EstimatorConfig()
        self.x = np.zeros(4)
        self._T_key: bytes | None = None
        self._T = np.eye(4)
        self.P = np.eye(4)
        self.measured = False
        self.time_since_measurement_s = math.inf

    def prior_sigma(self, sigma_xy_m: float | None = None) -> np.ndarray:
        """(4,) standard deviations of the USBL-like prior [x, y, z (m), yaw (rad)]."""
        c = self.cfg
        s_xy = c.prior_sigma_xy_m if sigma_xy_m is None else sigma_xy_m
        return np.array([s_xy, s_xy, c.prior_sigma_z_m, math.radians(c.prior_sigma_yaw_deg)])

    def set_prior(
        self,
        T_world_ds_prior: np.ndarray,
        sigma_xy_m: float | None = None,
        sigma_z_m: float | None = None,
    ) -> None:
        """Start from a prior DS pose (a USBL fix, a survey) with the configured uncertainty
        (``sigma_xy_m``, ``sigma_z_m``: the position's instead, m)."""
        self.x = self._state(T_world_ds_prior)
        sigma = self.prior_sigma(sigma_xy_m)
        if sigma_z_m is not None:
            sigma[2] = sigma_z_m
        self.P = np.diag(np.maximum(sigma, 1e-6) ** 2)
        self.measured = False
        self.time_since_measurement_s = math.inf

    def set_prior_variances(self, T_world_ds_prior: np.ndarray, var_xyzyaw: np.ndarray) -> None:
        """Start from a prior DS pose with the variances of x, y, z (m^2) and yaw (rad^2), as a
        message's covariance carries them (the same state as :meth:`set_prior` with their
        square roots, without a round trip through them)."""
        var = np.asarray(var_xyzyaw, dtype=np.float64)
        if var.shape != (4,) or not np.all(np.isfinite(var)) or np.any(var < 0):
            raise ValueError(f"prior variances must be 4 finite values >= 0, got {var.tolist()}")
        self.x = self._state(T_world_ds_prior)
        self.P = np.diag(np.maximum(var, 1e-12))
        self.measured = False
        self.time_since_measurement_s = math.inf

    def reset(self, T_world_ds_true: np.ndarray, rng: np.random.Generator) -> None:
        """Start from the USBL-like prior: the truth plus a draw of the prior's noise."""
        self.set_prior(T_world_ds_true)
        self.x = self.x + self.prior_sigma() * rng.standard_normal(4)
        self.x[3] = float(wrap_angle_rad(self.x[3]))

    @staticmethod
    def _state(T_world_ds: np.ndarray) -> np.ndarray:
        return np.array([*T_world_ds[:3, 3], rpy_from_R(T_world_ds[:3, :3])[2]])

    def predict(self, dt_s: float) -> None:
        """Grow the uncertainty over ``dt_s`` seconds without a measurement."""
        c = self.cfg
        q = np.array([c.drift_xyz_m_per_sqrt_s] * 3 + [math.radians(c.drift_yaw_deg_per_sqrt_s)])
        self.P = self.P + np.diag(q**2 * dt_s)
        self.time_since_measurement_s += dt_s

    def update(self, T_world_ds_meas: np.ndarray, cov_xyzyaw: np.ndarray) -> bool:
        """Fuse one measurement (4x4 covariance of x, y, z, yaw). Returns False if gated out."""
        z = self._state(T_world_ds_meas)
        R = np.asarray(cov_xyzyaw, dtype=np.float64)
        if not self.cfg.fuse:
            self.x, self.P = z, R.copy()
        else:
            innov = z - self.x
            innov[3] = float(wrap_angle_rad(innov[3]))
            S = self.P + R
            if self.cfg.gate_sigma > 0:
                d2 = float(innov @ np.linalg.solve(S, innov))
                if d2 > self.cfg.gate_sigma**2:
                    return False
            K = self.P @ np.linalg.inv(S)
            self.x = self.x + K @ innov
            self.x[3] = float(wrap_angle_rad(self.x[3]))
            self.P = (np.eye(4) - K) @ self.P
        self.measured = True
        self.time_since_measurement_s = 0.0
        return True

    def update_position(
        self, p_world_ds_m: np.ndarray, sigma_m: float | None = None, var_m2: float | None = None
    ) -> bool:
        """Fuse a position-only fix of the DS (USBL; world NED, m) with a standard deviation
        ``sigma_m`` (m) or a variance ``var_m2`` (m^2) on each axis: the yaw estimate is kept."""
        var = sigma_m**2 if var_m2 is None else var_m2
        T = self.T_world_ds.copy()
        T[:3, 3] = p_world_ds_m
        return self.update(T, np.diag([var] * 3 + [1e6]))

    @property
    def T_world_ds(self) -> np.ndarray:
        """(4, 4) estimated DS pose (level: roll and pitch zero), a fresh copy.

        Read several times per control step while the state changes only on updates: the
        validated matrix is rebuilt only when ``x`` has changed.
        """
        key = self.x.tobytes()
        if key != self._T_key:
            self._T, self._T_key = make_T(R_from_rpy(0.0, 0.0, self.x[3]), self.x[:3]), key
        return self._T.copy()

    @property
    def sigma_xyz_m(self) -> np.ndarray:
        """(3,) current standard deviations of the DS position estimate (m)."""
        return np.sqrt(np.diag(self.P)[:3])
