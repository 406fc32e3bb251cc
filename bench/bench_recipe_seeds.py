"""Does a training recipe give a good policy on EVERY seed? Train N seeds, fly each on held-out
episodes beside the PID, judge the worst seed.

Usage::

    python bench/bench_recipe_seeds.py [--recipe shipped] [--seeds 0,1,2,3,4,5,6,7]
        [--work /work/recipe_seeds] [--episodes 100] [--stress-episodes 100] [--seed 99000]
        [--rows "camera,current 0.4,long approach,all"] [--workers 2]
        [--skip-train] [--skip-eval] [--quick] [--name recipe_seeds] [--out-dir bench/results]

Steps (each resumable: run the same command again after an interruption):

1. train (unless ``--skip-train``): ``rl train --recipe RECIPE --seed S --out WORK/seed_S`` per
   seed, one after the other (~5 min a seed on 2 cores), the output streamed; a seed whose
   ``recipe.json`` lists every stage as done (and whose policy files are there) is skipped, an
   interrupted one resumes where it stopped.
2. evaluate (unless ``--skip-eval``): ``bench/bench_docking.py --controllers policy`` on each
   trained seed's folder into ``WORK/eval/seed_S.json``, and once ``--controllers pid`` (env
   settings from the first trained seed's folder: every seed of a recipe has the same ones) into
   ``WORK/eval/pid.json``; episode k is seed ``--seed`` + k in every file (99000...: held out,
   never used in development or for picking a checkpoint; 95000... were flown while the
   recipe's ``best/`` rule was chosen, 97000... while its width and length were). A file that
   is there, ``complete`` and flown with these settings is kept (and a seed's file older than
   its policy is flown again); one flown with other settings is refused, not overwritten.
3. report (always): the statistics below over the seeds whose evaluation is there; a missing
   seed is listed, and the bar is then at best INCOMPLETE.

``--quick`` is a smoke run of steps 2-3: ``--episodes 4 --stress-episodes 2 --rows camera``
into ``WORK/eval_quick/`` and ``<name>`` ``recipe_seeds_quick`` (training is the recipe's own
length: give ``--seeds 0`` or ``--skip-train`` for a short run). ``--skip-train --skip-eval``
only re-reads ``WORK`` and writes the report again.

Statistics (pure functions of this file, checked by ``tests/test_recipe_seeds_stats.py``):

per seed (the camera row, clear tank, against the PID on the same episodes)
    strict success with its Wilson 95 % interval; the mean time to dock over the episodes BOTH
    the seed's policy and the PID docked (strict) and its ratio to the PID's mean over the same
    episodes; collisions per episode minus the PID's, with a paired bootstrap 95 % interval
    (episodes resampled: ``bench_docking.paired_change``, percentile, 10,000 resamples, seed 0,
    which also gives the strict change with its exact McNemar p and the paired time change);
    each harder row's strict success (Wilson) and paired change against the PID.
across seeds
    the worst seed, the median and the interquartile mean (IQM) of the camera strict success,
    the time ratio and the collision difference, each with a percentile bootstrap 95 % interval
    over seeds (seeds resampled with replacement, 10,000 resamples, generator seed 0; a resample's
    worst seed is never worse than the observed worst, so that interval lies on its better side:
    it shows how much a lucky draw of seeds could flatter the worst, not a symmetric error). The
    IQM is the mean of the middle 50 % of the sorted per-seed scores, the scores straddling the
    25th and 75th percentile positions weighted by the fraction of them inside (:func:`iqm`:
    with n seeds, the sorted score i covers [i, i+1) of [0, n) and weighs its overlap with
    [n/4, 3n/4]). That is ``scipy.stats.trim_mean(x, 0.25)`` (rliable's IQM) when n is a
    multiple of 4, and differs otherwise (trim_mean drops floor(n/4) scores each side whole).
    Pooled: every seed's episodes paired with the PID's same episode, per row
    (``paired_change``; the episodes are treated as independent, so its intervals ignore the
    seed-to-seed spread the per-seed numbers show).

The bar (PASS / FAIL per criterion; INCOMPLETE while seeds are missing and none fails):
    camera strict success of the worst seed >= 95 %; the worst seed's time ratio <= 0.75; every
    seed's collisions per episode below the PID's with the paired 95 % interval below 0.

Writes ``<out-dir>/<name>.json`` (``save_results``: machine, commit; ``rows``: one per seed;
``bench_config``: the settings, the PID's rows, ``aggregates``, ``pooled_vs_pid``, ``bar``,
``verdict``, ``commands``, the learning curves and each seed's ``recipe.json``, stage
provenance (command, commit, numerics) and policy checksums) and ``<name>.png``: (a) the
periodic evaluation's strict success and (b) mean return of every seed against training steps
(``runs/<stage>/eval_history.jsonl``, each stage drawn after the one before on a common step
axis; the median over seeds, the min-max band, each seed faint; the stages evaluate on their
own training conditions, so the curves jump at a stage boundary); (c) every seed's camera
strict success with its Wilson interval, the PID's as a line and the IQM with its interval.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from compare_docking import bench_docking_module  # bench/, beside this file

from uwdock.dockcore.bench import format_table, save_results

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
WORK = Path("/work/recipe_seeds")
ROWS = ("camera", "current 0.4", "long approach", "all")
REF = "camera"  # the row the bar is judged on
BAR_STRICT = 0.95  # worst seed's camera strict success, at least
BAR_TIME_RATIO = 0.75  # worst seed's time to dock over the PID's (same episodes), at most
N_RESAMPLES = 10_000
BOOT_SEED = 0
Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile
TOL = 1e-12  # 95 / 100 is exactly at the bar


# --- statistics (pure) ------------------------------------------------------------------------


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a success rate (95 % with the default ``z``); (0, 1) for n = 0.
    The same interval as ``scipy.stats.binomtest(k, n).proportion_ci(method="wilson")``."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def iqm(values: Any, axis: int = -1) -> Any:
    """Interquartile mean along ``axis``: the mean of the middle 50 % of the sorted values, the
    two values straddling the quartile positions weighted by their fraction inside.

    With n values sorted, value i covers [i, i+1) of [0, n); its weight is its overlap with
    [n/4, 3n/4] over n/2 (the weights sum to 1). For n a multiple of 4 this is the plain mean
    of the middle n/2 values (``scipy.stats.trim_mean(x, 0.25)``); e.g. n = 5 weighs the sorted
    values 0, 3/4, 1, 3/4, 0 (over 5/2), where trim_mean would take the middle three alike.
    """
    x = np.sort(np.moveaxis(np.asarray(values, dtype=float), axis, -1), axis=-1)
    n = x.shape[-1]
    if n == 0:
        raise ValueError("iqm of no values")
    i = np.arange(n)
    w = np.clip(np.minimum(i + 1, 3 * n / 4) - np.maximum(i, n / 4), 0.0, None) / (n / 2)
    return x @ w


def bootstrap_interval(
    values: Sequence[float],
    statistic: Callable[..., Any],
    n_resamples: int = N_RESAMPLES,
    seed: int = BOOT_SEED,
    level: float = 0.95,
) -> tuple[float | None, float | None]:
    """Percentile bootstrap interval of ``statistic(values)``: ``values`` resampled with
    replacement ``n_resamples`` times (``numpy.random.default_rng(seed)``, so the same values give
    the same interval); ``statistic(array, axis=-1)`` reduces each resample (np.median, np.min,
    :func:`iqm` ...). (None, None) for no values; one value gives (it, it)."""
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        return (None, None)
    rng = np.random.default_rng(seed)
    stats = statistic(x[rng.integers(0, x.size, size=(n_resamples, x.size))], axis=-1)
    tail = 100 * (1 - level) / 2
    lo, hi = np.percentile(stats, [tail, 100 - tail])
    return (float(lo), float(hi))


def across_seeds(
    values: Sequence[float | None],
    higher_is_better: bool,
    n_resamples: int = N_RESAMPLES,
    seed: int = BOOT_SEED,
) -> dict[str, Any]:
    """The worst seed, the median and the IQM of per-seed scores, each with a percentile
    bootstrap 95 % interval over seeds (:func:`bootstrap_interval`). A None score (a seed where
    the metric is undefined, e.g. no episode both docked) is left out and counted in ``undefined``.
    """
    x = [float(v) for v in values if v is not None and math.isfinite(v)]
    worst_of = np.min if higher_is_better else np.max
    out: dict[str, Any] = {"seeds": len(x), "undefined": len(values) - len(x),
                           "higher_is_better": higher_is_better}  # fmt: skip
    for key, fn in (("worst", worst_of), ("median", np.median), ("iqm", iqm)):
        out[key] = float(fn(np.asarray(x), axis=-1)) if x else None
        out[f"{key}_ci95"] = bootstrap_interval(x, fn, n_resamples, seed)
    return out


def paired_episodes(
    base: Sequence[dict[str, Any]], other: Sequence[dict[str, Any]]
) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(base's, other's) outcome of every episode both flew (same ``episode`` index)."""
    a = {e["episode"]: e for e in base}
    return [(a[e["episode"]], e) for e in other if e["episode"] in a]


