"""One world config: ``EnvConfig.world`` (``[env.world]``) is the only place a world field is
set, and the loader reads the flat ``[env]`` keys of run folders and policies written before it
existed (``EnvConfig.MOVED_KEYS``) without rewriting them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
import tomli_w

from tests.hostile_runs import assert_refused, run_digest
from uwdock.dockcore.config import (
    ConfigError,
    dumps_toml,
    from_dict,
    load_config,
    merge,
    read_toml,
    replace,
    to_dict,
)
from uwdock.rl import cli
from uwdock.rl.env.config import LEGACY_IDEAL_USBL_KEYS, LEGACY_WORLD_KEYS, EnvConfig
from uwdock.rl.train.training import TrainConfig, run_config
from uwdock.sim.usbl import USBL_PRESETS
from uwdock.sim.world_config import WorldConfig

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted(p for p in (ROOT / "rl" / "policies").iterdir() if (p / "config.toml").is_file())
#: The shipped run configs written before [env.world] existed (flat world keys in [env]).
LEGACY = [p for p in SHIPPED if "world" not in read_toml(p / "config.toml")["train"]["env"]]

#: A value other than the default for every WorldConfig field (a table: some of its keys).
NON_DEFAULT: dict[str, Any] = {
    "physics_hz": 600.0,
    "tank_size_m": [21.0, 10.0, 6.0],
    "marker_set_path": "markers/ds.toml",
    "camera_file": "cam.yaml",
    "camera_width_px": 320,
    "water_preset": "coastal",
    "water_device": "cpu",
    "randomise_vehicle": False,
    "camera_mount_error_m": 0.02,
    "camera_mount_error_deg": 1.5,
    "current": {"mode": "constant", "velocity_ned_mps": [0.1, -0.05, 0.0]},
    "vehicle": {"mass_kg": 160.0},
    "vehicle_randomisation": {"mass_rel": 0.1},
    "batch_contact": "own",
}


def _names(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    return d


def _assert_within(part: Any, whole: Any, key: str = "") -> None:
    """Every value of ``part`` (nested tables key by key) is the same in ``whole``."""
    if isinstance(part, dict):
        assert isinstance(whole, dict), key
        for k, v in part.items():
            assert k in whole, f"{key}.{k} missing"
            _assert_within(v, whole[k], f"{key}.{k}")
    else:
        assert part == whole, (key, part, whole)


def _ideal_usbl_moved(raw: dict[str, Any]) -> dict[str, Any]:
    """A run's ``[train]`` table with the "ideal" USBL numbers its ``[env.estimator]`` held
    before ``[env.usbl]`` existed taken out, after checking that they are the ideal preset's (so
    the loader drops them: the model the run trained with is the preset's, unchanged)."""
    est = dict(raw["env"].get("estimator", {}))
    held = {new: est.pop(old) for old, new in LEGACY_IDEAL_USBL_KEYS.items() if old in est}
    ideal = USBL_PRESETS["ideal"]
    assert all(v == getattr(ideal, k) for k, v in held.items()), held
    return raw | {"env": raw["env"] | {"estimator": est}}


def _flat_layout(env: dict[str, Any]) -> dict[str, Any]:
    """An ``[env]`` table of the current layout written as before ``[env.world]`` existed (the
    world fields of that time flat; those added since did not exist)."""
    out = {k: v for k, v in env.items() if k != "world"}
    return out | {k: v for k, v in env["world"].items() if k in LEGACY_WORLD_KEYS}


def test_env_config_shares_no_field_name_with_the_world_config():
    assert _names(EnvConfig) & _names(WorldConfig) == set()
    assert "world" in _names(EnvConfig)
    # the old flat keys are world fields, and every one of them is lifted into world
    assert set(LEGACY_WORLD_KEYS) <= _names(WorldConfig)
    assert dict(EnvConfig.MOVED_KEYS) == dict.fromkeys(LEGACY_WORLD_KEYS, "world")


