"""The seam from the simulator to the vehicle node, message by message: the env renders, the
vehicle's sensors become ROS 2 messages (serialised to CDR and read back, as DDS carries them),
the node's chain turns them into the policy's observation, and the env steps on the node's
command. At every step the chain's observation equals the env's own (float32, bit for bit) and
the episode ends as in-process evaluation's (``rl eval`` with the same ONNX policy)."""

from __future__ import annotations

import numpy as np
import pytest

from uwdock.dockcore.config import replace
from uwdock.rl.deploy.cli import SHIPPED_POLICY, build_chain
from uwdock.rl.deploy.config import load_node_config
from uwdock.rl.deploy.wire import Dispatcher
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.evaluate.episodes import run_episodes
from uwdock.rl.policy.env_settings import command_env
from uwdock.rl.policy.policy_io import OnnxPolicy
from uwdock.ros import messages as rm

pytestmark = pytest.mark.render

PROFILE = SHIPPED_POLICY.parents[2] / "deploy" / "profiles" / "sim.toml"
SEED = 91001


def _wire(msg, typename):
    return rm.deserialize(rm.serialize(msg, typename), typename)


def test_node_observation_equals_the_envs_at_every_step():
    resolved = command_env(str(SHIPPED_POLICY), defaults={"terminate_on": "strict"})
    cfg = replace(resolved.cfg, obs_source="camera")
    env = DockingEnv(cfg)
    ncfg = load_node_config(str(PROFILE))
    chain = build_chain(None, None, None, ncfg, armed=True)
    feed = Dispatcher(chain, ncfg, camera_file_given=False, check_future=False).feed
    obs, _ = env.reset(seed=SEED)
    cam = env.world.camera.model
    info_msg = rm.camera_info_msg(cam.K, cam.dist, cam.width_px, cam.height_px, 0, "camera")
    feed("camera_info", _wire(info_msg, "sensor_msgs/msg/CameraInfo"), 0)
    assert chain.runner.camera.K.tolist() == cam.K.tolist()
    T, var = env.ds_prior
    cov = np.zeros((6, 6))
    cov[[0, 1, 2, 5], [0, 1, 2, 5]] = var
    t = 1_000_000_000
    pwcs = "geometry_msgs/msg/PoseWithCovarianceStamped"
    feed("ds_prior", _wire(rm.pose_cov_stamped_msg(T, cov, t, "world_ned"), pwcs), t)
    steps, detected, done, exact = 0, 0, False, 0
    while not done:
        nav = env.navigation_solution()
        Tn, w = nav["T_world_body"], nav["angular_velocity_frd_radps"]
        odom = rm.odometry_msg(Tn, nav["velocity_frd_mps"], w, t, "world_ned", "base")
        feed("odometry", _wire(odom, "nav_msgs/msg/Odometry"), t)
        imu = rm.imu_msg(Tn[:3, :3], w, nav["specific_force_frd_mps2"], t, "base")
        feed("imu", _wire(imu, "sensor_msgs/msg/Imu"), t)
        acc = rm.accel_stamped_msg(nav["acceleration_frd_mps2"], t, "base")
        feed("accel", _wire(acc, "geometry_msgs/msg/AccelWithCovarianceStamped"), t)
        if env.last_usbl_fix is not None:
            p, sigma = env.last_usbl_fix
            fix = np.eye(4)
            fix[:3, 3] = p
            v = sigma**2
            msg = rm.pose_cov_stamped_msg(fix, np.diag([v, v, v, 0, 0, 0]), t, "world_ned")
            feed("usbl", _wire(msg, pwcs), t)
        img = rm.image_msg(env.source.last_frame.img_bgr(), t, "camera")
        feed("image", _wire(img, "sensor_msgs/msg/Image"), t)
        tick = chain.tick(t)
        # the same float32 input, but for the last place: the pose crosses the wire as a
        # quaternion, whose round trip moves the rotation by ~1e-16, and tanh(e / 0.1 m) (the
        # fine error) can carry that into one unit in the last place of an entry (seen: one
        # entry, at one step of an episode)
        diff = np.abs(tick.observation.astype(np.float64) - obs)
        assert diff.max() <= 2 * np.spacing(np.float32(1.0)), f"step {steps}: {diff.max()}"
        exact += bool(np.array_equal(tick.observation, obs))
        detected += tick.measurement is not None
        obs, _, term, trunc, info = env.step_wrench(tick.command)
        t += chain.period_ns
        steps += 1
        done = term or trunc
    assert detected > 20 and chain.counts["refused_image"] == 0
    assert exact >= 0.9 * steps  # bit for bit at nearly every step
    ref = run_episodes(OnnxPolicy(SHIPPED_POLICY), cfg, 1, seed=SEED, record=False).episodes[0]
    assert info["success_strict"] and ref["success_strict"]
    assert steps == ref["steps"]
