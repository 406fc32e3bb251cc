"""How long the one command takes: ``rl train --recipe NAME --seed N --out DIR``, from scratch.

Usage::

    python bench/bench_recipe_time.py [--recipe shipped] [--seed 0 | --seeds 0,1,...]
        [--repeats 1] [--work DIR] [--keep] [--name recipe_time]

Runs the command as a user would (the ``rl`` console script, a fresh process, a new folder),
``--repeats`` times for each seed (``--seed``, or each of ``--seeds``), each from scratch, and
times it whole (wall clock, start-up, both stages, their periodic evaluations and checkpoints
included) and per stage (from the stages' own run
records: the first and last modification of each stage's run folder). The table gives each
run, the median against the target (5 minutes on two idle cores), and the policy's
SHA-256 (the same seed gives the same bytes), and whether it is the shipped policy's
(``shipped_weights``: the shipped recipe and seed, retrained from scratch). The runs' folders
go to a temporary folder (``--work`` to keep them elsewhere, ``--keep`` not to remove them).

This machine's speed varies by the hour and the day, so each run also records what the
machine did meanwhile: the shares of all its CPUs' time that were idle (on an idle machine,
what the two training processes leave while one waits for the other) and stolen by the host
(``idle_pct``, ``steal_pct``, from ``/proc/stat``), and ``reference_s``, a fixed single-threaded
pure-Python workload timed just before the run (the median of five after a second of it
untimed): a slower core shows there, not every slowdown. The command runs the checkout's code
as it is when each run starts: the record says whether the commit and its uncommitted changes
stayed the same through every run (``source_unchanged``).

Writes ``bench/results/<name>.json`` (rows, machine, commit, packages) via
:func:`uwdock.dockcore.bench.save_results`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.provenance import git_commit_at_start, source_state

TARGET_MIN = 5.0
ROOT = Path(__file__).resolve().parent.parent
#: /proc/stat's CPU columns: user nice system idle iowait irq softirq steal
_IDLE, _IOWAIT, _STEAL = 3, 4, 7


def cpu_counters(stat: Path = Path("/proc/stat")) -> list[int] | None:
    """All CPUs' time counters (``/proc/stat``'s ``cpu`` line, its first eight columns), or
    None where there is no such file."""
    try:
        with stat.open(encoding="ascii") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != "cpu":
        return None
    return [int(x) for x in fields[1:9]]


def cpu_shares(before: list[int] | None, after: list[int] | None) -> dict[str, float | None]:
    """The shares (%) of the CPUs' time between two :func:`cpu_counters` readings that were
    idle (idle and waiting for I/O) and stolen by the host; None without both readings."""
    if before is None or after is None:
        return {"idle_pct": None, "steal_pct": None}
    d = [b - a for a, b in zip(before, after, strict=True)]
    total = sum(d)
    if total <= 0:
        return {"idle_pct": None, "steal_pct": None}
    return {
        "idle_pct": 100.0 * (d[_IDLE] + d[_IOWAIT]) / total,
        "steal_pct": 100.0 * d[_STEAL] / total,
    }


def _workload() -> float:
    t0 = time.perf_counter()
    acc = 0
    for i in range(2_000_000):
        acc = (acc + i * i) % 1_000_003
    return time.perf_counter() - t0


def reference_s(repeats: int = 5, warm_s: float = 1.0) -> float:
    """The median time (s) of a fixed single-threaded pure-Python workload, after ``warm_s``
    of it untimed (a CPU coming out of idle runs its first fraction of a second slower): how
    fast this machine runs now, to set beside the recipe's time."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < warm_s:
        _workload()
    return statistics.median(_workload() for _ in range(repeats))


def _stage_walls(out: Path) -> dict[str, float]:
    """Each stage's wall time (s): from its run folder's provenance (written first) to its
    DONE file (written last)."""
    walls = {}
    for run in sorted((out / "runs").iterdir()):
        first, last = run / "provenance.json", run / "DONE"
        if first.is_file() and last.is_file():
            walls[run.name] = last.stat().st_mtime - first.stat().st_mtime
    return walls


def shipped_weights(recipe: str, seed: int) -> str | None:
    """The SHA-256 of the shipped policy's weights when ``recipe`` and ``seed`` are those it
    was trained with (its ``recipe.json``), else None."""
    shipped = ROOT / "rl" / "policies" / "realistic_ppo"
    try:
        state = json.loads((shipped / "recipe.json").read_text(encoding="utf-8"))
        sums = (shipped / "checksums.sha256").read_text(encoding="utf-8").splitlines()
    except (OSError, ValueError):
        return None
    if (state.get("recipe"), state.get("seed")) != (recipe, seed):
        return None
    return next((ln.split()[0] for ln in sums if ln.split()[-1] == "weights.npz"), None)


