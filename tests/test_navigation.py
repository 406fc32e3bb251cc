"""The vehicle's navigation (issue 30 point 3): dead reckoning over a DVL, an AHRS and a depth
sensor, checked against closed-form drift, the Gauss-Markov statistics, the frame seam (a fresh
relative measurement is exact whatever the drift) and the env and batched env using it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, inv_T, make_T, rpy_from_R
from uwdock.dockcore.config import ConfigError, from_dict
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.task import docking_errors
from uwdock.sim.navigation import (
    NAV_PRESETS,
    RESET_DRAWS,
    STEP_DRAWS,
    NavConfig,
    NavErrors,
    correction,
)

MEMS = NavConfig("mems-ahrs-dvl")


def _T(yaw_rad: float, xyz=(1.0, 2.0, 3.0), roll_rad=0.05, pitch_rad=-0.03) -> np.ndarray:
    return make_T(R_from_rpy(roll_rad, pitch_rad, yaw_rad), xyz)


def test_ideal_is_the_true_pose_and_draws_nothing():
    nav = NavErrors(NavConfig(), 2)
    assert nav.ideal and nav.step_draws == 0
    T = np.stack([_T(0.3), _T(-2.0, (4, 5, 6))])
    nav.reset(0, None)
    nav.step(0.2, T, np.ones((2, 3)), np.ones((2, 3)) * 2.0, None)
    assert np.array_equal(nav.T_nav(T, [9.0, 9.0]), T)  # not even the depth reading
    assert np.array_equal(nav.error_m(), [0.0, 0.0])
    assert np.array_equal(nav.dvl_velocity(np.ones((2, 3))), np.ones((2, 3)))


def test_a_constant_heading_error_drifts_as_the_chord_of_the_turned_velocity():
    """Straight run at v for t with heading error d: |dp| = 2 v t sin(d / 2), and the AHRS
    attitude differs from the truth by d in yaw only."""
    cfg = NavConfig("mems-ahrs-dvl", heading_tau_s=1e6, tilt_sigma_deg=0.0, dvl_scale_sigma_rel=0)
    nav = NavErrors(cfg, 1)
    nav.reset(0, np.zeros(RESET_DRAWS))
    d = math.radians(2.0)
    nav.att_err_rad[0] = [0.0, 0.0, d]
    T = _T(0.7, roll_rad=0.0, pitch_rad=0.0)
    v = np.array([[0.5, 0.0, 0.0]])
    dt, steps = 0.2, 300
    for _ in range(steps):
        nav.step(dt, T, v, v, np.zeros((1, STEP_DRAWS)))
    t = dt * steps
    assert nav.error_m()[0] == pytest.approx(2 * 0.5 * t * math.sin(d / 2), rel=1e-4)
    roll, pitch, yaw = rpy_from_R(nav.T_nav(T, [3.0])[0, :3, :3])
    assert (roll, pitch) == pytest.approx((0.0, 0.0), abs=1e-6)
    assert yaw == pytest.approx(0.7 + d * math.exp(-t / 1e6), abs=1e-9)  # Gauss-Markov decay


def test_a_dvl_scale_error_drifts_along_the_track_and_depth_takes_its_offset():
    cfg = NavConfig("mems-ahrs-dvl", heading_sigma_deg=0.0, tilt_sigma_deg=0.0)
    nav = NavErrors(cfg, 1)
    z = np.zeros(RESET_DRAWS)
    z[3], z[6] = 2.0, -1.5  # surge scale +2 sigma, depth offset -1.5 sigma
    nav.reset(0, z)
    assert nav.scale[0, 0] == pytest.approx(1.0 + 2 * cfg.resolved().dvl_scale_sigma_rel)
    yaw = 0.4
    T = _T(yaw, roll_rad=0.0, pitch_rad=0.0)
    v = np.array([[0.4, 0.0, 0.0]])
    for _ in range(100):
        nav.step(0.2, T, v, v, np.zeros((1, STEP_DRAWS)))
    along = 0.02 * 0.4 * 20.0  # scale error x speed x time
    assert nav.dp_xy_m[0] == pytest.approx([along * math.cos(yaw), along * math.sin(yaw)])
    T_nav = nav.T_nav(T, [3.25])[0]
    assert T_nav[2, 3] == pytest.approx(3.25 - 1.5 * 0.02)


def test_attitude_errors_have_the_stated_spread_and_correlation_time():
    """Gauss-Markov: stationary sigma, autocorrelation exp(-lag / tau), across many vehicles."""
    n = 4000
    nav = NavErrors(MEMS, n)
    rng = np.random.default_rng(5)
    for i in range(n):
        nav.reset(i, rng.standard_normal(RESET_DRAWS))
    r = MEMS.resolved()
    T = np.tile(np.eye(4), (n, 1, 1))
    v = np.zeros((n, 3))
    start = nav.att_err_rad.copy()
    dt, tau = 0.2, r.heading_tau_s
    for _ in range(round(tau / dt)):
        nav.step(dt, T, v, v, rng.standard_normal((n, STEP_DRAWS)))
    sigma = math.radians(r.heading_sigma_deg)
    assert np.std(nav.att_err_rad[:, 2]) == pytest.approx(sigma, rel=0.05)
    assert np.std(nav.att_err_rad[:, 0]) == pytest.approx(math.radians(r.tilt_sigma_deg), rel=0.05)
    corr = np.corrcoef(start[:, 2], nav.att_err_rad[:, 2])[0, 1]
    assert corr == pytest.approx(math.exp(-1.0), abs=0.04)


def test_a_fresh_relative_measurement_is_exact_in_the_drifted_frame():
    """The seam: a pose measured relative to the vehicle and placed with the navigation pose
    (correction @ the truth-frame pose) gives the true docking errors back, whatever the drift;
    so the policy sees the drift only through stale estimates and the attitude error."""
    T_true = _T(1.1, (3.0, -1.0, 4.0))
    T_nav = _T(1.13, (3.4, -0.7, 4.05), roll_rad=0.051, pitch_rad=-0.028)
    T_world_ds = make_T(R_from_rpy(0.0, 0.0, -0.4), [1.0, 0.5, 6.0])
    C = correction(T_nav, T_true)
    assert np.allclose(C @ T_true, T_nav)
    T_meas = C @ T_world_ds
    assert np.allclose(inv_T(T_nav) @ T_meas, inv_T(T_true) @ T_world_ds)
    from uwdock.rl.env.task import DockingTaskConfig

    task = DockingTaskConfig()
    e_nav, psi_nav = docking_errors(T_nav, T_meas, task)
    e_true, psi_true = docking_errors(T_true, T_world_ds, task)
    assert np.allclose(e_nav, e_true, atol=1e-12)
    # yaw read off a tilted frame moves at second order in the tilt (0.05 rad here: 3e-5 rad)
    assert psi_nav == pytest.approx(psi_true, abs=1e-4)
    batch = correction(np.stack([T_nav, T_true]), np.stack([T_true, T_true]))
    assert np.allclose(batch[0], C) and np.allclose(batch[1], np.eye(4))


def test_rows_step_alike_alone_or_in_a_batch():
    rng = np.random.default_rng(2)
    resets = rng.standard_normal((3, RESET_DRAWS))
    batch = NavErrors(MEMS, 3)
    singles = [NavErrors(MEMS, 1) for _ in range(3)]
    for i in range(3):
        batch.reset(i, resets[i])
        singles[i].reset(0, resets[i])
    T = np.stack([_T(0.1 * i, (i, 2 * i, 3.0)) for i in range(3)])
    for _ in range(20):
        v_true = rng.normal(0, 0.3, (3, 3))
        v_meas = v_true + rng.normal(0, 0.01, (3, 3))
        z = rng.standard_normal((3, STEP_DRAWS))
        batch.step(0.2, T, v_true, v_meas, z)
        for i, s in enumerate(singles):
            s.step(0.2, T[i : i + 1], v_true[i : i + 1], v_meas[i : i + 1], z[i : i + 1])
    depth = np.array([3.0, 3.1, 3.2])
    T_b = batch.T_nav(T, depth)
    for i, s in enumerate(singles):
        assert np.allclose(T_b[i], s.T_nav(T[i : i + 1], depth[i : i + 1])[0], atol=1e-12)
    batch.copy_row(0, singles[2])
    assert np.array_equal(batch.dp_xy_m[0], singles[2].dp_xy_m[0])


def test_the_ahrs_attitude_adds_its_errors_to_fossens_zyx_angles():
    rng = np.random.default_rng(5)
    nav = NavErrors(MEMS, 50)
    nav.att_err_rad = rng.normal(0.0, 0.05, (50, 3))
    rpy = np.column_stack(
        [rng.uniform(-0.6, 0.6, 50), rng.uniform(-1.4, 1.4, 50), rng.uniform(-3.1, 3.1, 50)]
    )
    R = np.stack([R_from_rpy(*a) for a in rpy])
    R_nav = nav.R_nav(R)
    for i in range(50):  # against the frames module's closed form, angle by angle
        want = R_from_rpy(*(rpy[i] + nav.att_err_rad[i]))
        np.testing.assert_allclose(R_nav[i], want, atol=1e-12)
        np.testing.assert_allclose(rpy_from_R(R_nav[i]), rpy[i] + nav.att_err_rad[i], atol=1e-9)
    np.testing.assert_allclose(
        R_nav @ R_nav.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    nav.att_err_rad[:] = 0.0  # no error: the true attitude back
    np.testing.assert_allclose(nav.R_nav(R), R, atol=1e-12)


def test_the_config_takes_a_preset_and_refuses_an_unknown_one():
    cfg = from_dict(EnvConfig, {"nav": {"preset": "mems-ahrs-dvl", "heading_sigma_deg": 2.0}})
    r = cfg.nav.resolved()
    assert (
        r.heading_sigma_deg == 2.0 and r.tilt_sigma_deg == NAV_PRESETS[MEMS.preset].tilt_sigma_deg
    )
    assert EnvConfig().nav.is_ideal
    with pytest.raises(ConfigError, match=r"nav\.preset: unknown navigation preset"):
        from_dict(EnvConfig, {"nav": {"preset": "gps"}})
    with pytest.raises(ConfigError, match=r"nav\.heading_sigma_deg"):
        from_dict(EnvConfig, {"nav": {"heading_sigma_deg": float("nan")}})


def _run(env, steps: int, action) -> dict:
    env.reset(seed=11)
    info = {}
    for _ in range(steps):
        _, _, term, trunc, info = env.step(action)
        if term or trunc:
            break
    return info


def test_the_env_navigates_with_drift_and_starts_from_the_usbl_fix():
    from uwdock.rl.env.docking_env import DockingEnv
    from uwdock.sim.usbl import UsblConfig

    base = {"obs_source": "acoustic", "episode_s": 30.0}
    ideal = DockingEnv(from_dict(EnvConfig, base | {"usbl": {"preset": "evologics-s2cr"}}))
    mems = DockingEnv(
        from_dict(
            EnvConfig,
            base | {"usbl": {"preset": "evologics-s2cr"}, "nav": {"preset": "mems-ahrs-dvl"}},
        )
    )
    surge = np.array([0.4, 0, 0, 0, 0, 0])
    # the DS prior: the survey's 1 m spread (ideal preset) against the first USBL fix's
    ideal.reset(seed=11)
    mems.reset(seed=11)
    assert ideal.filter.sigma_xyz_m[0] < 1.0  # the survey prior, fused with the first fix
    fix_sigma = mems.usbl.sigma_m(
        float(np.linalg.norm(mems.world.T_world_ds[:3, 3] - mems.world.T_world_body[:3, 3]))
    )
    assert mems.filter.sigma_xyz_m == pytest.approx([fix_sigma] * 3, rel=1e-6)
    info_i = _run(ideal, 100, surge)
    info_m = _run(mems, 100, surge)
    assert info_i["nav_error_m"] == 0.0
    assert 0.0 < info_m["nav_error_m"] < 1.0  # 20 s of dead reckoning at a MEMS grade
    # the vehicle's own motion is the same: navigation only changes what it believes
    assert np.allclose(info_i["T_world_body"], info_m["T_world_body"])
    assert isinstance(UsblConfig().preset, str)


def test_the_batched_env_navigates_as_the_scalar_one():
    """Both simulators carry the same navigation: the per-episode errors drawn at reset (the
    batch takes the slot env's), a drift of the same size, zero when ideal."""
    from uwdock.rl.env.batch_env import BatchDockingEnv

    cfg = from_dict(
        EnvConfig,
        {"obs_source": "acoustic", "episode_s": 30.0, "nav": {"preset": "mems-ahrs-dvl"}},
    )
    batch = BatchDockingEnv(cfg, 4, seed=3)
    batch.reset()
    for i in range(4):
        assert np.array_equal(batch.nav.scale[i], batch.envs[i].nav.scale[0])
        assert np.array_equal(batch.T_nav[i], batch.envs[i].T_nav)
    assert not np.allclose(batch.nav.scale, 1.0)
    infos = []
    for _ in range(60):
        batch.step_async(np.tile([0.4, 0, 0, 0, 0, 0], (4, 1)))
        _, _, _, infos = batch.step_wait()
    drift = [i["nav_error_m"] for i in infos]
    assert all(0.0 < d < 1.0 for d in drift), drift
    ideal = BatchDockingEnv(from_dict(EnvConfig, {"obs_source": "acoustic"}), 2, seed=3)
    ideal.reset()
    ideal.step_async(np.zeros((2, 6)))
    assert [i["nav_error_m"] for i in ideal.step_wait()[3]] == [0.0, 0.0]
