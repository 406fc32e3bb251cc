"""Contacts between the AUV and the docking station (physics-only scene, no renderer)."""

from __future__ import annotations

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.dockcore.config import replace
from uwdock.rl.env.task import DockingTaskConfig, pegs_seated
from uwdock.sim.docking_station import DockingStationConfig, build_docking_station, build_tank
from uwdock.sim.physics import VehicleBody, make_physics_scene
from uwdock.sim.vehicle import VehicleConfig

TASK = DockingTaskConfig()


@pytest.fixture()
def world():
    scene = make_physics_scene()
    cfg = DockingStationConfig()
    build_tank(scene, cfg, visual=False, surface_lid=True)
    ds = build_docking_station(scene, cfg, visual=False)
    return scene, ds


def test_vehicle_resting_in_the_notches_stays_put(world):
    """A slightly heavy AUV lowered onto the DS settles with its pegs in the notches."""
    scene, ds = world
    heavy = replace(VehicleConfig(), net_buoyancy_kg=-4.0)
    T_world_ds = ds.T_worldned_ds.copy()
    T_dock = T_world_ds @ TASK.T_ds_target
    start = T_dock.copy()
    start[2, 3] -= 0.03  # 3 cm above the seat
    body = VehicleBody(scene, heavy)
    body.reset(start)
    for _ in range(10):  # settle for 2 s
        body.step(np.zeros(6))
    settled = body.T_world_ned_body_frd
    assert pegs_seated(settled, T_world_ds, TASK)
    for _ in range(50):  # then 10 s at rest
        body.step(np.zeros(6))
    final = body.T_world_ned_body_frd
    assert np.linalg.norm(final[:3, 3] - settled[:3, 3]) < 0.01
    assert np.linalg.norm(final[:3, 3] - T_dock[:3, 3]) < 0.03
    assert pegs_seated(final, T_world_ds, TASK)
    assert np.abs(body.nu).max() < 0.01


def test_striking_a_guide_spikes_the_imu(world):
    """Driving sideways into an X-guide plate gives an acceleration spike; free water does not."""
    scene, ds = world
    T_world_ds = ds.T_worldned_ds
    body = VehicleBody(scene, replace(VehicleConfig(), net_buoyancy_kg=0.0))
    # level with the guides' top, 0.6 m beside the plate at DS x = +0.57, moving toward it
    p = T_world_ds[:3, 3] + [1.45, 0.0, -1.0]
    # yawed 90 deg, body +y points to world -x: a sway of +0.8 m/s drives it onto the plate
    body.reset(make_T(R_from_rpy(0, 0, np.pi / 2), p), nu=[0.0, 0.8, 0.0, 0.0, 0.0, 0.0])
    jumps, prev = [], body.read_imu().specific_force_frd_mps2
    for _ in range(15):
        body.step(np.zeros(6))
        acc = body.read_imu().specific_force_frd_mps2
        jumps.append(np.linalg.norm(acc - prev))
        prev = acc
    free = max(jumps[:2])  # before reaching the plate: damping only
    assert max(jumps) > 5.0 * max(free, 0.2)
    assert max(jumps) > 1.0  # above the reward's collision threshold Gamma_set
