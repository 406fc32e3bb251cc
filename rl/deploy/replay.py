"""``rl replay``: a recorded mission through the node's chain, on message time.

The bag's input topics (the node's config names them: camera, camera info, odometry, IMU,
acceleration, USBL, DS prior, enable, abort) are read in the order they were recorded
(:meth:`uwdock.dockcore.bags.Bag.messages`) and handed to the same :class:`DockingChain` the
live node runs, through the same dispatcher; the chain ticks on the control period's grid of
the recording's time, after every message recorded at or before the tick. Nothing depends on
the wall clock but the latencies: two replays of one bag give the same DS pose track, the
same detections and the same commands.

Outputs (``--out DIR``): ``replay.mcap`` (the inputs used and every output, ROS 2 CDR with
``ros2msg`` schemas), ``summary.json`` (frames, detections per frame, the DS pose track, the
commands, latency per stage, the config and provenance) and ``replay_track.png``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from uwdock.calibration.frames import rpy_from_R
from uwdock.dockcore.bags import Bag
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_json, check_regular_file
from uwdock.dockcore.provenance import provenance
from uwdock.rl.deploy.chain import DockingChain, Tick
from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.wire import Dispatcher, input_topics, tick_messages
from uwdock.ros import messages as rm
from uwdock.ros.mcap import McapRecorder

__all__ = ["replay_bag"]

_STAGES = ("decode", "perception", "filter", "policy", "total")


def _track_row(tick: Tick) -> dict[str, Any]:
    """One tick of the deterministic track (no wall-clock value)."""
    T, P = tick.T_world_ds, tick.cov_xyzyaw
    row: dict[str, Any] = {
        "t_s": tick.stamp_ns / 1e9,
        "state": tick.state,
        "reasons": tick.reasons,
        "frame_t_s": None if tick.frame_stamp_ns is None else tick.frame_stamp_ns / 1e9,
        "detections": tick.detections,
        "ds_estimate_xyz_m": [float(v) for v in T[:3, 3]],
        "ds_estimate_yaw_rad": rpy_from_R(T[:3, :3])[2],
        "ds_estimate_sigma_xy_m": math.sqrt(max(P[0, 0], P[1, 1])),
        "command_wrench": None if tick.command is None else [float(v) for v in tick.command],
    }
    m = tick.measurement
    row["ds_pose_xyz_m"] = None if m is None else [float(v) for v in m.T_world_ds[:3, 3]]
    row["ds_pose_yaw_rad"] = None if m is None else rpy_from_R(m.T_world_ds[:3, :3])[2]
    return row


def replay_bag(
    bag_path: str | Path,
    chain: DockingChain,
    cfg: NodeConfig,
    out_dir: Path,
    camera_file_given: bool,
    settings: dict[str, Any],
) -> dict[str, Any]:
    """Replay ``bag_path`` through ``chain`` into ``out_dir`` (module docstring); returns the
    summary. ``settings``: what the summary records of the run (policy, camera file ...).

    Raises:
        DockError: the bag has none of the node's input topics, or no navigation topic.
    """
    if not Path(bag_path).is_dir():  # a FIFO or device would block the reader
        check_regular_file(bag_path, "recording")
    dispatch = Dispatcher(chain, cfg, camera_file_given)
    inputs = input_topics(cfg)
    ticks: list[Tick] = []
    with Bag(bag_path) as bag:
        present = {t.name for t in bag.topics()}
        used = {name: it for name, it in inputs.items() if name in present}
        if cfg.topics.odometry not in used:
            raise DockError(
                f"bag {Path(bag_path).name} has no navigation topic {cfg.topics.odometry!r} "
                f"(its topics: {', '.join(sorted(present)) or 'none'}); name yours in the "
                "node config's [node.topics]"
            )
        if cfg.topics.image not in used:
            raise DockError(
                f"bag {Path(bag_path).name} has no camera topic {cfg.topics.image!r} "
                f"({cfg.topics.image_format}); name yours in the node config's [node.topics]"
            )
        total = sum(t.count for t in bag.topics() if t.name in used)
        rec = McapRecorder(out_dir / "replay.mcap")
        skipped = 0
        try:
            next_tick: int | None = None
            bar = tqdm(total=total, desc="replay", unit="msg")
            for topic, _, t_log, msg, raw, error in bag.messages(list(used)):
                it = used[topic]
                if next_tick is None:
                    next_tick = chain.next_tick_ns(t_log)
                while t_log > next_tick:
                    ticks.append(_tick(chain, cfg, rec, next_tick))
                    next_tick += chain.period_ns
                if msg is not None:
                    try:  # the Jazzy bytes of what was read (a ROS 1 bag's are not CDR)
                        cdr = raw if not bag.is_ros1 else rm.serialize(msg, it.typename)
                        rec.write_cdr(topic, it.typename, cdr, t_log)
                    except Exception:  # a ROS 1 type that differs from Jazzy's: not recorded
                        skipped += 1
                dispatch.feed(it.kind, msg, t_log, error)
                bar.update(1)
            bar.close()
            if next_tick is not None:
                ticks.append(_tick(chain, cfg, rec, next_tick))
            rec.close()
        except BaseException:
            rec.discard()
            raise
    summary = _summary(chain, ticks, skipped, cfg, settings, Path(bag_path))
    atomic_write_json(out_dir / "summary.json", summary)
    _plot(ticks, out_dir / "replay_track.png")
    return summary


def _tick(chain: DockingChain, cfg: NodeConfig, rec: McapRecorder, t_ns: int) -> Tick:
    tick = chain.tick(t_ns)
    for _, topic, typename, msg in tick_messages(tick, cfg, chain.damping):
        rec.write(topic, typename, msg, t_ns)
    return tick


def _summary(
    chain: DockingChain,
    ticks: list[Tick],
    skipped: int,
    cfg: NodeConfig,
    settings: dict[str, Any],
    bag: Path,
) -> dict[str, Any]:
    lat = {
        k: np.array([t.latency_ms[k] for t in ticks if t.frame_stamp_ns is not None])
        for k in _STAGES
    }

    def stats(a: np.ndarray) -> dict[str, float | None]:
        if a.size == 0:
            return {"p50": None, "p99": None, "mean": None}
        return {
            "p50": float(np.percentile(a, 50)),
            "p99": float(np.percentile(a, 99)),
            "mean": float(a.mean()),
        }

    c = chain.counts
    used = [t for t in ticks if t.frame_stamp_ns is not None]
    summary = {
        "bag": str(bag),
        "ticks": len(ticks),
        "frames": {
            "received": c["frames"],
            "used": c["frames_used"],
            "dropped_superseded": c["frames_dropped"],
            "refused": c["refused_image"],
            "outside_navigation": c["frames_outside_nav"],
        },
        "frames_with_ds_pose": sum(t.measurement is not None for t in used),
        "detections_per_frame": [t.detections for t in used],
        "states": {s: sum(t.state == s for t in ticks) for s in ("disarmed", "armed", "holding")},
        "inputs_not_recorded": skipped,
        "counts": dict(sorted(c.items())),
        "latency_ms": {k: stats(v) for k, v in lat.items()},
        "track": [_track_row(t) for t in ticks],
        **settings,
        "config": to_dict(cfg),
    }
    summary["provenance"] = provenance({"node": cfg}, extra={"bag": str(bag)})
    return summary


def _plot(ticks: list[Tick], path: Path) -> None:
    """The DS estimate against the camera measurements, the command, and detections."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not ticks:
        return
    t = np.array([k.stamp_ns for k in ticks]) / 1e9
    t = t - t[0]
    est = np.array([k.T_world_ds[:3, 3] for k in ticks])
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, name in enumerate("xyz"):
        ax[0].plot(t, est[:, i], label=f"estimate {name}")
    meas = [
        (tt, k.measurement.T_world_ds[:3, 3])
        for tt, k in zip(t, ticks, strict=True)
        if k.measurement is not None
    ]
    if meas:
        mt = np.array([m[0] for m in meas])
        mp = np.array([m[1] for m in meas])
        for i in range(3):
            ax[0].plot(mt, mp[:, i], ".", ms=3, color=f"C{i}")
    ax[0].set_ylabel("DS position (m)")
    ax[0].legend(loc="upper right", fontsize=8)
    cmd = np.array([k.command if k.command is not None else np.full(6, np.nan) for k in ticks])
    for i, name in enumerate(("Fx", "Fy", "Fz")):
        ax[1].plot(t, cmd[:, i], label=name)
    ax[1].set_ylabel("command (N)")
    ax[1].legend(loc="upper right", fontsize=8)
    ax[2].step(t, [k.detections for k in ticks], where="post")
    holding = [tt for tt, k in zip(t, ticks, strict=True) if k.state == "holding"]
    if holding:
        ax[2].plot(holding, np.zeros(len(holding)), "r|", ms=12, label="holding")
        ax[2].legend(loc="upper right", fontsize=8)
    ax[2].set_ylabel("markers decoded")
    ax[2].set_xlabel("time (s)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
