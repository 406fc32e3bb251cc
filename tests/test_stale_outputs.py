"""Reruns into one's own output folder leave no stale files, and an output folder inside
another tool's output is refused (issue 32): ``markers generate`` STLs of IDs no longer in the
set, ``perception detect`` annotated frames, ``perception eval`` compare files."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from uwdock.calibration.camera import reference_camera, save_camera
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.outdir import MANIFEST_FILE, OWNER_FILE, claim_output_dir, tracked_outputs
from uwdock.markers import cli as markers_cli
from uwdock.perception import cli as perception_cli


def _frames(folder: Path, names: list[str]) -> Path:
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    for name in names:
        cv2.imwrite(str(folder / name), rng.integers(0, 255, (48, 64), dtype=np.uint8))
    return folder


def _camera(tmp_path: Path) -> Path:
    cam = tmp_path / "cam.yaml"
    save_camera(cam, reference_camera().scaled(64, 48))
    return cam


def test_markers_generate_rerun_removes_the_parts_of_dropped_ids(run_cli, tmp_path):
    out = tmp_path / "m"
    user_file = out / "notes.txt"
    assert run_cli(markers_cli.main, "generate", "--ids", "13,14", "--out", out).code == 0
    user_file.write_text("mine")
    first = {p.name for p in out.iterdir()}
    assert {"3dbm_DICT_4X4_50_14_insert.stl", "3dbm_DICT_4X4_50_14.glb"} <= first
    assert run_cli(markers_cli.main, "generate", "--ids", "13", "--out", out).code == 0
    second = {p.name for p in out.iterdir()}
    assert not [n for n in second if "_14" in n], second  # every file of ID 14 is gone
    assert "3dbm_DICT_4X4_50_13_insert.stl" in second and user_file.read_text() == "mine"
    listed = set(json.loads((out / MANIFEST_FILE).read_text())["files"])
    assert listed == second - {OWNER_FILE, ".uwdock.lock", MANIFEST_FILE, "notes.txt"}


def test_perception_detect_rerun_removes_old_annotated_frames(run_cli, tmp_path):
    cam = _camera(tmp_path)
    out = tmp_path / "d"
    args = ["--dictionary", "DICT_4X4_50", "--camera", cam, "--out", out]
    frames = _frames(tmp_path / "a", ["f0.png", "f1.png", "f2.png"])
    assert run_cli(perception_cli.main, "detect", frames, *args).code == 0
    assert sorted(p.name for p in (out / "annotated").iterdir()) == ["f0.png", "f1.png", "f2.png"]
    other = _frames(tmp_path / "b", ["g0.png"])
    assert run_cli(perception_cli.main, "detect", other, *args).code == 0
    assert sorted(p.name for p in (out / "annotated").iterdir()) == ["g0.png"]
    # without annotation: the folder of annotated frames goes, the tables stay
    assert run_cli(perception_cli.main, "detect", other, *args, "--no-annotate").code == 0
    assert not (out / "annotated").exists() and (out / "detections.csv").is_file()


def test_perception_eval_rerun_removes_the_compare_files(run_cli, tmp_path):
    cam = _camera(tmp_path)
    frames = _frames(tmp_path / "f", ["0.png", "1.png"])
    out = tmp_path / "e"
    args = ["eval", frames, "--dictionary", "DICT_4X4_50", "--marker-size-m", "0.1",
            "--camera", cam, "--out", out]  # fmt: skip
    assert run_cli(perception_cli.main, *args, "--compare", "default,plain").code == 0
    assert (out / "compare.json").is_file() and (out / "compare.md").is_file()
    assert run_cli(perception_cli.main, *args).code == 0
    assert not (out / "compare.json").exists() and not (out / "compare.md").exists()
    assert (out / "report.json").is_file() and (out / "timeline.png").is_file()


def test_a_failed_run_keeps_both_runs_files_listed(tmp_path):
    """After a run that failed part-way, the next successful run removes what either earlier
    run wrote and it does not; a user's file is never removed."""
    out = tmp_path / "o"
    with claim_output_dir(out, "perception eval") as d, tracked_outputs(d) as files:
        for name in ("a.txt", "b.txt"):
            (d / name).write_text(name)
            files.add(d / name)
    (out / "user.txt").write_text("mine")
    written: list[Path] = []
    with pytest.raises(RuntimeError):
        with claim_output_dir(out, "perception eval") as d, tracked_outputs(d, written):
            (d / "c.txt").write_text("c")
            written.append(d / "c.txt")
            raise RuntimeError("killed")
    assert {p.name for p in out.iterdir()} >= {"a.txt", "b.txt", "c.txt", "user.txt"}
    with claim_output_dir(out, "perception eval") as d, tracked_outputs(d) as files:
        (d / "a.txt").write_text("again")
        files.add("a.txt")
        files.add(tmp_path / "outside.txt", "../escape.txt")  # outside: ignored
    names = {p.name for p in out.iterdir()} - {OWNER_FILE, ".uwdock.lock", MANIFEST_FILE}
    assert names == {"a.txt", "user.txt"}
    # a manifest that names files outside the folder removes nothing there
    (tmp_path / "victim.txt").write_text("keep")
    (out / MANIFEST_FILE).write_text(json.dumps({"files": ["../victim.txt", "/etc/hostname"]}))
    with claim_output_dir(out, "perception eval") as d, tracked_outputs(d):
        pass
    assert (tmp_path / "victim.txt").read_text() == "keep"