@pytest.mark.parametrize("name", sorted(_names(WorldConfig)))
def test_every_world_field_is_set_from_env_world(tmp_path, name):
    """Each WorldConfig field (a new one too: NON_DEFAULT must name it) is set through
    ``[env.world]`` of a training config and of an env config."""
    assert set(NON_DEFAULT) == _names(WorldConfig), "give the new world field a value here"
    value = NON_DEFAULT[name]
    default = to_dict(WorldConfig())[name]
    want = merge(default, value) if isinstance(value, dict) else value
    assert want != default
    train_file = tmp_path / "train.toml"
    train_file.write_text(tomli_w.dumps({"env": {"world": {name: value}}}), encoding="utf-8")
    env_file = tmp_path / "env.toml"
    env_file.write_text(tomli_w.dumps({"env": {"world": {name: value}}}), encoding="utf-8")
    from_train = load_config(TrainConfig, train_file, section="train").env
    from_env = load_config(EnvConfig, env_file, section="env")
    for cfg in (from_train, from_env):
        assert to_dict(cfg.world)[name] == want
        assert to_dict(cfg.world) == merge(to_dict(WorldConfig()), {name: want})


def test_shipped_policies_in_both_layouts():
    assert len(LEGACY) >= 2 and len(SHIPPED) > len(LEGACY)


@pytest.mark.parametrize("policy", sorted(set(SHIPPED) - set(LEGACY)), ids=lambda p: p.name)
def test_shipped_policies_in_the_current_layout_load_unchanged(policy):
    """A run config written with [env.world] loads with every world value as written."""
    raw = read_toml(policy / "config.toml")["train"]
    assert not set(LEGACY_WORLD_KEYS) & set(raw["env"])  # nothing flat left to lift
    cfg = run_config(policy)
    _assert_within(_ideal_usbl_moved(raw), to_dict(cfg))


@pytest.mark.parametrize("policy", LEGACY, ids=lambda p: p.name)
def test_shipped_policies_load_through_the_shim_unchanged(policy):
    """The shipped run configs keep the flat layout on disk; the loader lifts every flat world
    key into world with the same value, and every other value stays where it was."""
    raw_bytes = (policy / "config.toml").read_bytes()
    raw = _ideal_usbl_moved(read_toml(policy / "config.toml")["train"])
    assert "world" not in raw["env"] and "camera_width_px" in raw["env"]  # the old layout
    cfg = run_config(policy)
    moved = {k: raw["env"][k] for k in LEGACY_WORLD_KEYS if k in raw["env"]}
    assert set(moved) >= {"physics_hz", "tank_size_m", "vehicle", "current", "water_preset"}
    want = raw | {"env": {k: v for k, v in raw["env"].items() if k not in moved} | {"world": moved}}
    _assert_within(want, to_dict(cfg))  # (fields added since it was written: their defaults)
    world = to_dict(cfg.env.world)
    assert _drop_none(world) == merge(_drop_none(to_dict(WorldConfig())), moved)
    assert (policy / "config.toml").read_bytes() == raw_bytes  # read, never rewritten
    # the same config in the current layout is the same config
    assert from_dict(TrainConfig, to_dict(cfg)) == cfg


def test_a_key_given_flat_and_in_env_world_is_one_line(tmp_path):
    path = tmp_path / "env.toml"
    path.write_text("[env]\nphysics_hz = 600.0\n[env.world]\nphysics_hz = 300.0\n")
    with pytest.raises(ConfigError) as err:
        load_config(EnvConfig, path, section="env")
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("world.physics_hz: given twice")
    # a flat table and the same table in world: refused too, under [train]
    path.write_text("[env.vehicle]\nmass_kg = 1.0\n[env.world.vehicle]\nmass_kg = 2.0\n")
    with pytest.raises(ConfigError, match=r"^env\.world\.vehicle: given twice"):
        load_config(TrainConfig, path, section="train")
    # flat keys and [env.world] together are fine when they name different fields
    path.write_text("[env]\nphysics_hz = 600.0\n[env.world]\ncamera_width_px = 320\n")
    w = load_config(EnvConfig, path, section="env").world
    assert (w.physics_hz, w.camera_width_px) == (600.0, 320)


