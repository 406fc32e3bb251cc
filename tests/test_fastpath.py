"""Free-flight fast path (sim.fastpath) against the PhysX path it stands in for."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import sapien
from scipy.spatial.transform import Rotation

from uwdock.calibration.frames import (
    R_from_rpy,
    make_T,
    ned_pose_to_zup,
    pos_quat_from_T,
    rotation_angle_deg,
)
from uwdock.sim.docking_station import DockingStationConfig, build_tank
from uwdock.sim.fastpath import (
    OBSTACLE_COLS,
    StaticObstacles,
    _overlaps,
    body_params,
    hydro_params,
    physx_wrench,
)
from uwdock.sim.physics import FREE_FLIGHT_MARGIN_M, VehicleBody, make_physics_scene
from uwdock.sim.vehicle import (
    Current,
    CurrentConfig,
    Hydrodynamics,
    VehicleConfig,
    VehicleRandomisation,
)

NEUTRAL = replace(VehicleConfig(), net_buoyancy_kg=0.0)
#: The paths differ only by PhysX's float32 arithmetic: over 3 s they agree to ~1e-5 m,
#: ~1e-3 deg and ~6e-6 m/s (rad/s); the bounds below leave a factor of ~10.
POS_TOL_M, ROT_TOL_DEG, VEL_TOL, ACC_TOL = 1e-4, 0.01, 1e-4, 2e-3
HULL_BOTTOM_M = 0.45  # bottom hull (capsule r 0.15 at z = +0.30) below the origin
CONTACT_OFFSET_M = 0.01  # SAPIEN's default, on every shape


def _pair(cfg: VehicleConfig, current: CurrentConfig | None = None, seed: int = 0):
    """The same vehicle twice, in two scenes: fast path on, and PhysX only."""
    current = current or CurrentConfig(mode="constant")
    return [
        VehicleBody(
            make_physics_scene(), cfg, Current(current, np.random.default_rng(seed)), fast_path=f
        )
        for f in (True, False)
    ]


def _floor(scene: sapien.Scene, top_depth_m: float) -> sapien.Entity:
    """A static 10 x 10 m slab whose top is ``top_depth_m`` below the surface (z-up world)."""
    builder = scene.create_actor_builder().add_box_collision(half_size=(5.0, 5.0, 0.5))
    builder.set_initial_pose(sapien.Pose([0.0, 0.0, -top_depth_m - 0.5]))
    return builder.build_static("floor")


@pytest.mark.parametrize("seed", [0, 1])
def test_free_flight_matches_physx(seed):
    """Random vehicle, drifting current, tilted and moving start, random wrenches for 3 s."""
    rng = np.random.default_rng(seed)
    cfg = VehicleRandomisation().sample(VehicleConfig(), rng)
    current = CurrentConfig(
        mode="varying", drift_std_mps=0.1, drift_time_constant_s=2.0, drift_knot_interval_s=0.5
    )
    fast, ref = _pair(cfg, current, seed)
    T0 = make_T(R_from_rpy(0.3, -0.25, 1.0), [1.0, 2.0, 5.0])
    nu0 = np.array([0.3, 0.1, -0.1, 0.3, -0.3, 0.4])
    for body in (fast, ref):
        body.reset(T0, nu0)
    for wrench in rng.uniform(-1, 1, (15, 6)) * [200, 100, 200, 20, 100, 50]:
        for body in (fast, ref):
            body.step(wrench, 0.2)
        assert fast.last_step_fast and not ref.last_step_fast
        Ta, Tb = fast.T_world_ned_body_frd, ref.T_world_ned_body_frd
        assert np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) < POS_TOL_M
        assert rotation_angle_deg(Ta[:3, :3], Tb[:3, :3]) < ROT_TOL_DEG
        np.testing.assert_allclose(fast.nu, ref.nu, rtol=0, atol=VEL_TOL)
        np.testing.assert_allclose(fast.nu_dot, ref.nu_dot, rtol=0, atol=ACC_TOL)
        np.testing.assert_array_equal(fast.thrust_n, ref.thrust_n)
        assert fast.time_s == ref.time_s
    assert np.linalg.norm(Tb[:3, 3] - T0[:3, 3]) > 0.5  # it did go somewhere
    imu_a, imu_b = fast.read_imu(), ref.read_imu()  # same rng: only the state differs
    np.testing.assert_allclose(imu_a.specific_force_frd_mps2, imu_b.specific_force_frd_mps2,
                               rtol=0, atol=ACC_TOL)  # fmt: skip


def test_one_substep_mirrors_the_physx_integrator():
    """Spinning fast about all axes (gyroscopic term ~1e-3 rad/s per substep) under a large
    wrench: one substep agrees to float32 round-off, so the integrator is PhysX's."""
    cfg = VehicleRandomisation().sample(VehicleConfig(), np.random.default_rng(4))
    fast, ref = _pair(cfg)
    T0 = make_T(R_from_rpy(0.5, -0.4, 2.0), [0.0, 0.0, 3.0])
    nu0 = np.array([0.5, -0.3, 0.2, 1.2, -0.9, 1.5])
    for body in (fast, ref):
        body.reset(T0, nu0)
        body.step([300.0, -100.0, 200.0, 30.0, 80.0, -60.0], 1.0 / 300.0)
    Ta, Tb = fast.T_world_ned_body_frd, ref.T_world_ned_body_frd
    assert np.abs(Ta[:3, 3] - Tb[:3, 3]).max() < 1e-6
    assert np.abs(Ta[:3, :3] - Tb[:3, :3]).max() < 1e-6
    np.testing.assert_allclose(fast.nu, ref.nu, rtol=0, atol=2e-6)


