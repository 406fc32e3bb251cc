"""``datasets synth`` against hostile input and interrupted runs: values that passed validation
and then crashed, a dataset shrunk by a smaller ``--n``, broken images kept on resume, two runs
into one folder, a run killed with SIGKILL (its workers, its temporary files, its resume).

Tests that render are marked ``render`` (SAPIEN on lavapipe or a GPU).
"""

from __future__ import annotations

import json
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.hostile_runs import assert_refused, dataset, dead_pid, group_process, tree
from uwdock.datasets import cli as datasets_cli
from uwdock.datasets.synth import PoseSamplingConfig, SynthConfig, generate
from uwdock.dockcore.config import replace
from uwdock.dockcore.errors import ConfigError, DockError

#: The dataset of these tests (the config of tests/test_datasets.py's: one render scene).
SMALL = SynthConfig(n_frames=6, seed=11, water="random", width_px=160)
SMALL_ARGS = ("--width", "160", "--seed", "11", "--water", "random")


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """A complete dataset of ``SMALL``, rendered uninterrupted."""
    out = tmp_path_factory.mktemp("hostile") / "small"
    assert generate(out, SMALL, progress=False).rendered == tuple(range(6))
    return out


# ----------------------------------------------------------------------------- values


def _markers_copy(tmp_path: Path) -> Path:
    """A copy of the default marker set folder (with render meshes); its marker set file."""
    from uwdock.sim.docking_station import default_marker_set

    ms = default_marker_set()
    folder = tmp_path / "markers"
    shutil.copytree(ms.render_mesh_path(ms.ids[0]).parent, folder)
    return folder / "markerset.toml"


@pytest.mark.parametrize(
    "toml,key",
    [
        pytest.param('[render]\nshader = "nope"\n', "render.shader", id="shader-unknown"),
        pytest.param('[render]\nshader = ""\n', "render.shader", id="shader-empty"),
        pytest.param(  # SAPIEN ships it, but it cannot render our scene
            '[render]\nshader = "vertex_color"\n', "render.shader", id="shader-unusable"
        ),
        pytest.param('[render]\nshader = "a\\u0000b"\n', "render.shader", id="shader-nul"),
        pytest.param("[render]\nnear_m = 1e-300\n", "render.near_m", id="near-tiny"),
        pytest.param(
            "[water_randomisation]\nbeta_log_sigma = inf\n", "beta_log_sigma", id="sigma-inf"
        ),
        pytest.param(
            "[water_randomisation]\nblur_scale_range = [0.5, inf]\n", "blur_scale_range[1]",
            id="blur-scale-inf",
        ),
        pytest.param(
            "[water_randomisation]\nphotons_at_white_range = [500.0, inf]\n",
            "photons_at_white_range[1]", id="photons-inf",
        ),
        pytest.param(
            "[water_randomisation]\nphotons_at_white_range = [1e-300, 1e-300]\n",
            "photons_at_white_range[0]", id="photons-tiny",
        ),
        pytest.param("width_px = 100000\n", "width_px", id="width-huge"),
        pytest.param("occlusion_tol_m = inf\n", "occlusion_tol_m", id="occlusion-inf"),
        pytest.param("seed = 4294967296\n", "seed", id="seed-huge"),
        pytest.param(
            "[poses]\nuniform_height_m = inf\n", "poses.uniform_height_m", id="height-inf"
        ),
        pytest.param(  # above the water surface of the 5 m tank
            "[poses]\nuniform_height_m = 40.0\n", "poses.uniform_height_m", id="height-above"
        ),
        pytest.param(
            "[poses]\ntank_margin_m = 50.0\n", "poses.tank_margin_m", id="tank-margin"
        ),
        pytest.param(
            "[poses]\naimed_range_m = [60.0, 80.0]\n", "poses.aimed_range_m", id="range-far"
        ),
        pytest.param(
            "[poses]\nmin_depth_m = 3.0\nmin_height_m = 3.0\n", "poses.min_depth_m",
            id="no-water-left",
        ),
    ],
)  # fmt: skip
def test_bad_config_values_stop_with_one_line(run_cli, tmp_path, toml, key):
    cfg = tmp_path / "synth.toml"
    cfg.write_text(toml, encoding="utf-8")
    out = tmp_path / "out"
    res = run_cli(datasets_cli.main, "synth", "--n", "1", "--out", out, "--config", cfg)
    assert key in assert_refused(res, out)