def _median_or_none(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return statistics.median(known) if known else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recipe", default="shipped")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", default=None, help="comma-separated seeds, each timed (not --seed)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--work", type=Path, default=None, help="where the runs go [a temp folder]")
    ap.add_argument("--keep", action="store_true", help="keep the runs' folders")
    ap.add_argument("--name", default="recipe_time")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    if a.repeats < 1:
        sys.exit("error: --repeats must be at least 1")
    try:
        seeds = [int(s) for s in a.seeds.split(",")] if a.seeds else [a.seed]
    except ValueError:
        sys.exit(f"error: --seeds must be comma-separated integers, not {a.seeds!r}")
    if len(set(seeds)) != len(seeds) or min(seeds) < 0:
        sys.exit("error: --seeds must be distinct non-negative integers")
    rl = Path(sys.executable).with_name("rl")
    if not rl.exists():
        sys.exit(f"error: no rl console script next to {sys.executable}: pip install -e .")
    git_commit_at_start()  # the record names the tree the runs started from
    source = source_state()
    unchanged = True
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_recipe_"))
    rows = []
    runs = [(seed, k) for seed in seeds for k in range(a.repeats)]
    for n, (seed, k) in enumerate(runs):
        out = work / f"{a.recipe}_s{seed}_run{k}"
        if out.exists():
            sys.exit(f"error: {out} exists: give another --work (each run starts from scratch)")
        cmd = [str(rl), "train", "--recipe", a.recipe, "--seed", str(seed), "--out", str(out)]
        if source_state() != source:
            unchanged = False
            print("warning: the checkout changed since the first run", file=sys.stderr)
        ref_s = reference_s()
        print(f"run {n + 1}/{len(runs)}: {' '.join(cmd)}", flush=True)
        c0 = cpu_counters()
        t0 = time.perf_counter()
        res = subprocess.run(cmd)
        wall_s = time.perf_counter() - t0
        shares = cpu_shares(c0, cpu_counters())
        if res.returncode != 0:
            sys.exit(f"error: the command failed (exit {res.returncode})")
        weights = hashlib.sha256((out / "weights.npz").read_bytes()).hexdigest()
        first = json.loads((out / "recipe.json").read_text())["stages"][0]["name"]
        prov = json.loads((out / "runs" / first / "provenance.json").read_text())
        rows.append(
            {
                "seed": seed,
                "run": k,
                "wall_min": wall_s / 60.0,
                **{f"{s}_min": w / 60.0 for s, w in _stage_walls(out).items()},
                "weights_sha256": weights[:16],
                "shipped_weights": weights == shipped_weights(a.recipe, seed),
                "numerics": prov.get("machine", {}).get("numerics", {}).get("UWDOCK_NUMERICS"),
                **shares,
                "reference_s": ref_s,
            }
        )
        print(f"run {n + 1}: {wall_s / 60:.2f} min", flush=True)
        if not a.keep and a.work is None:
            shutil.rmtree(out, ignore_errors=True)
    unchanged = unchanged and source_state() == source
    med = statistics.median(r["wall_min"] for r in rows)
    longest = max(r["wall_min"] for r in rows)
    print(format_table(rows, list(rows[0])))
    print(
        f"median {med:.2f} min (longest {longest:.2f}) for the "
        f"{a.recipe} recipe from scratch over {len(rows)} runs (target {TARGET_MIN:g} min)"
    )
    bench_cfg = {
        "recipe": a.recipe,
        "seeds": seeds,
        "repeats": a.repeats,
        "command": "rl train --recipe RECIPE --seed SEED --out DIR",
        "wall_min_median": med,
        "wall_min_max": longest,
        "target_min": TARGET_MIN,
        "meets_target": med <= TARGET_MIN,
        # each seed's runs give one policy (a seed's repeats are byte for byte the same)
        "same_weights_every_run": all(
            len({r["weights_sha256"] for r in rows if r["seed"] == s}) == 1 for s in seeds
        ),
        "source_unchanged": unchanged,
        "reference_s_median": statistics.median(r["reference_s"] for r in rows),
        "idle_pct_median": _median_or_none([r["idle_pct"] for r in rows]),
        "steal_pct_max": max(
            (r["steal_pct"] for r in rows if r["steal_pct"] is not None), default=None
        ),
    }
    print("wrote", save_results(a.name, rows, bench_cfg, a.out_dir))
    if a.work is None and not a.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
