"""rl task geometry, reward terms against hand-computed values, and the DS pose filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, inv_T, make_T
from uwdock.rl.env.estimator import DSPoseFilter, EstimatorConfig
from uwdock.rl.env.rewards import DockingReward, RewardConfig
from uwdock.rl.env.task import (
    DockingTaskConfig,
    docking_errors,
    ds_visible,
    paper_success,
    pegs_seated,
)

CFG = DockingTaskConfig()


def test_docked_pose_has_zero_error_and_seated_pegs():
    T_world_ds = make_T(R_from_rpy(0, 0, 0.7), [3.0, -2.0, 5.0])
    T_world_body = T_world_ds @ CFG.T_ds_target
    e, psi = docking_errors(T_world_body, T_world_ds, CFG)
    np.testing.assert_allclose(e, 0, atol=1e-12)
    assert psi == pytest.approx(0, abs=1e-12)
    assert pegs_seated(T_world_body, T_world_ds, CFG)
    assert paper_success(e, psi, ds_visible(inv_T(T_world_body) @ T_world_ds, CFG), CFG)


def test_errors_are_in_the_body_frame():
    # AUV 2 m above the target, yawed 90 deg: the target is straight below (+z body)
    T_world_ds = np.eye(4)
    T_target = CFG.T_ds_target
    T_world_body = make_T(T_target[:3, :3], T_target[:3, 3] + [0, 0, -2.0])
    e, psi = docking_errors(T_world_body, T_world_ds, CFG)
    assert psi == pytest.approx(0, abs=1e-12)
    np.testing.assert_allclose(e, [0, 0, 2.0], atol=1e-12)
    # displaced 1 m north in the world, the AUV (yawed +90: body y = south) sees it at body +y
    T_world_body2 = make_T(T_target[:3, :3], T_target[:3, 3] + [1.0, 0, 0])
    e2, _ = docking_errors(T_world_body2, T_world_ds, CFG)
    np.testing.assert_allclose(e2, [0, 1.0, 0], atol=1e-12)
    # yawed 20 deg too far: e_psi = -20 deg
    R = R_from_rpy(0, 0, math.radians(110))
    _, psi3 = docking_errors(make_T(R, T_target[:3, 3]), T_world_ds, CFG)
    assert math.degrees(psi3) == pytest.approx(-20.0)


def test_visibility_cone_and_range():
    assert ds_visible(make_T(t=[0, 0, 3.0]), CFG)
    assert not ds_visible(make_T(t=[0, 0, -3.0]), CFG)  # above
    assert not ds_visible(make_T(t=[0, 0, 5.5]), CFG)  # too far
    # along body x the half-angle is 31 deg, along y 38.7 deg
    assert ds_visible(make_T(t=[math.tan(math.radians(30)), 0, 1.0]), CFG)
    assert not ds_visible(make_T(t=[math.tan(math.radians(32)), 0, 1.0]), CFG)
    assert ds_visible(make_T(t=[0, math.tan(math.radians(38)), 1.0]), CFG)
    assert not ds_visible(make_T(t=[0, math.tan(math.radians(39.5)), 1.0]), CFG)


def test_paper_success_thresholds():
    assert paper_success(np.array([0.06, -0.06, 0.09]), math.radians(9), True, CFG)
    assert not paper_success(np.array([0.08, 0, 0]), 0.0, True, CFG)
    assert not paper_success(np.array([0, 0, 0.11]), 0.0, True, CFG)
    assert not paper_success(np.zeros(3), math.radians(11), True, CFG)
    assert not paper_success(np.zeros(3), 0.0, False, CFG)


def test_pegs_not_seated_when_yaw_is_wrong_or_high():
    T_world_ds = np.eye(4)
    T = CFG.T_ds_target.copy()
    assert not pegs_seated(T @ make_T(t=[0, 0, -0.1]), T_world_ds, CFG)  # 10 cm above
    T_wrong = make_T(R_from_rpy(0, 0, 0.0), T[:3, 3])  # not yawed 90 deg to the DS
    assert not pegs_seated(T_wrong, T_world_ds, CFG)


def test_reward_terms_hand_computed():
    r = DockingReward(RewardConfig())
    a = np.array([0.5, 0, 0, 0, 0, -0.5])
    prev = np.zeros(6)
    terms = r(np.array([1.0, -2.0, 4.0]), 0.5, a, prev, False, False, False)
    assert terms["dist"] == pytest.approx(-(1 + 2 + 0.5 * 4))
    assert terms["angle"] == pytest.approx(math.exp(-1.0) - 1)
    assert terms["smooth"] == pytest.approx(-(0.1 / 6) * math.exp(1.0))
    assert terms["collision"] == 0 and terms["mission"] == 0
    assert r(np.zeros(3), 0, a, a, True, True, False)["mission"] == 500
    assert r(np.zeros(3), 0, a, a, False, False, True)["mission"] == -10
    assert r(np.zeros(3), 0, a, a, True, False, False)["collision"] == -10
    linear = DockingReward(RewardConfig(angle_linear=2.0))
    assert linear(np.zeros(3), 0.5, a, a, False, False, False)["angle"] == pytest.approx(
        math.exp(-1.0) - 1 - 2.0 * 0.5 / math.pi
    )
    assert terms["precision"] == 0  # off by default: the paper's reward
    precise = DockingReward(RewardConfig(precision_gain=2.0, precision_scale_m=0.1))
    e = np.array([0.03, -0.04, 0.0])  # 5 cm off
    assert precise(e, 0, a, a, False, False, False)["precision"] == pytest.approx(
        2.0 * math.exp(-0.5)
    )
    gated = DockingReward(RewardConfig(precision_gain=2.0, precision_yaw_scale_rad=0.1))
    assert gated(e, 0.05, a, a, False, False, False)["precision"] == pytest.approx(
        2.0 * math.exp(-0.5) * math.exp(-0.5)
    )
    assert terms["stall"] == 0  # off by default: the paper's reward
    weighted = DockingReward(RewardConfig(weights={"dist": 0.5}))
    assert weighted(np.array([1.0, 0, 0]), 0, a, a, False, False, False)["dist"] == -0.5


def test_smoothness_counts_only_actuated_components():
    """Roll is not actuated: its change costs nothing and N counts the five actuated ones;
    ``smooth_over = "all"`` is the paper's six-component formula."""
    actuated = np.array([1, 1, 1, 0, 1, 1], dtype=bool)
    prev = np.zeros(6)
    a = np.array([0.5, 0, 0, 1.0, 0, -0.5])  # roll jumps by 1
    r = DockingReward(RewardConfig(), actuated=actuated)
    assert r(np.zeros(3), 0, a, prev, False, False, False)["smooth"] == pytest.approx(
        -(0.1 / 5) * math.exp(1.0)
    )
    paper = DockingReward(RewardConfig(smooth_over="all"), actuated=actuated)
    assert paper(np.zeros(3), 0, a, prev, False, False, False)["smooth"] == pytest.approx(
        -(0.1 / 6) * math.exp(2.0)
    )


