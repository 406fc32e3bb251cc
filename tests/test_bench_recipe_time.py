"""bench/bench_recipe_time.py: what a timed run records about the machine beside its time."""

from __future__ import annotations

import pytest

from tests.conftest import bench_module
from uwdock.dockcore.provenance import source_state


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
    commit, changes = source_state()
    assert commit is None or len(commit) == 40
    assert changes is None or len(changes) == 64
    assert source_state() == (commit, changes)  # nothing changed in between


def test_source_state_changes_with_a_tracked_files_content(tmp_path):
    import subprocess

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "a")
    clean = source_state(tmp_path)
    assert clean[0] is not None and len(clean[0]) == 40
    (tmp_path / "a.py").write_text("x = 2\n")
    edited = source_state(tmp_path)
    assert edited[0] == clean[0] and edited[1] != clean[1]
    (tmp_path / "a.py").write_text("x = 1\n")
    assert source_state(tmp_path) == clean
    assert source_state(tmp_path / "missing") == (None, None)
