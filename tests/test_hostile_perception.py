"""Hostile input for ``markers``, ``perception`` and ``calibration``: every failure is one line
(exit status 2, ``error: ...``, no traceback) and writes nothing; damaged inputs are counted, not
silently shortened; output folders of other tools are left alone; nothing leaks on stderr.

Each test here failed on the code before the validation work (commit e7a8124~1).
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import CameraModel, save_camera
from uwdock.calibration.intrinsics import IntrinsicsConfig
from uwdock.dockcore.config import validated
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.dockcore.media import AtomicVideoWriter
from uwdock.markers import cli as markers_cli
from uwdock.markers.config import MarkerConfig
from uwdock.markers.generate import generate
from uwdock.markers.markerset import load_marker_set, marker_set_from_config, save_marker_set
from uwdock.perception import cli as perception_cli
from uwdock.perception.avi import mjpeg_avi_index
from uwdock.perception.detector import DetectorConfig
from uwdock.perception.groundtruth import QUAT_NORM_TOL, load_pose_csv
from uwdock.perception.video import FrameSource, open_frames

REPO = Path(__file__).resolve().parents[1]
CAM = CameraModel.from_hfov(64, 48, 55.0, name="tiny")
CSV_HEADER = "frame,x_m,y_m,z_m,qw,qx,qy,qz\n"


def _one_line(res) -> str:
    """The single ``error:`` line of a failed command (exit status 2, nothing on stdout)."""
    assert res.code == 2, (res.code, res.out, res.err)
    assert res.out == "" and "Traceback" not in res.err, res.err
    assert res.err.count("\n") == 1 and res.err.startswith("error: "), res.err
    return res.err.strip()


def _grey_frames(n: int, size: tuple[int, int] = (64, 48)) -> list[np.ndarray]:
    """``n`` flat BGR frames; frame k has grey level 10 k, so a decoded frame tells its index."""
    return [np.full((size[1], size[0], 3), 10 * k, np.uint8) for k in range(n)]


def _frame_number(image: np.ndarray) -> int:
    return round(float(image.mean()) / 10.0)


def _write_folder(folder: Path, frames: list[np.ndarray]) -> Path:
    folder.mkdir(parents=True)
    for k, img in enumerate(frames):
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    return folder


@pytest.fixture
def camera_file(tmp_path) -> Path:
    return save_camera(tmp_path / "cam.yaml", CAM)[0]


# --------------------------------------------------------------------------- markers


def test_generate_enclosure_nan_is_one_line_and_writes_nothing(run_cli, tmp_path):
    out = tmp_path / "m"
    msg = _one_line(run_cli(markers_cli.main, "generate", "--enclosure-mm", "nan", "--out", out))
    assert "'--enclosure-mm'" in msg and "nan" in msg
    cfg = tmp_path / "m.toml"
    cfg.write_text("enclosure_side_mm = nan\n")
    msg = _one_line(run_cli(markers_cli.main, "generate", "--config", cfg, "--out", out))
    assert msg.startswith("error: enclosure_side_mm: must be a finite number")
    with pytest.raises(ConfigError, match="enclosure_side_mm"):  # the API refuses it too
        generate(MarkerConfig(enclosure_side_mm=math.nan), out)
    assert not out.exists()


@pytest.mark.parametrize(
    "args, match",
    [
        (["--size-mm", "300"], "use a bigger --paper"),  # the sheet is checked before writing
        (["--clearance-mm", "6"], "clearance_mm: 6 mm would close the openings"),
        (["--ids", "13,13"], "ids: marker ID 13 is listed more than once"),
    ],
)
def test_generate_values_that_cannot_be_made_stop_before_writing(run_cli, tmp_path, args, match):
    out = tmp_path / "m"
    assert match in _one_line(run_cli(markers_cli.main, "generate", *args, "--out", out))
    assert not out.exists()


def _marker_set_text(**edits) -> str:
    """The default marker set as TOML, with ``edits`` applied to its data (a callable each)."""
    data = marker_set_from_config(MarkerConfig()).to_dict()
    for edit in edits.values():
        edit(data)
    return tomli_w.dumps(data)


def _set0(key, value):
    return lambda d: d["markers"][0].__setitem__(key, value)


@pytest.mark.parametrize(
    "edit, match",
    [
        (_set0("id", 13.7), "markers[0].id must be an integer, got 13.7"),
        (_set0("id", True), "markers[0].id must be an integer, got True"),
        (_set0("colour", "red"), "markers[0]: unknown key 'colour'"),
        (lambda d: d.__setitem__("author", "me"), "unknown key 'author'"),
        (lambda d: d["geometry"].__setitem__("size_inch", 4), "geometry: unknown key 'size_inch'"),
        (lambda d: d["geometry"].__setitem__("size_mm", -1.0), "geometry.size_mm must be"),
        (_set0("side_m", math.nan), "markers[0].side_m: must be a finite number"),
        (_set0("side_m", 0.0), "markers[0].side_m: must be a finite number in (0, 1]"),
        (_set0("side_m", -0.1), "markers[0].side_m: must be a finite number in (0, 1]"),
        (_set0("side_m", "0.1"), "markers[0].side_m: must be a finite number"),
        (
            lambda d: d["markers"][0]["corners_marker_m"][1].__setitem__(0, math.inf),
            "markers[0].corners_marker_m must hold finite numbers, got inf",
        ),
        (
            lambda d: d["markers"][0]["T_ds_marker"][0].__setitem__(3, math.nan),
            "markers[0].T_ds_marker must hold finite numbers, got nan",
        ),
        (
            lambda d: d["markers"][0]["T_ds_marker"][2].__setitem__(3, 5000.0),
            "markers[0].T_ds_marker: the marker lies 5000 m from the DS origin",
        ),
        (
            lambda d: d["markers"][0]["T_ds_marker"][3].__setitem__(3, True),
            "markers[0].T_ds_marker must hold finite numbers, got True",
        ),
        (_set0("render_mesh", 5), "markers[0].render_mesh must be a file name"),
        (lambda d: d.__setitem__("version", True), "unsupported version True"),
    ],
)
def test_marker_set_refuses_what_it_would_have_coerced_or_ignored(tmp_path, edit, match):
    path = tmp_path / "set.toml"
    path.write_text(_marker_set_text(e=edit))
    with pytest.raises(ConfigError, match="^invalid marker set .*: " + re.escape(match)):
        load_marker_set(path)


def test_marker_set_json_nan_and_non_utf8(tmp_path):
    data = marker_set_from_config(MarkerConfig()).to_dict()
    data["markers"][2]["side_m"] = float("nan")
    path = tmp_path / "set.json"
    path.write_text(json.dumps(data))  # Python writes the non-standard token NaN
    with pytest.raises(ConfigError, match=re.escape("markers[2].side_m: must be a finite number")):
        load_marker_set(path)
    for suffix in (".json", ".toml"):
        bad = tmp_path / f"latin1{suffix}"
        bad.write_bytes('# caf\xe9\nformat = "uwdock.markerset"\n'.encode("latin-1"))
        with pytest.raises(ConfigError, match="not UTF-8 text"):
            load_marker_set(bad)
    bom = save_marker_set(tmp_path / "bom.json", marker_set_from_config(MarkerConfig()))
    bom.write_bytes(b"\xef\xbb\xbf" + bom.read_bytes())  # a byte-order mark is fine
    assert load_marker_set(bom).ids == MarkerConfig().ids


def test_missing_or_non_utf8_markers_config_and_camera_files_are_one_line(
    run_cli, tmp_path, camera_file
):
    folder = _write_folder(tmp_path / "frames", _grey_frames(2))
    out = tmp_path / "o"
    detect = ["detect", folder, "--out", out]
    msg = _one_line(run_cli(perception_cli.main, *detect, "--markers", tmp_path / "nope.toml"))
    assert "marker set file not found" in msg
    latin = tmp_path / "latin1.toml"
    latin.write_bytes("# r\xe9glages\n".encode("latin-1"))
    for args in (["--markers", latin], ["--config", latin]):
        assert "not UTF-8" in _one_line(run_cli(perception_cli.main, *detect, *args))
    assert "not UTF-8" in _one_line(
        run_cli(markers_cli.main, "generate", "--config", latin, "--out", out)
    )
    assert "not UTF-8" in _one_line(
        run_cli(calibration_cli.main, "intrinsics", folder, "--config", latin)
    )
    for suffix in (".yaml", ".json"):
        cam = tmp_path / f"latin1{suffix}"
        text = camera_file.with_suffix(suffix).read_text().replace("tiny", "cam\xe9ra")
        cam.write_bytes(text.encode("latin-1"))
        msg = _one_line(run_cli(perception_cli.main, *detect, "--camera", cam))
        assert f"camera file {cam} is not UTF-8 text" in msg
        msg = _one_line(run_cli(calibration_cli.main, "extrinsics", "show", cam))
        assert "not UTF-8 text" in msg
    assert not out.exists()


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("camera_matrix", [[1e300, 0, 31.5], [0, 1e300, 23.5], [0, 0, 1]], "fx_px: must be within"),
        ("distortion_coefficients", [1e300, 0, 0, 0, 0], "dist: must be finite and within"),
        ("image_width", 10**9, "width_px: must be an integer in [1, 100000]"),
    ],
)
def test_camera_values_that_overflow_are_refused(run_cli, tmp_path, camera_file, key, value, match):
    """A focal length of 1e300 px was accepted and overflowed in the pose solver."""
    cam = camera_file.with_suffix(".json")
    cam.write_text(json.dumps({**json.loads(cam.read_text()), key: value}))
    folder = _write_folder(tmp_path / "frames", _grey_frames(2))
    out = tmp_path / "o"
    msg = _one_line(run_cli(perception_cli.main, "detect", folder, "--camera", cam, "--out", out))
    assert f"{cam}: {match}" in msg and not out.exists()


# --------------------------------------------------------------------------- ground truth


def test_pose_csv_quaternion_must_be_unit(tmp_path):
    """A quaternion off unit length is refused (normalising it turned a 3 deg rotation error
    into 17 deg); one rounded to 3-6 decimals is accepted."""
    rng = np.random.default_rng(1)
    rows = []
    for k in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        decimals = 3 + k % 4
        rows.append(f"{k},0.1,0.2,2.0," + ",".join(f"{v:.{decimals}f}" for v in q))
    good = tmp_path / "good.csv"
    good.write_text(CSV_HEADER + "\n".join(rows) + "\n")
    assert len(load_pose_csv(good)) == 200
    for q, why in [
        ("0.99966,0.02618,0,0.1", "norm 1.00499"),  # a 3 deg turn about x, qz mistyped
        ("0.95,0,0,0", "norm 0.95"),
        ("0,0,0,0", "norm 0"),
        (f"{1 + 2 * QUAT_NORM_TOL},0,0,0", "norm 1.002"),
    ]:
        bad = tmp_path / "bad.csv"
        bad.write_text(CSV_HEADER + "0,0,0,2,1,0,0,0\n" + f"1,0,0,2,{q}\n")
        with pytest.raises(DockError, match=rf"bad.csv line 3: quaternion .* {why},"):
            load_pose_csv(bad)
    for value in ("nan", "inf", "-inf"):
        bad.write_text(CSV_HEADER + f"0,0,0,2,{value},0,0,0\n")
        with pytest.raises(DockError, match="line 2: column 'qw' is not finite"):
            load_pose_csv(bad)


def test_eval_refuses_a_non_unit_quaternion_with_one_line(run_cli, tmp_path, camera_file):
    folder = _write_folder(tmp_path / "frames", _grey_frames(2))
    gt = tmp_path / "mocap.csv"
    gt.write_text(CSV_HEADER + "0,0,0,2,1,0,0,0\n1,0,0,2,0.9986,0.0523,0,0.1\n")
    out = tmp_path / "o"
    msg = _one_line(
        run_cli(
            perception_cli.main,
            *("eval", folder, "--camera", camera_file, "--ground-truth", gt, "--out", out),
        )
    )
    assert "mocap.csv line 3: quaternion" in msg and "not 1" in msg
    assert not out.exists()


def test_pose_csv_with_a_byte_order_mark_or_latin1(tmp_path):
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + (CSV_HEADER + "0,0,0,2,1,0,0,0\n").encode())
    assert list(load_pose_csv(bom)) == [0]
    latin = tmp_path / "latin.csv"
    latin.write_bytes((CSV_HEADER + "0,0,0,2,1,0,0,0,caf\xe9\n").encode("latin-1"))
    with pytest.raises(DockError, match=r"latin\.csv is not UTF-8 text \(byte \d+: 0xe9\)"):
        load_pose_csv(latin)


# --------------------------------------------------------------------------- video frames


def _mjpg_avi(path: Path, frames: list[np.ndarray]) -> list[tuple[int, int]]:
    """Write an MJPG AVI; return (offset, size) of each frame's JPEG in the file."""
    with AtomicVideoWriter(path, fps=5.0) as video:
        for img in frames:
            video.write(img)
    data = path.read_bytes()
    chunks = []
    start = data.index(b"movi")
    while (k := data.find(b"00dc", start)) >= 0:
        size = struct.unpack("<I", data[k + 4 : k + 8])[0]
        if data[k + 8 : k + 10] == b"\xff\xd8":  # a JPEG frame (not the index entry)
            chunks.append((k + 8, size))
        start = k + 4
    assert len(chunks) == len(frames)
    return chunks


