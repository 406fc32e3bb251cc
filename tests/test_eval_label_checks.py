"""``perception eval`` checks a labelled dataset's labels the way ``datasets.loaders`` does
(issue 54: every value in its domain).

Before, ``perception eval DATASET`` read ``labels.jsonl`` with no check against the dataset: a
label naming ``../../etc/passwd``, a FIFO, a folder or a missing image, or a pose 1e9 m away,
went into the report. Now each is refused before any work: exit status 2, one ``error:`` line
naming the labels file, the line and the frame, and no output folder.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.hostile_runs import assert_refused
from tests.test_perception_cli import CAM, CORNERS_DS, MARKER_SET, look_at, render_board
from uwdock.calibration.camera import save_camera
from uwdock.calibration.frames import make_T
from uwdock.markers.markerset import save_marker_set
from uwdock.perception.cli import main
from uwdock.perception.groundtruth import label_frame, write_dataset_json, write_labels

N_FRAMES = 3


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A tiny dataset in the ``datasets synth`` format: three rendered views of the DS board
    with their labels (``T_world_body`` too), camera file and marker set."""
    root = tmp_path_factory.mktemp("evalchecks") / "ds"
    (root / "images").mkdir(parents=True)
    save_camera(root / "camera.yaml", CAM)
    save_marker_set(root / "markerset.toml", MARKER_SET)
    rng = np.random.default_rng(3)
    labels = []
    for k in range(N_FRAMES):
        T_cam_ds = look_at(1.4 + 0.2 * k, 8.0, 40.0 * k, 90.0)
        image = f"images/{k:06d}.png"
        cv2.imwrite(str(root / image), render_board(T_cam_ds, rng))
        T_world_body = make_T(t=[0.1 * k, 0.0, 2.0])
        labels.append(label_frame(k, T_cam_ds, CAM, CORNERS_DS, image, T_world_body))
    write_labels(root / "labels.jsonl", labels)
    write_dataset_json(root, N_FRAMES, config={"seed": 3})
    return root


def _variant(dataset: Path, tmp_path: Path, change) -> Path:
    """A copy of the dataset whose second label (line 2, frame 1) ``change(root, label)``
    edited (the label dict, or the files of the copy)."""
    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    lines = (root / "labels.jsonl").read_text().splitlines()
    label = json.loads(lines[1])
    change(root, label)
    lines[1] = json.dumps(label)  # NaN / Infinity are written as JSON's extensions
    (root / "labels.jsonl").write_text("\n".join(lines) + "\n")
    return root


def _release(fifo: Path, after_s: float = 20.0) -> None:
    """Let a reader that opened ``fifo`` go after ``after_s`` (an empty write end: EOF), so that
    code which opens it fails the test instead of hanging the suite."""
    end = time.monotonic() + after_s + 10.0
    time.sleep(after_s)
    while time.monotonic() < end and fifo.exists():
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))  # ENXIO: no reader yet
        except OSError:
            pass
        time.sleep(0.1)


def _fifo(root: Path, label: dict) -> None:
    fifo = root / label["image"]
    fifo.unlink()
    os.mkfifo(fifo)
    threading.Thread(target=_release, args=(fifo,), daemon=True).start()


def _link(target: str):
    def change(root: Path, label: dict) -> None:
        (root / label["image"]).unlink()
        (root / label["image"]).symlink_to(target)

    return change


def _set(key: str, value):
    return lambda root, label: label.update({key: value})


def _far(key: str, row: int, value: float):
    return lambda root, label: label[key][row].__setitem__(3, value)


def _nan_pose(root: Path, label: dict) -> None:
    label["T_cam_ds"][0][3] = float("nan")


def _inf_body(root: Path, label: dict) -> None:
    label["T_world_body"][1][3] = float("inf")


def _image_folder(root: Path, label: dict) -> None:
    (root / label["image"]).unlink()
    (root / label["image"]).mkdir()


