"""One typed path for the env's settings: flags are typed where the command line is parsed
(presets as objects), every layer is data in the current layout before it merges, the reported
settings are typed selectors of ``EnvConfig``, each preset's numbers live once, and run folders
of older layouts still load."""

from __future__ import annotations

import ast
import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from uwdock.dockcore.config import field_path, from_dict, has_path, read_toml, to_dict
from uwdock.rl import cli
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.estimator import EstimatorConfig
from uwdock.rl.policy.env_settings import (
    REPORTED,
    EnvFlags,
    command_env,
    policy_training_env,
)
from uwdock.rl.policy.policy_io import POLICY_INTERFACE_FIELDS
from uwdock.sim.navigation import NAV_PRESETS, NavConfig
from uwdock.sim.usbl import USBL_PRESETS, UsblConfig
from uwdock.sim.water import PRESETS, Water

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "rl" / "policies" / "scratch_error_model_ppo"


# ------------------------------------------------------------------ typed selectors
def test_field_path_follows_the_attributes_and_refuses_what_is_not_a_field():
    assert field_path(EnvConfig, lambda c: c.world.camera_width_px) == ("world", "camera_width_px")
    assert field_path(EnvConfig, lambda c: c.usbl.preset) == ("usbl", "preset")
    assert field_path(EnvConfig, lambda c: c.episode_s) == ("episode_s",)
    with pytest.raises(AttributeError, match="WorldConfig has no field 'width_px'"):
        field_path(EnvConfig, lambda c: c.world.width_px)
    with pytest.raises(AttributeError, match="not a table"):
        field_path(EnvConfig, lambda c: c.episode_s.real)
    with pytest.raises(AttributeError, match="reads no field"):
        field_path(EnvConfig, lambda c: 3)


def test_reported_settings_are_fields_of_the_config_with_one_name_each():
    names = [r.name for r in REPORTED]
    assert len(set(names)) == len(names)
    cfg = EnvConfig()
    for r in REPORTED:
        obj = cfg
        for part in r.path:
            obj = getattr(obj, part)
        assert obj == r.select(cfg), r.name
    # the render width has the one name the config gives it, from the flag to the renderer
    assert ("world", "camera_width_px") in {r.path for r in REPORTED}
    assert "camera_width_px" in names and "width_px" not in names
    opts = {o for p in cli.eval_cmd.params for o in getattr(p, "opts", [])}
    assert {"--camera-width-px", "--width"} <= opts  # --width: the old spelling, kept


def test_has_path_reads_nested_data():
    data = {"world": {"camera_width_px": 320}, "episode_s": None}
    assert has_path(data, ("world", "camera_width_px"))
    assert has_path(data, ("episode_s",))
    assert not has_path(data, ("world", "water_preset"))
    assert not has_path(data, ("episode_s", "x"))


# ------------------------------------------------------------------ presets as objects
def test_flags_turn_preset_names_into_objects_where_the_line_is_parsed():
    assert cli.USBL_TYPE.convert("cerulean-rovl", None, None) == UsblConfig(preset="cerulean-rovl")
    assert cli.NAV_TYPE.convert("mems-ahrs-dvl", None, None) == NavConfig(preset="mems-ahrs-dvl")
    water = cli.WATER_TYPE.convert("coastal", None, None)
    assert water == Water("coastal", PRESETS["coastal"])
    assert set(cli.USBL_TYPE.choices) == set(USBL_PRESETS)
    assert set(cli.NAV_TYPE.choices) == set(NAV_PRESETS)


def test_a_water_file_is_read_once_at_the_edge(tmp_path):
    good = tmp_path / "w.toml"
    good.write_text("[water]\nblur_sigma_per_m = 0.002\n")
    water = cli.WATER_TYPE.convert(str(good), None, None)
    assert water.spec == str(good) and water.config.blur_sigma_per_m == 0.002


@pytest.mark.parametrize(
    "value, said",
    [("murky", "unknown 'murky'"), ("missing.toml", "missing.toml"), ("none.toml", "none.toml")],
)
def test_a_bad_water_is_one_usage_line_before_anything_runs(run_cli, tmp_path, value, said):
    out = tmp_path / "e"
    res = run_cli(
        cli.main, "eval", "--policy", "pid", "--water", value, "--episodes", "1", "--out", out
    )
    assert res.code == 2 and not out.exists()
    lines = [line for line in res.err.splitlines() if line.strip()]
    assert "--water" in lines[-1] and said in lines[-1], res.err


def test_env_flags_are_a_layer_of_the_config():
    flags = EnvFlags(
        obs_source="acoustic",
        error_model_path=Path("m.json"),
        terminate_on="paper",
        episode_s=12.0,
        usbl=UsblConfig(preset="evologics-s2cr"),
        nav=NavConfig(preset="mems-ahrs-dvl"),
        water=Water.named("turbid"),
        camera_width_px=320,
    )
    layer = flags.layer()
    assert layer == {
        "obs_source": "acoustic",
        "error_model_path": "m.json",
        "terminate_on": "paper",
        "episode_s": 12.0,
        "usbl": {"preset": "evologics-s2cr"},
        "nav": {"preset": "mems-ahrs-dvl"},
        "world": {"water_preset": "turbid", "camera_width_px": 320},
    }
    cfg = from_dict(EnvConfig, layer)
    assert cfg.usbl_model == USBL_PRESETS["evologics-s2cr"]
    assert cfg.world.water == Water("turbid", PRESETS["turbid"])
    assert EnvFlags().layer() == {}


