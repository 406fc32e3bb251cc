"""Recipes (issue 53): ``rl train --recipe NAME --seed N --out DIR`` trains every stage from
scratch, stage 2 from stage 1's best/, into a folder laid out as a shipped policy; a rerun
resumes and trains nothing twice; the stages equal plain ``rl train`` runs."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.hostile_runs import ROOT, run_digest
from uwdock.dockcore.config import load_config, replace
from uwdock.dockcore.errors import DockError
from uwdock.rl.train import recipe as R
from uwdock.rl.train.training import TrainConfig

STAGE = """\
n_envs = 4
simulator = "batched"
total_steps = {steps}
checkpoint_every = 64
eval_every = 64
eval_episodes = 1
[env]
obs_source = "error-model"
error_model_path = "rl/models/error_model_clear_tank_480_ar1.json"
episode_s = 3.0
[ppo]
n_steps = 32
batch_size = 64
n_epochs = 1
"""

RECIPE = """\
description = "two small stages"
batch_workers = 1

[[stage]]
name = "first"
config = "configs/first.toml"

[[stage]]
name = "second"
config = "configs/second.toml"
init_from = "first"
"""


@pytest.fixture
def small_recipe(tmp_path, monkeypatch):
    """A recipe ``small`` in a repository root of its own (its data file from this one)."""
    root = tmp_path / "repo"
    (root / "configs" / "recipes").mkdir(parents=True)
    (root / "rl" / "models").mkdir(parents=True)
    model = "rl/models/error_model_clear_tank_480_ar1.json"
    (root / model).write_bytes((ROOT / model).read_bytes())
    (root / "configs" / "first.toml").write_text(STAGE.format(steps=128))
    (root / "configs" / "second.toml").write_text(STAGE.format(steps=64))
    (root / "configs" / "recipes" / "small.toml").write_text(RECIPE)
    monkeypatch.setattr(R, "ROOT", root)
    monkeypatch.setattr(R, "RECIPES", root / "configs" / "recipes")
    return root


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_recipe_trains_its_stages_into_a_policy_folder(small_recipe, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # not the root: the recipe's data files are found from it
    out = tmp_path / "out"
    R.run_recipe("small", 3, out, progress=False)
    state = json.loads((out / "recipe.json").read_text())
    assert (state["recipe"], state["seed"], state["done"]) == ("small", 3, ["first", "second"])
    # the folder is the last stage's best/, laid out as a shipped policy, the first stage beside
    for folder, stage in ((out, "second"), (out / "first", "first")):
        best = out / "runs" / stage / "best"
        for name in ("model.json", "weights.npz"):
            assert _sha(folder / name) == _sha(best / name)
        sums = dict(line.split()[::-1] for line in (folder / "checksums.sha256").read_text()
                    .splitlines())  # fmt: skip
        assert sums == {n: _sha(folder / n) for n in ("model.json", "weights.npz")}
        # the run config, its data file named from the recipe's root (the run's: absolute)
        run_cfg = load_config(TrainConfig, out / "runs" / stage / "config.toml", section="train")
        kept = load_config(TrainConfig, folder / "config.toml", section="train")
        model_file = "rl/models/error_model_clear_tank_480_ar1.json"
        assert run_cfg.env.error_model_path == str(small_recipe / model_file)
        assert kept == replace(run_cfg, env=replace(run_cfg.env, error_model_path=model_file))
    from uwdock.rl.policy.policy_io import load_policy, policy_train_env

    model, _ = load_policy(out)  # `rl eval --policy OUT` reads it
    assert model.algorithm == "ppo"
    # out is outside any checkout: the file is found in the toolkit's own
    found = Path(policy_train_env(str(out))["error_model_path"])
    assert found.is_absolute() and found.read_bytes() == (small_recipe / model_file).read_bytes()
    # the second stage started from the first's best/, every stage with the recipe's seed
    prov = json.loads((out / "runs" / "second" / "provenance.json").read_text())
    assert prov["init_policy"]["path"] == str((out / "runs" / "first" / "best").resolve())
    assert prov["init_policy"]["weights_sha256"] == _sha(out / "first" / "weights.npz")
    for stage in ("first", "second"):
        assert "seed = 3" in (out / "runs" / stage / "config.toml").read_text()


def test_a_rerun_trains_nothing_twice_and_another_seed_is_refused(
    small_recipe, tmp_path, monkeypatch
):
    out = tmp_path / "out"
    R.run_recipe("small", 0, out, progress=False)
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("weights.npz")}
    R.run_recipe("small", 0, out, progress=False)
    assert stamps == {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("weights.npz")}
    # the stages' data files are named from the checkout that trained them: run again from
    # another checkout (the same files elsewhere), the finished stages train nothing and the
    # same policy is published
    before = {p: _sha(p) for p in out.rglob("*") if p.is_file()}
    moved = tmp_path / "moved"
    small_recipe.rename(moved)
    with monkeypatch.context() as m:
        m.setattr(R, "ROOT", moved)
        m.setattr(R, "RECIPES", moved / "configs" / "recipes")
        m.setattr(R, "train", lambda *a, **k: pytest.fail("a finished stage trained again"))
        notes: list[str] = []
        R.run_recipe("small", 0, out, note=notes.append, progress=False)
    assert [n for n in notes if ": done (" in n] == [
        f"recipe small, seed 0: stage {k}/2 {s}: done ({out / 'runs' / s})"
        for k, s in ((1, "first"), (2, "second"))
    ]
    assert {p: _sha(p) for p in out.rglob("*") if p.is_file()} == before
    moved.rename(small_recipe)
    with pytest.raises(DockError, match="another recipe run"):
        R.run_recipe("small", 1, out, progress=False)
    # a comment is not the recipe: the folder resumes (nothing to do)
    second = small_recipe / "configs" / "second.toml"
    second.write_text("# a note on the stage\n" + STAGE.format(steps=64))
    R.run_recipe("small", 0, out, progress=False)
    # a value, or the content of a data file the stages read, is
    second.write_text(STAGE.format(steps=96))
    with pytest.raises(DockError, match="another version of the recipe"):
        R.run_recipe("small", 0, out, progress=False)
    second.write_text(STAGE.format(steps=64))
    model = small_recipe / "rl" / "models" / "error_model_clear_tank_480_ar1.json"
    model.write_bytes(model.read_bytes() + b"\n")
    with pytest.raises(DockError, match="another version of the recipe"):
        R.run_recipe("small", 0, out, progress=False)


def test_stage_configs_moved_or_split_with_extends_are_the_same_recipe(small_recipe, tmp_path):
    """Where a stage's config lives and how it is split into files is not the recipe: the
    second stage moved into a folder of its own and written as the first plus its one
    difference (``extends``) resumes the folder; another value there does not."""
    out = tmp_path / "out"
    R.run_recipe("small", 0, out, progress=False)
    (small_recipe / "configs" / "second.toml").unlink()
    moved = small_recipe / "configs" / "small" / "stage2.toml"
    moved.parent.mkdir()
    moved.write_text('extends = "configs/first.toml"\ntotal_steps = 64\n')
    recipe = small_recipe / "configs" / "recipes" / "small.toml"
    recipe.write_text(RECIPE.replace("configs/second.toml", "configs/small/stage2.toml"))
    R.run_recipe("small", 0, out, progress=False)  # nothing to train: both stages are done
    moved.write_text('extends = "configs/first.toml"\ntotal_steps = 96\n')
    with pytest.raises(DockError, match="another version of the recipe"):
        R.run_recipe("small", 0, out, progress=False)


def test_a_stage_interrupted_resumes_to_the_same_weights(small_recipe, tmp_path):
    """The first stage done, the second's folder started and left without a checkpoint (as
    a run killed early): the rerun goes on and the policy equals an uninterrupted recipe's."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    R.run_recipe("small", 5, whole, progress=False)
    R.run_recipe("small", 5, cut, progress=False)
    second = cut / "runs" / "second"
    for p in sorted(second.rglob("*"), reverse=True):  # back to a run killed at its start
        if p.name not in ("config.toml", "provenance.json", ".uwdock-owner.json"):
            p.unlink() if p.is_file() else p.rmdir()
    state = json.loads((cut / "recipe.json").read_text())
    (cut / "recipe.json").write_text(json.dumps({**state, "done": ["first"]}))
    for name in ("model.json", "weights.npz", "checksums.sha256"):
        (cut / name).unlink()
    R.run_recipe("small", 5, cut, progress=False)
    assert _sha(cut / "weights.npz") == _sha(whole / "weights.npz")
    a, b = run_digest(whole / "runs" / "second"), run_digest(cut / "runs" / "second")
    assert [k for k in a if a[k] != b.get(k)] == []


