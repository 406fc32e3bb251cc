"""The training configs in configs/: each loads and the files it names are in the tree; each
shipped stage config is the config its policy in rl/policies/ records, and resolves (over the
bases it extends) to pinned values, so an edit to a base cannot silently change a shipped policy's
recipe."""

import hashlib
import json
from pathlib import Path

import pytest

from uwdock.dockcore.config import config_data, from_dict, load_config, read_toml, replace
from uwdock.rl.env.config import LEGACY_WORLD_KEYS, check_env_files
from uwdock.rl.train.training import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p for p in (ROOT / "configs").rglob("*.toml") if "recipes" not in p.parts)

#: Each stage config, the policy folder (and the file in it) whose run config it is, and the
#: SHA-256 of its values as the loader resolves them (:func:`_resolved_digest`).
SHIPPED = {
    "realistic/policy.toml": (
        "realistic_ppo/config.toml",
        "34946dfd486ad1b1d4ec2481ede9a25d49bf8c1e1f20e72a3e195f454a71f9c9",
    ),
    "scratch/stage1.toml": (
        "scratch_error_model_ppo/stage1_provenance.json",
        "345fcc6c0804f82e1c2fb79aa7f98cd7971d5c4498c52c6f1d0ca6e9e4bfeb4e",
    ),
    "scratch/stage2.toml": (
        "scratch_error_model_ppo/config.toml",
        "3b53fd383e67b94e668e34e656144d3c5b84ab11904bdbc484b4b259ea87086c",
    ),
    "dagger.toml": (
        "error_model_ppo/config.toml",
        "f0fdbd9871ed44138439b503a0c243e95ca8757826ad2d5f15c1004348fcf17e",
    ),
}

#: How each policy's provenance names its config: the command it was trained with (the older
#: policies by the names their configs had then; the files are in the git tag
#: lab-notebook-2026-12).
TRAINED_AS = {
    "realistic/policy.toml": "rl train --recipe shipped ",
    "scratch/stage1.toml": "--config configs/scratch_error_model_precision_ppo.toml ",
    "scratch/stage2.toml": "--config configs/scratch_error_model_precision_soft_ppo.toml ",
    "dagger.toml": "--config configs/train_error_model_ppo.toml ",
}


def _load(name: str) -> TrainConfig:
    return load_config(TrainConfig, ROOT / "configs" / name, section="train")


def _resolved_digest(name: str) -> str:
    """SHA-256 of the values the config at ``configs/<name>`` sets, its bases' included (not the
    code's defaults, so a new field in TrainConfig does not change it; not comments)."""
    data = config_data(ROOT / "configs" / name, section="train", cls=TrainConfig)
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def test_configs_holds_the_shipped_recipes_only():
    """configs/ is the shipped recipes and the bases they name, no experiment records."""
    files = sorted(str(p.relative_to(ROOT / "configs")) for p in (ROOT / "configs").rglob("*"))
    files = [f for f in files if (ROOT / "configs" / f).is_file()]
    assert len(files) <= 8, files
    assert sorted(str(p.relative_to(ROOT / "configs")) for p in CONFIGS) == sorted(SHIPPED)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: str(p.relative_to(ROOT / "configs")))
def test_shipped_config_loads_and_its_files_exist(path, monkeypatch):
    monkeypatch.chdir(ROOT)  # the configs name files relative to the repository root
    cfg = load_config(TrainConfig, path, section="train")
    check_env_files(cfg.env)
    assert cfg.total_steps > 0


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: str(p.relative_to(ROOT / "configs")))
def test_shipped_config_sets_the_world_in_env_world(path):
    """The recipes are written in the current layout: world keys in [env.world], none flat in
    [env] (the loader still reads the flat layout of run folders, tests/test_env_config.py)."""
    env = read_toml(path).get("env", {})
    assert sorted(set(env) & set(LEGACY_WORLD_KEYS)) == []


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_each_stage_config_is_the_run_config_its_policy_records(name):
    """Ground truth: the config each shipped policy (or its stage 1) was trained with, as its
    run folder recorded it, equals the stage config as it loads now (the seed aside)."""
    record = ROOT / "rl" / "policies" / SHIPPED[name][0]
    prov_path = record if record.suffix == ".json" else record.parent / "provenance.json"
    prov = json.loads(prov_path.read_text(encoding="utf-8"))
    if record.suffix == ".json":
        recorded = from_dict(TrainConfig, prov["config"]["train"])
    else:
        recorded = load_config(TrainConfig, record, section="train")
    assert replace(_load(name), seed=recorded.seed) == recorded
    assert TRAINED_AS[name] in prov["command"]


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_each_stage_config_resolves_to_its_pinned_values(name):
    """An edit to a stage config or to a base it extends that changes a value changes the
    digest: a change to a shipped policy's recipe is then a deliberate edit of this test."""
    data = config_data(ROOT / "configs" / name, section="train", cls=TrainConfig)
    assert _resolved_digest(name) == SHIPPED[name][1], json.dumps(data, sort_keys=True)