# ------------------------------------------------------------------ one definition of a preset
def test_the_ideal_usbl_numbers_live_only_in_its_preset():
    assert not [f.name for f in dataclasses.fields(EstimatorConfig) if "usbl" in f.name]
    assert EnvConfig().usbl_model == USBL_PRESETS["ideal"]
    assert EnvConfig().usbl == UsblConfig()  # a preset name, its numbers taken from the preset


# ------------------------------------------------------------------ no plumbing in commands
def _command_modules() -> list[Path]:
    mods = sorted(ROOT.glob("*/cli.py")) + sorted(ROOT.glob("*/*/cli.py"))
    mods += [ROOT / "rl" / "policy" / "env_settings.py", ROOT / "rl" / "train" / "sweep.py"]
    return [m for m in mods if ".venv" not in m.parts and "build" not in m.parts]


def test_command_code_does_not_rewrite_layouts():
    """Layouts are the loader's and the stored-config readers' business (``config_layers(...,
    cls=)``, ``policy_train_env``): command code never calls the layout functions."""
    assert len(_command_modules()) >= 8
    banned = {"current_layout", "lift_moved_keys", "_lift_here", "upgrade_layout", "MOVED_KEYS"}
    for module in _command_modules():
        tree = ast.parse(module.read_text(encoding="utf-8"))
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        names |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        names |= {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        assert not names & banned, (module, names & banned)


# ------------------------------------------------------------------ old run folders
def _oldest_layout_run(tmp_path: Path) -> Path:
    """A run folder whose config is in the oldest layout: world keys flat in [env], no [usbl]
    table, the ideal acoustic model's numbers in [env.estimator] (a 2 s period of its own)."""
    folder = tmp_path / "old"
    folder.mkdir()
    for name in ("model.json", "weights.npz"):
        shutil.copy(SHIPPED / name, folder / name)
    raw = read_toml(SHIPPED / "config.toml")
    env = raw["train"]["env"]
    world = env.pop("world", {})
    env.update(world)  # flat
    env.pop("usbl", None)
    env.pop("nav", None)
    env["estimator"] = {**env.get("estimator", {}), "usbl_period_s": 2.0,
                        "usbl_sigma_floor_m": 0.15, "usbl_sigma_per_m": 0.03}  # fmt: skip
    env["camera_width_px"] = 320
    import tomli_w

    (folder / "config.toml").write_text(tomli_w.dumps(raw))
    return folder


def test_a_run_folder_of_the_oldest_layout_runs_as_it_trained(tmp_path):
    folder = _oldest_layout_run(tmp_path)
    trained = policy_training_env(str(folder))
    assert trained is not None
    cfg = trained.cfg
    assert cfg.world.camera_width_px == 320
    assert cfg.usbl == UsblConfig(period_s=2.0)  # the estimator's own number, now in [usbl]
    assert cfg.usbl_model == dataclasses.replace(USBL_PRESETS["ideal"], period_s=2.0)
    resolved = command_env(str(folder), defaults={"terminate_on": "strict"})
    assert resolved.cfg.usbl_model.period_s == 2.0
    assert resolved.settings()["camera_width_px"] == {"value": 320, "from": "policy config"}
    # --usbl names a whole model: the policy's own fields of its model do not apply
    flagged = command_env(str(folder), flags=EnvFlags(usbl=UsblConfig(preset="ideal")))
    assert flagged.cfg.usbl_model == USBL_PRESETS["ideal"]
    assert flagged.settings()["usbl"] == {"value": "ideal", "from": "flag"}
    # written back, the config is in the current layout and reads the same
    again = from_dict(EnvConfig, to_dict(cfg))
    assert again == cfg and "usbl_period_s" not in to_dict(cfg)["estimator"]


def test_the_policys_interface_is_its_own_even_under_another_policys_env(tmp_path):
    """The observation layout and action scaling are what the weights were made for: read from
    the policy (once, in the same resolution), never from --env-from or a flag."""
    folder = _oldest_layout_run(tmp_path)
    other = tmp_path / "other"
    shutil.copytree(folder, other)
    text = (other / "config.toml").read_text()
    assert "obs_contact = " in text or "obs_uncertainty = " in text
    raw = read_toml(other / "config.toml")
    raw["train"]["env"]["wrench_scale"] = 0.5
    raw["train"]["env"]["obs_frames"] = 3
    import tomli_w

    (other / "config.toml").write_text(tomli_w.dumps(raw))
    resolved = command_env(str(folder), env_from=other)
    own = read_toml(folder / "config.toml")["train"]["env"]
    for name in POLICY_INTERFACE_FIELDS:
        if name in own:
            got = getattr(resolved.cfg, name)
            assert to_dict(got) == own[name] or got == own[name], name
    assert resolved.cfg.wrench_scale == own.get("wrench_scale", 1.0) != 0.5
    assert resolved.cfg.obs_frames == own.get("obs_frames", 1) != 3


def test_eval_records_the_settings_under_their_one_name(run_cli, tmp_path):
    short = tmp_path / "short.toml"
    short.write_text("episode_s = 1.0\n")
    out = tmp_path / "e"
    res = run_cli(
        cli.main, "eval", "--policy", "pid", "--obs", "acoustic", "--episodes", "1",
        "--videos", "", "--config", short, "--camera-width-px", "320", "--out", out,
    )  # fmt: skip
    assert res.code == 0, res.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["env_settings"]["camera_width_px"] == {"value": 320, "from": "flag"}
    assert summary["config"]["world"]["camera_width_px"] == 320
