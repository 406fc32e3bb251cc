"""Multi-seed and hyper-parameter sweeps of whole ``rl train`` runs through Ray Tune
(``rl sweep``).

A sweep is a grid: every training seed times every combination of the ``--set`` values, each
a complete ``rl train`` run of the base config with those fields changed, in its own run folder
``OUT/<trial>`` (a normal run folder: ``rl eval``, ``rl export`` and ``rl train --resume`` take
it). Ray Tune schedules the trials on the cluster's CPUs (a local Ray instance by default): each
trial reserves one CPU for its learner and one per env worker (its envs are Ray actors in the
trial's placement group when it has more than one).

Killed at any moment and run again with the same arguments, a sweep goes on where it stopped:
every trial resumes from its own newest checkpoint (:func:`rl.train.train` with ``resume``)
and a finished trial is not trained again, so the results equal an uninterrupted sweep's. The
sweep's own record is ``OUT/sweep.json`` (the plan: trial names, seeds, changed fields) and
``OUT/sweep_summary.json`` (per trial: steps, the best and the last evaluation), written
atomically from the run folders themselves.
"""

from __future__ import annotations

import datetime
import itertools
import json
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from uwdock.dockcore.config import from_dict, lift_moved_keys, merge, to_dict
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json
from uwdock.dockcore.pool import PoolConfig, loopback_local_ray, preflight, start_ray
from uwdock.rl.train import TrainConfig, train

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["SweepConfig", "Trial", "parse_grid", "plan_trials", "run_sweep"]


@dataclass(frozen=True)
class SweepConfig:
    """How a sweep runs.

    Attributes:
        seeds: the training seeds of every grid point.
        max_concurrent_trials: trials running at once (0: as many as the CPUs allow).
        max_failures: times Tune restarts a failed trial (from its newest checkpoint).
    """

    seeds: tuple[Annotated[int, Interval(ge=0, le=2**31 - 1)], ...] = (0, 1, 2)
    max_concurrent_trials: Annotated[int, Interval(ge=0, le=10_000)] = 0
    max_failures: Annotated[int, Interval(ge=0, le=100)] = 1

    def validate(self) -> None:
        """Raise ValueError for no seed or a repeated one."""
        if not self.seeds:
            raise ValueError("seeds: give at least one")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds: repeated in {list(self.seeds)}")


@dataclass(frozen=True)
class Trial:
    """One run of a sweep: its name (the run folder's), seed, changed fields and config."""

    name: str
    seed: int
    changes: dict[str, Any]
    config: TrainConfig


