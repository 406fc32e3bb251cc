"""Training curriculum: the schedule, what it does to the env, and that training pushes it."""

from __future__ import annotations

import numpy as np
import pytest

from uwdock.calibration.frames import inv_T, make_T
from uwdock.dockcore.config import ConfigError, from_dict, replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.curriculum import CurriculumConfig, curriculum_level, near_start_share
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.train.session import TrainingSession
from uwdock.rl.train.training import TrainConfig

CUR = CurriculumConfig(steps=1000, z_tolerance_start_m=1.0, spawn_scale_start=0.3)


def test_schedule_is_linear_then_the_envs_own_values():
    assert curriculum_level(CurriculumConfig(), 0, 0.1) == (0.1, 1.0)  # off
    assert curriculum_level(CUR, 0, 0.1) == pytest.approx((1.0, 0.3))
    assert curriculum_level(CUR, 500, 0.1) == pytest.approx((0.55, 0.65))
    assert curriculum_level(CUR, 1000, 0.1) == pytest.approx((0.1, 1.0))
    assert curriculum_level(CUR, 10**6, 0.1) == pytest.approx((0.1, 1.0))


def test_relaxed_z_tolerance_pays_success_half_a_metre_high():
    env = DockingEnv(replace(EnvConfig(), episode_s=4.0))
    try:
        env.reset(seed=0)
        T_world_ds = env.world.T_world_ds
        above = T_world_ds @ env.cfg.task.T_ds_target @ make_T(t=[0.0, 0.0, -0.5])
        results = []
        for z_m in (0.1, 1.0):
            env.set_curriculum(z_m, 1.0)
            env.reset(seed=0)
            env.world.reset(T_world_ds, above, np.random.default_rng(0))
            _, _, terminated, _, info = env.step(np.zeros(6))
            assert abs(info["e_true"][2]) == pytest.approx(0.5, abs=0.05)
            results.append(terminated and info["success_paper"])
        assert results == [False, True]
        with pytest.raises(ValueError, match="curriculum"):
            env.set_curriculum(float("nan"), 1.0)
    finally:
        env.close()


def test_strict_env_relaxes_the_seated_height_not_the_paper_test():
    """With strict termination the curriculum's z tolerance is the pegs' height above their
    seats: the AUV held aligned 0.5 m above the dock counts as seated at 1.0 m, not at the
    task's own 0.04 m; the paper test keeps its 0.1 m."""
    env = DockingEnv(replace(EnvConfig(), episode_s=8.0, terminate_on="strict"))
    try:
        env.reset(seed=0)
        T_world_ds = env.world.T_world_ds
        above = T_world_ds @ env.cfg.task.T_ds_target @ make_T(t=[0.0, 0.0, -0.5])
        held = {}
        for z_m in (env.cfg.task.strict_peg_z_m, 1.0):
            env.set_curriculum(z_m, 1.0)
            env.reset(seed=0)
            for _ in range(10):  # pinned above the dock (the hold is 5 steps at 5 Hz)
                env.world.reset(T_world_ds, above, np.random.default_rng(0))
                _, _, terminated, _, info = env.step(np.zeros(6))
                assert not info["success_paper"]
                if terminated:
                    break
            held[z_m] = terminated and info["success_strict"]
        assert held == {env.cfg.task.strict_peg_z_m: False, 1.0: True}
    finally:
        env.close()


def test_spawn_scale_brings_the_auv_closer_to_the_ds():
    env = DockingEnv(replace(EnvConfig(), episode_s=4.0))

    def horizontal(seed: int) -> float:
        _, info = env.reset(seed=seed)
        return float(np.linalg.norm(info["T_world_body"][:2, 3] - info["T_world_ds"][:2, 3]))

    try:
        full = [horizontal(s) for s in range(30)]
        env.set_curriculum(0.1, 0.2)
        near = [horizontal(s) for s in range(30)]
    finally:
        env.close()
    assert np.mean(near) == pytest.approx(0.2 * np.mean(full), rel=0.35)
    assert max(near) < 0.2 * np.hypot(6 + 1, 3 + 2) + 1e-9