def test_physx_wrench_realises_the_model_acceleration():
    """Force and torque make PhysX's body (m_e, I_e at the CG) reach the NumPy model's nu_dot."""
    rng = np.random.default_rng(7)
    cfg = VehicleRandomisation().sample(VehicleConfig(), rng)
    hydro = Hydrodynamics(cfg)
    body = VehicleBody(make_physics_scene(), cfg)
    P, B = hydro_params(hydro), body_params(body.engine_mass_kg, body.engine_inertia_kgm2,
                                            body.component)  # fmt: skip
    me, ie = B[0], B[1:4]
    assert me == pytest.approx(cfg.mass_kg + sum(cfg.added_mass[:3]) / 3, rel=1e-12)
    np.testing.assert_allclose(ie, np.add(cfg.inertia_kgm2, cfg.added_mass[3:]), rtol=1e-12)
    c = np.asarray(cfg.cg_m)
    S = np.diag([1.0, -1.0, -1.0])  # FRD <-> FLU
    for _ in range(10):
        T_ned = make_T(R_from_rpy(*rng.uniform(-1.2, 1.2, 3)), [*rng.normal(size=2), 0.0])
        T_ned[2, 3] = rng.uniform(-0.2, 0.6)  # near the surface: the free surface matters
        R_ned, R_zup = T_ned[:3, :3], ned_pose_to_zup(T_ned)[:3, :3]
        p_zup = ned_pose_to_zup(T_ned)[:3, 3]
        depth_cb = float((T_ned @ np.r_[cfg.cb_m, 1.0])[2])
        q = pos_quat_from_T(make_T(R_zup))[1]
        nu, v_c, tau = rng.normal(size=6) * 0.5, rng.normal(size=3) * 0.3, rng.normal(size=6) * 100
        w_frd = nu[3:]
        v_cg_frd = nu[:3] + np.cross(w_frd, c)
        v_cg_zup, w_zup = R_zup @ (S @ v_cg_frd), R_zup @ (S @ w_frd)
        current_zup = np.diag([1.0, -1.0, -1.0]) @ v_c  # NED -> z-up world
        no_planes = np.zeros((0, 4))
        force, torque = physx_wrench(
            P, B, p_zup, q, v_cg_zup, w_zup, current_zup[None], tau[None], 0,
            np.zeros((0, 4)), no_planes, np.zeros(5),
        )  # fmt: skip
        nu_dot = hydro.acceleration(R_ned, nu, v_c, tau, depth_cb)
        a_cg = nu_dot[:3] + np.cross(nu_dot[3:], c) + np.cross(w_frd, v_cg_frd)
        t_cg = ie * nu_dot[3:] + np.cross(w_frd, ie * w_frd)
        np.testing.assert_allclose(force, R_zup @ (S @ (me * a_cg)), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(torque, R_zup @ (S @ t_cg), rtol=1e-9, atol=1e-9)


def test_heavy_vehicle_lands_on_the_floor_through_physx():
    """A sinking vehicle flies fast until the floor is within reach, then PhysX takes over and
    it settles exactly as with PhysX only."""
    cfg = replace(VehicleConfig(), net_buoyancy_kg=-5.0)
    fast, ref = (
        VehicleBody(scene, cfg, fast_path=f)
        for scene, f in ((make_physics_scene(), True), (make_physics_scene(), False))
    )
    for body in (fast, ref):
        _floor(body.scene, 6.0)
        body.reset(make_T(t=[0.0, 0.0, 5.0]))
    used_fast = []
    for _ in range(30):  # 6 s
        for body in (fast, ref):
            body.step(np.zeros(6), 0.2)
        used_fast.append(fast.last_step_fast)
        if fast.last_step_fast:  # the PhysX run stayed clear of the floor during this step
            gap = 6.0 - (ref.T_world_ned_body_frd[2, 3] + HULL_BOTTOM_M)
            assert gap > FREE_FLIGHT_MARGIN_M
    k = used_fast.index(False)  # ~2 s to fall the 0.55 m, then PhysX for good
    assert k >= 5 and not any(used_fast[k:])
    for body in (fast, ref):
        assert body.T_world_ned_body_frd[2, 3] == pytest.approx(6.0 - HULL_BOTTOM_M, abs=0.01)
        assert np.max(np.abs(body.nu)) < 1e-3
    np.testing.assert_allclose(
        fast.T_world_ned_body_frd, ref.T_world_ned_body_frd, rtol=0, atol=1e-4
    )


@pytest.mark.parametrize(("clearance_m", "fast"), [(0.09, True), (0.065, False)])
def test_contact_test_threshold(clearance_m, fast):
    """A neutral vehicle at rest stays put: free flight iff the hull clears the floor by the
    margin plus both contact offsets (0.07 m)."""
    body = VehicleBody(make_physics_scene(), NEUTRAL)
    _floor(body.scene, 5.0 + HULL_BOTTOM_M + clearance_m)
    body.reset(make_T(t=[0.0, 0.0, 5.0]))
    body.step(np.zeros(6), 0.2)
    assert body.last_step_fast is fast
    assert FREE_FLIGHT_MARGIN_M + 2 * CONTACT_OFFSET_M == pytest.approx(0.07)


def test_tank_boxes_and_obstacle_updates():
    """The tank's boxes come out right; a moved static actor is seen; a second dynamic body
    (which only PhysX can move) turns the fast path off."""
    ds_cfg = DockingStationConfig()
    scene = make_physics_scene()
    build_tank(scene, ds_cfg, visual=False, surface_lid=True)
    body = VehicleBody(scene, NEUTRAL)
    boxes = StaticObstacles(scene, body.component).boxes()
    assert boxes.shape == (6, OBSTACLE_COLS)
    L, W, D = ds_cfg.tank_length_m, ds_cfg.tank_width_m, ds_cfg.tank_depth_m
    co = CONTACT_OFFSET_M
    floor = boxes[np.argmin(boxes[:, 2])]
    assert floor[5] == pytest.approx(-D + co, abs=1e-6)  # floor top, z-up
    lid = boxes[np.argmax(boxes[:, 5])]
    assert lid[2] == pytest.approx(0.0 - co, abs=1e-6)  # lid bottom at the surface
    assert boxes[:, 3].max() == pytest.approx(L / 2 + ds_cfg.tank_wall_thickness_m + co)
    assert boxes[:, 4].max() == pytest.approx(W / 2 + ds_cfg.tank_wall_thickness_m + co)
    # mid-water: fast; just under the lid (upper hulls 0.43 m above the origin): PhysX
    body.reset(make_T(t=[0.0, 0.0, 2.5]))
    body.step(np.zeros(6), 0.2)
    assert body.last_step_fast
    body.reset(make_T(t=[0.0, 0.0, 0.47]))
    body.step(np.zeros(6), 0.2)
    assert not body.last_step_fast
    # a static actor that moves next to the vehicle is picked up
    body.reset(make_T(t=[0.0, 0.0, 2.5]))
    slab = _floor(scene, 10.0)
    body.step(np.zeros(6), 0.2)
    assert body.last_step_fast
    slab.set_pose(sapien.Pose([0.0, 0.0, -2.5 - HULL_BOTTOM_M - 0.52]))  # top 2 cm below
    body.step(np.zeros(6), 0.2)
    assert not body.last_step_fast
    slab.set_pose(sapien.Pose([0.0, 0.0, -20.0]))
    body.step(np.zeros(6), 0.2)
    assert body.last_step_fast
    scene.create_actor_builder().add_sphere_collision(radius=0.1).build("ball")
    body.step(np.zeros(6), 0.2)
    assert not body.last_step_fast


def test_fast_path_is_deterministic_and_can_be_disabled():
    cfg = VehicleRandomisation().sample(VehicleConfig(), np.random.default_rng(9))
    current = CurrentConfig(mode="varying", drift_std_mps=0.1, drift_time_constant_s=2.0)
    wrenches = np.random.default_rng(9).uniform(-1, 1, (10, 6)) * [200, 100, 200, 20, 100, 50]
    runs = []
    for _ in range(2):
        body = VehicleBody(make_physics_scene(), cfg, Current(current, np.random.default_rng(3)))
        body.reset(make_T(R_from_rpy(0.2, 0.1, -1.0), [0.0, 0.0, 4.0]))
        for w in wrenches:
            body.step(w, 0.2)
            assert body.last_step_fast
        runs.append((body.T_world_ned_body_frd, body.nu, body.nu_dot, body.thrust_n))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
    off = VehicleBody(make_physics_scene(), cfg, fast_path=False)
    off.reset(make_T(t=[0.0, 0.0, 4.0]))
    off.step(np.zeros(6), 0.2)
    assert not off.last_step_fast


def _obstacle_row(R: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """An oriented box as :class:`StaticObstacles` hands it to the kernel."""
    h = np.abs(R) @ half
    row = np.zeros(OBSTACLE_COLS)
    row[:6] = np.concatenate([centre - h, centre + h])
    row[6] = 1.0
    row[7:10], row[10:13], row[13:22] = centre, half, R.reshape(9)
    return row


def _box_distance(points: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Distance of points (n, 3) to an obstacle row's oriented box (0 inside)."""
    R = row[13:22].reshape(3, 3)
    local = (points - row[7:10]) @ R
    return np.linalg.norm(local - np.clip(local, -row[10:13], row[10:13]), axis=1)


def test_oriented_obstacle_test_never_misses_a_touch():
    """Random hull boxes swept between two origin positions against random oriented boxes:
    wherever a point of the swept hull comes within the margin of the obstacle, the test says
    a contact is possible; and it clears many pairs whose world boxes overlap."""
    rng = np.random.default_rng(4)
    margin = 0.05
    cleared = 0
    u = np.linspace(-1.0, 1.0, 7)
    grid = np.stack(np.meshgrid(u, u, u, indexing="ij"), axis=-1).reshape(-1, 3)
    for _ in range(400):
        R0 = Rotation.random(random_state=rng).as_matrix()
        hull = np.zeros((1, 7))
        hull[0, :3] = rng.uniform(-0.3, 0.3, 3)
        hull[0, 3:6] = rng.uniform(0.05, 0.6, 3)
        hull[0, 6] = np.linalg.norm(hull[0, :3]) + np.linalg.norm(hull[0, 3:6])
        a, b = rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.5, 0.5, 3) * rng.uniform(0, 0.3)
        lo, hi = np.minimum(a, a + b), np.maximum(a, a + b)
        row = _obstacle_row(
            Rotation.random(random_state=rng).as_matrix(),
            rng.uniform(-1.2, 1.2, 3),
            rng.uniform(0.02, 0.8, 3),
        )
        possible = _overlaps(hull, row[None], lo, hi, R0, 0.0, margin)
        # the swept hull: its box at every corner of the origin's path box
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])  # fmt: skip
        body = hull[0, :3] + grid * hull[0, 3:6]
        pts = (corners[:, None, :] + (body @ R0.T)[None]).reshape(-1, 3)
        if _box_distance(pts, row).min() <= margin:
            assert possible
        h = np.abs(R0) @ hull[0, 3:6] + margin
        c = R0 @ hull[0, :3]
        world_overlap = np.all(lo + c - h <= row[3:6]) and np.all(hi + c + h >= row[:3])
        cleared += bool(world_overlap and not possible)
    assert cleared >= 40


