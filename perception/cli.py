"""``perception``: detect 3DBM markers and the docking-station pose in images or video, and
evaluate pipelines against ground truth."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import click

from uwdock.calibration.camera import load_camera, resolve_camera
from uwdock.calibration.formats import camera_from_camera_info_msg
from uwdock.dockcore.bags import Bag, camera_info_topic_for, resolve_image_topic
from uwdock.dockcore.bench import format_table
from uwdock.dockcore.cli import domain_type, run_group
from uwdock.dockcore.config import load_config
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import display_name, silence_opencv_log
from uwdock.dockcore.options import (
    command_group,
    config_option,
    json_option,
    out_dir_option,
    quiet_option,
)
from uwdock.markers.config import MarkerSideM
from uwdock.perception.detector import list_pipelines
from uwdock.perception.evaluate import PerceptionConfig, resolve_markers, run_detect, run_eval
from uwdock.perception.groundtruth import (
    is_dataset,
    load_checked_dataset,
    load_ground_truth,
    truth_from_bag,
)
from uwdock.perception.report_plots import COMPARE_COLUMNS


@command_group()
def cli() -> None:
    """Perception: 3DBM detection and docking-station pose from the marker board."""
    silence_opencv_log()  # the toolkit's own lines only (library noise: dockcore.media)


def _note(msg: str) -> None:
    msg = display_name(msg)  # a file name that is not UTF-8: \\xNN
    click.echo(msg if msg.startswith("warning: ") else f"note: {msg}", err=True)


def _config(config_path: Path | None, pipeline: str | None, level_ds: bool | None = None):
    overrides: dict[str, Any] = {"detector": {"pipeline": pipeline}} if pipeline else {}
    if level_ds is not None:
        overrides["pose"] = {"level_ds": level_ds}
    return load_config(PerceptionConfig, config_path, overrides=overrides, section="perception")


def _camera(path: Path | None):
    if path is None:
        return None

    return load_camera(path)[0]


def _bag_camera(input_path: Path, topic: str | None):
    """The camera of a bag's image topic from its ``camera_info`` topic (noted), or None when
    the bag has none."""
    if topic is None:
        return None
    with Bag(input_path) as bag:
        info = camera_info_topic_for(topic, bag.topics())
        if info is None:
            return None
        cam = camera_from_camera_info_msg(bag.camera_info(info))
    _note(f"camera from the bag's {info} ({cam.width_px}x{cam.height_px})")
    return cam


def _topic_option(fn):
    return click.option(
        "--topic",
        help="Image topic when INPUT is a ROS bag (.bag, .db3, .mcap or a ROS 2 folder); "
        "without it the bag's topics are listed and its only image topic is read.",
    )(fn)


def _marker_options(fn):
    opts = [
        click.option(
            "--markers",
            "markers_path",
            type=click.Path(dir_okay=False, path_type=Path),
            help="Marker set file (TOML/JSON from `markers generate`) [default: the DS set].",
        ),
        click.option(
            "--dictionary", help="Detect single markers of this dictionary (no board pose)."
        ),
        click.option(
            "--marker-size-m",
            type=domain_type(MarkerSideM),
            help="Single-marker side (m, at most 1): enables their poses.",
        ),
        click.option("--pipeline", help="Preprocessing pipeline [default]; see `pipelines`."),
        config_option("TOML with [detector], [board] and [report] tables (flags override it)."),
        quiet_option("No progress bar; print only the output."),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


def _camera_option(help_text: str):
    """``--camera`` (a camera file), described by ``help_text``."""
    return click.option(
        "--camera", "camera_path", type=click.Path(dir_okay=False, path_type=Path), help=help_text
    )


@cli.command()
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@_marker_options
@_camera_option("Camera file [default: the reference camera scaled to the frames].")
@out_dir_option(default=Path("perception_detect"), show_default=True)
@click.option("--no-annotate", is_flag=True, help="Write only detections.jsonl/.csv.")
@_topic_option
def detect(
    input_path,
    markers_path,
    dictionary,
    marker_size_m,
    pipeline,
    config_path,
    quiet,
    camera_path,
    out_dir,
    no_annotate,
    topic,
) -> None:
    """Detect markers in INPUT (an image, a folder of images, a video or a ROS bag's image
    topic) and solve the DS pose.

    Writes detections.jsonl and detections.csv (one row per frame; a bag's rows carry the
    frame's stamp_ns) and annotated images, or annotated.mp4 for a video or bag, into --out.
    A bag's camera comes from its camera_info topic unless --camera is given.
    """
    cfg = _config(config_path, pipeline)
    setup = resolve_markers(markers_path, dictionary, marker_size_m)
    if dictionary is not None and marker_size_m is None:
        _note("no --marker-size-m: markers are detected but no pose is solved")
    topic = resolve_image_topic(input_path, topic, _note)
    camera = _camera(camera_path) if camera_path is not None else _bag_camera(input_path, topic)
    result = run_detect(
        input_path,
        out_dir,
        setup,
        camera,
        cfg,
        annotate_frames=not no_annotate,
        progress=False if quiet else None,
        note=_note,
        topic=topic,
    )
    if quiet:
        click.echo(str(Path(out_dir) / "detections.jsonl"))
        return
    click.echo(
        f"frames: {result['frames']} decoded, {result['corrupt_frames']} corrupt; "
        f"{result['frames_with_detection']} with markers, {result['frames_with_pose']} with a "
        f"DS pose; {result['markers_detected_total']} markers in all"
    )
    click.echo(f"wrote {len(result['outputs'])} files to {out_dir}")


def _fmt(v: Any, unit: str = "", digits: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}{unit}"


def _print_summary(report: dict[str, Any], out_dir: Path) -> None:
    click.echo(
        f"[{report['pipeline']}] frames {report['frames']} ({report['corrupt_frames']} corrupt), "
        f"detection rate {_fmt(report['detection_rate'])}, pose rate {_fmt(report['pose_rate'])}, "
        f"{report['markers_detected_total']} markers, "
        f"{_fmt(report['ms_per_frame_median'], ' ms', 1)}/frame (median)"
    )
    if report["ground_truth"] is not None:
        click.echo(
            f"pose error: translation median {_fmt(report['translation_error_m_median'], ' m', 4)}"
            f" p90 {_fmt(report['translation_error_m_p90'], ' m', 4)}; rotation median "
            f"{_fmt(report['rotation_error_deg_median'], ' deg', 2)} p90 "
            f"{_fmt(report['rotation_error_deg_p90'], ' deg', 2)}; marker recall "
            f"{_fmt(report['marker_recall'])}"
        )
    if report["compare"]:
        click.echo(format_table(report["compare"], COMPARE_COLUMNS))
    click.echo(f"wrote {out_dir / 'report.json'} and {len(report['plots'])} plots")


@cli.command(name="eval")
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@_marker_options
@_camera_option("Camera file (required unless INPUT is a labelled dataset folder).")
@click.option(
    "--ground-truth",
    "gt_path",
    type=click.Path(path_type=Path),
    help="Labelled dataset folder, labels.jsonl or pose CSV (frame,x_m,y_m,z_m,qw,qx,qy,qz).",
)
@click.option("--compare", help="Comma-separated pipelines to run side by side.")
@click.option(
    "--level-ds/--no-level-ds",
    default=None,
    help="Re-solve the board with the DS level where a frame's label gives the vehicle attitude "
    "(T_world_body), as the env's camera source does [default: on, or [pose] level_ds].",
)
@_topic_option
@click.option(
    "--pose-topic",
    help="Ground truth from a bag: a pose topic (PoseStamped, PoseWithCovarianceStamped, "
    "TransformStamped or Odometry) holding T_cam_ds, matched to frames by time.",
)
@click.option(
    "--pose-tolerance-ms",
    type=domain_type(Annotated[float, Interval(gt=0.0, le=60_000.0)]),
    default=10.0,
    show_default=True,
    help="Largest time between a frame and the pose it is matched to (ms).",
)
@out_dir_option(required=True)
@json_option("Print report.json to stdout.")
def eval_cmd(
    input_path,
    markers_path,
    dictionary,
    marker_size_m,
    pipeline,
    config_path,
    quiet,
    camera_path,
    gt_path,
    compare,
    level_ds,
    topic,
    pose_topic,
    pose_tolerance_ms,
    out_dir,
    as_json,
) -> None:
    """Evaluate detection and DS pose on INPUT (images, a video, a ROS bag's image topic, or a
    labelled dataset folder).

    Writes report.json (rates, time, reprojection error; with ground truth: pose error
    percentiles, binned by range and viewing angle, jitter on static stretches), frames.jsonl,
    plots and a contact sheet. --compare runs several pipelines on the same frames and adds
    compare.json / compare.md.
    """
    cfg = _config(config_path, pipeline, level_ds)
    names = [p.strip() for p in (compare or "").split(",") if p.strip()]
    if compare is not None and not names:
        raise DockError("--compare needs at least one pipeline name")
    if pipeline is not None and pipeline not in names:
        names.insert(0, pipeline)
    names = names or [cfg.detector.pipeline]
    frames_path, truth, truth_source = input_path, None, None
    if is_dataset(input_path):
        # labels checked against the dataset before any work (image paths inside it and
        # regular files, poses in range): one line, nothing written
        ds = load_checked_dataset(input_path)
        frames_path = ds.images_dir
        camera_path = camera_path or ds.camera_path
        if markers_path is None and dictionary is None and marker_size_m is None:
            markers_path = ds.marker_set_path
        if gt_path is None:
            truth, truth_source = ds.frames, str(input_path)
    topic = resolve_image_topic(input_path, topic, _note)
    if pose_topic is not None and topic is None:
        raise DockError("--pose-topic is for bags; INPUT is not one")
    if pose_topic is not None and gt_path is not None:
        raise DockError("give either --ground-truth or --pose-topic, not both")
    bag_camera = _bag_camera(input_path, topic) if camera_path is None else None
    if camera_path is None and bag_camera is None:
        raise DockError("--camera is required (the camera file of INPUT's frames)")
    camera, T_body_cam = resolve_camera(camera_path)  # the mounting: reference when unstated
    if bag_camera is not None:
        camera = bag_camera
    setup = resolve_markers(markers_path, dictionary, marker_size_m)
    if gt_path is not None:
        truth, truth_source = load_ground_truth(gt_path), str(gt_path)
    if pose_topic is not None:
        truth = truth_from_bag(input_path, topic, pose_topic, pose_tolerance_ms)
        truth_source = f"{input_path}:{pose_topic}"
    report = run_eval(
        frames_path,
        out_dir,
        setup,
        camera,
        cfg,
        names,
        truth,
        truth_source,
        progress=False if (quiet or as_json) else None,
        note=_note,
        T_body_cam=T_body_cam,
        topic=topic,
    )
    if as_json:
        click.echo(json.dumps(report, indent=2))
    elif quiet:
        click.echo(str(Path(out_dir) / "report.json"))
    else:
        _print_summary(report, Path(out_dir))


@cli.command()
def pipelines() -> None:
    """List the preprocessing pipelines."""
    for name, text in list_pipelines().items():
        click.echo(f"{name:18s} {text}")


def main() -> None:
    run_group(cli)