#: (change, what the line says after "LABELS line 2 (frame 1): ", or None where the reader of
#: the labels refuses the value itself and names "LABELS line 2: ...")
HOSTILE = [
    pytest.param(_set("image", "../../etc/passwd"),
                 "image '../../etc/passwd' leads out of the dataset folder ('..')", id="dotdot"),
    pytest.param(_set("image", "/etc/passwd"),
                 "image '/etc/passwd' is not a path relative to the dataset folder",
                 id="absolute"),
    pytest.param(_set("image", "~/frame.png"), "is not a path relative to the dataset folder",
                 id="home"),
    pytest.param(_set("image", "images/a\x00.png"), "holds a NUL character", id="nul"),
    pytest.param(_link("/etc/passwd"), "leads out of the dataset folder (a symbolic link)",
                 id="symlink-out"),
    pytest.param(_link("/dev/zero"), "leads out of the dataset folder (a symbolic link)",
                 id="device-link"),
    pytest.param(_fifo, "image images/000001.png is a FIFO (named pipe), not a regular file",
                 id="fifo"),
    pytest.param(_set("image", "images"), "image images is a folder", id="folder"),
    pytest.param(_image_folder, "image images/000001.png is a folder", id="image-is-folder"),
    pytest.param(lambda r, lb: (r / lb["image"]).unlink(), "image images/000001.png is missing",
                 id="missing"),
    pytest.param(_set("image", None), "names no image", id="no-image"),
    pytest.param(_far("T_cam_ds", 2, 1e9), "T_cam_ds translation is 1e+09 m (at most 1000 m",
                 id="cam-1e9-m"),
    pytest.param(_far("T_world_body", 0, -2e6), "T_world_body translation is 2e+06 m",
                 id="body-2e6-m"),
    pytest.param(_set("range_m", 1e9), "range_m is 1e+09 m but T_cam_ds gives", id="range"),
    pytest.param(_set("view_angle_deg", 370.0), "view_angle_deg is 370 deg but T_cam_ds gives",
                 id="view-angle"),
    pytest.param(_nan_pose, None, id="nan-pose"),
    pytest.param(_inf_body, None, id="inf-body"),
    pytest.param(_set("range_m", float("inf")), None, id="inf-range"),
]  # fmt: skip


@pytest.mark.parametrize(("change", "message"), HOSTILE)
def test_eval_refuses_a_hostile_label_before_any_work(run_cli, dataset, tmp_path, change, message):
    root = _variant(dataset, tmp_path, change)
    out = tmp_path / "out"
    t0 = time.monotonic()
    res = run_cli(main, "eval", root, "--out", out)
    line = assert_refused(res, out)  # exit 2, one "error:" line, no output folder
    assert time.monotonic() - t0 < 15  # the FIFO is never opened
    labels = root / "labels.jsonl"
    if message is None:  # a non-finite number: refused where the labels are parsed
        assert f"{labels} line 2: " in line and "finite" in line, line
    else:
        assert f"{labels} line 2 (frame 1): " in line and message in line, line


@pytest.mark.parametrize(
    ("change", "message"),
    [HOSTILE[0], HOSTILE[6], HOSTILE[11]],
    ids=["dotdot", "fifo", "cam-1e9-m"],
)
def test_a_dataset_as_ground_truth_is_checked_too(run_cli, dataset, tmp_path, change, message):
    """``--ground-truth DATASET`` (or its ``dataset.json``) with frames from elsewhere."""
    root = _variant(dataset, tmp_path, change)
    for gt in (root, root / "dataset.json"):
        out = tmp_path / "out"
        res = run_cli(
            main, "eval", dataset / "images", "--camera", dataset / "camera.yaml",
            "--ground-truth", gt, "--out", out,
        )  # fmt: skip
        line = assert_refused(res, out)
        assert f"{root / 'labels.jsonl'} line 2 (frame 1): {message}" in line, line


def test_a_labels_file_as_ground_truth_has_its_poses_checked(run_cli, dataset, tmp_path):
    """A ``labels.jsonl`` alone (no dataset to check its images against): the poses' range."""
    root = _variant(dataset, tmp_path, _far("T_cam_ds", 2, 1e9))
    out = tmp_path / "out"
    res = run_cli(
        main, "eval", dataset / "images", "--camera", dataset / "camera.yaml",
        "--ground-truth", root / "labels.jsonl", "--out", out,
    )  # fmt: skip
    line = assert_refused(res, out)
    assert f"{root / 'labels.jsonl'} line 2 (frame 1): T_cam_ds translation is 1e+09 m" in line


def test_a_good_dataset_still_evaluates(run_cli, dataset, tmp_path):
    out = tmp_path / "out"
    res = run_cli(main, "eval", dataset, "--out", out, "--json")
    assert res.code == 0, res.err
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == N_FRAMES and report["corrupt_frames"] == 0
    assert report["ground_truth"] is not None and report["detection_rate"] == 1.0
    assert report["translation_error_m_median"] < 0.05
    # and as ground truth of its own images, folder and labels file
    for gt in (dataset, dataset / "labels.jsonl"):
        out = tmp_path / f"out_{gt.name}"
        res = run_cli(
            main, "eval", dataset / "images", "--camera", dataset / "camera.yaml",
            "--ground-truth", gt, "--out", out,
        )  # fmt: skip
        assert res.code == 0, res.err
        assert json.loads((out / "report.json").read_text())["frames"] == N_FRAMES
