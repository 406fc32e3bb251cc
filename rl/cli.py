"""``rl``: train, evaluate and export docking policies."""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Annotated, get_args

import click
from tqdm import tqdm

from uwdock.datasets.loaders import write_pose_track_csv
from uwdock.dockcore import numerics
from uwdock.dockcore.cli import ParsedType, PresetType, domain_type, field_type, run_group
from uwdock.dockcore.config import (
    config_data,
    from_dict,
    load_config,
    merge,
    to_dict,
)
from uwdock.dockcore.domains import Count, Interval, Seed
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, check_output_path
from uwdock.dockcore.library_notes import with_library_notes
from uwdock.dockcore.numerics import recorded_mode
from uwdock.dockcore.options import (
    backend_options,
    command_group,
    config_option,
    out_dir_option,
    out_file_option,
    quiet_option,
    seed_option,
    workers_option,
)
from uwdock.dockcore.outdir import claim_output_dir
from uwdock.dockcore.provenance import write_provenance
from uwdock.dockcore.supervise import clean_after_kill, supervise
from uwdock.rl.env.config import EnvConfig, ObsSourceName, check_env_files
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.env.error_model import ErrorModelConfig, fit_error_model, save_error_model
from uwdock.rl.evaluate.episode_video import EpisodeVideoConfig, mark_killed, record_episode
from uwdock.rl.evaluate.report import evaluate_to_folder
from uwdock.rl.evaluate.trajectories import record_pid_trajectories
from uwdock.rl.policy.baselines import PIDController
from uwdock.rl.policy.env_settings import EnvFlags, command_env, policy_training_env
from uwdock.rl.policy.export import export_onnx
from uwdock.rl.policy.policy_convert import convert_policy
from uwdock.rl.train.recipe import recipe_names, run_recipe
from uwdock.rl.train.sweep import SweepConfig, parse_grid, run_sweep
from uwdock.rl.train.training import BatchWorkerCount, TrainConfig, run_config
from uwdock.rl.train.training import train as run
from uwdock.rl.train.vec_envs import EnvsPerWorker
from uwdock.sim.navigation import NAV_PRESETS, NavConfig
from uwdock.sim.usbl import USBL_PRESETS, UsblConfig
from uwdock.sim.water import Water
from uwdock.sim.world_config import WorldConfig

#: The config whose fields the options override (imported when an option is first used).
_TRAIN = "uwdock.rl.train.training:TrainConfig"
_ENV = "uwdock.rl.env.config:EnvConfig"
_WORLD = "uwdock.sim.world_config:WorldConfig"
_VIDEO = "uwdock.rl.evaluate.episode_video:EpisodeVideoConfig"

#: ``rl episode``'s values of EnvConfig fields that neither a flag nor ``--config`` sets (the
#: camera's render width is the env's own, ``WorldConfig.camera_width_px``).
_EPISODE_DEFAULTS = {"episode_s": 30.0, "world": {"water_preset": "coastal"}}
#: a previous episode's files that an interrupted one removes with its video
_EPISODE_OLD = ("provenance.json", "config.toml")
#: ``rl eval``'s values of EnvConfig fields that neither a flag, ``--config`` nor the policy's
#: training env sets: the camera in the loop, both success rates on the same episodes.
_EVAL_DEFAULTS = {"terminate_on": "strict", "obs_source": "camera"}
OBS_CHOICES = click.Choice(list(get_args(ObsSourceName)))
#: ``--usbl NAME``: the preset as a config object (``EnvConfig.usbl``).
USBL_TYPE = PresetType(USBL_PRESETS, lambda name: UsblConfig(preset=name))
#: ``--nav NAME``: the preset as a config object (``EnvConfig.nav``).
NAV_TYPE = PresetType(NAV_PRESETS, lambda name: NavConfig(preset=name))
#: ``--water SPEC``: a :class:`Water` (a water file read and checked as the line is parsed).
WATER_TYPE = ParsedType("water", Water.named)
#: ``--water``: the water of the camera sources (``EnvConfig.world.water_preset``).
WATER_OPTION = click.option(
    "--water",
    "water",
    type=WATER_TYPE,
    help="Water of the downward camera (obs camera / error-model): a preset or a water file "
    "(.toml, `sim fit-water`) [the config's, clear_tank].",
)
#: ``--usbl``: the acoustic positioning model (``EnvConfig.usbl.preset``).
USBL_OPTION = click.option(
    "--usbl",
    "usbl",
    type=USBL_TYPE,
    help="Acoustic (USBL) positioning model, a preset of uwdock.sim.usbl; fields of the "
    "--config's [usbl] table still override it [ideal].",
)

