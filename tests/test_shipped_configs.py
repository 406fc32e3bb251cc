"""Every training config shipped in configs/ loads, and the files it names are in the tree."""

import json
from pathlib import Path

import pytest

from uwdock.dockcore.config import load_config, read_toml, replace
from uwdock.rl.config import LEGACY_WORLD_KEYS, check_env_files
from uwdock.rl.train import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").glob("*.toml"))


def test_configs_are_shipped():
    assert len(CONFIGS) >= 5


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_shipped_config_loads_and_its_files_exist(path, monkeypatch):
    monkeypatch.chdir(ROOT)  # the configs name files relative to the repository root
    cfg = load_config(TrainConfig, path, section="train")
    check_env_files(cfg.env)
    assert cfg.total_steps > 0


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_shipped_config_sets_the_world_in_env_world(path):
    """The recipes are written in the current layout: world keys in [env.world], none flat in
    [env] (the loader still reads the flat layout of run folders, tests/test_env_config.py)."""
    env = read_toml(path).get("env", {})
    assert sorted(set(env) & set(LEGACY_WORLD_KEYS)) == []


def test_stage_two_only_raises_the_collision_penalty():
    """The soft fine-tune differs from the precision recipe in the collision penalty, the step
    budget, the evaluation cadence and the curriculum (a fine-tune starts at full spawn range)."""
    load = lambda n: load_config(TrainConfig, ROOT / "configs" / n, section="train")  # noqa: E731
    one = load("scratch_error_model_precision_ppo.toml")
    two = load("scratch_error_model_precision_soft_ppo.toml")
    assert one.env.reward.collision_penalty == 10.0
    assert two.env.reward.collision_penalty == 30.0
    assert two.curriculum.steps == 0
    reward_one = replace(two.env.reward, collision_penalty=one.env.reward.collision_penalty)
    assert replace(two.env, reward=reward_one) == one.env
    assert one.ppo == two.ppo


def test_proxy_precision_recipe_only_adds_r_precision():
    """The proxy recipe that reaches the paper's figure in three seeds is the large-batch one
    plus r_precision (the error-model recipe's values); nothing else differs."""
    load = lambda n: load_config(TrainConfig, ROOT / "configs" / n, section="train")  # noqa: E731
    batch = load("scratch_proxy_batch_ppo.toml")
    precise = load("scratch_proxy_precision_ppo.toml")
    em = load("scratch_error_model_precision_ppo.toml")
    assert batch.env.reward.precision_gain == 0.0
    assert precise.env.reward.precision_gain == em.env.reward.precision_gain == 1.0
    assert precise.env.reward.precision_scale_m == em.env.reward.precision_scale_m
    reward = replace(
        precise.env.reward,
        precision_gain=batch.env.reward.precision_gain,
        precision_scale_m=batch.env.reward.precision_scale_m,
    )
    assert replace(precise, env=replace(precise.env, reward=reward)) == batch


def _shipped_stage2(name: str, recipe: str):
    """The shipped policy folder ``name``: its run config is the committed stage-2 ``recipe`` (its
    seed aside), trained from a clean tree from a stage 1's best/, without imitation, and its kept
    checkpoint docked >= 90 % strict on its 30 evaluation episodes. Returns (folder, config,
    model)."""
    from uwdock.rl.policy_io import load_policy

    shipped = ROOT / "rl" / "policies" / name
    cfg = load_config(TrainConfig, shipped / "config.toml", section="train")
    recipe_cfg = load_config(TrainConfig, ROOT / "configs" / recipe, section="train")
    assert cfg == replace(recipe_cfg, seed=cfg.seed)
    assert cfg.imitation.teacher == "none" and not (shipped / "imitation.json").exists()
    prov = json.loads((shipped / "provenance.json").read_text(encoding="utf-8"))
    assert prov["git"]["dirty"] is False and len(prov["git"]["commit"]) == 40
    assert "--init-policy" in prov["command"] and f"--seed {cfg.seed}" in prov["command"]
    history = [json.loads(line) for line in (shipped / "eval_history.jsonl").open()]
    best = [r for r in history if r.get("best")][-1]
    assert best["success_rate_strict"] >= 0.9
    model = load_policy(shipped)[0]
    return shipped, cfg, model


def test_the_true_pose_policy_is_the_from_scratch_recipe():
    """The policy shipped before realistic_ppo: stage 2 of the true-pose recipe."""
    _shipped, _cfg, model = _shipped_stage2(
        "scratch_error_model_ppo", "scratch_error_model_precision_soft_ppo.toml"
    )
    assert model.observation_space.shape[0] > 0


def test_shipped_policy_is_the_realistic_recipe():
    """The main job's policy: stage 2 of the realistic recipe (its own drifting navigation, the
    EvoLogics USBL, contact sensing, the refitted error model; near-seat starts in stage 1, the
    highest-return evaluation kept in stage 2, the fine error added and the collision penalty 70
    in stage 2; the docking station's contact in the numba kernel while training), from a stage
    1 of the committed stage-1 config shipped beside it (``stage1/``); both match their
    checksums and stage 2 reads the observation the recipe's env gives, three values wider than
    stage 1's."""
    import hashlib

    from uwdock.rl.observation import observation_size
    from uwdock.rl.policy_io import load_policy

    shipped, cfg, model = _shipped_stage2(
        "realistic_ppo",
        "realistic_batched_yaw_contact_gentle_return_kernel_fine_collision70_ppo.toml",
    )
    assert cfg.env.nav.preset == "mems-ahrs-dvl" and cfg.env.usbl.preset == "evologics-s2cr"
    assert cfg.env.obs_contact and cfg.env.error_model_path.endswith("_ar1_refit.json")
    assert cfg.env.world.batch_contact == "kernel"
    stage1_path = ROOT / "configs" / "realistic_batched_yaw_contact_near_kernel_ppo.toml"
    stage1 = load_config(TrainConfig, stage1_path, section="train")
    assert cfg.env.obs_fine_error and not stage1.env.obs_fine_error
    # only the reward and the fine error differ
    assert replace(stage1.env, reward=cfg.env.reward, obs_fine_error=True) == cfg.env
    kept = shipped / "stage1"  # stage 1 ships beside stage 2, in the same format
    stage1_prov = json.loads((kept / "provenance.json").read_text(encoding="utf-8"))
    assert stage1_prov["git"]["dirty"] is False and len(stage1_prov["git"]["commit"]) == 40
    assert "realistic_batched_yaw_contact_near_kernel_ppo.toml" in stage1_prov["command"]
    assert load_config(TrainConfig, kept / "config.toml", section="train") == replace(
        stage1, seed=stage1_prov["config"]["train"]["seed"]
    )
    for folder in (shipped, kept):
        lines = (folder / "checksums.sha256").read_text().splitlines()
        assert {line.split("  ", 1)[1] for line in lines} == {"model.json", "weights.npz"}
        for line in lines:
            digest, name = line.split("  ", 1)
            assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name
    stage1_model = load_policy(kept)[0]
    assert stage1_model.observation_space.shape[0] == observation_size(stage1.env)
    assert model.observation_space.shape[0] == observation_size(cfg.env)
    assert observation_size(cfg.env) == observation_size(stage1.env) + 3
