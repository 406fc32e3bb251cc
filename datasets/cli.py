"""``datasets``: labelled synthetic frames (and, through :mod:`datasets.loaders`, footage)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from uwdock.dockcore.cli import CONTEXT, domain_type, field_type, run_group

#: Configs whose fields the options override (imported when an option is first used).
_SYNTH = "uwdock.datasets.synth:SynthConfig"


@click.group(context_settings=CONTEXT)
def cli() -> None:
    """Datasets: labelled synthetic frames and loaders for real footage."""


@cli.command(context_settings=CONTEXT)
@click.option(
    "--n",
    "n_frames",
    type=field_type(_SYNTH, "n_frames"),
    help="Number of frames [default: 100]; more than a folder holds extends it, fewer is refused.",
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Dataset folder (created; an interrupted run there is resumed; locked while it runs).",
)
@click.option(
    "--water",
    help="Water preset (clear_tank, coastal, turbid, very_turbid), "
    "'random' (a draw per frame) or 'none' [default: random].",
)
@click.option(
    "--workers",
    type=domain_type("uwdock.datasets.synth:Workers"),
    default=1,
    show_default=True,
    help="Worker processes (the output is the same for any number).",
)
@click.option("--seed", type=field_type(_SYNTH, "seed"), help="Base seed [default: 0].")
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
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="TOML overriding SynthConfig (a dataset's config.toml works; flags override it).",
)
@click.option("--quiet", is_flag=True, help="No progress bar; print only the folder.")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary.")
def synth(
    n_frames, out_dir, water, workers, seed, camera_file, width_px, marker_set_path,
    config_path, quiet, as_json,
) -> None:  # fmt: skip
    """Render a labelled dataset of the docking station from random AUV poses.

    Writes images/, labels.jsonl (T_cam_ds, marker corners and visibility, water per frame),
    camera.yaml/.json, markerset.toml, dataset.json, config.toml and provenance.json.
    """
    from uwdock.datasets.synth import SynthConfig, generate
    from uwdock.dockcore.config import load_config

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
    result = generate(out_dir, cfg, workers=workers, progress=False if quiet or as_json else None)
    summary = {
        "out_dir": str(result.out_dir),
        "frames": result.frames,
        "rendered": len(result.rendered),
        "kept": result.frames - len(result.rendered),
        "seconds": round(result.seconds, 2),
        "frames_per_s": round(len(result.rendered) / max(result.seconds, 1e-9), 2),
    }
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    elif quiet:
        click.echo(str(result.out_dir))
    else:
        click.echo(
            f"wrote {result.frames} frames to {result.out_dir} (rendered {summary['rendered']}, "
            f"kept {summary['kept']}) in {result.seconds:.1f} s"
        )


def main() -> None:
    run_group(cli)