#: ``--nav``: the vehicle's navigation model (``EnvConfig.nav.preset``).
NAV_OPTION = click.option(
    "--nav",
    "nav",
    type=NAV_TYPE,
    help="The vehicle's navigation, a preset of uwdock.sim.navigation ('ideal': its true pose; "
    "'mems-ahrs-dvl': dead reckoning that drifts); fields of the --config's [env.nav] table "
    "still override it [ideal].",
)


#: ``--env-from``: another policy's training env (e.g. the PID under a policy's settings).
ENV_FROM_OPTION = click.option(
    "--env-from",
    "env_from",
    type=click.Path(path_type=Path, exists=True),
    help="Take the env settings from this policy folder (policy.zip / run folder / .onnx) "
    "instead of --policy's, e.g. `--policy pid --env-from rl/policies/P` [--policy's].",
)


def _note(message: str) -> None:
    click.echo(message, err=True)


def pin_numerics(requested: str | None, out_dir: Path, may_resume: bool) -> None:
    """Run this command with the numerics ``requested``, else those the run (or recipe) in
    ``out_dir`` was trained with, else pinned (:mod:`dockcore.numerics`): this process starts
    again with them when its variables differ, before any work."""
    mode = requested
    if mode is None and may_resume:
        recorded = _recorded_numerics(Path(out_dir))
        mode = recorded_mode(recorded) if recorded is not None else None
    numerics.ensure(mode or "pinned")