def test_bad_marker_size_and_width_stop_with_one_line(run_cli, tmp_path):
    out = tmp_path / "out"
    path = _markers_copy(tmp_path)
    path.write_text(path.read_text().replace("side_m = 0.1", "side_m = nan", 1))
    res = run_cli(datasets_cli.main, "synth", "--n", "1", "--out", out, "--markers", path)
    assert "side_m" in assert_refused(res, out)
    for width in ("100000", "-5", "8", "nan"):
        res = run_cli(datasets_cli.main, "synth", "--n", "1", "--out", out, "--width", width)
        assert "--width" in assert_refused(res, out) or "width_px" in res.err


def test_the_api_refuses_what_a_file_would(tmp_path):
    out = tmp_path / "out"
    for cfg in (
        SynthConfig(n_frames=1, occlusion_tol_m=float("nan")),
        SynthConfig(n_frames=1, poses=PoseSamplingConfig(tank_margin_m=float("inf"))),
        SynthConfig(n_frames=True),
    ):
        with pytest.raises(ConfigError):
            generate(out, cfg)
    for workers in (0, 65, 1.5):
        with pytest.raises(DockError, match="workers"):
            generate(out, SynthConfig(n_frames=1), workers=workers)
    far = np.eye(4)
    far[0, 3] = 1e30
    with pytest.raises(DockError, match=r"poses\[0\]"):
        generate(out, SynthConfig(n_frames=1), poses=[far])
    assert not out.exists()


# ----------------------------------------------------------------------------- resume


