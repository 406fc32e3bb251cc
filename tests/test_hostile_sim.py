"""``sim`` against hostile input: values that passed validation and then crashed (through the
CLI and through the library), output folders of other tools, in-domain extremes of the
per-episode randomisations.

Tests that render are marked ``render`` (SAPIEN on lavapipe or a GPU).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.hostile_runs import assert_refused, dead_pid, tree
from uwdock.datasets import cli as datasets_cli
from uwdock.rl import cli as rl_cli
from uwdock.rl.evaluate.episode_video import EpisodeVideoConfig, record_episode
from uwdock.sim.docking_station import DockingStationConfig, build_docking_station, build_tank
from uwdock.sim.render import CameraRig, RenderConfig, make_render_scene
from uwdock.sim.thrusters import ThrusterArray, ThrusterArrayConfig, ThrusterRandomisation
from uwdock.sim.vehicle import (
    Current,
    CurrentConfig,
    Hydrodynamics,
    Imu,
    ImuConfig,
    VehicleConfig,
    VehicleRandomisation,
)
from uwdock.sim.water import WaterConfig, WaterRandomisation, apply_water

NAN, INF = math.nan, math.inf
#: A short, small episode (two control steps).
SMALL = ("--width", "96", "--outside-width", "96", "--quiet")
QUICK = ("--seconds", "0.4", *SMALL)


# ----------------------------------------------------------------------------- the CLI


@pytest.mark.parametrize(
    "args,key",
    [
        pytest.param(("--seconds", "1e-9"), "episode_s", id="seconds-tiny"),
        pytest.param(("--seconds", "1e12"), "--seconds", id="seconds-huge"),
        pytest.param(("--seconds", "nan"), "--seconds", id="seconds-nan"),
        pytest.param(("--width", "9000"), "--width", id="width-huge"),
        pytest.param(("--outside-width", "5000"), "--outside-width", id="outside-huge"),
        pytest.param(("--seed", "-1"), "--seed", id="seed-negative"),
    ],
)
def test_bad_episode_options_stop_with_one_line(run_cli, tmp_path, args, key):
    out = tmp_path / "ep"
    res = run_cli(rl_cli.main, "episode", "--out", out, *QUICK, *args)
    assert key in assert_refused(res, out)


@pytest.mark.parametrize(
    "toml,key",
    [
        pytest.param("episode_s = nan\n", "episode_s", id="episode-nan"),
        pytest.param("spawn_auv_height_m = nan\n", "spawn_auv_height_m", id="spawn-nan"),
        pytest.param("[vehicle]\nmass_kg = nan\n", "vehicle.mass_kg", id="mass-nan"),
        pytest.param("[vehicle]\nmass_kg = 1e-9\n", "vehicle.mass_kg", id="mass-tiny"),
        pytest.param("[vehicle]\ncollision = []\n", "vehicle", id="no-hull"),
        pytest.param(
            "[vehicle.imu]\ndepth_noise_std_m = inf\n", "depth_noise_std_m", id="imu-inf"
        ),
        pytest.param(
            "[vehicle.thrusters]\nallocation_weights = [0, 0, 0, 0, 0, 0]\n",
            "allocation_weights", id="no-allocation",
        ),
        pytest.param(
            '[current]\nmode = "varying"\ndrift_knot_interval_s = 1e-300\n',
            "current.drift_knot_interval_s", id="knots-tiny",
        ),
        pytest.param("[current]\nmax_speed_mps = inf\n", "current.max_speed_mps", id="speed-inf"),
        pytest.param(
            "[vehicle_randomisation.thrusters]\naxis_deg = 1e9\n", "axis_deg", id="tilt-huge"
        ),
        pytest.param(  # in every domain, but the 300 Hz integration would blow up
            "[vehicle]\nmass_kg = 1.0\ninertia_kgm2 = [0.01, 0.01, 0.01]\n"
            "added_mass = [0, 0, 0, 0, 0, 0]\nlinear_damping = [1e5, 1e5, 1e5, 1e5, 1e5, 1e5]\n",
            "linear_damping", id="too-stiff",
        ),
    ],
)  # fmt: skip
def test_bad_episode_config_values_stop_with_one_line(run_cli, tmp_path, toml, key):
    cfg = tmp_path / "env.toml"
    short = "" if toml.startswith("episode_s") else "episode_s = 0.4\n"  # were it accepted
    cfg.write_text(short + toml, encoding="utf-8")
    out = tmp_path / "ep"
    res = run_cli(rl_cli.main, "episode", "--out", out, *SMALL, "--config", cfg)
    assert key in assert_refused(res, out)


def _foreign_folder(tmp_path, name: str, command: str):
    """A folder made by another tool before folders had owners (its provenance names it)."""
    folder = tmp_path / name
    folder.mkdir()
    (folder / "config.toml").write_text("[marker]\nsize_mm = 80.0\n")
    (folder / "provenance.json").write_text(json.dumps({"command": command}))
    return folder


def test_another_tools_folder_is_refused(run_cli, tmp_path):
    markers = _foreign_folder(tmp_path, "markers", "markers generate --out markers")
    before = tree(markers)
    res = run_cli(rl_cli.main, "episode", "--out", markers, *QUICK)
    assert "`markers generate`" in assert_refused(res)
    res = run_cli(datasets_cli.main, "render", "--out", markers, "--n", "1", "--width", "96")
    assert "`markers generate`" in assert_refused(res)
    run = tmp_path / "run"
    run.mkdir()
    (run / ".uwdock-owner.json").write_text(json.dumps({"tool": "rl train", "pid": 1}))
    res = run_cli(datasets_cli.main, "synth", "--n", "1", "--width", "96", "--out", run)
    assert "`rl train`" in assert_refused(res)
    assert tree(markers) == before
    assert list(tree(run)) == [".uwdock-owner.json"]


@pytest.mark.render
def test_render_and_episode_claim_their_folders(run_cli, tmp_path):
    synth = tmp_path / "synth"
    args = ("--n", "2", "--width", "160", "--seed", "11", "--water", "none", "--out", synth)
    assert run_cli(datasets_cli.main, "synth", *args).code == 0
    before = tree(synth)
    # the same engine and settings: before folders had owners this "resumed" and took it over
    res = run_cli(datasets_cli.main, "render", *args)
    assert "`datasets synth`" in assert_refused(res)
    assert tree(synth) == before
    episode = tmp_path / "ep"
    env_toml = tmp_path / "env.toml"  # the file's values count unless a flag overrides them
    env_toml.write_text("episode_s = 0.4\ncamera_width_px = 96\n")
    args = ("--out", episode, "--outside-width", "96", "--quiet", "--config", env_toml)
    assert run_cli(rl_cli.main, "episode", *args).code == 0
    assert json.loads((episode / "summary.json").read_text())["steps"] == 2
    assert "camera_width_px = 96" in (episode / "config.toml").read_text()
    owner = json.loads((episode / ".uwdock-owner.json").read_text())
    assert owner["tool"] == "rl episode"
    stale = episode / f".episode.mp4.{dead_pid()}.x7_k2q.uwtmp.mp4"  # a killed run's video
    stale.write_bytes(b"half a video")
    assert run_cli(rl_cli.main, "episode", *args).code == 0  # its own folder: rewritten
    assert not stale.exists()
    before = tree(episode)
    res = run_cli(datasets_cli.main, "render", "--out", episode, "--n", "1", "--width", "96")
    assert "`rl episode`" in assert_refused(res)
    assert tree(episode) == before


# ----------------------------------------------------------------------------- the library


def _img_and_range() -> tuple[np.ndarray, np.ndarray]:
    return np.full((6, 8, 3), 128, np.uint8), np.full((6, 8), 2.0, np.float32)


@pytest.mark.parametrize(
    "call,match",
    [
        pytest.param(
            lambda: record_episode(None, None, "x", cfg=EpisodeVideoConfig(panel_height_px=10**6)),
            "panel_height_px", id="video-huge",
        ),
        pytest.param(
            lambda: record_episode(None, None, "x", water=WaterConfig(gamma=NAN)),
            "gamma", id="episode-water-nan",
        ),
        pytest.param(
            lambda: make_render_scene(render_cfg=RenderConfig(near_m=NAN)), "near_m",
            id="near-nan",
        ),
        pytest.param(
            lambda: CameraRig(None, cfg=RenderConfig(shader="vertex_color")), "shader",
            id="shader-unusable",
        ),
        pytest.param(
            lambda: build_tank(None, DockingStationConfig(tank_depth_m=INF)), "tank_depth_m",
            id="tank-inf",
        ),
        pytest.param(
            lambda: build_docking_station(None, DockingStationConfig(frame_tube_m=1.5)),
            "frame_tube_m", id="tube-wider-than-cage",
        ),
        pytest.param(
            lambda: build_tank(None, DockingStationConfig(tank_depth_m=1.0)), "tank_depth_m",
            id="ds-above-the-surface",
        ),
        pytest.param(
            lambda: apply_water(*_img_and_range(), WaterConfig(blur_sigma_per_m=INF), None),
            "blur_sigma_per_m", id="blur-inf",
        ),
        pytest.param(
            lambda: apply_water(*_img_and_range(), WaterConfig(photons_at_white=1e-300), None),
            "photons_at_white", id="photons-tiny",
        ),
        pytest.param(
            lambda: WaterRandomisation(turbidity_range=(NAN, 1.0)).validate(), "turbidity",
            id="turbidity-nan",
        ),
        pytest.param(
            lambda: RenderConfig(lamp_rgb=(NAN, 1.0, 1.0)).validate(), "lamp_rgb", id="lamp-nan"
        ),
        pytest.param(
            lambda: EpisodeVideoConfig(outside_haze_scale=NAN).validate(), "outside_haze_scale",
            id="haze-nan",
        ),
        pytest.param(lambda: Hydrodynamics(VehicleConfig(mass_kg=NAN)), "mass_kg", id="mass-nan"),
        pytest.param(
            lambda: Current(CurrentConfig(range_x_mps=(NAN, 0.2))), "range_x_mps",
            id="current-nan",
        ),
        pytest.param(
            lambda: Imu(ImuConfig(depth_noise_std_m=NAN), 9.81, np.random.default_rng(0)),
            "imu", id="imu-nan",
        ),
        pytest.param(
            lambda: ThrusterArray(ThrusterArrayConfig(allocation_weights=(0.0,) * 6)),
            "allocation_weights", id="no-allocation",
        ),
        pytest.param(
            lambda: VehicleRandomisation(mass_rel=NAN).validate(), "relative", id="rel-nan"
        ),
        pytest.param(
            lambda: ThrusterRandomisation(axis_deg=NAN).validate(), "ranges", id="tilt-nan"
        ),
    ],
)  # fmt: skip
def test_python_built_configs_are_refused_with_one_line(call, match):
    with pytest.raises(ValueError, match=match) as err:
        call()
    assert "\n" not in str(err.value)


def test_randomisation_draws_at_the_edges_of_their_domains_stay_valid():
    rng = np.random.default_rng(5)
    water = WaterRandomisation(
        turbidity_range=(3.0, 3.0), beta_log_sigma=2.0, B_inf_scale_range=(10.0, 10.0),
        blur_scale_range=(10.0, 10.0), photons_at_white_range=(1.0, 1e9),
        jpeg_quality_range=(1, 1), jpeg_probability=1.0,
    )  # fmt: skip
    img, r = _img_and_range()
    for _ in range(200):
        apply_water(img, r, water.sample(rng), rng)  # validates the draw
    vehicle = VehicleRandomisation(
        mass_rel=0.99, inertia_rel=0.99, added_mass_rel=0.99, damping_rel=0.99,
        net_buoyancy_kg=1000.0,
        thrusters=ThrusterRandomisation(position_m=1.0, axis_deg=90.0, max_thrust_rel=0.99),
    )  # fmt: skip
    for _ in range(200):
        Hydrodynamics(vehicle.sample(VehicleConfig(), rng))  # validates the draw


@pytest.mark.parametrize(
    "row,where",
    [
        ("0,0,-1.0,0,0,0", "0.55 m above the water surface"),
        ("0,0,6.0,0,0,0", "below the tank floor (5 m deep)"),
        ("12,0,2.0,0,0,0", "outside the 19 x 9 m tank"),
    ],
)
def test_given_poses_must_put_the_camera_under_water(run_cli, tmp_path, row, where):
    """A camera above the water used to be rendered and its markers labelled visible."""
    poses = tmp_path / "poses.csv"
    poses.write_text(f"x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg\n0,0,2.0,0,0,0\n{row}\n")
    out = tmp_path / "r"
    line = assert_refused(run_cli(datasets_cli.main, "render", "--poses", poses, "--out", out), out)
    assert line.startswith("error: poses[1]: the camera (world NED") and where in line
