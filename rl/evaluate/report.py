"""``rl eval`` output folder: summary.json, episodes.csv, the paper's figures, videos, stress."""

from __future__ import annotations

import csv
import io
import json
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from uwdock.dockcore.cli import interrupt_name
from uwdock.dockcore.config import replace, to_dict
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_json, atomic_write_text
from uwdock.dockcore.outdir import claim_output_dir, tracked_outputs
from uwdock.dockcore.pool import PoolConfig, preflight
from uwdock.dockcore.provenance import provenance
from uwdock.rl.env.config import EnvConfig, check_env_files
from uwdock.rl.env.docking_env import SOURCE_CLASSES
from uwdock.rl.evaluate.episodes import (
    PARTIAL_EVAL_DIR,
    EpisodeStore,
    EpisodeTrace,
    episodes_key,
    run_episodes_parallel,
)
from uwdock.rl.policy.policy_io import load_controller
from uwdock.sim.thrusters import ThrusterRandomisation
from uwdock.sim.vehicle import VehicleRandomisation
from uwdock.sim.water import PRESET_ORDER


def csv_text(rows: list[dict[str, Any]]) -> str:
    """``episodes.csv``'s text: one row per episode, the first row's keys as the header."""
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return buf.getvalue()


def plot_trajectories(traces: list[EpisodeTrace], rows: list[dict], path: Path) -> None:
    """Top view of every episode relative to its DS (green: docked, red: not)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    for tr, row in zip(traces, rows, strict=True):
        if not tr.pos_body_m:
            continue
        p = np.asarray(tr.pos_body_m) - np.asarray(tr.pos_ds_m)
        ax.plot(
            p[:, 1], p[:, 0], color="tab:green" if row["success"] else "tab:red", lw=0.8, alpha=0.7
        )
        ax.plot(p[0, 1], p[0, 0], "o", color="grey", ms=3)
    ax.add_patch(plt.Rectangle((-1.14, -0.97), 2.28, 1.94, fill=False, color="k", lw=1.5))
    ax.plot(0, 0, "k+", ms=12)
    ax.set(
        xlabel="east of DS (m)",
        ylabel="north of DS (m)",
        aspect="equal",
        title="top-view trajectories (green: docked)",
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def plot_traces(tr: EpisodeTrace, path: Path, title: str) -> None:
    """Requested wrench and error per axis over one episode (true and observed error)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(tr.time_s)
    w = np.asarray(tr.wrench)
    et, eo = np.asarray(tr.e_true), np.asarray(tr.e_obs)
    fig, axes = plt.subplots(4, 2, figsize=(11, 8), sharex=True)
    names = ["x (m)", "y (m)", "z (m)", "yaw (rad)"]
    wnames = ["Fx (N)", "Fy (N)", "Fz (N)", "Mz (N m)"]
    widx = [0, 1, 2, 5]
    for i in range(4):
        axes[i, 0].plot(t, et[:, i], label="true")
        axes[i, 0].plot(t, eo[:, i], label="observed", alpha=0.7)
        axes[i, 0].set_ylabel(f"e_{names[i]}")
        axes[i, 1].plot(t, w[:, widx[i]], color="tab:purple")
        axes[i, 1].set_ylabel(wnames[i])
    det = np.asarray(tr.detected, dtype=float)
    axes[0, 0].fill_between(
        t,
        axes[0, 0].get_ylim()[0],
        axes[0, 0].get_ylim()[1],
        where=det > 0,
        color="tab:green",
        alpha=0.1,
        label="DS detected",
    )
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    axes[-1, 1].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def plot_eval_history(history_path: Path, path: Path) -> Path | None:
    """Training curve from a run's ``eval_history.jsonl``: paper and strict success, time to
    dock and collisions against environment steps (each new best checkpoint marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(line) for line in Path(history_path).read_text().splitlines() if line]
    if not rows:
        return None
    step = np.array([r["step"] for r in rows], dtype=float)

    def col(key: str) -> np.ndarray:
        return np.array([np.nan if r.get(key) is None else r[key] for r in rows], dtype=float)

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    ax = axes[0]
    ax.plot(step, 100 * col("success_rate"), "o-", label="paper")
    ax.plot(step, 100 * col("success_rate_strict"), "s-", label="strict")
    best = np.array([bool(r.get("best")) for r in rows])
    ax.plot(step[best], 100 * col("success_rate")[best], "k*", ms=10, label="new best (kept)")
    ax.set(xlabel="env steps", ylabel="success (%)", ylim=(-3, 103), title="evaluation success")
    ax.legend(loc="lower right", fontsize=8)
    axes[1].plot(step, col("mean_time_to_dock_s"), "o-")
    axes[1].set(xlabel="env steps", ylabel="s", title="mean time to dock")
    axes[2].plot(step, col("mean_collisions"), "o-", color="tab:red")
    axes[2].set(xlabel="env steps", ylabel="per episode", title="IMU-detected collisions")
    for a in axes:
        a.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    return Path(path)


STRESS_CURRENTS_MPS = (0.0, 0.1, 0.2, 0.3)
STRESS_THRUSTER_ERRORS_M = (0.0, 0.02, 0.05)


def stress_tables(
    policy: str, env_cfg: EnvConfig, episodes: int, seed: int, workers: int = 1,
    backend: str = "local", ray_address: str | None = None,
) -> dict[str, list[dict[str, Any]]]:  # fmt: skip
    """Graded stress: current speed (random direction), water preset, thruster placement.

    One progress bar over all rows, its label naming the row being run."""
    rows: list[tuple[str, str, Any, EnvConfig]] = []
    for speed in STRESS_CURRENTS_MPS:
        cur = replace(
            env_cfg.world.current,
            mode="random",
            range_x_mps=(-speed, speed),
            range_y_mps=(-speed, speed),
        )
        cfg = replace(env_cfg, world=replace(env_cfg.world, current=cur))
        rows.append(("current", "current_max_mps", speed, cfg))
    if SOURCE_CLASSES[env_cfg.obs_source].needs.camera:  # the water acts on rendered frames
        for preset in PRESET_ORDER:
            cfg = replace(env_cfg, world=replace(env_cfg.world, water_preset=preset))
            rows.append(("water", "water", preset, cfg))
    for err in STRESS_THRUSTER_ERRORS_M:
        rnd = VehicleRandomisation(thrusters=ThrusterRandomisation(position_m=err))
        world = replace(env_cfg.world, randomise_vehicle=True, vehicle_randomisation=rnd)
        cfg = replace(env_cfg, world=world)
        rows.append(("thruster", "thruster_position_error_m", err, cfg))

    out: dict[str, list[dict[str, Any]]] = {"current": [], "water": [], "thruster": []}
    bar = tqdm(total=len(rows) * episodes, desc="stress", unit="ep")
    try:
        for table, name, value, cfg in rows:
            bar.set_description(f"stress {table} {value}")
            done = bar.n
            res = run_episodes_parallel(
                policy, cfg, episodes, seed, workers=workers, record=False,
                progress=lambda k, n, done=done: bar.update(done + k - bar.n),
                backend=backend, ray_address=ray_address,
            )  # fmt: skip
            out[table].append({name: value, **_short(res.summary)})
    finally:
        bar.close()
    return out


def _short(s: dict[str, Any]) -> dict[str, Any]:
    keys = (
        "episodes",
        "success_rate",
        "success_rate_strict",
        "mean_time_to_dock_s",
        "mean_collisions",
    )
    return {k: s[k] for k in keys}


def evaluate_to_folder(
    policy: str,
    env_cfg: EnvConfig,
    episodes: int,
    seed: int,
    out_dir: Path,
    video_episodes: tuple[int, ...] = (),
    stress: bool = False,
    stress_episodes: int = 20,
    workers: int = 1,
    backend: str = "local",
    ray_address: str | None = None,
    env_settings: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Run the evaluation and write the report folder; returns the summary.

    The summary names the sensor presets it ran (``usbl_preset``, ``nav_preset``) and, given
    ``env_settings`` (:meth:`uwdock.rl.policy.env_settings.ResolvedEnv.settings`), where each
    reported setting came from (``env_settings``: policy config, ``--config``, flag or default).

    ``workers`` processes (``backend = "local"``) or Ray actors (``"ray"``, on a local Ray
    instance or the cluster at ``ray_address``) run the episodes, handed out one at a time; the
    rows and the summary do not depend on either.

    Everything is checked (counts, filmed episodes, the policy file and its observation
    layout) before the folder is claimed (``rl eval``) and anything is written."""
    if episodes < 1 or workers < 1:
        raise DockError(f"need episodes >= 1 and workers >= 1, got {episodes} and {workers}")
    pool = PoolConfig(backend, workers, ray_address)
    try:
        pool.validate()
    except ValueError as exc:
        raise DockError(str(exc)) from None
    preflight(pool)  # before the folder is claimed
    bad = [k for k in video_episodes if not 0 <= k < episodes]
    if bad:
        raise DockError(f"--videos: episode {bad[0]} is not among the {episodes} episodes")
    check_env_files(env_cfg)
    _, _, label = load_controller(policy, env_cfg)  # fail fast on a bad policy
    with claim_output_dir(out_dir, "rl eval") as out, tracked_outputs(out) as files:
        try:
            summary = _evaluate_into(
                out, policy, label, env_cfg, episodes, seed, video_episodes, stress,
                stress_episodes, pool, env_settings,
            )  # fmt: skip
        except KeyboardInterrupt as exc:
            _mark_interrupted(out / "summary.json", exc, episodes)
            raise
        # what this run wrote: a rerun with fewer films or episodes removes the rest
        names = ["episodes.csv", "trajectories_top.png", "summary.json"]
        names += [f"traces_ep{k}.png" for k in sorted(set(video_episodes) | {0})]
        names += [f"camera_ep{k}{s}" for k in video_episodes for s in (".mp4", "_frames.jpg")]
        files.add(*(out / n for n in names if (out / n).is_file()))
        return summary


