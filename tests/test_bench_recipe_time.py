"""bench/bench_recipe_time.py: what a timed run records about the machine beside its time."""

from __future__ import annotations

import pytest

from tests.conftest import bench_module


@pytest.fixture(scope="module")
def bench():
    yield from bench_module("bench_recipe_time")


def test_cpu_shares_are_the_idle_and_stolen_parts_of_the_time_between_readings(bench):
    # user nice system idle iowait irq softirq steal
    before = [100, 0, 20, 500, 10, 0, 0, 5]
    after = [250, 0, 50, 600, 20, 0, 0, 25]  # 150 + 30 busy, 100 + 10 idle, 20 stolen of 310
    shares = bench.cpu_shares(before, after)
    assert shares["idle_pct"] == pytest.approx(100.0 * 110 / 310)
    assert shares["steal_pct"] == pytest.approx(100.0 * 20 / 310)
    assert bench.cpu_shares(None, after) == {"idle_pct": None, "steal_pct": None}
    assert bench.cpu_shares(after, after) == {"idle_pct": None, "steal_pct": None}


def test_cpu_counters_read_the_first_line_of_proc_stat(bench, tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  1 2 3 4 5 6 7 8 9 10\ncpu0 1 1 1 1 1 1 1 1 0 0\n", encoding="ascii")
    assert bench.cpu_counters(stat) == [1, 2, 3, 4, 5, 6, 7, 8]
    stat.write_text("intr 1 2 3\n", encoding="ascii")
    assert bench.cpu_counters(stat) is None
    assert bench.cpu_counters(tmp_path / "missing") is None


def test_the_reference_workload_is_timed_and_the_source_named(bench):
    assert 0.0 < bench.reference_s(repeats=1, warm_s=0.0) < 60.0
    commit, changes = bench.source_state()
    assert commit is None or len(commit) == 64
    assert bench.source_state() == (commit, changes)  # nothing changed in between
