"""``extends = "BASE"`` in a TOML config (dockcore.config.config_layers): the base loads first,
the file's own values merge over it key by key, recursively; bad chains are one line."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from uwdock.dockcore.config import (
    EXTENDS_DEPTH,
    ROOT,
    config_data,
    config_layers,
    load_config,
    replace,
)
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.rl.train.training import TrainConfig

BASE = """\
total_steps = 5000
n_envs = 4
seed = 3

[env]
obs_source = "proxy"
terminate_on = "strict"

[env.reward]
collision_penalty = 20.0
precision_gain = 1.0
precision_scale_m = 0.2

[env.world]
camera_width_px = 480

[curriculum]
steps = 1000
near_start_height_m = [0.05, 0.4]
"""


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def _refused(path: Path, section: str | None = "train") -> str:
    with pytest.raises(ConfigError) as err:
        config_data(path, section=section, cls=TrainConfig)
    text = str(err.value)
    assert "\n" not in text and isinstance(err.value, DockError)
    return text


def test_the_files_values_merge_over_the_base_key_by_key(tmp_path):
    """Tables merge (a key the file does not set keeps the base's), scalars and arrays
    replace; ground truth written out."""
    _write(tmp_path / "base.toml", BASE)
    child = _write(
        tmp_path / "child.toml",
        'extends = "base.toml"\ntotal_steps = 800\n\n[env.reward]\ncollision_penalty = 70.0\n\n'
        "[curriculum]\nnear_start_height_m = [0.1, 0.2]\n",
    )
    assert config_data(child) == {
        "total_steps": 800,
        "n_envs": 4,
        "seed": 3,
        "env": {
            "obs_source": "proxy",
            "terminate_on": "strict",
            "reward": {"collision_penalty": 70.0, "precision_gain": 1.0, "precision_scale_m": 0.2},
            "world": {"camera_width_px": 480},
        },
        "curriculum": {"steps": 1000, "near_start_height_m": [0.1, 0.2]},
    }
    cfg = load_config(TrainConfig, child, section="train")
    assert (cfg.total_steps, cfg.n_envs, cfg.seed) == (800, 4, 3)
    assert cfg.env.obs_source == "proxy" and cfg.env.terminate_on == "strict"
    assert cfg.env.reward.collision_penalty == 70.0
    assert (cfg.env.reward.precision_gain, cfg.env.reward.precision_scale_m) == (1.0, 0.2)
    assert cfg.env.world.camera_width_px == 480
    assert cfg.curriculum.steps == 1000 and cfg.curriculum.near_start_height_m == (0.1, 0.2)


def test_a_file_overriding_one_nested_key_changes_only_that_key(tmp_path):
    base = _write(tmp_path / "base.toml", BASE)
    child = _write(
        tmp_path / "child.toml", 'extends = "base.toml"\n\n[env.reward]\nprecision_gain = 0.5\n'
    )
    one = load_config(TrainConfig, base, section="train")
    two = load_config(TrainConfig, child, section="train")
    assert two == replace(one, env=replace(one.env, reward={"precision_gain": 0.5}))
    assert two.env.reward.precision_gain == 0.5 and one.env.reward.precision_gain == 1.0


def test_a_chain_of_three(tmp_path):
    """c extends b extends a: each file's values over the one before; the layers come furthest
    base first, each with only its own values."""
    a = _write(tmp_path / "a.toml", "total_steps = 100\nn_envs = 2\nseed = 1\n")
    b = _write(
        tmp_path / "sub" / "b.toml", f'extends = "{a}"\nn_envs = 8\n[env]\nepisode_s = 30.0\n'
    )
    c = _write(tmp_path / "sub" / "c.toml", 'extends = "b.toml"\nseed = 7\n')
    cfg = load_config(TrainConfig, c, section="train")
    assert (cfg.total_steps, cfg.n_envs, cfg.seed, cfg.env.episode_s) == (100, 8, 7, 30.0)
    layers = config_layers(c, section="train")
    assert [layer.path for layer in layers] == [a, b, c]
    assert [layer.base for layer in layers] == [True, True, False]
    assert [layer.data for layer in layers] == [
        {"total_steps": 100, "n_envs": 2, "seed": 1},
        {"n_envs": 8, "env": {"episode_s": 30.0}},
        {"seed": 7},
    ]


def test_a_file_that_only_extends_is_its_base(tmp_path):
    base = _write(tmp_path / "base.toml", BASE)
    alias = _write(tmp_path / "alias.toml", '# the same as base.toml\nextends = "base.toml"\n')
    assert load_config(TrainConfig, alias, section="train") == load_config(
        TrainConfig, base, section="train"
    )


def test_relative_paths_resolve_beside_the_file_then_above_it_then_at_the_repository_root(
    tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)  # not where any of these files is looked for
    _write(tmp_path / "top" / "base.toml", "total_steps = 111\n")
    _write(tmp_path / "top" / "sub" / "base.toml", "total_steps = 222\n")
    beside = _write(tmp_path / "top" / "sub" / "x.toml", 'extends = "base.toml"\n')
    above = _write(tmp_path / "top" / "sub" / "deeper" / "y.toml", 'extends = "base.toml"\n')
    from_top = _write(tmp_path / "top" / "sub" / "z.toml", 'extends = "top/base.toml"\n')
    shipped = _write(
        tmp_path / "mine.toml", 'extends = "configs/realistic/policy.toml"\nseed = 5\n'
    )
    assert config_data(beside)["total_steps"] == 222
    assert config_data(above)["total_steps"] == 222  # the nearest folder above that holds it
    assert config_data(from_top)["total_steps"] == 111
    policy = load_config(TrainConfig, ROOT / "configs/realistic/policy.toml", section="train")
    assert load_config(TrainConfig, shipped, section="train") == replace(policy, seed=5)
    assert config_layers(shipped)[-2].path == ROOT / "configs" / "realistic" / "policy.toml"


def test_a_base_in_the_older_flat_layout_takes_overrides_in_the_current_one(tmp_path):
    """A run folder's config.toml written before [env.world] existed (flat world keys in
    [env], inside a [train] table) extended by a file in the current layout: each file is put in
    the current layout before they merge, so the key is not "given twice"."""
    _write(
        tmp_path / "run" / "config.toml",
        "[train]\ntotal_steps = 64\n[train.env]\ncamera_width_px = 480\n",
    )
    child = _write(
        tmp_path / "child.toml", 'extends = "run/config.toml"\n[env.world]\ncamera_width_px = 640\n'
    )
    cfg = load_config(TrainConfig, child, section="train")
    assert cfg.total_steps == 64 and cfg.env.world.camera_width_px == 640


def test_a_cycle_is_one_line(tmp_path):
    a = _write(tmp_path / "a.toml", 'extends = "b.toml"\nseed = 1\n')
    _write(tmp_path / "b.toml", 'extends = "a.toml"\nseed = 2\n')
    line = _refused(a)
    assert line == (
        f"config {a}: extends goes round in a cycle: {a} -> {tmp_path / 'b.toml'} -> "
        f"{tmp_path / 'a.toml'}"
    )
    itself = _write(tmp_path / "self.toml", 'extends = "self.toml"\nseed = 1\n')
    assert "extends goes round in a cycle" in _refused(itself)


def test_a_missing_base_is_one_line(tmp_path):
    child = _write(tmp_path / "child.toml", 'extends = "nowhere_at_all_7f3a.toml"\nseed = 1\n')
    line = _refused(child)
    assert line.startswith(f"{child}: extends 'nowhere_at_all_7f3a.toml': no such file in ")
    absent = tmp_path / "absent.toml"
    child2 = _write(tmp_path / "child2.toml", f'extends = "{absent}"\nseed = 1\n')
    assert _refused(child2) == f"{child2}: extends '{absent}': no such file"


def test_a_chain_deeper_than_the_limit_is_one_line(tmp_path):
    _write(tmp_path / "f0.toml", "seed = 0\n")
    for k in range(1, EXTENDS_DEPTH + 1):
        _write(tmp_path / f"f{k}.toml", f'extends = "f{k - 1}.toml"\nseed = {k}\n')
    last_ok = tmp_path / f"f{EXTENDS_DEPTH - 1}.toml"  # EXTENDS_DEPTH files in all
    assert config_data(last_ok)["seed"] == EXTENDS_DEPTH - 1
    line = _refused(tmp_path / f"f{EXTENDS_DEPTH}.toml")
    assert f"its extends chain holds more than {EXTENDS_DEPTH} files" in line


@pytest.mark.parametrize(
    "value", ["3", "true", '["base.toml"]', '{ path = "base.toml" }', '""', '"  "']
)
def test_extends_that_is_not_a_path_is_one_line(tmp_path, value):
    _write(tmp_path / "base.toml", BASE)
    child = _write(tmp_path / "child.toml", f"extends = {value}\nseed = 1\n")
    assert _refused(child).startswith(f"{child}: extends: expected a config file's path, got ")


def test_extends_inside_the_section_table_is_one_line(tmp_path):
    _write(tmp_path / "base.toml", BASE)
    child = _write(tmp_path / "child.toml", '[train]\nextends = "base.toml"\nseed = 1\n')
    assert _refused(child) == f"{child}: extends goes at the top of the file, not in [train]"


def test_a_base_that_is_not_a_regular_utf8_toml_file_is_one_line(tmp_path):
    (tmp_path / "folder.toml").mkdir()
    child = _write(tmp_path / "child.toml", 'extends = "folder.toml"\nseed = 1\n')
    assert "is a folder, not a file" in _refused(child)
    (tmp_path / "latin1.toml").write_bytes("seed = 1 # caf\xe9\n".encode("latin-1"))
    child = _write(tmp_path / "child.toml", 'extends = "latin1.toml"\nseed = 1\n')
    assert "is not UTF-8 text" in _refused(child)
    _write(tmp_path / "broken.toml", "seed = = 1\n")
    child = _write(tmp_path / "child.toml", 'extends = "broken.toml"\nseed = 1\n')
    assert _refused(child).startswith(f"malformed TOML in {tmp_path / 'broken.toml'}")
    _write(tmp_path / "empty.toml", "# nothing\n")
    child = _write(tmp_path / "child.toml", 'extends = "empty.toml"\nseed = 1\n')
    assert _refused(child) == (
        f"base config {tmp_path / 'empty.toml'} (extended by {child}) is empty (only comments "
        "or empty tables): it sets no [train] value"
    )
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "fifo.toml")
        child = _write(tmp_path / "child.toml", 'extends = "fifo.toml"\nseed = 1\n')
        assert "is a FIFO (named pipe), not a regular file" in _refused(child)


def test_a_bad_value_in_a_base_names_its_key(tmp_path):
    _write(tmp_path / "base.toml", "n_envs = -1\n")
    child = _write(tmp_path / "child.toml", 'extends = "base.toml"\nseed = 1\n')
    with pytest.raises(ConfigError, match=r"^n_envs: "):
        load_config(TrainConfig, child, section="train")


def test_the_env_line_names_the_base_a_value_came_from(tmp_path, monkeypatch):
    """`rl eval --config FILE` prints which layer set each setting: a value FILE takes from its
    base is labelled with the base's path, one FILE sets itself with "--config"."""
    from uwdock.rl.policy.env_settings import command_env

    monkeypatch.chdir(tmp_path)
    _write(
        tmp_path / "bases" / "water.toml",
        '[env]\nepisode_s = 40.0\n[env.world]\nwater_preset = "turbid"\n'
        '[env.usbl]\npreset = "evologics-s2cr"\n',
    )
    mine = _write(
        tmp_path / "mine.toml", 'extends = "bases/water.toml"\n[env.usbl]\npreset = "ideal"\n'
    )
    resolved = command_env("pid", config_path=mine, defaults={"terminate_on": "strict"})
    settings = resolved.settings()
    base = "--config base bases/water.toml"
    assert settings["water"] == {"value": "turbid", "from": base}
    assert settings["episode_s"] == {"value": 40.0, "from": base}
    assert settings["usbl"] == {"value": "ideal", "from": "--config"}
    assert settings["terminate_on"] == {"value": "strict", "from": "default"}
    assert "water turbid (--config base bases/water.toml)" in resolved.line("rl eval")


def test_rl_train_refuses_a_cycle_in_one_line(run_cli, tmp_path):
    from uwdock.rl import cli as rl_cli

    a = _write(tmp_path / "a.toml", 'extends = "b.toml"\ntotal_steps = 64\n')
    _write(tmp_path / "b.toml", 'extends = "a.toml"\nn_envs = 2\n')
    out = tmp_path / "run"
    res = run_cli(rl_cli.main, "train", "--config", a, "--out", out)
    assert res.code != 0 and not out.exists()
    lines = [line for line in res.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: config {a}: extends goes round"), lines
