"""The batched physics (sim.batch) against the scalar VehicleBody: same wrenches, same
trajectory, in free flight and through PhysX contacts (the surface lid, the docking station):
to the bit with each vehicle in its own PhysX scene (``contact="own"``), within PhysX's own
sensitivity with all of them in one shared scene (``contact="shared"``, sim.contact_scene)."""

from __future__ import annotations

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.dockcore.config import replace
from uwdock.rl.env.task import DockingTaskConfig
from uwdock.sim.batch import BatchVehicles
from uwdock.sim.vehicle import CurrentConfig, ImuConfig, VehicleConfig
from uwdock.sim.world import DockingWorld
from uwdock.sim.world_config import WorldConfig

_QUIET_IMU = ImuConfig(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _world(cfg: WorldConfig, seed: int, T_world_body: np.ndarray, ds_xy=(0.5, 0.2)) -> DockingWorld:
    w = DockingWorld(cfg)
    T_ds = make_T(R_from_rpy(0, 0, 0.3), [ds_xy[0], ds_xy[1], w.floor_z_m])
    w.reset(T_ds, T_world_body, np.random.default_rng(seed))
    return w


def _compare(
    cfg: WorldConfig,
    T_start: np.ndarray,
    wrench_of_step,
    n_steps: int,
    contact: str = "own",
    nudge_m: float = 0.0,
):
    """Step a scalar world and the first slot of a two-vehicle batch with the same wrenches
    (the batch's start moved ``nudge_m`` along x); return the largest difference of pose, body
    velocity and mean acceleration, and how many steps went through PhysX."""
    scalar = _world(cfg, 1, T_start)
    twin = _world(cfg, 1, T_start)
    other = _world(cfg, 2, make_T(np.eye(3), [3.0, 1.0, 3.0]))
    batch = BatchVehicles([twin.vehicle, other.vehicle], contact=contact)
    batch.state[0, 0] += nudge_m
    worst, physx = 0.0, 0
    for k in range(n_steps):
        w = wrench_of_step(k)
        scalar.vehicle.step(w, 0.2)
        batch.step(np.stack([w, -w]), 0.2)
        v = scalar.vehicle
        worst = max(
            worst,
            np.abs(v.T_world_ned_body_frd - batch.T_world_body()[0]).max(),
            np.abs(v.nu - batch.nu()[0]).max(),
            np.abs(v.nu_dot_mean - batch.nu_dot_mean()[0]).max(),
        )
        assert v.last_step_fast == (not batch.last_physx[0]), f"step {k}: paths differ"
        physx += int(batch.last_physx[0])
    return worst, physx, scalar, batch


def test_free_flight_contact_and_surface_equal_the_scalar_body():
    """Driven down onto the DS (PhysX), then up through the free surface (free flight)."""
    cfg = replace(WorldConfig(), randomise_vehicle=True)
    T0 = make_T(R_from_rpy(0, 0, 1.0), [0.8, 0.0, 1.9])

    def wrench(k):
        w = np.array([60.0, 10.0, 120.0 if k < 60 else 200.0, 0.0, 3.0, 5.0])
        return w if k < 100 else -0.5 * w

    worst, physx, scalar, _ = _compare(cfg, T0, wrench, 150)
    assert physx > 10
    assert scalar.T_world_body[2, 3] < 0.6  # it reached the surface
    assert worst < 1e-9


def test_docking_station_contact_equals_the_scalar_body():
    """Pushed down onto the DS frame, then sideways: PhysX contacts with the DS."""
    cfg = replace(WorldConfig(), current=CurrentConfig(mode="varying"))
    T0 = make_T(R_from_rpy(0, 0, 0.2), [0.5, 0.2, 2.2])

    def wrench(k):
        return np.array([0.0, 40.0 if k > 30 else 0.0, 268.0, 0.0, 0.0, 20.0])

    worst, physx, scalar, _ = _compare(cfg, T0, wrench, 60)
    assert physx > 20
    assert scalar.T_world_body[2, 3] > 3.0  # it went down to the DS
    assert worst < 1e-9


_SCENARIOS = {
    "surface": (
        replace(WorldConfig(), randomise_vehicle=True),
        make_T(R_from_rpy(0, 0, 1.0), [0.8, 0.0, 1.9]),
        lambda k: (
            (1.0 if k < 100 else -0.5)
            * np.array([60.0, 10.0, 120.0 if k < 60 else 200.0, 0.0, 3.0, 5.0])
        ),
        150,
    ),
    "docking station": (
        replace(WorldConfig(), current=CurrentConfig(mode="varying")),
        make_T(R_from_rpy(0, 0, 0.2), [0.5, 0.2, 2.2]),
        lambda k: np.array([0.0, 40.0 if k > 30 else 0.0, 268.0, 0.0, 0.0, 20.0]),
        60,
    ),
}


@pytest.mark.parametrize("scenario", sorted(_SCENARIOS))
def test_shared_contact_scene_stays_within_physx_own_sensitivity(scenario):
    """All vehicles in one PhysX scene (offset positions, a twin body, copied statics): the
    same paths as the scalar body, and a trajectory no farther from it than PhysX's own answer
    to a 1 um nudge of the start. Largest difference of pose, body velocity and mean
    acceleration over the run, measured shared / nudged: surface 0.025 / 0.019, docking
    station 0.013 / 0.025 (poses alone: 1.8 / 1.2 mm and 1.2 / 1.4 mm)."""
    cfg, T0, wrench, n = _SCENARIOS[scenario]
    shared, physx, _, batch = _compare(cfg, T0, wrench, n, contact="shared")
    nudged, physx_nudged, _, _ = _compare(cfg, T0, wrench, n, contact="own", nudge_m=1e-6)
    assert physx == physx_nudged and physx > 20
    assert batch.physx_steps >= physx
    assert shared < 0.1
    assert shared < 3.0 * max(nudged, 1e-3)


def test_shared_contact_scene_keeps_slots_apart_and_idle_twins_asleep():
    """Eight vehicles pressed onto eight differently placed stations, in one scene: each
    touches only its own station's copy; a vehicle that leaves PhysX sleeps (costs nothing);
    a new episode moves its slot's statics with the station."""
    cfg = WorldConfig()
    T_seat = DockingTaskConfig().T_ds_target  # the docked pose in the DS frame
    rng = np.random.default_rng(3)
    worlds = []
    for i in range(8):
        w = DockingWorld(cfg)
        T_ds = make_T(R_from_rpy(0, 0, rng.uniform(-1, 1)), [*rng.uniform(-1, 1, 2), w.floor_z_m])
        w.reset(T_ds, T_ds @ make_T(t=[0.0, 0.0, -0.3]) @ T_seat, np.random.default_rng(i))
        worlds.append(w)
    batch = BatchVehicles([w.vehicle for w in worlds])
    sc = batch._shared
    push = np.tile([0.0, 0.0, 268.0, 0.0, 0.0, 0.0], (8, 1))
    for _ in range(15):
        batch.step(push, 0.2)
    assert batch.last_physx.all()
    slot_of = {}
    for i, twin in enumerate(sc._twins):
        slot_of[twin.entity.per_scene_id] = i
        for _, copy in sc._copies[i]:
            slot_of[copy.per_scene_id] = i
    contacts = sc.system.get_contacts()
    assert len(contacts) >= 8
    for c in contacts:
        a, b = (slot_of[x.entity.per_scene_id] for x in c.bodies)
        assert a == b
    # each vehicle came down onto its own station: within 5 cm of the seat's height
    for i, w in enumerate(worlds):
        seat_z = (w.T_world_ds @ T_seat)[2, 3]
        assert abs(batch.T_world_body()[i][2, 3] - seat_z) < 0.05
    # vehicle 0 flies up and away: out of PhysX, its twin parked asleep
    lift = push.copy()
    lift[0] = [0.0, 0.0, -268.0, 0.0, 0.0, 0.0]
    for _ in range(12):
        batch.step(lift, 0.2)
    assert not batch.last_physx[0] and batch.last_physx[1:].all()
    assert sc._twins[0].is_sleeping and not sc._twins[1].is_sleeping
    # a new episode for slot 3: its statics' copy follows the moved station
    T_new = make_T(R_from_rpy(0, 0, 0.5), [1.5, -1.0, worlds[3].floor_z_m])
    worlds[3].reset(T_new, T_new @ make_T(t=[0.0, 0.0, -0.3]) @ T_seat, np.random.default_rng(9))
    batch.load(3)
    ((src, copy),) = sc._copies[3]
    np.testing.assert_allclose(
        copy.get_pose().p, np.asarray(src.get_pose().p) + sc.offsets[3], atol=1e-5
    )
    np.testing.assert_allclose(copy.get_pose().q, src.get_pose().q, atol=1e-7)


def test_slot_grid_is_a_compact_spiral_of_distinct_points():
    from uwdock.sim.contact_scene import spiral_point

    pts = [spiral_point(k) for k in range(289)]
    assert pts[:5] == [(0, 0), (1, 0), (1, 1), (0, 1), (-1, 1)]
    assert len(set(pts)) == 289  # 17 x 17: rings 0 .. 8 filled exactly
    assert max(max(abs(x), abs(y)) for x, y in pts) == 8
    for k in range(1, 289):  # neighbours on the grid: the spiral never jumps
        (x0, y0), (x1, y1) = pts[k - 1], pts[k]
        assert abs(x1 - x0) + abs(y1 - y0) == 1


def test_batch_imu_equals_the_scalar_imu_without_noise():
    vehicle = replace(VehicleConfig(), imu=_QUIET_IMU)
    cfg = replace(WorldConfig(), vehicle=vehicle)
    T0 = make_T(R_from_rpy(0.1, -0.05, 0.4), [1.0, -1.0, 3.0])
    scalar, twin = _world(cfg, 3, T0), _world(cfg, 3, T0)
    batch = BatchVehicles([twin.vehicle], contact="own")  # it bumps the DS: bit-equal PhysX
    rng = np.random.default_rng(0)
    for k in range(5):
        w = np.array([80.0, -20.0, 30.0, 0.0, 5.0, 10.0 * k])
        scalar.vehicle.step(w, 0.2)
        batch.step(w[None], 0.2)
        a, b = scalar.vehicle.read_imu(), batch.read_imu(rng.standard_normal((1, 10)))
        for name in (
            "specific_force_frd_mps2",
            "acceleration_frd_mps2",
            "angular_velocity_frd_radps",
            "velocity_frd_mps",
        ):
            np.testing.assert_allclose(getattr(b, name)[0], getattr(a, name), atol=1e-9)
        assert b.depth_m[0] == pytest.approx(a.depth_m, abs=1e-12)


def test_batch_imu_noise_has_the_configured_spread():
    cfg = WorldConfig()
    worlds = [_world(cfg, s, make_T(np.eye(3), [0.0, 0.0, 3.0])) for s in range(2)]
    batch = BatchVehicles([w.vehicle for w in worlds])
    rng = np.random.default_rng(1)
    vel = np.array(
        [batch.read_imu(rng.standard_normal((2, 10))).velocity_frd_mps for _ in range(3000)]
    )
    std = vel.reshape(-1, 3).std(axis=0)
    np.testing.assert_allclose(std, cfg.vehicle.imu.velocity_noise_std_mps, rtol=0.08)


def test_bad_wrench_shape_is_refused():
    w = _world(WorldConfig(), 0, make_T(np.eye(3), [0.0, 0.0, 3.0]))
    batch = BatchVehicles([w.vehicle])
    with pytest.raises(ValueError, match="wrench_frd"):
        batch.step(np.zeros((2, 6)), 0.2)
    with pytest.raises(ValueError):
        batch.step(np.zeros((1, 6)), 0.2015)
    with pytest.raises(ValueError, match="normals"):
        batch.read_imu(np.zeros((1, 9)))
    with pytest.raises(ValueError, match="no vehicles"):
        BatchVehicles([])


def _hull_extent(world: DockingWorld) -> np.ndarray:
    """(min xyz, max xyz) of the hull's contact spheres in world NED (m)."""
    spheres, _, _ = world.vehicle.plane_params
    T = world.T_world_body
    c = spheres[:, :3] * [1.0, -1.0, -1.0]  # FLU -> FRD
    p = c @ T[:3, :3].T + T[:3, 3]
    r = spheres[:, 3:]
    return np.concatenate([(p - r).min(axis=0), (p + r).max(axis=0)])


def test_tank_walls_and_floor_hold_the_vehicle_without_physx():
    """Pushed at full surge into a wall, then at full heave onto the floor: the hull stops at
    them (our plane contact, ~1 mm of give), in free flight, the same in the batch."""
    cfg = WorldConfig()
    L, _, D = cfg.tank_size_m
    T0 = make_T(np.eye(3), [L / 2 - 2.0, -2.0, 3.0])  # heading +x, towards the end wall
    scalar, twin = _world(cfg, 4, T0, ds_xy=(-3.0, 0.0)), _world(cfg, 4, T0, ds_xy=(-3.0, 0.0))
    batch = BatchVehicles([twin.vehicle])
    for k in range(100):
        w = (
            np.array([280.0, 0.0, 0.0, 0.0, 0.0, 0.0])
            if k < 50
            else np.array([0, 0, 268.0, 0, 0, 0])
        )
        scalar.vehicle.step(w, 0.2)
        batch.step(w[None], 0.2)
        assert scalar.vehicle.last_step_fast and not batch.last_physx[0]
        if k == 49:
            ext = _hull_extent(scalar)
            assert L / 2 - 0.01 < ext[3] < L / 2 + 0.003  # at the wall, not through it
            assert abs(scalar.vehicle.nu[0]) < 0.01
    ext = _hull_extent(scalar)
    assert D - 0.01 < ext[5] < D + 0.003  # on the floor
    assert abs(scalar.vehicle.nu[2]) < 0.01
    np.testing.assert_allclose(batch.T_world_body()[0], scalar.T_world_body, atol=1e-9)


def test_row_cross_products_are_numpys_bit_for_bit():
    from uwdock.sim.batch import _cross_rows

    rng = np.random.default_rng(4)
    a, b, c = rng.normal(size=(32, 3)), rng.normal(size=(32, 3)), rng.normal(size=3)
    assert np.array_equal(_cross_rows(a, b), np.cross(a, b))
    assert np.array_equal(_cross_rows(a, c), np.cross(a, c))
    assert np.array_equal(_cross_rows(a, _cross_rows(a, c)), np.cross(a, np.cross(a, c)))
