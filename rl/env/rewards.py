"""The paper's reward, as named terms (Chaarani et al., eqs. r_dist ... r_mission).

R = r_dist + r_angle + r_smooth + r_collision + r_mission, each term multiplied by a weight from
:class:`RewardConfig` (all 1 by default, i.e. the paper) and reported separately in
``info["reward_terms"]``. Two terms are ours, off by default: r_precision, a bonus that rises
steeply in the last decimetres (the paper's r_dist is linear, so a policy 6 cm off the seat
pays 0.06 per step for it, lost in PPO's noise), and r_stall, a penalty for pushing at
saturated thrust outside the guides without getting closer (the "wedged" failure of
:mod:`rl.evaluate.failures`: nothing else in the reward tells pushing against the DS frame from
approaching it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np

from uwdock.dockcore.domains import Interval

_Weight = Annotated[float, Interval(ge=0, le=1000)]
_Reward = Annotated[float, Interval(ge=0, le=1e6)]


@dataclass(frozen=True)
class RewardConfig:
    """Reward constants (docs/reference-system.md section 1; paper appendix table).

    Attributes:
        w_xyz: weights of |e_x|, |e_y|, |e_z| in r_dist (1/m).
        angle_gain: k in r_angle = exp(-k |e_psi|) - 1 (1/rad).
        angle_linear: c_lin, an added linear yaw term -c_lin |e_psi| / pi in r_angle (-); 0 is
            the paper's. The exponential is nearly flat beyond 45 deg (its slope at 90 deg is
            4 % of that at 0), so a policy far off in yaw gets almost no signal to turn.
        smooth_scale: c in r_smooth = -(c / N) exp(sum |a_k - a_k-1|) (-).
        smooth_over: the action components r_smooth sums over (N of them): "actuated" (those
            with a non-zero wrench limit; roll is not actuated) or "all" six (the paper's
            formula). Summed over all six, the unactuated roll's exploration noise alone
            makes the term as large as r_dist at PPO's initial noise, and PPO escapes it by
            saturating the roll mean beyond +-1 (bench/diagnose_reward.py; README).
        collision_penalty: p_c, paid when the IMU acceleration jumps by more than Gamma (-).
        gamma_set_mps2: nominal collision threshold Gamma_set (m/s^2).
        precision_gain: c_p in r_precision = c_p exp(-||e_xyz|| / s_p) (-); 0 (the default)
            is the paper's reward. Its slope at the dock is c_p / s_p per metre, against r_dist's
            1: it pays for the centimetres that seat the pegs (strict: within 5 cm).
        precision_scale_m: s_p, the distance over which r_precision falls by e (m).
        precision_yaw_scale_rad: s_psi; > 0 multiplies r_precision by exp(-|e_psi| / s_psi),
            so it pays only when the heading is right too (rad); 0: position only. A policy
            that lands with its yaw 10-20 deg off rests on the guides' crests, where r_angle's
            slope (about 0.02 per degree) is too small to make it lift and turn.
        stall_penalty: p_stall in r_stall, paid each step the vehicle pushes at saturated thrust
            (an action component at least ``stall_saturated``) more than ``stall_clearance_m``
            from the docking point horizontally and gets less than ``stall_progress_m`` closer
            than at the step before (-); 0 (the default) is the paper's reward.
        stall_clearance_m: the guides' horizontal clearance: closer than this r_stall is not paid.
        stall_progress_m: the horizontal approach per control step below which pushing is a stall.
        stall_saturated: an action component at least this large is saturated thrust.
        success_reward: p_s on docking (-).
        truncation_penalty: p_f when the episode is truncated (-).
        weights: multiplier per term name (:data:`TERMS`).
    """

    w_xyz: tuple[_Weight, _Weight, _Weight] = (1.0, 1.0, 0.5)
    angle_gain: Annotated[float, Interval(ge=0, le=100)] = 2.0
    angle_linear: Annotated[float, Interval(ge=0, le=100)] = 0.0
    smooth_scale: _Weight = 0.1
    smooth_over: Literal["actuated", "all"] = "actuated"
    collision_penalty: _Reward = 10.0
    gamma_set_mps2: Annotated[float, Interval(gt=0, le=1000)] = 1.0
    precision_gain: _Weight = 0.0
    precision_scale_m: Annotated[float, Interval(gt=0, le=100)] = 0.1
    precision_yaw_scale_rad: Annotated[float, Interval(ge=0, le=10)] = 0.0
    stall_penalty: _Reward = 0.0
    stall_clearance_m: Annotated[float, Interval(ge=0, le=100)] = 0.25
    stall_progress_m: Annotated[float, Interval(ge=0, le=10)] = 0.01
    stall_saturated: Annotated[float, Interval(gt=0, le=1)] = 0.95
    success_reward: _Reward = 500.0
    truncation_penalty: _Reward = 10.0
    weights: dict[str, _Weight] | None = None

    def validate(self) -> None:
        unknown = set(self.weights or {}) - set(TERMS)
        if unknown:
            raise ValueError(f"weights: unknown term {sorted(unknown)[0]!r} (terms: {TERMS})")


TERMS = ("dist", "angle", "smooth", "collision", "mission", "precision", "stall")


class DockingReward:
    """Stateful reward (the collision threshold Gamma adapts); call :meth:`reset` per episode."""

    def __init__(self, cfg: RewardConfig | None = None, actuated: np.ndarray | None = None) -> None:
        """
        Args:
            cfg: the reward constants.
            actuated: (6,) bool, the action components that move the vehicle (the env's
                non-zero wrench limits); None: all six.
        """
        self.cfg = cfg or RewardConfig()
        mask = np.ones(6, dtype=bool) if actuated is None else np.asarray(actuated, dtype=bool)
        self._smooth_mask = mask if self.cfg.smooth_over == "actuated" else np.ones(6, bool)
        self._w = {t: 1.0 for t in TERMS} | dict(self.cfg.weights or {})
        self.gamma_mps2 = self.cfg.gamma_set_mps2
        self._prev_e_xy_m = math.nan

    def reset(self) -> None:
        self.gamma_mps2 = self.cfg.gamma_set_mps2
        self._prev_e_xy_m = math.nan

    @property
    def smooth_mask(self) -> np.ndarray:
        """(6,) bool: the action components r_smooth sums over."""
        return self._smooth_mask.copy()

    @property
    def weights(self) -> dict[str, float]:
        """Each term's weight (1 unless ``cfg.weights`` says otherwise)."""
        return dict(self._w)

    def collision(self, acc_mps2: np.ndarray, prev_acc_mps2: np.ndarray) -> bool:
        """Detect a collision from the IMU jump and adapt Gamma (doubles on a hit, halves back)."""
        hit = float(np.linalg.norm(np.asarray(acc_mps2) - prev_acc_mps2)) > self.gamma_mps2
        if hit:
            self.gamma_mps2 *= 2.0
        elif self.gamma_mps2 > self.cfg.gamma_set_mps2:
            self.gamma_mps2 = max(self.cfg.gamma_set_mps2, self.gamma_mps2 / 2.0)
        return hit

    def __call__(
        self,
        e_xyz_m: np.ndarray,
        e_psi_rad: float,
        action: np.ndarray,
        prev_action: np.ndarray,
        collided: bool,
        docked: bool,
        truncated: bool,
    ) -> dict[str, float]:
        """The weighted terms of one step (their sum is the reward)."""
        c = self.cfg
        a = np.asarray(action, dtype=np.float64)
        da = np.abs(a - prev_action)[self._smooth_mask]
        precision = 0.0  # off (the paper's reward): nothing to compute on the step's hot path
        if c.precision_gain > 0:
            x = math.hypot(*e_xyz_m) / c.precision_scale_m
            if c.precision_yaw_scale_rad > 0:
                x += abs(e_psi_rad) / c.precision_yaw_scale_rad
            precision = c.precision_gain * math.exp(-x)
        stall = 0.0
        if c.stall_penalty > 0:
            e_xy = math.hypot(float(e_xyz_m[0]), float(e_xyz_m[1]))
            pushing = float(np.max(np.abs(a))) >= c.stall_saturated
            before = self._prev_e_xy_m  # NaN right after a reset: nothing to compare with
            stuck = not math.isnan(before) and before - e_xy < c.stall_progress_m
            if pushing and stuck and e_xy > c.stall_clearance_m:
                stall = -c.stall_penalty
            self._prev_e_xy_m = e_xy
        terms = {
            "dist": -float(np.dot(c.w_xyz, np.abs(e_xyz_m))),
            "angle": math.exp(-c.angle_gain * abs(e_psi_rad))
            - 1.0
            - c.angle_linear * abs(e_psi_rad) / math.pi,
            "smooth": -(c.smooth_scale / max(da.size, 1)) * math.exp(float(da.sum())),
            "collision": -c.collision_penalty if collided else 0.0,
            "mission": c.success_reward if docked else -c.truncation_penalty if truncated else 0.0,
            "precision": precision,
            "stall": stall,
        }
        return {k: self._w[k] * v for k, v in terms.items()}