@pytest.mark.render
def test_fewer_frames_than_the_folder_holds_is_refused(run_cli, small, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(small, out)
    before = tree(out)
    res = run_cli(datasets_cli.main, "synth", "--n", "2", "--out", out, *SMALL_ARGS)
    line = assert_refused(res)
    assert "frames up to 5" in line and "would delete frames 2-5" in line
    assert tree(out) == before  # nothing deleted, nothing written
    # more frames extend the dataset: only the new one is rendered
    res = run_cli(datasets_cli.main, "synth", "--n", "7", "--out", out, *SMALL_ARGS, "--json")
    assert res.code == 0, res.err
    assert json.loads(res.out) | {"seconds": 0, "frames_per_s": 0} == {
        "out_dir": str(out), "frames": 7, "rendered": 1, "kept": 6, "seconds": 0,
        "frames_per_s": 0,
    }  # fmt: skip
    old, new = dataset(small), dataset(out)
    assert all(new[name] == data for name, data in old.items() if name.startswith("images/"))
    assert new["labels.jsonl"].startswith(old["labels.jsonl"])
    # an interrupted run (frames as images and partial labels only) is not shrunk either
    out = tmp_path / "crashed"
    shutil.copytree(small, out)
    lines = (out / "labels.jsonl").read_text().splitlines(keepends=True)
    (out / "labels.jsonl").unlink()
    (out / "dataset.json").unlink()
    (out / ".partial").mkdir()
    for k, line in enumerate(lines):
        (out / ".partial" / f"{k:06d}.json").write_text(line)
    (out / "images" / "000005.png").unlink()
    before = tree(out)
    res = run_cli(datasets_cli.main, "synth", "--n", "4", "--out", out, *SMALL_ARGS)
    assert "would delete frames 4-5" in assert_refused(res)
    assert tree(out) == before


@pytest.mark.render
def test_resume_renders_broken_images_again(small, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(small, out)
    images = out / "images"
    png = (images / "000002.png").read_bytes()
    (images / "000001.png").write_bytes(b"")  # zero length
    (images / "000002.png").write_bytes(png[: len(png) // 2])  # truncated
    (images / "000003.png").write_bytes(b"not a png at all")  # undecodable
    flipped = bytearray((images / "000004.png").read_bytes())
    flipped[len(flipped) // 2] ^= 0xFF  # one corrupted byte inside the pixel data
    (images / "000004.png").write_bytes(bytes(flipped))
    assert generate(out, SMALL, progress=False).rendered == (1, 2, 3, 4)
    assert dataset(out) == dataset(small)


@pytest.mark.render
def test_stale_temporary_files_of_a_killed_run_are_removed(small, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(small, out)
    dead = dead_pid()
    stale = [
        out / "images" / f".000002.png.{dead}.k3x9_q.uwtmp",
        out / f".labels.jsonl.{dead}.a1b2c3d4.uwtmp",
        out / ".partial" / f".000001.json.{dead}.zz.uwtmp",
    ]
    for p in stale:
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(b"half a frame")
    assert generate(out, SMALL, progress=False).rendered == ()
    assert not any(p.exists() for p in stale)
    assert dataset(out) == dataset(small)


# ----------------------------------------------------------------------------- processes


def _wait_for(condition, timeout_s: float, what: str, period_s: float = 0.01) -> None:
    end = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(period_s)


def _gone(proc: psutil.Process) -> bool:
    try:
        return proc.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _frames_on_disk(out: Path) -> set[str]:
    """Names of the complete images and partial labels in a dataset folder."""
    return {p.name for p in (out / "images").glob("*.png")} | {
        p.name for p in (out / ".partial").glob("*.json")
    }


def _owner_pid(out: Path) -> int | None:
    try:
        return json.loads((out / ".uwdock-owner.json").read_text()).get("pid")
    except (OSError, ValueError):
        return None


@pytest.mark.render
@pytest.mark.slow  # ~14 s on 2 cores: in the slow set (CI runs it)
def test_second_run_and_sigkill_leave_nothing_behind(run_cli, small, tmp_path):
    """Two real ``datasets synth`` processes into one folder: the second stops at once with one
    line naming the first. The first (two workers) is then killed with SIGKILL mid-run: its
    workers die with it (without it they would each finish a frame into the folder, then
    fail), and a rerun completes the dataset byte for byte as an uninterrupted run makes it
    (the killed run's temporary files are gone)."""
    n = 80  # about a second of rendering for two workers at 160 px, once they are ready
    out = tmp_path / "ds"
    args = ("synth", "--n", n, "--out", out, *SMALL_ARGS, "--quiet")
    first = group_process("datasets", *args, "--workers", "2")
    try:
        _wait_for(lambda: _owner_pid(out) == first.pid, 60, "the first run's claim", 0.05)
        second = group_process("datasets", *args)
        _, err = second.communicate(timeout=60)
        assert second.returncode == 2, err
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), err
        assert "in use" in err and "datasets synth" in err and f"pid {first.pid}" in err
        assert not [p for p in out.rglob("*") if f".{second.pid}." in p.name]
        assert _owner_pid(out) == first.pid

        # a whole frame (its image, then its partial label): waiting for the image alone let
        # the kill land between the two, and the rerun then had no frame to keep
        _wait_for(lambda: any((out / ".partial").glob("*.json")), 120, "the first whole frame")
        workers = psutil.Process(first.pid).children(recursive=True)
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=10)
        on_disk = _frames_on_disk(out)
    finally:
        if first.poll() is None:
            first.kill()
    assert len(workers) >= 2
    _wait_for(lambda: all(_gone(w) for w in workers), 5, "the workers to end", 0.05)
    assert _frames_on_disk(out) == on_disk, "workers wrote frames after the run was killed"
    assert 0 < len(list((out / "images").glob("*.png"))) < n, "it ended before the kill"

    res = run_cli(datasets_cli.main, *[str(a) for a in args], "--json")
    assert res.code == 0, res.err
    summary = json.loads(res.out)
    assert summary["frames"] == n and summary["kept"] > 0
    reference = tmp_path / "reference"
    generate(reference, replace(SMALL, n_frames=n), progress=False)
    assert dataset(out) == dataset(reference)
    assert not list(out.rglob("*.uwtmp*")) and not (out / ".partial").exists()