def test_stage_two_only_raises_the_collision_penalty():
    """The true-pose stage 2 differs from its stage 1 in the collision penalty, the step
    budget, the evaluation cadence and the curriculum (a fine-tune starts at full spawn range)."""
    one = _load("scratch/stage1.toml")
    two = _load("scratch/stage2.toml")
    assert one.env.reward.collision_penalty == 10.0
    assert two.env.reward.collision_penalty == 30.0
    assert two.curriculum.steps == 0
    assert (one.total_steps, two.total_steps, one.eval_every, two.eval_every) == (
        1_000_000,
        200_000,
        50_000,
        25_000,
    )
    reward_one = replace(two.env.reward, collision_penalty=one.env.reward.collision_penalty)
    assert replace(two.env, reward=reward_one) == one.env
    assert one.ppo == two.ppo
    assert (
        replace(
            two,
            env=one.env,
            total_steps=one.total_steps,
            eval_every=one.eval_every,
            curriculum=one.curriculum,
        )
        == one
    )


def _shipped_stage2(name: str, recipe: str):
    """The shipped policy folder ``name``: its run config is the committed stage-2 ``recipe`` (its
    seed aside), trained from a clean tree from a stage 1's best/, without imitation, and its kept
    checkpoint docked >= 90 % strict on its 30 evaluation episodes. Returns (folder, config,
    model)."""
    from uwdock.rl.policy.policy_io import load_policy

    shipped = ROOT / "rl" / "policies" / name
    cfg = load_config(TrainConfig, shipped / "config.toml", section="train")
    assert cfg == replace(_load(recipe), seed=cfg.seed)
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
    _shipped, _cfg, model = _shipped_stage2("scratch_error_model_ppo", "scratch/stage2.toml")
    assert model.observation_space.shape[0] > 0


def test_shipped_policy_is_the_realistic_recipe():
    """The main job's policy: the shipped recipe's one stage (DAgger from the PID, the critic
    alone for 60k steps, then PPO to 600k steps; its own drifting navigation, the EvoLogics USBL,
    contact sensing and the fine error in the observation, the refitted error model, collisions
    at 70, of the evaluations within one episode of the highest strict success the fastest kept,
    the docking station's contact in the numba kernel), trained from scratch by `rl train
    --recipe shipped` from a clean tree with the numerics pinned; its files match their
    checksums, no stage 1 ships beside it."""
    import hashlib

    from uwdock.rl.env.observation import observation_size
    from uwdock.rl.policy.policy_io import load_policy
    from uwdock.rl.train.recipe import load_recipe

    shipped = ROOT / "rl" / "policies" / "realistic_ppo"
    cfg = load_config(TrainConfig, shipped / "config.toml", section="train")
    assert cfg == replace(_load("realistic/policy.toml"), seed=cfg.seed)
    assert cfg.env.nav.preset == "mems-ahrs-dvl" and cfg.env.usbl.preset == "evologics-s2cr"
    assert cfg.env.obs_contact and cfg.env.obs_fine_error
    assert cfg.env.error_model_path == "rl/models/error_model_clear_tank_480_ar1_refit.json"
    assert cfg.env.world.batch_contact == "kernel" and cfg.env.reward.collision_penalty == 70
    assert cfg.imitation.teacher == "pid" and cfg.imitation.critic_warmup_steps == 60_000
    recipe, _configs, digest = load_recipe("shipped")
    assert [(s.name, s.config) for s in recipe.stages] == [
        ("policy", "configs/realistic/policy.toml")
    ]
    state = json.loads((shipped / "recipe.json").read_text(encoding="utf-8"))
    assert (state["recipe"], state["seed"], state["done"]) == ("shipped", cfg.seed, ["policy"])
    assert state["recipe_sha256"] == digest  # the recipe as committed trains it
    prov = json.loads((shipped / "provenance.json").read_text(encoding="utf-8"))
    assert prov["git"]["dirty"] is False and len(prov["git"]["commit"]) == 40
    assert f"rl train --recipe shipped --seed {cfg.seed} " in prov["command"]
    numerics = prov["machine"]["numerics"]
    assert numerics["UWDOCK_NUMERICS"] == "pinned" and numerics["MKL_CBWR"] == "AVX2,STRICT"
    assert numerics["numpy_simd"] == []
    assert not (shipped / "stage1").exists()
    imitation = json.loads((shipped / "imitation.json").read_text(encoding="utf-8"))
    assert len(imitation["loss"]) == cfg.imitation.iterations
    lines = (shipped / "checksums.sha256").read_text().splitlines()
    assert {line.split("  ", 1)[1] for line in lines} == {"model.json", "weights.npz"}
    for line in lines:
        sha, name = line.split("  ", 1)
        assert hashlib.sha256((shipped / name).read_bytes()).hexdigest() == sha, name
    history = [json.loads(line) for line in (shipped / "eval_history.jsonl").open()]
    best = [r for r in history if r.get("best")][-1]
    assert best["success_rate_strict"] >= 0.95
    model = load_policy(shipped)[0]
    assert model.observation_space.shape[0] == observation_size(cfg.env) == 18
