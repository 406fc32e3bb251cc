"""The vehicle node's chain without a transport (``uwdock.rl.deploy.chain``): arming, the
holds and their reasons within one tick (stale camera, stale navigation, a refused input, an
uncertain DS estimate, an abort), frames placed at their own stamps, dropped and refused
frames counted, the USBL prior, and the wire messages a tick publishes.

The policy is the shipped one, exported to ONNX (``rl/policies/realistic_ppo/policy.onnx``);
frames are blank (no marker), so the DS estimate lives on the prior and the fixes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.dockcore.config import from_dict
from uwdock.rl.deploy.chain import DockingChain, NavBuffer
from uwdock.rl.deploy.cli import SHIPPED_POLICY, build_chain
from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.inputs import NavSample
from uwdock.rl.deploy.wire import Dispatcher, tick_messages
from uwdock.ros import messages as rm

NS = 1_000_000_000
TICK = 200_000_000  # the shipped policy's 5 Hz


def _nav(t_ns: int, x: float = 0.0) -> NavSample:
    T = make_T(R_from_rpy(0.0, 0.0, 0.3), [x, 0.5, 3.0])
    return NavSample(t_ns, T, np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, 0.01]))


def _blank() -> np.ndarray:
    return np.full((363, 480, 3), 90, np.uint8)


def _chain(armed: bool = True, **safety) -> DockingChain:
    cfg = from_dict(NodeConfig, {"flat_markers": False, "safety": safety})
    return build_chain(None, None, None, cfg, armed)


def _start(chain: DockingChain, t0: int = NS) -> None:
    """A DS prior 3 m below the vehicle, then a tick's worth of inputs at t0."""
    T_ds = make_T(R_from_rpy(0.0, 0.0, 1.0), [0.5, 0.2, 6.0])
    chain.on_ds_prior(t0, T_ds, np.array([1.0, 1.0, 0.09, 0.07]))
    _inputs(chain, t0)


def _inputs(chain: DockingChain, t: int, frame: bool = True, nav: bool = True) -> None:
    if nav:
        chain.on_nav(_nav(t))
        chain.on_imu(t, np.array([0.0, 0.0, -9.81]))
    if frame:
        chain.on_frame(t, _blank)


def test_shipped_policy_is_exported():
    """The node's default policy: an ONNX file and its .json, no pickle, as
    ``make_artefacts.sh onnx`` wrote them (checksums), carrying the env it was trained in."""
    import hashlib
    import json

    folder = SHIPPED_POLICY.parent
    for line in (folder / "onnx_checksums.sha256").read_text().splitlines():
        digest, name = line.split()
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name
    meta = json.loads(SHIPPED_POLICY.with_suffix(".json").read_text())
    assert meta["obs_dim"] == 18 and meta["env"]["nav"]["preset"] == "mems-ahrs-dvl"
    # its data files named from a checkout's root, not where it was exported
    assert meta["env"]["error_model_path"] == "rl/models/error_model_clear_tank_480_ar1_refit.json"


def test_disarmed_publishes_no_command_and_enable_arms():
    chain = _chain(armed=False)
    _start(chain)
    tick = chain.tick(NS)
    assert tick.state == "disarmed" and tick.command is None
    assert not any(kind == "command" for kind, *_ in tick_messages(tick, chain.cfg))
    chain.on_enable(True)
    _inputs(chain, NS + TICK)
    tick = chain.tick(NS + TICK)
    assert tick.state == "armed" and tick.reasons == []
    assert tick.command is not None and np.all(np.isfinite(tick.command))
    # the wrench is the policy's action scaled by the limits it was trained with
    limits = chain.runner.limits
    assert np.all(np.abs(tick.command) <= limits + 1e-9)
    assert np.any(tick.command != 0)


def test_camera_stale_holds_within_one_tick_and_resumes():
    chain = _chain(camera_timeout_s=0.5)
    _start(chain)
    assert chain.tick(NS).state == "armed"
    t, states = NS, []
    for k in range(1, 8):  # frames stop after t0: the newest is k * 0.2 s old
        t = NS + k * TICK
        _inputs(chain, t, frame=False)
        tick = chain.tick(t)
        states.append((k * 0.2, tick.state, tick.command))
    for age_s, state, command in states:
        if age_s <= 0.5 + 1e-9:
            assert state == "armed"
        else:  # the first tick past the limit already holds, with a zero wrench
            assert state == "holding" and np.array_equal(command, np.zeros(6))
    assert "camera stale" in tick.values["reasons"]
    assert tick.values["state"] == "holding"
    t += TICK
    _inputs(chain, t)  # the camera is back
    tick = chain.tick(t)
    assert tick.state == "armed" and np.any(tick.command != 0)


