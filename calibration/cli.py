"""``calibration``: camera intrinsics, the camera-to-vehicle extrinsics, the reference camera,
and camera files of ROS (camera_info) and Kalibr (camchain) in and out."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import click

from uwdock.calibration.camera import MAX_CAMERA_OFFSET_M, load_camera, twin_paths
from uwdock.calibration.extrinsics import (
    T_body_cam_from_xyz_rpy,
    format_extrinsics,
    read_extrinsics,
    write_extrinsics,
    write_reference_camera,
)
from uwdock.calibration.formats import (
    IMPORT_FORMATS,
    camera_import_bytes,
)
from uwdock.calibration.formats_export import (
    EXPORT_FORMATS,
    export_camera_file,
)
from uwdock.calibration.intrinsics import IntrinsicsConfig, calibrate_intrinsics
from uwdock.calibration.intrinsics_report import output_paths as intrinsics_output_paths
from uwdock.calibration.intrinsics_report import write_outputs
from uwdock.calibration.stereo import (
    StereoConfig,
    StereoResult,
    calibrate_stereo,
    stereo_output_paths,
    write_stereo_outputs,
)
from uwdock.calibration.stereo_formats import export_stereo_file, stereo_import_bytes
from uwdock.calibration.stereo_rig import is_stereo_file
from uwdock.dockcore.bags import resolve_image_topic
from uwdock.dockcore.cli import DomainType, domain_type, field_type, run_group
from uwdock.dockcore.config import load_config
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, check_output_path
from uwdock.dockcore.media import display_name, silence_opencv_log
from uwdock.dockcore.options import (
    command_group,
    config_option,
    json_option,
    out_file_option,
    out_path_checked,
    quiet_option,
)

#: ``extrinsics set --xyz-m``: the camera's position in the body frame (m; a vehicle is a few
#: metres long): the range every reader of ``T_body_cam`` accepts (``check_T_body_cam``).
XyzM = Annotated[float, Interval(ge=-MAX_CAMERA_OFFSET_M, le=MAX_CAMERA_OFFSET_M)]
#: ``extrinsics set --rpy-deg``: roll, pitch, yaw (deg).
RpyDeg = Annotated[float, Interval(ge=-360.0, le=360.0)]
#: ``reference-camera --width/--height`` (px).
ImageSidePx = Annotated[int, Interval(ge=16, le=20000)]


def _stereo_cfg(name: str) -> DomainType:
    """The type of an option overriding ``StereoConfig.<name>``."""
    return field_type("uwdock.calibration.stereo_config:StereoConfig", name)


def _cfg(name: str) -> DomainType:
    """The type of an option overriding ``IntrinsicsConfig.<name>`` (imported when first used)."""
    return field_type("uwdock.calibration.intrinsics:IntrinsicsConfig", name)


def _target_options(fn):
    """The target's options (``--pattern`` ... ``--dictionary``), shared by ``intrinsics`` and
    ``stereo`` (``IntrinsicsConfig`` fields)."""
    options = [
        click.option("--pattern", help="Target: chessboard or charuco [chessboard]."),
        click.option(
            "--cols",
            type=_cfg("cols"),
            help="Chessboard: inner corners per row; charuco: squares [9].",
        ),
        click.option(
            "--rows",
            type=_cfg("rows"),
            help="Chessboard: inner corners per column; charuco: squares [6]",
        ),
        click.option("--square-mm", type=_cfg("square_mm"), help="Square side in mm [25]."),
        click.option(
            "--marker-mm",
            type=_cfg("marker_mm"),
            help="ChArUco marker side in mm [0.75 x square].",
        ),
        click.option("--dictionary", help="ChArUco marker dictionary [DICT_4X4_50]."),
    ]
    for option in reversed(options):
        fn = option(fn)
    return fn


def _echo_note(note: str) -> None:
    """A result's note on stderr: "note: ...", or the warning as it is ("warning: ...")."""
    note = display_name(note)  # a file name that is not UTF-8: \\xNN
    click.echo(note if note.startswith("warning: ") else f"note: {note}", err=True)


