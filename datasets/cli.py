"""``datasets``: labelled synthetic frames (and, through :mod:`datasets.loaders`, footage)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import click
from tqdm import tqdm

from uwdock.calibration.camera import resolve_camera
from uwdock.datasets.loaders import load_pose_track_csv
from uwdock.datasets.synth import SynthConfig, generate
from uwdock.datasets.tank_report import TankReportConfig, detection_ranges, plot_ranges
from uwdock.datasets.water_fit import fit_water, sample_frames
from uwdock.datasets.water_fit_config import FitWaterConfig
from uwdock.datasets.water_fit_report import plot_fit, write_water_file
from uwdock.dockcore.bags import resolve_image_topic
from uwdock.dockcore.cli import domain_type, field_type, run_group
from uwdock.dockcore.config import load_config
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json
from uwdock.dockcore.options import (
    backend_options,
    command_group,
    config_option,
    json_option,
    out_dir_option,
    quiet_option,
    seed_option,
    workers_option,
)
from uwdock.dockcore.outdir import claim_output_dir
from uwdock.dockcore.provenance import write_provenance
from uwdock.dockcore.supervise import clean_after_kill, supervise
from uwdock.markers.markerset import load_marker_set
from uwdock.perception.video import open_frames
from uwdock.sim.docking_station import DockingStationConfig, resolve_marker_set
from uwdock.sim.water import (
    PRESET_ORDER,
    PRESETS,
    WaterConfig,
    load_water_file,
    water_choice,
    water_file_notes,
)

#: Configs whose fields the options override (imported when an option is first used).
_SYNTH = "uwdock.datasets.synth_config:SynthConfig"
_TANK = "uwdock.datasets.tank_report:TankReportConfig"
_FIT = "uwdock.datasets.water_fit_config:FitWaterConfig"


@command_group()
def cli() -> None:
    """Datasets: labelled synthetic frames and loaders for real footage."""


def _on_nodes(ray: dict) -> str:
    """What a Ray run adds to the summary line (", on 2 Ray nodes (30 + 30 frames)"), else ""."""
    if not ray:
        return ""
    counts = sorted(ray["tasks_by_node"].values(), reverse=True)
    text = f", on {len(counts)} Ray node{'s' if len(counts) != 1 else ''} "
    text += f"({' + '.join(str(c) for c in counts)} frames)"
    if ray["workers_replaced"]:
        text += f", {ray['workers_replaced']} lost worker(s) replaced"
    return text


@cli.command()
@click.option(
    "--n",
    "n_frames",
    type=field_type(_SYNTH, "n_frames"),
    help="Number of frames [default: 100]; more than a folder holds extends it, fewer is refused.",
)
@out_dir_option(
    "Dataset folder (created; an interrupted run there is resumed; locked while it runs).",
    required=True,
)
@click.option(
    "--water",
    help="Water preset (clear_tank, coastal, turbid, very_turbid), a water file (.toml, from "
    "`sim fit-water`), 'random' (a draw per frame) or 'none' [default: random].",
)
@workers_option(
    domain_type("uwdock.datasets.synth:Workers"),
    "Worker processes or Ray actors (the output is the same for any number).",
)
@backend_options("the same bytes either way")
@seed_option(field_type(_SYNTH, "seed"), "Base seed [default: 0].")
@click.option(
    "--camera",
    "camera_file",
    type=click.Path(dir_okay=False),
    help="Camera YAML/JSON (intrinsics + T_body_cam) [default: the reference camera].",
)
@click.option(
    "--width",
    "width_px",
    type=field_type(_SYNTH, "width_px"),
    help="Render width in px, 16-8192 (intrinsics scaled; 0: the camera's).",
)
@click.option(
    "--markers",
    "marker_set_path",
    type=click.Path(dir_okay=False),
    help="Marker set file with render meshes [default: the reference DS set].",
)
@config_option("TOML overriding SynthConfig (a dataset's config.toml works; flags override it).")
@quiet_option("No progress bar; print only the folder.")
@json_option("Print a JSON summary.")
def synth(
    n_frames, out_dir, water, workers, backend, ray_address, seed, camera_file, width_px,
    marker_set_path, config_path, quiet, as_json,
) -> None:  # fmt: skip
    """Render a labelled dataset of the docking station from random AUV poses.

    Writes images/, labels.jsonl (T_cam_ds, marker corners and visibility, water per frame),
    camera.yaml/.json, markerset.toml, dataset.json, config.toml and provenance.json.
    """
    supervise(clean_after_kill(out_dir))  # frames rendered in this process stop in time too
    cfg = load_config(
        SynthConfig,
        config_path,
        overrides={
            "n_frames": n_frames,
            "water": water,
            "seed": seed,
            "camera_file": camera_file,
            "width_px": width_px,
            "marker_set_path": marker_set_path,
        },
        section="synth",
    )
    result = generate(
        out_dir,
        cfg,
        workers=workers,
        progress=False if quiet or as_json else None,
        backend=backend,
        ray_address=ray_address,
    )
    summary = {
        "out_dir": str(result.out_dir),
        "frames": result.frames,
        "rendered": len(result.rendered),
        "kept": result.frames - len(result.rendered),
        "seconds": round(result.seconds, 2),
        "frames_per_s": round(len(result.rendered) / max(result.seconds, 1e-9), 2),
    }
    if result.ray:
        summary["ray"] = result.ray
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    elif quiet:
        click.echo(str(result.out_dir))
    else:
        click.echo(
            f"wrote {result.frames} frames to {result.out_dir} (rendered {summary['rendered']}, "
            f"kept {summary['kept']}) in {result.seconds:.1f} s{_on_nodes(result.ray)}"
        )


@cli.command()
@out_dir_option(
    "Output folder (images/, labels.jsonl, camera, marker set, dataset.json).", required=True
)
@click.option(
    "--n",
    "n_frames",
    type=field_type(_SYNTH, "n_frames"),
    help="Random poses to render [default: 8].",
)
@click.option(
    "--poses",
    "poses_csv",
    type=click.Path(dir_okay=False, path_type=Path),
    help="CSV of vehicle poses in world NED: x_m,y_m,z_m + qw,qx,qy,qz or "
    "roll_deg,pitch_deg,yaw_deg (DS origin at 0,0,4.98); optional sequence,step,time_s columns "
    "(e.g. from `rl trajectories`) are recorded in dataset.json.",
)
@click.option(
    "--water", help="Water preset, a water file (.toml), 'random' or 'none' [default: none]."
)
@click.option(
    "--width",
    "width_px",
    type=field_type(_SYNTH, "width_px"),
    default=0,
    help="Render width in px, 16-8192 [0: the camera's].",
)
@seed_option(field_type(_SYNTH, "seed"), default=0, show_default=True)
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), help="Camera file.")
@click.option("--markers", "marker_set_path", type=click.Path(dir_okay=False), help="Marker set.")
@workers_option(domain_type("uwdock.datasets.synth:Workers"))
@backend_options("the same bytes either way")
@quiet_option("No progress bar; print only the folder.")
def render(
    out_dir, n_frames, poses_csv, water, width_px, seed, camera_file, marker_set_path, workers,
    backend, ray_address, quiet,
) -> None:  # fmt: skip
    """Render images (+ labels.jsonl in the dataset format) for given or random poses: the
    ``synth`` engine fed with explicit vehicle poses (``--poses``) or a few random ones."""
    if n_frames is not None and poses_csv is not None:
        raise DockError("give either --n or --poses, not both")
    poses, sequences = load_pose_track_csv(poses_csv) if poses_csv is not None else (None, None)
    n = len(poses) if poses is not None else (8 if n_frames is None else n_frames)
    cfg = SynthConfig(  # checked by generate() before it writes anything
        n_frames=n,
        seed=seed,
        water=water_choice(water, allow_random=True),
        camera_file=camera_file,
        width_px=width_px,
        marker_set_path=marker_set_path,
    )
    result = generate(
        out_dir,
        cfg,
        workers=workers,
        poses=poses,
        progress=False if quiet else None,
        tool="datasets render",
        sequences=sequences,
        backend=backend,
        ray_address=ray_address,
    )
    if quiet:
        click.echo(str(result.out_dir))
    else:
        click.echo(
            f"rendered {len(result.rendered)} of {result.frames} frames into {result.out_dir} "
            f"in {result.seconds:.1f} s{_on_nodes(result.ray)}"
        )


@cli.command(name="tank-report")
@out_dir_option("Output folder (tank_report.json, tank_report.png, provenance).", required=True)
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False),
              help="Camera file [default: the reference camera].")  # fmt: skip
@click.option(
    "--water",
    "water_names",
    help="Comma-separated water presets [default: clear_tank,coastal,turbid,very_turbid].",
)
@click.option(
    "--water-file",
    "water_files",
    multiple=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="A water file (TOML, [water] table of sim.water.WaterConfig fields); repeatable.",
)
@click.option("--markers", "marker_set_path", type=click.Path(dir_okay=False), help="Marker set.")
@click.option("--altitude-max-m", type=field_type(_TANK, "altitude_max_m"),
              help="Highest camera altitude above the DS floor [10 m].")  # fmt: skip
@click.option("--altitude-step-m", type=field_type(_TANK, "altitude_step_m"),
              help="Altitude step: the resolution of the ranges [0.5 m].")  # fmt: skip
@click.option("--draws", type=field_type(_TANK, "draws"), help="Noise draws per altitude [5].")
@seed_option(field_type(_TANK, "seed"), "Seed of the noise draws [0].")
@json_option("Print the rows as JSON.")
@quiet_option("No progress; print only the report path.")
def tank_report(
    out_dir, camera_file, water_names, water_files, marker_set_path, altitude_max_m,
    altitude_step_m, draws, seed, as_json, quiet,
) -> None:  # fmt: skip
    """Predict how far above the docking station your camera decodes 1 and 3 of its markers in
    your water: renders the DS straight below the camera at each altitude and runs the
    detector (rendered, not guessed)."""
    cfg = load_config(
        TankReportConfig,
        None,
        overrides={
            "altitude_max_m": altitude_max_m,
            "altitude_step_m": altitude_step_m,
            "draws": draws,
            "seed": seed,
        },
    )
    waters, bounds, notes = _tank_waters(water_names, water_files)
    camera, _ = resolve_camera(camera_file)
    progress = None if quiet or as_json else (
        lambda alt: click.echo(f"  rendered altitude {alt:.2f} m", err=True))  # fmt: skip
    rows = detection_ranges(camera, waters, cfg, marker_set_path, progress, bounds)
    _add_water_file_notes(rows, notes, bounds)
    with claim_output_dir(out_dir, "datasets tank-report") as out:
        path = atomic_write_json(out / "tank_report.json", {"rows": rows})
        plot_ranges(rows, out / "tank_report.png")
        write_provenance(out, {"tank_report": cfg}, {"camera": camera_file,
                         "waters": {k: str(v) for k, v in waters.items()}})  # fmt: skip
    if as_json:
        click.echo(json.dumps(rows, indent=2))
    elif quiet:
        click.echo(str(path))
    else:
        _print_tank_report(rows, path)


def _tank_waters(
    water_names: str | None, water_files: tuple[Path, ...]
) -> tuple[dict[str, WaterConfig], dict[str, tuple[WaterConfig, WaterConfig]], dict[str, dict]]:
    """The tank report's waters (presets, then files keyed by the path as given), the bounds of
    the fitted ones (beta_D at -+ its uncertainty: higher, lower) and the files' notes."""
    names = [n.strip() for n in (water_names or "").split(",") if n.strip()]
    if not names and not water_files:
        names = list(PRESET_ORDER)
    waters = {}
    for n in names:
        if n not in PRESETS:
            raise DockError(f"unknown water preset {n!r}; known: {', '.join(PRESET_ORDER)}")
        waters[n] = PRESETS[n]
    bounds, notes = {}, {}
    for f in water_files:  # keyed by the path as given: two folders' water.toml are two rows
        key = str(f)
        if key in waters:
            continue  # the same file twice
        waters[key] = load_water_file(f)
        notes[key] = water_file_notes(f)
        low, high = notes[key].get("beta_D_low_rgb"), notes[key].get("beta_D_high_rgb")
        if low is not None and high is not None:
            try:
                bounds[key] = (
                    dataclasses.replace(waters[key], beta_D_rgb=tuple(high)),
                    dataclasses.replace(waters[key], beta_D_rgb=tuple(low)),
                )
                for w in bounds[key]:
                    w.validate()
            except (TypeError, ValueError) as exc:
                raise DockError(f"{f}: [fit] beta_D_low_rgb/beta_D_high_rgb: {exc}") from None
    return waters, bounds, notes


