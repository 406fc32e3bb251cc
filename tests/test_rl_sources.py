"""Observation sources and the seams: error model (fit + sampling), camera source, runner."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.error_models import above_ds, synthetic_model
from uwdock.calibration.frames import inv_T, make_T
from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.error_model import (
    ErrorModel,
    ErrorModelSource,
    apply_error,
    fit_error_model,
    load_error_model,
    pose_error,
)
from uwdock.rl.env.obs_sources import StepContext
from uwdock.rl.env.task import DockingTaskConfig


def test_pose_error_round_trip():
    rng = np.random.default_rng(0)
    T = make_T(t=[0.1, -0.2, 3.0])
    for _ in range(20):
        err = np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, 0.05, 3)])
        np.testing.assert_allclose(pose_error(apply_error(T, err), T), err, atol=1e-12)


def test_error_model_source_samples_the_fitted_statistics():
    bias = np.array([0.01, -0.02, 0.03, 0.0, 0.0, 0.01])
    sd = np.array([0.01, 0.02, 0.03, 0.01, 0.01, 0.02])
    model = ErrorModel(synthetic_model(0.7, bias, np.diag(sd**2)))
    src = ErrorModelSource(model, DockingTaskConfig())
    src.reset(np.random.default_rng(1))
    T_world_ds, T_world_body = above_ds(3.0)
    T_world_cam = T_world_body @ model.T_body_cam
    T_cam_ds = inv_T(T_world_cam) @ T_world_ds
    ctx = StepContext(T_world_body, T_world_ds, 0.0)
    errs, hits, n = [], 0, 6000
    for _ in range(n):
        m = src.measure(ctx)
        if m is not None:
            hits += 1
            errs.append(pose_error(inv_T(T_world_cam) @ m.T_world_ds, T_cam_ds))
    assert hits / n == pytest.approx(0.7, abs=0.02)
    errs = np.asarray(errs)
    np.testing.assert_allclose(errs.mean(axis=0), bias, atol=3 * sd.max() / np.sqrt(hits) + 1e-3)
    np.testing.assert_allclose(errs.std(axis=0), sd, rtol=0.06)


def test_error_model_never_detects_without_markers_in_view():
    model = ErrorModel(synthetic_model(1.0, np.zeros(6), np.diag(np.full(6, 0.01) ** 2)))
    src = ErrorModelSource(model, DockingTaskConfig())
    T_world_ds, T_world_body = above_ds(3.0)
    far = T_world_body.copy()
    far[:3, 3] += [6.0, 0.0, 0.0]  # DS out of the field of view
    assert all(src.measure(StepContext(far, T_world_ds, 0.0)) is None for _ in range(50))


def test_bad_error_model_files(tmp_path):
    from uwdock.dockcore.errors import DockError

    with pytest.raises(DockError, match="not found"):
        load_error_model(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(DockError, match="malformed JSON"):
        load_error_model(bad)
    bad.write_text(json.dumps({"format": "other"}))
    with pytest.raises(DockError, match="not a version-1"):
        load_error_model(bad)


@pytest.mark.render
def test_fit_error_model_from_rendered_frames(tmp_path):
    """The seam: datasets synth -> perception -> fitted model, with sane close-range errors."""
    from uwdock.datasets.synth import SynthConfig, generate

    generate(
        tmp_path / "ds",
        SynthConfig(n_frames=24, seed=3, water="clear_tank", width_px=640),
        workers=1,
        progress=False,
    )
    model = fit_error_model(tmp_path / "ds", progress=False)
    assert model["dataset"]["frames"] == 24 and len(model["dataset"]["sha256"]) == 64
    t = model["tables"]["clear_tank"]
    frames = np.asarray(t["frames"])
    assert frames.sum() == 24
    p = np.asarray(t["p_detect"])
    assert np.all((p >= 0) & (p <= 1))
    seen = frames[:, 3] > 0  # bins with 3+ markers in view were seen
    assert p[seen, 3].max() > 0.5
    close = [b for b in t["bins"] if b["range_m"][1] <= 3.0 and b["detections"] > 0]
    assert close and all(np.linalg.norm(b["bias"][:3]) < 0.05 for b in close)
    ErrorModel(model)  # loads


@pytest.fixture(scope="module")
def camera_env():
    from uwdock.rl.env.docking_env import DockingEnv

    cfg = replace(
        EnvConfig(),
        usbl={"period_s": 0.0},
        obs_source="camera",
        camera_width_px=640,
        episode_s=4.0,
        randomise_vehicle=False,
    )
    env = DockingEnv(cfg)
    yield env
    env.close()


@pytest.mark.render
def test_camera_source_measures_the_ds_from_its_render(camera_env):
    env = camera_env
    env.reset(seed=0)
    T_world_ds = env.world.T_world_ds.copy()
    T_target = T_world_ds @ env.cfg.task.T_ds_target
    pose = make_T(T_target[:3, :3], T_target[:3, 3] - [0.0, 0.0, 2.5])
    env.world.vehicle.reset(pose)
    env.filter.reset(T_world_ds, np.random.default_rng(0))
    _, _, _, _, info = env.step(np.zeros(6))
    m = env.last_measurement
    assert m is not None and m.detected
    np.testing.assert_allclose(m.T_world_ds[:3, 3], T_world_ds[:3, 3], atol=0.03)
    assert info["detected"]


@pytest.mark.render
def test_runner_reproduces_the_env_observation(camera_env):
    """Deployment path: the same frames and odometry give the env's observation exactly."""
    from uwdock.rl.deploy.runner import DockingRunner, Odometry
    from uwdock.rl.policy.baselines import PIDController

    env = camera_env
    obs, _ = env.reset(seed=4)
    teacher = PIDController(np.asarray(env.cfg.wrench_limits))
    runner = DockingRunner(teacher, env_cfg=env.cfg)
    runner.reset(env.filter.T_world_ds)
    runner.filter.P = env.filter.P.copy()
    compared = 0
    for _ in range(6):
        action = teacher.act(obs)
        obs, *_ = env.step(action)
        reading = env._last_imu  # the noisy reading the env drew this step
        odom = Odometry(
            env.world.T_world_body,
            reading.velocity_frd_mps,
            float(reading.angular_velocity_frd_radps[2]),
            reading.acceleration_frd_mps2,
        )
        runner.prev_action = np.clip(action, -1, 1)
        got = runner.observe(env.source.last_frame.img_bgr(), odom)
        np.testing.assert_allclose(got, obs, atol=1e-4)
        compared += 1
    assert compared == 6
