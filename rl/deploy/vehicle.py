"""``sim vehicle``: the simulator as the vehicle, over the same middleware as a real one.

:class:`SimVehicle` runs the docking env (:class:`uwdock.rl.env.docking_env.DockingEnv`: SAPIEN
physics, the rendered underwater camera, the drifting navigation and the USBL of the policy's
training env) and speaks to the node only through ROS 2 topics (:class:`uwdock.ros.dds.DdsGraph`):

* it publishes, each control step, the downward camera (``Image`` bgr8 or JPEG
  ``CompressedImage``, as the node's config says), the navigation solution (``Odometry``: the
  navigation's drifting pose, the DVL velocity, the gyro), the accelerometer (``Imu``: specific
  force) and the gravity-free acceleration (``AccelWithCovarianceStamped``), each acoustic fix
  when one arrives (the USBL preset's period, noise, bias, dropouts and latency), the camera's
  ``CameraInfo`` (latched) and ``/clock``; at the start of each episode, the DS prior the mission
  starts from;
* it applies the newest ``WrenchStamped`` command with a zero-order hold, and a zero wrench once
  the newest is older than ``command_timeout_s``.

``clock = "sim"`` runs lock-step on simulated time: the vehicle publishes a step's sensors,
waits until the node's readers have acknowledged them, advances ``/clock``, then waits for the
node's diagnostics of that tick (the command comes first) before it steps the physics. The
episode is then the one in-process ``rl eval`` runs on the same seed, step for step (the node
computes what the env's camera source computes, from the same frames). ``clock = "wall"``
runs in real time and never waits for the node.

The camera and the navigation are sampled at the control rate (the env computes them once per
control step); acoustic fixes land on control steps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.wire import input_topics, output_types
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.evaluate.episodes import episode_row, summarise
from uwdock.rl.evaluate.failures import FailureTracker
from uwdock.ros import conventions as conv
from uwdock.ros import messages as rm
from uwdock.ros.mcap import McapRecorder
from uwdock.ros.qos import QosProfile

if TYPE_CHECKING:  # Cyclone DDS: the graph is made by the command (rl.deploy.cli)
    from uwdock.ros.dds import DdsGraph, Publisher, Subscription

__all__ = ["SimVehicle", "VehicleTimeout"]

_NS = 1_000_000_000
#: Simulated time between two episodes (s): the node sees the new DS prior after a gap.
EPISODE_GAP_S = 1.0


class VehicleTimeout(RuntimeError):
    """The node did not answer a lock-step tick in time."""


@dataclass
class _Command:
    stamp_ns: int
    wrench_frd: np.ndarray


class SimVehicle:
    """The simulated vehicle on DDS (module docstring).

    Args:
        env_cfg: the env (the policy's training env with the camera source).
        node_cfg: the node's topics, frames and axes (the vehicle publishes what the node
            reads and reads what it publishes).
        graph: the DDS participant.
        sim_clock: lock-step on simulated time (else real time).
        command_timeout_s: a command older than this is replaced by a zero wrench (s).
        jpeg_quality: JPEG quality of ``CompressedImage`` frames.
        camera_outage_s: (start, end) of each episode's time (s) during which no frame is
            published (a camera that fails and comes back); None: always on.
        answer_timeout_s: lock-step: how long to wait for the node's tick (s, wall time).
        recorder: an MCAP recording of everything published and received.
        log: progress lines.
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        node_cfg: NodeConfig,
        graph: DdsGraph,
        sim_clock: bool = True,
        command_timeout_s: float = 1.0,
        jpeg_quality: int = 90,
        camera_outage_s: tuple[float, float] | None = None,
        answer_timeout_s: float = 60.0,
        recorder: McapRecorder | None = None,
        log: Callable[[str], None] = lambda line: None,
    ) -> None:
        self.env = DockingEnv(env_cfg)
        self.cfg, self.graph, self.sim_clock = node_cfg, graph, sim_clock
        self.command_timeout_ns = round(command_timeout_s * _NS)
        self.jpeg_quality = int(jpeg_quality)
        self.camera_outage_s = camera_outage_s
        self.answer_timeout_s = answer_timeout_s
        self.recorder, self.log = recorder, log
        self.period_ns = round(_NS / env_cfg.control_hz)
        q = node_cfg.qos

        def qos(p: QosProfile) -> QosProfile:
            return QosProfile("reliable", max(p.depth, 4), p.durability) if sim_clock else p

        # the vehicle publishes what the node reads (its topics, types and QoS), but the
        # operator's enable and abort
        self.pubs: dict[str, tuple[Publisher, str, str]] = {
            it.kind: (graph.publisher(topic, it.typename, it.qos), topic, it.typename)
            for topic, it in input_topics(node_cfg, sim_clock).items()
            if it.kind not in ("enable", "abort")
        }
        outs = output_types(node_cfg)
        self.subs: dict[str, tuple[Subscription, str, str]] = {}
        for kind in ("command", "diagnostics"):
            if kind in outs:
                topic, typename = outs[kind]
                profile = q.command if kind == "command" else q.outputs
                self.subs[kind] = (
                    graph.subscription(topic, typename, qos(profile)),
                    topic,
                    typename,
                )
        self._command: _Command | None = None
        self._answered_ns: int | None = None
        self.clock_ns = 0
        #: wall clock: stamps are simulated time plus this (the system time at the start)
        self._origin_ns = 0
        self.states: list[tuple[int, str]] = []

    # ------------------------------------------------------------------ wire

    def _publish(self, kind: str, msg: Any, t_ns: int) -> None:
        entry = self.pubs.get(kind)
        if entry is None:
            return
        pub, topic, typename = entry
        cdr = pub.publish(msg)
        if self.recorder is not None:
            self.recorder.write_cdr(topic, typename, cdr, t_ns)

    def _drain(self) -> None:
        """Take the node's commands and diagnostics."""
        for kind, (sub, topic, typename) in self.subs.items():
            for r in sub.take():
                if self.recorder is not None and r.cdr:
                    self.recorder.write_cdr(topic, typename, r.cdr, self.clock_ns)
                if r.msg is None:
                    continue
                try:
                    stamp = rm.stamp_ns(r.msg)
                except ValueError:
                    continue
                if kind == "diagnostics":
                    self._answered_ns = stamp
                    values = rm.diagnostic_values(r.msg) if r.msg.status else {}
                    self.states.append((stamp, values.get("state", "")))
                    continue
                try:
                    w = rm.wrench6(r.msg)
                except ValueError:
                    continue  # a non-finite command is no command: the hold times out
                w = np.concatenate(
                    [conv.body_vector_from_wire(w[:3], self.cfg.axes),
                     conv.body_vector_from_wire(w[3:], self.cfg.axes)]
                )  # fmt: skip
                if self._command is None or stamp >= self._command.stamp_ns:
                    self._command = _Command(stamp, w)

    def wait_for_node(self, timeout_s: float) -> None:
        """Wait until the node subscribes to the camera, the navigation, the mission (and, on
        simulated time, ``/clock``) and publishes its outputs.

        Raises:
            VehicleTimeout: no node on this DDS domain within ``timeout_s``.
        """
        needed = ["image", "odometry", "ds_prior"] + (["clock"] if self.sim_clock else [])
        pubs = [self.pubs[k] for k in needed if k in self.pubs]
        ends = [p for p, _, _ in pubs] + [s for s, _, _ in self.subs.values()]
        if not self.graph.wait_matched(ends, timeout_s):
            missing = [t for p, t, _ in pubs if p.matched() == 0]
            missing += [t for s, t, _ in self.subs.values() if s.matched() == 0]
            raise VehicleTimeout(
                f"no docking node on DDS domain {self.graph.domain_id} after {timeout_s:g} s "
                f"(unmatched: {', '.join(missing[:4])})"
            )

    def _wait_answer(self, t_ns: int) -> None:
        """Lock-step: wait for the node's diagnostics of the tick at ``t_ns``."""
        deadline = time.monotonic() + self.answer_timeout_s
        while self._answered_ns is None or self._answered_ns < t_ns:
            left = deadline - time.monotonic()
            if left <= 0:
                raise VehicleTimeout(
                    f"the node did not answer the tick at {t_ns / _NS:.1f} s within "
                    f"{self.answer_timeout_s:g} s"
                )
            self.graph.wait(min(left, 0.5))
            self._drain()
        self._drain()  # the command, acknowledged before the diagnostics, is here now

    # ------------------------------------------------------------------ sensors

    def _sensors(self, t_ns: int, t_episode_s: float) -> None:
        """Publish what the vehicle's sensors and navigation report now."""
        env, cfg, axes = self.env, self.cfg, self.cfg.axes
        f = cfg.frames
        nav = env.navigation_solution()
        T_wire = conv.pose_to_wire(nav["T_world_body"], axes)
        self._publish(
            "odometry",
            rm.odometry_msg(
                T_wire,
                conv.body_vector_to_wire(nav["velocity_frd_mps"], axes),
                conv.body_vector_to_wire(nav["angular_velocity_frd_radps"], axes),
                t_ns,
                f.world,
                f.body,
            ),
            t_ns,
        )
        self._publish(
            "imu",
            rm.imu_msg(
                T_wire[:3, :3],
                conv.body_vector_to_wire(nav["angular_velocity_frd_radps"], axes),
                conv.body_vector_to_wire(nav["specific_force_frd_mps2"], axes),
                t_ns,
                f.body,
            ),
            t_ns,
        )
        self._publish(
            "accel",
            rm.accel_stamped_msg(
                conv.body_vector_to_wire(nav["acceleration_frd_mps2"], axes), t_ns, f.body
            ),
            t_ns,
        )
        fix = env.last_usbl_fix
        if fix is not None:
            p, sigma = fix
            var = sigma**2  # as the env's filter squares it
            T = np.eye(4)
            T[:3, 3] = conv.world_vector_to_wire(p, axes)
            cov = np.diag([var, var, var, 0.0, 0.0, 0.0])
            self._publish("usbl", rm.pose_cov_stamped_msg(T, cov, t_ns, f.world), t_ns)
        out = self.camera_outage_s
        if out is None or not out[0] <= t_episode_s < out[1]:
            frame = env.source.last_frame
            if frame is not None:
                img = frame.img_bgr()
                if cfg.topics.image_format == "compressed":
                    msg = rm.compressed_image_msg(img, t_ns, "camera", self.jpeg_quality)
                else:
                    msg = rm.image_msg(img, t_ns, "camera")
                self._publish("image", msg, t_ns)

    def _advance_clock(self, t_ns: int) -> None:
        """Let the node's readers acknowledge what was published, then move ``/clock``."""
        if self.sim_clock:
            for pub, _, _ in self.pubs.values():
                pub.wait_for_acks(5.0)
        self.clock_ns = t_ns
        self._publish("clock", rm.clock_msg(t_ns), t_ns)

    def _camera_info(self, t_ns: int) -> None:
        cam = self.env.world.camera.model
        msg = rm.camera_info_msg(cam.K, cam.dist, cam.width_px, cam.height_px, t_ns, "camera")
        self._publish("camera_info", msg, t_ns)

    # ------------------------------------------------------------------ episodes

    def _wrench(self, t_ns: int) -> np.ndarray:
        """The newest command, held until it is ``command_timeout_s`` old, then zero."""
        c = self._command
        if c is None or t_ns - c.stamp_ns > self.command_timeout_ns:
            return np.zeros(6)
        return c.wrench_frd

    def episode(self, k: int, seed: int, start_ns: int) -> tuple[dict[str, Any], int]:
        """Episode ``k`` on seed ``seed + k`` from simulated time ``start_ns``; returns its row
        (the keys of ``rl eval``'s ``episodes.csv``) and the time it ended."""
        env = self.env
        _, info = env.reset(seed=seed + k)
        if not self.sim_clock:  # real time: the episode starts now, whatever the reset took
            self._origin_ns = time.time_ns() - start_ns
        self._command = None
        T_prior, var = env.ds_prior
        cov = np.zeros((6, 6))
        cov[[0, 1, 2, 5], [0, 1, 2, 5]] = var
        T_wire = conv.frame_pose_to_wire(T_prior, self.cfg.axes)
        stamp = self._origin_ns + start_ns
        prior = rm.pose_cov_stamped_msg(T_wire, cov, stamp, self.cfg.frames.world)
        self._publish("ds_prior", prior, stamp)
        failures = FailureTracker()
        ret, collisions, steps, dock_time = 0.0, 0, 0, None
        t_ns, done = start_ns, False
        while not done:
            stamp = self._origin_ns + t_ns
            self._sensors(stamp, (t_ns - start_ns) / _NS)
            self._advance_clock(stamp)
            if self.sim_clock:
                self._wait_answer(stamp)
            else:  # real time: the node's commands arrive while the period runs out
                while time.time_ns() < stamp + self.period_ns:
                    left = (stamp + self.period_ns - time.time_ns()) / _NS
                    self.graph.wait(max(0.0, min(left, 0.02)))
                    self._drain()
            w = self._wrench(stamp + (0 if self.sim_clock else self.period_ns))
            _, r, term, trunc, info = env.step_wrench(w)
            ret += r
            steps += 1
            collisions += int(info["collided"])
            a = np.divide(w, env.action_limits, out=np.zeros(6), where=env.action_limits > 0)
            failures.update(info["time_s"], info["T_world_body"][:3, 3], info["e_true"], a)
            if info["success_paper"] and dock_time is None:
                dock_time = info["time_s"]
            t_ns += self.period_ns
            done = term or trunc
        row = episode_row(k, seed, info, dock_time, steps, ret, collisions, failures)
        return row, t_ns

    def run(
        self,
        episodes: int,
        seed: int,
        progress: Callable[[int, dict[str, Any]], None] | None = None,
    ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        """``episodes`` seeded episodes (episode k: seed + k), one after another on one clock;
        returns (summary, rows) with ``rl eval``'s keys."""
        rows = []
        gap = round(EPISODE_GAP_S * _NS)
        t_ns = self.period_ns * math.ceil(gap / self.period_ns)
        if not self.sim_clock:
            self._origin_ns = time.time_ns() - t_ns
        self._camera_info(self._origin_ns + t_ns)
        for k in range(episodes):
            row, end_ns = self.episode(k, seed, t_ns)
            rows.append(row)
            if progress is not None:
                progress(k + 1, row)
            t_ns = self.period_ns * math.ceil((end_ns + gap) / self.period_ns)
        return summarise(rows), rows

    def close(self) -> None:
        self.env.close()
        if self.recorder is not None:
            self.recorder.close()