def _damage(path: Path, chunks, data: tuple[int, ...] = (), headers: tuple[int, ...] = ()) -> None:
    """Zero the JPEG data after its first 100 bytes of the frames in ``data``, and the chunk
    header ('00dc' and size) of the frames in ``headers``; the AVI index stays intact."""
    raw = bytearray(path.read_bytes())
    for k in data:
        offset, size = chunks[k]
        raw[offset + 100 : offset + size] = bytes(size - 100)
    for k in headers:
        offset, _ = chunks[k]
        raw[offset - 8 : offset] = bytes(8)
    path.write_bytes(bytes(raw))


def _numbers(source) -> list[tuple[int, int | None]]:
    return [(k, None if img is None else _frame_number(img)) for k, _, img in source]


def test_damaged_avi_frames_are_corrupt_at_their_own_index(tmp_path):
    """A damaged chunk header made FFmpeg resynchronise on the next frame: the frame vanished
    and every later frame moved up one index, with "0 corrupt"."""
    video = tmp_path / "dive.avi"
    chunks = _mjpg_avi(video, _grey_frames(20))
    _damage(video, chunks, data=(3, 4, 12), headers=(7, 12))
    source = open_frames(video)
    seen = _numbers(source)
    assert [k for k, n in seen if n is None] == [3, 4, 12]  # frame 7 (header only) decodes
    assert all(n == k for k, n in seen if n is not None), seen  # every frame at its own index
    assert len(seen) == 20 and source.corrupt == 3 and source.warnings == []