def time_ratio(pid_eps: Sequence[dict[str, Any]], pol_eps: Sequence[dict[str, Any]]) -> dict:
    """Mean time to dock of the policy and of the PID over the episodes BOTH docked (strict),
    and the policy's over the PID's (None when no episode both docked)."""

    def docked(e: dict[str, Any]) -> bool:
        return bool(e["success_strict"]) and e.get("time_to_dock_s") is not None

    both = [(p, q) for p, q in paired_episodes(pid_eps, pol_eps) if docked(p) and docked(q)]
    if not both:
        return {"both_docked": 0, "time_to_dock_s": None, "pid_time_to_dock_s": None,
                "time_ratio": None}  # fmt: skip
    t_pol = float(np.mean([q["time_to_dock_s"] for _, q in both]))
    t_pid = float(np.mean([p["time_to_dock_s"] for p, _ in both]))
    return {"both_docked": len(both), "time_to_dock_s": t_pol, "pid_time_to_dock_s": t_pid,
            "time_ratio": t_pol / t_pid if t_pid > 0 else None}  # fmt: skip


def strict_of(eps: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Strict success of episodes with its Wilson 95 % interval."""
    k = sum(1 for e in eps if e["success_strict"])
    return {"episodes": len(eps), "strict": k / len(eps) if eps else None,
            "strict_ci95": wilson_interval(k, len(eps))}  # fmt: skip


def vs_pid(pid_eps: Sequence[dict[str, Any]], pol_eps: Sequence[dict[str, Any]]) -> dict:
    """One row's policy episodes against the PID's on the same episodes: both strict successes
    (Wilson), the time ratio (:func:`time_ratio`), collisions per episode of both over the
    common episodes, and ``bench_docking.paired_change`` (strict change with McNemar p, paired
    time change, collisions change, each with its paired bootstrap 95 % interval)."""
    pairs = paired_episodes(pid_eps, pol_eps)
    if not pairs:
        raise ValueError("the policy and the PID share no episode (other --seed?)")
    change = bench_docking_module().paired_change(list(pid_eps), list(pol_eps))
    mine = strict_of([q for _, q in pairs])
    pid = strict_of([p for p, _ in pairs])
    return {
        **mine,
        "pid_strict": pid["strict"],
        "pid_strict_ci95": pid["strict_ci95"],
        **time_ratio(pid_eps, pol_eps),
        "collisions": float(np.mean([q["collisions"] for _, q in pairs])),
        "pid_collisions": float(np.mean([p["collisions"] for p, _ in pairs])),
        "collisions_diff": change["collisions_change"],
        "collisions_diff_ci95": change["collisions_change_ci95"],
        "paired_change": change,
    }


def seed_stats(pid_rows: dict[str, dict], pol_rows: dict[str, dict], ref: str = REF) -> dict:
    """A seed's numbers: the ``ref`` row against the PID (:func:`vs_pid`, flattened) and every
    other row the PID flew too under ``hard_rows`` (:func:`vs_pid` of each)."""
    if ref not in pol_rows or ref not in pid_rows:
        raise ValueError(f"the {ref!r} row is missing (policy or PID)")
    out = vs_pid(pid_rows[ref]["per_episode"], pol_rows[ref]["per_episode"])
    out["hard_rows"] = {
        cond: vs_pid(pid_rows[cond]["per_episode"], row["per_episode"])
        for cond, row in pol_rows.items()
        if cond != ref and cond in pid_rows
    }
    return out


def pooled_vs_pid(pid_rows: dict[str, dict], seeds: Sequence[dict[str, dict]]) -> list[dict]:
    """Per row: every seed's episode k paired with the PID's episode k (keys made unique across
    seeds), compared as one sample (:func:`vs_pid`)."""
    out = []
    for cond, p in pid_rows.items():
        pid_eps: list[dict] = []
        pol_eps: list[dict] = []
        for rows in seeds:
            if cond not in rows:
                continue
            common = paired_episodes(p["per_episode"], rows[cond]["per_episode"])
            k0 = len(pol_eps)
            pid_eps += [{**a, "episode": k0 + j} for j, (a, _) in enumerate(common)]
            pol_eps += [{**b, "episode": k0 + j} for j, (_, b) in enumerate(common)]
        if pol_eps:
            stats = vs_pid(pid_eps, pol_eps)
            out.append({"condition": cond, "seeds": sum(cond in r for r in seeds), **stats})
    return out


def judge(per_seed: Sequence[dict[str, Any]], expected: int) -> tuple[list[dict], str]:
    """The bar over the seeds evaluated (``per_seed``: :func:`seed_stats` results) and the
    verdict: FAIL when a criterion fails (more seeds cannot mend it), INCOMPLETE when fewer than
    ``expected`` seeds were evaluated and none fails, else PASS."""
    strict = [s["strict"] for s in per_seed]
    ratios = [s["time_ratio"] for s in per_seed]
    worst_strict = min(strict) if strict else None
    undefined = any(r is None for r in ratios)
    worst_ratio = None if undefined or not ratios else max(ratios)
    fewer = [s for s in per_seed
             if s["collisions_diff"] < 0 and s["collisions_diff_ci95"][1] is not None
             and s["collisions_diff_ci95"][1] < 0]  # fmt: skip
    bar = [
        {"criterion": f"camera strict success, worst seed >= {100 * BAR_STRICT:.0f} %",
         "value": worst_strict,
         "pass": worst_strict is not None and worst_strict >= BAR_STRICT - TOL},
        {"criterion": f"time to dock / PID's (both docked), worst seed <= {BAR_TIME_RATIO}",
         "value": worst_ratio if not undefined else "undefined on a seed",
         "pass": worst_ratio is not None and worst_ratio <= BAR_TIME_RATIO + TOL},
        {"criterion": "collisions per episode below the PID's on every seed (paired 95 % "
                      "interval below 0)",
         "value": f"{len(fewer)} of {len(per_seed)} seeds",
         "pass": bool(per_seed) and len(fewer) == len(per_seed)},
    ]  # fmt: skip
    if not all(b["pass"] for b in bar) and per_seed:
        verdict = "FAIL"
    elif len(per_seed) < expected:
        verdict = "INCOMPLETE"
    else:
        verdict = "PASS"
    for b in bar:
        b["verdict"] = "PASS" if b["pass"] else ("FAIL" if per_seed else "INCOMPLETE")
        if b["pass"] and len(per_seed) < expected:
            b["verdict"] = "INCOMPLETE"
    return bar, verdict


def learning_curves(
    histories: dict[str, list[list[dict[str, Any]]]], metric: str
) -> tuple[list[dict[str, Any]], list[float]]:
    """Per-seed evaluation histories (label -> one list of records per stage, in order) on one
    step axis: stage j's steps are offset by the sum over earlier stages of their last
    evaluation step (the largest over seeds). Returns the points, one per (stage, step) with the
    median, min and max over the seeds that have it and each seed's value, and the offsets (the
    stage boundaries)."""
    n_stages = max((len(h) for h in histories.values()), default=0)
    offsets = [0.0]
    for j in range(1, n_stages):
        last = [max(int(r["step"]) for r in h[j - 1]) for h in histories.values()
                if len(h) >= j and h[j - 1]]  # fmt: skip
        offsets.append(offsets[-1] + (max(last) if last else 0))
    points: dict[tuple[int, int], dict[str, float]] = {}
    for label, stages in histories.items():
        for j, records in enumerate(stages):
            for r in records:
                v = r.get(metric)
                if v is not None:
                    points.setdefault((j, int(r["step"])), {})[label] = float(v)
    out = []
    for (j, step), by_seed in sorted(points.items()):
        vals = list(by_seed.values())
        out.append({"stage": j, "step": step, "x": offsets[j] + step, "seeds": len(vals),
                    "median": float(np.median(vals)), "min": min(vals), "max": max(vals),
                    "per_seed": by_seed})  # fmt: skip
    return out, offsets[1:]


# --- the folders ------------------------------------------------------------------------------


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def trained(folder: Path) -> bool:
    """Every stage of the recipe in ``folder`` is done and its policy published."""
    state = read_json(folder / "recipe.json")
    if not isinstance(state, dict):
        return False
    names = [s.get("name") for s in state.get("stages", [])]
    done = state.get("done", [])
    return (bool(names) and all(n in done for n in names)
            and all((folder / f).is_file() for f in ("model.json", "weights.npz")))  # fmt: skip


#: Settings of the PID's evaluation that may exceed the seeds' (its episodes are paired with
#: theirs by index: the first ones are the same seeds).
AT_LEAST = ("episodes", "stress_episodes")


def eval_state(
    path: Path, expect: dict[str, Any], policy: Path | None = None, at_least: Sequence[str] = ()
) -> tuple[str, str]:
    """Whether a bench_docking output can be used: ("ok", ""), ("run", why: missing, incomplete
    or older than the policy) or ("other", how its settings differ from ``expect``; a setting
    named in ``at_least`` may be larger)."""
    data = read_json(path)
    if data is None:
        return ("run", "not there" if not path.exists() else "unreadable")
    cfg = data.get("bench_config", {})
    if not cfg.get("complete"):
        return ("run", "incomplete (interrupted)")

    def agrees(k: str, v: Any) -> bool:
        got = cfg.get(k)
        if k in at_least and isinstance(got, int) and isinstance(v, int):
            return got >= v
        return got == v

    diff = [f"{k} {cfg.get(k)!r} (wanted {v!r})" for k, v in expect.items() if not agrees(k, v)]
    if diff:
        return ("other", ", ".join(diff))
    if policy is not None:
        weights = policy / "weights.npz"
        if weights.is_file() and weights.stat().st_mtime > path.stat().st_mtime:
            return ("run", "older than the policy (retrained)")
    return ("ok", "")


def first_episodes(rows: dict[str, dict[str, Any]], episodes: int, stress: int) -> dict:
    """``rows`` (by condition) with only their first ``episodes`` (the headline rows) or
    ``stress`` (the harder rows) episodes: the PID flown with more than the seeds, compared on
    the episodes they flew."""
    headline = {r.name for r in bench_docking_module().ROWS if r.headline}
    return {cond: {**row, "per_episode": [e for e in row["per_episode"]
                                          if e["episode"] < (episodes if cond in headline
                                                             else stress)]}
            for cond, row in rows.items()}  # fmt: skip


def rows_of(path: Path, controller: str) -> dict[str, dict[str, Any]]:
    data = read_json(path) or {}
    return {r["condition"]: r for r in data.get("rows", []) if r.get("controller") == controller}


def stage_names(folder: Path) -> list[str]:
    state = read_json(folder / "recipe.json")
    if isinstance(state, dict) and state.get("stages"):
        return [s["name"] for s in state["stages"]]
    runs = folder / "runs"
    return sorted(p.name for p in runs.iterdir() if p.is_dir()) if runs.is_dir() else []


def eval_history(run: Path) -> list[dict[str, Any]]:
    path = run / "eval_history.jsonl"
    if not path.is_file():
        return []
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue  # a line being written
    return [r for r in out if isinstance(r, dict) and "step" in r]


def provenance_of(folder: Path) -> dict[str, Any]:
    """A recipe folder's records: ``recipe.json``, each stage's provenance (command, commit,
    numerics, packages) and the policy's checksums."""
    stages = {}
    for name in stage_names(folder):
        p = read_json(folder / "runs" / name / "provenance.json") or {}
        stages[name] = {"created_utc": p.get("created_utc"), "command": p.get("command"),
                        "git": p.get("git"), "numerics": p.get("machine", {}).get("numerics"),
                        "packages": p.get("packages")}  # fmt: skip
    sums = folder / "checksums.sha256"
    return {
        "folder": str(folder),
        "recipe_json": read_json(folder / "recipe.json"),
        "stages": stages,
        "checksums": sums.read_text(encoding="utf-8") if sums.is_file() else None,
    }


