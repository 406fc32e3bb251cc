"""bench/bench_recipe_seeds.py's statistics on hand-made numbers and episodes (no simulation)."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from tests.conftest import bench_module


@pytest.fixture(scope="module")
def rs():
    had = "bench_docking" in sys.modules
    yield from bench_module("bench_recipe_seeds")
    if not had:  # registered by compare_docking.bench_docking_module
        sys.modules.pop("bench_docking", None)


def _eps(outcomes, collisions=None):
    """outcomes: (docked strictly, time to dock or None) per episode 0, 1, ..."""
    hits = collisions or [0] * len(outcomes)
    return [
        {"episode": k, "success_strict": ok, "success": ok, "time_to_dock_s": t, "collisions": c}
        for k, ((ok, t), c) in enumerate(zip(outcomes, hits, strict=True))
    ]


def _row(condition, eps):
    return {"condition": condition, "per_episode": eps}


# --- intervals, IQM, bootstrap ----------------------------------------------------------------


def test_wilson_interval_of_95_in_100(rs):
    from scipy.stats import binomtest

    lo, hi = rs.wilson_interval(95, 100)
    # by hand: p = .95, z = 1.95996 (z² = 3.84146): centre (.95 + z²/200) / (1 + z²/100)
    # = .969207 / 1.038415 = .933353, half z * sqrt(.95 * .05 / 100 + z²/40000) / 1.038415
    # = 1.95996 * .0238964 / 1.038415 = .045103
    assert (lo, hi) == pytest.approx((0.88825, 0.97846), abs=1e-5)
    ci = binomtest(95, 100).proportion_ci(0.95, method="wilson")
    assert (lo, hi) == pytest.approx((ci.low, ci.high), abs=1e-12)
    assert rs.wilson_interval(100, 100)[1] == pytest.approx(1.0)
    assert rs.wilson_interval(0, 100)[0] == pytest.approx(0.0)
    assert rs.wilson_interval(0, 0) == (0.0, 1.0)


def test_iqm_of_eight_seeds_is_the_mean_of_the_middle_four(rs):
    from scipy.stats import trim_mean

    x = [1, 0.97, 0.9, 1, 0.99, 1, 0.95, 1]  # sorted: .9 .95 | .97 .99 1 1 | 1 1
    assert rs.iqm(x) == pytest.approx((0.97 + 0.99 + 1 + 1) / 4)  # 0.99
    assert rs.iqm(x) == pytest.approx(trim_mean(x, 0.25))  # n a multiple of 4: rliable's


def test_iqm_weighs_the_straddling_scores_by_their_fraction(rs):
    from scipy.stats import trim_mean

    # n = 5: [1.25, 3.75] of [0, 5): weights 0, 3/4, 1, 3/4, 0 over 5/2
    assert rs.iqm([10, 0, 4, 1, 2]) == pytest.approx((0.75 * 1 + 2 + 0.75 * 4) / 2.5)  # 2.3
    assert trim_mean([10, 0, 4, 1, 2], 0.25) == pytest.approx(7 / 3)  # not the same
    # n = 6: [1.5, 4.5]: weights 0, 1/2, 1, 1, 1/2, 0 over 3
    assert rs.iqm([0, 1, 2, 3, 5, 9]) == pytest.approx((0.5 + 2 + 3 + 2.5) / 3)  # 8/3
    # n = 3: [0.75, 2.25]: weights 1/4, 1, 1/4 over 3/2
    assert rs.iqm([0, 3, 6]) == pytest.approx((0 + 3 + 1.5) / 1.5)  # 3
    assert rs.iqm([0, 1, 3]) == pytest.approx((0.25 * 0 + 1 + 0.25 * 3) / 1.5)  # 7/6
    assert rs.iqm([0.7]) == pytest.approx(0.7)
    assert rs.iqm([0.2, 0.6]) == pytest.approx(0.4)
    # along an axis, one IQM per row (as the bootstrap calls it)
    rows = np.array([[10, 0, 4, 1, 2], [1, 1, 1, 1, 1]], dtype=float)
    assert rs.iqm(rows, axis=-1) == pytest.approx([2.3, 1.0])
    with pytest.raises(ValueError):
        rs.iqm([])


def test_bootstrap_interval_by_hand_and_repeatable(rs):
    # two values: a resample's mean is 0, 1/2 or 1 with chances 1/4, 1/2, 1/4, so the 2.5th and
    # 97.5th percentiles are 0 and 1
    assert rs.bootstrap_interval([0.0, 1.0], np.mean) == pytest.approx((0.0, 1.0))
    x = [0.9, 0.95, 0.97, 0.99, 1, 1, 1, 1]
    a = rs.bootstrap_interval(x, rs.iqm)
    assert a == rs.bootstrap_interval(x, rs.iqm)  # fixed generator seed
    assert 0.9 <= a[0] <= rs.iqm(x) <= a[1] <= 1.0
    assert rs.bootstrap_interval([0.3] * 5, np.median) == pytest.approx((0.3, 0.3))
    assert rs.bootstrap_interval([0.4], np.min) == pytest.approx((0.4, 0.4))
    assert rs.bootstrap_interval([], np.min) == (None, None)


def test_across_seeds_worst_median_iqm(rs):
    x = [1, 0.97, 0.9, 1, 0.99, 1, 0.95, 1]
    a = rs.across_seeds(x, higher_is_better=True)
    assert a["seeds"] == 8 and a["undefined"] == 0
    assert a["worst"] == pytest.approx(0.9)
    assert a["median"] == pytest.approx((0.99 + 1) / 2)
    assert a["iqm"] == pytest.approx(0.99)
    # a resample's worst is never below the observed worst: the interval is on its better side
    assert a["worst_ci95"][0] == pytest.approx(0.9)
    assert 0.9 <= a["worst_ci95"][1] <= 1.0
    assert a["median_ci95"][0] <= a["median"] <= a["median_ci95"][1]
    # lower is better (a time ratio): the worst is the largest; an undefined seed is left out
    r = rs.across_seeds([0.6, 0.7, None, 0.65], higher_is_better=False)
    assert r["worst"] == pytest.approx(0.7) and r["undefined"] == 1 and r["seeds"] == 3
    assert r["median"] == pytest.approx(0.65)
    assert r["iqm"] == pytest.approx((0.25 * 0.6 + 0.65 + 0.25 * 0.7) / 1.5)  # n = 3
    none = rs.across_seeds([None], higher_is_better=False)
    assert none["worst"] is None and none["iqm_ci95"] == (None, None)


# --- the policy against the PID on the same episodes ------------------------------------------


def test_time_ratio_over_the_episodes_both_docked(rs):
    pid = _eps([(True, 20.0), (True, 20.0), (False, None), (True, 16.0)])
    pol = _eps([(True, 10.0), (False, None), (True, 12.0), (True, 12.0)])
    t = rs.time_ratio(pid, pol)
    assert t["both_docked"] == 2  # episodes 0 and 3
    assert t["time_to_dock_s"] == pytest.approx((10 + 12) / 2)
    assert t["pid_time_to_dock_s"] == pytest.approx((20 + 16) / 2)
    assert t["time_ratio"] == pytest.approx(11 / 18)
    assert rs.time_ratio(pid[2:3], pol[2:3])["time_ratio"] is None  # none both docked


def test_seed_stats_of_a_camera_row_and_a_hard_row(rs):
    # 20 episodes: the policy docks 19 (all but episode 7), the PID 18 (all but 3 and 11)
    pol_out = [(k != 7, None if k == 7 else 10.0) for k in range(20)]
    pid_out = [(k not in (3, 11), None if k in (3, 11) else 15.0) for k in range(20)]
    pol_hits = [0] * 10 + [1] * 10  # 0.5 a episode
    pid_hits = [2] * 20  # 2 a episode
    pid = {"camera": _row("camera", _eps(pid_out, pid_hits)),
           "all": _row("all", _eps([(True, 30.0)] * 4)),
           "coastal": _row("coastal", _eps([(True, 30.0)] * 4))}  # fmt: skip
    pol = {"camera": _row("camera", _eps(pol_out, pol_hits)),
           "all": _row("all", _eps([(True, 18.0), (True, 24.0), (False, None), (True, 30.0)])),
           "turbid": _row("turbid", _eps([(True, 1.0)] * 4))}  # fmt: skip
    s = rs.seed_stats(pid, pol)
    assert s["episodes"] == 20
    assert s["strict"] == pytest.approx(0.95)
    assert s["strict_ci95"] == pytest.approx(rs.wilson_interval(19, 20))
    assert s["pid_strict"] == pytest.approx(0.9)
    assert s["both_docked"] == 17  # 20 less episodes 3, 7, 11
    assert s["time_ratio"] == pytest.approx(10 / 15)
    assert s["collisions"] == pytest.approx(0.5) and s["pid_collisions"] == pytest.approx(2.0)
    assert s["collisions_diff"] == pytest.approx(-1.5)
    lo, hi = s["collisions_diff_ci95"]
    assert lo < -1.5 < hi < 0  # diffs -2 (10 episodes) and -1 (10): the mean stays in [-2, -1]
    assert -2 <= lo and hi <= -1
    # the interval is bench_docking.paired_change's, on the same episodes
    change = s["paired_change"]
    assert change["collisions_change_ci95"] == pytest.approx([lo, hi])
    assert change["strict_gained"] == 2 and change["strict_lost"] == 1
    # the hard rows: only those the PID flew too
    assert set(s["hard_rows"]) == {"all"}
    h = s["hard_rows"]["all"]
    assert h["strict"] == pytest.approx(0.75) and h["pid_strict"] == pytest.approx(1.0)
    assert h["time_ratio"] == pytest.approx(24 / 30)  # (18 + 24 + 30) / 3 over 30
    with pytest.raises(ValueError):
        rs.seed_stats({"all": pid["all"]}, pol)  # no camera row


def test_pooled_pairs_each_seed_with_the_pid_on_its_episodes(rs):
    pid = {"camera": _row("camera", _eps([(True, 20.0), (True, 10.0)], [2, 2]))}
    a = {"camera": _row("camera", _eps([(True, 10.0), (True, 5.0)], [0, 1]))}
    b = {"camera": _row("camera", _eps([(False, None), (True, 10.0)], [1, 1]))}
    (p,) = rs.pooled_vs_pid(pid, [a, b])
    assert p["condition"] == "camera" and p["seeds"] == 2 and p["episodes"] == 4
    assert p["strict"] == pytest.approx(0.75) and p["pid_strict"] == pytest.approx(1.0)
    assert p["both_docked"] == 3
    assert p["time_ratio"] == pytest.approx((10 + 5 + 10) / (20 + 10 + 10))
    assert p["collisions_diff"] == pytest.approx((-2 - 1 - 1 - 1) / 4)


# --- the bar ----------------------------------------------------------------------------------


def _seed(strict=0.98, ratio=0.6, d=-0.5, ci=(-0.8, -0.2)):
    return {"strict": strict, "time_ratio": ratio, "collisions_diff": d,
            "collisions_diff_ci95": ci}  # fmt: skip


def test_bar_pass_fail_incomplete(rs):
    bar, verdict = rs.judge([_seed(), _seed(strict=0.95, ratio=0.75)], expected=2)
    assert verdict == "PASS" and [b["verdict"] for b in bar] == ["PASS"] * 3
    assert bar[0]["value"] == pytest.approx(0.95) and bar[1]["value"] == pytest.approx(0.75)
    bar, verdict = rs.judge([_seed(), _seed(strict=0.94)], expected=2)
    assert verdict == "FAIL" and [b["pass"] for b in bar] == [False, True, True]
    bar, verdict = rs.judge([_seed(), _seed(ratio=0.76)], expected=2)
    assert verdict == "FAIL" and [b["pass"] for b in bar] == [True, False, True]
    bar, verdict = rs.judge([_seed(), _seed(ratio=None)], expected=2)  # none both docked
    assert verdict == "FAIL" and not bar[1]["pass"]
    bar, verdict = rs.judge([_seed(), _seed(ci=(-0.8, 0.0))], expected=2)  # touches 0
    assert verdict == "FAIL" and not bar[2]["pass"] and bar[2]["value"] == "1 of 2 seeds"
    bar, verdict = rs.judge([_seed()], expected=2)  # a seed missing, none fails
    assert verdict == "INCOMPLETE" and {b["verdict"] for b in bar} == {"INCOMPLETE"}
    bar, verdict = rs.judge([_seed(strict=0.5)], expected=2)  # more seeds cannot mend it
    assert verdict == "FAIL" and bar[0]["verdict"] == "FAIL"
    assert rs.judge([], expected=2)[1] == "INCOMPLETE"


# --- learning curves and the evaluation files -------------------------------------------------


def test_learning_curves_put_stage_two_after_stage_one(rs):
    def h(*pairs):
        return [{"step": s, "success_rate_strict": v} for s, v in pairs]

    hist = {
        "seed 0": [h((10, 0.0), (20, 0.5)), h((5, 0.8), (10, 0.9))],
        "seed 1": [h((10, 0.2), (20, 0.7), (30, 0.9)), h((5, 0.6))],
        "seed 2": [h((10, 0.4))],  # still in stage 1
    }
    points, bounds = rs.learning_curves(hist, "success_rate_strict")
    assert bounds == [30]  # stage 1's last evaluation, the largest over seeds
    by = {(p["stage"], p["step"]): p for p in points}
    first = by[(0, 10)]
    assert first["x"] == 10 and first["seeds"] == 3
    assert (first["median"], first["min"], first["max"]) == pytest.approx((0.2, 0.0, 0.4))
    assert by[(0, 30)]["seeds"] == 1
    s2 = by[(1, 5)]
    assert s2["x"] == 35 and s2["median"] == pytest.approx(0.7)
    assert s2["per_seed"] == {"seed 0": 0.8, "seed 1": 0.6}
    assert by[(1, 10)]["x"] == 40 and by[(1, 10)]["seeds"] == 1
    assert [p["x"] for p in points] == sorted(p["x"] for p in points)


def test_eval_state(rs, tmp_path):
    want = {"episodes": 100, "seed": 95000, "controllers": ["policy"]}
    path = tmp_path / "seed_0.json"
    assert rs.eval_state(path, want)[0] == "run"  # not there
    cfg = {"episodes": 100, "seed": 95000, "controllers": ["policy"], "complete": False}
    path.write_text(json.dumps({"bench_config": cfg, "rows": []}))
    assert rs.eval_state(path, want) == ("run", "incomplete (interrupted)")
    path.write_text(json.dumps({"bench_config": {**cfg, "complete": True}, "rows": []}))
    assert rs.eval_state(path, want) == ("ok", "")
    state, why = rs.eval_state(path, {**want, "seed": 91000})
    assert state == "other" and "91000" in why
    # the PID flown with more episodes than the seeds is used, on its first ones
    assert rs.eval_state(path, {**want, "episodes": 50}, at_least=rs.AT_LEAST) == ("ok", "")
    state, why = rs.eval_state(path, {**want, "episodes": 50})
    assert state == "other" and "wanted 50" in why
    state, _ = rs.eval_state(path, {**want, "episodes": 200}, at_least=rs.AT_LEAST)
    assert state == "other"  # fewer than the seeds flew: not enough


def test_the_pid_rows_are_cut_to_the_episodes_the_seeds_flew(rs):
    eps = [{"episode": k, "success_strict": k % 2 == 0} for k in range(100)]
    rows = {"camera": {"per_episode": eps}, "long approach": {"per_episode": eps}}
    cut = rs.first_episodes(rows, 100, 50)
    assert [e["episode"] for e in cut["camera"]["per_episode"]] == list(range(100))
    assert [e["episode"] for e in cut["long approach"]["per_episode"]] == list(range(50))
    assert len(rows["long approach"]["per_episode"]) == 100  # the input is left as it was
