"""Seeded evaluation episodes: summary, per-episode rows and traces for the figures."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from rl.config import EnvConfig


class Controller(Protocol):
    def reset(self) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...


class SB3Controller:
    """A stable-baselines3 policy (deterministic), with its observation normalisation."""

    def __init__(self, model, vecnorm=None) -> None:
        self.model = model
        self.vecnorm = vecnorm

    def reset(self) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        o = obs[None, :]
        if self.vecnorm is not None:
            o = self.vecnorm.normalize_obs(o)
        action, _ = self.model.predict(o, deterministic=True)
        return np.asarray(action[0], dtype=np.float64)


@dataclass
class EpisodeTrace:
    """Per-step record of one episode (world NED, body FRD)."""

    time_s: list[float] = field(default_factory=list)
    pos_body_m: list[np.ndarray] = field(default_factory=list)
    pos_ds_m: list[np.ndarray] = field(default_factory=list)
    wrench: list[np.ndarray] = field(default_factory=list)
    e_true: list[np.ndarray] = field(default_factory=list)
    e_obs: list[np.ndarray] = field(default_factory=list)
    detected: list[bool] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)


@dataclass
class EvalResult:
    summary: dict[str, Any]
    episodes: list[dict[str, Any]]
    traces: list[EpisodeTrace]


def _as_controller(policy, vecnorm) -> Controller:
    return policy if hasattr(policy, "act") else SB3Controller(policy, vecnorm)


def run_episodes(
    policy,
    env_cfg: EnvConfig,
    n_episodes: int,
    seed: int = 0,
    vecnorm=None,
    record: bool = True,
    video_episodes: tuple[int, ...] = (),
    progress=None,
) -> EvalResult:
    """Run ``n_episodes`` seeded episodes (episode k uses seed + k) and summarise them.

    Args:
        policy: a :class:`Controller` or an SB3 model.
        env_cfg: the environment (its ``obs_source`` decides what the policy sees).
        n_episodes: number of episodes.
        seed: seed of the first episode.
        vecnorm: observation normalisation of an SB3 model.
        record: keep per-step traces (for the figures).
        video_episodes: episode indices whose camera view is kept as frames.
        progress: optional callable(k, n) called after each episode.
    """
    from rl.env import DockingEnv

    ctrl = _as_controller(policy, vecnorm)
    env = DockingEnv(env_cfg, render_mode="rgb_array" if video_episodes else None)
    rows, traces = [], []
    try:
        for k in range(n_episodes):
            obs, info = env.reset(seed=seed + k)
            ctrl.reset()
            tr = EpisodeTrace()
            ret, collisions, steps = 0.0, 0, 0
            dock_time = None
            done = False
            while not done:
                a = ctrl.act(obs)
                obs, r, term, trunc, info = env.step(a)
                ret += r
                steps += 1
                collisions += int(info["collided"])
                if info["success_paper"] and dock_time is None:
                    dock_time = info["time_s"]
                if record:
                    tr.time_s.append(info["time_s"])
                    tr.pos_body_m.append(info["T_world_body"][:3, 3].copy())
                    tr.pos_ds_m.append(info["T_world_ds"][:3, 3].copy())
                    tr.wrench.append(np.asarray(a) * env._limits)
                    tr.e_true.append(np.append(info["e_true"], info["e_psi_true"]))
                    tr.e_obs.append(np.append(obs[0:3] * 5.0, obs[3] * math.pi))
                    tr.detected.append(info["detected"])
                if k in video_episodes:
                    frame = env.render()
                    if frame is not None:
                        tr.frames.append(frame)
                done = term or trunc
            e = info["e_true"]
            rows.append(
                {
                    "episode": k,
                    "seed": seed + k,
                    "success": bool(info["success_paper"]),
                    "success_strict": bool(info["success_strict"]),
                    "time_to_dock_s": dock_time,
                    "steps": steps,
                    "return": ret,
                    "collisions": collisions,
                    "final_e_xy_m": float(np.hypot(e[0], e[1])),
                    "final_e_z_m": float(abs(e[2])),
                    "final_e_yaw_deg": float(abs(math.degrees(info["e_psi_true"]))),
                }
            )
            traces.append(tr)
            if progress is not None:
                progress(k + 1, n_episodes)
    finally:
        env.close()
    return EvalResult(summarise(rows), rows, traces)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The summary of per-episode rows (success rates, time to dock, collisions, errors)."""
    n = len(rows)
    succ = [r for r in rows if r["success"]]
    times = [r["time_to_dock_s"] for r in succ if r["time_to_dock_s"] is not None]

    def med(key: str) -> float:
        return float(np.median([r[key] for r in rows])) if rows else float("nan")

    return {
        "episodes": n,
        "success_rate": len(succ) / n if n else 0.0,
        "success_rate_strict": sum(r["success_strict"] for r in rows) / n if n else 0.0,
        "mean_time_to_dock_s": float(np.mean(times)) if times else None,
        "mean_collisions": float(np.mean([r["collisions"] for r in rows])) if n else 0.0,
        "mean_return": float(np.mean([r["return"] for r in rows])) if n else 0.0,
        "final_e_xy_m_median": med("final_e_xy_m"),
        "final_e_z_m_median": med("final_e_z_m"),
        "final_e_yaw_deg_median": med("final_e_yaw_deg"),
    }
