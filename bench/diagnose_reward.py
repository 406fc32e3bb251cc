"""Reward diagnosis: per-term reward magnitudes and success sightings under several controllers.

Usage::

    python bench/diagnose_reward.py [--episodes 20] [--seed 70000] [--source SOURCE]
        [--config configs/X.toml] [--smooth-over all|actuated] [--policy PATH ...]
        [--out-dir DIR] [--name NAME]

Controllers: Gaussian actions with std 1 (PPO's initial policy: ``log_std_init`` 0), std 0.37
(``log_std_init`` -1), the PID baseline, and each ``--policy`` (deterministic). Every controller
runs the same seeded episodes; a PPO policy acts with its Gaussian's mean before clipping (the
env clips), so means beyond +-1 show in the saturation columns. ``--config`` takes the
``[env]`` table of a training config (the reward and task of that recipe). See
:mod:`uwdock.rl.evaluate.diagnose` for the figures.

Writes ``bench/results/<name>.json`` (default ``reward_diagnosis``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=70_000)
    parser.add_argument("--source", default=None, help="override the observation source")
    parser.add_argument("--config", default=None, help="a training config (its [env] is used)")
    parser.add_argument(
        "--smooth-over",
        choices=["all", "actuated"],
        default=None,
        help="override the reward's smooth_over ('all': the paper's six-component formula)",
    )
    parser.add_argument("--policy", action="append", default=[])
    parser.add_argument("--out-dir", type=Path, default=None)
    parser.add_argument("--name", default="reward_diagnosis")
    args = parser.parse_args()

    from uwdock.dockcore.config import load_config, replace, to_dict
    from uwdock.rl.env.config import EnvConfig
    from uwdock.rl.evaluate.diagnose import GaussianController, diagnose
    from uwdock.rl.evaluate.episodes import SB3Controller
    from uwdock.rl.policy.baselines import PIDController
    from uwdock.rl.policy.policy_io import load_controller

    if args.config:
        from uwdock.rl.train.training import TrainConfig

        env_cfg = load_config(TrainConfig, args.config, section="train").env
    else:
        env_cfg = EnvConfig()
    if args.source:
        env_cfg = replace(env_cfg, obs_source=args.source)
    if args.smooth_over:
        env_cfg = replace(env_cfg, reward=replace(env_cfg.reward, smooth_over=args.smooth_over))
    controllers = {
        "gauss_std1": GaussianController(1.0, seed=args.seed),
        f"gauss_std{math.exp(-1):.2f}": GaussianController(math.exp(-1), seed=args.seed),
        "pid": PIDController.for_env(env_cfg),
    }
    for p in args.policy:
        ctrl, vecnorm, label = load_controller(p, env_cfg)
        if hasattr(ctrl, "act"):
            controllers[label] = ctrl
        else:  # PPO: the mean before clipping
            pre_clip = hasattr(ctrl.policy, "get_distribution")
            controllers[label] = SB3Controller(ctrl, vecnorm, pre_clip=pre_clip)
    t0 = time.perf_counter()

    def progress(name: str, done: int, total: int) -> None:
        if done == total or done % 5 == 0:
            print(f"  {name}: {done}/{total} episodes", file=sys.stderr, flush=True)

    res = diagnose(controllers, env_cfg, args.episodes, args.seed, progress)
    rows = []
    for name, s in res.items():
        row = {"controller": name}
        for k, v in s["per_step_mean"].items():
            row[f"{k}/step"] = v
        row["smooth_min"] = s["per_step_min"]["smooth"]
        row["return"] = s["per_episode_total_mean"]
        row["smooth>dist"] = s["smooth_beats_dist_share"]
        beyond = s["raw_action_beyond_1_share"]
        row["|a|>1 roll"] = beyond[3]
        row["|a|>1 yaw"] = beyond[5]
        for k, v in s["ever_met_share"].items():
            row[f"met {k}"] = v
        row["paper"] = s["success_paper"]
        row["strict"] = s["success_strict"]
        rows.append(row)
    print(format_table(rows, list(rows[0])))
    config = {
        "episodes": args.episodes,
        "seed": args.seed,
        "source": args.source,
        "smooth_over": env_cfg.reward.smooth_over,
        "config": args.config,
        "policies": args.policy,
        "wall_s": time.perf_counter() - t0,
        "env": to_dict(env_cfg),
        "detail": res,
    }
    print(f"wrote {save_results(args.name, rows, config, args.out_dir)}")


if __name__ == "__main__":
    main()