def test_detect_reports_damaged_video_frames_as_corrupt(run_cli, tmp_path, camera_file):
    video = tmp_path / "dive.avi"
    chunks = _mjpg_avi(video, _grey_frames(20))
    _damage(video, chunks, data=(12,), headers=(7, 12))
    out = tmp_path / "det"
    res = run_cli(perception_cli.main, "detect", video, "--camera", camera_file, "--out", out)
    assert res.code == 0, res.err
    assert "19 decoded, 1 corrupt" in res.out
    rows = [json.loads(line) for line in (out / "detections.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in rows] == list(range(20))
    assert [r["corrupt"] for r in rows] == [k == 12 for k in range(20)]


def test_only_indexed_motion_jpeg_avis_are_read_through_their_index(tmp_path):
    video = tmp_path / "dive.avi"
    chunks = _mjpg_avi(video, _grey_frames(5))
    index = mjpeg_avi_index(video)
    assert index is not None and (index.width_px, index.height_px, index.fps) == (64, 48, 5.0)
    assert [off + 8 for off, _ in index.frames] == [off for off, _ in chunks]
    mp4 = tmp_path / "dive.mp4"
    with AtomicVideoWriter(mp4, fps=5.0) as writer:
        writer.write(_grey_frames(1)[0])
    cut = tmp_path / "cut.avi"
    cut.write_bytes(video.read_bytes()[: chunks[3][0]])  # no index at the end
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"RIFF\xff\xff\xff\xffAVI LIST" + bytes(100))
    for path in (mp4, cut, junk, tmp_path / "missing.avi"):
        assert mjpeg_avi_index(path) is None  # left to cv2.VideoCapture


class _ScriptedCapture:
    """A ``cv2.VideoCapture`` stand-in replaying ``(ok, frame number, timestamp ms)`` reads."""

    def __init__(self, reads: list[tuple[bool, int, float]]) -> None:
        self.reads, self.t_ms = list(reads), 0.0

    def read(self):
        if not self.reads:
            return False, None
        ok, k, self.t_ms = self.reads.pop(0)
        return (True, _grey_frames(k + 1)[k]) if ok else (False, None)

    def get(self, prop: int) -> float:
        assert prop == cv2.CAP_PROP_POS_MSEC
        return self.t_ms

    def release(self) -> None:
        self.reads = []


def _scripted(tmp_path, reads, total=10) -> tuple[list, FrameSource]:
    """What a FrameSource yields for scripted reads after a first frame 0 at 0 ms (5 Hz)."""
    source = FrameSource(
        tmp_path / "v.mp4",
        "video",
        total,
        5.0,
        _cap=_ScriptedCapture(reads),
        _first=_grey_frames(1)[0],
    )
    return _numbers(source), source


def test_timestamps_place_video_frames_the_decoder_skipped(tmp_path):
    """Through cv2.VideoCapture (any container): frame 3 fails, frame 4 is skipped without a
    failed read, frame 9 never comes; the timestamps (5 Hz) put every frame at its index."""
    ok = [(True, k, 200.0 * k) for k in range(10)]
    seen, source = _scripted(tmp_path, [*ok[1:3], (False, 3, 0.0), *ok[5:9]])
    assert seen == [(0, 0), (1, 1), (2, 2), (3, None), (4, None)] + [
        (k, k) for k in (5, 6, 7, 8)
    ] + [(9, None)]
    assert source.corrupt == 3 and "the container lists 10 frames" in source.warnings[0]
    # a failure before the timestamps could be checked: they are checked on the next pair
    seen, _ = _scripted(tmp_path, [(False, 1, 0.0), *ok[2:4], *ok[6:10]])
    assert seen == [(0, 0), (1, None), (2, 2), (3, 3), (4, None), (5, None)] + [
        (k, k) for k in (6, 7, 8, 9)
    ]
    # timestamps that do not step by one frame interval are not used (decode order)
    seen, _ = _scripted(tmp_path, [(True, k, 500.0 * k) for k in range(1, 10)])
    assert seen == [(k, k) for k in range(10)]


def test_a_corrupt_first_frame_or_a_truncated_video_is_counted(run_cli, tmp_path):
    video = tmp_path / "first.avi"
    chunks = _mjpg_avi(video, _grey_frames(10))
    _damage(video, chunks, data=(0,))
    assert _numbers(open_frames(video)) == [(0, None)] + [(k, k) for k in range(1, 10)]
    cut = tmp_path / "cut.avi"  # the recorder died: the end of the file (and the index) is lost
    chunks = _mjpg_avi(cut, _grey_frames(10))
    cut.write_bytes(cut.read_bytes()[: chunks[6][0] + 50])
    res = run_cli(perception_cli.main, "detect", cut, "--out", tmp_path / "o", "--no-annotate")
    assert res.code == 0, res.err
    assert "corrupt" in res.out and "0 corrupt" not in res.out
    assert "the container lists 10 frames" in res.err


def test_a_one_pixel_image_in_a_folder_is_skipped_and_counted(run_cli, tmp_path, camera_file):
    folder = _write_folder(tmp_path / "frames", _grey_frames(3))
    cv2.imwrite(str(folder / "001b.png"), np.zeros((1, 1, 3), np.uint8))
    out = tmp_path / "o"
    res = run_cli(perception_cli.main, "detect", folder, "--camera", camera_file, "--out", out)
    assert res.code == 0, res.err
    assert "3 decoded, 1 corrupt" in res.out and "001b.png (1x1 px)" in res.err
    res = run_cli(
        perception_cli.main, "eval", folder, "--camera", camera_file, "--out", tmp_path / "e"
    )
    assert res.code == 0, res.err
    report = json.loads((tmp_path / "e" / "report.json").read_text())
    assert report["frames"] == 3 and report["corrupt_frames"] == 1


# --------------------------------------------------------------------------- output folders


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def test_another_tools_output_folder_is_refused_and_left_as_it_was(run_cli, tmp_path, camera_file):
    frames = _write_folder(tmp_path / "frames", _grey_frames(2))
    markers = tmp_path / "markers"
    assert run_cli(markers_cli.main, "generate", "--ids", "1", "--out", markers).code == 0
    detected = tmp_path / "det"
    res = run_cli(perception_cli.main, "detect", frames, "--camera", camera_file, "--out", detected)
    assert res.code == 0, res.err
    for folder, args in [
        (markers, [perception_cli.main, "eval", frames, "--camera", camera_file]),
        (markers, [perception_cli.main, "detect", frames, "--camera", camera_file]),
        (detected, [perception_cli.main, "eval", frames, "--camera", camera_file]),
        (detected, [markers_cli.main, "generate", "--ids", "1"]),
    ]:
        before = _snapshot(folder)
        msg = _one_line(run_cli(*args, "--out", folder))
        assert f"{folder} holds the output of `" in msg and "use another --out" in msg
        assert _snapshot(folder) == before  # config.toml, provenance.json untouched
    again = run_cli(
        perception_cli.main, "detect", frames, "--camera", camera_file, "--out", detected
    )
    assert again.code == 0, again.err  # the same tool may write its folder again


def test_stale_temp_files_of_a_killed_run_are_removed(run_cli, tmp_path, camera_file):
    frames = _write_folder(tmp_path / "frames", _grey_frames(2))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "det"
    out.mkdir()
    stale = [
        out / f".detections.jsonl.{dead.pid}.k3x9q1.uwtmp",
        out / f".annotated.mp4.{dead.pid}.a7b2c4.uwtmp.mp4",
        out / "annotated" / f".000.png.{dead.pid}.z0z0z0.uwtmp",
    ]
    live = out / f".detections.csv.{os.getppid()}.l1v3l1.uwtmp"  # a running process's: kept
    for path in [*stale, live]:
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(b"half a file")
    res = run_cli(perception_cli.main, "detect", frames, "--camera", camera_file, "--out", out)
    assert res.code == 0, res.err
    assert not any(p.exists() for p in stale) and live.exists()


def test_a_failed_run_leaves_no_folder_behind(run_cli, tmp_path, camera_file):
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "a.png").write_bytes(b"not a png")
    out = tmp_path / "new" / "o"
    msg = _one_line(
        run_cli(perception_cli.main, "eval", frames, "--camera", camera_file, "--out", out)
    )
    assert "no decodable frame" in msg
    assert not (tmp_path / "new").exists()