def parse_grid(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["ppo.learning_rate=1e-4,3e-4", "ppo.ent_coef=0.0"]`` -> field -> values (each value
    read as a TOML value: numbers, booleans, quoted strings; a bare word is a string)."""
    grid: dict[str, list[Any]] = {}
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", key):
            raise DockError(f"--set: expected FIELD=V1,V2,... (e.g. ppo.learning_rate=1e-4,3e-4), "
                            f"got {item[:80]!r}")  # fmt: skip
        if key == "seed":
            raise DockError("--set: the seeds are --seeds")
        parsed = []
        for raw in values.split(","):
            raw = raw.strip()
            if not raw:
                raise DockError(f"--set {key}: an empty value in {values[:80]!r}")
            parsed.append(_toml_value(raw))
        if key in grid:
            raise DockError(f"--set: {key} given twice")
        grid[key] = parsed
    return grid


def _toml_value(raw: str) -> Any:
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw  # a bare word: a string (an obs source, a preset name)


def _nested(key: str, value: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def _slug(value: Any) -> str:
    return re.sub(r"[^A-Za-z0-9.+-]+", "-", str(value)).strip("-")[:40] or "x"


def plan_trials(
    base: TrainConfig, cfg: SweepConfig, grid: Mapping[str, Sequence[Any]]
) -> list[Trial]:
    """Every seed times every grid point, each config validated (a bad field or value is a
    one-line :class:`ConfigError` naming it)."""
    cfg.validate()
    keys = sorted(grid)
    trials = []
    for values in itertools.product(*(grid[k] for k in keys)):
        changes = dict(zip(keys, values, strict=True))
        point = "".join(f"_{k.split('.')[-1]}={_slug(v)}" for k, v in changes.items())
        for seed in cfg.seeds:
            data = to_dict(base)
            for k, v in changes.items():  # a key that moved (env.water_preset): to its table
                data = merge(data, lift_moved_keys(TrainConfig, _nested(k, v)))
            data["seed"] = int(seed)
            trials.append(
                Trial(f"seed{seed}{point}", int(seed), changes, from_dict(TrainConfig, data))
            )
    names = [t.name for t in trials]
    if len(set(names)) != len(names):
        raise DockError("--set: two grid values give the same trial name; make them differ")
    return trials


def _trial_summary(run: Path) -> dict[str, Any]:
    """What a finished (or interrupted) run folder says about itself."""
    out: dict[str, Any] = {"done": (run / "DONE").is_file()}
    if out["done"]:
        out["steps"] = json.loads((run / "DONE").read_text(encoding="utf-8")).get("steps")
    path = run / "eval_history.jsonl"
    history = []
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                history.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    if history:
        keys = ("step", "success_rate", "success_rate_strict", "mean_time_to_dock_s",
                "mean_collisions", "mean_return")  # fmt: skip
        best = max(history, key=lambda h: (h.get("success_rate_strict", 0.0), h.get("step", 0)))
        out["last_eval"] = {k: history[-1].get(k) for k in keys}
        out["best_eval"] = {k: best.get(k) for k in keys}
    return out


def _run_trial(config: dict[str, Any], plan: dict[str, Any]) -> None:
    """A Tune trial: train (or resume) its run folder, then report the run's summary."""
    from ray import tune

    name = config["trial"]
    entry = plan[name]
    cfg = from_dict(TrainConfig, entry["config"])
    run = Path(entry["run_dir"])
    resume = (run / "config.toml").is_file()
    train(
        cfg, run, resume=resume, progress=False, note=lambda _m: None,
        backend="ray" if cfg.n_envs > 1 else "local",
    )  # fmt: skip
    summary = _trial_summary(run)
    flat = {f"{k}.{kk}": vv for k, v in summary.items() if isinstance(v, dict)
            for kk, vv in v.items() if isinstance(vv, (int, float))}  # fmt: skip
    tune.report({"done": summary["done"], **flat})


def run_sweep(
    base: TrainConfig,
    cfg: SweepConfig,
    grid: Mapping[str, Sequence[Any]],
    out_dir: str | Path,
    ray_address: str | None = None,
    note: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Run (or resume) the sweep into ``out_dir``; returns its summary (also written to
    ``sweep_summary.json``).

    Raises:
        DockError: a bad grid or config, Ray or Ray Tune missing, a trial that failed more
            than ``cfg.max_failures`` times (its reason).
    """
    trials = plan_trials(base, cfg, grid)
    loopback_local_ray(ray_address)  # before Ray's import: a local instance on 127.0.0.1 only
    try:
        import ray
        from ray import tune
    except ModuleNotFoundError:
        raise DockError(
            "rl sweep needs Ray Tune (pip install 'uwdock[ray]', which installs ray[tune])"
        ) from None
    # the address answers and Ray starts or joins before anything is written: a bad address
    # is one line and leaves no sweep folder behind
    preflight(PoolConfig("ray", 1, ray_address))
    os.environ["TUNE_DISABLE_SIGINT_HANDLER"] = "1"  # (see below)
    start_ray(ray, max(t.config.n_envs + 1 for t in trials), ray_address)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plan = {
        t.name: {"config": to_dict(t.config), "run_dir": str((out / t.name).resolve()),
                 "seed": t.seed, "changes": t.changes}
        for t in trials
    }  # fmt: skip
    old = out / "sweep.json"
    if old.is_file():
        before = json.loads(old.read_text(encoding="utf-8")).get("trials", {})
        # a sweep.json written before [env.world]: its configs in the current layout
        before = {k: lift_moved_keys(TrainConfig, v["config"]) for k, v in before.items()}
        if before != {k: v["config"] for k, v in plan.items()}:
            raise DockError(
                f"{out} holds another sweep (other trials or configs): use another --out"
            )
    atomic_write_json(old, {"trials": plan, "seeds": list(cfg.seeds), "grid": dict(grid)})
    # Ctrl-C ends the command as any other (one line, exit 130; rerunning resumes every trial
    # from its own run folder), not through Tune's graceful stop and its Tuner.restore advice:
    # TUNE_DISABLE_SIGINT_HANDLER, set above
    n_envs = {t.name: t.config.n_envs for t in trials}  # a grid may change it per trial

    def resources(config: dict[str, Any]) -> Any:
        """One CPU for the learner, one per env worker when they are Ray actors."""
        n = n_envs[config["trial"]]
        return tune.PlacementGroupFactory([{"CPU": 1.0}] * (1 + (n if n > 1 else 0)))

    trainable = tune.with_resources(tune.with_parameters(_run_trial, plan=plan), resources)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S")
    tuner = tune.Tuner(
        trainable,
        param_space={"trial": tune.grid_search(list(plan))},
        tune_config=tune.TuneConfig(max_concurrent_trials=cfg.max_concurrent_trials or None),
        run_config=tune.RunConfig(
            name=f"tune-{stamp}",
            storage_path=str((out / ".tune").resolve()),
            verbose=0,
            failure_config=tune.FailureConfig(max_failures=cfg.max_failures),
        ),
    )
    note(f"{len(trials)} trials into {out}")
    results = tuner.fit()
    summary = {name: {**_trial_summary(Path(p["run_dir"])), "seed": p["seed"],
                      "changes": p["changes"]} for name, p in plan.items()}  # fmt: skip
    atomic_write_json(out / "sweep_summary.json", summary)
    failed = [r for r in results if r.error is not None]
    if failed:
        why = " ".join(str(failed[0].error).split())[:300]
        raise DockError(f"{len(failed)} of {len(trials)} trials failed; the first: {why}")
    return summary
