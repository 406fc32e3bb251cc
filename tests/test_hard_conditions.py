"""The harder test distribution's conditions: a long approach (spawn distance band) and a
camera mounting error (true mounting != calibration), against geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T, rpy_from_R
from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv

FAR = replace(
    EnvConfig(),
    episode_s=2.0,
    spawn_auv_range_m=(8.5, 4.0, 1.4),
    spawn_horizontal_range_m=(8.0, 10.0),
)


def _horizontal_m(env: DockingEnv) -> float:
    w = env.world
    return float(np.linalg.norm(w.T_world_body[:2, 3] - w.T_world_ds[:2, 3]))


def test_long_approach_spawns_inside_the_distance_band():
    env = DockingEnv(FAR)
    try:
        d = []
        for seed in range(25):
            env.reset(seed=seed)
            d.append(_horizontal_m(env))
        assert all(8.0 <= x <= 10.0 for x in d), d
        assert max(d) - min(d) > 0.8  # a band, not one distance
    finally:
        env.close()


def test_default_spawn_accepts_near_and_far():
    env = DockingEnv(replace(EnvConfig(), episode_s=2.0))
    try:
        d = []
        for seed in range(25):
            env.reset(seed=seed)
            d.append(_horizontal_m(env))
        assert min(d) < 3.0 and max(d) > 5.0
    finally:
        env.close()


def test_unreachable_spawn_band_is_a_clear_error():
    env = DockingEnv(replace(FAR, spawn_auv_range_m=(2.0, 2.0, 1.4)))
    try:
        with pytest.raises(ValueError, match="spawn_horizontal_range_m"):
            env.reset(seed=0)
    finally:
        env.close()
    with pytest.raises(ValueError, match="spawn_horizontal_range_m: min 5 m must be below"):
        replace(EnvConfig(), spawn_horizontal_range_m=(5.0, 5.0)).validate()


def test_mounting_error_is_drawn_within_its_range_and_only_when_asked():
    from uwdock.sim.world import DockingWorld

    T_ds = make_T(np.eye(3), [0.0, 0.0, 4.9])
    T_body = make_T(np.eye(3), [1.0, 0.0, 2.0])
    plain = DockingWorld(EnvConfig().world)
    mis = DockingWorld(
        replace(EnvConfig(), camera_mount_error_m=0.01, camera_mount_error_deg=1.0).world
    )
    try:
        rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
        plain.reset(T_ds, T_body, rng_a)
        mis.reset(T_ds, T_body, rng_b)
        np.testing.assert_array_equal(plain.T_camcal_camtrue, np.eye(4))
        # the mounting error is drawn last: the vehicle's draws are the same in both worlds
        assert plain.vehicle.config == mis.vehicle.config
        assert rng_a.random() != rng_b.random()  # ... and the error took draws of its own
        T = mis.T_camcal_camtrue
        assert np.all(np.abs(T[:3, 3]) <= 0.01) and np.linalg.norm(T[:3, 3]) > 0
        rpy = np.degrees(rpy_from_R(T[:3, :3]))
        assert np.all(np.abs(rpy) <= 1.0 + 1e-9) and np.linalg.norm(rpy) > 0
    finally:
        plain.close()
        mis.close()


@pytest.mark.render
def test_a_mounting_error_renders_from_the_true_camera_and_biases_the_estimate():
    """Above the DS at 2 m, a 2 deg pitch of the true camera against its calibration moves the
    camera's DS estimate by about altitude x tan(2 deg) (7 cm); without it the estimate is
    within 2 cm. The frame records the true camera pose."""
    from uwdock.rl.env.camera_source import CameraSource
    from uwdock.rl.env.obs_sources import StepContext
    from uwdock.sim.world import DockingWorld

    cfg = EnvConfig()
    world = DockingWorld(cfg.world, with_camera=True)
    try:
        T_world_ds = make_T(R_from_rpy(0, 0, 0.3), [0.0, 0.0, world.floor_z_m])
        T_world_target = T_world_ds @ cfg.task.T_ds_target
        T_world_body = T_world_target @ make_T(np.eye(3), [0.05, 0.0, -1.1])
        world.reset(T_world_ds, T_world_body, np.random.default_rng(0))
        source = CameraSource(world)
        source.reset(np.random.default_rng(1))
        T_world_body = world.T_world_body
        ctx = StepContext(T_world_body, T_world_ds, 0.0, T_world_ds)
        errs = {}
        for pitch_deg in (0.0, 2.0):
            world.set_camera_mount_error(make_T(R_from_rpy(math.radians(pitch_deg), 0, 0)))
            m = source.measure(ctx)
            assert m is not None
            T_true_cam = T_world_body @ world.camera.T_body_cam @ world.T_camcal_camtrue
            np.testing.assert_allclose(source.last_frame.T_world_cam, T_true_cam, atol=1e-9)
            errs[pitch_deg] = float(np.linalg.norm(m.T_world_ds[:3, 3] - T_world_ds[:3, 3]))
        altitude_m = float(T_world_ds[2, 3] - T_world_body[2, 3])
        expected_m = altitude_m * math.tan(math.radians(2.0))
        assert errs[0.0] < 0.02
        assert abs(errs[2.0] - expected_m) < 0.4 * expected_m, (errs, expected_m)
    finally:
        world.close()
