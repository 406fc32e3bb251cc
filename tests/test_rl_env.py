"""The docking env against Gymnasium/SB3 checkers, determinism, bad input; training CLI smoke."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from uwdock.dockcore.config import replace
from uwdock.rl import cli
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.evaluate.episodes import run_episodes
from uwdock.rl.policy.baselines import PIDController

ROOT = Path(__file__).resolve().parents[1]
SHORT = replace(EnvConfig(), episode_s=3.0)


@pytest.fixture(scope="module")
def env():
    e = DockingEnv(SHORT)
    yield e
    e.close()


def test_gymnasium_and_sb3_checkers_pass_without_warnings(env):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check(env, skip_render_check=True)
        sb3_check(env, warn=True)


def test_same_seed_same_rollout(env):
    def rollout(seed):
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(5)
        out = [obs]
        for _ in range(8):
            obs, r, *_ = env.step(rng.uniform(-1, 1, 6))
            out.append(np.append(obs, r))
        return np.concatenate(out)

    a, b, c = rollout(3), rollout(3), rollout(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_reward_terms_sum_to_the_reward(env):
    env.reset(seed=0)
    _, r, _, _, info = env.step(np.zeros(6))
    assert set(info["reward_terms"]) == {
        "dist",
        "angle",
        "smooth",
        "collision",
        "mission",
        "precision",
        "stall",
    }
    assert r == pytest.approx(sum(info["reward_terms"].values()))


def test_truncation_at_episode_end(env):
    env.reset(seed=1)
    steps, trunc = 0, False
    while not trunc:
        _, _, term, trunc, info = env.step(np.zeros(6))
        steps += 1
        assert not term
    assert steps == round(SHORT.episode_s * SHORT.control_hz)
    assert info["reward_terms"]["mission"] == -10.0


@pytest.mark.parametrize("bad", [[np.nan, 0, 0, 0, 0, 0], [0, 0, np.inf, 0, 0, 0], [0, 0]])
def test_bad_actions_raise_a_clear_error(env, bad):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must be 6 finite numbers"):
        env.step(np.array(bad, dtype=float))


@pytest.mark.parametrize("offset_m,visible", [((0.3, 0.2, 2.5), True), ((4.0, 0.0, 2.0), False)])
def test_proxy_noise_follows_the_paper(offset_m, visible):
    """sigma = |e|/6; N(0, (sigma/2)^2) always, plus N(0, sigma^2) when not visible."""
    from uwdock.calibration.frames import make_T
    from uwdock.rl.env.obs_sources import ProxySource, StepContext
    from uwdock.rl.env.task import DockingTaskConfig, docking_errors

    task = DockingTaskConfig()
    T_world_ds = np.eye(4)
    T_target = task.T_ds_target
    T_world_body = make_T(T_target[:3, :3], T_target[:3, 3] - np.asarray(offset_m))
    src = ProxySource(task)
    src.reset(np.random.default_rng(0))
    ctx = StepContext(T_world_body, T_world_ds, 0.0)
    e_true, _ = docking_errors(T_world_body, T_world_ds, task)
    errs = []
    for _ in range(4000):
        m = src.measure(ctx)
        assert m.detected is visible
        errs.append(docking_errors(T_world_body, m.T_world_ds, task)[0] - e_true)
    sigma = np.linalg.norm(e_true) / 6
    expected = sigma / 2 if visible else np.sqrt((sigma / 2) ** 2 + sigma**2)
    np.testing.assert_allclose(np.std(errs, axis=0), expected, rtol=0.05)
    np.testing.assert_allclose(np.mean(errs, axis=0), 0, atol=4 * expected / np.sqrt(4000))


def test_pid_baseline_docks_with_the_proxy():
    cfg = replace(EnvConfig(), terminate_on="strict")
    res = run_episodes(PIDController(np.asarray(cfg.wrench_limits)), cfg, 3, seed=0, record=False)
    assert res.summary["success_rate"] >= 2 / 3
    assert res.summary["success_rate_strict"] >= 2 / 3


def test_pid_reads_the_newest_frame_of_a_stacked_observation():
    cfg = replace(EnvConfig(), obs_frames=3, episode_s=2.0)
    env = DockingEnv(cfg)
    try:
        obs, _ = env.reset(seed=4)
        for _ in range(4):
            obs, *_ = env.step(np.zeros(6))
    finally:
        env.close()
    limits = np.asarray(cfg.wrench_limits)
    frames = obs.reshape(3, -1)
    assert not np.allclose(frames[0], frames[-1])  # history differs from the present
    stacked = PIDController(limits, obs_frames=3).act(obs)
    single = PIDController(limits).act(frames[-1])
    np.testing.assert_allclose(stacked, single)


def test_train_resume_eval_export_through_the_cli(run_cli, tmp_path):
    cfg = tmp_path / "train.toml"
    cfg.write_text(
        "n_envs = 1\ncheckpoint_every = 64\neval_every = 0\n"
        "[env]\nepisode_s = 4.0\n[ppo]\nn_steps = 64\nbatch_size = 64\nn_epochs = 1\n"
    )
    run = tmp_path / "run"
    res = run_cli(cli.main, "train", "--config", cfg, "--steps", "128", "--out", run)
    assert res.code == 0, res.err
    assert (run / "model.json").is_file() and (run / "weights.npz").is_file()
    assert (run / "checkpoints" / "step_0000000128" / "manifest.json").is_file()
    # a longer run is a change of the run's config: refused unless asked for, then recorded
    res = run_cli(cli.main, "train", "--steps", "256", "--out", run, "--resume")
    assert res.code == 2 and "differs from the run's config.toml in total_steps" in res.err
    res = run_cli(
        cli.main, "train", "--steps", "256", "--out", run, "--resume", "--allow-config-change"
    )
    assert res.code == 0, res.err
    assert json.loads((run / "DONE").read_text())["steps"] == 256
    log = json.loads((run / "resume_log.jsonl").read_text().splitlines()[-1])
    assert log["from_step"] == 128 and log["config_changed"] == ["total_steps"]
    # a second fresh run into the same folder is refused
    res = run_cli(cli.main, "train", "--config", cfg, "--steps", "64", "--out", run)
    assert res.code != 0 and "already holds a run" in res.err

    env_cfg = tmp_path / "env.toml"
    env_cfg.write_text("episode_s = 2.0\n")
    out = tmp_path / "eval"
    res = run_cli(
        cli.main,
        "eval",
        "--policy",
        run,
        "--episodes",
        "2",
        "--obs",
        "proxy",
        "--config",
        env_cfg,
        "--videos",
        "",
        "--out",
        out,
    )
    assert res.code == 0, res.err
    summary = json.loads((out / "summary.json").read_text())
    for key in (
        "episodes",
        "success_rate",
        "success_rate_strict",
        "mean_time_to_dock_s",
        "mean_collisions",
        "final_e_xy_m_median",
    ):
        assert key in summary
    assert summary["episodes"] == 2
    assert (out / "episodes.csv").read_text().count("\n") == 3
    assert (out / "trajectories_top.png").is_file() and (out / "traces_ep0.png").is_file()

    onnx_path = tmp_path / "policy.onnx"
    res = run_cli(cli.main, "export", "--policy", run, "--out", onnx_path)
    assert res.code == 0, res.err
    from uwdock.rl.evaluate.episodes import SB3Controller
    from uwdock.rl.policy.policy_io import OnnxPolicy, load_policy

    model, vecnorm = load_policy(run)
    sb3, onnx = SB3Controller(model, vecnorm), OnnxPolicy(onnx_path)
    # the exported policy carries its interface (observation layout, limits) for eval and runner
    from uwdock.rl.policy.policy_io import policy_env_settings

    carried = policy_env_settings(str(onnx_path))
    assert carried == policy_env_settings(str(run)) and carried["obs_last_action"] is False
    assert len(carried["wrench_limits"]) == 6
    obs = np.random.default_rng(0).normal(size=(5, model.observation_space.shape[0]))
    for o in obs.astype(np.float32):
        np.testing.assert_allclose(onnx.act(o), sb3.act(o), atol=1e-5)


def test_eval_pid_and_bad_policy_file(run_cli, tmp_path):
    env_cfg = tmp_path / "env.toml"
    env_cfg.write_text("episode_s = 2.0\n")
    res = run_cli(
        cli.main,
        "eval",
        "--policy",
        "pid",
        "--episodes",
        "1",
        "--obs",
        "proxy",
        "--config",
        env_cfg,
        "--videos",
        "",
        "--out",
        tmp_path / "e",
    )
    assert res.code == 0, res.err
    res = run_cli(
        cli.main,
        "eval",
        "--policy",
        tmp_path / "missing.zip",
        "--episodes",
        "1",
        "--obs",
        "proxy",
        "--out",
        tmp_path / "e2",
    )
    assert res.code != 0 and "policy file not found" in res.err
    bad = tmp_path / "bad.zip"  # the pickled format: refused unread
    bad.write_bytes(b"not a zip")
    args = ["--episodes", "1", "--obs", "proxy"]
    res = run_cli(cli.main, "eval", "--policy", bad, *args, "--out", tmp_path / "e3")
    assert res.code == 2 and "pickled format" in res.err and res.err.count("\n") == 1
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "model.json").write_bytes(b"\xff not json")
    res = run_cli(cli.main, "eval", "--policy", garbage, *args, "--out", tmp_path / "e4")
    assert res.code == 2 and "cannot read policy model" in res.err and res.err.count("\n") == 1


def test_error_model_source_requires_a_model(run_cli, tmp_path):
    res = run_cli(
        cli.main,
        "eval",
        "--policy",
        "pid",
        "--episodes",
        "1",
        "--obs",
        "error-model",
        "--out",
        tmp_path / "e",
    )
    assert res.code != 0 and "error_model_path" in res.err


def test_registered_with_gymnasium():
    import gymnasium as gym

    import uwdock.rl

    env = gym.make(uwdock.rl.ENV_ID, config=SHORT)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    env.close()


def test_dagger_warm_start_imitates_the_teacher(tmp_path):
    """After the warm start the policy's mean action follows the PID teacher on its states."""
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from uwdock.rl.train.imitation import ImitationConfig, warm_start
    from uwdock.rl.train.training import PPOConfig, TrainConfig, build_model

    cfg = replace(
        TrainConfig(),
        n_envs=1,
        env=replace(EnvConfig(), episode_s=6.0),
        ppo=replace(PPOConfig(), batch_size=512),  # one env x 512 steps: no partial batch
    )
    venv = VecNormalize(DummyVecEnv([lambda: DockingEnv(cfg.env)]))
    model = build_model(cfg, venv, tmp_path / "tb")
    icfg = ImitationConfig(iterations=2, episodes_per_iteration=2, epochs=40, log_std=-1.5)
    hist = warm_start(model, venv, cfg.env, icfg, seed=0, gamma=0.99, progress=False)
    assert len(hist["loss"]) == 2 and hist["loss"][-1] < 0.08
    assert torch.allclose(model.policy.log_std, torch.full((6,), -1.5))
    # the kept student comes with the normalisation statistics it was fitted under
    sel = hist["selected_iteration"][0]
    assert venv.obs_rms.count == pytest.approx(1e-4 + sum(hist["samples"][: sel + 1]))
    # the student reproduces the teacher on the states it was taught (seeded as warm_start does)
    env = DockingEnv(cfg.env)
    teacher = PIDController(np.asarray(cfg.env.wrench_limits))
    obs, _ = env.reset(seed=500_000)
    diffs = []
    for _ in range(20):
        a_t = teacher.act(obs)
        with torch.no_grad():
            o = torch.as_tensor(venv.normalize_obs(obs[None]), dtype=torch.float32)
            a_s = model.policy.get_distribution(o).distribution.mean.numpy()[0]
        diffs.append(np.abs(np.clip(a_s, -1, 1) - a_t).mean())
        obs, *_ = env.step(a_t)
    assert np.mean(diffs) < 0.2