def eval_meta(path: Path) -> dict[str, Any]:
    data = read_json(path) or {}
    return {"file": str(path), "command": data.get("command"), "git": data.get("git"),
            "created_utc": data.get("created_utc"),
            "numerics": data.get("machine", {}).get("numerics")}  # fmt: skip


# --- the steps --------------------------------------------------------------------------------

T0 = time.monotonic()


def say(message: str) -> None:
    print(f"[{(time.monotonic() - T0) / 60:6.1f} min] {message}", flush=True)


def rl_command() -> str:
    """The ``rl`` console script beside this Python (the virtualenv's), else on PATH."""
    here = Path(sys.executable).parent / "rl"
    found = str(here) if here.is_file() else shutil.which("rl")
    if found is None:
        raise SystemExit(f"error: no `rl` command beside {sys.executable} or on PATH")
    return found


def run_streamed(cmd: list[str]) -> int:
    """Run ``cmd`` with this process's stdout and stderr (its progress shown as it goes)."""
    say(f"$ {shlex.join(cmd)}")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd)
    try:
        rc = proc.wait()
    except KeyboardInterrupt:  # the command got the SIGINT too: let it stop cleanly
        say("interrupted: waiting for the command to stop (Ctrl-C again: kill it)")
        try:
            proc.wait()
        except KeyboardInterrupt:
            proc.kill()
            proc.wait()
        raise
    say(f"exit {rc} after {(time.monotonic() - t0) / 60:.1f} min")
    return rc