def _add_water_file_notes(
    rows: list[dict], notes: dict[str, dict], bounds: dict[str, tuple[WaterConfig, WaterConfig]]
) -> None:
    """Add to a water file's row its file, lighting and undetermined values, and, where it has
    bounds, what its intervals come from."""
    for r in rows:
        undetermined = notes.get(r["water"], {}).get("undetermined")
        if r["water"] in notes:
            r["water_file"] = r["water"]
            r["lighting"] = notes[r["water"]].get("lighting")
            r["undetermined"] = dict(undetermined or {})
            r["beta_D_determined"] = not (undetermined or {}).get("beta_D")
        if r["water"] in bounds:
            r["interval_from"] = (
                "the water rendered at beta_D -+1 of its relative uncertainty (the larger of the "
                "fit's bootstrap over frames and Jacobian; [fit] of the water file), all "
                "channels together"
            )


def _print_tank_report(rows: list[dict], path: Path) -> None:
    """The tank report in words: per water, its ranges (and intervals), and what the footage
    left undetermined; then the files written."""
    lo_m, hi_m = float(rows[0]["altitudes_m"][0]), float(rows[0]["altitudes_m"][-1])
    for r in rows[:-1]:
        parts = []
        for n, key in ((3, "max_alt_3_markers"), (1, "max_alt_1_marker")):
            text = f"{n} marker{'s' if n > 1 else ''} {_alt(r[f'{key}_m'], lo_m, hi_m)}"
            if f"{key}_interval_m" in r:
                a, b = r[f"{key}_interval_m"]
                text += f" ({_span(a, b, lo_m, hi_m)} over beta_D -+ its uncertainty)"
            parts.append(text)
        click.echo(f"{r['water']} ({r['width']}): " + "; ".join(parts))
        und = r.get("undetermined") or {}
        if und.get("beta_D"):
            click.echo(
                f"  beta_D of {', '.join(und['beta_D'])} is NOT determined by the footage: "
                "these ranges are not a prediction"
            )
        other = {k: v for k, v in und.items() if k != "beta_D" and v}
        if other:
            click.echo(
                "  not determined by the footage (the fit's values used): "
                + "; ".join(f"{k} of {', '.join(v)}" for k, v in other.items())
            )
    click.echo(f"wrote {path} and tank_report.png")


