"""A policy on the per-env and the batched simulator: the same spawns, its success on both.

Usage::

    python bench/bench_batch_equivalence.py [--policy rl/policies/scratch_error_model_ppo]
        [--episodes 100] [--seed 81000] [--name batch_equivalence]

Episode ``k`` of the per-env simulator (``rl.evaluate.episodes.run_episodes``: a ``DockingEnv``
reset with ``seed + k``) and env ``k`` of one :class:`rl.env.batch_env.BatchDockingEnv` of
``episodes`` envs (first reset with ``seed + k``: the same draws, so the same spawn, vehicle,
current and prior) run the policy deterministically in the policy's own training env (its
``config.toml``); only the per-step noise differs (each simulator draws its own). The table gives
per simulator the strict and paper success with Wilson 95 % intervals, the mean time to dock and
collisions, and the paired discordant counts (docked on one, not the other); the first episode of
each batch env is the one counted.

Writes ``bench/results/<name>.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from bench_docking import wilson_ci

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import replace
from uwdock.rl.evaluate.batched import batched_episodes
from uwdock.rl.evaluate.episodes import SB3Controller, run_episodes
from uwdock.rl.policy.policy_io import load_controller
from uwdock.rl.train.training import run_config


def summary(name: str, rows: list[dict], wall_s: float) -> dict:
    n = len(rows)
    strict = sum(r["success_strict"] for r in rows)
    paper = sum(r["success"] for r in rows)
    times = [r["time_to_dock_s"] for r in rows if r["time_to_dock_s"] is not None]
    lo, hi = wilson_ci(strict, n)
    plo, phi = wilson_ci(paper, n)
    return {
        "simulator": name,
        "episodes": n,
        "strict_pct": 100.0 * strict / n,
        "strict_ci": f"{100 * lo:.0f}-{100 * hi:.0f}",
        "paper_pct": 100.0 * paper / n,
        "paper_ci": f"{100 * plo:.0f}-{100 * phi:.0f}",
        "time_to_dock_s": float(np.mean(times)) if times else None,
        "collisions": float(np.mean([r["collisions"] for r in rows])),
        "wall_s": wall_s,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", default="rl/policies/scratch_error_model_ppo")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=81000)
    ap.add_argument(
        "--nav", default=None, help="the vehicle's navigation preset [the policy's training one]"
    )
    ap.add_argument("--name", default="batch_equivalence")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    if a.episodes < 1:
        sys.exit("error: --episodes must be at least 1")
    env_cfg = replace(run_config(a.policy).env, obs_privileged=False)
    if a.nav is not None:
        env_cfg = replace(env_cfg, nav={"preset": a.nav})
    model, vecnorm, label = load_controller(a.policy, env_cfg)
    ctrl = model if hasattr(model, "act") else SB3Controller(model, vecnorm)
    t0 = time.perf_counter()
    per_env = run_episodes(ctrl, env_cfg, a.episodes, a.seed, record=False).episodes
    t1 = time.perf_counter()
    batch = batched_episodes(ctrl, env_cfg, a.episodes, a.seed)
    t2 = time.perf_counter()
    rows = [summary("per-env", per_env, t1 - t0), summary("batched", batch, t2 - t1)]
    pairs = list(zip(per_env, batch, strict=True))
    only_per = sum(p["success_strict"] and not b["success_strict"] for p, b in pairs)
    only_bat = sum(b["success_strict"] and not p["success_strict"] for p, b in pairs)
    print(format_table(rows, list(rows[0])))
    print(f"strict: docked per-env only {only_per}, batched only {only_bat} (paired, same spawns)")
    cfg = {
        "policy": a.policy,
        "label": label,
        "episodes": a.episodes,
        "seed": a.seed,
        "obs_source": env_cfg.obs_source,
        "usbl": env_cfg.usbl.preset,
        "nav": env_cfg.nav.preset,
        "discordant_strict": {"per_env_only": only_per, "batched_only": only_bat},
    }
    print("wrote", save_results(a.name, rows, cfg, a.out_dir))


if __name__ == "__main__":
    main()
