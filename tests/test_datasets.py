"""datasets: pose sampling, the synth generator (determinism, workers, resume), the labels
against perception, the loaders and the ``datasets synth`` CLI.

Tests that render are marked ``render`` (SAPIEN on lavapipe or a GPU).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV, reference_camera
from uwdock.calibration.frames import inv_T, make_T, transform_points
from uwdock.datasets import cli as datasets_cli
from uwdock.datasets.loaders import load_poses_csv
from uwdock.datasets.synth import (
    PoseSamplingConfig,
    SynthConfig,
    frame_rng,
    generate,
    sample_pose,
)
from uwdock.dockcore.config import from_dict
from uwdock.dockcore.errors import ConfigError, DockError

CAM = reference_camera().scaled(320, 242)
T_BC = np.array(REFERENCE_T_BODYFRD_CAMCV)
T_WD = make_T(t=[0.0, 0.0, 4.98])  # the default DS pose (tank 5 m deep)


# ----------------------------------------------------------------------------- pose sampling


def _camera_stats(T_world_body: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(DS origin pixel, optical-axis tilt from straight down (deg), camera position)."""
    T_wc = T_world_body @ T_BC
    p_cam = transform_points(inv_T(T_wc), T_WD[:3, 3])
    tilt = math.degrees(math.acos(np.clip(T_wc[2, 2], -1.0, 1.0)))  # z_cam . down
    return CAM.project(p_cam), tilt, T_wc[:3, 3]


def test_aimed_poses_put_the_ds_origin_in_view_within_ranges():
    cfg = PoseSamplingConfig(aimed_fraction=1.0)
    ranges = []
    for k in range(300):
        T, kind = sample_pose(cfg, frame_rng(0, k), CAM, T_BC, T_WD)
        assert kind == "aimed"
        px, tilt, p_cam = _camera_stats(T)
        m = cfg.aimed_image_margin
        assert m * CAM.width_px - 0.5 - 1e-6 <= px[0] <= (1 - m) * CAM.width_px - 0.5 + 1e-6
        assert m * CAM.height_px - 0.5 - 1e-6 <= px[1] <= (1 - m) * CAM.height_px - 0.5 + 1e-6
        assert tilt <= cfg.aimed_tilt_max_deg + 1e-6
        assert p_cam[2] >= cfg.min_depth_m and T_WD[2, 3] - p_cam[2] >= cfg.min_height_m
        ranges.append(np.linalg.norm(T_WD[:3, 3] - p_cam))
    ranges = np.array(ranges)
    assert ranges.min() >= 1.0 - 1e-9 and ranges.max() <= 6.0 + 1e-9
    assert ranges.max() > 5.0 and ranges.min() < 1.5  # long oblique views survive rejection


def test_pose_mix_and_uniform_box():
    cfg = PoseSamplingConfig()
    kinds = []
    for k in range(1000):
        T, kind = sample_pose(cfg, frame_rng(1, k), CAM, T_BC, T_WD)
        kinds.append(kind)
        if kind == "uniform":
            d = T[:3, 3] - (T_WD[:3, 3] - [0.0, 0.0, cfg.uniform_height_m])
            assert np.all(np.abs(d) <= np.asarray(cfg.uniform_range_m) + 1e-9)
            tilt = math.degrees(math.acos(np.clip(T[2, 2], -1.0, 1.0)))
            assert tilt <= cfg.uniform_tilt_max_deg + 1e-6
    aimed = kinds.count("aimed") / len(kinds)
    assert abs(aimed - 0.8) < 0.04  # binomial sd 0.013


def test_frame_rng_is_per_seed_and_frame():
    a = frame_rng(3, 5).random(4)
    assert np.array_equal(a, frame_rng(3, 5).random(4))
    assert not np.allclose(a, frame_rng(4, 4).random(4))  # not seed + k
    assert not np.allclose(a, frame_rng(3, 6).random(4))


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="water"):
        from_dict(SynthConfig, {"water": "swamp"})
    with pytest.raises(ConfigError, match="n_frames"):
        from_dict(SynthConfig, {"n_frames": 0})
    with pytest.raises(ConfigError, match="aimed_fraction"):
        from_dict(SynthConfig, {"poses": {"aimed_fraction": 1.5}})