def _mark_interrupted(path: Path, exc: BaseException, episodes: int) -> None:
    """``summary.json`` of an evaluation stopped by SIGINT or SIGTERM: says so, in place of a
    previous run's report (which would otherwise sit beside this run's films and tables as if
    it were theirs). The episodes it finished are kept for the rerun (``PARTIAL_EVAL_DIR``)."""
    record = {
        "complete": False,
        "interrupted": interrupt_name(exc),
        "episodes": episodes,
        "resume": "run the same command again: it goes on from the episodes it finished",
    }
    try:
        atomic_write_json(path, record)
    except OSError:  # a full disk: the run still ends as interrupted, without the mark
        pass


def _evaluate_into(
    out: Path,
    policy: str,
    label: str,
    env_cfg: EnvConfig,
    episodes: int,
    seed: int,
    video_episodes: tuple[int, ...],
    stress: bool,
    stress_episodes: int,
    pool: PoolConfig,
    env_settings: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    workers = pool.workers
    bar = tqdm(total=episodes, desc=f"eval {env_cfg.obs_source}", unit="ep")
    t0 = time.perf_counter()
    try:
        res = run_episodes_parallel(
            policy,
            env_cfg,
            episodes,
            seed,
            workers=workers,
            record=True,
            video_episodes=video_episodes,
            video_dir=str(out),
            progress=lambda k, n: bar.update(k - bar.n),
            backend=pool.backend,
            ray_address=pool.ray_address,
            # finished episodes kept until the report is written: a rerun goes on from them
            store=EpisodeStore(out / PARTIAL_EVAL_DIR, episodes_key(policy, env_cfg, seed, True)),
        )
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    steps = sum(r["steps"] for r in res.episodes)
    summary = {
        "policy": label,
        "obs_source": env_cfg.obs_source,
        "usbl_preset": env_cfg.usbl.preset,
        "nav_preset": env_cfg.nav.preset,
        "water_preset": env_cfg.world.water_preset,
        "camera_width_px": env_cfg.world.camera_width_px,
        "terminate_on": env_cfg.terminate_on,
        **({"env_settings": env_settings} if env_settings is not None else {}),
        **res.summary,
        "wall_clock_s": wall,
        "control_steps_per_s": steps / wall,
        "workers": workers,
        "backend": pool.backend,
        **({"ray": res.ray_nodes} if res.ray_nodes else {}),
    }
    atomic_write_text(out / "episodes.csv", csv_text(res.episodes))
    plot_trajectories(res.traces, res.episodes, out / "trajectories_top.png")
    for k in sorted(set(video_episodes) | {0}):
        if k < len(res.traces):
            ok = "docked" if res.episodes[k]["success"] else "not docked"
            plot_traces(res.traces[k], out / f"traces_ep{k}.png", f"episode {k} ({ok})")
    if stress:
        summary["stress"] = stress_tables(
            policy, env_cfg, stress_episodes, seed, workers, pool.backend, pool.ray_address
        )
    record = provenance({"env": env_cfg}, extra={"summary": summary})
    atomic_write_json(
        out / "summary.json", {**summary, "config": to_dict(env_cfg), "provenance": record}
    )
    shutil.rmtree(out / PARTIAL_EVAL_DIR, ignore_errors=True)  # the report holds them now
    return summary