def test_unknown_or_malformed_recipes_are_one_line(small_recipe):
    with pytest.raises(DockError, match="the recipes are small"):
        R.load_recipe("nope")
    bad = small_recipe / "configs" / "recipes" / "bad.toml"
    bad.write_text(RECIPE.replace('init_from = "first"', 'init_from = "later"'))
    with pytest.raises(DockError, match="not an earlier stage"):
        R.load_recipe("bad")
    bad.write_text(RECIPE.replace("configs/second.toml", "configs/missing.toml"))
    with pytest.raises(DockError, match=r"missing\.toml"):
        R.load_recipe("bad")


def test_the_shipped_recipe_is_the_shipped_policys_one_stage():
    """Its one stage is the config the shipped policy records, its input files named from the
    repository's root."""
    import tomllib

    recipe, configs, _ = R.load_recipe("shipped")
    assert [s.name for s in recipe.stages] == ["policy"] and recipe.stages[0].init_from is None
    cfg = configs["policy"]
    kept = tomllib.loads((ROOT / "rl/policies/realistic_ppo/config.toml").read_text())["train"]
    assert cfg.total_steps == kept["total_steps"] == 600_000
    assert list(cfg.ppo.net_arch) == list(kept["ppo"]["net_arch"]) == [64, 64]
    assert cfg.imitation.teacher == kept["imitation"]["teacher"] == "pid"
    assert cfg.env.reward.collision_penalty == kept["env"]["reward"]["collision_penalty"]
    assert Path(cfg.env.error_model_path).is_absolute()
    assert Path(cfg.env.error_model_path).is_file()
    assert cfg.env.error_model_path.endswith(kept["env"]["error_model_path"])


def test_the_command_refuses_flags_that_the_recipe_sets(tmp_path):
    out = subprocess.run(
        [sys.executable, "-c",
         "import sys; sys.argv[0] = 'rl'; from uwdock.rl.cli import main; main()",
         "train", "--recipe", "shipped", "--steps", "5", "--out", tmp_path / "x"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 2
    assert out.stderr.strip() == "error: --recipe sets the configs of its stages: not with --steps"
    assert not (tmp_path / "x").exists()