def test_unknown_keys_stay_errors(tmp_path):
    path = tmp_path / "env.toml"
    path.write_text("[env.world]\nphysics_hertz = 600.0\n")
    with pytest.raises(ConfigError, match=r"^unknown config key 'world\.physics_hertz'"):
        load_config(EnvConfig, path, section="env")
    path.write_text("[env]\nphysics_hertz = 600.0\n")  # not a key that moved: unknown
    with pytest.raises(ConfigError, match=r"^unknown config key 'env\.physics_hertz'"):
        load_config(TrainConfig, path, section="train")
    path.write_text("[env]\nworld = 3\n")
    with pytest.raises(ConfigError, match=r"^world: expected a table"):
        load_config(EnvConfig, path, section="env")


def test_replace_changes_a_world_field_by_its_old_name_or_in_world():
    cfg = EnvConfig()
    a = replace(cfg, world={"water_preset": "coastal"})
    b = replace(cfg, water_preset="coastal")  # the key that moved: the same change
    c = replace(cfg, world=replace(cfg.world, water_preset="coastal"))
    assert a == b == c and a.world.water_preset == "coastal"
    assert a.world.vehicle == cfg.world.vehicle  # the rest of the world kept
    with pytest.raises(ConfigError, match=r"world\.camera_width_px: must be 0 or >= 16"):
        replace(cfg, world={"camera_width_px": 8})
    with pytest.raises(ConfigError, match="given twice"):
        replace(cfg, world={"water_preset": "turbid"}, water_preset="coastal")


def test_world_rules_are_reported_under_world():
    from uwdock.datasets.synth import SynthConfig

    with pytest.raises(ValueError, match=r"^world\.camera_width_px: must be 0 or >= 16, got 8"):
        dataclasses.replace(EnvConfig(), world=WorldConfig(camera_width_px=8)).validate()
    stiff = {"vehicle": {"mass_kg": 1.0, "linear_damping": [1e5] * 6}}
    with pytest.raises(ConfigError, match=r"^world\.vehicle\.linear_damping: too stiff"):
        from_dict(EnvConfig, {"world": stiff})
    with pytest.raises(ConfigError, match=r"^world\.physics_hz: must be a positive multiple"):
        from_dict(EnvConfig, {"world": {"physics_hz": 301.0}})
    # the width rule is one rule: SynthConfig's width says the same
    with pytest.raises(ConfigError, match=r"^width_px: must be 0 or >= 16, got 8"):
        from_dict(SynthConfig, {"width_px": 8})


def test_eval_flags_and_an_old_layout_config_set_the_world(run_cli, tmp_path):
    """``rl eval --config`` of the flat layout, with ``--water``: the flag wins, the file's
    other world keys are kept; the report records them under world."""
    old = tmp_path / "old.toml"
    old.write_text(
        '[env]\nepisode_s = 1.0\nphysics_hz = 600.0\nwater_preset = "turbid"\n'
        '[env.current]\nmode = "constant"\n'
    )
    out = tmp_path / "ev"
    res = run_cli(
        cli.main, "eval", "--policy", "pid", "--obs", "proxy", "--episodes", "1", "--videos", "",
        "--config", old, "--water", "coastal", "--out", out,
    )  # fmt: skip
    assert res.code == 0, res.err
    env = json.loads((out / "summary.json").read_text())["config"]
    world = env.get("env", env)["world"]
    assert (world["water_preset"], world["physics_hz"]) == ("coastal", 600.0)
    assert world["current"]["mode"] == "constant"
    # rl episode: --width goes to world (checked before anything renders)
    res = run_cli(cli.main, "episode", "--out", tmp_path / "ep", "--width", "8")
    assert "world.camera_width_px: must be 0 or >= 16" in assert_refused(res, tmp_path / "ep")
    old.write_text("[env]\ncamera_width_px = 8\n")
    res = run_cli(cli.main, "episode", "--out", tmp_path / "ep", "--config", old)
    assert "world.camera_width_px: must be 0 or >= 16" in assert_refused(res, tmp_path / "ep")


