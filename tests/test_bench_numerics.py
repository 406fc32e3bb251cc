"""bench/bench_numerics.py: where two training runs' evaluation histories part, and its switches."""

from __future__ import annotations

import json

import pytest

from tests.conftest import bench_module


@pytest.fixture(scope="module")
def bench():
    yield from bench_module("bench_numerics")


def test_runs_agree_through_the_last_equal_evaluation(bench):
    ref = [(53248, -1489.7988961935043), (102400, -1158.0809967111795), (151552, -892.5232)]
    same_two = [(53248, -1489.7988961935043), (102400, -1158.0809967111795), (151552, -947.79)]
    assert bench.agrees_through(same_two, ref) == 102400
    assert bench.agrees_through(ref, ref) == 151552
    assert bench.agrees_through(ref[:2], ref) == 102400  # only the steps both have
    # the last digit counts, and so does the step an evaluation was taken at
    assert bench.agrees_through([(53248, -1489.7988961935045)], ref) is None
    assert bench.agrees_through([(53249, -1489.7988961935043)], ref) is None
    assert bench.agrees_through([], ref) is None


def test_history_is_read_from_eval_history_jsonl(bench, tmp_path):
    path = tmp_path / "eval_history.jsonl"
    rows = [{"step": 53248, "mean_return": -1.5, "x": 0.0}, {"step": 102400, "mean_return": 2}]
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n", encoding="utf-8")
    assert bench.read_history(path) == [(53248, -1.5), (102400, 2.0)]


def test_switches_are_default_or_one_variable(bench):
    assert bench.parse_switch("default") == {}
    assert bench.parse_switch("NPY_DISABLE_CPU_FEATURES=X86_V4 AVX512_ICL") == {
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL"
    }
    assert bench.parse_switch("MKL_CBWR=") == {"MKL_CBWR": ""}
    for bad in ("MKL_CBWR", "=x", "NOT A NAME=1"):
        with pytest.raises(SystemExit, match="not 'default' or NAME=VALUE"):
            bench.parse_switch(bad)
