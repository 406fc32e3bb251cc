"""Training curriculum: the success test's z tolerance and the spawn distance, eased over training.

The paper's reference code tightens the z tolerance of its docking test from 1.0 m to 0.1 m
while training: a policy that has learned to hover aligned above the DS is paid the success
reward early, and then learns to descend. With ``terminate_on = "strict"`` the same schedule
eases the strict test's peg height (``strict_peg_z_m``, 0.04 m at the end), which can pay a
policy only once it is aligned within the pegs' 5 cm: measured on the error model (seed 0), a
run with it was identical to one without it up to 200k steps, and its effect after that is not
measured (README, "Learning to dock from scratch"). A spawn-distance
curriculum starts the AUV close to the DS (horizontally) and widens the spawn box to the env's
full range. Both are pure functions of the number of environment steps taken, so a resumed run
follows the same schedule.

The level is pushed to every training env at the start of each rollout
(:meth:`rl.env.DockingEnv.set_curriculum`); evaluations always use the env's own test.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from uwdock.dockcore.domains import Interval


@dataclass(frozen=True)
class CurriculumConfig:
    """Curriculum of a training run (off when ``steps`` = 0).

    Attributes:
        steps: environment steps over which both schedules reach the env's own values; 0
            disables the curriculum.
        z_tolerance_start_m: the z tolerance of the episode-ending test at step 0 (m); it falls
            linearly to the task's own (:func:`curriculum_z_end`: the paper test's
            ``success_z_m``, as in the reference code 1.0 -> 0.1 m, or the strict test's
            ``strict_peg_z_m``).
        spawn_scale_start: the AUV's horizontal offset from the DS at spawn is scaled by this at
            step 0 (-); it grows linearly to 1 (the env's spawn box).
    """

    steps: Annotated[int, Interval(ge=0, le=10**10)] = 0
    z_tolerance_start_m: Annotated[float, Interval(gt=0, le=10)] = 1.0
    spawn_scale_start: Annotated[float, Interval(gt=0, le=1)] = 1.0


def curriculum_z_field(env_cfg) -> str:
    """The :class:`~uwdock.rl.task.DockingTaskConfig` field the curriculum eases: the z
    tolerance of the env's episode-ending test."""
    return "strict_peg_z_m" if env_cfg.terminate_on == "strict" else "success_z_m"


def curriculum_z_end(env_cfg) -> float:
    """The z tolerance (m) a curriculum ends at: the task's own value of that field."""
    return float(getattr(env_cfg.task, curriculum_z_field(env_cfg)))


def curriculum_level(
    cfg: CurriculumConfig, steps_done: int, z_tolerance_end_m: float
) -> tuple[float, float]:
    """(z tolerance (m), spawn scale (-)) after ``steps_done`` environment steps."""
    if cfg.steps <= 0:
        return z_tolerance_end_m, 1.0
    f = min(1.0, max(0.0, steps_done / cfg.steps))
    z = cfg.z_tolerance_start_m + (z_tolerance_end_m - cfg.z_tolerance_start_m) * f
    return z, cfg.spawn_scale_start + (1.0 - cfg.spawn_scale_start) * f
