"""How a docking episode fails: the two failures seen on film, named and counted.

Issue 30 named them from evaluation videos:

* **wedged**: the vehicle arrives beside the DS frame (outside the guides) and pushes against
  it at saturated thrust, not moving, for tens of seconds;
* **landed off**: it settles on the station at dock height a few centimetres to decimetres off
  the seat (inside the guides, pegs not in their notches) and stays there.

:class:`FailureTracker` follows an episode step by step on the true state (as the reward and the
success tests do) and keeps the longest stretch of each state; :func:`failure_mode` names the
episode: ``"docked"`` (strict success), ``"wedged"``, ``"landed_off"``, or ``"other"`` (any other
failure: it never got there). An episode that was wedged for a while and then docked counts as
docked, and as a recovery (``wedged_s`` > 0 in its row).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from uwdock.dockcore.domains import Interval

_M = Annotated[float, Interval(ge=0, le=100)]


@dataclass(frozen=True)
class FailureThresholds:
    """Thresholds of the failure states (true state; m, m/s, s): the definitions of the named
    failures, fixed so that counts compare across runs and policies (not a setting of a run).

    Attributes:
        clearance_m: the guides' horizontal clearance: a horizontal docking error beyond it
            means the vehicle is outside the guides (the reference DS: +-0.25 m).
        beside_m: a vehicle within this horizontal error of the docking point is beside the DS.
        seat_m: within this horizontal error the pegs can seat (the strict test's tolerance).
        dock_height_m: within this vertical error the vehicle is at dock height (resting).
        still_mps: slower than this the vehicle is not moving.
        saturated: an action component at least this large (of 1) is saturated thrust.
        min_duration_s: a state must last this long to name the episode.
    """

    clearance_m: _M = 0.25
    beside_m: _M = 2.5
    seat_m: _M = 0.05
    dock_height_m: _M = 0.15
    still_mps: _M = 0.05
    saturated: Annotated[float, Interval(gt=0, le=1)] = 0.95
    min_duration_s: Annotated[float, Interval(gt=0, le=3600)] = 10.0


class FailureTracker:
    """The longest wedged and landed-off stretches of one episode (module docstring)."""

    def __init__(self, cfg: FailureThresholds | None = None) -> None:
        self.cfg = cfg or FailureThresholds()
        self.reset()

    def reset(self) -> None:
        """Start a new episode."""
        self._prev_pos: np.ndarray | None = None
        self._prev_t = 0.0
        self._run = {"wedged": 0.0, "landed_off": 0.0}
        self.longest_s = {"wedged": 0.0, "landed_off": 0.0}

    def update(
        self, time_s: float, pos_m: np.ndarray, e_true: np.ndarray, action: np.ndarray
    ) -> None:
        """One control step: the time (s), the vehicle's true position (m, world), its true
        docking error (body frame, m) and the action it commanded ([-1, 1]^6)."""
        c = self.cfg
        pos = np.asarray(pos_m, dtype=np.float64)
        dt = time_s - self._prev_t
        moving = True
        if self._prev_pos is not None and dt > 0:
            moving = float(np.linalg.norm(pos - self._prev_pos)) / dt >= c.still_mps
        self._prev_pos, self._prev_t = pos, time_s
        e_xy = math.hypot(float(e_true[0]), float(e_true[1]))
        pushing = float(np.max(np.abs(action))) >= c.saturated
        states = {
            "wedged": not moving and pushing and c.clearance_m < e_xy <= c.beside_m,
            "landed_off": not moving
            and c.seat_m < e_xy <= c.clearance_m
            and abs(float(e_true[2])) <= c.dock_height_m,
        }
        for name, on in states.items():
            self._run[name] = self._run[name] + dt if on and dt > 0 else 0.0
            self.longest_s[name] = max(self.longest_s[name], self._run[name])

    def failure_mode(self, docked_strict: bool) -> str:
        """``"docked"``, ``"wedged"``, ``"landed_off"`` or ``"other"`` (module docstring)."""
        if docked_strict:
            return "docked"
        for name in ("wedged", "landed_off"):
            if self.longest_s[name] >= self.cfg.min_duration_s:
                return name
        return "other"


def failure_counts(rows: list[dict]) -> dict[str, int]:
    """Episodes per failure mode, and how many were wedged for a while and still docked."""
    modes = [r.get("failure_mode", "other") for r in rows]
    out = {m: modes.count(m) for m in ("docked", "wedged", "landed_off", "other")}
    min_s = FailureThresholds().min_duration_s
    out["recovered_from_wedge"] = sum(
        1 for r in rows if r.get("failure_mode") == "docked" and r.get("wedged_s", 0) >= min_s
    )
    return out