@cli.command(name="fit-water")
@click.argument("frames", type=click.Path(path_type=Path))
@click.option(
    "--camera",
    "camera_file",
    required=True,
    type=click.Path(dir_okay=False),
    help="Camera file of the frames (calibrated in water).",
)
@click.option(
    "--target",
    type=click.Choice(["chessboard", "markers"]),
    help="What the frames show: a chessboard or the DS marker board [chessboard].",
)
@click.option("--cols", type=field_type(_FIT, "cols"), help="Chessboard inner corners per row [8].")
@click.option(
    "--rows", type=field_type(_FIT, "rows"), help="Chessboard inner corners per column [6]."
)
@click.option(
    "--square-mm", type=field_type(_FIT, "square_mm"), help="Chessboard square side [100 mm]."
)
@click.option(
    "--markers",
    "marker_set_path",
    type=click.Path(dir_okay=False),
    help="Marker set file (--target markers) [default: the reference DS set].",
)
@click.option(
    "--lighting",
    type=click.Choice(["auto", "lamp", "ambient", "both"]),
    help="What lit the target: a lamp beside the camera, ambient (tank/room) light only, both, "
    "or auto: each fitted, the one with the least error on held-out frames chosen [auto].",
)
@click.option(
    "--no-lamp",
    "no_lamp",
    is_flag=True,
    help="Same as --lighting ambient (daylight or tank lights, no lamp beside the camera).",
)
@click.option("--base", help="Preset whose blur the water file keeps [coastal].")
@click.option("--topic", help="Image topic when FRAMES is a ROS bag (listed when left out).")
@config_option("TOML overriding FitWaterConfig ([fit_water] table; flags override it).")
@out_dir_option("Output folder (water.toml, fit_water.json, fit_water.png, provenance).",
                required=True)  # fmt: skip