def test_navigation_stale_holds():
    chain = _chain(nav_timeout_s=0.3)
    _start(chain)
    chain.tick(NS)
    _inputs(chain, NS + TICK, nav=False)
    assert chain.tick(NS + TICK).state == "armed"  # 0.2 s old
    _inputs(chain, NS + 2 * TICK, nav=False)
    tick = chain.tick(NS + 2 * TICK)  # 0.4 s old
    assert tick.state == "holding"
    assert any(r.startswith("navigation stale") for r in tick.reasons)


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("position", float("nan")),
        ("position", 1e12),
        ("quaternion", 0.0),
        ("velocity", float("inf")),
    ],
)
def test_refused_odometry_holds_one_tick_later_and_never_raises(field, bad):
    chain = _chain(bad_input_hold_s=0.5)
    dispatch = Dispatcher(chain, chain.cfg, camera_file_given=True)
    _start(chain)
    chain.tick(NS)
    t = NS + TICK
    msg = rm.odometry_msg(_nav(t).T_world_body, np.zeros(3), np.zeros(3), t, "w", "b")
    if field == "position":
        msg.pose.pose.position.x = bad
    elif field == "quaternion":
        q = msg.pose.pose.orientation
        q.w = q.x = q.y = q.z = bad
    else:
        msg.twist.twist.linear.y = bad
    logged = []
    chain.log = logged.append
    dispatch.feed("odometry", msg, t)  # refused: counted, logged, never raised
    _inputs(chain, t, nav=False)
    tick = chain.tick(t)
    assert tick.state == "holding" and np.array_equal(tick.command, np.zeros(6))
    assert any("odometry refused" in r for r in tick.reasons)
    assert chain.counts["refused_odometry"] == 1 and len(logged) == 1
    assert tick.values["count_refused_odometry"] == "1"
    # the hold ends once the input is good again for the hold time
    for k in range(2, 6):
        _inputs(chain, NS + k * TICK)
        tick = chain.tick(NS + k * TICK)
    assert tick.state == "armed"


def test_undecodable_frame_and_garbage_bytes_are_refused():
    chain = _chain()
    dispatch = Dispatcher(chain, chain.cfg, camera_file_given=True)
    _start(chain)
    chain.tick(NS)
    t = NS + TICK
    msg = rm.image_msg(_blank(), t, "camera")
    msg.data = msg.data[:100]  # truncated
    dispatch.feed("image", msg, t)
    dispatch.feed("odometry", None, t, error="not a nav_msgs/msg/Odometry message")
    chain.on_nav(_nav(t))
    tick = chain.tick(t)
    assert chain.counts["refused_image"] == 1 and chain.counts["refused_odometry"] == 1
    assert tick.state == "holding"


def test_uncertain_estimate_holds():
    chain = _chain(max_ds_sigma_m=0.5)
    _start(chain)  # prior sigma 1 m horizontally
    tick = chain.tick(NS)
    assert any(r.startswith("DS estimate too uncertain") for r in tick.reasons)
    # a tight USBL fix brings it under the bound on the next tick
    chain.on_usbl(NS + TICK, np.array([0.5, 0.2, 6.0]), 0.01)
    _inputs(chain, NS + TICK)
    tick = chain.tick(NS + TICK)
    assert tick.state == "armed", tick.reasons
    assert math.sqrt(tick.cov_xyzyaw[0, 0]) < 0.5


def test_abort_holds_until_enable():
    chain = _chain()
    _start(chain)
    chain.tick(NS)
    chain.on_abort()
    _inputs(chain, NS + TICK)
    tick = chain.tick(NS + TICK)
    assert tick.state == "holding" and np.array_equal(tick.command, np.zeros(6))
    assert tick.reasons[0].startswith("aborted")
    chain.on_enable(True)
    _inputs(chain, NS + 2 * TICK)
    assert chain.tick(NS + 2 * TICK).state == "armed"


