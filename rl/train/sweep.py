"""Multi-seed and hyper-parameter sweeps of whole ``rl train`` runs through Ray Tune
(``rl sweep``).

A sweep is a grid: every training seed times every combination of the ``--set`` values, each
a complete ``rl train`` run of the base config with those fields changed, in its own run folder
``OUT/<trial>`` (a normal run folder: ``rl eval``, ``rl export`` and ``rl train --resume`` take
it). Ray Tune schedules the trials on the cluster's CPUs (a local Ray instance by default). What
a trial reserves (:func:`trial_resources`): with the per-env simulator and more than one env,
one CPU for its learner and one per env worker (Ray actors in the trial's placement group);
with ``--cpus-per-trial N`` the envs share N - 1 actors (results do not depend on how envs are
grouped). A batched-simulator trial runs its batch in the learner's process: one CPU, or N
split over N local batch processes (the same rollouts). ``--gpus-per-trial`` adds GPUs to the
learner's share. Before anything is written, every trial is checked against the cluster: one
that can never be placed is one line saying what to change.

Killed at any moment and run again with the same arguments, a sweep goes on where it stopped:
every trial resumes from its own newest checkpoint (:func:`rl.train.training.train` with ``resume``)
and a finished trial is not trained again, so the results equal an uninterrupted sweep's. The
sweep's own record is ``OUT/sweep.json`` (the plan: trial names, seeds, changed fields) and
``OUT/sweep_summary.json`` (per trial: steps, the best and the last evaluation), written
atomically from the run folders themselves.
"""

from __future__ import annotations

import dataclasses
import datetime
import itertools
import json
import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from uwdock.dockcore.config import from_dict, merge, replace, to_dict
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, atomic_write_text
from uwdock.dockcore.pool import (
    PoolConfig,
    check_inputs_on_nodes,
    input_mapping,
    loopback_local_ray,
    materialize_inputs,
    preflight,
    read_inputs,
    relocate,
    start_ray,
)
from uwdock.rl.env.config import absolute_inputs, check_env_files, with_absolute_inputs
from uwdock.rl.train.training import TrainConfig, train

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "SweepConfig",
    "Trial",
    "TrialResources",
    "check_fits",
    "parse_grid",
    "plan_trials",
    "run_sweep",
    "trial_resources",
]


@dataclass(frozen=True)
class SweepConfig:
    """How a sweep runs.

    Attributes:
        seeds: the training seeds of every grid point.
        max_concurrent_trials: trials running at once (0: as many as the CPUs allow).
        max_failures: times Tune restarts a failed trial (from its newest checkpoint).
        cpus_per_trial: CPUs each trial reserves (0: what its config needs,
            :func:`trial_resources`).
        gpus_per_trial: GPUs each trial's learner reserves (e.g. for ``water_device = "cuda"``
            or a CUDA learner; fractions share a GPU).
    """

    seeds: tuple[Annotated[int, Interval(ge=0, le=2**31 - 1)], ...] = (0, 1, 2)
    max_concurrent_trials: Annotated[int, Interval(ge=0, le=10_000)] = 0
    max_failures: Annotated[int, Interval(ge=0, le=100)] = 1
    cpus_per_trial: Annotated[int, Interval(ge=0, le=1024)] = 0
    gpus_per_trial: Annotated[float, Interval(ge=0.0, le=64.0)] = 0.0

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


@dataclass(frozen=True)
class TrialResources:
    """What one trial reserves and how it runs in it.

    Attributes:
        bundles: the placement group's bundles, the learner's first (``{"CPU": c, "GPU": g}``).
        backend: where ``rl train`` puts the env workers: "ray" (actors in the bundles after
            the first) or "local" (in the learner's process or its local processes).
        envs_per_worker: envs per env actor (``backend == "ray"``).
        batch_workers: processes the batched simulator is split over (``rl train
            --batch-workers``).
        why: how the reservation follows from the config, for the error lines.
    """

    bundles: tuple[dict[str, float], ...]
    backend: str
    envs_per_worker: int = 1
    batch_workers: int = 1
    why: str = ""

    @property
    def cpus(self) -> float:
        return sum(b.get("CPU", 0.0) for b in self.bundles)

    @property
    def gpus(self) -> float:
        return sum(b.get("GPU", 0.0) for b in self.bundles)


