"""A full disk never empties an existing file (issue 32): every command that writes over an
existing file is run with ENOSPC raised at one of its writes (drawn by hypothesis), and must
stop with one ``error:`` line (exit status 2) leaving the file it was writing byte for byte as
it was; files written as one unit (camera twins, an ONNX policy and its ``.json``) are all left
as they were.

The disk is "filled" in :func:`uwdock.dockcore.io._sync`, the step every atomic write takes
between writing its temporary file and renaming it (where a late write error surfaces).
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import re
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uwdock.dockcore import io as dio
from uwdock.dockcore.io import TEMP_MARK, atomic_write_files

ROOT = Path(__file__).resolve().parent.parent
_TEMP_NAME = re.compile(r"^\.(.+)\.\d+\.[A-Za-z0-9_]+\.uwtmp")
_REAL_SYNC = dio._sync


class FullDisk:
    """``dockcore.io._sync`` that raises ENOSPC at its ``fail_at``-th call (0-based), or at
    the first write of a file named ``fail_on``; records the target of the write it failed
    and counts every call."""

    def __init__(self, fail_at: int | None, fail_on: str | None = None) -> None:
        self.fail_at = fail_at
        self.fail_on = fail_on
        self.calls = 0
        self.target: Path | None = None
        #: the target's bytes when its write failed (None: it did not exist)
        self.target_bytes: bytes | None = None

    def __call__(self, path: Path) -> int:
        k, self.calls = self.calls, self.calls + 1
        target = Path(path).with_name(_TEMP_NAME.match(Path(path).name).group(1))
        if self.target is None and (k == self.fail_at or target.name == self.fail_on):
            self.target = target
            if self.target.is_file():
                self.target_bytes = self.target.read_bytes()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return _REAL_SYNC(path)


def _run(main: Callable[[], None], args: list, full_disk: FullDisk) -> tuple[int, str, str]:
    """Run a console entry point in-process with ``_sync`` replaced: (exit status, out, err)."""
    out, err = io.StringIO(), io.StringIO()
    argv, sync = sys.argv, dio._sync
    sys.argv = ["prog", *map(str, args)]
    dio._sync = full_disk
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv, dio._sync = argv, sync
    return code, out.getvalue(), err.getvalue()


def _snapshot(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@dataclass
class Case:
    """A command that writes over existing files.

    Attributes:
        main: the console entry point.
        prepare: makes the inputs and the existing outputs in a folder; returns the arguments
            of the run that overwrites them.
        unit: the outputs are written as one unit (all are left as they were on a failure).
    """

    main: Callable[[], None]
    prepare: Callable[[Path], list]
    unit: bool


def _calibration():
    from uwdock.calibration import cli

    return cli.main


def _prep_reference(d: Path) -> list:
    ok = _run(_calibration(), ["reference-camera", "--out", d / "cam.yaml", "--width", 640],
              FullDisk(None))  # fmt: skip
    assert ok[0] == 0, ok
    return ["reference-camera", "--out", d / "cam.yaml", "--width", 480]


def _prep_extrinsics(d: Path) -> list:
    _prep_reference(d)
    return ["extrinsics", "set", d / "cam.yaml", "--xyz-m", 1, 2, 3, "--rpy-deg", 0, 0, 90]


def _prep_import(d: Path) -> list:
    from uwdock.calibration.camera import reference_camera
    from uwdock.calibration.formats_export import ros_camera_info_yaml

    (d / "ost.yaml").write_text(ros_camera_info_yaml(reference_camera().scaled(640, 484)))
    _prep_reference(d)
    return ["import", d / "ost.yaml", "--out", d / "cam.yaml"]


def _prep_export(d: Path) -> list:
    from uwdock.rl import cli

    policies = ROOT / "rl" / "policies"
    out = d / "p.onnx"
    ok = _run(cli.main, ["export", "--policy", policies / "error_model_ppo", "--out", out],
              FullDisk(None))  # fmt: skip
    assert ok[0] == 0, ok
    return ["export", "--policy", policies / "scratch_error_model_ppo", "--out", out]


def _rl():
    from uwdock.rl import cli

    return cli.main


def _markers():
    from uwdock.markers import cli

    return cli.main


def _prep_markers(d: Path) -> list:
    args = ["generate", "--ids", "13", "--out", d / "m"]
    ok = _run(_markers(), [*args, "--size-mm", 80], FullDisk(None))
    assert ok[0] == 0, ok
    return [*args, "--size-mm", 90]


def _perception():
    from uwdock.perception import cli

    return cli.main


def _prep_eval(d: Path) -> list:
    import cv2

    from uwdock.calibration.camera import reference_camera, save_camera

    frames = d / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        cv2.imwrite(str(frames / f"{k}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
    save_camera(d / "cam.yaml", reference_camera().scaled(64, 48))
    args = ["eval", frames, "--camera", d / "cam.yaml", "--dictionary", "DICT_4X4_50",
            "--marker-size-m", "0.1", "--out", d / "e"]  # fmt: skip
    ok = _run(_perception(), args, FullDisk(None))
    assert ok[0] == 0, ok
    return args


CASES = {
    "calibration reference-camera": lambda: Case(_calibration(), _prep_reference, True),
    "calibration extrinsics set": lambda: Case(_calibration(), _prep_extrinsics, True),
    "calibration import": lambda: Case(_calibration(), _prep_import, True),
    "rl export": lambda: Case(_rl(), _prep_export, True),
    "markers generate": lambda: Case(_markers(), _prep_markers, False),
    "perception eval": lambda: Case(_perception(), _prep_eval, False),
}
#: Per case: a prepared folder (its existing outputs), the overwriting run's arguments, and
#: how many writes (``_sync`` calls) that run makes; made once.
_PREPARED: dict[str, tuple[Path, list, int]] = {}


def _prepared(name: str, case: Case, tmp_path_factory) -> tuple[Path, list, int]:
    if name not in _PREPARED:
        template = tmp_path_factory.mktemp("template") / "run"
        template.mkdir()
        args = case.prepare(template)
        count = tmp_path_factory.mktemp("count") / "run"
        shutil.copytree(template, count, symlinks=True)
        counter = FullDisk(None)
        code, _, err = _run(case.main, _moved(args, template, count), counter)
        assert code == 0, err
        _PREPARED[name] = (template, args, counter.calls)
    return _PREPARED[name]


def _moved(args: list, old: Path, new: Path) -> list:
    """``args`` with paths inside ``old`` moved to ``new``."""
    out = []
    for a in args:
        if isinstance(a, Path) and a.is_relative_to(old):
            a = new / a.relative_to(old)
        out.append(a)
    return out


@pytest.mark.parametrize("name", list(CASES))
@settings(
    max_examples=4,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(data=st.data())
@pytest.mark.slow  # ~19 s on 2 cores: in the slow set (CI runs it)
def test_a_full_disk_leaves_existing_files_intact(tmp_path_factory, name, data):
    case = CASES[name]()
    template, template_args, n = _prepared(name, case, tmp_path_factory)
    fail_at = data.draw(st.integers(0, n - 1), label="failing write")
    d = tmp_path_factory.mktemp("full") / "run"
    shutil.copytree(template, d, symlinks=True)
    args = _moved(template_args, template, d)
    before = _snapshot(d)
    disk = FullDisk(fail_at)
    code, out, err = _run(case.main, args, disk)
    assert code == 2, (code, out, err)
    lines = [line for line in err.splitlines() if line.startswith("error")]
    assert len(lines) == 1 and "no space left on the device" in lines[0], err
    assert "Traceback" not in err
    assert disk.target is not None and str(disk.target) in lines[0], (disk.target, lines)
    after = _snapshot(d)
    assert not [p for p in after if TEMP_MARK in p.name], "temporary files left behind"
    if case.unit:
        assert after == before  # every output of the unit, byte for byte
    else:
        # the file being written keeps the bytes it had (a file written twice by the run, as
        # report.json: those of the run's first write)
        assert after.get(disk.target) == disk.target_bytes
        for p, data_before in before.items():  # nothing emptied, nothing lost
            assert p in after and (after[p] == data_before or after[p]), p


def test_synth_camera_is_kept_on_a_full_disk(tmp_path):
    """``datasets synth`` resumed on a full disk: its camera twins were left 0-byte."""
    from uwdock.datasets import cli

    out = tmp_path / "ds"
    args = ["synth", "--n", 1, "--width", 64, "--quiet", "--out", out]
    assert _run(cli.main, args, FullDisk(None))[0] == 0
    before = _snapshot(out)
    args[2] = 2  # extend: the camera is written again
    disk = FullDisk(None, fail_on="camera.yaml")
    code, _, err = _run(cli.main, args, disk)
    assert code == 2 and "no space left on the device" in err and err.count("\n") == 1, err
    assert disk.target == out / "camera.yaml"
    after = _snapshot(out)
    for name in ("camera.yaml", "camera.json"):  # the twins, as one unit
        assert after[out / name] == before[out / name] and before[out / name]
    assert not [p for p in after if TEMP_MARK in p.name]


def test_a_failed_rename_puts_the_old_set_back(tmp_path, monkeypatch):
    """atomic_write_files: the second rename fails, the first file gets its old bytes back; a
    file that did not exist before is removed again."""
    a, b, c = tmp_path / "a.onnx", tmp_path / "a.json", tmp_path / "new.txt"
    a.write_bytes(b"old onnx")
    b.write_bytes(b"old json")
    real = os.replace
    calls = []

    def replace(src, dst):
        calls.append(Path(dst))
        if Path(dst) == b and TEMP_MARK in Path(src).name and len(calls) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError) as exc:
        atomic_write_files({c: b"fresh", a: b"new onnx", b: b"new json"})
    assert exc.value.errno == errno.ENOSPC and exc.value.filename == str(b)
    assert a.read_bytes() == b"old onnx" and b.read_bytes() == b"old json" and not c.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "a.onnx"]
    monkeypatch.undo()
    atomic_write_files({a: b"new onnx", b: b"new json"})
    assert a.read_bytes() == b"new onnx" and b.read_bytes() == b"new json"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "a.onnx"]


def test_a_write_that_does_not_read_back_is_refused(tmp_path, monkeypatch):
    """A writer that reports success but leaves fewer bytes (FileStorage on a full disk)."""
    target = tmp_path / "cam.yaml"
    target.write_bytes(b"old")
    monkeypatch.setattr(dio, "_write_all", lambda path, data: path.write_bytes(data[:-1]))
    with pytest.raises(OSError) as exc:
        dio.atomic_write_bytes(target, b"new content")
    assert exc.value.errno == errno.EIO and exc.value.filename == str(target)
    assert "does not read back (10 of 11 bytes)" in str(exc.value)
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["cam.yaml"]


def test_intrinsics_over_an_existing_camera_on_a_full_disk(tmp_path):
    """``calibration intrinsics --out cam.yaml`` over an existing file said "no space left"
    but left the old file empty; now both twins keep their bytes, whichever fails. With 2-3
    pages free the small twins went through and the report or the plot failed after them: the
    run exited 2 with the new calibration in cam.yaml/cam.json. All four files are one unit
    now: whichever fails, every existing file keeps its bytes."""
    import cv2

    from tests.test_calibration import (
        CB_ARGS,
        DIST_TRUE,
        H_PX,
        K_TRUE,
        W_PX,
        chessboard_views,
        write_folder,
    )

    uv = np.stack(np.meshgrid(np.arange(W_PX), np.arange(H_PX)), -1).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    rays = cv2.undistortPoints(uv.reshape(-1, 1, 2), K_TRUE, DIST_TRUE, criteria=crit)
    views = write_folder(tmp_path / "views", chessboard_views(rays.reshape(H_PX, W_PX, 2), 10, 1))
    cam = tmp_path / "cam.yaml"
    assert _prep_reference(tmp_path)[2] == cam
    before = _snapshot(tmp_path)
    (tmp_path / "cam_report.json").write_text("{}\n")  # a previous run's report
    before = _snapshot(tmp_path)
    args = ["intrinsics", views, *CB_ARGS, "--out", cam]
    for name in ("cam.yaml", "cam.json", "cam_report.json", "cam_errors.png"):
        disk = FullDisk(None, fail_on=name)
        code, _, err = _run(_calibration(), args, disk)
        assert code == 2 and f"error: {tmp_path / name}: no space left on the device" in err
        assert disk.target == tmp_path / name
        assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("fail_on", ["p.onnx", "p.json"])
def test_rl_export_writes_the_onnx_and_its_json_as_one_unit(tmp_path, fail_on):
    """``rl export`` left an .onnx without its .json: now a failure of either leaves the old
    pair (or, exporting anew, neither file)."""
    policy = ROOT / "rl" / "policies" / "scratch_error_model_ppo"
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    disk = FullDisk(None, fail_on=fail_on)
    code, _, err = _run(_rl(), ["export", "--policy", policy, "--out", fresh / "p.onnx"], disk)
    assert code == 2 and f"error: {fresh / fail_on}: no space left on the device" in err, err
    assert list(fresh.iterdir()) == []
    d = tmp_path / "old"
    d.mkdir()
    args = _prep_export(d)
    before = _snapshot(d)
    disk = FullDisk(None, fail_on=fail_on)
    code, _, err = _run(_rl(), args, disk)
    assert code == 2 and disk.target == d / fail_on
    assert _snapshot(d) == before
    assert _run(_rl(), args, FullDisk(None))[0] == 0  # the same export goes through
    after = _snapshot(d)
    assert after[d / "p.onnx"] != before[d / "p.onnx"]
    assert b"scratch_error_model_ppo" in after[d / "p.json"]