def test_collision_threshold_adapts():
    r = DockingReward()
    z = np.zeros(3)
    assert r.collision(np.array([0, 0, 1.5]), z) and r.gamma_mps2 == 2.0
    assert not r.collision(np.array([0, 0, 1.5]), z) and r.gamma_mps2 == 1.0  # decays back
    assert r.collision(np.array([0, 0, 1.5]), z)
    r.reset()
    assert r.gamma_mps2 == 1.0


def test_filter_prior_measurement_and_growth():
    rng = np.random.default_rng(0)
    f = DSPoseFilter(EstimatorConfig(prior_sigma_xy_m=1.0))
    truth = make_T(R_from_rpy(0, 0, 0.3), [2.0, 1.0, 5.0])
    errs = []
    for _ in range(400):
        f.reset(truth, rng)
        errs.append(f.x[:2] - truth[:2, 3])
    assert np.std(errs) == pytest.approx(1.0, rel=0.1)  # the prior's spread
    s0 = f.sigma_xyz_m.copy()
    f.predict(4.0)
    assert np.all(f.sigma_xyz_m > s0)
    # a precise measurement pulls the estimate onto it
    f.update(truth, np.diag([1e-4, 1e-4, 1e-4, 1e-4]))
    np.testing.assert_allclose(f.T_world_ds[:3, 3], truth[:3, 3], atol=0.01)
    assert f.time_since_measurement_s == 0 and f.measured


