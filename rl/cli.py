"""``rl``: train, evaluate and export docking policies."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import click

from uwdock.dockcore.cli import CONTEXT, domain_type, field_type, run_group
from uwdock.dockcore.config import config_data, from_dict, load_config, merge, replace, to_dict
from uwdock.dockcore.domains import Count, Interval, Seed
from uwdock.dockcore.errors import DockError

#: The config whose fields the options override (imported when an option is first used).
_TRAIN = "uwdock.rl.train:TrainConfig"
OBS_CHOICES = click.Choice(["proxy", "error-model", "camera"])


@click.group(context_settings=CONTEXT)
def cli() -> None:
    """Reinforcement learning: docking env, PPO training, evaluation, export."""


@cli.command(context_settings=CONTEXT)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="TOML overriding TrainConfig (env, ppo, sac tables).",
)
@click.option("--obs", type=OBS_CHOICES, help="Observation source [proxy].")
@click.option(
    "--error-model",
    "error_model",
    type=click.Path(path_type=Path),
    help="Fitted error model file (for --obs error-model).",
)
@click.option("--algo", type=click.Choice(["ppo", "sac"]), help="Algorithm [ppo].")
@click.option("--steps", type=field_type(_TRAIN, "total_steps"), help="Total env steps.")
@click.option("--envs", type=field_type(_TRAIN, "n_envs"), help="Parallel environments.")
@click.option("--seed", type=field_type(_TRAIN, "seed"), help="Base seed.")
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
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Run folder.",
)
def train(
    config_path, obs, error_model, algo, steps, envs, seed, init_policy, resume,
    allow_config_change, out_dir,
) -> None:  # fmt: skip
    """Train a docking policy (PPO with the paper's hyperparameters by default).

    Killed at any moment, `--resume` goes on from the newest complete checkpoint and gives the
    same checkpoints, evaluation history and best/ as a run never stopped.
    """
    from uwdock.rl.train import TrainConfig, run_config
    from uwdock.rl.train import train as run

    env_over = {"obs_source": obs, "error_model_path": str(error_model) if error_model else None}
    overrides = {
        "algo": algo,
        "total_steps": steps,
        "n_envs": envs,
        "seed": seed,
        "env": {k: v for k, v in env_over.items() if v is not None},
    }
    if allow_config_change and not resume:
        raise DockError("--allow-config-change goes with --resume")
    if resume:
        base = to_dict(run_config(out_dir))
        extra = config_data(config_path, section="train") if config_path else {}
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
    )
    click.echo(f"policy: {final}")


@cli.command("eval", context_settings=CONTEXT)
@click.option(
    "--policy",
    required=True,
    type=click.Path(path_type=Path),
    help="policy.zip / run folder / .onnx, or 'pid' for the classical baseline.",
)
@click.option("--episodes", type=domain_type(Count), default=100, show_default=True)
@click.option("--obs", type=OBS_CHOICES, default="camera", show_default=True)
@click.option("--error-model", "error_model", type=click.Path(path_type=Path))
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="TOML overriding EnvConfig.",
)
@click.option("--seed", type=domain_type(Seed), default=1000, show_default=True)
@click.option(
    "--videos",
    default="0",
    show_default=True,
    help="Comma-separated episode indices to film ('' for none).",
)
@click.option(
    "--terminate-on",
    type=click.Choice(["strict", "paper"]),
    default="strict",
    show_default=True,
    help="What ends an episode early: 'strict' runs on past the paper's condition, so both "
    "success rates are measured on the same episodes.",
)
@click.option("--stress", is_flag=True, help="Also run the graded stress tables.")
@click.option("--stress-episodes", type=domain_type(Count), default=20, show_default=True)
@click.option(
    "--workers",
    type=domain_type(Annotated[int, Interval(ge=1, le=256)]),
    default=1,
    show_default=True,
    help="Evaluation processes (episodes are split; results do not depend on it).",
)
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True)
def eval_cmd(
    policy,
    episodes,
    obs,
    error_model,
    config_path,
    seed,
    videos,
    terminate_on,
    stress,
    stress_episodes,
    workers,
    out_dir,
) -> None:
    """Evaluate a policy (or the PID baseline) over seeded episodes."""
    from uwdock.rl.config import EnvConfig
    from uwdock.rl.report import evaluate_to_folder, policy_env_settings, policy_error_model

    em = str(error_model) if error_model else None
    if em is None and obs == "error-model":
        # neither --error-model nor the --config file names one: the one the policy trained on
        in_file = config_path is not None and "error_model_path" in config_data(config_path, "env")
        em = None if in_file else policy_error_model(str(policy))
    env_cfg = load_config(
        EnvConfig,
        config_path,
        section="env",
        overrides={
            "obs_source": obs,
            "error_model_path": em,
            "terminate_on": terminate_on,
        },
    )
    # the policy's observation layout and action scaling come from its own run config
    env_cfg = replace(env_cfg, **policy_env_settings(str(policy)))
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
    )
    click.echo(
        f"success {summary['success_rate']:.1%} (strict "
        f"{summary['success_rate_strict']:.1%}) over {summary['episodes']} episodes; "
        f"report in {out_dir}"
    )


@cli.command(context_settings=CONTEXT)
@click.option("--policy", required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="ONNX file to write.",
)
def export(policy, out_path) -> None:
    """Export a policy to ONNX (observation normalisation included)."""
    from uwdock.rl.export import export_onnx

    click.echo(f"wrote {export_onnx(policy, out_path)}")


@cli.command("fit-error-model", context_settings=CONTEXT)
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Error model file (JSON) to write.",
)
@click.option(
    "--range-bin-m",
    type=field_type("uwdock.rl.error_model:ErrorModelConfig", "range_bin_m"),
    help="Range bin width [0.5].",
)
def fit_error_model_cmd(dataset, out_path, range_bin_m) -> None:
    """Fit the image-derived error model from a labelled dataset (`datasets synth`)."""
    from uwdock.rl.error_model import ErrorModelConfig, fit_error_model, save_error_model

    cfg = load_config(ErrorModelConfig, overrides={"range_bin_m": range_bin_m})
    model = fit_error_model(dataset, cfg)
    save_error_model(model, out_path)
    t = model["tables"]["all"]
    n = sum(sum(row) for row in t["frames"])
    click.echo(f"fitted on {int(n)} frames ({model['dataset']['sha256'][:12]}): {out_path}")


def main() -> None:
    run_group(cli)
