"""Training curriculum: the success test's z tolerance and the spawn distance, eased over training.

The paper's reference code tightens the z tolerance of its docking test from 1.0 m to 0.1 m
while training: a policy that has learned to hover aligned above the DS is paid the success
reward early, and then learns to descend. With ``terminate_on = "strict"`` the same schedule
eases the strict test's peg height (``strict_peg_z_m``, 0.04 m at the end), which can pay a
policy only once it is aligned within the pegs' 5 cm: measured on the error model (seed 0), a
run with it was identical to one without it up to 200k steps, and its effect after that is not
measured (README, "Learning to dock from scratch"). A spawn-distance
curriculum starts the AUV close to the DS (horizontally) and widens the spawn box to the env's
full range. Near-seat starts (a reverse curriculum: Florensa et al., "Reverse Curriculum
Generation for Reinforcement Learning", CoRL 2017, start the agent where the goal is a few
actions away and move the starts outward) spawn a share of the training episodes aligned a
little above the seat, so the landing the success reward pays is met long before a policy
flying in from 3 m would find it; the share falls linearly to none. All schedules are pure
functions of the number of environment steps taken, so a resumed run follows the same
schedule.

The level is pushed to every training env at the start of each rollout
(:meth:`rl.env.docking_env.DockingEnv.set_curriculum`); evaluations always use the env's own test.
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
        near_start_fraction: share of the training episodes spawned near the seat at step 0
            (-); it falls linearly to 0 at ``near_start_steps``. 0: none (the spawn draws are
            then exactly those of a run without the option).
        near_start_steps: environment steps over which the near-seat share falls to 0; 0: the
            curriculum's ``steps``.
        near_start_height_m: (min, max) height of a near-seat start above the docked pose (m).
        near_start_xy_m: horizontal offset of a near-seat start from the docked pose, uniform
            within +- this along each DS axis (m).
        near_start_yaw_deg: yaw of a near-seat start from the docked yaw, uniform within +-
            this (deg). The defaults keep the hull clear of the guides and posts at every
            height (tests/test_curriculum.py).
    """

    steps: Annotated[int, Interval(ge=0, le=10**10)] = 0
    z_tolerance_start_m: Annotated[float, Interval(gt=0, le=10)] = 1.0
    spawn_scale_start: Annotated[float, Interval(gt=0, le=1)] = 1.0
    near_start_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.0
    near_start_steps: Annotated[int, Interval(ge=0, le=10**10)] = 0
    near_start_height_m: tuple[
        Annotated[float, Interval(gt=0, le=5)], Annotated[float, Interval(gt=0, le=5)]
    ] = (0.03, 0.6)
    near_start_xy_m: Annotated[float, Interval(ge=0, le=0.5)] = 0.02
    near_start_yaw_deg: Annotated[float, Interval(ge=0, le=45)] = 2.0

    def validate(self) -> None:
        lo, hi = self.near_start_height_m
        if lo > hi:
            raise ValueError(f"near_start_height_m: min {lo} m above max {hi} m")

    @property
    def near_start_box(self) -> tuple[float, float, float, float]:
        """(min height m, max height m, xy m, yaw deg) of a near-seat start, as
        :meth:`rl.env.docking_env.DockingEnv.set_curriculum` takes it."""
        lo, hi = self.near_start_height_m
        return float(lo), float(hi), float(self.near_start_xy_m), float(self.near_start_yaw_deg)


def curriculum_z_field(env_cfg) -> str:
    """The :class:`~uwdock.rl.env.task.DockingTaskConfig` field the curriculum eases: the z
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


def near_start_share(cfg: CurriculumConfig, steps_done: int) -> float:
    """The share of training episodes spawned near the seat after ``steps_done`` environment
    steps (0 when the curriculum is off or has no near-seat starts)."""
    if cfg.steps <= 0 or cfg.near_start_fraction <= 0:
        return 0.0
    horizon = cfg.near_start_steps or cfg.steps
    f = min(1.0, max(0.0, steps_done / horizon))
    return float(cfg.near_start_fraction * (1.0 - f))
