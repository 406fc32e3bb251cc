"""bench/bench_train_speed.py's steady rate: the steps after a run's first rollout over the time
its own TensorBoard log stamped between them, on a short real training run."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import bench_module
from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.train.training import PPOConfig, TrainConfig, train


@pytest.fixture(scope="module")
def bench():
    yield from bench_module("bench_train_speed")


def test_the_rollout_clock_counts_the_rollouts_after_the_first(bench, tmp_path):
    cfg = replace(
        TrainConfig(), n_envs=4, simulator="batched", total_steps=3 * 16 * 4,
        checkpoint_every=10**9, eval_every=0, env=replace(EnvConfig(), episode_s=3.0),
        ppo=replace(PPOConfig(), n_steps=16, batch_size=64, n_epochs=1),
    )  # fmt: skip
    run = tmp_path / "run"
    train(cfg, run, progress=False, note=lambda _m: None)
    steps, seconds, alone = bench.rollout_clock(run)
    assert steps == 2 * 16 * 4  # the second and third rollouts
    assert 0 < alone < seconds < 120  # the rollouts alone: the updates between them left out
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(tmp_path / "one" / "tb" / "tb_1")) as log:  # a one-rollout run's log
        log.add_scalar("time/fps", 100.0, 64)
    assert bench.rollout_clock(tmp_path / "one") == (0, 0.0, None)  # no steady interval
    with SummaryWriter(str(tmp_path / "old" / "tb" / "tb_1")) as log:  # no rollout_s logged
        log.add_scalar("time/fps", 100.0, 64)
        log.add_scalar("time/fps", 100.0, 128)
    assert bench.rollout_clock(tmp_path / "old")[2] is None
    with pytest.raises(RuntimeError, match="no TensorBoard log"):
        bench.rollout_clock(Path(tmp_path / "absent"))
