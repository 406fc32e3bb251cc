"""The tank report (``datasets tank-report``): detection ranges rendered by SAPIEN and read by the
detector, against the simulator benchmark's measured ranges (``bench/results/sim.json`` (d))."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from uwdock.datasets import cli as datasets_cli

ROOT = Path(__file__).resolve().parents[1]
STEP_M = 0.5  # the benchmark's altitude step


def _bench_rows(width: str) -> dict[str, dict]:
    rows = json.loads((ROOT / "bench/results/sim.json").read_text())["rows"]
    return {r["water"]: r for r in rows if r.get("section") == "range" and r["width"] == width}


@pytest.mark.render
@pytest.mark.slow  # ~15 s on 2 cores: in the slow set (CI runs it)
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
    assert [r["water"] for r in rows] == [str(water), "(visible)"]  # keyed by the path
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


def _fitted_water(folder: Path, beta_d: list[float], rel: float, undetermined: str = "") -> Path:
    """A water file as `sim fit-water` writes it: [water] and its [fit] notes."""
    folder.mkdir()
    low = [b * math.exp(-rel) for b in beta_d]
    high = [b * math.exp(rel) for b in beta_d]
    path = folder / "water.toml"
    path.write_text(
        f"[water]\nbeta_D_rgb = {beta_d}\nbeta_B_rgb = [0.6, 0.3, 0.35]\n"
        'B_inf_rgb = [0.02, 0.2, 0.18]\n\n[fit]\nlighting = "both"\n'
        f"beta_D_low_rgb = {low}\nbeta_D_high_rgb = {high}\n\n[fit.undetermined]\n" + undetermined
    )
    return path


@pytest.mark.render
def test_fitted_waters_give_intervals_per_path_in_plain_words(tmp_path, run_cli):
    """Two water.toml from different folders are two rows (nothing dropped); a fitted water's
    ranges come with an interval from its beta_D uncertainty (the fitted value inside it);
    undetermined values are named; a range that never holds reads "not within"."""
    clear = _fitted_water(tmp_path / "tank_a", [0.15, 0.08, 0.1], 0.5)
    murky = _fitted_water(
        tmp_path / "tank_b", [2.5, 2.5, 2.8], 0.1, 'B_inf = ["G", "B"]\nbeta_D = ["R"]\n'
    )
    args = ("--altitude-max-m", 5, "--altitude-step-m", 1, "--draws", 1)
    files = ("--water-file", clear, "--water-file", murky)
    res = run_cli(datasets_cli.main, "tank-report", "--out", tmp_path / "a", *files, *args,
                  "--json")  # fmt: skip
    assert res.code == 0, res.err
    rows = {r["water"]: r for r in json.loads(res.out)}
    assert set(rows) == {str(clear), str(murky), "(visible)"}
    a, b = rows[str(clear)], rows[str(murky)]
    for r in (a, b):
        for key in ("max_alt_3_markers", "max_alt_1_marker"):
            lo, hi = r[f"{key}_interval_m"]
            v = r[f"{key}_m"]
            if v is not None:  # the fitted value lies inside its interval
                assert (lo is None or lo <= v) and hi is not None and v <= hi, (key, r)
        assert "beta_D" in r["interval_from"]
    # the clear water decodes higher up than the murky one
    assert a["max_alt_1_marker_m"] is not None
    assert b["max_alt_1_marker_m"] is None or b["max_alt_1_marker_m"] < a["max_alt_1_marker_m"]
    assert a["beta_D_determined"] and not b["beta_D_determined"]
    assert b["undetermined"] == {"B_inf": ["G", "B"], "beta_D": ["R"]}
    # the same in words
    res = run_cli(datasets_cli.main, "tank-report", "--out", tmp_path / "b", *files, *args)
    assert res.code == 0, res.err
    assert "never" not in res.out
    assert "over beta_D -+ its uncertainty" in res.out
    assert "beta_D of R is NOT determined" in res.out and "B_inf of G, B" in res.out
    if b["max_alt_3_markers_m"] is None:
        assert "3 markers not within 1-5 m" in res.out
