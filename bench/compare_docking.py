"""Two policies' docking benchmarks compared episode by episode (same rows, same seeds).

Usage::

    python bench/compare_docking.py --base BASE.json [BASE2.json ...] --other OTHER.json [...]
        --name NAME [--label-base A] [--label-other B] [--out-dir bench/results]

The files are outputs of ``bench/bench_docking.py`` (each row keeps its episodes' outcomes,
``per_episode``); each side's rows are pooled over its files (a condition and controller in
two files of one side is refused). For every (condition, controller) the two sides share,
and on the episodes both flew (the same episode index, so the same seed when both ran with the
same ``--seed``), ``OTHER`` is compared with ``BASE``: the change in strict success with an exact
McNemar test on the discordant episodes, and the paired change in time to dock over the episodes
both docked, with a bootstrap 95 % interval (``paired_change`` of ``bench_docking.py``). Each
output row also carries both sides' success, time to dock and collisions per episode, and the
file records every input's command, commit and seed. Writes ``<out-dir>/<NAME>.json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

from uwdock.dockcore.bench import format_table, save_results

HERE = Path(__file__).resolve().parent


def bench_docking_module():
    """``bench/bench_docking.py`` as a module (registered first: its dataclasses need it)."""
    mod = sys.modules.get("bench_docking")
    if mod is None:
        spec = importlib.util.spec_from_file_location("bench_docking", HERE / "bench_docking.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules["bench_docking"] = mod
        spec.loader.exec_module(mod)
    return mod


def _load_side(paths: list[Path]) -> dict[str, Any]:
    """The files of one side: their rows pooled, each tagged with its file."""
    rows, seen, sources = [], {}, []
    for path in paths:
        data = _load(path)
        for r in data["rows"]:
            key = (r.get("condition"), r.get("controller"))
            if key in seen:
                sys.exit(f"error: {key[0]!r} / {key[1]!r} is in both {seen[key]} and {path}")
            seen[key] = path
            rows.append({**r, "file": str(path)})
        sources.append((path, data))
    return {"rows": rows, "sources": sources}


def _load(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        sys.exit(f"error: {path}: not a readable benchmark JSON ({type(exc).__name__})")
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        sys.exit(f"error: {path}: no rows (not an output of bench/bench_docking.py)")
    return data


def _side(row: dict[str, Any]) -> dict[str, Any]:
    keys = ("file", "episodes", "strict", "paper", "time_to_dock_s", "collisions")
    return {k: row.get(k) for k in keys}


def compare(
    base: dict[str, Any], other: dict[str, Any], base_controller: str | None = None
) -> list[dict[str, Any]]:
    """Rows of ``other`` against the same (condition, controller) rows of ``base``; with
    ``base_controller``, against ``base``'s rows of that controller (e.g. the PID's)."""
    paired_change = bench_docking_module().paired_change
    index = {(r.get("condition"), r.get("controller")): r for r in base["rows"]}
    out = []
    for r in other["rows"]:
        b = index.get((r.get("condition"), base_controller or r.get("controller")))
        if b is None or "per_episode" not in b or "per_episode" not in r:
            continue
        change = paired_change(b["per_episode"], r["per_episode"])
        if change is None:
            continue
        out.append({
            "condition": r["condition"],
            "controller": r["controller"],
            "base": _side(b),
            "other": _side(r),
            **change,
        })  # fmt: skip
    return out


def _source(path: Path, data: dict[str, Any], label: str) -> dict[str, Any]:
    cfg = data.get("bench_config", {})
    return {
        "label": label,
        "file": str(path),
        "command": data.get("command"),
        "git": data.get("git"),
        "policy": cfg.get("policy"),
        "seed": cfg.get("seed"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", type=Path, nargs="+", required=True, help="the reference side")
    ap.add_argument("--other", type=Path, nargs="+", required=True, help="compared with it")
    ap.add_argument("--name", required=True)
    ap.add_argument(
        "--base-controller",
        choices=("policy", "pid"),
        help="compare with the base side's rows of this controller (default: the same one)",
    )
    ap.add_argument("--label-base", default="base")
    ap.add_argument("--label-other", default="other")
    ap.add_argument("--out-dir", type=Path, default=HERE / "results")
    a = ap.parse_args()
    base, other = _load_side(a.base), _load_side(a.other)
    seeds = {d.get("bench_config", {}).get("seed") for side in (base, other)
             for _, d in side["sources"]}  # fmt: skip
    if len(seeds) != 1:
        sys.exit(f"error: the benchmarks flew different seeds ({sorted(map(str, seeds))})")
    rows = compare(base, other, a.base_controller)
    if not rows:
        sys.exit("error: the two sides share no (condition, controller) row with episodes")
    flat = [
        {
            "condition": r["condition"],
            "controller": r["controller"],
            "episodes": r["episodes"],
            f"strict {a.label_base}": r["base"]["strict"],
            f"strict {a.label_other}": r["other"]["strict"],
            "mcnemar_p": r["strict_mcnemar_p"],
            "time_change_s": r["time_change_s"],
            "collisions_change": r["collisions_change"],
        }
        for r in rows
    ]
    print(format_table(flat, list(flat[0])))
    config = {
        "base": [_source(p, d, a.label_base) for p, d in base["sources"]],
        "other": [_source(p, d, a.label_other) for p, d in other["sources"]],
    }
    print(save_results(a.name, rows, config, a.out_dir))


if __name__ == "__main__":
    main()