# --------------------------------------------------------------------------- stderr


def _run_quietly(group: str, *args: object) -> subprocess.CompletedProcess:
    """A command in a fresh process (native libraries log to file descriptor 2 there)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_FFMPEG_")}
    code = f"import sys; from uwdock.{group}.cli import main; sys.argv[0] = {group!r}; main()"
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.slow  # ~23 s on 2 cores: in the slow set (CI runs it)
def test_native_warnings_do_not_leak_to_stderr(tmp_path, camera_file):
    """FFmpeg's decoder errors on a damaged video and OpenCV's warnings (axes drawn off the
    image, a thin ChArUco border) stay off stderr: what is wrong is reported as corrupt
    frames or a note."""
    from tests.test_perception_cli import CAM as SCENE_CAM
    from tests.test_perception_cli import look_at, render_board

    rng = np.random.default_rng(0)
    video = tmp_path / "dive.mp4"
    with AtomicVideoWriter(video, fps=5.0) as writer:
        for k in range(30):
            writer.write(np.random.default_rng(k).integers(0, 255, (120, 160, 3), np.uint8))
    data = bytearray(video.read_bytes())
    data[len(data) // 3 : len(data) // 3 + 5000] = bytes(5000)
    video.write_bytes(bytes(data))
    frame = tmp_path / "board.png"
    cv2.imwrite(str(frame), render_board(look_at(1.6, 8.0, 30.0, 90.0), rng))
    scene_cam = save_camera(tmp_path / "scene.yaml", SCENE_CAM)[0]
    long_axes = tmp_path / "axes.toml"
    long_axes.write_text("[report]\naxis_length_m = 50.0\n")
    charuco = tmp_path / "charuco"
    charuco.mkdir()
    for k in range(2):
        cv2.imwrite(str(charuco / f"{k}.png"), np.full((48, 64), 128, np.uint8))
    runs = [
        _run_quietly("perception", "detect", video, "--out", tmp_path / "v", "--quiet"),
        _run_quietly("calibration", "intrinsics", video, "--out", tmp_path / "c.yaml"),
        _run_quietly(
            "perception",
            *("detect", frame, "--camera", scene_cam, "--config", long_axes),
            *("--out", tmp_path / "a", "--quiet"),
        ),
        _run_quietly(
            "calibration",
            *("intrinsics", charuco, "--pattern", "charuco", "--cols", 5, "--rows", 4),
            *("--square-mm", 20, "--marker-mm", 19, "--out", tmp_path / "ch.yaml"),
        ),
    ]
    for run in runs:
        lines = run.stderr.splitlines()
        leaked = [ln for ln in lines if not ln.startswith(("error: ", "note: ", "warning: "))]
        assert not leaked, (run.args[3:], run.stderr[:2000])
    assert runs[0].returncode == 0 and runs[2].returncode == 0, (runs[0].stderr, runs[2].stderr)
    assert "white border" in runs[3].stderr  # said once, in words, instead of OpenCV's warning


# --------------------------------------------------------------------------- config values


def test_values_inside_old_checks_that_crashed_or_hung_are_refused(run_cli, tmp_path):
    folder = _write_folder(tmp_path / "frames", _grey_frames(4, (640, 480)))
    msg = _one_line(run_cli(calibration_cli.main, "intrinsics", folder, "--cols", "2"))
    assert "'--cols': must be an integer in [3, 100], got 2" in msg  # OpenCV needs > 2
    cfg = tmp_path / "p.toml"
    cfg.write_text("[board]\nsigma_floor_px = 1e300\n")  # overflowed in the covariance
    msg = _one_line(run_cli(perception_cli.main, "detect", folder, "--config", cfg))
    assert "board.sigma_floor_px: must be a finite number in [0, 100], got 1e+300" in msg
    with pytest.raises(ConfigError, match="997 threshold windows"):  # 997 passes per frame
        validated(DetectorConfig(adaptive_thresh_win_sizes_px=(3, 999, 1)))
    with pytest.raises(ConfigError, match=r"^marker_mm: must be smaller than square_mm"):
        validated(IntrinsicsConfig(pattern="charuco", square_mm=20.0, marker_mm=30.0))


def test_a_distant_ground_truth_frame_does_not_make_a_million_bins(run_cli, tmp_path, camera_file):
    folder = _write_folder(tmp_path / "frames", _grey_frames(3))
    gt = tmp_path / "gt.csv"
    gt.write_text(CSV_HEADER + "0,0,0,1.5,1,0,0,0\n1,0,0,2.2,1,0,0,0\n2,0,0,1e5,1,0,0,0\n")
    out = tmp_path / "o"
    res = run_cli(
        perception_cli.main,
        *("eval", folder, "--camera", camera_file, "--ground-truth", gt, "--out", out),
    )
    assert res.code == 0, res.err
    report = json.loads((out / "report.json").read_text())
    assert [(b["lo"], b["frames"]) for b in report["by_range"]] == [
        (1.5, 1),
        (2.0, 1),
        (100000.0, 1),
    ]