def test_tilted_plate_only_claims_its_own_space():
    """A plate tilted 45 deg: a vehicle inside the plate's world box but well clear of the
    plate flies the fast path, with PhysX's trajectory; one at the plate is handed to PhysX."""
    rng = np.random.default_rng(2)
    wrenches = rng.uniform(-1, 1, (5, 6)) * [40, 20, 40, 4, 20, 10]
    tilt = sapien.Pose(q=Rotation.from_euler("y", 45, degrees=True).as_quat()[[3, 0, 1, 2]])
    bodies = []
    for fast_path in (True, False):
        scene = make_physics_scene()
        builder = scene.create_actor_builder().add_box_collision(half_size=(3.0, 3.0, 0.05))
        builder.set_initial_pose(sapien.Pose([0.0, 0.0, -8.0]) * tilt)
        builder.build_static("plate")
        body = VehicleBody(scene, NEUTRAL, fast_path=fast_path)
        # 1.5 m above the plate's surface (along its normal), inside its 4.3 m world box
        normal = Rotation.from_euler("y", 45, degrees=True).apply([0.0, 0.0, 1.0])
        start = np.array([0.0, 0.0, -8.0]) + 1.5 * normal
        body.reset(make_T(t=[start[0], -start[1], -start[2]]))  # z-up -> NED
        bodies.append(body)
    fast, ref = bodies
    for w in wrenches:
        for body in bodies:
            body.step(w, 0.2)
        assert fast.last_step_fast
    np.testing.assert_allclose(
        fast.T_world_ned_body_frd, ref.T_world_ned_body_frd, rtol=0, atol=1e-4
    )
    boxes = StaticObstacles(fast.scene, fast.component).boxes()
    assert boxes.shape == (1, OBSTACLE_COLS) and boxes[0, 6] == 1.0
    assert np.all(boxes[0, 3:6] - boxes[0, :3] > 4.0)  # the world box the old test used
    fast.reset(make_T(t=[0.0, 0.0, 8.0 - 0.6]))  # the plate passes 0.6 m below the origin
    fast.step(np.zeros(6), 0.2)
    assert not fast.last_step_fast