def test_frames_dropped_and_placed_at_their_own_stamp():
    chain = _chain()
    _start(chain)
    chain.tick(NS)
    t = NS + TICK
    chain.on_nav(_nav(t - TICK // 2, x=1.0))
    chain.on_nav(_nav(t, x=2.0))
    chain.on_frame(t - 150_000_000, _blank)  # superseded by the next one
    chain.on_frame(t - 50_000_000, _blank)
    chain.tick(t)
    assert chain.counts["frames_dropped"] == 1 and chain.counts["frames_used"] == 2
    # the frame at t - 0.05 s is placed with the navigation interpolated to its stamp,
    # halfway between the solutions at t - 0.1 s (x = 1 m) and t (x = 2 m)
    T = chain.nav.at(t - 50_000_000)
    assert T[0, 3] == pytest.approx(1.5)
    # a frame older than the navigation buffer is refused
    chain.on_frame(NS - 10 * NS, _blank)
    chain.on_nav(_nav(t + TICK))
    chain.tick(t + TICK)
    assert chain.counts["frames_stale"] + chain.counts["frames_outside_nav"] >= 1


def test_nav_buffer_interpolates_and_refuses_outside():
    buf = NavBuffer(span_ns=2 * NS, hold_ns=NS // 2)
    a = _nav(NS, x=0.0)
    b = NavSample(2 * NS, make_T(R_from_rpy(0, 0, 0.5), [2.0, 0.5, 3.0]), np.zeros(3), np.zeros(3))
    buf.add(a)
    buf.add(b)
    mid = buf.at(NS + NS // 2)
    assert mid[0, 3] == pytest.approx(1.0)
    yaw = math.atan2(mid[1, 0], mid[0, 0])
    assert yaw == pytest.approx(0.4, abs=1e-3)  # halfway between 0.3 and 0.5 rad
    assert buf.at(NS - 1) is None  # before the buffer
    assert np.array_equal(buf.at(2 * NS + NS // 4), b.T_world_body)  # held
    assert buf.at(2 * NS + NS) is None  # too far past the newest
    buf.add(NavSample(5 * NS, b.T_world_body, np.zeros(3), np.zeros(3)))
    assert buf.at(NS) is None  # fell out of the 2 s span


def test_first_fix_of_a_run_is_the_prior_for_a_usbl_trained_policy():
    chain = _chain()
    assert chain.runner.cfg.nav.resolved().ds_prior == "usbl"
    T_ds = make_T(R_from_rpy(0.0, 0.0, 1.0), [0.5, 0.2, 6.0])
    chain.on_ds_prior(NS, T_ds, np.array([1.0, 1.0, 0.09, 0.07]))
    chain.on_usbl(NS, np.array([0.8, -0.1, 6.1]), 0.04)
    _inputs(chain, NS)
    tick = chain.tick(NS)
    # the fix replaced the prior's position with its own variance; the yaw is the prior's
    assert np.allclose(tick.T_world_ds[:3, 3], [0.8, -0.1, 6.1])
    assert np.allclose(np.diag(tick.cov_xyzyaw)[:3], 0.04)
    assert math.atan2(tick.T_world_ds[1, 0], tick.T_world_ds[0, 0]) == pytest.approx(1.0)
    # a later fix is fused (the estimate moves part of the way)
    chain.on_usbl(NS + TICK, np.array([1.0, -0.1, 6.1]), 0.04)
    _inputs(chain, NS + TICK)
    x = chain.tick(NS + TICK).T_world_ds[0, 3]
    assert 0.8 < x < 1.0


def test_tick_messages_carry_the_estimate_command_and_reasons():
    chain = _chain(camera_timeout_s=0.3)
    _start(chain)
    chain.tick(NS)
    _inputs(chain, NS + 3 * TICK, frame=False)
    tick = chain.tick(NS + 3 * TICK)
    msgs = {kind: (topic, ty, m) for kind, topic, ty, m in tick_messages(tick, chain.cfg)}
    assert list(msgs) == ["ds_estimate", "tf", "command", "diagnostics"]
    _, ty, cmd = msgs["command"]
    assert ty == "geometry_msgs/msg/WrenchStamped"
    assert np.array_equal(rm.wrench6(cmd), np.zeros(6))
    assert rm.stamp_ns(cmd) == NS + 3 * TICK
    _, _, diag = msgs["diagnostics"]
    assert diag.status[0].level == rm.DIAG_ERROR
    assert "camera stale" in diag.status[0].message
    _, _, est = msgs["ds_estimate"]
    assert np.allclose(rm.pose_T(est.pose.pose)[:3, 3], tick.T_world_ds[:3, 3])
    # every message serialises to CDR and back (what DDS and MCAP carry)
    for _, ty, m in msgs.values():
        assert rm.serialize(rm.deserialize(rm.serialize(m, ty), ty), ty) == rm.serialize(m, ty)


def test_foxglove_layout_names_the_nodes_topics():
    """The shipped Foxglove layout shows topics the node (COLA2-like defaults) reads or
    publishes, so it does not go stale when a topic is renamed."""
    import json
    from pathlib import Path

    import uwdock.rl.deploy as deploy

    layout = json.loads((Path(deploy.__file__).parent / "foxglove_layout.json").read_text())
    t = NodeConfig().topics
    known = {getattr(t, f) for f in t.__dataclass_fields__ if f != "image_format"}

    def strings(node):
        if isinstance(node, dict):
            for k, v in node.items():
                yield from strings(k)
                yield from strings(v)
        elif isinstance(node, list):
            for v in node:
                yield from strings(v)
        elif isinstance(node, str):
            yield node

    used = {s.split(".")[0] for s in strings(layout["configById"]) if s.startswith("/")}
    used -= {"/move_base_simple/goal", "/clicked_point", "/initialpose"}  # Foxglove's own
    assert used and used <= known, used - known


def test_velocity_request_balances_the_damping():
    """The optional body velocity request: the speed at which the damping balances the
    wrench, d_l v + d_q |v| v = F, on each axis (and 0 for a zero or unactuated axis)."""
    from uwdock.rl.deploy.wire import steady_velocity

    dl = np.array([20.0, 20.0, 20.0, 130.0, 130.0, 130.0])
    dq = np.array([148.0, 148.0, 148.0, 180.0, 180.0, 0.0])
    F = np.array([140.0, -70.0, 0.0, 0.0, -39.0, 72.0])
    v = steady_velocity(F, dl, dq)
    assert np.allclose(dl * v + dq * np.abs(v) * v, F)
    assert v[0] > 0 > v[1] and v[2] == 0 and v[5] == pytest.approx(72.0 / 130.0)
    cfg = from_dict(NodeConfig, {"flat_markers": False, "topics": {"velocity_command": "/cmd_vel"}})
    chain = build_chain(None, None, None, cfg, armed=True)
    _start(chain)
    tick = chain.tick(NS)
    msgs = {kind: m for kind, _, _, m in tick_messages(tick, cfg, chain.damping)}
    twist = msgs["velocity_command"].twist
    got = np.array([twist.linear.x, twist.linear.y, twist.linear.z,
                    twist.angular.x, twist.angular.y, twist.angular.z])  # fmt: skip
    assert np.allclose(got, steady_velocity(tick.command, *chain.damping))
    assert list(msgs).index("velocity_command") < list(msgs).index("diagnostics")


def test_jpeg_frames_take_the_detectors_compressed_views():
    """A ``CompressedImage`` frame runs the detector's views for block-coded frames even after
    the chain has resized it to the policy's width (which blurs the 8x8 grid the detector would
    otherwise measure); a raw ``Image`` leaves the detector to measure it."""
    chain = _chain()
    dispatch = Dispatcher(chain, chain.cfg, camera_file_given=True)
    _start(chain)
    chain.tick(NS)
    detector = chain.runner.estimator.detector
    big = np.full((726, 960, 3), 90, np.uint8)  # twice the policy's 480 px: resized first
    for k, (msg_of, expect) in enumerate(
        [
            (lambda t: rm.compressed_image_msg(big, t, "camera", 25), True),
            (lambda t: rm.image_msg(big, t, "camera"), False),
        ],
        start=1,
    ):
        t = NS + k * TICK
        chain.on_nav(_nav(t))
        dispatch.feed("image", msg_of(t), t)
        chain.tick(t)
        assert chain.counts["frames_used"] == 1 + k
        assert detector.last_compressed is expect