def train_step(args, seeds: list[int]) -> dict[int, str]:
    """Train (or resume) every seed not yet trained; the seeds that failed, with why."""
    rl = rl_command()
    failed: dict[int, str] = {}
    took: list[float] = []  # minutes of the seeds this run trained
    for i, s in enumerate(seeds, 1):
        folder = args.work / f"seed_{s}"
        if trained(folder):
            say(f"train seed {s} ({i}/{len(seeds)}): done already ({folder})")
            continue
        how = "resuming" if (folder / "recipe.json").is_file() else "from scratch"
        eta = f", ~{sum(took) / len(took):.0f} min as the seeds before" if took else ""
        say(f"train seed {s} ({i}/{len(seeds)}): recipe {args.recipe}, {how}{eta}")
        t0 = time.monotonic()
        rc = run_streamed(train_cmd(rl, args.recipe, s, folder))
        took.append((time.monotonic() - t0) / 60)
        if rc != 0 or not trained(folder):
            failed[s] = f"rl train exit {rc}"
            say(f"train seed {s}: FAILED (exit {rc}); going on with the other seeds")
    return failed


def train_cmd(rl: str, recipe: str, seed: int, folder: Path) -> list[str]:
    return [rl, "train", "--recipe", recipe, "--seed", str(seed), "--out", str(folder)]


