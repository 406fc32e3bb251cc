"""A policy on the batched simulator with the docking station's contact in PhysX and in the kernel.

Usage::

    python bench/bench_kernel_contact.py [--policy rl/policies/realistic_ppo] [--episodes 100]
        [--seed 91000] [--contacts shared,kernel] [--name kernel_contact_check]

The same held-out episodes (seeds ``seed .. seed + episodes - 1``, the policy's training env:
its USBL, navigation, error model, termination) are flown by the policy (deterministic) on
:func:`rl.evaluate.batched.batched_episodes` once per contact model: ``shared`` (PhysX, one shared
scene, what the shipped policy trained on), ``kernel`` (:mod:`uwdock.sim.kernel_contact`, no
PhysX) and/or ``own`` (PhysX per vehicle, bit-equal to the per-env env). Per contact model: strict
success with its Wilson 95 % interval, mean time to dock, IMU-detected collisions per episode,
failure modes and the wall time; then, paired on the episodes, the difference in collisions per
episode (kernel minus the first) with a bootstrap 95 % interval and the episodes whose outcome
differs. A policy trained on one contact model and docking as well on the other is the check
that the kernel's model is a faithful stand-in where it matters, not that it is PhysX.

Writes ``bench/results/<name>.json`` (rows + per-episode outcomes, machine, commit, packages).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import from_dict, replace
from uwdock.rl.evaluate.batched import batched_episodes
from uwdock.rl.policy.policy_io import load_policy, policy_train_settings
from uwdock.rl.train.training import TrainConfig

CONTACTS = ("shared", "kernel", "own")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", default="rl/policies/realistic_ppo")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=91000)
    ap.add_argument("--contacts", default="shared,kernel")
    ap.add_argument("--bootstrap", type=int, default=10000)
    ap.add_argument("--name", default="kernel_contact_check")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    contacts = [c.strip() for c in a.contacts.split(",") if c.strip()]
    if not contacts or any(c not in CONTACTS for c in contacts) or a.episodes < 1:
        sys.exit(f"error: --contacts takes {', '.join(CONTACTS)}; --episodes at least 1")
    model, vecnorm = load_policy(a.policy)
    train, _ = policy_train_settings(Path(a.policy) / "policy.zip")
    env_cfg = from_dict(TrainConfig, train).env
    rows, outcomes = [], {}
    for contact in contacts:
        cfg = replace(env_cfg, world=replace(env_cfg.world, batch_contact=contact))
        t0 = time.perf_counter()
        eps = batched_episodes(model, cfg, a.episodes, a.seed, vecnorm=vecnorm)
        wall = time.perf_counter() - t0
        ok = [bool(r["success_strict"]) for r in eps]
        k = int(sum(ok))
        ci = binomtest(k, len(ok)).proportion_ci(method="wilson")
        times = [r["time_to_dock_s"] for r in eps if r.get("time_to_dock_s") is not None]
        modes: dict[str, int] = {}
        for r in eps:
            modes[str(r.get("failure_mode"))] = modes.get(str(r.get("failure_mode")), 0) + 1
        outcomes[contact] = {
            "strict": ok,
            "collisions": [int(r["collisions"]) for r in eps],
            "time_to_dock_s": [r.get("time_to_dock_s") for r in eps],
        }
        rows.append(
            {
                "contact": contact,
                "episodes": len(eps),
                "strict": k / len(eps),
                "strict_ci95_low": ci.low,
                "strict_ci95_high": ci.high,
                "time_to_dock_s_mean": float(np.mean(times)) if times else None,
                "collisions_per_episode": float(np.mean(outcomes[contact]["collisions"])),
                "failure_modes": modes,
                "wall_s": wall,
            }
        )
        print(f"{contact}: {k}/{len(eps)} strict in {wall:.1f} s", flush=True)
    print(format_table(rows, [c for c in rows[0] if c != "failure_modes"]))
    paired = {}
    base = contacts[0]
    rng = np.random.default_rng(0)
    for contact in contacts[1:]:
        d = np.array(outcomes[contact]["collisions"]) - np.array(outcomes[base]["collisions"])
        boot = rng.choice(d, size=(a.bootstrap, len(d))).mean(axis=1)
        flips = [
            i
            for i, (x, y) in enumerate(
                zip(outcomes[base]["strict"], outcomes[contact]["strict"], strict=True)
            )
            if x != y
        ]
        paired[f"{contact}_minus_{base}"] = {
            "collisions_mean": float(d.mean()),
            "collisions_ci95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
            "outcome_differs_episodes": flips,
        }
        print(
            f"{contact} - {base}: collisions {d.mean():+.2f} per episode "
            f"({paired[f'{contact}_minus_{base}']['collisions_ci95'][0]:+.2f} ... "
            f"{paired[f'{contact}_minus_{base}']['collisions_ci95'][1]:+.2f}); outcome differs "
            f"in {len(flips)} of {a.episodes} episodes"
        )
    cfg_out = {
        "policy": a.policy,
        "episodes": a.episodes,
        "seed": a.seed,
        "contacts": contacts,
        "paired": paired,
        "outcomes": outcomes,
    }
    print("wrote", save_results(a.name, rows, cfg_out, a.out_dir))


if __name__ == "__main__":
    main()