def test_ownership_is_checked_up_the_tree(run_cli, tmp_path):
    """``perception detect --out`` into a synth dataset's images/ was allowed."""
    ds = tmp_path / "ds"
    with claim_output_dir(ds, "datasets synth"):
        (ds / "images").mkdir()
    frames = _frames(tmp_path / "f", ["0.png"])
    for out in (ds / "images", ds / "images" / "new" / "deeper"):
        res = run_cli(perception_cli.main, "detect", frames, "--dictionary", "DICT_4X4_50",
                      "--out", out)  # fmt: skip
        errors = [line for line in res.err.splitlines() if line.startswith("error")]
        assert res.code == 2 and len(errors) == 1, res.err
        assert f"{out} is inside {ds}, the output of `datasets synth`" in errors[0]
    # a symbolic link to the dataset's images/ is that folder (it was written into)
    link = tmp_path / "imglink"
    link.symlink_to(ds / "images")
    res = run_cli(perception_cli.main, "detect", frames, "--dictionary", "DICT_4X4_50",
                  "--out", link)  # fmt: skip
    errors = [line for line in res.err.splitlines() if line.startswith("error")]
    assert res.code == 2 and len(errors) == 1, res.err
    assert f"{(ds / 'images').resolve()} is inside {ds.resolve()}" in errors[0]
    assert sorted(p.name for p in (ds / "images").iterdir()) == []
    # the same tool may nest its own folders
    with claim_output_dir(ds / "images" / "more", "datasets synth"):
        pass
    with pytest.raises(DockError, match="is inside"):
        with claim_output_dir(ds / "x", "rl eval"):
            pass


def test_rl_eval_rerun_removes_the_films_and_traces_it_no_longer_makes(run_cli, tmp_path):
    from uwdock.rl import cli as rl_cli

    out = tmp_path / "e"
    env = tmp_path / "short.toml"
    env.write_text("episode_s = 3.0\n")
    common = ["eval", "--policy", "pid", "--obs", "proxy", "--config", env, "--out", out]
    first = run_cli(rl_cli.main, *common, "--episodes", "2", "--videos", "1", "--width", "160")
    assert first.code == 0, first.err
    assert {"camera_ep1.mp4", "camera_ep1_frames.jpg", "traces_ep1.png"} <= {
        p.name for p in out.iterdir()
    }
    (out / "mine.txt").write_text("a user's file")
    second = run_cli(rl_cli.main, *common, "--episodes", "1", "--videos", "")
    assert second.code == 0, second.err
    names = {p.name for p in out.iterdir() if not p.name.startswith(".")}
    assert names == {"episodes.csv", "summary.json", "traces_ep0.png", "trajectories_top.png",
                     "mine.txt"}  # fmt: skip