@command_group()
def cli() -> None:
    """Calibration: camera intrinsics and the camera-to-vehicle extrinsics."""
    silence_opencv_log()  # the toolkit's own lines only (library noise: dockcore.media)


@cli.command()
@click.argument("source", type=click.Path(path_type=Path))
@_target_options
@click.option(
    "--blur-threshold-px",
    type=_cfg("blur_threshold_px"),
    help="Reject views with wider edges (px) [6].",
)
@click.option(
    "--max-views", type=_cfg("max_views"), help="Most views kept, spread over poses [40]."
)
@click.option(
    "--corner-method",
    type=click.Choice(["auto", "classic", "sb"]),
    help="Chessboard corners: classic, sb (sector-based) or auto (both, compared) [auto].",
)
@click.option(
    "--cv-folds",
    type=_cfg("cv_folds"),
    help="Cross-validation folds: 0 = leave-one-view-out (10 folds above 40 views) [0].",
)
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
    corner_method,
    cv_folds,
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
    near-duplicates are rejected; the views are cross-validated (no random draw), outliers
    judged against the other views' consensus, the final fit uses every accepted view and the
    folds' spread is reported as the uncertainty. Calibrate an underwater camera in water,
    behind its own port.
    """
    check_output_path(out_path, "--out", intrinsics_output_paths(out_path))  # before any work
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
            "cv_folds": cv_folds,
            "corner_method": corner_method,
            "distortion_model": distortion_model,
        },
        section="intrinsics",
    )
    topic = resolve_image_topic(source, topic, lambda m: click.echo(f"note: {m}", err=True))
    result = calibrate_intrinsics(
        source, cfg, name=name, progress=False if quiet else None, topic=topic
    )
    for note in result.notes:
        _echo_note(note)
    paths, kept_T = write_outputs(result, out_path)
    if quiet:
        click.echo(str(paths[0]))
        return
    cam, n = result.camera, result.counts()
    rejected = ", ".join(f"{k} {v}" for k, v in n["rejected_by_reason"].items()) or "none"
    click.echo(
        f"views: {n['read'] + n['unreadable']} in, {n['pattern_found']} with the pattern, "
        f"{n['calibration']} calibration; rejected: {rejected}"
    )
    click.echo(
        f"fx {cam.fx_px:.3f} px  fy {cam.fy_px:.3f} px  cx {cam.cx_px:.3f} px  "
        f"cy {cam.cy_px:.3f} px  dist [{', '.join(f'{d:.5f}' for d in cam.dist)}]"
    )
    click.echo(
        f"rms {cam.rms_px:.4f} px (calibration views), cross-validated "
        f"{result.cv_rms_px:.4f} px ({result.cv.scheme})"
    )
    unc = result.uncertainty()
    click.echo(
        "uncertainty (fold jackknife, 1 sigma): "
        + "  ".join(f"{k[:2]} +-{v:.2f} px" for k, v in unc.items())
    )
    if kept_T:
        click.echo(f"kept T_body_cam from the existing {out_path}")
    click.echo("wrote " + ", ".join(str(p) for p in paths))


@cli.command()
@click.argument("left", type=click.Path(path_type=Path))
@click.argument("right", type=click.Path(path_type=Path), required=False)
@click.option(
    "--left-camera",
    type=click.Path(dir_okay=False, path_type=Path),
    help="The left camera's file: its intrinsics are kept fixed (give --right-camera too).",
)
@click.option(
    "--right-camera",
    type=click.Path(dir_okay=False, path_type=Path),
    help="The right camera's file. Without both, each camera's intrinsics are fitted.",
)
@click.option("--left-topic", help="Bag: the left camera's image topic.")
@click.option("--right-topic", help="Bag: the right camera's image topic.")
@_target_options
@click.option(
    "--distortion-model",
    type=click.Choice(["k1k2", "k1k2k3", "k1k2p1p2", "k1k2p1p2k3", "rational"]),
    help="Distortion terms fitted when no camera files are given [k1k2p1p2k3]; k1k2p1p2 "
    "exports to Kalibr.",
)
@click.option(
    "--pair-tolerance-ms",
    type=_stereo_cfg("pair_tolerance_ms"),
    help="Bag: most difference of the two header stamps of a pair (ms) [5].",
)
@click.option(
    "--skip-unpaired",
    is_flag=True,
    default=None,
    help="Skip images without a partner (same file stem, same frame index) instead of stopping.",
)
@click.option(
    "--rectify-alpha",
    type=_stereo_cfg("rectify_alpha"),
    help="Rectification scaling: 0 valid pixels only, 1 every source pixel [0].",
)
@click.option(
    "--maps", "write_maps", is_flag=True, help="Also write the rectification maps (.npz; large)."
)
@config_option(
    "TOML file overriding StereoConfig defaults, the target in an [intrinsics] table "
    "(flags override the file)."
)
@out_file_option(
    "Stereo file (.yaml + .json twin); camera files, a ROS camera_info pair, a Kalibr "
    "camchain, <stem>_report.json and <stem>_errors.png beside it.",
    default=Path("stereo.yaml"),
    show_default=True,
)
@quiet_option("Print only the stereo file path; no progress bar.")
def stereo(
    left,
    right,
    left_camera,
    right_camera,
    left_topic,
    right_topic,
    pattern,
    cols,
    rows,
    square_mm,
    marker_mm,
    dictionary,
    distortion_model,
    pair_tolerance_ms,
    skip_unpaired,
    rectify_alpha,
    write_maps,
    config_path,
    out_path,
    quiet,
) -> None:
    """Calibrate a stereo pair (T_right_left, rectification, epipolar error) from views of the
    target in LEFT and RIGHT, or in one ROS bag LEFT.

    LEFT and RIGHT: image folders (pairs: same file stem) or videos (pairs: same frame index);
    a bag: --left-topic and --right-topic (pairs: header stamps within --pair-tolerance-ms).
    T_right_left maps points of the left camera frame into the right one (m; cam_cv: x right,
    y down, z forward). Intrinsics come fixed from --left-camera and --right-camera, or are
    fitted (each camera alone, then jointly). A pair whose error is far above the others'
    median is rejected as an outlier.
    """
    target = {
        "pattern": pattern,
        "cols": cols,
        "rows": rows,
        "square_mm": square_mm,
        "marker_mm": marker_mm,
        "dictionary": dictionary,
        "distortion_model": distortion_model,
    }
    cfg = _stereo_config(config_path, target, pair_tolerance_ms, skip_unpaired, rectify_alpha)
    if out_path.suffix.lower() not in (".yaml", ".yml", ".json"):
        raise click.UsageError(f"--out must end in .yaml, .yml or .json: {out_path}")
    check_output_path(out_path, "--out", stereo_output_paths(out_path, write_maps))
    result = calibrate_stereo(
        left, right, cfg, left_camera, right_camera, left_topic, right_topic,
        progress=False if quiet else None,
    )  # fmt: skip
    paths, skipped = write_stereo_outputs(result, out_path, write_maps=write_maps)
    for note in result.notes + skipped:
        _echo_note(note)
    if quiet:
        click.echo(str(paths[0]))
        return
    _print_stereo(result, paths)


def _stereo_config(
    config_path: Path | None,
    target: dict[str, object],
    pair_tolerance_ms: float | None,
    skip_unpaired: bool | None,
    rectify_alpha: float | None,
) -> StereoConfig:
    """The stereo config: its defaults, the config file over them, the flags given over that
    (the target's flags, None where not given, go in its ``intrinsics`` table)."""
    target = {k: v for k, v in target.items() if v is not None}
    return load_config(
        StereoConfig,
        config_path,
        overrides={
            "intrinsics": target or None,
            "pair_tolerance_ms": pair_tolerance_ms,
            "skip_unpaired": skip_unpaired,
            "rectify_alpha": rectify_alpha,
        },
        section="stereo",
    )


def _print_stereo(result: StereoResult, paths: list[Path]) -> None:
    """The stereo calibration in words: pairs used, intrinsics, T_right_left, errors, files."""
    rig, n = result.rig, result.counts()
    rejected = ", ".join(f"{k} {v}" for k, v in n["rejected_by_reason"].items()) or "none"
    click.echo(f"pairs: {n['pairs']} read, {n['used']} used; rejected: {rejected}")
    how = "fitted" if result.intrinsics_fitted else "fixed from the camera files"
    for c in (rig.left, rig.right):
        click.echo(
            f"{c.name}: fx {c.fx_px:.3f} px  fy {c.fy_px:.3f} px  cx {c.cx_px:.3f} px  "
            f"cy {c.cy_px:.3f} px  ({how})"
        )
    T = rig.T_right_left
    click.echo("T_right_left (left camera frame in the right one, m):")
    for row in T:
        click.echo("  " + "  ".join(f"{v:+.9f}" for v in row))
    click.echo(
        f"baseline {rig.baseline_m:.5f} m, rotation {rig.rotation_deg:.3f} deg, "
        f"rms {rig.rms_px:.4f} px, epipolar {result.epipolar_rms_px:.4f} px, "
        f"rectified dy {result.rectified_dy_rms_px:.4f} px"
    )
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
    check_output_path(camera_file, "camera file", twin_paths(camera_file))
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
    check_output_path(out_path, "--out", twin_paths(out_path))
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
@click.option(
    "--right",
    type=click.Path(dir_okay=False, path_type=Path),
    help="ROS: the right camera's camera_info of a stereo pair (SOURCE is the left one).",
)
@click.option(
    "--stereo-out",
    type=click.Path(dir_okay=False, path_type=Path),
    callback=out_path_checked,
    help="Stereo file written when SOURCE holds a stereo pair (a camchain whose --cam has a "
    "T_cn_cnm1 link, or --right) [<out stem>_stereo.yaml].",
)
@click.option(
    "--no-stereo",
    is_flag=True,
    help="Import the one camera only: a camchain's T_cn_cnm1 is then not kept.",
)
def import_(source, fmt, cam_key, out_path, right, stereo_out, no_stereo) -> None:
    """Convert SOURCE, a ROS camera_info YAML or a Kalibr camchain, into a camera file.

    Intrinsics of one camera (--cam; ROS: SOURCE). Kalibr's T_cam_imu (the IMU frame in the
    camera frame) is printed, not written: T_body_cam = T_body_imu @ inv(T_cam_imu) needs where
    the IMU sits in the body frame; set it with `calibration extrinsics set`.

    Stereo: when the camchain links the camera to its neighbour by T_cn_cnm1 (cam0 -> cam1:
    left, right), or with --right for a ROS camera_info pair, the pair is also written as a
    stereo file (T_right_left = cam1's T_cn_cnm1, as read; the rectification as read from ROS,
    computed for Kalibr); a pair that cannot be represented is refused (--no-stereo imports the
    camera alone).
    """
    if no_stereo and (right is not None or stereo_out is not None):
        raise click.UsageError("--no-stereo goes with neither --right nor --stereo-out")
    stereo_path = stereo_out or out_path.with_name(f"{out_path.stem}_stereo.yaml")
    check_output_path(out_path, "--out", twin_paths(out_path))
    if right is not None and Path(right).resolve() in {p.resolve() for p in twin_paths(out_path)}:
        raise DockError(f"--out {out_path} would overwrite the file being imported, {right}")
    if stereo_out is not None:  # the default one is checked when SOURCE holds a pair
        check_output_path(stereo_out, "--stereo-out", twin_paths(stereo_out))
    found = None
    if not no_stereo:  # checked first: a pair that cannot be represented writes nothing
        found = stereo_import_bytes(source, stereo_path, fmt, cam_key, right)
        if found is None and stereo_out is not None:
            raise DockError(f"{source} holds no stereo pair for {cam_key}: --stereo-out unused")
    imported, files, kept_T = camera_import_bytes(source, out_path, fmt, cam_key)
    yaml_path, json_path = files
    if found is not None:
        overlap = {p.resolve() for p in files} & {p.resolve() for p in found[2]}
        if overlap:
            raise DockError(f"--stereo-out {stereo_path} and --out {out_path} are the same files")
        files = {**files, **found[2]}
    # the camera file and the stereo file as one unit: all new, or all as they were (a full
    # disk or an interrupt between them left a new stereo file beside the old camera file)
    atomic_write_files(files)
    for note in imported.notes:
        _echo_note(note)
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
    if found is not None:
        rig, what, stereo_files = found
        s_yaml, s_json = stereo_files
        click.echo(
            f"stereo pair {what}: baseline {rig.baseline_m:.5f} m, rotation "
            f"{rig.rotation_deg:.3f} deg; wrote {s_yaml} and {s_json}"
        )
    elif no_stereo and imported.T_cn_cnm1 is not None:
        click.echo(f"note: T_cn_cnm1 of {cam_key} not kept (--no-stereo)", err=True)


@cli.command()
@click.argument("camera_file", type=click.Path(path_type=Path))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(EXPORT_FORMATS),
    required=True,
    help="ros: camera_info YAML (plumb_bob or rational_polynomial); kalibr: a camchain "
    "(pinhole-radtan, k3 and higher must be zero).",
)
@out_file_option(
    "YAML file to write (.yaml or .yml); a stereo file's left camera for ros.", required=True
)
@click.option(
    "--right-out",
    type=click.Path(dir_okay=False, path_type=Path),
    callback=out_path_checked,
    help="ROS, a stereo file: the right camera's camera_info (required).",
)
@click.option(
    "--rostopic",
    help="Kalibr: the image topic of cam0 [the stereo file's, else /cam0/image_raw].",
)
@click.option(
    "--right-rostopic",
    help="Kalibr, a stereo file: the image topic of cam1 [the stereo file's, else "
    "/cam1/image_raw].",
)
def export(camera_file, fmt, out_path, right_out, rostopic, right_rostopic) -> None:
    """Write the intrinsics of CAMERA_FILE as ROS camera_info YAML or a Kalibr camchain.

    CAMERA_FILE may be a stereo file (`calibration stereo`, or an imported pair): it gives a
    camera_info pair (R1/P1 and R2/P2 of the rectification; the right P holds
    Tx = -fx' * baseline) or a two-camera camchain whose cam1 has T_cn_cnm1 = T_right_left.
    T_body_cam is not exported: camera_info has no extrinsics, and Kalibr's T_cam_imu is
    relative to the IMU, not the body frame.
    """
    if is_stereo_file(camera_file):
        paths, model = export_stereo_file(
            camera_file, out_path, fmt, right_out, (rostopic, right_rostopic)
        )
        label = (
            "ROS camera_info pair (left, right)"
            if fmt == "ros"
            else "Kalibr camchain (cam0 left, cam1 right with T_cn_cnm1)"
        )
        click.echo(f"wrote {' and '.join(str(p) for p in paths)}: {label}, distortion {model}")
        return
    if right_out is not None or right_rostopic is not None:
        raise click.UsageError(
            f"--right-out and --right-rostopic are for stereo files: {camera_file}"
        )
    path, model = export_camera_file(
        camera_file, out_path, fmt, rostopic=rostopic or "/cam0/image_raw"
    )
    label = "ROS camera_info" if fmt == "ros" else "Kalibr camchain (cam0, pinhole)"
    click.echo(f"wrote {path}: {label}, distortion model {model}")


def main() -> None:
    run_group(cli)