def test_poses_csv_quaternion_and_euler(tmp_path):
    q = tmp_path / "q.csv"
    q.write_text("x_m,y_m,z_m,qw,qx,qy,qz\n1,2,3,0,0,0,2\n")  # 180 deg about z, unnormalised
    e = tmp_path / "e.csv"
    e.write_text("frame,x_m,y_m,z_m,roll_deg,pitch_deg,yaw_deg\n0,1,2,3,0,0,180\n")
    expected = make_T(np.diag([-1.0, -1.0, 1.0]), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(load_poses_csv(q)[0], expected, atol=1e-12)
    np.testing.assert_allclose(load_poses_csv(e)[0], expected, atol=1e-12)
    bad = tmp_path / "bad.csv"
    bad.write_text("x_m,y_m,z_m,qw,qx,qy,qz\n1,2,x,1,0,0,0\n")
    with pytest.raises(DockError, match="line 2"):
        load_poses_csv(bad)
    missing = tmp_path / "missing.csv"
    missing.write_text("x_m,y_m\n1,2\n")
    with pytest.raises(DockError, match="missing column"):
        load_poses_csv(missing)


# ----------------------------------------------------------------------------- CLI errors


def _one_line_error(res) -> None:
    assert res.code != 0
    lines = res.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.err


def test_cli_bad_inputs(run_cli, tmp_path):
    out = tmp_path / "ds"
    res = run_cli(datasets_cli.main, "synth", "--n", "2", "--out", out, "--water", "swamp")
    _one_line_error(res)
    assert "swamp" in res.err
    _one_line_error(run_cli(datasets_cli.main, "synth", "--n", "0", "--out", out))
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    res = run_cli(datasets_cli.main, "synth", "--n", "1", "--out", blocker / "sub")
    _one_line_error(res)
    assert "cannot write" in res.err
    cfg = tmp_path / "bad.toml"
    cfg.write_text("n_frames = = 3\n")
    _one_line_error(run_cli(datasets_cli.main, "synth", "--out", out, "--config", cfg))
    cfg.write_text("frames_n = 3\n")
    res = run_cli(datasets_cli.main, "synth", "--out", out, "--config", cfg)
    _one_line_error(res)
    assert "frames_n" in res.err
    _one_line_error(run_cli(datasets_cli.main, "synth", "--out", out, "--workers", "0"))
    assert not (out / "dataset.json").exists()


# ----------------------------------------------------------------------------- rendering

TINY = SynthConfig(n_frames=6, seed=11, water="random", width_px=160)


def _tree(root: Path) -> dict[str, bytes]:
    files = sorted((root / "images").glob("*.png"))
    return {p.name: p.read_bytes() for p in files} | {
        "labels.jsonl": (root / "labels.jsonl").read_bytes()
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "one"
    result = generate(out, TINY, workers=1, progress=False)
    assert result.rendered == tuple(range(6))
    return out


@pytest.mark.render
@pytest.mark.slow  # ~11 s on 2 cores: in the slow set (CI runs it)
def test_two_workers_write_the_same_bytes(tiny, tmp_path):
    result = generate(tmp_path / "two", TINY, workers=2, progress=False)
    assert result.rendered == tuple(range(6))
    assert _tree(tmp_path / "two") == _tree(tiny)


@pytest.mark.render
def test_resume_renders_only_missing_frames(tiny, tmp_path):
    ref = _tree(tiny)
    # (a) finished dataset, two images deleted
    out = tmp_path / "a"
    shutil.copytree(tiny, out)
    for k in (1, 4):
        (out / "images" / f"{k:06d}.png").unlink()
    mtimes = {p.name: p.stat().st_mtime_ns for p in (out / "images").iterdir()}
    assert generate(out, TINY, progress=False).rendered == (1, 4)
    assert _tree(out) == ref
    for name, t in mtimes.items():
        assert (out / "images" / name).stat().st_mtime_ns == t
    # (b) a crash: per-frame labels of frames 0-2 only, no labels.jsonl, no dataset.json
    out = tmp_path / "b"
    shutil.copytree(tiny, out)
    lines = (out / "labels.jsonl").read_text().splitlines(keepends=True)
    (out / "labels.jsonl").unlink()
    (out / "dataset.json").unlink()
    (out / ".partial").mkdir()
    for k in range(3):
        (out / ".partial" / f"{k:06d}.json").write_text(lines[k])
    (out / "images" / "000004.png").unlink()  # 3 and 5 have images but no label
    assert generate(out, TINY, progress=False).rendered == (3, 4, 5)
    assert _tree(out) == ref
    assert not (out / ".partial").exists()
    # (c) another config in the same folder is refused
    with pytest.raises(DockError, match=r"another config \(differs in seed\)"):
        generate(out, SynthConfig(n_frames=6, seed=12, water="random", width_px=160))
    # (d) fewer frames would delete some: refused, nothing touched (tests/test_hostile_datasets)
    with pytest.raises(DockError, match="would delete frames 4-5"):
        generate(out, SynthConfig(n_frames=4, seed=11, water="random", width_px=160))
    assert _tree(out) == ref


@pytest.mark.render
def test_labels_agree_with_perception(tmp_path):
    from uwdock.markers.markerset import load_marker_set
    from uwdock.perception.detector import Detector, DetectorConfig
    from uwdock.perception.groundtruth import load_dataset
    from uwdock.perception.pose import solve_board

    cfg = SynthConfig(
        n_frames=6,
        seed=2,
        water="clear_tank",
        width_px=640,
        poses=PoseSamplingConfig(
            aimed_fraction=1.0, aimed_range_m=(1.4, 2.2), aimed_tilt_max_deg=15.0,
            aimed_image_margin=0.3,
        ),
    )  # fmt: skip
    out = tmp_path / "pnp"
    generate(out, cfg, progress=False)
    ds = load_dataset(out)
    ms = load_marker_set(ds.marker_set_path)
    from uwdock.calibration.camera import load_camera

    cam, _ = load_camera(ds.camera_path)
    detector = Detector(DetectorConfig(ids=ms.ids))
    checked = 0
    for ft in ds.frames.values():
        visible = ft.visible_ids
        if len(visible) < 3:
            continue
        img = cv2.imread(str(out / ft.image))
        dets = detector.detect(img)
        assert {d.marker_id for d in dets} <= set(ms.ids)
        assert len({d.marker_id for d in dets} & visible) >= 2
        # detected corners sit on the labelled ones (the median: a corner next to a guide
        # plate is sometimes refined a few px off, which the board solve absorbs)
        labelled = {m.marker_id: m.corners_px for m in ft.markers}
        err_px = [np.linalg.norm(d.corners_px - labelled[d.marker_id], axis=1) for d in dets]
        assert np.median(np.concatenate(err_px)) < 1.0, (ft.frame, err_px)
        pose = solve_board(dets, ms.corners_ds(), cam.K, cam.dist_coeffs)
        assert pose is not None
        err = np.linalg.norm(pose.T_cam_ds[:3, 3] - ft.T_cam_ds[:3, 3])
        assert err < 0.03, (ft.frame, err)
        checked += 1
    assert checked >= 2


@pytest.mark.render
def test_labelled_dataset_loader(tiny, tmp_path):
    from uwdock.datasets.loaders import FootageSource, LabelledDataset

    ds = LabelledDataset(tiny)
    assert len(ds) == 6 and ds.camera.width_px == 160
    np.testing.assert_allclose(ds.T_body_cam, REFERENCE_T_BODYFRD_CAMCV)
    assert set(ds.marker_set.ids) == {13, 14, 15, 28, 34}
    assert ds.config["seed"] == 11
    labels = [json.loads(s) for s in (tiny / "labels.jsonl").read_text().splitlines()]
    for sample, label in zip(ds, labels, strict=True):
        assert sample.image.shape == (ds.camera.height_px, ds.camera.width_px, 3)
        assert sample.image.dtype == np.uint8
        np.testing.assert_allclose(sample.truth.T_cam_ds, label["T_cam_ds"], atol=1e-9)
        t = np.asarray(label["T_cam_ds"])[:3, 3]
        assert sample.truth.range_m == pytest.approx(np.linalg.norm(t))
        # the labelled body pose, the camera extrinsics and the DS pose close the loop
        T_wd = np.asarray(label["T_world_body"]) @ T_BC @ np.asarray(label["T_cam_ds"])
        np.testing.assert_allclose(T_wd, T_WD, atol=1e-9)
        assert label["water"]["preset"] == "random"
    assert ds[-1].index == 5
    footage = FootageSource(tiny / "images")
    assert len(footage) == 6 and [i for i, _, _ in footage] == list(range(6))
    assert [i for i, _, _ in footage] == list(range(6))  # iterable again
    # a wrong version is refused with one line
    bad = tmp_path / "bad"
    shutil.copytree(tiny, bad)
    manifest = json.loads((bad / "dataset.json").read_text())
    (bad / "dataset.json").write_text(json.dumps({**manifest, "version": 2}))
    with pytest.raises(DockError, match="version") as exc:
        LabelledDataset(bad)
    assert "\n" not in str(exc.value)
    with pytest.raises(DockError):
        FootageSource(tmp_path / "nothing_here")


@pytest.mark.render
def test_cli_synth_tiny(run_cli, tmp_path):
    out = tmp_path / "cli"
    res = run_cli(
        datasets_cli.main, "synth", "--n", "2", "--out", out, "--width", "96",
        "--water", "turbid", "--seed", "4", "--json",
    )  # fmt: skip
    assert res.code == 0, res.err
    summary = json.loads(res.out)
    assert summary["frames"] == 2 and summary["rendered"] == 2
    labels = [json.loads(s) for s in (out / "labels.jsonl").read_text().splitlines()]
    assert [lab["frame"] for lab in labels] == [0, 1]
    assert all(lab["water"]["preset"] == "turbid" for lab in labels)
    assert cv2.imread(str(out / labels[0]["image"])).shape == (73, 96, 3)
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["format"] == "uwdock.dataset" and manifest["frames"] == 2
    assert (out / "config.toml").is_file() and (out / "provenance.json").is_file()
    # rerun: nothing to render
    res = run_cli(datasets_cli.main, "synth", "--n", "2", "--out", out, "--width", "96",
                  "--water", "turbid", "--seed", "4", "--json")  # fmt: skip
    assert res.code == 0 and json.loads(res.out)["rendered"] == 0
