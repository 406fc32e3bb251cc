"""A recipe's training seeds against the PID, condition by condition, on the same episodes.

Usage::

    python bench/seeds_vs_pid.py --pid PID.json --seeds S0.json S1.json S2.json \
        --name NAME [--labels "seed 0,seed 1,seed 2"] [--out-dir bench/results]

Every file is an output of ``bench/bench_docking.py`` flown with the same ``--seed`` (so episode
k is the same spawn in every file); ``PID.json`` holds the PID's rows (controller "pid"), each
seed file its policy's rows (controller "policy"). Per condition the table gives the PID's and
each seed's strict success (Wilson 95 %), and each seed's paired change against the PID on the
same episodes (``bench_docking.paired_change``: strict success with the exact McNemar p, time to
dock over the episodes both docked and collisions per episode, with bootstrap 95 % intervals);
then the seeds pooled (every seed's episodes paired with the PID's same episode). Writes
``<NAME>.json`` and ``<NAME>.png`` (strict success by condition, PID beside each seed, with the
intervals) in ``--out-dir``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from compare_docking import bench_docking_module  # bench/, beside this file

from uwdock.dockcore.bench import format_table, save_results

HERE = Path(__file__).resolve().parent


def _rows(path: Path, controller: str) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    data = json.loads(path.read_text(encoding="utf-8"))
    rows = {r["condition"]: r for r in data["rows"] if r["controller"] == controller}
    if not rows:
        raise SystemExit(f"error: {path} has no rows of controller {controller!r}")
    meta = {"file": str(path), "command": data.get("command"), "git": data.get("git"),
            "seed": data.get("bench_config", {}).get("seed")}  # fmt: skip
    return rows, meta


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pid", type=Path, required=True)
    ap.add_argument("--seeds", type=Path, nargs="+", required=True)
    ap.add_argument("--labels", help="comma-separated, one per --seeds file")
    ap.add_argument("--name", required=True)
    ap.add_argument("--out-dir", type=Path, default=HERE / "results")
    args = ap.parse_args()
    bd = bench_docking_module()
    n = len(args.seeds)
    labels = args.labels.split(",") if args.labels else [f"seed {i}" for i in range(n)]
    if len(labels) != len(args.seeds):
        raise SystemExit("error: --labels needs one label per --seeds file")
    pid, pid_meta = _rows(args.pid, "pid")
    seeds = [_rows(p, "policy") for p in args.seeds]
    metas = [m for _, m in seeds]
    if len({m["seed"] for m in [pid_meta, *metas]}) != 1:
        raise SystemExit("error: the files were flown from different --seed values")
    out, table = [], []
    for cond, p in pid.items():
        flown = [(lab, s[cond]) for lab, (s, _) in zip(labels, seeds, strict=True) if cond in s]
        if not flown:
            continue
        row: dict[str, Any] = {"condition": cond, "pid_strict": p["strict"],
                               "pid_strict_ci95": p["strict_ci95"], "seeds": {}}  # fmt: skip
        pooled_pid, pooled_pol = [], []
        for lab, r in flown:
            change = bd.paired_change(p["per_episode"], r["per_episode"])
            row["seeds"][lab] = {"strict": r["strict"], "strict_ci95": r["strict_ci95"],
                                 "episodes": r["episodes"], "failure_modes": r.get("failure_modes"),
                                 "vs_pid": change}  # fmt: skip
            # pooled: a seed's episode k paired with the PID's episode k (keys made unique)
            k0 = len(pooled_pol)
            pooled_pid += [{**e, "episode": k0 + e["episode"]} for e in p["per_episode"]]
            pooled_pol += [{**e, "episode": k0 + e["episode"]} for e in r["per_episode"]]
        row["pooled_vs_pid"] = bd.paired_change(pooled_pid, pooled_pol)
        out.append(row)
        for lab, s in row["seeds"].items():
            c = s["vs_pid"] or {}
            table.append({"condition": cond, "seed": lab, "strict": s["strict"],
                          "pid": p["strict"], **_short(c)})  # fmt: skip
        table.append({"condition": cond, "seed": "pooled", "strict": None, "pid": p["strict"],
                      **_short(row["pooled_vs_pid"] or {})})  # fmt: skip
    print(f"\n{n} seeds against the PID, paired episodes (d_: seed minus PID)")
    cols = ["condition", "seed", "strict", "pid", "d_strict", "mcnemar_p", "d_time_s",
            "d_time_ci95_s", "d_collisions", "d_collisions_ci95"]  # fmt: skip
    print(format_table(table, cols))
    config = {"pid": pid_meta, "seeds": dict(zip(labels, metas, strict=True))}
    path = save_results(args.name, out, config, out_dir=args.out_dir)
    _plot(out, labels, args.out_dir / f"{args.name}.png")
    print(f"wrote {path} and {args.name}.png")


def _short(c: dict[str, Any]) -> dict[str, Any]:
    """The table's columns of a :func:`bench_docking.paired_change` result."""

    def ci(v: Any) -> str:
        return "" if not v or v[0] is None else f"{v[0]:.2f} ... {v[1]:.2f}"

    return {"d_strict": c.get("strict_change"), "mcnemar_p": c.get("strict_mcnemar_p"),
            "d_time_s": c.get("time_change_s"), "d_time_ci95_s": ci(c.get("time_change_ci95_s")),
            "d_collisions": c.get("collisions_change"),
            "d_collisions_ci95": ci(c.get("collisions_change_ci95"))}  # fmt: skip


def _plot(rows: list[dict[str, Any]], labels: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = ["PID", *labels]
    width = 0.8 / len(series)
    fig, ax = plt.subplots(figsize=(max(5, 2.2 * len(rows)), 3.6))
    for j, name in enumerate(series):
        xs, ys, lo, hi = [], [], [], []
        for i, r in enumerate(rows):
            if name == "PID":
                v, ci = r["pid_strict"], r["pid_strict_ci95"]
            elif name in r["seeds"]:
                v, ci = r["seeds"][name]["strict"], r["seeds"][name]["strict_ci95"]
            else:
                continue
            xs.append(i + (j - (len(series) - 1) / 2) * width)
            ys.append(100 * v)
            lo.append(100 * (v - ci[0]))
            hi.append(100 * (ci[1] - v))
        ax.bar(xs, ys, width, yerr=[lo, hi], capsize=2, label=name,
               color="0.6" if name == "PID" else None)  # fmt: skip
    ax.set_xticks(range(len(rows)), [r["condition"] for r in rows])
    ax.set_ylabel("strict success (%)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=8, ncol=len(series))
    ax.set_title("Training seeds against the PID (same episodes; Wilson 95 %)", fontsize=9)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    tmp.replace(path)


if __name__ == "__main__":
    main()
