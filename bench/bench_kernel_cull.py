"""The numba kernel's docking-station contact with the near-pair cull and without, on the steps a
policy flies.

Usage::

    python bench/bench_kernel_cull.py [--policy rl/policies/realistic_ppo] [--envs 32]
        [--steps 300] [--repeats 7] [--seed 5] [--name kernel_cull]

The policy flies ``--envs`` vehicles on the batched simulator with its training env and the
kernel's contact (``batch_contact = "kernel"``), its mean action plus Gaussian noise of standard
deviation exp(-1) (the recipe's initial exploration), episodes ending and resetting as in
training; every control step's arguments of :func:`uwdock.sim.fastpath.kernel_flight_all` are
kept. Then each kept step is run again with ``near_m`` = :data:`uwdock.sim.fastpath.PRISM_NEAR_M`
(the pairs near their prism, chosen again as the hull moves: the kernel as it runs) and with
``near_m = inf`` (every pair of the step tested at every substep: the kernel before the cull),
the two alternating over ``--repeats`` rounds. Per variant: the median, fastest and slowest
round in microseconds per vehicle and control step, the ratio to every-pair, and whether the
states and accelerations are the same bytes as the run's own.

Writes ``bench/results/<name>.json`` (rows, machine, commit, packages).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from uwdock.dockcore import numerics


def _fly(policy: str, n_envs: int, steps: int, seed: int) -> tuple[list, int]:
    """The kernel's arguments and results of every control step of the flight, and how many
    episodes ended."""
    import uwdock.sim.batch as batch
    from uwdock.dockcore.config import from_dict, replace
    from uwdock.rl.env.batch_env import BatchDockingEnv
    from uwdock.rl.evaluate.episodes import as_controller
    from uwdock.rl.policy.policy_io import load_policy, policy_train_settings
    from uwdock.rl.train.training import TrainConfig

    model, vecnorm = load_policy(policy)
    train, _ = policy_train_settings(Path(policy) / "policy.zip")
    env_cfg = from_dict(TrainConfig, train).env
    env_cfg = replace(env_cfg, world=replace(env_cfg.world, batch_contact="kernel"))
    ctrl = as_controller(model, vecnorm)
    kept = []
    real = batch.kernel_flight_all

    def keep(*args):
        before = [a.copy() if isinstance(a, np.ndarray) else a for a in args]
        real(*args)
        kept.append((before, args[2].copy(), args[6].copy()))

    env = BatchDockingEnv(env_cfg, n_envs, seed=seed, privileged=True)
    rng = np.random.default_rng(seed)
    ended = 0
    batch.kernel_flight_all = keep
    try:
        obs = env.reset()
        width = int(model.observation_space.shape[0])
        for k in range(steps):
            a = np.asarray(ctrl.act_batch(obs[:, :width]), dtype=float).reshape(n_envs, 6)
            env.step_async(np.clip(a + math.exp(-1.0) * rng.standard_normal(a.shape), -1, 1))
            obs, _, done, _ = env.step_columns()
            ended += int(done.sum())
            if (k + 1) % 50 == 0:
                print(f"flown {k + 1}/{steps} steps", file=sys.stderr, flush=True)
    finally:
        batch.kernel_flight_all = real
        env.close()
    return kept, ended


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", default="rl/policies/realistic_ppo")
    ap.add_argument("--envs", type=int, default=32)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--name", default="kernel_cull")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    if a.envs < 1 or a.steps < 1 or a.repeats < 1:
        sys.exit("error: --envs, --steps and --repeats must be at least 1")
    numerics.pin_before_loading()  # the kernel as training runs it

    from uwdock.dockcore.bench import format_table, save_results
    from uwdock.sim.fastpath import PRISM_NEAR_M, kernel_flight_all

    kept, ended = _fly(a.policy, a.envs, a.steps, a.seed)
    variants = {"near pairs": PRISM_NEAR_M, "every pair": math.inf}
    times: dict[str, list[float]] = {v: [] for v in variants}
    same = {v: True for v in variants}
    for near in variants.values():  # compiled for an explicit near_m before any timing
        kernel_flight_all(*[x.copy() if isinstance(x, np.ndarray) else x for x in kept[0][0]], near)
    for r in range(a.repeats):
        order = list(variants) if r % 2 == 0 else list(variants)[::-1]
        for name in order:
            total = 0.0
            for before, state, acc in kept:
                args = [x.copy() if isinstance(x, np.ndarray) else x for x in before]
                t0 = time.perf_counter()
                kernel_flight_all(*args, variants[name])
                total += time.perf_counter() - t0
                same[name] &= args[2].tobytes() == state.tobytes()
                same[name] &= args[6].tobytes() == acc.tobytes()
            times[name].append(1e6 * total / (len(kept) * a.envs))
        print(f"round {r + 1}/{a.repeats}", file=sys.stderr, flush=True)
    base = statistics.median(times["every pair"])
    rows = [
        {
            "kernel": name,
            "near_m": variants[name],
            "us_per_vehicle_step": statistics.median(t),
            "us_min": min(t),
            "us_max": max(t),
            "against_every_pair": statistics.median(t) / base,
            "same_bytes": same[name],
        }
        for name, t in times.items()
    ]
    print(format_table(rows, list(rows[0])))
    cfg = {
        "policy": a.policy,
        "envs": a.envs,
        "steps": a.steps,
        "repeats": a.repeats,
        "seed": a.seed,
        "episodes_ended": ended,
        "exploration_std": math.exp(-1.0),
        "rounds_us": times,
    }
    print("wrote", save_results(a.name, rows, cfg, a.out_dir))


if __name__ == "__main__":
    main()
