"""The vehicle's commands: ``rl node``, ``rl replay`` (``uwdock[vehicle]``: no torch, no SAPIEN)
and ``sim vehicle`` (the simulator as the vehicle: ``uwdock[rl]``).

The umbrella command lends them to their groups (``uwdock.cli.LENT``): ``rl node`` and
``rl replay`` are the rl group's, ``sim vehicle`` the sim group's, while this module, which
imports neither the simulator nor the learning stack at module level, defines all three.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Annotated

import click

from uwdock.dockcore.cli import domain_type
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.domains import Count, Interval, Seed
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, atomic_write_text, check_regular_file
from uwdock.dockcore.options import (
    command_group,
    config_option,
    out_dir_option,
    out_path_checked,
    seed_option,
)
from uwdock.dockcore.outdir import claim_output_dir
from uwdock.dockcore.provenance import provenance
from uwdock.perception.detector import rendered_3dbm_config
from uwdock.rl.deploy.chain import DockingChain
from uwdock.rl.deploy.config import NodeConfig, load_node_config
from uwdock.rl.deploy.node import VehicleNode
from uwdock.rl.deploy.replay import replay_bag
from uwdock.rl.deploy.runner import DockingRunner
from uwdock.rl.policy.env_settings import command_env
from uwdock.ros.mcap import McapRecorder

#: The shipped policy, exported (``rl export``): what ``rl node`` and ``rl replay`` run unless
#: told otherwise.
SHIPPED_POLICY = Path(__file__).resolve().parents[1] / "policies" / "realistic_ppo" / "policy.onnx"

_DOMAIN = Annotated[int, Interval(ge=0, le=232)]

POLICY_OPTION = click.option(
    "--policy",
    type=click.Path(path_type=Path),
    default=None,
    help="An exported policy (.onnx with its .json: `rl export`) [the shipped policy, "
    "rl/policies/realistic_ppo/policy.onnx]. Policy folders (policy.zip, pickles) are refused: "
    "loading them can run code.",
)
CAMERA_OPTION = click.option(
    "--camera-file",
    type=click.Path(path_type=Path),
    help="Camera YAML/JSON (intrinsics + T_body_cam) [intrinsics from camera_info, the "
    "reference T_body_cam].",
)
MARKERS_OPTION = click.option(
    "--marker-set", type=click.Path(path_type=Path), help="DS marker set [the reference DS]."
)
CLOCK_OPTION = click.option(
    "--clock",
    type=click.Choice(["wall", "sim"]),
    default="wall",
    show_default=True,
    help="Tick on the system clock, or on /clock (simulated time, lock-step with `sim vehicle "
    "--clock sim`).",
)
DOMAIN_OPTION = click.option(
    "--domain-id",
    type=domain_type(_DOMAIN),
    default=lambda: int(os.environ.get("ROS_DOMAIN_ID", "0") or 0),
    show_default="ROS_DOMAIN_ID or 0",
    help="DDS domain (ROS_DOMAIN_ID).",
)
NETWORK_OPTION = click.option(
    "--network",
    type=click.Choice(["loopback", "system"]),
    default="loopback",
    show_default=True,
    help="loopback: discovery and traffic on 127.0.0.1 only (simulation, tests); system: "
    "Cyclone DDS's own configuration (CYCLONEDDS_URI), what a vehicle uses.",
)
RECORD_OPTION = click.option(
    "--record",
    type=click.Path(path_type=Path),
    callback=out_path_checked,
    help="Record every input received and output published to this .mcap file.",
)


@command_group()
def cli() -> None:
    """The docking node, mission replay and the simulated vehicle."""


def _policy_path(policy: Path | None) -> Path:
    """The exported policy to load: only an .onnx with its .json (no pickle ever)."""
    p = SHIPPED_POLICY if policy is None else Path(policy)
    if p.is_dir():
        raise DockError(
            f"--policy {p}: the node runs an exported policy (an .onnx and its .json): `rl "
            f"export --policy {p} --out POLICY.onnx` writes one"
        )
    if p.suffix in (".zip", ".pkl"):
        raise DockError(
            f"--policy {p}: a pickle, which can run code when loaded; the node runs an exported "
            "policy (an .onnx from `rl export`)"
        )
    if p.suffix != ".onnx":
        raise DockError(f"--policy {p}: not an .onnx file")
    check_regular_file(p, "ONNX policy")
    check_regular_file(p.with_suffix(".json"), "policy's .json (written by `rl export`)")
    return p


def build_chain(
    policy: Path | None,
    camera_file: Path | None,
    marker_set: Path | None,
    cfg: NodeConfig,
    armed: bool,
) -> DockingChain:
    """The docking chain of an exported policy, with the node's detector and safety settings.

    Raises:
        DockError: a bad policy, camera file or marker set, or a control rate other than the
            policy's.
    """
    p = _policy_path(policy)
    detector = None if cfg.flat_markers else rendered_3dbm_config()
    runner = DockingRunner(p, camera_file=camera_file, marker_set=marker_set, detector=detector)
    hz = runner.cfg.control_hz
    if cfg.control_hz and abs(cfg.control_hz - hz) > 1e-9:
        raise DockError(
            f"control_hz = {cfg.control_hz:g} in the node config, but the policy was trained "
            f"at {hz:g} Hz: its observation and action mean what they mean only at that rate"
        )
    return DockingChain(runner, cfg, armed=armed, log=lambda line: click.echo(line, err=True))


def _dds():
    """The DDS modules (Cyclone DDS's Python binding), imported only by the commands on the
    wire: ``rl replay`` runs without them (PyPI has no aarch64 wheel of ``cyclonedds``)."""
    try:
        from uwdock.ros import dds
    except ModuleNotFoundError as exc:
        raise DockError(
            f"this command needs Cyclone DDS's Python binding ({exc.name} is not installed): "
            "pip install 'uwdock[vehicle]' (x86-64; elsewhere see docs/guides/vehicle.md)"
        ) from None
    return dds


def _graph(domain_id: int, network: str):
    dds = _dds()
    try:
        return dds.DdsGraph(domain_id, loopback=network == "loopback")
    except Exception as exc:  # Cyclone's DDSException and configuration errors
        raise DockError(f"cannot join DDS domain {domain_id}: {exc}") from None


@cli.command("node")
@POLICY_OPTION
@CAMERA_OPTION
@MARKERS_OPTION
@config_option("TOML of the node: topics, frames, QoS, axes, safety (rl/deploy/profiles/).")
@click.option("--armed", is_flag=True, help="Start enabled (simulation, tests): no enable needed.")
@CLOCK_OPTION
@DOMAIN_OPTION
@NETWORK_OPTION
@RECORD_OPTION
@click.option(
    "--duration-s",
    type=domain_type(Annotated[float, Interval(gt=0, le=1e7)]),
    help="Stop after this long (s, wall clock) [run until SIGTERM / Ctrl-C].",
)
def node_cmd(
    policy, camera_file, marker_set, config_path, armed, clock, domain_id, network, record,
    duration_s,
) -> None:  # fmt: skip
    """Run the docking node on ROS 2 topics (DDS, no ROS install needed).

    Subscribes to the downward camera, camera_info, the navigation's odometry, IMU and USBL
    fixes and the mission topics (DS prior, enable, abort); publishes the DS pose and its
    filtered estimate, the body wrench, /tf and /diagnostics at the policy's rate. Starts
    disarmed (no command) until `true` arrives on the enable topic; holds with a zero wrench
    and says why when an input goes stale or is refused. SIGTERM stops it after a last zero
    wrench.
    """
    cfg = load_node_config(str(config_path) if config_path else None)
    chain = build_chain(policy, camera_file, marker_set, cfg, armed)
    graph = _graph(domain_id, network)
    recorder = McapRecorder(record) if record else None
    node = VehicleNode(chain, cfg, graph, clock == "sim", recorder, camera_file is not None)
    click.echo(
        f"rl node: {cfg.name} on DDS domain {domain_id} ({network}), clock {clock}, "
        f"{'armed' if armed else 'disarmed'}, {chain.runner.cfg.control_hz:g} Hz, policy "
        f"{_policy_path(policy)}",
        err=True,
    )
    end = None if duration_s is None else time.monotonic() + duration_s
    reason = "stopped"
    try:
        node.run(stop=lambda: end is not None and time.monotonic() >= end)
    except KeyboardInterrupt:
        reason = "stopped by a signal"
        raise
    finally:
        node.shutdown(reason)
        c = chain.counts
        click.echo(
            f"rl node: {node.ticks} ticks ({c['holding_ticks']} holding), "
            f"{c['frames_used']} frames used, {c['frames_dropped']} dropped, "
            f"{sum(v for k, v in c.items() if k.startswith('refused_'))} inputs refused",
            err=True,
        )


@cli.command("replay")
@click.argument("bag", type=click.Path(path_type=Path))
@POLICY_OPTION
@CAMERA_OPTION
@MARKERS_OPTION
@config_option("TOML of the node: the topics to read, frames, axes, safety.")
@click.option(
    "--armed/--disarmed",
    default=True,
    show_default=True,
    help="Compute commands as if enabled from the start (enable/abort messages in the bag "
    "still apply).",
)
@out_dir_option(None, required=True)
def replay_cmd(bag, policy, camera_file, marker_set, config_path, armed, out_dir) -> None:
    """Run a recorded mission (ROS 1 .bag, ROS 2 folder, .db3 or .mcap) through the node's
    chain on message time: writes replay.mcap (inputs and outputs), summary.json and a plot.
    Deterministic: two replays give the same track and commands."""
    cfg = load_node_config(str(config_path) if config_path else None)
    chain = build_chain(policy, camera_file, marker_set, cfg, armed)
    settings = {
        "policy": str(_policy_path(policy)),
        "camera_file": None if camera_file is None else str(camera_file),
        "marker_set": None if marker_set is None else str(marker_set),
        "armed_from_start": armed,
    }
    with claim_output_dir(out_dir, "rl replay") as out:
        s = replay_bag(bag, chain, cfg, out, camera_file is not None, settings)
    f = s["frames"]
    click.echo(
        f"rl replay: {s['ticks']} ticks, {f['used']} of {f['received']} frames used, "
        f"{s['frames_with_ds_pose']} with a DS pose; p99 {s['latency_ms']['total']['p99']} ms "
        f"per frame; wrote {out_dir}"
    )


@cli.command("vehicle")
@click.option(
    "--policy",
    type=click.Path(path_type=Path),
    default=None,
    help="The policy whose training env the vehicle simulates (its .json or run folder is "
    "read, never its weights) [the shipped policy].",
)
@click.option("--episodes", type=domain_type(Count), default=1, show_default=True)
@seed_option(domain_type(Seed), default=1000, show_default=True)
@config_option("TOML of the node (topics, frames, QoS, axes): the vehicle speaks its names.")
@CLOCK_OPTION
@DOMAIN_OPTION
@NETWORK_OPTION
@RECORD_OPTION
@click.option(
    "--camera-outage-s",
    help="START:END (s of each episode): publish no camera frame in between (a camera that "
    "fails and comes back).",
)
@click.option(
    "--jpeg-quality",
    type=domain_type(Annotated[int, Interval(ge=1, le=100)]),
    default=90,
    show_default=True,
    help="JPEG quality when the node's image_format is compressed.",
)
@click.option(
    "--command-timeout-s",
    type=domain_type(Annotated[float, Interval(gt=0, le=60)]),
    default=1.0,
    show_default=True,
    help="Apply a zero wrench once the newest command is older than this.",
)
@click.option(
    "--wait-node-s",
    type=domain_type(Annotated[float, Interval(gt=0, le=3600)]),
    default=60.0,
    show_default=True,
    help="How long to wait for the node to appear, and (lock-step) for each of its ticks.",
)
@out_dir_option("Write summary.json and episodes.csv (rl eval's keys) here.")
def vehicle_cmd(
    policy, episodes, seed, config_path, clock, domain_id, network, record, camera_outage_s,
    jpeg_quality, command_timeout_s, wait_node_s, out_dir,
) -> None:  # fmt: skip
    """Run the simulator as the vehicle on ROS 2 topics: the rendered downward camera, the
    drifting navigation, USBL fixes and /clock out; body wrench commands in (zero-order hold,
    its own timeout). With --clock sim, lock-step on simulated time: the same episodes as
    in-process `rl eval` on the same seeds."""
    try:  # the simulator (SAPIEN, through the env): uwdock[rl]
        from uwdock.rl.deploy.vehicle import SimVehicle, VehicleTimeout
        from uwdock.rl.evaluate.report import csv_text
    except ModuleNotFoundError as exc:
        raise DockError(
            f"sim vehicle needs the simulator ({exc.name} is not installed): "
            "pip install 'uwdock[rl]'"
        ) from None

    outage = _outage(camera_outage_s)
    source = str(SHIPPED_POLICY if policy is None else policy)
    if not Path(source).exists():
        raise DockError(f"--policy {source}: not found")
    cfg = load_node_config(str(config_path) if config_path else None)
    resolved = command_env(source, defaults={"terminate_on": "strict", "obs_source": "camera"})
    env_cfg = resolved.cfg
    click.echo(resolved.line("sim vehicle"), err=True)

    def run(out: Path | None) -> dict:
        graph = _graph(domain_id, network)
        recorder = McapRecorder(record) if record else None
        veh = SimVehicle(
            env_cfg, cfg, graph, clock == "sim", command_timeout_s, jpeg_quality, outage,
            wait_node_s, recorder,
        )  # fmt: skip
        try:
            click.echo(f"sim vehicle: waiting for the node on DDS domain {domain_id}", err=True)
            veh.wait_for_node(wait_node_s)

            def progress(k: int, row: dict) -> None:
                ok = "docked" if row["success_strict"] else "not docked"
                click.echo(f"sim vehicle: episode {k}/{episodes} (seed {row['seed']}): {ok}")

            summary, rows = veh.run(episodes, seed, progress)
        except VehicleTimeout as exc:
            raise DockError(str(exc)) from None
        finally:
            veh.close()
        summary = {
            "vehicle": "sim vehicle",
            "clock": clock,
            "obs_source": "camera (over DDS: rl node)",
            "usbl_preset": env_cfg.usbl.preset,
            "nav_preset": env_cfg.nav.preset,
            **summary,
        }
        if out is not None:
            atomic_write_text(out / "episodes.csv", csv_text(rows))
            record_ = provenance({"env": env_cfg, "node": cfg}, extra={"summary": summary})
            atomic_write_json(
                out / "summary.json", {**summary, "config": to_dict(env_cfg), "provenance": record_}
            )
        return summary

    if out_dir is None:
        s = run(None)
    else:
        with claim_output_dir(out_dir, "sim vehicle") as out:
            s = run(out)
    click.echo(
        f"sim vehicle: strict {s['success_rate_strict']:.1%} over {s['episodes']} episodes"
        + (f"; wrote {out_dir}" if out_dir else "")
    )


def _outage(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        a, b = (float(v) for v in text.split(":"))
    except ValueError:
        raise DockError(f"--camera-outage-s must be START:END in seconds, got {text!r}") from None
    if not (0 <= a < b <= 1e6):
        raise DockError(f"--camera-outage-s: need 0 <= START < END, got {text!r}")
    return a, b