def test_camera_frames_sheet_picks_evenly_spaced_captioned_frames(tmp_path):
    import cv2

    from uwdock.rl.evaluate.episode_media import write_frames_sheet

    frames = [np.full((48, 64, 3), 10 * k, np.uint8) for k in range(20)]
    path = write_frames_sheet(frames, tmp_path / "sheet.png", dt_s=0.2, n=8)
    sheet = cv2.imread(str(path))
    pad = 4
    assert sheet.shape[:2] == (2 * (48 + pad) + pad, 4 * (64 + pad) + pad)  # 8 tiles, 4 columns
    # first tile is frame 0 (dark), last tile frame 19 (brightest); sample above the caption
    assert sheet[pad + 5, pad + 5, 0] == 0
    assert sheet[2 * pad + 48 + 5, 3 * (64 + pad) + pad + 5, 0] == 190
    assert write_frames_sheet([], tmp_path / "none.png", dt_s=0.2) is None


def test_unknown_water_preset_is_refused_naming_the_key():
    from uwdock.dockcore.config import ConfigError

    with pytest.raises(ConfigError, match="water_preset: unknown 'lagoon'"):
        replace(EnvConfig(), water_preset="lagoon")


def test_eval_history_plot(tmp_path):
    from uwdock.rl.evaluate.report import plot_eval_history

    hist = tmp_path / "eval_history.jsonl"
    rows = [
        {"step": 0, "success_rate": 0.9, "success_rate_strict": 0.5, "mean_time_to_dock_s": 12.0,
         "mean_collisions": 0.5, "best": True},
        {"step": 25000, "success_rate": 0.0, "success_rate_strict": 0.0,
         "mean_time_to_dock_s": None, "mean_collisions": 2.0},
    ]  # fmt: skip
    hist.write_text("".join(json.dumps(r) + "\n" for r in rows))
    path = plot_eval_history(hist, tmp_path / "curve.png")
    import cv2

    assert cv2.imread(str(path)).shape == (340, 1200, 3)
    hist.write_text("")
    assert plot_eval_history(hist, tmp_path / "none.png") is None


