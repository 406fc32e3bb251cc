"""Vehicle dynamics against analytic ground truth (sim.vehicle + sim.physics, 300 Hz PhysX)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import sapien

from uwdock.calibration.frames import R_from_rpy, make_T, rotation_angle_deg, rpy_from_R
from uwdock.dockcore.config import ConfigError, from_dict, to_dict
from uwdock.sim.fastpath import accel_fn
from uwdock.sim.physics import VehicleBody, make_physics_scene
from uwdock.sim.thrusters import ThrusterArrayConfig
from uwdock.sim.vehicle import (
    Current,
    CurrentConfig,
    Hydrodynamics,
    Imu,
    ImuConfig,
    VehicleConfig,
    VehicleRandomisation,
)

NEUTRAL = replace(VehicleConfig(), net_buoyancy_kg=0.0)
QUIET_IMU = ImuConfig(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _instant_thrusters(cfg: VehicleConfig) -> VehicleConfig:
    """``cfg`` with lag-free thrusters (time constant 0)."""
    ts = tuple(replace(t, time_constant_s=0.0) for t in cfg.thrusters.thrusters)
    return replace(cfg, thrusters=replace(cfg.thrusters, thrusters=ts))


def _body(cfg: VehicleConfig = NEUTRAL, current: Current | None = None) -> VehicleBody:
    return VehicleBody(make_physics_scene(), cfg, current)


def _rpy_deg(auv: VehicleBody) -> np.ndarray:
    return np.degrees(rpy_from_R(auv.T_world_ned_body_frd[:3, :3]))


def _run(auv: VehicleBody, wrench, seconds: float) -> None:
    for _ in range(round(seconds / 0.2)):
        auv.step(wrench, 0.2)


# --------------------------------------------------------------------------- model pieces


def test_scalar_accel_matches_numpy_reference():
    rng = np.random.default_rng(3)
    cfg = VehicleRandomisation().sample(VehicleConfig(), rng)
    hydro = Hydrodynamics(cfg)
    fast = accel_fn(hydro)
    for _ in range(20):
        R = R_from_rpy(*rng.uniform(-1.5, 1.5, 3))
        nu, v_c, tau = rng.normal(size=6), rng.normal(size=3) * 0.3, rng.normal(size=6) * 100
        for depth_cb in (math.inf, rng.uniform(-0.3, 0.3), -1.0):  # deep, in the band, above
            ref = hydro.acceleration(R, nu, v_c, tau, depth_cb)
            got = fast(*R[2], *nu, *(R.T @ v_c), *tau, depth_cb)
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10)


def test_free_surface_buoyancy_and_floating_depth():
    """Buoyancy fades linearly through the surface band; a level vehicle floats where what is
    left of it equals the weight, and settles there in free flight (no lid, no contact)."""
    cfg = VehicleConfig()
    hydro = Hydrodynamics(cfg)
    band = cfg.surface_band_m
    assert hydro.submerged_fraction(math.inf) == 1.0
    assert hydro.submerged_fraction(0.5 * band) == 1.0
    assert hydro.submerged_fraction(0.0) == pytest.approx(0.5)
    assert hydro.submerged_fraction(-0.5 * band) == 0.0
    assert hydro.submerged_fraction(-5.0) == 0.0
    d_eq = band * (cfg.weight_n / cfg.buoyancy_n - 0.5)  # CB depth where s B = W
    assert hydro.restoring_wrench(np.eye(3), d_eq)[2] == pytest.approx(0.0, abs=1e-9)
    assert hydro.restoring_wrench(np.eye(3), d_eq + 0.01)[2] < 0  # deeper: pushed up
    assert hydro.restoring_wrench(np.eye(3), d_eq - 0.01)[2] > 0  # higher: pulled down
    auv = _body(cfg)
    auv.reset(make_T(t=[0.0, 0.0, 3.0]))
    fast_steps = 0
    for _ in range(300):  # 60 s
        auv.step(np.zeros(6), 0.2)
        fast_steps += auv.last_step_fast
    depth_cb = auv.T_world_ned_body_frd[2, 3] + cfg.cb_m[2]
    assert depth_cb == pytest.approx(d_eq, abs=0.01)
    assert abs(auv.nu[2]) < 0.03  # bobbing out slowly: the heave damping is light
    assert fast_steps == 300  # nothing to touch in open water


def test_restoring_wrench_analytic():
    cfg = VehicleConfig()
    hydro = Hydrodynamics(cfg)
    g = cfg.gravity_mps2
    level = hydro.restoring_wrench(np.eye(3))
    np.testing.assert_allclose(level, [0, 0, -cfg.net_buoyancy_kg * g, 0, 0, 0], atol=1e-9)
    # rolled by phi: righting moment -(W z_g - B z_b) sin(phi) about x (CG below, CB above)
    phi = math.radians(20)
    w = hydro.restoring_wrench(R_from_rpy(phi, 0, 0))
    k_expected = -(cfg.weight_n * cfg.cg_m[2] - cfg.buoyancy_n * cfg.cb_m[2]) * math.sin(phi)
    assert w[3] == pytest.approx(k_expected, rel=1e-12)
    assert w[3] < 0  # rights the vehicle


def test_added_mass_coriolis_is_workless_and_damping_dissipates():
    hydro = Hydrodynamics(VehicleConfig())
    rng = np.random.default_rng(0)
    for _ in range(10):
        nu = rng.normal(size=6)
        assert nu @ hydro.added_mass_coriolis_wrench(nu) == pytest.approx(0.0, abs=1e-9)
        assert nu @ hydro.rigid_body_coriolis_wrench(nu) == pytest.approx(0.0, abs=1e-9)
        assert nu @ hydro.damping_wrench(nu) < 0


# --------------------------------------------------------------------------- closed-loop physics


def test_reset_pose_and_velocity_round_trip():
    auv = _body()
    T = make_T(R_from_rpy(0.1, -0.2, 2.5), [1.0, -2.0, 4.0])
    nu = np.array([0.3, -0.1, 0.05, 0.02, -0.03, 0.1])
    auv.reset(T, nu)
    np.testing.assert_allclose(auv.T_world_ned_body_frd, T, atol=1e-6)
    np.testing.assert_allclose(auv.nu, nu, atol=1e-6)
    # SAPIEN's actor is z-up / FLU: depth 4 m is z = -4 there
    assert auv.entity.get_pose().p[2] == pytest.approx(-4.0, abs=1e-6)


def test_neutral_body_holds_depth():
    auv = _body()
    auv.reset(make_T(t=[0.0, 0.0, 5.0]))
    _run(auv, np.zeros(6), 20.0)
    assert abs(auv.T_world_ned_body_frd[2, 3] - 5.0) < 1e-4
    # released tilted: it rocks upright but does not sink or rise
    auv.reset(make_T(R_from_rpy(math.radians(10), math.radians(10), 0.3), [0.0, 0.0, 5.0]))
    depths = []
    for _ in range(100):
        auv.step(np.zeros(6))
        depths.append(auv.T_world_ned_body_frd[2, 3])
    assert np.max(np.abs(np.array(depths) - 5.0)) < 0.005
    assert abs(depths[-1] - 5.0) < 0.001


def test_positive_buoyancy_rises_at_terminal_speed():
    cfg = VehicleConfig()  # +3 kg
    auv = _body(cfg)
    auv.reset(make_T(t=[0.0, 0.0, 20.0]))
    _run(auv, np.zeros(6), 20.0)
    lin, quad = cfg.linear_damping[2], cfg.quadratic_damping[2]
    f = cfg.net_buoyancy_kg * cfg.gravity_mps2
    w_t = (-lin + math.sqrt(lin * lin + 4 * quad * f)) / (2 * quad)
    assert -auv.nu[2] == pytest.approx(w_t, rel=0.01)


@pytest.mark.parametrize("linear", [0.0, 20.0])
def test_terminal_surge_speed(linear):
    cfg = replace(NEUTRAL, linear_damping=(linear, *NEUTRAL.linear_damping[1:]))
    auv = _body(cfg)
    auv.reset(make_T(t=[0.0, 0.0, 5.0]))
    force = 100.0
    _run(auv, [force, 0, 0, 0, 0, 0], 15.0)
    quad = cfg.quadratic_damping[0]
    u_t = (-linear + math.sqrt(linear**2 + 4 * quad * force)) / (2 * quad)
    if linear == 0.0:
        assert u_t == pytest.approx(math.sqrt(force / quad))
    assert auv.nu[0] == pytest.approx(u_t, rel=0.01)
    assert np.max(np.abs(_rpy_deg(auv)[:2])) < 0.1  # no steady pitch: drag acts at the origin


@pytest.mark.parametrize("axis", [0, 1])
def test_roll_and_pitch_right_themselves(axis):
    auv = _body()
    rpy = [0.0, 0.0, 0.0]
    rpy[axis] = math.radians(20.0)
    auv.reset(make_T(R_from_rpy(*rpy), [0.0, 0.0, 5.0]))
    angles = []
    for _ in range(50):  # 10 s
        auv.step(np.zeros(6))
        angles.append(abs(_rpy_deg(auv)[axis]))
    assert angles[0] < 20.0  # moving back from the first control step on
    assert max(angles[25:]) < max(angles[:25])  # decaying
    assert angles[-1] < 1.0


def test_drifts_with_the_current():
    v_c = np.array([0.15, -0.1, 0.0])
    current = Current(CurrentConfig(mode="constant", velocity_ned_mps=tuple(v_c)))
    auv = _body(NEUTRAL, current)
    auv.reset(make_T(R_from_rpy(0, 0, 0.7), [0.0, 0.0, 5.0]))
    _run(auv, np.zeros(6), 60.0)
    v_ned = auv.T_world_ned_body_frd[:3, :3] @ auv.nu[:3]
    np.testing.assert_allclose(v_ned, v_c, rtol=0, atol=0.01 * np.linalg.norm(v_c))


def test_large_added_mass_step_response_and_stability():
    m = 150.0
    cfg = _instant_thrusters(
        replace(
            NEUTRAL,
            mass_kg=m,
            cg_m=(0.0, 0.0, 0.0),  # no CG lever: the surge/pitch coupling would blur F/(m+mA)
            cb_m=(0.0, 0.0, -0.2),
            added_mass=(2 * m, 2 * m, 2 * m, 28.0, 50.0, 44.0),
            linear_damping=(0.0,) * 6,
            quadratic_damping=(0.0,) * 6,
        )
    )
    auv = _body(cfg)
    auv.reset(make_T(t=[0.0, 0.0, 5.0]))
    force, torque = 90.0, 20.0
    auv.step([force, 0, 0, 0, 0, torque], 0.5)
    expected_u = force / (m + 2 * m)
    expected_r = torque / (cfg.inertia_kgm2[2] + cfg.added_mass[5])
    assert auv.nu[0] / 0.5 == pytest.approx(expected_u, rel=0.02)
    assert auv.nu[5] / 0.5 == pytest.approx(expected_r, rel=0.02)
    assert auv.nu_dot[0] == pytest.approx(expected_u, rel=0.02)
    # stability: 20 s of random full-scale commands at 300 Hz, damping off
    rng = np.random.default_rng(1)
    for _ in range(100):
        auv.step(rng.uniform(-1, 1, 6) * [280, 140, 260, 0, 150, 70], 0.2)
        assert np.all(np.isfinite(auv.nu)) and np.max(np.abs(auv.nu)) < 50


def test_thruster_lag_through_the_body():
    auv = _body()
    auv.reset(make_T(t=[0.0, 0.0, 5.0]))
    auv.step([100.0, 0, 0, 0, 0, 0], 0.2)  # 0.2 s = one time constant
    frac = auv.thrust_n[:2] / auv.thrust_command_n[:2]
    np.testing.assert_allclose(frac, 1 - math.exp(-1), rtol=1e-6)  # dt is float32 in PhysX


def test_imu_reads_gravity_and_acceleration():
    # CG = CB = origin and neutral: a tilted body at rest stays at rest, the IMU reads R^T (-g)
    cfg = replace(NEUTRAL, imu=QUIET_IMU, cg_m=(0.0, 0.0, 0.0), cb_m=(0.0, 0.0, 0.0))
    auv = _body(cfg)
    rpy = (0.2, -0.1, 1.0)
    auv.reset(make_T(R_from_rpy(*rpy), [0.0, 0.0, 3.0]))
    auv.step(np.zeros(6), 0.2)
    reading = auv.read_imu()
    g = NEUTRAL.gravity_mps2
    expected = R_from_rpy(*rpy).T @ np.array([0.0, 0.0, -g])
    np.testing.assert_allclose(reading.specific_force_frd_mps2, expected, atol=1e-4)
    assert reading.depth_m == pytest.approx(3.0, abs=1e-4)
    # under a surge force it adds the kinematic acceleration (X - drag) / (m + X_udot): the
    # last substep's, and the control step's mean (delta-velocity) that the IMU reports
    u0 = auv.nu[0]
    auv.step([100.0, 0, 0, 0, 0, 0], 0.4)
    u = auv.nu[0]
    drag = (cfg.linear_damping[0] + cfg.quadratic_damping[0] * abs(u)) * u
    a_expected = (auv.thrust_n[:2].sum() - drag) / (cfg.mass_kg + cfg.added_mass[0])
    assert auv.nu_dot[0] == pytest.approx(a_expected, rel=0.01)
    assert auv.read_imu().acceleration_frd_mps2[0] == pytest.approx((u - u0) / 0.4, rel=0.01)
    # noise and bias are drawn from the generator: same seed, same reading
    imu_cfg = ImuConfig()
    a = Imu(imu_cfg, g, np.random.default_rng(5)).measure(np.eye(3), np.zeros(6), np.zeros(3), 1)
    b = Imu(imu_cfg, g, np.random.default_rng(5)).measure(np.eye(3), np.zeros(6), np.zeros(3), 1)
    np.testing.assert_array_equal(a.specific_force_frd_mps2, b.specific_force_frd_mps2)
    assert abs(a.specific_force_frd_mps2[2] + g) < 0.5


def test_step_rejects_a_duration_off_the_grid():
    auv = _body()
    with pytest.raises(ValueError, match="multiple"):
        auv.step(np.zeros(6), 0.201)


# --------------------------------------------------------------------------- current, randomisation


def test_random_current_in_range_and_seeded():
    cfg = CurrentConfig(mode="random")
    draws = np.array([Current(cfg, np.random.default_rng(s)).velocity_ned(3.0) for s in range(50)])
    assert np.all(np.abs(draws[:, :2]) <= 0.2) and np.all(draws[:, 2] == 0)
    assert np.std(draws[:, 0]) > 0.05
    a = Current(cfg, np.random.default_rng(7)).velocity_ned(0.0)
    np.testing.assert_array_equal(a, Current(cfg, np.random.default_rng(7)).velocity_ned(9.0))


def test_varying_current_is_continuous_bounded_and_deterministic():
    cfg = CurrentConfig(mode="varying", drift_std_mps=0.05, drift_time_constant_s=10.0)
    cur = Current(cfg, np.random.default_rng(2))
    t = np.arange(0.0, 120.0, 0.01)
    v = cur.velocity_ned_at(t)
    assert np.max(np.abs(np.diff(v, axis=0))) < 0.01  # continuous (linear between knots)
    assert np.max(np.linalg.norm(v, axis=1)) <= cfg.max_speed_mps + 1e-12
    assert np.ptp(v[:, 0]) > 0.02  # it does move
    np.testing.assert_allclose(v[0], cur.mean_ned)
    other = Current(cfg, np.random.default_rng(2))  # queried in another order: same values
    np.testing.assert_array_equal(other.velocity_ned(100.0), cur.velocity_ned(100.0))


def test_vehicle_randomisation_ranges_and_seed():
    base = VehicleConfig()
    rnd = VehicleRandomisation()
    a = rnd.sample(base, np.random.default_rng(11))
    assert a == rnd.sample(base, np.random.default_rng(11))
    assert a != rnd.sample(base, np.random.default_rng(12))
    assert abs(a.mass_kg / base.mass_kg - 1) <= rnd.mass_rel
    assert np.all(np.abs(np.subtract(a.cg_m, base.cg_m)) <= rnd.cg_offset_m)
    assert abs(a.net_buoyancy_kg - base.net_buoyancy_kg) <= rnd.net_buoyancy_kg
    a.validate()
    # a randomised vehicle still runs, and switching draws keeps the actor
    auv = _body()
    auv.set_config(a, nominal_config=base)
    auv.reset(make_T(t=[0.0, 0.0, 5.0]))
    auv.step([50.0, 0, 0, 0, 0, 0])
    assert auv.component.get_mass() == pytest.approx(a.mass_kg + sum(a.added_mass[:3]) / 3)
    assert isinstance(auv.config.thrusters, ThrusterArrayConfig)


def test_configs_round_trip_through_toml_dicts():
    for cls in (VehicleConfig, VehicleRandomisation, CurrentConfig):
        assert from_dict(cls, to_dict(cls())) == cls()
    with pytest.raises(ConfigError, match="mass_kg"):
        from_dict(VehicleConfig, {"mass_kg": -1.0})
    with pytest.raises(ConfigError, match="mode"):
        from_dict(CurrentConfig, {"mode": "tidal"})


def _rk4_reference(hydro, p, R, nu, v_c, tau, seconds, dt):
    """Integrate the NED/FRD model directly (RK4, R re-orthonormalised): no PhysX, no frames."""

    def skew(a):
        return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])

    def f(p, R, nu):
        return R @ nu[:3], R @ skew(nu[3:]), hydro.acceleration(R, nu, v_c, tau)

    for _ in range(round(seconds / dt)):
        k1 = f(p, R, nu)
        k2 = f(*(x + dt / 2 * k for x, k in zip((p, R, nu), k1, strict=True)))
        k3 = f(*(x + dt / 2 * k for x, k in zip((p, R, nu), k2, strict=True)))
        k4 = f(*(x + dt * k for x, k in zip((p, R, nu), k3, strict=True)))
        p, R, nu = (
            x + dt / 6 * (a + 2 * b + 2 * c + d)
            for x, a, b, c, d in zip((p, R, nu), k1, k2, k3, k4, strict=True)
        )
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
    return p, R, nu


def test_physx_body_follows_the_model_in_full_6dof():
    """The SAPIEN bridge (z-up/FLU, CoM at the CG, folded mass, gyroscopic term) reproduces a
    direct integration of the Fossen model through a tumbling manoeuvre in a current."""
    rng = np.random.default_rng(0)
    cfg = _instant_thrusters(VehicleRandomisation().sample(VehicleConfig(), rng))
    v_c = np.array([0.1, -0.15, 0.02])
    auv = _body(cfg, Current(CurrentConfig(mode="constant", velocity_ned_mps=tuple(v_c))))
    T0 = make_T(R_from_rpy(0.3, -0.2, 1.0), [1.0, 2.0, 5.0])
    nu0 = np.array([0.3, 0.1, -0.1, 0.2, -0.3, 0.4])
    auv.reset(T0, nu0)
    p, R, nu = T0[:3, 3], T0[:3, :3], nu0
    hydro = Hydrodynamics(cfg)
    for _ in range(10):  # 2 s
        wrench = rng.uniform(-1, 1, 6) * [200, 100, 200, 0, 100, 50]
        setpoint = auv.allocator.setpoint_from_thrust(auv.allocator.allocate(wrench))
        tau = auv.thrusters.wrench_from_thrust(auv.thrusters.thrust_from_setpoint(setpoint))
        auv.step(wrench, 0.2)
        p, R, nu = _rk4_reference(hydro, p, R, nu, v_c, tau, 0.2, 1 / 600)
    T = auv.T_world_ned_body_frd
    assert np.linalg.norm(T[:3, 3] - p) < 0.005
    assert rotation_angle_deg(T[:3, :3], R) < 0.5
    np.testing.assert_allclose(auv.nu, nu, atol=0.01)


def test_heavy_vehicle_lands_on_a_floor():
    """Contacts: a negatively buoyant vehicle settles with its bottom hull (0.45 m) on a floor."""
    scene = make_physics_scene()
    floor = scene.create_actor_builder().add_box_collision(half_size=(5.0, 5.0, 0.5))
    floor.set_initial_pose(sapien.Pose([0.0, 0.0, -6.5])).build_static("floor")  # top 6 m deep
    auv = VehicleBody(scene, replace(VehicleConfig(), net_buoyancy_kg=-5.0))
    auv.reset(make_T(t=[0.0, 0.0, 5.0]))
    _run(auv, np.zeros(6), 6.0)
    assert auv.T_world_ned_body_frd[2, 3] == pytest.approx(6.0 - 0.45, abs=0.01)
    assert np.max(np.abs(auv.nu)) < 1e-3
