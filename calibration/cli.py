"""``calibration``: camera intrinsics, the camera-to-vehicle extrinsics, the reference camera,
and camera files of ROS (camera_info) and Kalibr (camchain) in and out."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import click

from uwdock.calibration.camera import load_camera
from uwdock.calibration.extrinsics import (
    T_body_cam_from_xyz_rpy,
    format_extrinsics,
    read_extrinsics,
    write_extrinsics,
    write_reference_camera,
)
from uwdock.calibration.formats import (
    EXPORT_FORMATS,
    IMPORT_FORMATS,
    export_camera_file,
    import_camera_file,
)
from uwdock.calibration.intrinsics import IntrinsicsConfig, calibrate_intrinsics, write_outputs
from uwdock.dockcore.bags import resolve_image_topic
from uwdock.dockcore.cli import DomainType, domain_type, field_type, run_group
from uwdock.dockcore.config import load_config
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.options import (
    command_group,
    config_option,
    json_option,
    out_file_option,
    quiet_option,
    seed_option,
)

#: ``extrinsics set --xyz-m``: the camera's position in the body frame (m; a vehicle is a few
#: metres long).
XyzM = Annotated[float, Interval(ge=-100.0, le=100.0)]
#: ``extrinsics set --rpy-deg``: roll, pitch, yaw (deg).
RpyDeg = Annotated[float, Interval(ge=-360.0, le=360.0)]
#: ``reference-camera --width/--height`` (px).
ImageSidePx = Annotated[int, Interval(ge=16, le=20000)]


def _cfg(name: str) -> DomainType:
    """The type of an option overriding ``IntrinsicsConfig.<name>`` (imported when first used)."""
    return field_type("uwdock.calibration.intrinsics:IntrinsicsConfig", name)


@command_group()
def cli() -> None:
    """Calibration: camera intrinsics and the camera-to-vehicle extrinsics."""


@cli.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option("--pattern", help="Target: chessboard or charuco [chessboard].")
@click.option(
    "--cols", type=_cfg("cols"), help="Chessboard: inner corners per row; charuco: squares [9]."
)
@click.option(
    "--rows", type=_cfg("rows"), help="Chessboard: inner corners per column; charuco: squares [6]"
)
@click.option("--square-mm", type=_cfg("square_mm"), help="Square side in mm [25].")
@click.option(
    "--marker-mm", type=_cfg("marker_mm"), help="ChArUco marker side in mm [0.75 x square]."
)
@click.option("--dictionary", help="ChArUco marker dictionary [DICT_4X4_50].")
@click.option(
    "--blur-threshold-px",
    type=_cfg("blur_threshold_px"),
    help="Reject views with wider edges (px) [6].",
)
@click.option(
    "--max-views", type=_cfg("max_views"), help="Most views kept, spread over poses [40]."
)
@click.option(
    "--holdout-fraction", type=_cfg("holdout_fraction"), help="Fraction of views held out [0.2]."
)
@seed_option(_cfg("seed"), "Seed of the hold-out draw [0].")
@click.option(
    "--distortion-model",
    type=click.Choice(["k1k2", "k1k2k3", "k1k2p1p2", "k1k2p1p2k3", "rational"]),
    help="Distortion terms to fit [k1k2p1p2k3].",
)
@config_option("TOML file overriding IntrinsicsConfig defaults (flags override the file).")
@click.option("--name", default="camera", show_default=True, help="Camera name in the file.")
@out_file_option(
    "Camera file (.yaml + .json twin); <stem>_report.json and <stem>_errors.png beside it.",
    default=Path("camera.yaml"),
    show_default=True,
)
@quiet_option("Print only the camera file path; no progress bar.")
@click.option(
    "--topic",
    help="Image topic when SOURCE is a ROS bag (.bag, .db3, .mcap or a ROS 2 folder); "
    "without it the bag's topics are listed and its only image topic is read.",
)
def intrinsics(
    source,
    pattern,
    cols,
    rows,
    square_mm,
    marker_mm,
    dictionary,
    blur_threshold_px,
    max_views,
    holdout_fraction,
    seed,
    distortion_model,
    config_path,
    name,
    out_path,
    quiet,
    topic,
) -> None:
    """Calibrate K and distortion from SOURCE: a folder of images, a video or a ROS bag of the
    target.

    Chessboard sizes count inner corners, ChArUco sizes count squares. Blurred views and
    near-duplicates are rejected, a seeded fraction is held out and its reprojection error
    reported. Calibrate an underwater camera in water, behind its own port.
    """
    cfg = load_config(
        IntrinsicsConfig,
        config_path,
        overrides={
            "pattern": pattern,
            "cols": cols,
            "rows": rows,
            "square_mm": square_mm,
            "marker_mm": marker_mm,
            "dictionary": dictionary,
            "blur_threshold_px": blur_threshold_px,
            "max_views": max_views,
            "holdout_fraction": holdout_fraction,
            "seed": seed,
            "distortion_model": distortion_model,
        },
        section="intrinsics",
    )
    topic = resolve_image_topic(source, topic, lambda m: click.echo(f"note: {m}", err=True))
    result = calibrate_intrinsics(
        source, cfg, name=name, progress=False if quiet else None, topic=topic
    )
    for note in result.notes:
        click.echo(f"note: {note}", err=True)
    paths, kept_T = write_outputs(result, out_path)
    if quiet:
        click.echo(str(paths[0]))
        return
    cam, n = result.camera, result.counts()
    rejected = ", ".join(f"{k} {v}" for k, v in n["rejected_by_reason"].items()) or "none"
    click.echo(
        f"views: {n['read'] + n['unreadable']} in, {n['pattern_found']} with the pattern, "
        f"{n['calibration']} calibration, {n['holdout']} held out; rejected: {rejected}"
    )
    click.echo(
        f"fx {cam.fx_px:.3f} px  fy {cam.fy_px:.3f} px  cx {cam.cx_px:.3f} px  "
        f"cy {cam.cy_px:.3f} px  dist [{', '.join(f'{d:.5f}' for d in cam.dist)}]"
    )
    hold = "n/a" if result.holdout_rms_px is None else f"{result.holdout_rms_px:.4f} px"
    click.echo(f"rms {cam.rms_px:.4f} px (calibration views), hold-out {hold}")
    if kept_T:
        click.echo(f"kept T_body_cam from the existing {out_path}")
    click.echo("wrote " + ", ".join(str(p) for p in paths))


@cli.group()
def extrinsics() -> None:
    """Show or set T_body_cam (camera cv frame in body FRD) in a camera file.

    Rotation as roll, pitch, yaw in degrees, ZYX: R_body_cam = Rz(yaw) Ry(pitch) Rx(roll).
    rpy 0 0 0 looks down with the image x axis forward; the reference camera is 0 0 90.
    """


@extrinsics.command()
@click.argument("camera_file", type=click.Path(path_type=Path))
@json_option("Print JSON.")
def show(camera_file, as_json) -> None:
    """Print T_body_cam of CAMERA_FILE (the reference default when it has none)."""
    T, from_file = read_extrinsics(camera_file)
    source = f"from {camera_file}" if from_file else "reference default (none in the file)"
    click.echo(format_extrinsics(T, source, as_json=as_json))


@extrinsics.command(name="set")
@click.argument("camera_file", type=click.Path(path_type=Path))
@click.option(
    "--xyz-m",
    nargs=3,
    type=domain_type(XyzM),
    help="Camera position X Y Z in body FRD (m, each within +-100) [required].",
)
@click.option(
    "--rpy-deg",
    nargs=3,
    type=domain_type(RpyDeg),
    help="Roll pitch yaw (deg, each within +-360), ZYX [required].",
)
def set_(camera_file, xyz_m, rpy_deg) -> None:
    """Write T_body_cam into CAMERA_FILE (both twins; intrinsics unchanged)."""
    # required, checked here rather than by click so that a bad value of either option is
    # reported before a missing one (both are parsed first)
    for name, value in (("--xyz-m", xyz_m), ("--rpy-deg", rpy_deg)):
        if value is None:
            raise click.UsageError(f"Missing option '{name}'.")
    T = T_body_cam_from_xyz_rpy(xyz_m, rpy_deg)
    yaml_path, json_path = write_extrinsics(camera_file, T)
    click.echo(format_extrinsics(T, f"written to {yaml_path} and {json_path}"))


@cli.command(name="reference-camera")
@out_file_option(
    "Camera file (.yaml + .json twin).", default=Path("camera.yaml"), show_default=True
)
@click.option(
    "--width",
    type=domain_type(ImageSidePx),
    help="Image width (px) [968]; alone keeps the aspect ratio.",
)
@click.option(
    "--height",
    type=domain_type(ImageSidePx),
    help="Image height (px) [732]; alone keeps the aspect ratio.",
)
def reference_camera(out_path, width, height) -> None:
    """Write the reference Girona downward camera (968x732, 55 deg HFOV) with its T_body_cam."""
    yaml_path, json_path = write_reference_camera(out_path, width, height)
    cam, _ = load_camera(yaml_path)
    click.echo(
        f"wrote {yaml_path} and {json_path}: {cam.width_px}x{cam.height_px} px, "
        f"f {cam.fx_px:.3f} px, HFOV {cam.hfov_deg:.2f} deg"
    )


_SOURCE_LABELS = {
    "ros": "ROS camera_info",
    "camera_info": "ROS CameraInfo message",
    "kalibr": "Kalibr camchain",
}


@cli.command(name="import")
@click.argument("source", type=click.Path(path_type=Path))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(IMPORT_FORMATS),
    default="auto",
    show_default=True,
    help="SOURCE's format: ros (camera_calibration's ost.yaml, or a CameraInfo message saved "
    "by rostopic echo), kalibr (camchain), or auto: told apart by the keys.",
)
@click.option(
    "--cam",
    "cam_key",
    default="cam0",
    show_default=True,
    help="Kalibr: the camera of the camchain (cam0, cam1, ...).",
)
@out_file_option(
    "Camera file (.yaml + .json twin); an existing file's T_body_cam is kept.",
    default=Path("camera.yaml"),
    show_default=True,
)
def import_(source, fmt, cam_key, out_path) -> None:
    """Convert SOURCE, a ROS camera_info YAML or a Kalibr camchain, into a camera file.

    Intrinsics only. Kalibr's T_cam_imu (the IMU frame in the camera frame) is printed, not
    written: T_body_cam = T_body_imu @ inv(T_cam_imu) needs where the IMU sits in the body
    frame; set it with `calibration extrinsics set`.
    """
    imported, (yaml_path, json_path), kept_T = import_camera_file(source, out_path, fmt, cam_key)
    for note in imported.notes:
        click.echo(f"note: {note}", err=True)
    cam = imported.camera
    click.echo(
        f"read {source} ({_SOURCE_LABELS[imported.source_format]}): "
        f"{cam.width_px}x{cam.height_px} px  fx {cam.fx_px:.3f} px  fy {cam.fy_px:.3f} px  "
        f"cx {cam.cx_px:.3f} px  cy {cam.cy_px:.3f} px  "
        f"dist [{', '.join(f'{d:.5f}' for d in cam.dist)}]"
    )
    if imported.T_cam_imu is not None:
        click.echo("T_cam_imu (IMU frame in the camera frame, m), not written:")
        for row in imported.T_cam_imu:
            click.echo("  " + "  ".join(f"{v:+.9f}" for v in row))
    if kept_T:
        click.echo(f"kept T_body_cam from the existing {out_path}")
    click.echo(f"wrote {yaml_path} and {json_path}")


@cli.command()
@click.argument("camera_file", type=click.Path(path_type=Path))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(EXPORT_FORMATS),
    required=True,
    help="ros: camera_info YAML (plumb_bob or rational_polynomial); kalibr: a one-camera "
    "camchain (pinhole-radtan, k3 and higher must be zero).",
)
@out_file_option("YAML file to write (.yaml or .yml).", required=True)
@click.option(
    "--rostopic",
    default="/cam0/image_raw",
    show_default=True,
    help="Kalibr: the image topic written into the camchain.",
)
def export(camera_file, fmt, out_path, rostopic) -> None:
    """Write the intrinsics of CAMERA_FILE as ROS camera_info YAML or a Kalibr camchain.

    T_body_cam is not exported: camera_info has no extrinsics, and Kalibr's T_cam_imu is
    relative to the IMU, not the body frame.
    """
    path, model = export_camera_file(camera_file, out_path, fmt, rostopic=rostopic)
    label = "ROS camera_info" if fmt == "ros" else "Kalibr camchain (cam0, pinhole)"
    click.echo(f"wrote {path}: {label}, distortion model {model}")


def main() -> None:
    run_group(cli)
