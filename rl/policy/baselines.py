"""A classical baseline: cascaded PD/PI control of the wrench on the same DS estimate.

It reads the same observation vector as the policy (so it sees the same filtered estimate,
whatever the observation source) and returns an action in [-1, 1]^6. Strategy: hold a safe
altitude above the docking point while aligning yaw and closing the horizontal error, and
descend as the alignment errors shrink (the funnels do the last centimetres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from uwdock.dockcore.domains import Interval
from uwdock.rl.env.observation import POS_SCALE_M

_Gain = Annotated[float, Interval(ge=0, le=100_000)]


@dataclass(frozen=True)
class PIDConfig:
    """Gains of the baseline (wrench in N and N m per m, m/s, rad, rad/s).

    Attributes:
        kp_xy: horizontal position gain (N/m).
        kd_xy: horizontal velocity damping (N s/m).
        ki_xy: horizontal integral gain (N/(m s)), for currents.
        kp_z: vertical gain (N/m).
        kd_z: vertical damping (N s/m).
        ki_z: vertical integral gain (N/(m s)), for the net buoyancy.
        kp_yaw: yaw gain (N m/rad).
        kd_yaw: yaw damping (N m s/rad).
        approach_altitude_m: altitude above the docking point held until aligned (m).
        descend_xy_m: horizontal error below which the descent starts (m).
        descend_yaw_deg: yaw error below which the descent starts (deg).
        descend_blend_m: the altitude offset grows from 0 to ``approach_altitude_m`` over this
            much horizontal error beyond ``descend_xy_m`` (m).
        descend_blend_deg: same over this much yaw error beyond ``descend_yaw_deg`` (deg).
        integral_limit: anti-windup bound of each horizontal integral (m s).
    """

    kp_xy: _Gain = 300.0
    kd_xy: _Gain = 450.0
    ki_xy: _Gain = 0.0
    kp_z: _Gain = 150.0
    kd_z: _Gain = 250.0
    ki_z: _Gain = 20.0
    kp_yaw: _Gain = 60.0
    kd_yaw: _Gain = 80.0
    approach_altitude_m: Annotated[float, Interval(ge=0, le=20)] = 1.6
    descend_xy_m: Annotated[float, Interval(gt=0, le=10)] = 0.08
    descend_yaw_deg: Annotated[float, Interval(gt=0, le=180)] = 8.0
    descend_blend_m: Annotated[float, Interval(gt=0, le=10)] = 0.06
    descend_blend_deg: Annotated[float, Interval(gt=0, le=180)] = 3.0
    integral_limit: Annotated[float, Interval(ge=0, le=1000)] = 5.0


class PIDController:
    """Cascaded PD(I) docking controller (module docstring)."""

    def __init__(
        self,
        limits: np.ndarray,
        cfg: PIDConfig | None = None,
        dt_s: float = 0.2,
        obs_frames: int = 1,
    ) -> None:
        self.cfg = cfg or PIDConfig()
        self.obs_frames = obs_frames  # a stacked observation: read the newest (last) frame
        self.limits = np.asarray(limits, dtype=np.float64)
        self.dt_s = dt_s
        self.reset()

    @classmethod
    def for_env(cls, env_cfg, cfg: PIDConfig | None = None) -> PIDController:
        """The baseline for an env's action limits, control rate and observation stacking."""
        return cls(
            env_cfg.action_limits, cfg, dt_s=1.0 / env_cfg.control_hz, obs_frames=env_cfg.obs_frames
        )

    def reset(self) -> None:
        self.integral = np.zeros(3)

    def act(self, obs: np.ndarray) -> np.ndarray:
        c = self.cfg
        o = np.asarray(obs, dtype=np.float64).reshape(self.obs_frames, -1)[-1]
        e = o[0:3] * POS_SCALE_M
        e_psi = o[3] * math.pi
        v = o[4:7]
        r = o[7]
        # hold the approach altitude while misaligned, descend smoothly as the horizontal and
        # yaw errors shrink (a continuous schedule: no switching, easy to imitate)
        misalign = max(
            (np.hypot(e[0], e[1]) - c.descend_xy_m) / c.descend_blend_m,
            (abs(e_psi) - math.radians(c.descend_yaw_deg)) / math.radians(c.descend_blend_deg),
        )
        e_z = e[2] - c.approach_altitude_m * float(np.clip(misalign, 0.0, 1.0))
        err = np.array([e[0], e[1], e_z])
        self.integral = np.clip(
            self.integral + err * self.dt_s, -c.integral_limit, c.integral_limit
        )
        fx, fy = c.kp_xy * e[:2] - c.kd_xy * v[:2] + c.ki_xy * self.integral[:2]
        fz = c.kp_z * e_z - c.kd_z * v[2] + c.ki_z * self.integral[2]
        mz = c.kp_yaw * e_psi - c.kd_yaw * r
        wrench = np.array([fx, fy, fz, 0.0, 0.0, mz])
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.where(self.limits > 0, wrench / self.limits, 0.0)
        return np.clip(a, -1.0, 1.0)