def eval_cmd(args, policy: Path, controllers: str, name: str) -> list[str]:
    return [sys.executable, str(HERE / "bench_docking.py"), "--policy", str(policy),
            "--controllers", controllers, "--rows", ",".join(args.rows),
            "--episodes", str(args.episodes), "--stress-episodes", str(args.stress_episodes),
            "--seed", str(args.seed), "--workers", str(args.workers), "--name", name,
            "--out-dir", str(args.eval_dir)]  # fmt: skip


def expected(args, controller: str) -> dict[str, Any]:
    """The bench_docking settings a usable output of ``controller`` was flown with."""
    return {"episodes": args.episodes, "stress_episodes": args.stress_episodes,
            "seed": args.seed, "rows": list(args.rows), "controllers": [controller]}  # fmt: skip


def eval_one(args, path: Path, policy: Path, controller: str, label: str, check_policy: bool):
    want = expected(args, controller)
    if check_policy:
        want["policy"] = str(policy)
    state, why = eval_state(path, want, policy if check_policy else None,
                            () if check_policy else AT_LEAST)  # fmt: skip
    if state == "ok":
        say(f"evaluate {label}: done already ({path})")
        return None
    if state == "other":
        raise SystemExit(f"error: {path} was flown with other settings: {why}; move it away or "
                         "give the settings it was flown with")  # fmt: skip
    n = len(args.rows)
    say(f"evaluate {label} ({why}): {n} rows x {args.episodes}/{args.stress_episodes} episodes")
    rc = run_streamed(eval_cmd(args, policy, controller, path.stem))
    return None if rc == 0 else f"bench_docking exit {rc}"


