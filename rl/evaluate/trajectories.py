"""Docking trajectories to render: the vehicle poses of the PID baseline's seeded episodes, one
per control step, as time sequences, for fitting the error model's memory.

The env draws a DS pose per episode (position and yaw on the tank floor); the renderer of
``datasets render`` keeps its DS at the tank centre, axes along world NED's
(:func:`uwdock.sim.docking_station.default_T_worldned_ds`). What the camera sees of the DS
depends only on the vehicle pose relative to the DS, so each pose is moved with its DS into
the render world: ``T_render_body = T_render_ds @ inv(T_world_ds) @ T_world_body``. Poses whose
camera would then be outside the render tank (a far spawn on the DS's other side) are left out;
the step numbering keeps the gap, so no pair of frames across it counts as consecutive.

Pipeline (``README``, "error model with memory")::

    rl trajectories --out traj --episodes 30 --seed 0 \\
        --error-model rl/models/error_model_clear_tank_480.json
    datasets render --poses traj/poses.csv --water clear_tank --width 480 --workers 1 --out seq480
    rl fit-error-model seq480 --out error_model_ar1.json
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwdock.calibration.camera import resolve_camera
from uwdock.calibration.frames import inv_T
from uwdock.datasets.sequences import FrameSequences, check_sequences
from uwdock.datasets.synth import camera_outside_tank
from uwdock.dockcore.errors import DockError
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.policy.baselines import PIDController
from uwdock.sim.docking_station import DockingStationConfig, default_T_worldned_ds

__all__ = ["Trajectories", "record_pid_trajectories", "render_world_pose"]


@dataclass(frozen=True)
class Trajectories:
    """Recorded trajectories (module docstring).

    Attributes:
        poses: (N, 4, 4) float64 vehicle poses ``T_world_body`` (body FRD in the render
            world's NED, m), DS at ``default_T_worldned_ds``.
        sequences: which episode (``sequence``), control step (``step``) and time (``time_s``,
            s) each pose belongs to.
        episodes: per episode ``{"episode", "seed", "steps", "success_strict", "kept",
            "left_out"}`` (steps: env steps after the reset; kept/left_out: poses, the reset's
            included).
    """

    poses: np.ndarray
    sequences: FrameSequences
    episodes: list[dict[str, Any]]


def render_world_pose(
    T_world_body: np.ndarray, T_world_ds: np.ndarray, T_render_ds: np.ndarray
) -> np.ndarray:
    """(4, 4) the vehicle pose with the same pose relative to the DS in a world whose DS is at
    ``T_render_ds`` (all (4, 4), NED, m)."""
    return T_render_ds @ inv_T(T_world_ds) @ T_world_body


def record_pid_trajectories(
    env_cfg: EnvConfig,
    episodes: int,
    seed: int,
    on_episode: Callable[[dict[str, Any]], None] | None = None,
) -> Trajectories:
    """Run the PID baseline for ``episodes`` episodes (episode k reset with ``seed + k``) and
    keep every control step's vehicle pose, the reset's included, in the render world.

    Args:
        env_cfg: the env (its camera file and width name the camera the poses are checked
            with; render them with the same ``--camera`` / ``--width``).
        episodes: number of episodes (>= 1).
        seed: reset seed of episode 0.
        on_episode: called with each episode's summary row as it ends.

    Raises:
        DockError: no pose kept (every camera outside the render tank).
    """
    ds_cfg = DockingStationConfig(marker_set_path=env_cfg.world.marker_set_path)
    T_render_ds = default_T_worldned_ds(ds_cfg)
    _, T_body_cam = resolve_camera(env_cfg.world.camera_file, env_cfg.world.camera_width_px)
    poses: list[np.ndarray] = []
    labels: list[tuple[int, int, float]] = []
    rows: list[dict[str, Any]] = []
    env = DockingEnv(env_cfg)
    try:
        pid = PIDController.for_env(env_cfg)
        for k in range(episodes):
            obs, info = env.reset(seed=seed + k)
            pid.reset()
            row = {"episode": k, "seed": seed + k, "steps": 0, "kept": 0, "left_out": 0}
            step, done = 0, False
            while True:
                T = render_world_pose(info["T_world_body"], info["T_world_ds"], T_render_ds)
                if camera_outside_tank(T, T_body_cam, ds_cfg) is None:
                    poses.append(T)
                    labels.append((k, step, float(info["time_s"])))
                    row["kept"] += 1
                else:
                    row["left_out"] += 1
                if done:
                    break
                obs, _, term, trunc, info = env.step(pid.act(obs))
                step += 1
                done = term or trunc
            row["steps"] = step
            row["success_strict"] = bool(info["success_strict"])
            rows.append(row)
            if on_episode is not None:
                on_episode(row)
    finally:
        env.close()
    if not poses:
        raise DockError("no pose kept: every camera was outside the render tank")
    seq = np.asarray(labels, np.float64).T
    sequences = check_sequences(seq[0], seq[1], seq[2], len(poses), "trajectories")
    return Trajectories(np.stack(poses), sequences, rows)
