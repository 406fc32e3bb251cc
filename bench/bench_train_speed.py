"""Training throughput: environment steps per second of a training recipe, by number of envs.

Usage::

    python bench/bench_train_speed.py [--config configs/scratch_error_model_precision_ppo.toml]
        [--envs 2] [--rollouts 8] [--repeats 3] [--seed 1] [--init-policy POLICY]
        [--name train_speed]

Each measurement trains the recipe (``rl.train.train``, no progress bar) from scratch in a
temporary run folder, in a fresh process (a process that has started SAPIEN cannot fork
working env workers on a GPU's Vulkan driver), with the periodic evaluation and checkpoints
switched off: once for one PPO rollout of ``n_steps x n_envs`` steps and once for ``rollouts``
rollouts. The difference gives the steady rate (steps/s of stepping and PPO updates) and the
start cost (processes, SAPIEN, the first observations). The table gives the median, min and max
of the steady rate over ``repeats`` pairs per env count, the median start cost, and the hours
the recipe's ``total_steps`` would take at the median (the recipe's own evaluations come on
top). More envs than the recipe's ``n_envs`` change the recipe (larger batches per update):
those rows measure the machine, not a validated recipe. ``--init-policy`` starts every run from
a trained policy (``rl train --init-policy``): an early policy's episodes are mostly free flight
far from the DS, a trained one's end in contact, which costs the physics more per step, so the
two bracket a training run's mix.

Writes ``bench/results/<name>.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import load_config, replace
from uwdock.rl.train import TrainConfig, train

OFF = 10**9  # an evaluation / checkpoint interval no run reaches


def _measure(
    cfg: TrainConfig, envs: int, rollouts: int, init: str | None = None
) -> tuple[int, float]:
    """Train ``rollouts`` rollouts with ``envs`` envs (from policy ``init`` if given); returns
    (steps, wall seconds)."""
    steps = rollouts * cfg.ppo.n_steps * envs
    run_cfg = replace(cfg, n_envs=envs, total_steps=steps, eval_every=OFF, checkpoint_every=OFF)
    with tempfile.TemporaryDirectory(prefix="bench_train_") as tmp:
        t0 = time.perf_counter()
        train(run_cfg, Path(tmp) / "run", progress=False, init_policy=init, note=lambda _m: None)
        return steps, time.perf_counter() - t0


def _child(cfg: TrainConfig, envs: int, rollouts: int, init, out: multiprocessing.Queue) -> None:
    out.put(_measure(cfg, envs, rollouts, init))


def measure(cfg: TrainConfig, envs: int, rollouts: int, init: str | None = None):
    """:func:`_measure` in a fresh (spawned, non-daemonic: it starts env workers) process."""
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=_child, args=(cfg, envs, rollouts, init, out))
    proc.start()
    proc.join()
    if proc.exitcode != 0:
        sys.exit(f"error: the measurement with {envs} envs failed (exit {proc.exitcode})")
    return out.get()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/scratch_error_model_precision_ppo.toml")
    ap.add_argument("--envs", default=None, help="comma-separated env counts [the recipe's]")
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--init-policy", default=None, help="start every run from this policy")
    ap.add_argument("--name", default="train_speed")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    if a.rollouts < 2 or a.repeats < 1:
        sys.exit("error: --rollouts must be at least 2 and --repeats at least 1")
    cfg = replace(load_config(TrainConfig, a.config, section="train"), seed=a.seed)
    env_counts = [int(e) for e in a.envs.split(",")] if a.envs else [cfg.n_envs]
    rows = []
    for envs in env_counts:
        rates, starts = [], []
        for k in range(a.repeats):
            steps_1, wall_1 = measure(cfg, envs, 1, a.init_policy)
            steps, wall_s = measure(cfg, envs, a.rollouts, a.init_policy)
            rates.append((steps - steps_1) / (wall_s - wall_1))
            starts.append(wall_1 - steps_1 / rates[-1])
            print(
                f"envs {envs}, pair {k + 1}/{a.repeats}: {steps_1:,} steps in {wall_1:.1f} s, "
                f"{steps:,} in {wall_s:.1f} s: {rates[-1]:.0f} steps/s, start {starts[-1]:.1f} s",
                flush=True,
            )
        med = statistics.median(rates)
        rows.append(
            {
                "envs": envs,
                "recipe": envs == cfg.n_envs,
                "steps_per_run": a.rollouts * cfg.ppo.n_steps * envs,
                "steps_per_s_median": med,
                "steps_per_s_min": min(rates),
                "steps_per_s_max": max(rates),
                "start_s_median": statistics.median(starts),
                "recipe_total_steps_h": cfg.total_steps / med / 3600.0,
            }
        )
    print(format_table(rows, list(rows[0])))
    bench_cfg = {
        "config": a.config,
        "seed": a.seed,
        "init_policy": a.init_policy,
        "rollouts": a.rollouts,
        "repeats": a.repeats,
        "n_steps": cfg.ppo.n_steps,
        "recipe_n_envs": cfg.n_envs,
        "recipe_total_steps": cfg.total_steps,
    }
    print("wrote", save_results(a.name, rows, bench_cfg, a.out_dir))


if __name__ == "__main__":
    main()