def eval_step(args, seeds: list[int]) -> dict[int | str, str]:
    """Fly the PID once and every trained seed's policy; the failures, with why."""
    args.eval_dir.mkdir(parents=True, exist_ok=True)
    ready = [s for s in seeds if trained(args.work / f"seed_{s}")]
    failed: dict[int | str, str] = {}
    for s in seeds:
        if s not in ready:
            say(f"evaluate seed {s}: not trained ({args.work / f'seed_{s}'}), skipped")
    if not ready:
        say("evaluate: no trained seed, nothing to fly")
        return failed
    why = eval_one(args, args.eval_dir / "pid.json", args.work / f"seed_{ready[0]}", "pid",
                   "the PID", check_policy=False)  # fmt: skip
    if why:
        failed["pid"] = why
    for i, s in enumerate(ready, 1):
        folder = args.work / f"seed_{s}"
        why = eval_one(args, args.eval_dir / f"seed_{s}.json", folder, "policy",
                       f"seed {s} ({i}/{len(ready)})", check_policy=True)  # fmt: skip
        if why:
            failed[s] = why
    return failed


def report(args, seeds: list[int], failures: dict) -> None:
    """Step 3: the statistics, the table, the bar, the JSON and the figure."""
    pid_path = args.eval_dir / "pid.json"
    state, why = eval_state(pid_path, expected(args, "pid"), at_least=AT_LEAST)
    if state != "ok":
        raise SystemExit(f"error: no usable PID evaluation {pid_path}: {why}")
    pid_rows = first_episodes(rows_of(pid_path, "pid"), args.episodes, args.stress_episodes)
    pid_cfg = (read_json(pid_path) or {}).get("bench_config", {})
    pid_env = pid_cfg.get("env")
    say(f"report: {len(seeds)} seeds, the PID from {pid_path}; paired bootstraps ...")
    per_seed, seed_rows, missing, env_differs = [], [], {}, []
    for s in seeds:
        folder, path = args.work / f"seed_{s}", args.eval_dir / f"seed_{s}.json"
        want = {**expected(args, "policy"), "policy": str(folder)}
        state, why = eval_state(path, want, folder)
        if state != "ok":
            missing[s] = failures.get(s) or (why if trained(folder) else "not trained")
            continue
        rows = rows_of(path, "policy")
        if (read_json(path) or {}).get("bench_config", {}).get("env") != pid_env:
            env_differs.append(s)
        stats = seed_stats(pid_rows, rows)
        per_seed.append({"seed": s, "folder": str(folder), "eval": eval_meta(path), **stats})
        seed_rows.append(rows)
    if env_differs:
        say(f"WARNING: seeds {env_differs} were flown in other env settings than the PID")
    metrics = {
        "camera_strict": across_seeds([r["strict"] for r in per_seed], True),
        "time_ratio": across_seeds([r["time_ratio"] for r in per_seed], False),
        "collisions_diff": across_seeds([r["collisions_diff"] for r in per_seed], False),
    }
    pooled = pooled_vs_pid(pid_rows, seed_rows)
    bar, verdict = judge(per_seed, len(seeds))
    hist = {f"seed {s}": [eval_history(args.work / f"seed_{s}" / "runs" / n)
                          for n in stage_names(args.work / f"seed_{s}")]
            for s in seeds if (args.work / f"seed_{s}" / "runs").is_dir()}  # fmt: skip
    names = next((stage_names(args.work / f"seed_{s}") for s in seeds
                  if (args.work / f"seed_{s}" / "runs").is_dir()), [])  # fmt: skip
    curves = {}
    for metric in ("success_rate_strict", "mean_return"):
        points, bounds = learning_curves(hist, metric)
        curves[metric] = {"points": points, "stage_boundaries": bounds, "stages": names}
    pid_strict = {c: strict_of(r["per_episode"]) for c, r in pid_rows.items()}
    print_tables(per_seed, pid_strict, metrics, pooled, bar, verdict, missing, args.rows)
    rl = "rl"  # the commands as a person would type them
    config = {
        "recipe": args.recipe,
        "seeds": seeds,
        "evaluated": [r["seed"] for r in per_seed],
        "missing": {str(k): v for k, v in missing.items()},
        "complete": not missing,
        "work": str(args.work),
        "eval_dir": str(args.eval_dir),
        "episodes": args.episodes,
        "stress_episodes": args.stress_episodes,
        "eval_seed": args.seed,
        "rows": list(args.rows),
        "quick": args.quick,
        "bootstrap": {
            "resamples": N_RESAMPLES,
            "generator_seed": BOOT_SEED,
            "method": "percentile, 95 %",
        },
        "iqm": "mean of the middle 50 % of the sorted per-seed scores, the two straddling the "
        "quartile positions weighted by their fraction inside (= trim_mean(x, 0.25) when the "
        "count is a multiple of 4)",
        "pid": {
            "eval": eval_meta(pid_path),
            "env_differs_for_seeds": env_differs,
            "strict": pid_strict,
            "rows": {
                c: {k: v for k, v in r.items() if k != "per_episode"} for c, r in pid_rows.items()
            },
        },
        "aggregates": metrics,
        "pooled_vs_pid": pooled,
        "bar": bar,
        "verdict": verdict,
        "failures": {str(k): v for k, v in failures.items()},
        "commands": {
            "train": {
                str(s): shlex.join(train_cmd(rl, args.recipe, s, args.work / f"seed_{s}"))
                for s in seeds
            },
            "eval": {
                **{
                    str(s): shlex.join(
                        eval_cmd(args, args.work / f"seed_{s}", "policy", f"seed_{s}")
                    )
                    for s in seeds
                },
                "pid": shlex.join(eval_cmd(args, Path(pid_cfg.get("policy", "?")), "pid", "pid")),
            },
        },
        "provenance": {
            str(s): provenance_of(args.work / f"seed_{s}")
            for s in seeds
            if (args.work / f"seed_{s}").is_dir()
        },
        "learning_curves": curves,
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = save_results(args.name, per_seed, config, out_dir=args.out_dir)
    png = args.out_dir / f"{args.name}.png"
    plot(per_seed, pid_strict, metrics, curves, png)
    say(f"wrote {path} and {png}")


def _ci(v: Any, scale: float = 1.0, digits: int = 2) -> str:
    if not v or v[0] is None:
        return ""
    return f"{scale * v[0]:.{digits}f} ... {scale * v[1]:.{digits}f}"


def print_tables(per_seed, pid_strict, metrics, pooled, bar, verdict, missing, rows) -> None:
    hard = [c for c in rows if c != REF]
    table = []
    for r in per_seed:
        line = {"seed": r["seed"], "strict_%": 100 * r["strict"],
                "strict_ci95_%": _ci(r["strict_ci95"], 100, 0), "both_docked": r["both_docked"],
                "time_s": r["time_to_dock_s"], "pid_time_s": r["pid_time_to_dock_s"],
                "time_ratio": r["time_ratio"], "d_collisions": r["collisions_diff"],
                "d_collisions_ci95": _ci(r["collisions_diff_ci95"])}  # fmt: skip
        for c in hard:
            h = r["hard_rows"].get(c)
            line[f"{c} %"] = "" if h is None else 100 * h["strict"]
        table.append(line)
    pid = pid_strict.get(REF)
    if pid is not None:
        line = {"seed": "PID", "strict_%": 100 * pid["strict"],
                "strict_ci95_%": _ci(pid["strict_ci95"], 100, 0)}  # fmt: skip
        for c in hard:
            line[f"{c} %"] = 100 * pid_strict[c]["strict"] if c in pid_strict else ""
        table.append(line)
    cols = ["seed", "strict_%", "strict_ci95_%", "both_docked", "time_s", "pid_time_s",
            "time_ratio", "d_collisions", "d_collisions_ci95",
            *(f"{c} %" for c in hard)]  # fmt: skip
    print(f"\nper seed, {REF} row against the PID on the same episodes (d_: seed minus PID; "
          "time over the episodes both docked)")  # fmt: skip
    print(format_table(table, cols))
    agg = [{"metric": m, "seeds": a["seeds"], "worst": a["worst"],
            "worst_ci95": _ci(a["worst_ci95"]), "median": a["median"],
            "median_ci95": _ci(a["median_ci95"]), "iqm": a["iqm"],
            "iqm_ci95": _ci(a["iqm_ci95"], digits=3)}
           for m, a in metrics.items()]  # fmt: skip
    print("\nacross seeds (percentile bootstrap 95 % over seeds)")
    print(format_table(agg, list(agg[0])))
    if pooled:
        pt = [{"condition": p["condition"], "seeds": p["seeds"], "episodes": p["episodes"],
               "strict": p["strict"], "pid_strict": p["pid_strict"],
               "d_strict": p["paired_change"]["strict_change"],
               "mcnemar_p": p["paired_change"]["strict_mcnemar_p"], "time_ratio": p["time_ratio"],
               "d_collisions": p["collisions_diff"],
               "d_collisions_ci95": _ci(p["collisions_diff_ci95"])} for p in pooled]  # fmt: skip
        print("\nall seeds' episodes pooled against the PID's")
        print(format_table(pt, list(pt[0])))
    if missing:
        print("\nmissing seeds: " + "; ".join(f"{s}: {why}" for s, why in missing.items()))
    print("\nthe bar:")
    for b in bar:
        v = b["value"]
        shown = f"{v:.3f}" if isinstance(v, float) else str(v)
        print(f"  {b['verdict']:<10} {b['criterion']}: {shown}")
    print(f"verdict: {verdict}\n")


def plot(per_seed, pid_strict, metrics, curves, path: Path) -> None:
    """(a) and (b) the learning curves, (c) the per-seed camera strict success."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from uwdock.dockcore.io import atomic_path

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    titles = {"success_rate_strict": "(a) periodic evaluation: strict success",
              "mean_return": "(b) periodic evaluation: mean return"}  # fmt: skip
    for ax, (metric, title) in zip(axes[:2], titles.items(), strict=True):
        pts, bounds = curves[metric]["points"], curves[metric]["stage_boundaries"]
        for stage in sorted({p["stage"] for p in pts}):
            sp = [p for p in pts if p["stage"] == stage]
            x = np.array([p["x"] for p in sp]) / 1e6
            scale = 100 if metric == "success_rate_strict" else 1
            for label in sorted({k for p in sp for k in p["per_seed"]}):
                xs = [p["x"] / 1e6 for p in sp if label in p["per_seed"]]
                ys = [scale * p["per_seed"][label] for p in sp if label in p["per_seed"]]
                ax.plot(xs, ys, color="tab:blue", alpha=0.2, lw=0.8)
            ax.fill_between(x, [scale * p["min"] for p in sp], [scale * p["max"] for p in sp],
                            color="tab:blue", alpha=0.15, lw=0,
                            label="min-max over seeds" if stage == 0 else None)  # fmt: skip
            ax.plot(x, [scale * p["median"] for p in sp], color="tab:blue", lw=2,
                    label="median over seeds" if stage == 0 else None)  # fmt: skip
        for b in bounds:
            ax.axvline(b / 1e6, color="k", ls="--", lw=0.8)
        for x0, name in zip([0, *bounds], curves[metric].get("stages", []), strict=False):
            ax.text(x0 / 1e6, 0.98, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7,
                    va="top", color="0.3")  # fmt: skip
        ax.set_xlabel("training steps (millions; stages one after the other)")
        ax.set_ylabel("strict success (%)" if metric == "success_rate_strict" else "mean return")
        ax.set_title(title, fontsize=9)
        if pts:
            ax.legend(fontsize=7, loc="lower right")
    ax = axes[2]
    if per_seed:
        xs = np.arange(len(per_seed))
        v = np.array([100 * r["strict"] for r in per_seed])
        lo = np.array([100 * r["strict_ci95"][0] for r in per_seed])
        hi = np.array([100 * r["strict_ci95"][1] for r in per_seed])
        ax.errorbar(xs, v, yerr=[v - lo, hi - v], fmt="o", color="tab:blue", capsize=3,
                    label="seed (Wilson 95 %)")  # fmt: skip
        a = metrics["camera_strict"]
        at = len(per_seed) + 0.5
        ax.errorbar([at], [100 * a["iqm"]], yerr=[[100 * (a["iqm"] - a["iqm_ci95"][0])],
                    [100 * (a["iqm_ci95"][1] - a["iqm"])]], fmt="D", color="tab:green",
                    capsize=3, label="IQM (bootstrap 95 % over seeds)")  # fmt: skip
        ax.set_xticks([*xs, at], [*(str(r["seed"]) for r in per_seed), "IQM"])
    pid = pid_strict.get(REF)
    if pid is not None:
        ax.axhline(100 * pid["strict"], color="0.4", lw=1.2, label="PID (band: Wilson 95 %)")
        ax.axhspan(100 * pid["strict_ci95"][0], 100 * pid["strict_ci95"][1], color="0.5",
                   alpha=0.15, lw=0)  # fmt: skip
    ax.axhline(100 * BAR_STRICT, color="tab:red", ls=":", lw=1, label="bar: worst seed")
    ax.set_xlabel("training seed")
    ax.set_ylabel(f"{REF} row strict success (%)")
    ax.set_title("(c) held-out episodes, every seed", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recipe", default="shipped", help="a recipe of configs/recipes [shipped]")
    ap.add_argument("--seeds", default="0,1,2,3,4,5,6,7", help="training seeds (comma)")
    ap.add_argument("--work", type=Path, default=WORK, help=f"seeds' folders, evaluations [{WORK}]")
    ap.add_argument("--episodes", type=int, help="episodes of the camera row [100; quick 4]")
    ap.add_argument("--stress-episodes", type=int, help="episodes of a harder row [100; quick 2]")
    ap.add_argument("--seed", type=int, default=99000, help="episode k is seed + k [99000]")
    ap.add_argument("--rows", help=f"bench_docking rows (comma, with {REF}) [{','.join(ROWS)}]")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--skip-train", action="store_true", help="train nothing")
    ap.add_argument("--skip-eval", action="store_true", help="fly nothing: only the report")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 4/2 episodes, the camera row, WORK/eval_quick")  # fmt: skip
    ap.add_argument("--name", help="output name [recipe_seeds; quick: recipe_seeds_quick]")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args()
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"error: --seeds {args.seeds!r}: integers, comma-separated") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise SystemExit("error: --seeds: at least one, each once")
    args.episodes = args.episodes or (4 if args.quick else 100)
    args.stress_episodes = args.stress_episodes or (2 if args.quick else 100)
    rows = args.rows or (REF if args.quick else ",".join(ROWS))
    args.rows = [r.strip() for r in rows.split(",") if r.strip()]
    if REF not in args.rows:
        raise SystemExit(f"error: --rows must include {REF!r} (the bar is judged on it)")
    args.name = args.name or ("recipe_seeds_quick" if args.quick else "recipe_seeds")
    args.work = args.work.resolve()
    args.eval_dir = args.work / ("eval_quick" if args.quick else "eval")
    say(f"recipe {args.recipe}, seeds {seeds}, work {args.work}, evaluations {args.eval_dir}")
    failures: dict = {}
    if not args.skip_train:
        failures.update(train_step(args, seeds))
    if not args.skip_eval:
        failures.update(eval_step(args, seeds))
    report(args, seeds, failures)


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        print("interrupted: run the same command again to go on where it stopped", file=sys.stderr)
        sys.exit(130)