def trial_resources(train_cfg: TrainConfig, cpus_per_trial: int = 0,
                    gpus_per_trial: float = 0.0) -> TrialResources:  # fmt: skip
    """The reservation of a trial of ``train_cfg`` (module docstring).

    Raises:
        DockError: ``cpus_per_trial`` 1 for a per-env trial with several envs (they need a
            learner and at least one env actor).
    """
    gpu = {"GPU": float(gpus_per_trial)} if gpus_per_trial > 0 else {}
    n = train_cfg.n_envs
    if train_cfg.simulator == "batched":
        b = max(1, min(int(cpus_per_trial) or 1, n, 64))
        why = f"the batched simulator in {b} process{'es' if b > 1 else ''}"
        return TrialResources(({"CPU": float(b), **gpu},), "local", batch_workers=b, why=why)
    if n == 1:
        c = max(1, int(cpus_per_trial))
        return TrialResources(({"CPU": float(c), **gpu},), "local", why="one env")
    if cpus_per_trial == 1:
        raise DockError(
            f"--cpus-per-trial 1: a per-env trial with {n} envs needs 2 CPUs at least (its "
            'learner and one env actor); give 2 or more, or use simulator = "batched"'
        )
    actors = n if cpus_per_trial == 0 else min(n, int(cpus_per_trial) - 1)
    per = -(-n // actors)  # ceil: the envs over the actors
    actors = -(-n // per)
    why = f"1 learner + {actors} env actor{'s' if actors > 1 else ''} for {n} envs"
    bundles = ({"CPU": 1.0, **gpu}, *({"CPU": 1.0} for _ in range(actors)))
    return TrialResources(bundles, "ray", envs_per_worker=per, why=why)


def check_fits(res: TrialResources, nodes: Sequence[Mapping[str, float]], name: str) -> None:
    """Raise a one-line :class:`DockError` when a trial's reservation can never be placed on a
    cluster whose alive nodes have ``nodes`` resources (``{"CPU": .., "GPU": ..}`` each): its
    total beyond the cluster's, or its learner's share beyond every node's."""
    total = {k: sum(float(nd.get(k, 0.0)) for nd in nodes) for k in ("CPU", "GPU")}
    hint = "give --cpus-per-trial (fewer env actors) or fewer n_envs"
    if res.cpus > total["CPU"]:
        raise DockError(
            f"trial {name} needs {res.cpus:g} CPUs ({res.why}) but the cluster has "
            f"{total['CPU']:g}: it could never start; {hint}"
        )
    if res.gpus > total["GPU"]:
        raise DockError(
            f"trial {name} needs {res.gpus:g} GPUs but the cluster has {total['GPU']:g}: it could "
            "never start; lower --gpus-per-trial or add a GPU node"
        )
    first = res.bundles[0]
    if not any(all(float(nd.get(k, 0.0)) >= v for k, v in first.items()) for nd in nodes):
        raise DockError(
            f"trial {name}'s learner needs {first} on one node but no node has that much: "
            "lower --cpus-per-trial / --gpus-per-trial"
        )


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
        given: dict[str, Any] = {}
        for k, v in changes.items():
            given = merge(given, _nested(k, v))
        for seed in cfg.seeds:
            # replace() reads the keys in any layout (env.water_preset: env.world's)
            config = replace(base, **{**given, "seed": int(seed)})
            trials.append(Trial(f"seed{seed}{point}", int(seed), changes, config))
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
        # what best/ holds: the last evaluation the run flagged as best (its first always is)
        best = next((h for h in reversed(history) if h.get("best")), history[-1])
        out["last_eval"] = {k: history[-1].get(k) for k in keys}
        out["best_eval"] = {k: best.get(k) for k in keys}
    return out


def _check_shared(ray: Any, out: Path, created: bool) -> None:
    """Trials write their run folders on the node that runs them, at ``out``'s absolute path:
    check that every node sees ``out`` (a probe file written here, looked for there); if not,
    one line, and ``out`` removed again when this call's sweep created it."""
    probe = out / ".uwdock-storage-probe"
    atomic_write_text(probe, f"{os.getpid()} {datetime.datetime.now().isoformat()}\n")
    try:
        check_inputs_on_nodes(ray, [probe])
    except DockError as exc:
        probe.unlink(missing_ok=True)
        if created and not any(out.iterdir()):
            out.rmdir()
        raise DockError(
            f"--out {out} is not on storage every Ray node mounts (trials write their run "
            f"folders where they run): use a shared path ({exc})"
        ) from None
    probe.unlink(missing_ok=True)


def _absolute(data: dict[str, Any]) -> dict[str, Any]:
    """A recorded trial config with its input paths absolute (a sweep.json written before they
    were); unreadable as a config: as it is (then it differs, as it should)."""
    try:
        cfg = from_dict(TrainConfig, data)
    except (ValueError, TypeError):
        return data
    return to_dict(dataclasses.replace(cfg, env=with_absolute_inputs(cfg.env)))


def _run_trial(config: dict[str, Any], plan: dict[str, Any]) -> None:
    """A Tune trial: train (or resume) its run folder, then report the run's summary."""
    from ray import tune

    name = config["trial"]
    entry = plan[name]
    cfg = from_dict(TrainConfig, entry["config"])
    res = entry["resources"]
    run = Path(entry["run_dir"])
    resume = (run / "config.toml").is_file()
    train(
        cfg, run, resume=resume, progress=False, note=lambda _m: None, backend=res["backend"],
        envs_per_worker=res["envs_per_worker"], batch_workers=res["batch_workers"],
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
    trials, inputs = _with_absolute_inputs(plan_trials(base, cfg, grid))
    loopback_local_ray(ray_address)  # before Ray's import: a local instance on 127.0.0.1 only
    ray, tune = _import_ray_tune()
    # the address answers and Ray starts or joins before anything is written: a bad address
    # is one line and leaves no sweep folder behind
    preflight(PoolConfig("ray", 1, ray_address), start=False)  # started by _start_cluster
    # Ctrl-C ends the command as any other (one line, exit 130; rerunning resumes every trial
    # from its own run folder), not through Tune's graceful stop and its Tuner.restore advice
    os.environ["TUNE_DISABLE_SIGINT_HANDLER"] = "1"
    reserve = {
        t.name: trial_resources(t.config, cfg.cpus_per_trial, cfg.gpus_per_trial) for t in trials
    }
    _start_cluster(ray, reserve, ray_address)
    out = Path(out_dir)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    _check_shared(ray, out, created)
    named = trials
    trials = _share_inputs(out, trials, inputs)
    plan = _write_plan(out, trials, reserve, cfg, grid, named)
    tuner = _tuner(tune, plan, reserve, cfg, out)
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


def _with_absolute_inputs(trials: list[Trial]) -> tuple[list[Trial], set[str]]:
    """The trials with their env's input files checked and named by absolute path, and those
    files (read here: a missing or broken one is one line before anything starts; copied into
    the sweep folder once Ray is up, :func:`_share_inputs`)."""
    inputs: set[str] = set()
    for i, t in enumerate(trials):
        check_env_files(t.config.env)
        env, files = absolute_inputs(t.config.env)
        inputs.update(files)
        trials[i] = dataclasses.replace(t, config=dataclasses.replace(t.config, env=env))
    return trials, inputs


def _import_ray_tune() -> tuple[Any, Any]:
    """The ``ray`` and ``ray.tune`` modules, or one line naming the extra that installs them."""
    try:
        import ray
        from ray import tune
    except ModuleNotFoundError:
        raise DockError(
            "rl sweep needs Ray Tune (pip install 'uwdock[ray]', which installs ray[tune])"
        ) from None
    return ray, tune


def _share_inputs(out: Path, trials: list[Trial], inputs: set[str]) -> list[Trial]:
    """The trials' input files copied once into ``out/inputs/<content>/`` (storage every node
    mounts, :func:`_check_shared`) at their own absolute paths below it, and the trials'
    configs pointed at the copies: a node never needs the driver's files, and the sweep folder
    holds what its runs read. Other content at the same paths is another folder (the plan then
    differs: another sweep)."""
    if not inputs:
        return trials
    files = read_inputs(inputs)
    mapping = input_mapping(files, materialize_inputs(files, out / "inputs"))
    return [dataclasses.replace(t, config=relocate(t.config, mapping)) for t in trials]


def _start_cluster(ray: Any, reserve: dict[str, TrialResources], ray_address: str | None) -> None:
    """Start or join Ray; refuse a trial its nodes can never place."""
    # a local instance holds the largest trial whatever the machine (it then runs alone)
    local_cpus = max(max(math.ceil(r.cpus) for r in reserve.values()), os.cpu_count() or 1)
    start_ray(ray, local_cpus, ray_address)
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    for name, r in reserve.items():
        check_fits(r, nodes, name)


def _write_plan(
    out: Path,
    trials: list[Trial],
    reserve: dict[str, TrialResources],
    cfg: SweepConfig,
    grid: Mapping[str, Sequence[Any]],
    named: list[Trial] | None = None,
) -> dict[str, dict[str, Any]]:
    """``sweep.json`` (refused when ``out`` holds another sweep's); returns the plan: trial ->
    its config, run folder, seed, changes and resources. ``named``: the same trials with their
    inputs at the paths the user gave (a sweep.json written before the inputs were copied into
    the sweep folder names those; its trials are the same)."""
    plan = {
        t.name: {"config": to_dict(t.config), "run_dir": str((out / t.name).resolve()),
                 "seed": t.seed, "changes": t.changes}
        for t in trials
    }  # fmt: skip
    run_how = {
        name: {"bundles": [dict(b) for b in r.bundles], "backend": r.backend,
               "envs_per_worker": r.envs_per_worker, "batch_workers": r.batch_workers}
        for name, r in reserve.items()
    }  # fmt: skip
    old = out / "sweep.json"
    if old.is_file():
        before = json.loads(old.read_text(encoding="utf-8")).get("trials", {})
        # a sweep.json of an older layout or with relative input paths: read as today's
        before = {k: _absolute(v["config"]) for k, v in before.items()}
        given = {t.name: to_dict(t.config) for t in (named or trials)}
        if before not in ({k: v["config"] for k, v in plan.items()}, given):
            raise DockError(
                f"{out} holds another sweep (other trials or configs): use another --out"
            )
    atomic_write_json(old, {"trials": plan, "seeds": list(cfg.seeds), "grid": dict(grid),
                            "resources": run_how})  # fmt: skip
    for name, how in run_how.items():  # not compared on resume: a rerun may reserve otherwise
        plan[name]["resources"] = how
    return plan


def _tuner(
    tune: Any,
    plan: dict[str, dict[str, Any]],
    reserve: dict[str, TrialResources],
    cfg: SweepConfig,
    out: Path,
) -> Any:
    """The Tune run of the plan: one grid point per trial, each in its own placement group,
    Tune's own files under ``out/.tune``."""

    def resources(config: dict[str, Any]) -> Any:
        """The trial's reservation (:func:`trial_resources`; a grid may change it per trial)."""
        return tune.PlacementGroupFactory([dict(b) for b in reserve[config["trial"]].bundles])

    trainable = tune.with_resources(tune.with_parameters(_run_trial, plan=plan), resources)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S")
    return tune.Tuner(
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