def test_training_session_pushes_the_level_at_every_boundary(tmp_path):
    calls = []

    class Venv:
        def env_method(self, name, *args):
            calls.append((name, *args))

    class Model:
        num_timesteps = 250

        def get_env(self):
            return Venv()

    cfg = replace(TrainConfig(), curriculum=CUR)
    session = TrainingSession(cfg, tmp_path, Model(), None, note=lambda m: None)
    session.apply_curriculum(250)
    ((name, z_m, scale, near, box),) = calls
    assert name == "set_curriculum"
    assert (z_m, scale, near) == pytest.approx((0.775, 0.475, 0.0))
    assert box == CUR.near_start_box
    calls.clear()  # near-seat starts: the share falls from 0.4 to 0 over 500 steps
    near_cfg = replace(cfg, curriculum=replace(CUR, near_start_fraction=0.4, near_start_steps=500))
    TrainingSession(near_cfg, tmp_path, Model(), None, lambda m: None).apply_curriculum(250)
    assert calls[0][3] == pytest.approx(0.2)
    calls.clear()  # strict termination: the schedule ends at the strict test's 0.04 m
    strict = replace(cfg, env=replace(cfg.env, terminate_on="strict"))
    TrainingSession(strict, tmp_path, Model(), None, lambda m: None).apply_curriculum(1000)
    assert calls[0][1] == pytest.approx(strict.env.task.strict_peg_z_m)
    calls.clear()
    TrainingSession(TrainConfig(), tmp_path, Model(), None, lambda m: None).apply_curriculum(9)
    assert not calls  # no curriculum: the envs keep their own test


def test_near_seat_share_falls_linearly_to_none():
    near = replace(CUR, near_start_fraction=0.5, near_start_steps=2000)
    assert near_start_share(near, 0) == pytest.approx(0.5)
    assert near_start_share(near, 1000) == pytest.approx(0.25)
    assert near_start_share(near, 2000) == 0.0 and near_start_share(near, 10**9) == 0.0
    # its horizon defaults to the curriculum's steps; none without a curriculum
    assert near_start_share(replace(near, near_start_steps=0), 500) == pytest.approx(0.25)
    assert near_start_share(replace(near, steps=0), 0) == 0.0
    assert near_start_share(CUR, 0) == 0.0
    with pytest.raises(ConfigError, match="near_start_height_m"):
        from_dict(CurriculumConfig, {"near_start_height_m": [0.5, 0.1]})
    with pytest.raises(ConfigError, match="near_start_fraction"):
        from_dict(CurriculumConfig, {"near_start_fraction": 1.5})


def test_near_seat_starts_are_above_the_seat_within_the_box_and_clear_of_the_station():
    """Every near-seat start is the docked pose raised by 3-60 cm, within 2 cm and 2 deg of
    it, and PhysX finds no hull shape inside the station's after a first control step; a
    share of 0 draws exactly the spawns of an env without the option."""
    env = DockingEnv(replace(EnvConfig(), episode_s=4.0, terminate_on="strict"))
    try:
        plain = [env.reset(seed=s)[1]["T_world_body"] for s in range(5)]
        env.set_curriculum(0.04, 1.0, 0.0)
        assert all(np.array_equal(env.reset(seed=s)[1]["T_world_body"], plain[s]) for s in range(5))
        env.set_curriculum(0.04, 1.0, 1.0, (0.03, 0.6, 0.02, 2.0))
        heights = []
        for seed in range(40):
            _, info = env.reset(seed=seed)
            T_target = info["T_world_ds"] @ env.cfg.task.T_ds_target
            T_target_body = inv_T(T_target) @ info["T_world_body"]
            dx, dy, dz = T_target_body[:3, 3]
            heights.append(-dz)  # body z down: above the target is -z
            assert 0.03 <= -dz <= 0.6
            assert abs(dx) <= 0.02 * np.sqrt(2) + 1e-9 and abs(dy) <= 0.02 * np.sqrt(2) + 1e-9
            yaw = np.degrees(np.arctan2(T_target_body[1, 0], T_target_body[0, 0]))
            assert abs(yaw) <= 2.0 + 1e-9
            env.step(np.zeros(6))
            for contact in env.world.scene.get_contacts():
                assert all(p.separation > -1e-3 for p in contact.points), seed
        assert max(heights) - min(heights) > 0.3  # the draws span the box
        # half the spawns near the seat: the others are the env's own (>= 2.4 m above the DS
        # floor or 2 m away from it)
        env.set_curriculum(0.04, 1.0, 0.5)
        near = 0
        for seed in range(40):
            _, info = env.reset(seed=seed)
            T_ds_body = inv_T(info["T_world_ds"]) @ info["T_world_body"]
            near += bool(np.linalg.norm(T_ds_body[:2, 3]) < 0.05)
        assert 10 <= near <= 30
        with pytest.raises(ValueError, match="curriculum"):
            env.set_curriculum(0.04, 1.0, 0.5, (0.6, 0.1, 0.02, 2.0))
    finally:
        env.close()
