"""``sim``: render the docking station from given or random poses; record a docking episode.

Both commands compose higher layers on purpose (this module is a composition root, imported
only by the ``sim`` entry point): ``render`` is the ``datasets`` synth engine fed with explicit
poses, ``episode`` drives ``rl``'s env and PID baseline. The ``sim`` library modules import
neither.
"""

from __future__ import annotations

from pathlib import Path

import click

from uwdock.dockcore.cli import CONTEXT, domain_type, field_type, run_group
from uwdock.dockcore.domains import Seed
from uwdock.dockcore.errors import DockError

#: Configs whose fields the options override (imported when an option is first used).
_SYNTH = "uwdock.datasets.synth:SynthConfig"
_ENV = "uwdock.rl.config:EnvConfig"
_VIDEO = "uwdock.sim.episode:EpisodeVideoConfig"


#: ``sim episode``'s values of EnvConfig fields that neither a flag nor ``--config`` sets.
_EPISODE_DEFAULTS = {"episode_s": 30.0, "camera_width_px": 484}


@click.group(context_settings=CONTEXT)
def cli() -> None:
    """Simulation: SAPIEN AUV and docking-station physics, underwater camera rendering."""


def _water_choice(water: str | None, allow_random: bool) -> str:
    from uwdock.sim.water import PRESETS

    name = water or "none"
    known = [*PRESETS, *(["random"] if allow_random else []), "none"]
    if name not in known:
        raise DockError(f"unknown water preset {name!r}; known: {', '.join(known)}")
    return name


@cli.command(context_settings=CONTEXT)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder (images/, labels.jsonl, camera, marker set, dataset.json).",
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
    "roll_deg,pitch_deg,yaw_deg (DS origin at 0,0,4.98).",
)
@click.option("--water", help="Water preset, 'random' or 'none' [default: none].")
@click.option(
    "--width",
    "width_px",
    type=field_type(_SYNTH, "width_px"),
    default=0,
    help="Render width in px, 16-8192 [0: the camera's].",
)
@click.option("--seed", type=field_type(_SYNTH, "seed"), default=0, show_default=True)
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), help="Camera file.")
@click.option("--markers", "marker_set_path", type=click.Path(dir_okay=False), help="Marker set.")
@click.option(
    "--workers", type=domain_type("uwdock.datasets.synth:Workers"), default=1, show_default=True
)
@click.option("--quiet", is_flag=True, help="No progress bar; print only the folder.")
def render(
    out_dir, n_frames, poses_csv, water, width_px, seed, camera_file, marker_set_path, workers,
    quiet,
) -> None:  # fmt: skip
    """Render images (+ labels.jsonl in the dataset format) for given or random poses."""
    from uwdock.datasets.loaders import load_poses_csv
    from uwdock.datasets.synth import SynthConfig, generate

    if n_frames is not None and poses_csv is not None:
        raise DockError("give either --n or --poses, not both")
    poses = load_poses_csv(poses_csv) if poses_csv is not None else None
    n = len(poses) if poses is not None else (8 if n_frames is None else n_frames)
    cfg = SynthConfig(  # checked by generate() before it writes anything
        n_frames=n,
        seed=seed,
        water=_water_choice(water, allow_random=True),
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
        tool="sim render",
    )
    if quiet:
        click.echo(str(result.out_dir))
    else:
        click.echo(
            f"rendered {len(result.rendered)} of {result.frames} frames into {result.out_dir} "
            f"in {result.seconds:.1f} s"
        )


@cli.command(context_settings=CONTEXT)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder (episode.mp4, summary.json, config.toml, provenance.json).",
)
@click.option("--controller", type=click.Choice(["pid"]), default="pid", show_default=True)
@click.option(
    "--seed", type=domain_type(Seed), default=0, show_default=True, help="Env reset seed."
)
@click.option("--water", help="Water of the downward view: a preset or 'none' [coastal].")
@click.option(
    "--seconds",
    type=field_type(_ENV, "episode_s"),
    help="Episode length (s); it ends earlier on docking [default: the --config's episode_s, "
    f"else {_EPISODE_DEFAULTS['episode_s']:g}].",
)
@click.option(
    "--width",
    "width_px",
    type=field_type(_ENV, "camera_width_px"),
    help="Downward camera render width (px) [default: the --config's camera_width_px, else "
    f"{_EPISODE_DEFAULTS['camera_width_px']}].",
)
@click.option(
    "--outside-width",
    "outside_width_px",
    type=field_type(_VIDEO, "outside_width_px"),
    default=480,
    show_default=True,
    help="Outside view width (px; 4:3).",
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="TOML overriding rl.config.EnvConfig (obs_source defaults to 'proxy').",
)
@click.option("--quiet", is_flag=True, help="No progress bar; print only the video path.")
def episode(
    out_dir, controller, seed, water, seconds, width_px, outside_width_px, config_path, quiet
) -> None:
    """Run the scripted PID controller in the docking env and write a side-by-side MP4 of the
    downward camera (with water) and an outside view, plus summary.json."""
    from tqdm import tqdm

    from uwdock.dockcore.config import config_data, from_dict, merge
    from uwdock.dockcore.io import atomic_write_json
    from uwdock.dockcore.outdir import claim_output_dir
    from uwdock.dockcore.provenance import write_provenance
    from uwdock.rl.baselines import PIDController
    from uwdock.rl.config import EnvConfig
    from uwdock.rl.env import DockingEnv
    from uwdock.sim.episode import EpisodeVideoConfig, record_episode
    from uwdock.sim.water import PRESETS

    water_name = _water_choice(water or "coastal", allow_random=False)
    given = config_data(config_path, section="env") if config_path is not None else {}
    flags = {"episode_s": seconds, "camera_width_px": width_px}
    data = merge(merge(_EPISODE_DEFAULTS, given), {k: v for k, v in flags.items() if v is not None})
    env_cfg = from_dict(EnvConfig, data)  # a flag, else the file's value, else our default
    outside_height_px = max(16, round(outside_width_px * 3 / 4))
    video_cfg = from_dict(
        EpisodeVideoConfig,
        {
            "outside_width_px": outside_width_px,
            "outside_height_px": outside_height_px,
            "panel_height_px": outside_height_px,
        },
    )
    env = DockingEnv(env_cfg, render_mode="rgb_array")  # may still refuse the config
    try:
        with claim_output_dir(out_dir, "sim episode") as out:
            policy = PIDController.for_env(env_cfg)
            steps = round(env_cfg.episode_s * env_cfg.control_hz)
            disable = True if quiet else None
            with tqdm(total=steps, unit="step", desc="episode", disable=disable) as bar:
                summary = record_episode(
                    env,
                    policy,
                    out,
                    seed=seed,
                    water=None if water_name == "none" else PRESETS[water_name],
                    water_name=water_name,
                    cfg=video_cfg,
                    on_step=lambda _k: bar.update(1),
                )
            summary["controller"] = controller
            atomic_write_json(out / "summary.json", summary)
            extra = {"summary": summary}
            write_provenance(out, {"env": env_cfg, "video": video_cfg}, extra=extra)
    finally:
        env.close()
    if quiet:
        click.echo(str(out / summary["video"]))
        return
    result = "docked" if summary["success_paper"] else "not docked"
    click.echo(
        f"{summary['steps']} steps ({summary['sim_time_s']:.1f} s), {result}, final |e| "
        f"{summary['final_distance_m']:.2f} m, return {summary['return']:.0f} -> "
        f"{out / summary['video']}"
    )


def main() -> None:
    run_group(cli)


if __name__ == "__main__":  # pragma: no cover
    main()
