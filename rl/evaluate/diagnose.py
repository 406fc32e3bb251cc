"""Reward and exploration diagnosis: what each reward term pays under a given controller.

PPO learns from the sum of the reward terms; when one term dwarfs the others at the policy's
initial noise, or the success that pays ``success_reward`` is never seen, PPO optimises the
wrong thing. :func:`diagnose` runs seeded episodes of several controllers (random Gaussian
actions like PPO's initial policy, the PID baseline, a trained policy) and reports, per
controller:

* each term's mean per step, mean sum per episode and worst step (``info["reward_terms"]``);
* how often the smoothness term outweighs the distance term;
* the share of raw (pre-clip) action components beyond +-1, per component (a policy that
  saturates its means escapes the smoothness term: a clipped action does not change);
* how often the episode ever meets the paper's success test with its position tolerances
  relaxed (the curriculum's z tolerance 1.0 -> 0.1 m; a wider horizontal tolerance), and the
  paper and strict success rates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from uwdock.calibration.frames import inv_T
from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.env.rewards import TERMS
from uwdock.rl.env.task import ds_visible, paper_success

#: (xy, z) position tolerances (m) of the paper's test (yaw and visibility unchanged) whose
#: first meeting is counted: the paper's own (0.07, 0.1), the curriculum's start (0.07, 1.0),
#: a wide one
TOLERANCES_M: tuple[tuple[float, float], ...] = ((0.07, 0.1), (0.07, 1.0), (0.25, 1.0))


class GaussianController:
    """Raw actions N(mean, std^2) per component, not clipped (the env clips): PPO's initial
    policy is this with mean ~ 0 and std = exp(log_std_init)."""

    def __init__(self, std: float, seed: int = 0, mean: float = 0.0) -> None:
        self.std, self.mean = float(std), float(mean)
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.mean + self.std * self.rng.standard_normal(6)


@dataclass
class _Tally:
    steps: int = 0
    episodes: int = 0

    def __post_init__(self) -> None:
        self.term_sum = dict.fromkeys(TERMS, 0.0)
        self.term_min = dict.fromkeys(TERMS, 0.0)
        self.episode_sums: dict[str, list[float]] = {t: [] for t in TERMS}
        self.smooth_beats_dist = 0
        self.beyond = np.zeros(6)
        self.met = np.zeros(len(TOLERANCES_M))
        self.paper = 0
        self.strict = 0
        self.lengths: list[int] = []


def diagnose(
    controllers: dict[str, Any],
    env_cfg: EnvConfig,
    n_episodes: int,
    seed: int = 0,
    progress=None,
) -> dict[str, dict[str, Any]]:
    """Run ``n_episodes`` seeded episodes (seeds ``seed + k``) of every controller.

    Args:
        controllers: name -> object with ``reset()`` and ``act(obs) -> raw action (6,)``.
        env_cfg: the environment.
        n_episodes: episodes per controller.
        seed: seed of episode 0 (every controller sees the same spawns).
        progress: optional callable(name, done, total).

    Returns:
        name -> summary (module docstring); per-step figures are means over all steps.
    """
    env = DockingEnv(env_cfg)
    relaxed = [replace(env_cfg.task, success_xy_m=xy, success_z_m=z) for xy, z in TOLERANCES_M]
    out: dict[str, dict[str, Any]] = {}
    try:
        for name, ctrl in controllers.items():
            t = _Tally()
            for k in range(n_episodes):
                obs, _ = env.reset(seed=seed + k)
                ctrl.reset()
                sums = dict.fromkeys(TERMS, 0.0)
                met = np.zeros(len(TOLERANCES_M), dtype=bool)
                n = 0
                while True:
                    raw = np.asarray(ctrl.act(obs), dtype=np.float64)
                    t.beyond += np.abs(raw) > 1.0
                    obs, _, term, trunc, info = env.step(np.clip(raw, -1.0, 1.0))
                    n += 1
                    for key, v in info["reward_terms"].items():
                        sums[key] += v
                        t.term_min[key] = min(t.term_min[key], v)
                    r = info["reward_terms"]
                    t.smooth_beats_dist += abs(r["smooth"]) > abs(r["dist"])
                    T_body_ds = inv_T(info["T_world_body"]) @ info["T_world_ds"]
                    visible = ds_visible(T_body_ds, env_cfg.task)
                    e, psi = info["e_true"], info["e_psi_true"]
                    met |= [paper_success(e, psi, visible, task) for task in relaxed]
                    if term or trunc:
                        break
                t.steps += n
                t.episodes += 1
                t.lengths.append(n)
                t.met += met
                t.paper += bool(info["success_paper"])
                t.strict += bool(info["success_strict"])
                for key in TERMS:
                    t.term_sum[key] += sums[key]
                    t.episode_sums[key].append(sums[key])
                if progress is not None:
                    progress(name, k + 1, n_episodes)
            out[name] = _summary(t)
    finally:
        env.close()
    return out


def _summary(t: _Tally) -> dict[str, Any]:
    return {
        "episodes": t.episodes,
        "steps": t.steps,
        "mean_episode_steps": float(np.mean(t.lengths)),
        "per_step_mean": {k: t.term_sum[k] / t.steps for k in TERMS},
        "per_step_min": dict(t.term_min),
        "per_episode_mean": {k: float(np.mean(v)) for k, v in t.episode_sums.items()},
        "per_episode_total_mean": float(
            np.mean(np.sum([t.episode_sums[k] for k in TERMS], axis=0))
        ),
        "smooth_beats_dist_share": t.smooth_beats_dist / t.steps,
        "raw_action_beyond_1_share": (t.beyond / t.steps).tolist(),
        "ever_met_share": {
            f"xy{xy:g}_z{z:g}": float(m / t.episodes)
            for (xy, z), m in zip(TOLERANCES_M, t.met, strict=True)
        },
        "success_paper": t.paper / t.episodes,
        "success_strict": t.strict / t.episodes,
    }
