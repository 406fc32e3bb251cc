"""The shipped policy docking over the wire against in-process evaluation, on the same seeds.

Usage::

    python bench/bench_vehicle_wire.py [--episodes 30] [--seed 91000] [--image-format raw]
                                       [--json] [--out-dir DIR]

Runs the exported shipped policy (``rl/policies/realistic_ppo/policy.onnx``) two ways on the
held-out episode seeds ``seed ... seed + episodes - 1`` (camera in the loop, the policy's
training env: mems-ahrs-dvl navigation, EvoLogics USBL):

* in process: ``rl eval``'s episode loop (:func:`uwdock.rl.evaluate.episodes.run_episodes`);
* over the wire: ``rl node`` and ``sim vehicle`` as two processes on a loopback DDS domain,
  lock-step on simulated time (``--clock sim``, ``rl/deploy/profiles/sim.toml``).

Reports each way's strict success with its Wilson 95 % interval, mean time to dock and
collisions, how many episodes have the same outcome (strict success, steps, collisions, time to
dock) both ways, and the wall time per episode. ``--image-format compressed`` sends the frames
as JPEG (quality 90) instead: outcomes then differ from in-process (the frames differ), and the
success rates are compared by their intervals.

Writes ``bench/results/vehicle_wire[_compressed].json`` (rows, per-episode pairs, machine,
commit).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import replace
from uwdock.rl.evaluate.episodes import run_episodes
from uwdock.rl.policy.env_settings import command_env
from uwdock.rl.policy.policy_io import OnnxPolicy

ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "rl" / "policies" / "realistic_ppo" / "policy.onnx"
PROFILE = ROOT / "rl" / "deploy" / "profiles" / "sim.toml"
SAME = ("success_strict", "steps", "collisions", "time_to_dock_s")


def wilson(k: int, n: int) -> tuple[float, float]:
    """Wilson 95 % interval of a proportion k / n."""
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def in_process(episodes: int, seed: int) -> tuple[list[dict], float]:
    resolved = command_env(str(POLICY), defaults={"terminate_on": "strict"})
    cfg = replace(resolved.cfg, obs_source="camera")
    t0 = time.perf_counter()
    res = run_episodes(
        OnnxPolicy(POLICY), cfg, episodes, seed=seed, record=False,
        progress=lambda k, n: print(f"in process: {k}/{n}", file=sys.stderr),
    )  # fmt: skip
    return res.episodes, time.perf_counter() - t0


def over_the_wire(episodes: int, seed: int, image_format: str) -> tuple[list[dict], float]:
    domain = 100 + os.getpid() % 120
    with tempfile.TemporaryDirectory(prefix="uwdock-wire-") as tmp:
        profile = Path(tmp) / "node.toml"
        text = PROFILE.read_text()
        if image_format == "compressed":
            text = text.replace("[node.topics]\n", '[node.topics]\nimage_format = "compressed"\n')
        profile.write_text(text)
        uwdock = [sys.executable, "-m", "uwdock.cli"]
        common = ["--clock", "sim", "--domain-id", str(domain), "--config", str(profile)]
        node = subprocess.Popen(
            [*uwdock, "rl", "node", "--armed", *common, "--policy", str(POLICY)],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        t0 = time.perf_counter()
        try:
            subprocess.run(
                [*uwdock, "sim", "vehicle", *common, "--policy", str(POLICY), "--seed", str(seed),
                 "--episodes", str(episodes), "--out", str(Path(tmp) / "veh")],
                check=True, text=True,
            )  # fmt: skip
        finally:
            wall = time.perf_counter() - t0
            node.terminate()
            node.communicate(timeout=60)
        with open(Path(tmp) / "veh" / "episodes.csv") as fh:
            rows = list(csv.DictReader(fh))
    for r in rows:
        r["success_strict"] = r["success_strict"] == "True"
        r["steps"], r["collisions"] = int(r["steps"]), int(r["collisions"])
        r["time_to_dock_s"] = float(r["time_to_dock_s"]) if r["time_to_dock_s"] else None
    return rows, wall


def summary(label: str, rows: list[dict], wall_s: float) -> dict:
    n = len(rows)
    k = sum(bool(r["success_strict"]) for r in rows)
    lo, hi = wilson(k, n)
    times = [r["time_to_dock_s"] for r in rows if r["time_to_dock_s"] is not None]
    return {
        "way": label,
        "episodes": n,
        "strict": k / n,
        "strict_ci95": f"{lo:.2f}-{hi:.2f}",
        "mean_time_to_dock_s": float(np.mean(times)) if times else None,
        "mean_collisions": float(np.mean([r["collisions"] for r in rows])),
        "wall_s_per_episode": wall_s / n,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--seed", type=int, default=91000)
    ap.add_argument("--image-format", choices=["raw", "compressed"], default="raw")
    ap.add_argument("--json", action="store_true", help="print one JSON line last")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    if not 1 <= a.episodes <= 1000:
        ap.error("--episodes must be 1 ... 1000")
    local, t_local = in_process(a.episodes, a.seed)
    wire, t_wire = over_the_wire(a.episodes, a.seed, a.image_format)
    pairs = [
        {
            "seed": int(w["seed"]),
            "same": all(w[key] == loc[key] for key in SAME),
            **{f"wire_{key}": w[key] for key in SAME},
            **{f"in_process_{key}": loc[key] for key in SAME},
        }
        for w, loc in zip(wire, local, strict=True)
    ]
    rows = [summary("in process (rl eval)", local, t_local), summary("over DDS", wire, t_wire)]
    same = sum(p["same"] for p in pairs)
    cols = ["way", "episodes", "strict", "strict_ci95", "mean_time_to_dock_s", "mean_collisions",
            "wall_s_per_episode"]  # fmt: skip
    print(format_table(rows, cols))
    print(f"same outcome episode by episode: {same} of {len(pairs)} (seeds {a.seed}+)")
    name = "vehicle_wire" + ("_compressed" if a.image_format == "compressed" else "")
    config = {"episodes": a.episodes, "seed": a.seed, "image_format": a.image_format,
              "policy": str(POLICY.relative_to(ROOT)), "profile": str(PROFILE.relative_to(ROOT)),
              "same_outcome": same, "pairs": pairs}  # fmt: skip
    path = save_results(name, rows, config, a.out_dir)
    print(f"wrote {path}")
    if a.json:
        print(json.dumps({"same_outcome": same, "episodes": len(pairs), "rows": rows}))


if __name__ == "__main__":
    main()
