"""``rl node``: the docking chain as a ROS 2 node on DDS (no ROS installation).

:class:`VehicleNode` subscribes to the vehicle's camera, navigation, USBL and mission topics
(:func:`rl.deploy.wire.input_topics`), hands every message to the chain, ticks it at the
policy's rate and publishes what each tick decided (:func:`rl.deploy.wire.tick_messages`).

Time. ``clock = "wall"``: ticks follow the system clock (a tick that comes late is run once,
the missed ones counted). ``clock = "sim"``: ticks follow ``/clock`` (ROS's ``use_sim_time``):
a tick at t runs once the clock has reached t, after the inputs that arrived before the clock
said so (:class:`rl.deploy.vehicle.SimVehicle` waits until they are acknowledged before it
advances the clock, so a lock-step run is deterministic).

Stopping. SIGTERM or SIGINT (the CLI turns them into ``KeyboardInterrupt``) ends the loop;
:meth:`VehicleNode.shutdown` then publishes a last zero wrench (when armed) and a diagnostics
message saying the node stopped, and closes the recording.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from uwdock.rl.deploy.chain import DockingChain, Tick
from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.wire import Dispatcher, input_topics, output_types, tick_messages
from uwdock.ros import messages as rm
from uwdock.ros.mcap import McapRecorder
from uwdock.ros.qos import QosProfile

if TYPE_CHECKING:  # Cyclone DDS: the graph is made by the command (rl.deploy.cli)
    from uwdock.ros.dds import DdsGraph, Publisher

__all__ = ["VehicleNode"]

#: How long a lock-step tick waits for the vehicle to acknowledge the command (s).
ACK_TIMEOUT_S = 2.0


class VehicleNode:
    """The chain on DDS (module docstring).

    Args:
        chain: the docking chain (policy, estimator, safety).
        cfg: topics, frames, QoS.
        graph: the DDS participant.
        sim_clock: tick on ``/clock`` (lock-step simulation) instead of the system clock.
        recorder: an MCAP recording of every input received and every output published.
        camera_file_given: the intrinsics come from a camera file (``camera_info`` is then
            recorded but not used).
    """

    def __init__(
        self,
        chain: DockingChain,
        cfg: NodeConfig,
        graph: DdsGraph,
        sim_clock: bool = False,
        recorder: McapRecorder | None = None,
        camera_file_given: bool = True,
    ) -> None:
        self.chain, self.cfg, self.graph = chain, cfg, graph
        self.sim_clock, self.recorder = sim_clock, recorder
        self.dispatch = Dispatcher(chain, cfg, camera_file_given, check_future=not sim_clock)
        self.inputs = input_topics(cfg, sim_clock)
        self.subs = {
            topic: (graph.subscription(topic, it.typename, it.qos), it)
            for topic, it in self.inputs.items()
        }
        self.pubs: dict[str, Publisher] = {}
        for kind, (topic, typename) in output_types(cfg).items():
            qos = {"command": cfg.qos.command, "velocity_command": cfg.qos.command,
                   "tf": cfg.qos.tf}.get(kind, cfg.qos.outputs)  # fmt: skip
            if sim_clock:
                qos = QosProfile("reliable", qos.depth, qos.durability)
            self.pubs[kind] = graph.publisher(topic, typename, qos)
        ends = [sub for sub, _ in self.subs.values()] + list(self.pubs.values())
        self._announce = graph.announce_node(cfg.name, ends)  # ``ros2 node list`` shows it
        self.ticks = 0
        self.last_tick: Tick | None = None

    # ------------------------------------------------------------------ loop

    def now_ns(self) -> int | None:
        """The node's time: the newest ``/clock`` (sim), or the system clock (wall)."""
        return self.dispatch.clock_ns if self.sim_clock else time.time_ns()

    def poll(self) -> int:
        """Take every waiting sample of every input and hand it to the chain; returns how
        many."""
        n = 0
        for topic, (sub, it) in self.subs.items():
            for r in sub.take():
                now = self.now_ns() or 0
                if self.recorder is not None and r.cdr:
                    self.recorder.write_cdr(topic, it.typename, r.cdr, now)
                self.dispatch.feed(it.kind, r.msg, now, r.error)
                n += 1
        return n

    def run(self, stop: Callable[[], bool] = lambda: False, max_ticks: int | None = None) -> int:
        """Run until ``stop()`` is true or ``max_ticks`` ticks have run; returns the ticks."""
        period = self.chain.period_ns
        next_tick: int | None = None
        while not stop() and (max_ticks is None or self.ticks < max_ticks):
            if self.sim_clock:
                self.graph.wait(0.2)
                self.poll()
                clock = self.dispatch.clock_ns
                if clock is None:
                    continue
                if next_tick is None:
                    next_tick = self.chain.next_tick_ns(clock)
                if clock >= next_tick:
                    self.poll()  # what was acknowledged before the clock moved is here now
                while clock >= next_tick and (max_ticks is None or self.ticks < max_ticks):
                    self._tick(next_tick)
                    next_tick += period
            else:
                now = time.time_ns()
                if next_tick is None:
                    next_tick = self.chain.next_tick_ns(now)
                if now < next_tick:
                    self.graph.wait(min((next_tick - now) / 1e9, 0.05))
                    self.poll()
                    continue
                self.poll()
                late = (now - next_tick) // period
                if late > 0:
                    self.chain.counts["ticks_missed"] += int(late)
                self._tick(now)
                next_tick = self.chain.next_tick_ns(now + 1)
        return self.ticks

    def _tick(self, t_ns: int) -> None:
        tick = self.chain.tick(t_ns)
        self.publish(tick_messages(tick, self.cfg, self.chain.damping), t_ns)
        self.ticks += 1
        self.last_tick = tick

    def publish(self, msgs: list[tuple[str, str, str, Any]], t_ns: int) -> None:
        """Publish (and record) a tick's messages; in lock-step, the command is acknowledged
        by the vehicle before the diagnostics go out."""
        for kind, topic, typename, msg in msgs:
            pub = self.pubs[kind]
            cdr = pub.publish(msg)
            if self.recorder is not None:
                self.recorder.write_cdr(topic, typename, cdr, t_ns)
            if kind == "command" and self.sim_clock:
                pub.wait_for_acks(ACK_TIMEOUT_S)

    def shutdown(self, reason: str = "stopped") -> None:
        """A last zero wrench (when armed) and a diagnostics message saying why the node
        stops; then the recording is closed."""
        t = self.now_ns() or 0
        if self.last_tick is not None:
            t = max(t, self.last_tick.stamp_ns)
        msgs = []
        f = self.cfg.frames
        if self.chain.armed and "command" in self.pubs:
            topic, typename = output_types(self.cfg)["command"]
            msgs.append(("command", topic, typename, rm.wrench_stamped_msg(np.zeros(6), t, f.body)))
        if "diagnostics" in self.pubs:
            topic, typename = output_types(self.cfg)["diagnostics"]
            values = {"state": "stopped", "reasons": reason}
            diag = rm.diagnostic_array_msg(
                t, [(rm.DIAG_STALE, self.cfg.name, reason, f.body, values)]
            )
            msgs.append(("diagnostics", topic, typename, diag))
        try:
            self.publish(msgs, t)
            for pub in self.pubs.values():
                pub.wait_for_acks(0.5)
        finally:
            if self.recorder is not None:
                self.recorder.close()