def test_dagger_restores_the_normalisation_of_the_student_it_keeps(tmp_path, monkeypatch):
    """When an earlier student scores best, it comes back with the statistics it was fitted on."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    import uwdock.rl.train.imitation
    from uwdock.rl.train.imitation import ImitationConfig, warm_start
    from uwdock.rl.train.training import PPOConfig, TrainConfig, build_model

    class ScriptedSuccess(DockingEnv):
        """Only the rollouts that score the iteration-0 student (episodes 2 and 3) 'dock'."""

        episodes = -1

        def reset(self, **kw):
            type(self).episodes += 1
            return super().reset(**kw)

        def step(self, action):
            obs, r, term, trunc, info = super().step(action)
            info = {**info, "success_paper": type(self).episodes in (2, 3)}
            return obs, r, term, trunc, info

    cfg = replace(
        TrainConfig(),
        n_envs=1,
        env=replace(EnvConfig(), episode_s=2.0),
        ppo=replace(PPOConfig(), batch_size=512),
    )
    venv = VecNormalize(DummyVecEnv([lambda: DockingEnv(cfg.env)]))
    model = build_model(cfg, venv, tmp_path / "tb")
    monkeypatch.setattr(uwdock.rl.train.imitation, "DockingEnv", ScriptedSuccess)
    icfg = ImitationConfig(iterations=3, episodes_per_iteration=2, epochs=2)
    hist = warm_start(model, venv, cfg.env, icfg, seed=0, gamma=0.99, progress=False)
    assert hist["selected_iteration"] == [0]
    assert venv.obs_rms.count == pytest.approx(1e-4 + hist["samples"][0])
    assert hist["samples"][0] < sum(hist["samples"])  # later data was seen, and left out


def test_sac_option_trains_and_resumes_through_the_cli(run_cli, tmp_path):
    cfg = tmp_path / "sac.toml"
    cfg.write_text(
        'algo = "sac"\nn_envs = 1\ncheckpoint_every = 48\neval_every = 0\n'
        "[env]\nepisode_s = 4.0\n"
        "[sac]\nbuffer_size = 1000\nbatch_size = 16\nlearning_starts = 16\nnet_arch = [16, 16]\n"
    )
    run = tmp_path / "sac_run"
    res = run_cli(cli.main, "train", "--config", cfg, "--steps", "48", "--out", run)
    assert res.code == 0, res.err
    arrays = np.load(run / "checkpoints" / "step_0000000048" / "training.npz")
    assert arrays["replay/observations"].shape[0] == 1000  # the replay buffer, as data
    res = run_cli(
        cli.main, "train", "--steps", "96", "--out", run, "--resume", "--allow-config-change"
    )
    assert res.code == 0, res.err
    assert json.loads((run / "DONE").read_text())["steps"] == 96
    # the same as a run of 96 steps never stopped (replay buffer, optimisers, entropy included)
    straight = tmp_path / "sac_straight"
    res = run_cli(cli.main, "train", "--config", cfg, "--steps", "96", "--out", straight)
    assert res.code == 0, res.err
    assert (run / "weights.npz").read_bytes() == (straight / "weights.npz").read_bytes()
    from stable_baselines3.sac.policies import SACPolicy

    from uwdock.rl.policy.policy_io import load_policy

    model, _ = load_policy(run)
    assert model.algorithm == "sac" and isinstance(model.policy, SACPolicy)


@pytest.mark.render
def test_filming_an_episode_does_not_change_it():
    cfg = replace(EnvConfig(), episode_s=3.0, camera_width_px=96)
    pid = PIDController.for_env(cfg)
    plain = run_episodes(pid, cfg, 1, seed=3, record=False)
    filmed = run_episodes(pid, cfg, 1, seed=3, record=False, video_episodes=(0,))
    assert filmed.traces[0].frames  # the camera view was filmed
    assert filmed.episodes[0]["return"] == plain.episodes[0]["return"]
    assert filmed.episodes[0]["final_e_xy_m"] == plain.episodes[0]["final_e_xy_m"]


def test_parallel_evaluation_equals_one_process():
    from uwdock.rl.evaluate.episodes import run_episodes_parallel

    cfg = replace(EnvConfig(), episode_s=2.0)
    ticks = []
    one = run_episodes_parallel("pid", cfg, 4, seed=3, workers=1, record=False)
    two = run_episodes_parallel(
        "pid", cfg, 4, seed=3, workers=2, record=False, progress=lambda k, n: ticks.append(k)
    )
    assert two.episodes == one.episodes and two.summary == one.summary
    assert ticks == [1, 2, 3, 4]


def test_stress_tables_rows_progress_and_seeds(capsys):
    from uwdock.rl.evaluate.episodes import run_episodes_parallel
    from uwdock.rl.evaluate.report import (
        STRESS_CURRENTS_MPS,
        STRESS_THRUSTER_ERRORS_M,
        stress_tables,
    )

    cfg = replace(EnvConfig(), episode_s=2.0)  # proxy source: no water rows
    tables = stress_tables("pid", cfg, 2, seed=5, workers=1)
    assert [r["current_max_mps"] for r in tables["current"]] == list(STRESS_CURRENTS_MPS)
    assert tables["water"] == []
    errs = [r["thruster_position_error_m"] for r in tables["thruster"]]
    assert errs == list(STRESS_THRUSTER_ERRORS_M)
    for row in tables["current"] + tables["thruster"]:
        assert row["episodes"] == 2 and 0.0 <= row["success_rate"] <= 1.0
    # a row is the plain evaluation of its config on the same seeds
    still = {"mode": "random", "range_x_mps": (0.0, 0.0), "range_y_mps": (0.0, 0.0)}
    calm = replace(cfg, world={"current": still})
    direct = run_episodes_parallel("pid", calm, 2, seed=5, workers=1, record=False).summary
    assert tables["current"][0]["mean_collisions"] == direct["mean_collisions"]
    assert tables["current"][0]["success_rate"] == direct["success_rate"]
    # one progress bar over all 7 rows x 2 episodes, naming the row it is on
    err = capsys.readouterr().err
    assert "14/14" in err and "stress thruster 0.05" in err


def test_eval_error_model_defaults_to_the_one_the_policy_trained_on(run_cli, tmp_path):
    import shutil

    from uwdock.rl.policy.policy_io import policy_error_model

    shipped = "rl/policies/error_model_ppo"
    # named from the checkout's root in its config, found from the policy's folder
    em = str(Path("rl/models/error_model_clear_tank_480.json").absolute())
    assert policy_error_model(shipped) == em
    env_cfg = tmp_path / "env.toml"
    env_cfg.write_text("episode_s = 1.0\n")
    args = ["eval", "--episodes", "1", "--obs", "error-model", "--config", env_cfg, "--videos", ""]
    res = run_cli(cli.main, *args, "--policy", shipped, "--out", tmp_path / "e")
    assert res.code == 0, res.err
    summary = json.loads((tmp_path / "e" / "summary.json").read_text())
    assert summary["config"]["error_model_path"] == em
    # the --config file's error model wins over the policy's
    other = tmp_path / "em.json"
    shutil.copy("rl/models/error_model_clear_tank_640.json", other)
    env_cfg.write_text(f"episode_s = 1.0\nerror_model_path = '{other}'\n")
    res = run_cli(cli.main, *args, "--policy", shipped, "--out", tmp_path / "e2")
    assert res.code == 0, res.err
    summary = json.loads((tmp_path / "e2" / "summary.json").read_text())
    assert summary["config"]["error_model_path"] == str(other)
    # the PID has no run to take one from: one line saying which option to give
    env_cfg.write_text("episode_s = 1.0\n")
    res = run_cli(cli.main, *args, "--policy", "pid", "--out", tmp_path / "e3")
    assert res.code == 2 and res.err.count("\n") == 1
    assert "required for obs_source 'error-model'" in res.err and "--error-model FILE" in res.err
    assert not (tmp_path / "e3").exists()


def test_env_reads_what_a_source_needs_not_its_name(monkeypatch):
    """The filter's fusion and the acoustic fixes follow the source class's ``needs``: the same
    ``proxy`` config gets both once its class declares them."""
    from uwdock.rl.env.camera_source import CameraSource
    from uwdock.rl.env.error_model import ErrorModelSource
    from uwdock.rl.env.obs_sources import ProxySource, SourceNeeds

    assert ProxySource.needs == SourceNeeds(camera=False, fusion=False, acoustic_fixes=False)
    assert ErrorModelSource.needs == SourceNeeds(camera=False, fusion=True, acoustic_fixes=True)
    assert CameraSource.needs == SourceNeeds(
        camera=True, fusion=True, acoustic_fixes=True, nav_frame=True
    )
    est = replace(EnvConfig().estimator, fuse=True)
    cfg = replace(SHORT, obs_source="proxy", estimator=est, usbl={"period_s": 1.0})

    def run(env: DockingEnv) -> list[float]:
        sigmas: list[float] = []
        update = env.filter.update_position
        env.filter.update_position = lambda p, s: (sigmas.append(s), update(p, s))[1]
        env.reset(seed=4)
        for _ in range(11):  # 2.2 s at 5 Hz: a fix at the start, then every 5 steps
            env.step(np.zeros(6, dtype=np.float32))
        env.close()
        return sigmas

    env = DockingEnv(cfg)
    assert (env.filter.cfg.fuse, env.world.with_camera) == (False, False)
    assert run(env) == []  # the paper's proxy: memoryless, no acoustic fixes
    monkeypatch.setattr(ProxySource, "needs", SourceNeeds(fusion=True, acoustic_fixes=True))
    env = DockingEnv(cfg)
    assert (env.filter.cfg.fuse, env.world.with_camera) == (True, False)
    sigmas = run(env)
    assert len(sigmas) == 3 and all(0 < s < 5 for s in sigmas)


def test_an_episode_does_not_depend_on_the_episodes_before_it():
    # PhysX keeps contact state (pair caches, friction anchors) between the episodes of a
    # process; the world gives every episode a fresh PhysX system. Without it, the shipped
    # recipe's episode 10 (seed 1010) ran after episode 2 (seed 1002, which ends seated with the
    # pegs in the guides) differed from the same episode run first (its return by -0.019).
    from uwdock.dockcore.config import load_config
    from uwdock.rl.train.training import TrainConfig

    cfg = load_config(TrainConfig, ROOT / "configs/scratch/stage1.toml", section="train").env
    cfg = replace(cfg, error_model_path=str(ROOT / cfg.error_model_path))
    pid = PIDController.for_env(cfg)
    after = run_episodes(pid, cfg, 11, seed=1000, episodes=[2, 10])
    alone = run_episodes(pid, cfg, 11, seed=1000, episodes=[10])
    assert after.episodes[0]["success_strict"] and after.episodes[0]["collisions"] > 0
    assert alone.episodes[0] == after.episodes[1]
    np.testing.assert_array_equal(
        np.array(alone.traces[0].pos_body_m), np.array(after.traces[1].pos_body_m)
    )


def test_training_evaluation_on_the_env_workers_equals_one_process(tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from uwdock.rl.train.session import EVAL_SEED, TrainingSession
    from uwdock.rl.train.training import TrainConfig
    from uwdock.rl.train.vec_envs import EnvWorkers

    cfg = TrainConfig(env=replace(SHORT, terminate_on="strict"), eval_episodes=5, n_envs=2)
    workers = EnvWorkers(cfg.env, 2, seed=0)
    try:
        vecnorm = VecNormalize(workers.venv)
        vecnorm.reset()
        rng = np.random.default_rng(0)
        for _ in range(10):  # normalisation statistics that are not the identity
            vecnorm.step(rng.uniform(-1, 1, (2, 6)))
        model = PPO("MlpPolicy", vecnorm, n_steps=8, batch_size=16, seed=0, device="cpu")
        session = TrainingSession(cfg, tmp_path, model, vecnorm, note=lambda m: None)
        rows = session._eval_rows()  # episodes 0, 2, 4 in one worker, 1, 3 in the other
        one = run_episodes(model, cfg.env, 5, EVAL_SEED, vecnorm=vecnorm, record=False)
    finally:
        workers.close()
    assert [r["episode"] for r in rows] == [0, 1, 2, 3, 4]
    assert rows == one.episodes
    assert len({r["return"] for r in rows}) == 5  # five different episodes
