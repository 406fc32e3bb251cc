"""The failure modes of a docking episode (issue 30 point 4): wedged against the DS frame,
landed off the seat, or anything else, from synthetic trajectories with known answers and
through `rl eval`'s rows and summary."""

from __future__ import annotations

import numpy as np
import pytest

from uwdock.rl.evaluate.failures import FailureThresholds, FailureTracker, failure_counts

DT = 0.2
FULL = np.array([1.0, 0, 0, 0, 0, 0])
SOFT = np.array([0.3, 0, 0, 0, 0, 0])


def _track(seconds: float, e, action, speed_mps: float = 0.0, t0: float = 0.0, tr=None):
    tr = tr or FailureTracker()
    pos = np.zeros(3)
    for k in range(round(seconds / DT) + 1):
        pos = pos + np.array([speed_mps * DT, 0.0, 0.0])
        tr.update(t0 + k * DT, pos, np.asarray(e, dtype=float), action)
    return tr


def test_pushing_still_beside_the_frame_for_ten_seconds_is_wedged():
    tr = _track(12.0, [0.6, 0.5, 0.9], FULL)
    assert tr.longest_s["wedged"] == pytest.approx(12.0)
    assert tr.failure_mode(False) == "wedged"
    assert tr.failure_mode(True) == "docked"  # it docked in the end: a recovery, not a failure


@pytest.mark.parametrize(
    ("seconds", "e", "action", "speed"),
    [
        (9.0, [0.6, 0.5, 0.9], FULL, 0.0),  # too short
        (12.0, [0.6, 0.5, 0.9], SOFT, 0.0),  # not pushing
        (12.0, [0.6, 0.5, 0.9], FULL, 0.2),  # moving
        (12.0, [3.0, 0.0, 0.9], FULL, 0.0),  # far from the DS
        (12.0, [0.2, 0.0, 0.9], FULL, 0.0),  # inside the guides, above dock height
    ],
)
def test_other_stretches_are_not_failures_of_a_named_kind(seconds, e, action, speed):
    tr = _track(seconds, e, action, speed)
    assert tr.failure_mode(False) == "other", tr.longest_s


def test_resting_inside_the_guides_off_the_seat_is_landed_off():
    tr = _track(15.0, [0.08, -0.03, 0.04], SOFT)
    assert tr.longest_s["landed_off"] == pytest.approx(15.0)
    assert tr.longest_s["wedged"] == 0.0
    assert tr.failure_mode(False) == "landed_off"
    seated = _track(15.0, [0.02, 0.01, 0.02], SOFT)  # within the strict tolerance: not "off"
    assert seated.failure_mode(False) == "other"


def test_the_longest_stretch_counts_not_the_sum():
    tr = _track(6.0, [0.6, 0.5, 0.9], FULL)
    tr = _track(1.0, [0.6, 0.5, 0.9], FULL, speed_mps=0.5, t0=6.2, tr=tr)  # it moved between
    tr = _track(6.0, [0.6, 0.5, 0.9], FULL, t0=7.4, tr=tr)
    assert max(tr.longest_s.values()) < FailureThresholds().min_duration_s
    assert tr.failure_mode(False) == "other"


def test_counts_name_recoveries():
    rows = [
        {"failure_mode": "docked", "wedged_s": 14.0},
        {"failure_mode": "docked", "wedged_s": 0.0},
        {"failure_mode": "wedged", "wedged_s": 40.0},
        {"failure_mode": "landed_off", "wedged_s": 0.0},
        {"failure_mode": "other", "wedged_s": 0.0},
    ]
    counts = failure_counts(rows)
    assert counts == {
        "docked": 2,
        "wedged": 1,
        "landed_off": 1,
        "other": 1,
        "recovered_from_wedge": 1,
    }


def test_eval_rows_and_summary_carry_the_failure_modes():
    from uwdock.rl.env.config import EnvConfig
    from uwdock.rl.evaluate.episodes import run_episodes
    from uwdock.rl.policy.baselines import PIDController

    cfg = EnvConfig(obs_source="proxy", episode_s=6.0)
    res = run_episodes(PIDController(cfg.action_limits), cfg, 2, seed=3, record=False)
    for row in res.episodes:
        assert row["failure_mode"] in ("docked", "wedged", "landed_off", "other")
        assert row["wedged_s"] >= 0 and row["landed_off_s"] >= 0
        assert row["final_nav_error_m"] == 0.0  # the ideal navigation: the true pose
    modes = res.summary["failure_modes"]
    assert sum(modes[m] for m in ("docked", "wedged", "landed_off", "other")) == 2
