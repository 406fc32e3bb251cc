"""Learning curves of training recipes: periodic evaluation success vs steps, seeds pooled.

Usage::

    python bench/learning_curves.py --recipe NAME RUN [RUN ...] [--recipe NAME RUN ...]
        [--metric success_rate] [--out-dir DIR] [--name learning_curves]

Each ``RUN`` is an ``rl train`` run folder (its ``eval_history.jsonl``: deterministic policy,
``eval_episodes`` fixed episodes every ``eval_every`` steps). Per recipe and evaluation step:
the mean over seeds, the min and max, and each seed's value. Writes
``bench/results/<name>.json`` and ``<name>.png`` (one line per recipe, the band between the
seeds' min and max).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from uwdock.dockcore.bench import RESULTS_DIR, format_table, save_results


def _history(run: Path) -> list[dict]:
    path = run / "eval_history.jsonl"
    if not path.is_file():
        raise SystemExit(f"error: {run} has no eval_history.jsonl (not an rl train run folder)")
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line]


def curves(recipes: dict[str, list[Path]], metric: str) -> list[dict]:
    rows = []
    for name, runs in recipes.items():
        by_step: dict[int, list[float]] = {}
        for run in runs:
            for h in _history(run):
                by_step.setdefault(int(h["step"]), []).append(float(h[metric]))
        for step in sorted(by_step):
            v = by_step[step]
            rows.append(
                {
                    "recipe": name,
                    "step": step,
                    "seeds": len(v),
                    "mean": sum(v) / len(v),
                    "min": min(v),
                    "max": max(v),
                    "values": v,
                }
            )
    return rows


def plot(rows: list[dict], metric: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name in dict.fromkeys(r["recipe"] for r in rows):
        rs = [r for r in rows if r["recipe"] == name]
        x = [r["step"] for r in rs]
        n = max(r["seeds"] for r in rs)
        ax.plot(x, [r["mean"] for r in rs], marker="o", label=f"{name} ({n} seed{'s' * (n > 1)})")
        ax.fill_between(x, [r["min"] for r in rs], [r["max"] for r in rs], alpha=0.2)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(metric.replace("_", " "))
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--recipe", nargs="+", action="append", required=True, metavar="NAME RUN")
    parser.add_argument("--metric", default="success_rate")
    parser.add_argument("--out-dir", type=Path, default=None)
    parser.add_argument("--name", default="learning_curves")
    args = parser.parse_args()
    recipes = {}
    for spec in args.recipe:
        if len(spec) < 2:
            raise SystemExit("error: --recipe takes a name and at least one run folder")
        recipes[spec[0]] = [Path(p) for p in spec[1:]]
    rows = curves(recipes, args.metric)
    print(format_table(rows, ["recipe", "step", "seeds", "mean", "min", "max"]))
    out_dir = args.out_dir or RESULTS_DIR
    plot(rows, args.metric, out_dir / f"{args.name}.png")
    config = {"metric": args.metric, "runs": {k: [str(p) for p in v] for k, v in recipes.items()}}
    print(f"wrote {save_results(args.name, rows, config, args.out_dir)} and {args.name}.png")


if __name__ == "__main__":
    main()
