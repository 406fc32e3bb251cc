"""Strict success by condition, the from-scratch recipe's training seeds beside the PID baseline.

Usage::

    python bench/plot_docking_summary.py [--name docking_summary_seeds]

Collects the rows of the committed docking benchmarks (``bench/bench_docking.py`` outputs in
``bench/results/``, every one flown on the episodes of seed 50000, camera in the loop unless the
condition says otherwise) named in :data:`SOURCES`, and draws one group of bars per condition:
the PID baseline, then each training seed of the shipped recipe (PPO from scratch on the
error model, stage 2), each with its Wilson 95 % interval and its episode count. A condition a
seed was not flown in has no bar for it. Writes ``<name>.png`` and ``<name>.json`` (the rows,
each with the file, commit and policy it came from) in ``bench/results/``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from uwdock.dockcore.bench import format_table, save_results

RESULTS = Path(__file__).resolve().parent / "results"

#: (series, file): the rows of ``file`` (controller "policy" for a seed, "pid" for the PID)
#: that feed ``series``. A (condition, series) found in two files keeps the one listed first.
SOURCES: tuple[tuple[str, str], ...] = (
    ("PID", "docking_scratch_headline.json"),
    ("PID", "docking_hard_pid.json"),
    ("seed 0", "docking_scratch_soft_camera.json"),
    ("seed 0", "docking_scratch_soft_camera_off.json"),
    ("seed 0", "docking_water_soft_policy.json"),
    ("seed 0", "docking_hard_soft_policy.json"),
    ("seed 0", "docking_fill_s0.json"),
    ("seed 1 (shipped)", "docking_water_shipped.json"),
    ("seed 1 (shipped)", "docking_hard_shipped.json"),
    ("seed 1 (shipped)", "docking_fill_s1.json"),
    ("seed 2", "docking_scratch_soft_camera_s2.json"),
    ("seed 2", "docking_hard_s2.json"),
    ("seed 2", "docking_fill_s2.json"),
)

CONDITIONS = (
    "camera",
    "camera off",
    "coastal",
    "turbid",
    "current 0.4",
    "long approach",
    "camera mount",
    "thrusters",
    "all",
)


def collect(results: Path = RESULTS) -> list[dict[str, Any]]:
    """One row per (condition, series) found in :data:`SOURCES`."""
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    for series, name in SOURCES:
        path = results / name
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            sys.exit(f"error: {path}: {type(exc).__name__}: {exc}")
        want = "pid" if series == "PID" else "policy"
        for r in data["rows"]:
            key = (r["condition"], series)
            if r["controller"] != want or r["condition"] not in CONDITIONS or key in rows:
                continue
            rows[key] = {
                "condition": r["condition"],
                "series": series,
                "episodes": r["episodes"],
                "strict": r["strict"],
                "strict_ci95": list(r["strict_ci95"]),
                "paper": r["paper"],
                "time_to_dock_s": r["time_to_dock_s"],
                "collisions": r["collisions"],
                "file": name,
                "commit": data["git"]["commit"],
                "policy": data["bench_config"].get("policy"),
                "seed": data["bench_config"].get("seed"),
            }
    return sorted(rows.values(), key=lambda r: (CONDITIONS.index(r["condition"]), r["series"]))


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from uwdock.dockcore.io import atomic_path

    conds = [c for c in CONDITIONS if any(r["condition"] == c for r in rows)]
    series = list(dict.fromkeys(s for s, _ in SOURCES))
    colours = {"PID": "0.55", "seed 0": "C0", "seed 1 (shipped)": "C1", "seed 2": "C2"}
    width = 0.8 / len(series)
    fig, ax = plt.subplots(figsize=(12, 4.2))
    for j, s in enumerate(series):
        label = s
        for i, c in enumerate(conds):
            r = next((r for r in rows if r["condition"] == c and r["series"] == s), None)
            if r is None:
                continue
            x = i - 0.4 + (j + 0.5) * width
            lo, hi = r["strict_ci95"]
            ax.bar(x, 100 * r["strict"], width, color=colours.get(s, f"C{j}"), label=label)
            label = None  # one legend entry per series
            err = np.array([[r["strict"] - lo], [hi - r["strict"]]]) * 100
            ax.errorbar(x, 100 * r["strict"], yerr=err, color="k", lw=0.8, capsize=2)
            ax.text(x, 2, str(r["episodes"]), ha="center", va="bottom", fontsize=6, rotation=90)
    ax.set_xticks(range(len(conds)), conds)
    ax.set_ylim(0, 105)
    ax.set_ylabel("strict success (%), Wilson 95 % CI")
    ax.set_title("Camera in the loop: PPO from scratch (3 training seeds) vs PID, episodes 50000+")
    ax.axhline(85, color="k", lw=0.5, ls=":")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--name", default="docking_summary_seeds")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    a = ap.parse_args()
    rows = collect()
    cols = ["condition", "series", "episodes", "strict", "paper", "time_to_dock_s", "file"]
    print(format_table(rows, cols))
    print(save_results(a.name, rows, {"sources": [list(s) for s in SOURCES]}, a.out_dir))
    plot(rows, a.out_dir / f"{a.name}.png")


if __name__ == "__main__":
    main()
