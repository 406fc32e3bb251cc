"""The simulated acoustic (USBL) positioning (``sim.usbl``) and its use in the docking env:
the "ideal" preset is the env's original model draw for draw; bias, bearing noise, outliers,
dropouts and latency are recovered from many fixes; hostile values are refused in one line; the
camera-off ``acoustic`` source never reports a detection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.dockcore.config import dumps_toml, from_dict, load_config, replace, to_dict
from uwdock.dockcore.errors import ConfigError
from uwdock.rl.env.config import EnvConfig
from uwdock.sim.usbl import MODEL_FIELDS, USBL_PRESETS, UsblConfig, UsblSensor

#: Every effect off: a noiseless, unbiased, on-time fix every 0.2 s (one control step).
QUIET = UsblConfig(preset="ideal", **{**dict.fromkeys(MODEL_FIELDS, 0.0), "period_s": 0.2})


def quiet(**changes: float) -> UsblConfig:
    return replace(QUIET, **changes)


def fixes(sensor: UsblSensor, T_world_body, p_ds, n: int, rng, period_s: float) -> list:
    """``n`` scheduled fixes at a fixed geometry (one call per period)."""
    return [sensor.fix(k * period_s, T_world_body, p_ds, rng) for k in range(n)]


# ----------------------------------------------------------------------- the "ideal" preset
def test_ideal_preset_is_the_old_formula_draw_for_draw():
    """Same sigma (0.15 m + 3 % of the slant range), same draws (one normal triple per fix from
    the episode's stream, nothing at reset), same schedule (every 5th control step at 5 Hz)."""
    ideal = USBL_PRESETS["ideal"]
    assert ideal == EnvConfig().usbl_model
    assert (ideal.period_s, ideal.sigma_floor_m, ideal.sigma_per_m) == (1.0, 0.15, 0.03)
    sensor = UsblSensor(UsblConfig())
    rng, old = np.random.default_rng(7), np.random.default_rng(7)
    sensor.reset(rng)
    p_ds = np.array([0.4, -1.0, 5.0])
    t_s = 0.0
    for step in range(26):
        T = make_T(R_from_rpy(0.0, 0.1, 0.3 * step), [0.05 * step, 0.3, 1.5 + 0.05 * step])
        fix = sensor.fix(t_s, T, p_ds, rng)
        if step % 5:
            assert fix is None
        else:  # the env's code before sim.usbl
            sigma = 0.15 + 0.03 * float(np.linalg.norm(p_ds - T[:3, 3]))
            assert fix.sigma_m == sigma
            np.testing.assert_array_equal(fix.p_world_ds_m, p_ds + old.normal(0.0, sigma, 3))
        for _ in range(60):  # the physics clock: 60 substeps of 1/300 s per control step
            t_s += 1.0 / 300.0
    assert rng.bit_generator.state == old.bit_generator.state  # no other draw


def test_old_run_configs_load_and_keep_the_ideal_model():
    from uwdock.rl.train.training import TrainConfig

    cfg = load_config(TrainConfig, "rl/policies/error_model_ppo/config.toml", section="train")
    assert cfg.env.usbl == UsblConfig()
    assert cfg.env.usbl_model == USBL_PRESETS["ideal"]
    # the ideal model's numbers those files held in [estimator] become [usbl] fields
    data = to_dict(cfg.env)
    assert "usbl_period_s" not in data["estimator"]
    data["estimator"] |= {"usbl_period_s": 0.0, "usbl_sigma_floor_m": 0.3, "usbl_sigma_per_m": 0.03}
    old = from_dict(EnvConfig, data)
    assert old.usbl == UsblConfig(period_s=0.0, sigma_floor_m=0.3)  # 0.03 is the preset's
    model = old.usbl_model
    assert (model.period_s, model.sigma_floor_m, model.sigma_per_m) == (0.0, 0.3, 0.03)
    # under another preset they described nothing the env simulated: dropped
    data["usbl"] = {"preset": "evologics-s2cr"}
    assert from_dict(EnvConfig, data).usbl == UsblConfig(preset="evologics-s2cr")
    # a field the [usbl] table sets itself wins, as it did over the estimator's
    data["usbl"] = {"period_s": 2.0}
    assert from_dict(EnvConfig, data).usbl_model.period_s == 2.0


def test_a_preset_plus_overrides_round_trips_through_toml(tmp_path):
    cfg = replace(EnvConfig(), usbl={"preset": "cerulean-rovl", "latency_s": 0.5})
    text = dumps_toml(cfg)
    assert '[usbl]\npreset = "cerulean-rovl"\nlatency_s = 0.5\n' in text
    path = tmp_path / "env.toml"
    path.write_text(text)
    again = load_config(EnvConfig, path)
    assert again == cfg
    model = again.usbl_model
    assert model.latency_s == 0.5
    assert model.bearing_sigma_deg == USBL_PRESETS["cerulean-rovl"].bearing_sigma_deg
    # a whole config replaces the table; a preset's estimator fields do not leak into it
    assert replace(cfg, usbl=UsblConfig()).usbl_model == USBL_PRESETS["ideal"]


# ----------------------------------------------------------------------- the error model
def test_bias_is_the_misalignment_and_range_error_drawn_at_reset():
    """With outliers and dropouts off, the mean error of many fixes at one geometry is the
    episode's bias: the transceiver's misalignment turning the line of sight, the range scale
    and the range offset."""
    cfg = quiet(
        tilt_bias_sigma_deg=2.0,
        heading_bias_sigma_deg=3.0,
        range_scale_sigma_rel=0.02,
        range_offset_sigma_m=0.1,
        bearing_sigma_deg=0.5,
        range_sigma_m=0.02,
    )
    sensor = UsblSensor(cfg)
    rng = np.random.default_rng(3)
    sensor.reset(rng)
    assert sensor.range_scale != 1.0 and sensor.range_offset_m != 0.0
    T = make_T(R_from_rpy(0.05, -0.03, 0.8), [1.0, 2.0, 1.0])
    p_ds = np.array([3.0, 0.5, 5.0])
    rel = p_ds - T[:3, 3]
    r = float(np.linalg.norm(rel))
    u_body = sensor.R_misalign @ (T[:3, :3].T @ rel / r)
    expected = T[:3, :3] @ ((r * sensor.range_scale + sensor.range_offset_m) * u_body) - rel
    errs = np.array([f.p_world_ds_m - p_ds for f in fixes(sensor, T, p_ds, 2000, rng, 0.2)])
    assert np.linalg.norm(expected) > 0.15  # tens of centimetres at 4.7 m
    np.testing.assert_allclose(errs.mean(axis=0), expected, atol=0.003)
    # a new episode draws a new bias
    sensor.reset(rng)
    again = np.array([f.p_world_ds_m - p_ds for f in fixes(sensor, T, p_ds, 400, rng, 0.2)])
    assert np.linalg.norm(again.mean(axis=0) - expected) > 0.02


@pytest.mark.parametrize("range_m", [1.0, 4.0, 8.0])
def test_bearing_noise_spreads_the_fix_across_the_line_of_sight_as_r_sigma(range_m):
    sigma_rad = math.radians(2.0)
    sensor = UsblSensor(quiet(bearing_sigma_deg=2.0))
    rng = np.random.default_rng(5)
    sensor.reset(rng)
    T = make_T(R_from_rpy(0.0, 0.0, 0.4), [0.0, 0.0, 0.0])
    p_ds = np.array([0.0, 0.0, range_m])  # straight below: x, y are across the line of sight
    errs = np.array([f.p_world_ds_m - p_ds for f in fixes(sensor, T, p_ds, 3000, rng, 0.2)])
    np.testing.assert_allclose(errs[:, :2].std(axis=0), range_m * sigma_rad, rtol=0.05)
    # the direction turns, the range is kept: the fix stays on the sphere of radius r
    np.testing.assert_allclose(np.linalg.norm(p_ds + errs, axis=1), range_m, rtol=1e-12)
    assert sensor.sigma_m(range_m) == pytest.approx(range_m * sigma_rad)


def test_dropout_and_outlier_rates_are_recovered():
    sensor = UsblSensor(quiet(dropout_prob=0.3, outlier_prob=0.1, outlier_sigma_m=2.0))
    rng = np.random.default_rng(1)
    sensor.reset(rng)
    T, p_ds = make_T(None, [0.0, 0.0, 1.0]), np.array([1.0, 0.0, 5.0])
    got = fixes(sensor, T, p_ds, 20000, rng, 0.2)
    delivered = [f for f in got if f is not None]
    # binomial standard errors: 0.0032 (dropouts of 20000), 0.0025 (outliers of 14000)
    assert 1 - len(delivered) / len(got) == pytest.approx(0.3, abs=0.01)
    outliers = np.array([f.p_world_ds_m - p_ds for f in delivered if f.outlier])
    assert len(outliers) / len(delivered) == pytest.approx(0.1, abs=0.008)
    np.testing.assert_allclose(outliers.std(axis=0), 2.0, rtol=0.06)
    clean = np.array([f.p_world_ds_m - p_ds for f in delivered if not f.outlier])
    assert np.abs(clean).max() < 1e-12


def test_latency_fix_describes_the_geometry_latency_s_earlier():
    """A fix arriving at t measured the DS from where the vehicle was at t - latency, and the
    vehicle adds it to where it is now: its relative vector is the old geometry."""

    def pose(t_s: float) -> np.ndarray:
        return make_T(R_from_rpy(0.0, 0.0, 0.2 * t_s), [0.3 * t_s, -0.1 * t_s**2, 1.0 + 0.05 * t_s])

    p_ds = np.array([2.0, 1.0, 5.0])
    for latency_s in (0.6, 0.5):  # a multiple of the control step, and between two steps
        sensor = UsblSensor(quiet(latency_s=latency_s, bearing_sigma_deg=0.0))
        sensor.reset(np.random.default_rng(0))
        for k in range(20):
            t_s = 0.2 * k
            fix = sensor.fix(t_s, pose(t_s), p_ds, np.random.default_rng(0))
            assert fix.ping_time_s == pytest.approx(t_s - latency_s)
            t_ping = max(t_s - latency_s, 0.0)  # before the episode: the spawn pose
            old = pose(t_ping)[:3, 3]
            if latency_s == 0.5 and t_ping > 0:  # between two kept poses: linear
                k0 = math.floor(t_ping / 0.2 + 1e-9)
                w = (t_ping - 0.2 * k0) / 0.2
                old = (1 - w) * pose(0.2 * k0)[:3, 3] + w * pose(0.2 * (k0 + 1))[:3, 3]
            rel = fix.p_world_ds_m - pose(t_s)[:3, 3]
            np.testing.assert_allclose(rel, p_ds - old, atol=1e-12)


def test_fixes_keep_their_period_and_time_must_not_run_backwards():
    sensor = UsblSensor(quiet(period_s=0.5))
    rng = np.random.default_rng(0)
    sensor.reset(rng)
    T, p_ds = make_T(None, [0.0, 0.0, 1.0]), np.array([0.0, 0.0, 5.0])
    times = [0.2 * k for k in range(16)]
    got = [t for t in times if sensor.fix(t, T, p_ds, rng) is not None]
    assert np.allclose(got, [0.0, 0.6, 1.0, 1.6, 2.0, 2.6, 3.0])  # 2 per second, on steps
    with pytest.raises(ValueError, match=r"time_s: .* before the last call"):
        sensor.fix(1.0, T, p_ds, rng)
    sensor.reset(rng)  # a new episode starts the clock again
    assert sensor.fix(0.0, T, p_ds, rng) is not None
    assert UsblSensor(quiet(period_s=0.0)).fix(0.0, T, p_ds, rng) is None


def test_realistic_presets_are_complete_and_valid():
    assert set(USBL_PRESETS) >= {"ideal", "cerulean-rovl", "evologics-s2cr"}
    for name, preset in USBL_PRESETS.items():
        assert preset.preset == name
        assert all(getattr(preset, f) is not None for f in MODEL_FIELDS), name
        sensor = UsblSensor(UsblConfig(preset=name))
        assert sensor.cfg == UsblConfig(preset=name).resolved()
    # the realistic ones are biased, late or lossy; the ideal one is none of these
    for name in ("cerulean-rovl", "evologics-s2cr"):
        p = USBL_PRESETS[name]
        assert p.tilt_bias_sigma_deg > 0 and p.latency_s > 0 and p.dropout_prob > 0


# ----------------------------------------------------------------------- hostile values
@pytest.mark.parametrize(
    "key,value,message",
    [
        ("latency_s", math.nan, "usbl.latency_s: must be a finite number in [0, 60], got nan"),
        ("dropout_prob", -0.1, "usbl.dropout_prob: must be a finite number in [0, 1], got -0.1"),
        ("outlier_prob", 1.5, "usbl.outlier_prob: must be a finite number in [0, 1], got 1.5"),
        ("bearing_sigma_deg", 1e9, "usbl.bearing_sigma_deg: must be a finite number in [0, 45]"),
        ("period_s", math.inf, "usbl.period_s: must be a finite number in [0, 3600], got inf"),
        ("range_sigma_m", "0.1", "usbl.range_sigma_m: expected a number, got '0.1'"),
        ("preset", "best\none", "usbl.preset: unknown USBL preset 'best\\none' (known: ideal"),
        ("lever_arm_m", 0.1, "unknown config key 'usbl.lever_arm_m' for UsblConfig"),
    ],
)
def test_hostile_values_are_refused_in_one_line(key, value, message):
    with pytest.raises(ConfigError) as err:
        from_dict(EnvConfig, {"usbl": {key: value}})
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_a_config_built_in_python_is_checked_by_the_sensor():
    with pytest.raises(ValueError, match=r"^latency_s: must be a finite number in \[0, 60\]"):
        UsblSensor(UsblConfig(latency_s=-1.0))
    with pytest.raises(ValueError, match=r"^preset: unknown USBL preset 'x'"):
        UsblSensor(UsblConfig(preset="x"))


# ----------------------------------------------------------------------- the env
SHORT = replace(EnvConfig(), episode_s=4.0, randomise_vehicle=False)


def _run(cfg: EnvConfig, seed: int, steps: int = 20):
    from uwdock.rl.env.docking_env import DockingEnv
    from uwdock.rl.policy.baselines import PIDController

    env = DockingEnv(cfg)
    pid = PIDController.for_env(cfg)
    sigmas: list[float] = []
    update = env.filter.update_position
    env.filter.update_position = lambda p, s: (sigmas.append(s), update(p, s))[1]
    try:
        obs, info = env.reset(seed=seed)
        detected = [info["detected"]]
        for _ in range(steps):
            obs, _, _, _, info = env.step(pid.act(obs))
            detected.append(info["detected"])
        return env, detected, sigmas, env.filter.x.copy()
    finally:
        env.close()


def test_acoustic_source_never_detects_and_lives_on_the_fixes():
    from uwdock.rl.cli import OBS_CHOICES
    from uwdock.rl.env.docking_env import SOURCE_CLASSES

    assert "acoustic" in SOURCE_CLASSES and "acoustic" in OBS_CHOICES.choices
    cfg = replace(SHORT, obs_source="acoustic")
    env, detected, sigmas, _ = _run(cfg, seed=2)
    assert not any(detected)
    assert not env.world.with_camera and env.filter.cfg.fuse
    assert len(sigmas) == 5  # t = 0, 1, 2, 3, 4 s over 20 steps at 5 Hz
    assert env.filter.measured  # the acoustic fixes are its only measurements


def test_env_with_a_realistic_preset_is_seeded_and_uses_the_preset():
    cfg = replace(SHORT, obs_source="acoustic", usbl={"preset": "cerulean-rovl"})
    env, _, sigmas, x = _run(cfg, seed=9)
    assert env.usbl.cfg == USBL_PRESETS["cerulean-rovl"]
    assert 0 < len(sigmas) <= 5
    _, _, sigmas2, x2 = _run(cfg, seed=9)
    assert sigmas2 == sigmas
    np.testing.assert_array_equal(x2, x)


def test_eval_cli_takes_the_acoustic_source_and_a_usbl_preset(run_cli, tmp_path):
    import json

    from uwdock.rl import cli

    env_cfg = tmp_path / "env.toml"
    env_cfg.write_text("episode_s = 1.0\n[usbl]\nlatency_s = 0.4\n")
    args = ["eval", "--policy", "pid", "--episodes", "1", "--obs", "acoustic", "--videos", ""]
    res = run_cli(
        cli.main, *args, "--usbl", "evologics-s2cr", "--config", env_cfg, "--out", tmp_path / "e"
    )
    assert res.code == 0, res.err
    config = json.loads((tmp_path / "e" / "summary.json").read_text())["config"]
    # the flag picks the preset, the file's [usbl] field still overrides it
    assert config["obs_source"] == "acoustic"
    assert config["usbl"]["preset"] == "evologics-s2cr" and config["usbl"]["latency_s"] == 0.4
    res = run_cli(cli.main, *args, "--usbl", "perfect", "--out", tmp_path / "e2")
    assert res.code == 2 and "'perfect' is not one of" in res.err
