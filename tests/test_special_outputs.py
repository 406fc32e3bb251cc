"""Writes that respect what is there (issue 54): an output that exists and is not a regular file
(a character device, a FIFO, a socket, a symlink loop) is refused in one line with exit status
2, before any work, and left as it was: same kind, same inode, same device numbers, no sibling
(``x.json``) and no temporary file created. The atomic writers refuse such a node themselves,
when they start and again right before the rename (a node can appear meanwhile).

Every special file here is made in the test's own folder (``os.mknod`` of a 1:3 character
device and of a block device node, ``os.mkfifo``, a bound socket, a pair of links pointing at
each other): never a real system path, and nothing opens them.
"""

from __future__ import annotations

import os
import socket
import stat
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from uwdock.dockcore.cli import run_group
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import (
    TEMP_MARK,
    atomic_path,
    atomic_write_bytes,
    atomic_write_files,
    check_output_dir,
    check_output_path,
    output_target,
)

ROOT = Path(__file__).resolve().parent.parent
KINDS = {  # what is made -> the words the refusal names it by
    "chr": "character device",
    "fifo": "FIFO",
    "socket": "socket",
    "loop": "symlink loop",
    "blk": "block device",
}


def make_node(path: Path, kind: str) -> Path:
    """A special file of ``kind`` at ``path`` (its folder exists)."""
    if kind == "chr":
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    elif kind == "blk":  # a node only: nothing here opens it
        os.mknod(path, stat.S_IFBLK | 0o600, os.makedev(7, 250))
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "socket":
        # bound by its name from inside its folder: a socket's path is limited to ~107 bytes
        cwd = os.getcwd()
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            os.chdir(path.parent)
            s.bind(path.name)
        finally:
            os.chdir(cwd)
            s.close()
    elif kind == "loop":
        other = path.with_name(path.name + ".loop")
        os.symlink(other.name, path)
        os.symlink(path.name, other)
    else:
        raise ValueError(kind)
    return path


def identity(path: Path) -> tuple[int, int, int]:
    """(file type, inode, device numbers) of the node itself (``lstat``)."""
    st = os.lstat(path)
    return stat.S_IFMT(st.st_mode), st.st_ino, st.st_rdev


def listing(folder: Path) -> dict[str, tuple[int, int, int]]:
    return {p.name: identity(p) for p in folder.iterdir()}


def _invoke(group: str, args: list) -> tuple[int, str, str]:
    """Run a command group in-process: (exit status, stdout, stderr)."""
    import contextlib
    import importlib
    import io

    module = importlib.import_module(f"uwdock.{group}.cli")
    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = [group.split(".")[0]]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                run_group(module.cli, [str(a) for a in args])
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = argv
    return code, out.getvalue(), err.getvalue()


# ---------------------------------------------------------------------------- the commands


@dataclass(frozen=True)
class Case:
    """A command that writes ``--out``: its group, its arguments (``OUT`` stands for the
    output) given the folder of inputs, and the output's name (a file, or a folder)."""

    group: str
    args: Callable[[Path], list]
    out_name: str


