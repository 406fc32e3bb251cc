"""Every training config shipped in configs/ loads, and the files it names are in the tree."""

from pathlib import Path

import pytest

from uwdock.dockcore.config import load_config, replace
from uwdock.rl.config import check_env_files
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