@json_option("Print the fit's summary as JSON.")
@quiet_option("No progress; print only the water file's path.")
def fit_water_cmd(
    frames, camera_file, target, cols, rows, square_mm, marker_set_path, lighting, no_lamp, base,
    topic, config_path, out_dir, as_json, quiet,
) -> None:  # fmt: skip
    """Fit the underwater model's attenuation, backscatter and veiling light per channel to
    frames of a known target (a chessboard or the DS marker board) seen at several ranges;
    writes a water file that every --water option takes.

    The target is posed by PnP in each frame; its black and white patches at the ranges seen
    give the direct signal and the backscatter per channel. Film it from as near as the
    target fits the image to as far as it is still found, across the whole image.

    Says what the frames cannot tell: a value is marked not determined where it sits at a
    bound, its uncertainty (the larger of a bootstrap over frames and the Jacobian) is large,
    or another lighting model that fits the held-out frames about as well gives another value;
    where that is the attenuation, no water file is written (exit 2) and what to film is said.
    """
    if no_lamp:
        if lighting not in (None, "ambient"):
            raise DockError(f"--no-lamp means --lighting ambient, not --lighting {lighting}")
        lighting = "ambient"
    cfg = load_config(
        FitWaterConfig,
        config_path,
        section="fit_water",
        overrides={
            "target": target,
            "cols": cols,
            "rows": rows,
            "square_mm": square_mm,
            "lighting": lighting,
            "base": base,
        },
    )
    camera, _ = resolve_camera(camera_file)
    ms = None
    if cfg.target == "markers":
        ms = (load_marker_set(marker_set_path) if marker_set_path
              else resolve_marker_set(DockingStationConfig(), None, None))  # fmt: skip
    topic = resolve_image_topic(frames, topic, lambda m: click.echo(f"note: {m}", err=True))
    source = open_frames(frames, topic)
    show = not (quiet or as_json)
    with tqdm(total=source.total, unit="frame", desc="fit-water", disable=not show) as bar:
        samples = sample_frames(source, camera, cfg, ms, progress=lambda _n: bar.update(1))
    for w in source.warnings:
        click.echo(f"warning: {w}", err=True)
    fit = fit_water(samples, cfg)
    summary = fit.summary()
    refused = not fit.beta_D_determined
    with claim_output_dir(out_dir, "sim fit-water") as out:
        water_path = None if refused else write_water_file(fit, out / "water.toml", str(frames))
        summary["water_file"] = None if water_path is None else str(water_path)
        atomic_write_json(out / "fit_water.json", summary)
        plot_fit(fit, out / "fit_water.png")
        write_provenance(out, {"fit_water": cfg}, {"frames": str(frames), "camera": camera_file,
                         "topic": topic, "marker_set": marker_set_path})  # fmt: skip
    if not refused:
        for w in fit.warnings:
            click.echo(f"warning: {w}", err=True)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    elif not quiet:
        _print_fit(fit, samples, out_dir)
    elif water_path is not None:
        click.echo(str(water_path))
    if refused:
        bad = [ch for ch, ok in zip("RGB", fit.determined["beta_D"], strict=True) if not ok]
        why = fit.verdict.reasons[("beta_D", bad[0])][0] if fit.verdict else ""
        raise DockError(
            f"beta_D ({', '.join(bad)}) is not determined by these frames ({why}): no water.toml "
            f"written (fit_water.json says why); to pin it down: {' | '.join(fit.to_film)}"
        )