def test_an_old_layout_run_folder_resumes_unchanged(run_cli, tmp_path):
    """A run folder whose config.toml has the flat layout (as every run before [env.world]):
    resumed from its first checkpoint, it gives the same checkpoints and policy as the run never
    stopped, and its config.toml is left as it was (no config change is seen)."""
    small = tmp_path / "small.toml"
    small.write_text(
        "n_envs = 1\ntotal_steps = 64\ncheckpoint_every = 32\neval_every = 0\n"
        "[env]\nepisode_s = 2.0\n[env.world]\nphysics_hz = 600.0\n"
        "[ppo]\nn_steps = 32\nbatch_size = 32\nn_epochs = 1\n"
    )
    run = tmp_path / "run"
    res = run_cli(cli.main, "train", "--config", small, "--out", run, "--water", "coastal")
    assert res.code == 0, res.err
    new = read_toml(run / "config.toml")
    assert new["train"]["env"]["world"]["water_preset"] == "coastal"  # the flag, in world
    assert new["train"]["env"]["world"]["physics_hz"] == 600.0
    full = run_digest(run)
    # the run as an old version wrote it: flat world keys in [train.env]
    flat = {"train": new["train"] | {"env": _flat_layout(new["train"]["env"])}}
    old_text = tomli_w.dumps(flat)
    (run / "config.toml").write_text(old_text, encoding="utf-8")
    assert run_config(run) == load_config(TrainConfig, small, section="train", overrides={
        "env": {"world": {"water_preset": "coastal"}}})  # fmt: skip
    # stopped after its first checkpoint
    for name in ("DONE", "model.json", "weights.npz"):
        (run / name).unlink()
    last = sorted((run / "checkpoints").glob("step_*"))[-1]
    for p in sorted(last.rglob("*"), reverse=True):
        p.unlink() if p.is_file() else p.rmdir()
    last.rmdir()
    # resumed with the same config given again in the flat layout (merged with the run's own)
    again = tmp_path / "again.toml"
    again.write_text('[env]\nphysics_hz = 600.0\nwater_preset = "coastal"\n')
    res = run_cli(cli.main, "train", "--out", run, "--resume", "--config", again)
    assert res.code == 0, res.err
    assert (run / "config.toml").read_text(encoding="utf-8") == old_text  # not rewritten
    log = [json.loads(s) for s in (run / "resume_log.jsonl").read_text().splitlines()]
    assert log[-1]["config_changed"] == [] and log[-1]["from_step"] == 32
    resumed = run_digest(run)
    assert {k: v for k, v in resumed.items() if k != "config.toml"} == {
        k: v for k, v in full.items() if k != "config.toml"
    }


def test_dumped_env_configs_use_the_world_table():
    text = dumps_toml({"env": EnvConfig()})
    assert "[env.world]" in text and "[env.world.vehicle]" in text
    assert "\nphysics_hz" not in text.split("[env.world]")[0]


def test_a_sweep_grid_sets_a_world_field_by_either_name():
    from uwdock.rl.train.sweep import SweepConfig, parse_grid, plan_trials

    grid = parse_grid(["env.water_preset=coastal,turbid", "env.world.physics_hz=600.0"])
    trials = plan_trials(TrainConfig(), SweepConfig(seeds=(0,)), grid)
    got = [(t.config.env.world.water_preset, t.config.env.world.physics_hz) for t in trials]
    assert got == [("coastal", 600.0), ("turbid", 600.0)]
