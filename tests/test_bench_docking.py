"""bench/bench_docking.py's paired comparison against the camera row, on hand-made episodes."""

from __future__ import annotations

import pytest

from tests.conftest import bench_module, load_bench


@pytest.fixture(scope="module")
def bench():
    yield from bench_module("bench_docking")


def _row(condition, outcomes, controller="policy", obs="camera", collisions=None):
    """outcomes: (docked strictly, time to dock or None) per episode 0, 1, ..."""
    hits = collisions or [0] * len(outcomes)
    eps = [
        {"episode": k, "success_strict": ok, "success": ok, "time_to_dock_s": t, "collisions": c}
        for k, ((ok, t), c) in enumerate(zip(outcomes, hits, strict=True))
    ]
    return {"condition": condition, "controller": controller, "obs": obs, "per_episode": eps}


def test_paired_change_against_the_camera_row(bench):
    camera = _row(
        "camera", [(True, 10.0), (True, 11.0), (True, 12.0), (False, None)], collisions=[1, 2, 0, 1]
    )
    turbid = _row(
        "turbid", [(True, 12.0), (False, None), (True, 13.0), (True, 14.0)], collisions=[3, 2, 1, 1]
    )
    pid_camera = _row("camera", [(True, 20.0)] * 4, controller="pid")
    off = _row("camera off", [(False, None)] * 4, obs="acoustic")  # not a camera row
    (p,) = bench.paired_vs_camera([camera, turbid, pid_camera, off])
    assert p["condition"] == "turbid" and p["controller"] == "policy"
    assert p["episodes"] == 4
    assert p["strict_change"] == pytest.approx(0.0)  # one gained, one lost
    assert p["strict_mcnemar_p"] == pytest.approx(1.0)
    assert p["both_docked"] == 2  # episodes 0 and 2
    assert p["time_change_s"] == pytest.approx(1.5)  # (2 + 1) / 2
    lo, hi = p["time_change_ci95_s"]
    assert 1.0 <= lo <= 1.5 <= hi <= 2.0
    assert p["collisions_change"] == pytest.approx(0.75)  # (2 + 0 + 1 + 0) / 4, every episode
    lo, hi = p["collisions_change_ci95"]
    assert 0.0 <= lo <= 0.75 <= hi <= 2.0


def test_paired_change_only_on_common_episodes(bench):
    camera = _row("camera", [(True, 10.0)] * 10)
    coastal = _row("coastal", [(False, None)] * 3)  # 3 episodes: compared on episodes 0-2
    (p,) = bench.paired_vs_camera([camera, coastal])
    assert p["episodes"] == 3
    assert p["strict_change"] == pytest.approx(-1.0)
    assert p["strict_mcnemar_p"] == pytest.approx(0.25)  # 3 discordant, all one way: 2 x 1/8
    assert p["both_docked"] == 0 and p["time_change_s"] is None


def test_two_policies_compared_on_their_common_rows():
    cmp = load_bench("compare_docking")
    a_cam = _row("camera", [(True, 10.0), (True, 10.0), (False, None), (True, 9.0)])
    b_cam = _row("camera", [(True, 12.0), (False, None), (False, None), (True, 10.0)])
    a_em = _row("error model", [(True, 8.0)] * 4, obs="error-model")
    b_pid = _row("camera", [(True, 20.0)] * 4, controller="pid")  # not in the base file
    for r, s in ((a_cam, 0.75), (b_cam, 0.5), (a_em, 1.0), (b_pid, 1.0)):
        r.update(strict=s, paper=s, time_to_dock_s=None, collisions=0.0, episodes=4)
    (row,) = cmp.compare({"rows": [a_cam, a_em]}, {"rows": [b_cam, b_pid]})
    assert (row["condition"], row["controller"]) == ("camera", "policy")
    assert row["base"]["strict"] == 0.75 and row["other"]["strict"] == 0.5
    assert (row["strict_gained"], row["strict_lost"]) == (0, 1)
    assert row["strict_change"] == pytest.approx(-0.25)
    assert row["both_docked"] == 2 and row["time_change_s"] == pytest.approx(1.5)
    # a policy against the PID's row of the base file
    (vs_pid,) = cmp.compare({"rows": [a_em, b_pid]}, {"rows": [b_cam]}, base_controller="pid")
    assert vs_pid["base"]["strict"] == 1.0 and vs_pid["other"]["strict"] == 0.5
    assert (vs_pid["strict_gained"], vs_pid["strict_lost"]) == (0, 2)
    assert vs_pid["time_change_s"] == pytest.approx(-9.0)  # 12 - 20 and 10 - 20


def test_comparison_pools_a_side_over_files_and_refuses_a_row_twice(tmp_path):
    import json

    cmp = load_bench("compare_docking")
    cam, em = _row("camera", [(True, 10.0)]), _row("error model", [(True, 9.0)], obs="error-model")
    files = []
    for name, rows in (("a", [cam]), ("b", [em]), ("c", [cam])):
        files.append(tmp_path / f"{name}.json")
        files[-1].write_text(json.dumps({"rows": rows, "bench_config": {"seed": 50000}}))
    side = cmp._load_side(files[:2])
    assert [(r["condition"], r["file"]) for r in side["rows"]] == [
        ("camera", str(files[0])), ("error model", str(files[1]))
    ]  # fmt: skip
    with pytest.raises(SystemExit, match="in both"):
        cmp._load_side([files[0], files[2]])


def test_an_unfinished_output_with_the_same_settings_resumes(bench, tmp_path):
    """The cells an interrupted run wrote are kept, marked with the commit that flew them; a
    finished output, other settings, or a file that is not a record keep nothing."""
    import json

    config = {"policy": "p", "episodes": 4, "rows": ["camera", "all"], "env": {"a": [1.0, 2]}}
    cell = _row("camera", [(True, 10.0)] * 4, controller="pid")
    record = {"git": {"commit": "abc", "dirty": False}, "rows": [cell],
              "bench_config": {**config, "complete": False}}  # fmt: skip
    path = tmp_path / "pid.json"
    path.write_text(json.dumps(record))
    kept = bench.finished_cells(path, config)
    assert list(kept) == [("camera", "pid")]
    assert kept["camera", "pid"]["resumed_from"] == {"commit": "abc", "dirty": False}
    assert kept["camera", "pid"]["per_episode"] == cell["per_episode"]
    # tuples in the settings compare as the JSON lists they were written as
    assert bench.finished_cells(path, {**config, "env": {"a": (1.0, 2)}}) == kept
    assert bench.finished_cells(path, {**config, "episodes": 8}) == {}
    path.write_text(json.dumps({**record, "bench_config": {**config, "complete": True}}))
    assert bench.finished_cells(path, config) == {}  # finished: run again from the start
    for text in ("", "[1, 2]", '{"rows": []}', "\udcff"):
        path.write_text(text, errors="surrogateescape")
        assert bench.finished_cells(path, config) == {}
    assert bench.finished_cells(tmp_path / "absent.json", config) == {}
    assert bench.finished_cells(tmp_path, config) == {}  # a folder