def test_filter_without_fusion_takes_the_measurement():
    f = DSPoseFilter(EstimatorConfig(fuse=False))
    f.reset(np.eye(4), np.random.default_rng(1))
    meas = make_T(R_from_rpy(0, 0, -3.0), [1, 2, 3])
    f.update(meas, np.eye(4))
    np.testing.assert_allclose(f.T_world_ds, meas, atol=1e-12)


def test_filter_gating_rejects_outliers():
    f = DSPoseFilter(EstimatorConfig(gate_sigma=3.0, prior_sigma_xy_m=0.1, prior_sigma_z_m=0.1))
    f.reset(np.eye(4), np.random.default_rng(2))
    assert not f.update(make_T(t=[5.0, 0, 0]), np.diag([1e-3] * 4))
    assert f.update(make_T(t=[0.05, 0, 0]), np.diag([1e-3] * 4))


def test_yaw_of_is_rpy_from_R_yaw_to_one_ulp():
    # math.atan2 (libm) and NumPy's arctan2 agree bit for bit on some CPUs; where NumPy takes
    # its AVX-512 kernels (seen on an AMD EPYC) they differ by at most one unit in the last place
    from uwdock.calibration.frames import rpy_from_R
    from uwdock.rl.env.task import yaw_of

    rng = np.random.default_rng(1)
    for rpy in rng.uniform(-3.2, 3.2, (2000, 3)) * [0.5, 0.45, 1.0]:
        T = make_T(R_from_rpy(*rpy), [0.0, 0.0, 0.0])
        ref = rpy_from_R(T[:3, :3])[2]
        assert abs(yaw_of(T) - ref) <= np.spacing(abs(ref))
        assert abs(math.remainder(yaw_of(T) - rpy[2], 2 * math.pi)) < 1e-12  # the yaw put in
    locked = make_T(R_from_rpy(0.3, np.pi / 2, 1.0), [0.0, 0.0, 0.0])  # gimbal lock
    assert yaw_of(locked) == rpy_from_R(locked[:3, :3])[2]


def test_stall_is_paid_for_pushing_outside_the_guides_without_getting_closer():
    """r_stall (ours, off by default): saturated thrust beyond the guides' clearance with less
    than stall_progress_m of approach since the step before; not on the first step, not when
    approaching, not inside the clearance, not below saturation (the batched twin:
    tests/test_batch_twins.py)."""
    cfg = RewardConfig(stall_penalty=2.0)
    r = DockingReward(cfg)
    full = np.array([1.0, 0, 0, 0, 0, 0])
    soft = np.array([0.5, 0, 0, 0, 0, 0])
    e_far = np.array([0.6, 0.0, 1.0])
    steps = [  # (horizontal error x, action, stall paid)
        (0.60, full, 0.0),  # first step: nothing to compare with
        (0.60, full, -2.0),  # pushing, not closer
        (0.595, full, -2.0),  # 5 mm closer: still a stall
        (0.50, full, 0.0),  # 9.5 cm closer: approaching
        (0.50, soft, 0.0),  # not saturated
        (0.20, full, 0.0),  # inside the guides' clearance
        (0.20, full, 0.0),
    ]
    got = []
    for x, a, _ in steps:
        e = e_far.copy()
        e[0] = x
        got.append(r(e, 0.0, a, a, False, False, False)["stall"])
    assert got == [s for *_, s in steps]
    r.reset()
    assert r(e_far, 0.0, full, full, False, False, False)["stall"] == 0.0  # a new episode
