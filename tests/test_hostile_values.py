"""Values outside their domain (issue 54, part 4): error-model covariances that are not symmetric
positive definite, error-model files Python's JSON reader cannot take, dataset labels that lead
out of their dataset, name a missing image or a FIFO, or put the station 10^9 m away, an empty
``--config``, and library warnings that leaked as raw lines. Each is one line and exit 2 (or one
``note:`` line), with nothing written."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.error_models import synthetic_model
from tests.hostile_runs import ROOT, assert_refused
from uwdock.dockcore.errors import DockError
from uwdock.rl import cli as rl_cli
from uwdock.rl.env.error_model import load_error_model

BIAS = np.zeros(6)
#: 5 mm and 0.01 rad standard deviations, a little correlation between x and y
COV = np.diag([0.005**2] * 3 + [0.01**2] * 3)
COV[0, 1] = COV[1, 0] = 0.3 * 0.005**2


def _model_file(tmp_path: Path, cov: np.ndarray, name: str = "em.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(synthetic_model(0.9, BIAS, cov)))
    return path


def _one_line_error(path: Path) -> str:
    with pytest.raises(DockError) as exc:
        load_error_model(path)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


# ----------------------------------------------------------------------------- error models


def test_a_covariance_that_is_not_positive_semidefinite_is_refused(tmp_path):
    """Before, the matrix was projected to the nearest PSD one without a word: a model whose
    variances said 5 mm sampled errors of 0.7 m. A zero variance (an exact component) is a
    covariance and loads."""
    bad = COV.copy()
    bad[0, 1] = bad[1, 0] = 0.5  # |corr| >> 1
    msg = _one_line_error(_model_file(tmp_path, bad))
    assert "tables.all.bins[0].cov: not positive semi-definite (smallest eigenvalue -0.5" in msg
    semidefinite = COV.copy()
    semidefinite[2, 2] = 0.0  # a variance of zero: that component is exact
    semidefinite[0, 2] = semidefinite[2, 0] = semidefinite[1, 2] = semidefinite[2, 1] = 0.0
    model = load_error_model(_model_file(tmp_path, semidefinite))
    assert model.table("all")["cov"][0, 2, 2] == 0.0


def test_an_asymmetric_covariance_is_refused_a_rounding_one_is_not(tmp_path):
    bad = COV.copy()
    bad[0, 1] = 1e-5  # [1][0] stays 7.5e-6
    msg = _one_line_error(_model_file(tmp_path, bad))
    assert "tables.all.bins[0].cov: not symmetric (tables.all.bins[0].cov[0][1] = 1e-05" in msg
    # a few ulps of asymmetry (a file written by another tool): loads, as it is
    rounding = COV.copy()
    rounding[0, 1] *= 1 + 1e-13
    model = load_error_model(_model_file(tmp_path, rounding))
    np.testing.assert_array_equal(model.table("all")["cov"][0], rounding)
    L = model.table("all")["chol"][0]
    np.testing.assert_allclose(L @ L.T, rounding, rtol=1e-12, atol=0)


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "rl" / "models").glob("*.json")))
def test_the_shipped_error_models_still_load(name):
    model = load_error_model(ROOT / "rl" / "models" / name)
    for water in model.data["tables"]:
        cov = model.table(water)["cov"]
        assert np.array_equal(cov, np.swapaxes(cov, 1, 2))  # symmetric to the bit
        assert np.linalg.eigvalsh(cov).min() > 0


def test_json_python_cannot_read_and_an_array_are_one_line(tmp_path):
    text = json.dumps(synthetic_model(0.9, BIAS, COV))
    long_int = tmp_path / "digits.json"  # past Python's int-to-str limit (4300 digits)
    long_int.write_text(text.replace('"range_bin_m": 0.5', '"range_bin_m": ' + "1" * 5001))
    assert "malformed JSON (a number too long)" in _one_line_error(long_int)
    array = tmp_path / "array.json"
    array.write_text("[1, 2, 3]")
    assert "not an error model (a JSON list, not an object)" in _one_line_error(array)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    assert "malformed JSON" in _one_line_error(deep)


def test_rl_eval_refuses_a_bad_covariance_in_one_line(run_cli, tmp_path):
    bad = COV.copy()
    bad[0, 1] = bad[1, 0] = 0.5
    em = _model_file(tmp_path, bad)
    out = tmp_path / "e"
    res = run_cli(rl_cli.main, "eval", "--policy", "pid", "--obs", "error-model",
                  "--error-model", em, "--episodes", "1", "--out", out)  # fmt: skip
    line = assert_refused(res, out)
    assert "em.json" in line and "cov: not positive semi-definite" in line


# ----------------------------------------------------------------------------- dataset labels


@pytest.fixture(scope="module")
def labelled(tmp_path_factory) -> Path:
    """A small labelled dataset in the ``datasets synth`` format: real labels of the default
    board, blank images (nothing to detect: the labels are what these tests are about)."""
    from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV, reference_camera, save_camera
    from uwdock.calibration.frames import inv_T, make_T
    from uwdock.markers.config import MarkerConfig
    from uwdock.markers.markerset import marker_set_from_config, save_marker_set
    from uwdock.perception.groundtruth import label_frame, write_dataset_json, write_labels

    root = tmp_path_factory.mktemp("labels") / "ds"
    (root / "images").mkdir(parents=True)
    cam = reference_camera().scaled(160, 121)
    T_bc = np.asarray(REFERENCE_T_BODYFRD_CAMCV)
    save_camera(root / "camera.yaml", cam, T_bc)
    ms = marker_set_from_config(MarkerConfig())
    save_marker_set(root / "markerset.toml", ms)
    T_world_ds = make_T(t=[0.0, 0.0, 4.98])
    frames = []
    for k in range(3):
        T_world_body = make_T(t=[0.1 * k, 0.0, 2.0])
        T_cam_ds = inv_T(T_world_body @ T_bc) @ T_world_ds
        image = f"images/{k:06d}.png"
        cv2.imwrite(str(root / image), np.full((121, 160, 3), 40, np.uint8))
        frames.append(label_frame(k, T_cam_ds, cam, ms.corners_ds(), image, T_world_body))
    write_labels(root / "labels.jsonl", frames)
    write_dataset_json(root, len(frames))
    return root


def _variant(labelled: Path, tmp_path: Path, change) -> Path:
    """A copy of the dataset whose second label (line 2, frame 1) ``change(root, label)``
    edited."""
    root = tmp_path / "ds"
    shutil.copytree(labelled, root)
    lines = (root / "labels.jsonl").read_text().splitlines()
    label = json.loads(lines[1])
    change(root, label)
    lines[1] = json.dumps(label)
    (root / "labels.jsonl").write_text("\n".join(lines) + "\n")
    return root


def _far(root: Path, label: dict) -> None:
    label["T_cam_ds"][2][3] = 1e9
    del label["range_m"], label["view_angle_deg"]  # as a reader recomputes them


def _fifo(root: Path, label: dict) -> None:
    fifo = root / label["image"]
    fifo.unlink()
    os.mkfifo(fifo)
    threading.Thread(target=_release, args=(fifo,), daemon=True).start()


def _release(fifo: Path, after_s: float = 20.0) -> None:
    """Let a reader that opened ``fifo`` go after ``after_s`` (an empty write end: EOF), so
    that code which opens it fails this test instead of hanging the suite."""
    end = time.monotonic() + after_s + 10.0
    time.sleep(after_s)
    while time.monotonic() < end and fifo.exists():
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))  # ENXIO: no reader yet
        except OSError:
            pass
        time.sleep(0.1)


def _link_out(root: Path, label: dict) -> None:
    (root / label["image"]).unlink()
    (root / label["image"]).symlink_to("/etc/passwd")


@pytest.mark.parametrize(
    "change,message",
    [
        pytest.param(_far, "T_cam_ds translation is 1e+09 m (at most 1000 m", id="1e9-m"),
        pytest.param(lambda r, lb: lb["T_world_body"][0].__setitem__(3, -2e6),
                     "T_world_body translation is 2e+06 m", id="body-2e6-m"),
        pytest.param(lambda r, lb: lb.update(range_m=1e9),
                     "range_m is 1e+09 m but T_cam_ds gives", id="range"),
        pytest.param(lambda r, lb: (r / lb["image"]).unlink(),
                     "image images/000001.png is missing", id="missing-image"),
        pytest.param(lambda r, lb: lb.update(image="/etc/passwd"),
                     "image '/etc/passwd' is not a path relative to the dataset folder",
                     id="absolute"),
        pytest.param(lambda r, lb: lb.update(image="../../../../../etc/passwd"),
                     "leads out of the dataset folder ('..')", id="dotdot"),
        pytest.param(_link_out, "leads out of the dataset folder (a symbolic link)", id="symlink"),
        pytest.param(_fifo, "image images/000001.png is a FIFO (named pipe), not a regular file",
                     id="fifo"),
        pytest.param(lambda r, lb: lb.update(image="images"), "image images is a folder",
                     id="folder"),
        pytest.param(lambda r, lb: lb.update(image=None), "names no image", id="no-image"),
    ],
)  # fmt: skip
def test_labels_are_checked_against_their_dataset(run_cli, labelled, tmp_path, change, message):
    """`rl fit-error-model` (and every reader through datasets.loaders): one line naming the
    labels file, the line and the frame. Before, all of these were fitted on (the label at
    10^9 m in the model's last range bin; the image outside the dataset read, or dropped
    without a word) and the FIFO hung the fit forever."""
    from uwdock.datasets.loaders import LabelledDataset

    root = _variant(labelled, tmp_path, change)
    out = tmp_path / "em.json"
    t0 = time.monotonic()
    res = run_cli(rl_cli.main, "fit-error-model", root, "--out", out)
    line = assert_refused(res, out)
    assert time.monotonic() - t0 < 30
    assert f"{root / 'labels.jsonl'} line 2 (frame 1): " in line and message in line, line
    with pytest.raises(DockError, match="line 2 \\(frame 1\\)"):
        LabelledDataset(root)


def test_manifest_paths_stay_inside_the_dataset(labelled, tmp_path):
    from uwdock.datasets.loaders import load_checked_dataset

    root = tmp_path / "ds"
    shutil.copytree(labelled, root)
    manifest = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**manifest, "camera": "/etc/hostname"}))
    with pytest.raises(DockError, match="'camera' '/etc/hostname' is not a path relative"):
        load_checked_dataset(root)
    # the images folder may be a link to another disk
    elsewhere = tmp_path / "disk" / "images"
    shutil.move(root / "images", elsewhere)
    (root / "images").symlink_to(elsewhere)
    (root / "dataset.json").write_text(json.dumps(manifest))
    assert len(load_checked_dataset(root).frames) == 3


def test_a_good_dataset_still_fits(run_cli, labelled, tmp_path):
    out = tmp_path / "em.json"
    res = run_cli(rl_cli.main, "fit-error-model", labelled, "--out", out)
    assert res.code == 0, res.err
    assert json.loads(out.read_text())["dataset"]["frames"] == 3


# ----------------------------------------------------------------------------- empty configs


@pytest.mark.parametrize(
    "text,why",
    [("", "0 bytes"), ("# only a comment\n\n", "only comments or empty tables"),
     ("[train]\n[env]\n", "only comments or empty tables")],
)  # fmt: skip
def test_an_empty_training_config_is_refused(run_cli, tmp_path, text, why):
    """Before, `rl train --config empty.toml` started a 2,000,000-step run with the defaults
    without a word."""
    cfg = tmp_path / "empty.toml"
    cfg.write_text(text)
    out = tmp_path / "run"
    # (the flags only keep a run that is not refused short)
    res = run_cli(rl_cli.main, "train", "--config", cfg, "--out", out, "--steps", "64")
    line = assert_refused(res, out)
    assert line == (
        f"error: config {cfg} is empty ({why}): it sets no [train] value; leave --config out "
        "to run with the defaults"
    )


def test_every_command_taking_a_config_refuses_an_empty_one(run_cli, tmp_path):
    from uwdock.datasets import cli as datasets_cli
    from uwdock.markers import cli as markers_cli

    cfg = tmp_path / "empty.toml"
    cfg.write_text("")
    out = tmp_path / "o"
    # (the flags only keep a run that is not refused short; `rl sweep` reads its config as
    # `rl train` does)
    runs = [
        (rl_cli.main, "eval", "--policy", "pid", "--obs", "proxy", "--episodes", "1", "[env]"),
        (rl_cli.main, "episode", "--seconds", "1", "--width", "32", "--outside-width", "32",
         "[env]"),
        (rl_cli.main, "trajectories", "--episodes", "1", "[env]"),
        (datasets_cli.main, "synth", "--n", "1", "--width", "32", "[synth]"),
        (markers_cli.main, "generate", "[marker]"),
    ]  # fmt: skip
    for main, *args, table in runs:
        line = assert_refused(run_cli(main, *args, "--config", cfg, "--out", out), out)
        assert f"config {cfg} is empty (0 bytes): it sets no {table} value" in line, args


# ----------------------------------------------------------------------------- library noise


def test_library_warnings_become_one_note_line():
    import io

    from uwdock.dockcore.library_notes import library_notes

    err = io.StringIO()
    with library_notes(err):
        sb3 = (
            "You have specified a mini-batch size of 32, but because the `RolloutBuffer` is of "
            "size `n_steps * n_envs = 48`, after every 1 untruncated mini-batches, there will be "
            "a truncated mini-batch of size 16\nWe recommend using a `batch_size` that is a "
            "factor of `n_steps * n_envs`.\nInfo: (n_steps=48 and n_envs=1)"
        )
        warnings.warn_explicit(sb3, UserWarning, "/x/site-packages/stable_baselines3/ppo/ppo.py", 1)
        warnings.warn_explicit(sb3, UserWarning, "/x/site-packages/stable_baselines3/ppo/ppo.py", 1)
        warnings.warn_explicit(
            "\x1b[33mWARN: The obs returned by the `step()` method is not within the observation "
            "space.\x1b[0m", UserWarning, "/x/site-packages/gymnasium/utils/passive_env_checker.py",
            2,
        )  # fmt: skip
        warnings.warn_explicit(
            "The given NumPy array is not writable", UserWarning, "/x/site-packages/torch/a.py", 3
        )
    assert err.getvalue().splitlines() == [
        "note: ppo.batch_size 32 does not divide the rollout of 48 steps (ppo.n_steps x "
        "n_envs): each epoch ends with a mini-batch of 16; a batch_size that divides 48 avoids it",
        "note: gymnasium UserWarning: The obs returned by the `step()` method is not within the "
        "observation space.",
    ]


@pytest.mark.slow  # a real (tiny) training run: about 15 s
def test_rl_train_says_the_sb3_batch_warning_in_one_line(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "total_steps = 48\nn_envs = 1\neval_every = 0\ncheckpoint_every = 48\n"
        "[ppo]\nn_steps = 48\nbatch_size = 32\nn_epochs = 1\n[env]\nepisode_s = 2.0\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", "from uwdock.cli import rl; rl()", "train", "--config", cfg,
         "--out", tmp_path / "run"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "warnings.warn" not in proc.stderr and "UserWarning" not in proc.stderr
    notes = [line for line in proc.stderr.splitlines() if "mini-batch" in line]
    assert notes == [
        "note: ppo.batch_size 32 does not divide the rollout of 48 steps (ppo.n_steps x n_envs): "
        "each epoch ends with a mini-batch of 16; a batch_size that divides 48 avoids it"
    ]