def _print_fit(fit, samples, out_dir) -> None:
    p = fit.params
    chosen = fit.models[fit.lighting]
    click.echo(
        f"{len(samples)} patches in {samples.frames_used} of {samples.frames_read} frames, "
        f"ranges {fit.range_m[0]:.2f}-{fit.range_m[1]:.2f} m"
    )
    if len(fit.models) > 1:
        errs = ", ".join(
            f"{k} {m.heldout_rms_8bit:.2f}"
            + ("" if m.plausible else " (not a lamp model)" if m.degenerate else " (worse)")
            for k, m in fit.models.items()
        )
        click.echo(f"lighting: {fit.lighting} (held-out error in grey levels: {errs})")
    else:
        click.echo(f"lighting: {fit.lighting} (as asked)")
    click.echo(
        f"uncertainty: the larger of the Jacobian's and a bootstrap over frames "
        f"({chosen.resamples} resamples)"
    )
    for b, unit in (("beta_D", "/m"), ("beta_B", "/m"), ("B_inf", "")):
        vals = ", ".join(
            f"{v:.4g} (+-{100 * e:.0f} %{'' if ok else ', NOT DETERMINED'})"
            for v, e, ok in zip(p[b], fit.rel_std[b], fit.determined[b], strict=True)
        )
        click.echo(f"  {b:7s} R, G, B: {vals}{unit}")
    click.echo(
        f"  vignetting {fit.vignetting:.3f}; noise: {fit.water.photons_at_white:.4g} photons at "
        f"white, read {fit.water.read_noise:.4f}"
    )
    click.echo(
        f"residual {fit.residual_rms_8bit:.2f} grey levels (RMS); contrast error R/G/B "
        + " / ".join(f"{100 * e:.1f} %" for e in fit.contrast_error)
    )
    for line in fit.to_film:
        click.echo(f"to film: {line}")
    water = "water.toml, " if fit.beta_D_determined else "no water.toml (beta_D undetermined), "
    click.echo(f"wrote {water}fit_water.json, fit_water.png in {out_dir}")


def _alt(v: float | None, lo_m: float, hi_m: float) -> str:
    """Plain words for a greatest altitude (None: at no altitude rendered)."""
    if v is None:
        return f"not within {lo_m:g}-{hi_m:g} m"
    if v >= hi_m - 1e-9:
        return f"up to {v:g} m or more (the highest rendered)"
    return f"up to {v:g} m"


def _span(a: float | None, b: float | None, lo_m: float, hi_m: float) -> str:
    """Plain words for an interval of greatest altitudes."""
    if a is None and b is None:
        return f"not within {lo_m:g}-{hi_m:g} m either way"
    if a == b:
        return f"{a:g} m at either end"
    ends = ["none" if v is None else f"{v:g}" for v in (a, b)]
    more = " or more" if b is not None and b >= hi_m - 1e-9 else ""
    return f"{ends[0]}-{ends[1]} m{more}"


def main() -> None:
    run_group(cli)
