"""``obs_contact``: what a vehicle can tell of its own contacts, in the env, the batch and the
deployment runner (rl.env.observation.ContactMemory)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration.frames import make_T
from uwdock.rl.env.batch_env import BatchDockingEnv
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.env.estimator import DSPoseFilter
from uwdock.rl.env.observation import (
    CONTACT_TAU_S,
    REST_FULL_S,
    ContactMemory,
    frame_dim,
    observation_frame,
)
from uwdock.rl.env.task import docking_errors


def test_contact_memory_traces_collisions_and_counts_rest():
    m = ContactMemory(2, 0.2)
    still, moving = [0.0, 0.0, 0.04], [0.1, 0.0, 0.0]
    f = m.update([True, False], [still, moving])
    np.testing.assert_allclose(f, [[1.0, 0.2 / REST_FULL_S], [0.0, 0.0]])
    f = m.update([False, False], [still, still])
    decay = math.exp(-0.2 / CONTACT_TAU_S)
    np.testing.assert_allclose(f, [[decay, 0.4 / REST_FULL_S], [0.0, 0.2 / REST_FULL_S]])
    for _ in range(40):
        f = m.update([False, False], [still, still])
    np.testing.assert_allclose(f[:, 1], [1.0, 1.0])  # capped
    assert f[0, 0] == pytest.approx(decay**41)
    f = m.update([False, True], [moving, still])  # moving again: the rest time starts over
    np.testing.assert_allclose(f, [[decay**42, 0.0], [1.0, 1.0]])
    m.reset(1)
    np.testing.assert_allclose(m.features()[1], [0.0, 0.0])
    assert m.features()[0, 0] > 0


def test_contact_values_end_every_frame():
    cfg = EnvConfig(obs_contact=True)
    assert frame_dim(cfg) == frame_dim(EnvConfig()) + 2
    rng = np.random.default_rng(2)
    f = DSPoseFilter(cfg.estimator)
    T_body = make_T(np.eye(3), [0.3, -0.2, 3.0])
    f.reset(make_T(np.eye(3), [0.0, 0.0, 5.0]), rng)
    contact = np.array([0.7, 0.25])
    vel, acc, prev = rng.normal(0, 0.3, 3), rng.normal(0, 2, 3), rng.uniform(-1, 1, 6)
    ref = observation_frame(cfg, T_body, f, vel, 0.05, acc, prev, True, contact)
    np.testing.assert_allclose(ref[-2:], contact, atol=1e-7)
    with pytest.raises(ValueError, match="contact"):
        observation_frame(cfg, T_body, f, vel, 0.05, acc, prev, True)


def _pushing_down(env, steps: int) -> list[np.ndarray]:
    """Full downward thrust (body z, FRD) for ``steps`` control steps: the obs' contact pair."""
    out = []
    for _ in range(steps):
        obs, *_ = env.step(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
        out.append(obs[-2:].copy())
    return out


def test_a_vehicle_pushed_onto_the_station_sees_its_landing():
    """Spawned right above the DS and pushed down: it lands (a detected collision) and comes
    to rest, and the observation says so; the batched env says the same."""
    cfg = EnvConfig(
        obs_source="acoustic", obs_contact=True, spawn_ds_range_m=(0.0, 0.3, 0.0),
        spawn_auv_yaw_deg=5.0, spawn_ds_yaw_deg=5.0, episode_s=30.0,
    )  # fmt: skip
    env = DockingEnv(cfg)
    obs, _ = env.reset(seed=3)
    np.testing.assert_allclose(obs[-2:], [0.0, 0.0])
    pairs = np.array(_pushing_down(env, 60))
    assert pairs[:, 0].max() == pytest.approx(1.0)  # a collision was detected
    assert pairs[-1, 1] > 0.3  # and it has been at rest for more than 1.5 s by the end
    batch = BatchDockingEnv(cfg, 1, seed=3)
    batch.reset()
    got = []
    for _ in range(60):
        ob, *_ = batch.step(np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]))
        got.append(ob[0, -2:].copy())
    got = np.array(got)
    assert got[:, 0].max() == pytest.approx(1.0) and got[-1, 1] > 0.3


def test_the_runner_senses_contacts_from_its_odometry():
    from uwdock.rl.deploy.runner import DockingRunner, Odometry

    cfg = EnvConfig(obs_contact=True)

    class Idle:
        def act(self, obs):
            return np.zeros(6)

    runner = DockingRunner(Idle(), env_cfg=cfg)
    runner.reset(make_T(np.eye(3), [0.0, 0.0, 5.0]))
    T = make_T(np.eye(3), [0.0, 0.0, 4.0])
    level = np.zeros(3)
    obs = runner.observe(None, Odometry(T, np.zeros(3), 0.0, level), predict=False)
    np.testing.assert_allclose(obs[-2:], [0.0, 0.0])
    obs = runner.observe(None, Odometry(T, np.zeros(3), 0.0, level))  # still: at rest
    np.testing.assert_allclose(obs[-2:], [0.0, runner.dt_s / REST_FULL_S], atol=1e-7)
    bump = np.array([0.0, 0.0, -30.0])  # a 30 m/s^2 jump: a collision
    obs = runner.observe(None, Odometry(T, np.array([0.2, 0.0, 0.0]), 0.0, bump))
    np.testing.assert_allclose(obs[-2:], [1.0, 0.0], atol=1e-7)
    runner.reset(make_T(np.eye(3), [0.0, 0.0, 5.0]))
    obs = runner.observe(None, Odometry(T, np.zeros(3), 0.0, level), predict=False)
    np.testing.assert_allclose(obs[-2:], [0.0, 0.0])


def test_fine_error_ends_the_frame_and_resolves_centimetres():
    """obs_fine_error appends tanh(e / 0.1 m) of the estimated error to the docking point: 5 cm
    off reads 0.46 there against 0.01 in the frame's first entries."""
    cfg = EnvConfig(obs_contact=True, obs_fine_error=True)
    assert frame_dim(cfg) == frame_dim(EnvConfig(obs_contact=True)) + 3
    rng = np.random.default_rng(3)
    f = DSPoseFilter(cfg.estimator)
    f.reset(make_T(np.eye(3), [0.0, 0.0, 5.0]), rng)
    T_target = f.T_world_ds @ cfg.task.T_ds_target  # the estimate's docking target
    T_body = T_target @ make_T(np.eye(3), [-0.05, 0.02, -0.3])  # 5 cm aft, 2 cm port, 30 cm up
    e, _ = docking_errors(T_body, f.T_world_ds, cfg.task)
    np.testing.assert_allclose(e, [0.05, -0.02, 0.3], atol=1e-9)
    contact = np.array([0.0, 0.5])
    vel, acc, prev = rng.normal(0, 0.3, 3), rng.normal(0, 2, 3), np.zeros(6)
    ref = observation_frame(cfg, T_body, f, vel, 0.0, acc, prev, True, contact)
    np.testing.assert_allclose(ref[-3:], np.tanh(np.array([0.5, -0.2, 3.0])), atol=1e-6)
    np.testing.assert_allclose(ref[:3], [0.01, -0.004, 0.06], atol=1e-6)
    np.testing.assert_allclose(ref[-5:-3], contact, atol=1e-7)