def _recorded_numerics(out: Path) -> dict | None:
    """``machine.numerics`` of the run in ``out`` (or of a recipe's first run), or None
    without a readable record."""
    for prov in (out / "provenance.json", *sorted(out.glob("runs/*/provenance.json"))[:1]):
        try:
            data = json.loads(prov.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        found = data.get("machine", {}).get("numerics") if isinstance(data, dict) else None
        return found if isinstance(found, dict) else {}
    return None


@command_group()
def cli() -> None:
    """Reinforcement learning: docking env, PPO training, evaluation, export."""


@cli.command()
@config_option("TOML overriding TrainConfig (env, ppo, sac tables).")
@click.option("--obs", type=OBS_CHOICES, help="Observation source [proxy].")
@click.option(
    "--error-model",
    "error_model",
    type=click.Path(path_type=Path),
    help="Fitted error model file (for --obs error-model).",
)
@USBL_OPTION
@NAV_OPTION
@WATER_OPTION
@click.option("--algo", type=click.Choice(["ppo", "sac"]), help="Algorithm [ppo].")
@click.option("--steps", type=field_type(_TRAIN, "total_steps"), help="Total env steps.")
@click.option("--envs", type=field_type(_TRAIN, "n_envs"), help="Parallel environments.")
@click.option(
    "--simulator",
    type=click.Choice(["per-env", "batched"]),
    help="per-env: one env per worker process [default]; batched: all --envs stepped as "
    "arrays in this process (many times faster; not --obs camera).",
)
@seed_option(field_type(_TRAIN, "seed"), "Base seed.")
@click.option(
    "--init-policy", type=click.Path(path_type=Path), help="Start from this policy (fine-tuning)."
)
@click.option(
    "--resume",
    is_flag=True,
    help="Continue the run in --out from its newest complete checkpoint, with its config.toml.",
)
@click.option(
    "--allow-config-change",
    is_flag=True,
    help="With --resume: accept --config/flags that change the run's config (recorded).",
)
@backend_options("the same rollouts; a run may be resumed on either")
@click.option(
    "--envs-per-worker",
    "envs_per_worker",
    type=domain_type(EnvsPerWorker),
    default=1,
    show_default=True,
    help="Envs each worker process (or Ray actor) holds, sharing its renderer, torch and "
    "memory; with Ray, one round trip per worker and step (the same rollouts).",
)
@click.option(
    "--batch-workers",
    "batch_workers",
    type=domain_type(BatchWorkerCount),
    default=1,
    show_default=True,
    help="With --simulator batched: processes the batch is split over, to use more cores "
    "(the same rollouts).",
)
@click.option(
    "--trust-pickle",
    is_flag=True,
    help="With --resume: read checkpoints of an older version (SB3's zip and pickles, which "
    "run any code they hold); only for a run folder that is your own.",
)
@click.option(
    "--recipe",
    type=click.Choice(recipe_names()),
    help="Train a shipped recipe, every stage from scratch, into --out (with --seed; a rerun "
    "resumes it); the result is a policy folder `rl eval --policy OUT` takes.",
)
@click.option(
    "--numerics",
    type=click.Choice(["pinned", "native"]),
    help="pinned: NumPy, MKL, ATen and numba held to kernels every x86-64 CPU runs alike, so "
    "a seed gives the same weights on any CPU; native: this CPU's fastest [pinned for a new "
    "run; a resumed run keeps its own].",
)
@out_dir_option("Run folder (with --recipe, the recipe's folder).", required=True)
def train(
    config_path, obs, error_model, usbl, nav, water, algo, steps, envs, simulator, seed,
    init_policy, resume, allow_config_change, backend, ray_address, envs_per_worker,
    batch_workers, trust_pickle, recipe, numerics, out_dir,
) -> None:  # fmt: skip
    """Train a docking policy (PPO with the paper's hyperparameters by default), or a whole
    recipe of stages (`--recipe shipped --seed N`).

    Killed at any moment, `--resume` goes on from the newest complete checkpoint and gives the
    same checkpoints, evaluation history and best/ as a run never stopped.
    """
    if recipe is not None:
        given = {"--config": config_path, "--obs": obs, "--error-model": error_model,
                 "--usbl": usbl, "--nav": nav, "--water": water, "--algo": algo,
                 "--steps": steps, "--envs": envs, "--simulator": simulator,
                 "--init-policy": init_policy, "--allow-config-change": allow_config_change,
                 "--trust-pickle": trust_pickle,
                 "--envs-per-worker": envs_per_worker > 1}  # fmt: skip
        clash = [k for k, v in given.items() if v]
        if clash:
            raise DockError(f"--recipe sets the configs of its stages: not with {', '.join(clash)}")
    pin_numerics(numerics, out_dir, resume or recipe is not None)
    supervise(clean_after_kill(out_dir))  # an env rendering in this process stops in time too
    if recipe is not None:
        run_recipe(recipe, 0 if seed is None else seed, out_dir, note=_note,
                   batch_workers=batch_workers if batch_workers != 1 else None,
                   backend=backend, ray_address=ray_address)  # fmt: skip
        click.echo(f"policy: {out_dir}")
        return
    flags = EnvFlags(obs_source=obs, error_model_path=error_model, usbl=usbl, nav=nav,
                     water=water)  # fmt: skip
    overrides = {
        "algo": algo,
        "total_steps": steps,
        "n_envs": envs,
        "simulator": simulator,
        "seed": seed,
        "env": flags.layer(),
    }
    if allow_config_change and not resume:
        raise DockError("--allow-config-change goes with --resume")
    if resume:
        base = to_dict(run_config(out_dir))
        extra = config_data(config_path, section="train", cls=TrainConfig) if config_path else {}
        overrides = {k: v for k, v in overrides.items() if v is not None and v != {}}
        cfg = from_dict(TrainConfig, merge(merge(base, extra), overrides))
    else:
        cfg = load_config(TrainConfig, config_path, section="train", overrides=overrides)
    final = run(
        cfg,
        out_dir,
        resume=resume,
        init_policy=str(init_policy) if init_policy else None,
        allow_config_change=allow_config_change,
        backend=backend,
        ray_address=ray_address,
        envs_per_worker=envs_per_worker,
        batch_workers=batch_workers,
        trust_pickle=trust_pickle,
    )
    click.echo(f"policy: {final}")


@cli.command()
@config_option("TOML of the base TrainConfig ([train] table, as for rl train).")
@click.option(
    "--seeds", default="0,1,2", show_default=True, help="Training seeds, comma-separated."
)
@click.option(
    "--set",
    "grid",
    multiple=True,
    help="A TrainConfig field and its values, FIELD=V1,V2 (e.g. ppo.learning_rate=1e-4,3e-4); "
    "repeatable: the sweep is every seed times every combination.",
)
@click.option(
    "--concurrent",
    type=domain_type(Annotated[int, Interval(ge=0, le=10_000)]),
    default=0,
    show_default=True,
    help="Trials at once (0: as many as the CPUs allow).",
)
@click.option(
    "--cpus-per-trial",
    type=domain_type(Annotated[int, Interval(ge=0, le=1024)]),
    default=0,
    show_default=True,
    help="CPUs each trial reserves (0: per-env, 1 learner + 1 per env; batched, 1). Per-env "
    "envs share N-1 actors, a batched trial splits its batch over N processes.",
)
@click.option(
    "--gpus-per-trial",
    type=domain_type(Annotated[float, Interval(ge=0.0, le=64.0)]),
    default=0.0,
    show_default=True,
    help="GPUs each trial's learner reserves (water_device = 'cuda', a CUDA learner).",
)
@click.option(
    "--ray-address",
    "ray_address",
    help="A running Ray cluster ('auto': the one this machine belongs to) [default: a local Ray "
    "instance].",
)
@out_dir_option("Sweep folder: one run folder per trial, sweep.json, sweep_summary.json.",
                required=True)  # fmt: skip
def sweep(
    config_path, seeds, grid, concurrent, cpus_per_trial, gpus_per_trial, ray_address, out_dir
) -> None:
    """Sweep whole training runs over seeds and config values with Ray Tune, each trial a run
    folder that resumes from its own checkpoints.

    Run again with the same arguments after an interruption, the sweep goes on where it
    stopped: finished trials are kept, the others resume. The trials' input files are copied
    into the sweep folder (OUT/inputs), which every Ray node must mount.
    """
    pin_numerics(None, out_dir, may_resume=False)  # trials train pinned, as rl train does
    try:
        seed_list = tuple(int(s, 10) for s in seeds.split(",") if s.strip())
    except ValueError:
        raise DockError(f"--seeds must be comma-separated integers, got '{seeds}'") from None
    base = load_config(TrainConfig, config_path, section="train")
    cfg = SweepConfig(
        seeds=seed_list,
        max_concurrent_trials=concurrent,
        cpus_per_trial=cpus_per_trial,
        gpus_per_trial=gpus_per_trial,
    )
    try:
        cfg.validate()
    except ValueError as exc:
        raise DockError(str(exc)) from None
    summary = run_sweep(
        base, cfg, parse_grid(grid), out_dir, ray_address,
        note=lambda m: click.echo(f"note: {m}", err=True),
    )  # fmt: skip
    for name, s in summary.items():
        best = s.get("best_eval") or {}
        strict = best.get("success_rate_strict")
        shown = (
            "no evaluation" if strict is None else f"best strict {strict:.0%} at {best['step']:,}"
        )
        click.echo(f"{name}: {'done' if s['done'] else 'not done'}, {shown}")
    click.echo(f"wrote {Path(out_dir) / 'sweep_summary.json'}")


@cli.command("eval")
@click.option(
    "--policy",
    required=True,
    type=click.Path(path_type=Path),
    help="Policy folder (model.json + weights.npz) / .onnx, or 'pid' for the classical baseline.",
)
@click.option("--episodes", type=domain_type(Count), default=100, show_default=True)
@click.option("--obs", type=OBS_CHOICES, help="Observation source [camera].")
@click.option(
    "--error-model",
    "error_model",
    type=click.Path(path_type=Path),
    help="Fitted error model file (for --obs error-model) [the one the policy trained on].",
)
@click.option(
    "--usbl",
    "usbl",
    type=USBL_TYPE,
    help="Acoustic (USBL) positioning model, a preset of uwdock.sim.usbl [the policy's "
    "training preset; ideal without one].",
)
@click.option(
    "--nav",
    "nav",
    type=NAV_TYPE,
    help="The vehicle's navigation, a preset of uwdock.sim.navigation [the policy's training "
    "preset; ideal without one].",
)
@click.option(
    "--water",
    "water",
    type=WATER_TYPE,
    help="Water of the downward camera: a preset or a water file (.toml, `sim fit-water`) "
    "[the policy's training water; clear_tank without one].",
)
@click.option(
    "--camera-width-px",
    "--width",
    "camera_width_px",
    type=field_type(_WORLD, "camera_width_px"),
    help="Downward camera render width (px) [the policy's training width; "
    f"{WorldConfig.camera_width_px} without one].",
)
@ENV_FROM_OPTION
@config_option("TOML overriding EnvConfig (over the policy's training env, under the flags).")
@seed_option(domain_type(Seed), default=1000, show_default=True)
@click.option(
    "--videos",
    default="0",
    show_default=True,
    help="Comma-separated episode indices to film ('' for none).",
)
@click.option(
    "--terminate-on",
    type=click.Choice(["strict", "paper"]),
    help="What ends an episode early: 'strict' runs on past the paper's condition, so both "
    "success rates are measured on the same episodes [the policy's training setting; strict "
    "without one].",
)
@click.option("--stress", is_flag=True, help="Also run the graded stress tables.")
@click.option("--stress-episodes", type=domain_type(Count), default=20, show_default=True)
@workers_option(
    domain_type(Annotated[int, Interval(ge=1, le=256)]),
    "Evaluation processes or Ray actors (episodes are handed out one at a time; results do "
    "not depend on it).",
)
@backend_options("the same rows and summary either way")
@out_dir_option(None, required=True)
def eval_cmd(
    policy,
    episodes,
    obs,
    error_model,
    usbl,
    nav,
    water,
    camera_width_px,
    env_from,
    config_path,
    seed,
    videos,
    terminate_on,
    stress,
    stress_episodes,
    workers,
    backend,
    ray_address,
    out_dir,
) -> None:
    """Evaluate a policy (or the PID baseline) over seeded episodes.

    The env is the policy's training env (USBL, water, camera width, termination, spawn,
    vehicle, ...; `--env-from` another policy's, e.g. for the PID), then the --config file, then
    the flags; one line names the settings used and where each came from.
    """
    supervise(clean_after_kill(out_dir))  # an env rendering in this process stops in time too
    flags = EnvFlags(
        obs_source=obs,
        error_model_path=error_model,
        terminate_on=terminate_on,
        usbl=usbl,
        nav=nav,
        water=water,
        camera_width_px=camera_width_px,
    )
    resolved = command_env(str(policy), env_from, config_path, flags, _EVAL_DEFAULTS)
    env_cfg = resolved.cfg
    click.echo(resolved.line("rl eval"))
    try:
        vids = tuple(int(v, 10) for v in videos.split(",") if v.strip())
    except ValueError:
        raise DockError(
            f"--videos must be comma-separated episode numbers, got '{videos}'"
        ) from None
    bad = [v for v in vids if not 0 <= v < episodes]
    if bad:
        raise DockError(f"--videos: episode {bad[0]} is not among the {episodes} episodes")
    summary = evaluate_to_folder(
        str(policy),
        env_cfg,
        episodes,
        seed,
        out_dir,
        vids,
        stress=stress,
        stress_episodes=stress_episodes,
        workers=workers,
        backend=backend,
        ray_address=ray_address,
        env_settings=resolved.settings(),
    )
    click.echo(
        f"success {summary['success_rate']:.1%} (strict "
        f"{summary['success_rate_strict']:.1%}) over {summary['episodes']} episodes; "
        f"report in {out_dir}"
    )


@cli.command()
@click.option("--policy", required=True, type=click.Path(path_type=Path))
@out_file_option("ONNX file to write.", required=True)
def export(policy, out_path) -> None:
    """Export a policy to ONNX (observation normalisation included); the .json beside it
    carries the env the policy was trained in (one line names its settings), which `rl eval`
    and the deployment runner take by default."""
    # the .onnx and its .json, checked before the policy is loaded
    if out_path.suffix.lower() == ".json":  # the ONNX and its sidecar would be one file
        raise DockError(f"--out must not end in .json (its .json is written beside it): {out_path}")
    check_output_path(out_path, "--out", [out_path.with_suffix(".json")])
    written = export_onnx(policy, out_path)
    trained = policy_training_env(str(policy))
    if trained is None:
        click.echo(f"rl export env: no run config beside {policy}: only its interface is known")
    else:
        click.echo(trained.line("rl export"))
    click.echo(f"wrote {written}")


@cli.command("convert-policy")
@click.argument("source", type=click.Path(path_type=Path))
@click.option(
    "--trust-pickle",
    is_flag=True,
    help="Read SOURCE's pickles (policy.zip, vecnormalize.pkl): they can run code, so only for "
    "a folder whose origin you trust.",
)
@out_dir_option("Folder to write (model.json, weights.npz and the run's records).", required=True)
def convert_policy_cmd(source, trust_pickle, out_dir) -> None:
    """Convert a policy folder of the pickled format (SB3's policy.zip, vecnormalize.pkl) into
    the data format every command loads (model.json + weights.npz; nothing in it can run code).
    The same actions, bit for bit."""
    if trust_pickle:
        click.echo(
            f"warning: --trust-pickle: reading the pickles of {source}, which run any code "
            "they hold",
            err=True,
        )
    written = convert_policy(source, out_dir, trust_pickle)
    click.echo(f"wrote {written}")


@cli.command("fit-error-model")
@click.argument("dataset", type=click.Path(path_type=Path))
@out_file_option("Error model file (JSON) to write.", required=True)
@click.option(
    "--range-bin-m",
    type=field_type("uwdock.rl.env.error_model:ErrorModelConfig", "range_bin_m"),
    help="Range bin width [0.5].",
)
def fit_error_model_cmd(dataset, out_path, range_bin_m) -> None:
    """Fit the image-derived error model from a labelled dataset (`datasets synth`).

    A dataset whose frames form time sequences (`rl trajectories`, then `datasets render
    --poses`) also gives the model's memory: the AR(1) correlation of consecutive errors.
    """
    cfg = load_config(ErrorModelConfig, overrides={"range_bin_m": range_bin_m})
    model = fit_error_model(dataset, cfg)
    save_error_model(model, out_path)
    t = model["tables"]["all"]
    n = sum(sum(row) for row in t["frames"])
    click.echo(f"fitted on {int(n)} frames ({model['dataset']['sha256'][:12]}): {out_path}")
    for water, table in model["tables"].items() if model["sequences"] else ():
        ar1 = table["ar1"]
        rho = "memoryless (too few pairs)" if ar1["rho"] is None else _fmt_rho(ar1["rho"])
        pairs = ar1["pairs"]
        click.echo(f"  {water}: AR(1) rho (standardised dt xyz, drot xyz) {rho}, {pairs} pairs")


def _fmt_rho(rho: list[float]) -> str:
    return "[" + " ".join(f"{r:+.2f}" for r in rho) + "]"


@cli.command()
@out_dir_option(
    "Output folder (episode.mp4, summary.json, config.toml, provenance.json).", required=True
)
@click.option("--controller", type=click.Choice(["pid"]), default="pid", show_default=True)
@seed_option(domain_type(Seed), "Env reset seed.", default=0, show_default=True)
@click.option(
    "--water",
    type=WATER_TYPE,
    help="Water of the downward view: a preset, a water file (.toml, `sim fit-water`) or 'none' "
    "[the --config's, else the --env-from policy's training water, else coastal].",
)
@click.option(
    "--seconds",
    type=field_type(_ENV, "episode_s"),
    help="Episode length (s); it ends earlier on docking [default: the --config's episode_s, "
    f"else {_EPISODE_DEFAULTS['episode_s']:g}].",
)
@click.option(
    "--camera-width-px",
    "--width",
    "camera_width_px",
    type=field_type(_WORLD, "camera_width_px"),
    help="Downward camera render width (px) [default: the --config's world.camera_width_px, "
    f"else the --env-from policy's, else the env's, {WorldConfig.camera_width_px}].",
)
@ENV_FROM_OPTION
@click.option(
    "--outside-width",
    "outside_width_px",
    type=field_type(_VIDEO, "outside_width_px"),
    default=480,
    show_default=True,
    help="Outside view width (px; 4:3).",
)
@config_option("TOML overriding rl.env.config.EnvConfig (obs_source defaults to 'proxy').")
@quiet_option("No progress bar; print only the video path.")
def episode(
    out_dir, controller, seed, water, seconds, camera_width_px, env_from, outside_width_px,
    config_path,
    quiet,
) -> None:  # fmt: skip
    """Run the scripted PID controller in the docking env and write a side-by-side MP4 of the
    downward camera (with water) and an outside view, plus summary.json.

    `--env-from POLICY` runs it under a policy's training env (USBL, water, camera width,
    termination, ...); the --config file and the flags override it. One line names the settings
    used and where each came from.
    """
    # the first frame's shaders compile for seconds inside SAPIEN, deaf to signals: run in a
    # child this process can stop in time, and mark the folder as the child would
    supervise(functools.partial(mark_killed, out_dir, outputs=("episode.mp4", *_EPISODE_OLD)))
    flags = EnvFlags(
        episode_s=seconds,
        camera_width_px=camera_width_px,
        water=water if water is not None and water.config is not None else None,
    )  # "none" films without water and leaves the env's (a world always has one)
    resolved = command_env("pid", env_from, config_path, flags, _EPISODE_DEFAULTS)
    env_cfg = resolved.cfg  # a flag, else the file's value, else the policy's, else our default
    film = water if water is not None else env_cfg.world.water
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
        with claim_output_dir(out_dir, "rl episode") as out:
            click.echo(resolved.line("rl episode"), err=quiet)  # --quiet: stdout is the video
            policy = PIDController.for_env(env_cfg)
            steps = round(env_cfg.episode_s * env_cfg.control_hz)
            disable = True if quiet else None
            with tqdm(total=steps, unit="step", desc="episode", disable=disable) as bar:
                summary = record_episode(
                    env,
                    policy,
                    out,
                    seed=seed,
                    water=film.config,
                    water_name=film.spec,
                    cfg=video_cfg,
                    on_step=lambda _k: bar.update(1),
                    # an interrupt writes it as {"complete": false, "interrupted": ...}
                    # and removes a previous run's video and provenance
                    summary_name="summary.json",
                    previous_outputs=_EPISODE_OLD,
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


@cli.command()
@out_dir_option(
    "Output folder (poses.csv, episodes.json, config.toml, provenance.json).", required=True
)
@click.option("--episodes", type=domain_type(Count), default=30, show_default=True)
@seed_option(domain_type(Seed), "Reset seed of episode 0 (episode k: seed + k).", default=0)
@click.option("--obs", type=OBS_CHOICES, default="error-model", show_default=True)
@click.option(
    "--error-model",
    "error_model",
    type=click.Path(path_type=Path),
    help="Fitted error model file (for --obs error-model), e.g. "
    "rl/models/error_model_clear_tank_480.json.",
)
@config_option("TOML overriding rl.env.config.EnvConfig (terminate_on defaults to 'strict').")
@quiet_option("No progress bar; print only the CSV path.")
def trajectories(out_dir, episodes, seed, obs, error_model, config_path, quiet) -> None:
    """Record the PID baseline's docking trajectories as a pose CSV with sequence, step and
    time columns (`datasets render --poses` renders them): frames consecutive in time, for
    fitting the error model's memory.

    Each pose is moved with its episode's DS into the render world (DS at the tank centre);
    poses whose camera then falls outside the tank are left out (a gap in the steps).
    """
    em = str(error_model) if error_model else None
    given = config_data(config_path, section="env", cls=EnvConfig) if config_path else {}
    base = merge({"terminate_on": "strict"}, given)
    env_cfg = from_dict(
        EnvConfig,
        merge(base, {k: v for k, v in {"obs_source": obs, "error_model_path": em}.items() if v}),
    )
    check_env_files(env_cfg)
    disable = True if quiet else None  # None: a bar on a terminal only
    with claim_output_dir(out_dir, "rl trajectories") as out:
        with tqdm(total=episodes, unit="episode", desc="trajectories", disable=disable) as bar:
            result = record_pid_trajectories(
                env_cfg, episodes, seed, on_episode=lambda _row: bar.update(1)
            )
        csv_path = write_pose_track_csv(out / "poses.csv", result.poses, result.sequences)
        summary = {
            "episodes": episodes,
            "seed": seed,
            "poses": len(result.poses),
            "left_out": sum(r["left_out"] for r in result.episodes),
            "success_strict": sum(r["success_strict"] for r in result.episodes) / episodes,
            "step_s": result.sequences.step_s(),
            "rows": result.episodes,
        }
        atomic_write_json(out / "episodes.json", summary)
        extra = {k: v for k, v in summary.items() if k != "rows"}
        write_provenance(out, {"env": env_cfg}, extra={"trajectories": extra})
    if quiet:
        click.echo(str(csv_path))
        return
    click.echo(
        f"{summary['poses']} poses of {episodes} episodes ({summary['left_out']} left out, "
        f"{summary['success_strict']:.0%} docked strictly) -> {csv_path}; render them with "
        f"`datasets render --poses {csv_path} --width {env_cfg.world.camera_width_px} --water ...`"
    )


# SB3's, gymnasium's and torch's warnings as one `note:` line each (dockcore.library_notes)
with_library_notes(cli)


def main() -> None:
    run_group(cli)
