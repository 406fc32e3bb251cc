"""bench/bench_update_kernels.py: one PPO update per MKL path and thread count, each in a fresh
process, whose weight digests say which pins keep the update's bits."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import bench_module

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    yield from bench_module("bench_update_kernels")


def _small_config(tmp_path):
    """The recipe's config with 4 envs, 16-step rollouts and 32-step minibatches."""
    text = (ROOT / "configs" / "realistic" / "policy.toml").read_text(encoding="utf-8")
    for old, new in (("n_envs = 64", "n_envs = 4"), ("n_steps = 64", "n_steps = 16"),
                     ("batch_size = 1024", "batch_size = 32")):  # fmt: skip
        assert old in text
        text = text.replace(old, new)
    text = text.replace('"rl/models/', f'"{ROOT.as_posix()}/rl/models/')
    path = tmp_path / "small.toml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.slow
def test_the_pinned_path_gives_the_same_update_whatever_the_threads_and_repeats(bench, tmp_path):
    """The pin's path (MKL ``AVX2,STRICT``) gives one digest on one thread, on two with one
    more timed update, and in a third process: every update starts from the same weights and
    minibatch order (the rollout buffer shuffles with NumPy's global RNG, seeded before each
    update), so the digest depends neither on the thread count nor on ``--repeats``."""
    cfg = _small_config(tmp_path)
    runs = [bench.run_child(cfg, "AVX2,STRICT", t, r) for t, r in ((1, 1), (2, 2), (1, 1))]
    assert [r["torch_threads"] for r in runs] == [1, 2, 1]
    assert [len(r["times_s"]) for r in runs] == [1, 2, 1]
    assert runs[0]["grad_steps"] == 10 * (16 * 4 // 32)  # 10 epochs of 2 minibatches
    digests = {r["weights_sha256"] for r in runs}
    assert len(digests) == 1 and len(digests.pop()) == 12


def test_bad_arguments_get_one_line_and_a_non_zero_exit(bench, tmp_path):
    for argv in (["--threads", "1,x"], ["--repeats", "0"], ["--threads", "0"],
                 ["--config", str(tmp_path / "missing.toml")]):  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            bench.main(argv)
        assert str(exc.value).startswith("error: ")
