"""Start-up time of the commands: what ``<group> --help`` and importing the env cost.

Usage::

    python bench/bench_startup.py [--repeats 7] [--before DIR] [--out-dir DIR]

Each row is one command run in a fresh Python subprocess (the interpreter running this script,
``-c`` code that calls the function the console script runs, as ``[project.scripts]`` of the
tree's ``pyproject.toml`` names it, with ``--help``; output discarded): ``uwdock --help``,
``<group> --help`` for the six groups, and ``import uwdock.rl.env.docking_env`` (what every training
worker pays). The wall time of the whole subprocess is taken ``repeats`` times after one untimed
warm-up run (which also compiles the bytecode); the table gives the median and the spread in
seconds.

``--before DIR`` also times a checkout of the old layout (top-level packages ``perception``,
``rl``, ... instead of ``uwdock.perception``, run with ``DIR`` as working directory and on
``PYTHONPATH``), the same commands where they exist there, interleaved with the new ones run for
run so that both see the same machine load.

Writes ``bench/results/startup.json`` (rows + machine, commit, packages; the old checkout's
commit in the bench config).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent

#: (row label, console script whose entry point runs with ``--help``, or a module to import)
COMMANDS = (
    ("uwdock --help", "uwdock", None),
    *((f"{g} --help", g, None) for g in ("markers", "calibration", "perception")),
    *((f"{g} --help", g, None) for g in ("sim", "datasets", "rl")),
    ("import uwdock.rl.env.docking_env", None, "rl.env.docking_env"),
)
#: Modules by another name in the old layout (``--before``): the env was ``rl.env``.
OLD_MODULES = {"rl.env.docking_env": "rl.env"}


def console_scripts(tree: Path) -> dict[str, str]:
    """``[project.scripts]`` of the ``pyproject.toml`` in ``tree``: script -> ``module:function``
    (what the installed script runs)."""
    with (tree / "pyproject.toml").open("rb") as fh:
        return tomllib.load(fh)["project"].get("scripts", {})


def _spec(script: str | None, module: str | None, tree: Path, old: bool) -> dict | None:
    """The subprocess of one command in ``tree``: the new layout (``old`` False: modules under
    ``uwdock``) or an old checkout (top-level packages, on ``PYTHONPATH``); None where that tree
    has no such script."""
    if script is not None:
        target = console_scripts(tree).get(script)
        if target is None:
            return None
        mod, func = target.split(":")
        code = f"import sys; sys.argv = [{script!r}, '--help']; from {mod} import {func}; {func}()"
    else:
        code = f"import {OLD_MODULES.get(module, module) if old else 'uwdock.' + module}"
    if not old:
        return {"argv": [sys.executable, "-c", code], "cwd": str(tree)}
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return {"argv": [sys.executable, "-c", code], "cwd": str(tree), "env": env}


def _run_s(spec: dict) -> float:
    """Wall time (s) of one run; a failing command is an error, not a fast sample."""
    t0 = time.perf_counter()
    out = subprocess.run(
        spec["argv"], cwd=spec["cwd"], env=spec.get("env"), capture_output=True, timeout=300
    )
    dt = time.perf_counter() - t0
    if out.returncode != 0:
        err = out.stderr.decode(errors="replace").strip().splitlines()[-1:]
        raise SystemExit(f"{' '.join(spec['argv'][-1:])} exited {out.returncode}: {err}")
    return dt


def _stats(samples: list[float]) -> dict[str, float]:
    return {
        "median_s": statistics.median(samples),
        "min_s": min(samples),
        "max_s": max(samples),
    }


def measure(repeats: int, before: Path | None) -> list[dict]:
    """One row per command: ``after_*`` (this tree) and, with ``before``, ``before_*`` times."""
    specs = {
        label: {
            "after": _spec(script, module, ROOT, old=False),
            "before": before and _spec(script, module, before, old=True),
        }
        for label, script, module in COMMANDS
    }
    samples: dict[tuple[str, str], list[float]] = {}
    for rep in range(repeats + 1):  # run 0 is the warm-up
        for label, pair in specs.items():
            order = ("after", "before") if rep % 2 else ("before", "after")
            for which in order:
                if pair[which] is None:
                    continue
                dt = _run_s(pair[which])
                if rep:
                    samples.setdefault((label, which), []).append(dt)
    rows = []
    for label, _, _ in COMMANDS:
        row: dict = {"command": label}
        for which in ("before", "after"):
            if (label, which) in samples:
                row.update({f"{which}_{k}": v for k, v in _stats(samples[label, which]).items()})
        if "before_median_s" in row:
            row["after_over_before"] = row["after_median_s"] / row["before_median_s"]
        rows.append(row)
    return rows


def _git_commit(folder: Path) -> str:
    out = subprocess.run(
        ["git", "-C", str(folder), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    return out.stdout.strip() or "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per command")
    parser.add_argument("--before", type=Path, default=None, help="checkout of the old layout")
    parser.add_argument("--out-dir", type=Path, default=None)
    args = parser.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats must be at least 1")
    before = args.before.resolve() if args.before else None
    load_start = os.getloadavg()[0]
    rows = measure(args.repeats, before)
    cols = ["command", "after_median_s", "after_min_s", "after_max_s"]
    if before:
        cols[1:1] = ["before_median_s", "before_min_s", "before_max_s"]
        cols.append("after_over_before")
    print(format_table(rows, cols))
    config = {
        "repeats": args.repeats,
        "python": sys.executable,
        "before": str(before) if before else None,
        "before_commit": _git_commit(before) if before else None,
        "loadavg_1min_start": load_start,
        "loadavg_1min_end": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
    }
    path = save_results("startup", rows, config, args.out_dir)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
