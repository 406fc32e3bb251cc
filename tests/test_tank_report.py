"""The tank report (``datasets tank-report``): detection ranges rendered by SAPIEN and read by the
detector, against the simulator benchmark's measured ranges (``bench/results/sim.json`` (d))."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from uwdock.datasets import cli as datasets_cli

ROOT = Path(__file__).resolve().parents[1]
STEP_M = 0.5  # the benchmark's altitude step


def _bench_rows(width: str) -> dict[str, dict]:
    rows = json.loads((ROOT / "bench/results/sim.json").read_text())["rows"]
    return {r["water"]: r for r in rows if r.get("section") == "range" and r["width"] == width}


@pytest.mark.render
def test_report_ranges_agree_with_the_benchmark_within_one_step(tmp_path, run_cli):
    res = run_cli(datasets_cli.main, "tank-report", "--out", tmp_path / "tr", "--json")
    assert res.code == 0, res.err
    rows = {r["water"]: r for r in json.loads(res.out)}
    bench = _bench_rows("968x732")  # the reference camera, the command's default
    presets = ("clear_tank", "coastal", "turbid", "very_turbid")
    assert set(presets) <= set(rows) and set(presets) <= set(bench)
    for name in presets:
        for key in ("max_alt_3_markers_m", "max_alt_1_marker_m"):
            got, want = rows[name][key], bench[name][key]
            assert (got is None) == (want is None), (name, key, got, want)
            if got is not None:
                assert abs(got - want) <= STEP_M + 1e-9, (name, key, got, want)
    # clearer water reaches further: the ranges are ordered like the presets
    ones = [rows[n]["max_alt_1_marker_m"] for n in presets]
    assert ones == sorted(ones, reverse=True) and ones[0] > ones[-1]
    out = tmp_path / "tr"
    assert (out / "tank_report.png").stat().st_size > 0 and (out / "provenance.json").exists()


@pytest.mark.render
def test_a_water_file_is_read_and_bad_input_is_one_line(tmp_path, run_cli):
    water = tmp_path / "my_tank.toml"
    water.write_text(
        "[water]\nbeta_D_rgb = [0.5, 0.2, 0.25]\nbeta_B_rgb = [0.6, 0.3, 0.35]\n"
        "B_inf_rgb = [0.02, 0.2, 0.18]\n"
    )
    args = ("--water-file", water, "--altitude-max-m", 3, "--altitude-step-m", 1, "--draws", 1)
    res = run_cli(datasets_cli.main, "tank-report", "--out", tmp_path / "a", *args, "--json")
    assert res.code == 0, res.err
    rows = json.loads(res.out)
    assert [r["water"] for r in rows] == ["my_tank", "(visible)"]
    assert rows[0]["altitudes_m"] == [1.0, 2.0, 3.0]
    for args, fragment in (
        (("--water", "murky"), "unknown water preset 'murky'"),
        (("--altitude-max-m", 0.5), "altitude_max_m"),
        (("--draws", 0), "--draws"),
    ):
        bad = run_cli(datasets_cli.main, "tank-report", "--out", tmp_path / "b", *args)
        assert bad.code != 0
        lines = bad.err.strip().splitlines()
        assert len(lines) == 1 and fragment in lines[0], bad.err
    assert not (tmp_path / "b").exists()