OUT = object()
POLICY = ROOT / "rl" / "policies" / "error_model_ppo"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Small valid inputs: a camera file, a ROS camera_info, three frames."""
    import cv2

    from uwdock.calibration.camera import reference_camera, save_camera
    from uwdock.calibration.formats_export import ros_camera_info_yaml

    d = tmp_path_factory.mktemp("inputs")
    save_camera(d / "cam.yaml", reference_camera().scaled(64, 48))
    (d / "ost.yaml").write_text(ros_camera_info_yaml(reference_camera().scaled(640, 484)))
    frames = d / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        cv2.imwrite(str(frames / f"{k}.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    for name in ("left", "right", "dataset"):
        (d / name).mkdir()
    return d


EVAL_SIZE = ["--marker-size-m", 0.1]
CB = ["--pattern", "chessboard", "--cols", 9, "--rows", 6, "--square-mm", 25]
CASES = {
    # one file (and the files written with it)
    "calibration reference-camera": Case(
        "calibration", lambda i: ["reference-camera", "--out", OUT], "x.yaml"
    ),
    "calibration export": Case(
        "calibration",
        lambda i: ["export", i / "cam.yaml", "--format", "ros", "--out", OUT],
        "x.yaml",
    ),
    "calibration import": Case(
        "calibration", lambda i: ["import", i / "ost.yaml", "--out", OUT], "x.yaml"
    ),
    "calibration intrinsics": Case(
        "calibration", lambda i: ["intrinsics", i / "frames", *CB, "--out", OUT], "x.yaml"
    ),
    "calibration stereo": Case(
        "calibration",
        lambda i: ["stereo", i / "left", i / "right", "--cols", 9, "--rows", 6, "--out", OUT],
        "x.yaml",
    ),
    "calibration extrinsics set": Case(
        "calibration",
        lambda i: ["extrinsics", "set", OUT, "--xyz-m", 0, 0, 0, "--rpy-deg", 0, 0, 0],
        "x.yaml",
    ),
    "rl export": Case("rl", lambda i: ["export", "--policy", POLICY, "--out", OUT], "x.onnx"),
    "rl fit-error-model": Case(
        "rl", lambda i: ["fit-error-model", i / "dataset", "--out", OUT], "x.json"
    ),
    # a folder
    "markers generate": Case("markers", lambda i: ["generate", "--ids", 13, "--out", OUT], "o"),
    "perception detect": Case(
        "perception",
        lambda i: ["detect", i / "frames", "--camera", i / "cam.yaml", "--out", OUT],
        "o",
    ),
    "perception eval": Case(
        "perception",
        lambda i: ["eval", i / "frames", "--camera", i / "cam.yaml", *EVAL_SIZE, "--out", OUT],
        "o",
    ),
    "datasets synth": Case("datasets", lambda i: ["synth", "--n", 1, "--out", OUT], "o"),
    "datasets render": Case("datasets", lambda i: ["render", "--out", OUT], "o"),
    "datasets tank-report": Case("datasets", lambda i: ["tank-report", "--out", OUT], "o"),
    "datasets fit-water": Case(
        "datasets",
        lambda i: ["fit-water", i / "frames", "--camera", i / "cam.yaml", "--out", OUT],
        "o",
    ),
    "rl train": Case("rl", lambda i: ["train", "--steps", 64, "--out", OUT], "o"),
    "rl sweep": Case("rl", lambda i: ["sweep", "--out", OUT], "o"),
    "rl eval": Case(
        "rl", lambda i: ["eval", "--policy", "pid", "--episodes", 1, "--out", OUT], "o"
    ),
    "rl episode": Case("rl", lambda i: ["episode", "--out", OUT], "o"),
    "rl trajectories": Case("rl", lambda i: ["trajectories", "--episodes", 1, "--out", OUT], "o"),
    "rl replay": Case("rl.deploy", lambda i: ["replay", i / "none.mcap", "--out", OUT], "o"),
    "sim vehicle": Case("rl.deploy", lambda i: ["vehicle", "--out", OUT], "o"),
}


def _args(case: Case, inputs: Path, out: Path) -> list:
    return [out if a is OUT else a for a in case.args(inputs)]


def assert_refused(
    code: int, out: str, err: str, path: Path, words: str, notes: bool = False
) -> str:
    """Exit 2 and one ``error:`` line naming ``path`` and ``words`` (the only line on stderr,
    unless ``notes``: then the last, after the run's notes); the line."""
    assert code == 2, (code, out, err)
    lines = err.splitlines()
    assert lines and (notes or len(lines) == 1), err
    line = lines[-1]
    assert line.startswith("error: ") and [s for s in lines if s.startswith("error")] == [line]
    assert "internal error" not in err and "Traceback" not in err, err
    assert str(path) in line and words in line, err
    return line


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("name", list(CASES))
def test_an_output_that_is_a_special_file_is_refused_and_kept(name, kind, inputs, tmp_path):
    case = CASES[name]
    work = tmp_path / "w"
    work.mkdir()
    node = make_node(work / case.out_name, kind)
    before = listing(work)
    code, out, err = _invoke(case.group, _args(case, inputs, node))
    assert_refused(code, out, err, node, KINDS[kind])
    assert listing(work) == before  # the node as it was, no x.json, no temporary file


SIDECARS = {  # a command, its --out (a regular file) and a file written with it
    "calibration reference-camera": ("x.yaml", "x.json"),
    "calibration import": ("x.yaml", "x.json"),
    "calibration intrinsics": ("x.yaml", "x_report.json"),
    "calibration stereo": ("x.yaml", "x_left.json"),
    "rl export": ("x.onnx", "x.json"),
}


@pytest.mark.parametrize("kind", ["chr", "fifo"])
@pytest.mark.parametrize("name", list(SIDECARS))
def test_a_sidecar_that_is_a_special_file_refuses_the_run(name, kind, inputs, tmp_path):
    """``--out x.yaml`` (a regular file) whose twin ``x.json`` is a device: refused before any
    work, both left as they were."""
    case = CASES[name]
    out_name, sidecar = SIDECARS[name]
    work = tmp_path / "w"
    work.mkdir()
    out_file = work / out_name
    out_file.write_bytes(b"old")
    node = make_node(work / sidecar, kind)
    before = listing(work)
    code, out, err = _invoke(case.group, _args(case, inputs, out_file))
    assert_refused(code, out, err, node, KINDS[kind])
    assert listing(work) == before and out_file.read_bytes() == b"old"


def test_other_output_options_are_checked(inputs, tmp_path):
    """``calibration export --right-out``, ``calibration import --stereo-out``."""
    node = make_node(tmp_path / "r.yaml", "fifo")
    args = ["export", inputs / "cam.yaml", "--format", "ros", "--out", tmp_path / "l.yaml"]
    code, out, err = _invoke("calibration", [*args, "--right-out", node])
    assert_refused(code, out, err, node, "FIFO")
    assert "--right-out" in err
    args = ["import", inputs / "ost.yaml", "--out", tmp_path / "c.yaml"]
    code, out, err = _invoke("calibration", [*args, "--stereo-out", node])
    assert_refused(code, out, err, node, "FIFO")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.yaml"]


def test_a_symlink_to_a_regular_file_is_followed(tmp_path):
    """``--out link.yaml`` -> ``real.yaml``: the file it leads to is written, the link kept."""
    real = tmp_path / "real.yaml"
    real.write_text("old")
    link = tmp_path / "link.yaml"
    link.symlink_to(real.name)
    code, _, err = _invoke("calibration", ["reference-camera", "--out", link, "--width", 64])
    assert code == 0, err
    assert link.is_symlink() and os.readlink(link) == "real.yaml"
    assert real.read_text().startswith("%YAML") and (tmp_path / "link.json").is_file()
    assert not [p for p in tmp_path.iterdir() if TEMP_MARK in p.name]


def test_a_dangling_symlink_and_a_loop_above_are_refused(tmp_path):
    dangling = tmp_path / "d.yaml"
    dangling.symlink_to("nowhere/x.yaml")
    code, out, err = _invoke("calibration", ["reference-camera", "--out", dangling])
    assert_refused(code, out, err, dangling, "dangling symlink")
    loop = make_node(tmp_path / "l", "loop")
    inside = loop / "x.yaml"
    code, out, err = _invoke("calibration", ["reference-camera", "--out", inside])
    assert_refused(code, out, err, inside, "symlink loop")
    code, out, err = _invoke("markers", ["generate", "--ids", 13, "--out", loop / "m"])
    assert_refused(code, out, err, loop / "m", "symlink loop")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.yaml", "l", "l.loop"]


def test_a_special_file_inside_an_output_folder_is_refused_at_the_write(inputs, tmp_path):
    """``perception eval --out DIR`` where ``DIR/report.json`` is a FIFO: the run stops with
    one line when it comes to write it, and the FIFO is left as it was."""
    folder = tmp_path / "e"
    folder.mkdir()
    node = make_node(folder / "report.json", "fifo")
    ident = identity(node)
    args = ["eval", inputs / "frames", "--camera", inputs / "cam.yaml", "--marker-size-m", 0.1,
            "--out", folder]  # fmt: skip
    code, out, err = _invoke("perception", args)
    assert_refused(code, out, err, node, "FIFO", notes=True)
    assert identity(node) == ident
    assert not [p for p in folder.rglob("*") if TEMP_MARK in p.name]


# ----------------------------------------------------------------- the atomic writers themselves


@pytest.mark.parametrize("kind", list(KINDS))
def test_every_atomic_writer_refuses_a_special_target(kind, tmp_path):
    node = make_node(tmp_path / "t", kind)
    before = listing(tmp_path)
    with pytest.raises(DockError, match=KINDS[kind]):
        atomic_write_bytes(node, b"x")
    with pytest.raises(DockError, match=KINDS[kind]):
        with atomic_path(node) as tmp:
            tmp.write_bytes(b"x")
    regular = tmp_path / "a.onnx"
    with pytest.raises(DockError, match=KINDS[kind]):  # the unit: nothing written
        atomic_write_files({regular: b"a", node: b"b"})
    with pytest.raises(DockError, match=KINDS[kind]):
        output_target(node)
    with pytest.raises(DockError, match=KINDS[kind]):
        check_output_path(tmp_path / "ok.yaml", "--out", [node])
    with pytest.raises(DockError, match=KINDS[kind]):
        check_output_dir(node)
    assert listing(tmp_path) == before


def test_a_folder_is_refused_where_a_file_is_expected(tmp_path):
    with pytest.raises(DockError, match="is a folder, not a file"):
        atomic_write_bytes(tmp_path, b"x")
    assert list(tmp_path.iterdir()) == []


def test_a_node_that_appears_before_the_rename_is_kept(tmp_path, monkeypatch):
    """A FIFO made at the target while the file is being written (after the first check):
    the second check, right before the rename, refuses it."""
    from uwdock.dockcore import io as dio

    target = tmp_path / "cam.yaml"
    real_sync = dio._sync

    def sync_then_fifo(path):
        size = real_sync(path)
        if not target.exists():
            os.mkfifo(target)
        return size

    monkeypatch.setattr(dio, "_sync", sync_then_fifo)
    with pytest.raises(DockError, match="FIFO"):
        atomic_write_bytes(target, b"new")
    assert stat.S_ISFIFO(os.lstat(target).st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["cam.yaml"]


def test_a_unit_stops_before_its_first_rename_when_a_node_appears(tmp_path, monkeypatch):
    """``atomic_write_files``: the second target becomes a device while the temporary files are
    written; the first file keeps its old bytes (no rename has happened)."""
    from uwdock.dockcore import io as dio

    a, b = tmp_path / "p.onnx", tmp_path / "p.json"
    a.write_bytes(b"old onnx")
    real_sync = dio._sync
    calls = []

    def sync(path):
        calls.append(path)
        if len(calls) == 2:
            os.mknod(b, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        return real_sync(path)

    monkeypatch.setattr(dio, "_sync", sync)
    with pytest.raises(DockError, match="character device"):
        atomic_write_files({a: b"new onnx", b: b"new json"})
    assert a.read_bytes() == b"old onnx" and stat.S_ISCHR(os.lstat(b).st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.json", "p.onnx"]


def test_a_unit_puts_the_old_files_back_when_a_late_check_refuses(tmp_path, monkeypatch):
    """The node appears between the first and the second rename: the first file gets its old
    bytes back."""
    from uwdock.dockcore import io as dio

    a, b = tmp_path / "c.yaml", tmp_path / "c.json"
    a.write_bytes(b"old yaml")
    real_replace = dio.replace_checked

    def replace(tmp, target):
        real_replace(tmp, target)
        if Path(target) == a:
            os.mkfifo(b)

    monkeypatch.setattr(dio, "replace_checked", replace)
    with pytest.raises(DockError, match="FIFO"):
        atomic_write_files({a: b"new yaml", b: b"new json"})
    assert a.read_bytes() == b"old yaml" and stat.S_ISFIFO(os.lstat(b).st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json", "c.yaml"]


def test_the_video_and_recording_writers_refuse_special_files(tmp_path):
    from uwdock.dockcore.media import AtomicVideoWriter

    node = make_node(tmp_path / "v.mp4", "fifo")
    with pytest.raises(DockError, match="FIFO"):
        AtomicVideoWriter(node, 10.0)
    loop = make_node(tmp_path / "r.mcap", "loop")
    pytest.importorskip("mcap")
    from uwdock.ros.mcap import McapRecorder

    with pytest.raises(DockError, match="symlink loop"):
        McapRecorder(loop)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.mcap", "r.mcap.loop", "v.mp4"]


def test_a_file_where_a_folder_should_be_is_one_line(tmp_path):
    """A file where a folder of the path should be: the system's reason naming the path (one
    line, exit 2), not an internal error."""
    f = tmp_path / "f"
    f.write_text("")
    with pytest.raises(NotADirectoryError) as exc:
        output_target(f / "x.yaml")
    assert exc.value.filename == str(f / "x.yaml")
    with pytest.raises(DockError, match="cannot write to output folder"):
        check_output_dir(f / "sub")
    code, out, err = _invoke("calibration", ["reference-camera", "--out", f / "x.yaml"])
    assert_refused(code, out, err, f / "x.yaml", "Not a directory")
    code, out, err = _invoke("markers", ["generate", "--ids", 13, "--out", f / "sub"])
    assert_refused(code, out, err, f / "sub", "cannot write to output folder")
    assert [p.name for p in tmp_path.iterdir()] == ["f"]


def test_rl_export_refuses_an_out_that_is_its_own_sidecar(tmp_path):
    """``rl export --out p.json``: the ONNX and its .json would be one file (the ONNX lost)."""
    out = tmp_path / "p.json"
    code, o, err = _invoke("rl", ["export", "--policy", POLICY, "--out", out])
    assert_refused(code, o, err, out, "must not end in .json")
    assert list(tmp_path.iterdir()) == []
