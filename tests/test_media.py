"""dockcore.media: the atomic video writer and the native-stderr silencer."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import AtomicVideoWriter, open_video, quiet_native_stderr
from uwdock.perception.video import AnnotatedVideoWriter

W_PX, H_PX = 96, 64
GREYS = (20, 60, 100, 140, 180, 220, 250)  # one flat grey level per frame


def _frame(level: int, w: int = W_PX, h: int = H_PX) -> np.ndarray:
    return np.full((h, w, 3), level, np.uint8)


def _read_back(path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    ok, frame = cap.read()
    while ok:
        frames.append(frame)
        ok, frame = cap.read()
    cap.release()
    return frames


@pytest.mark.parametrize("suffix", [".mp4", ".avi"])
def test_writer_writes_a_video_that_reads_back(tmp_path, suffix):
    path = tmp_path / "sub" / f"clip{suffix}"
    with AtomicVideoWriter(path, fps=12.0) as video:
        for level in GREYS:
            video.write(_frame(level))
    assert video.path == path and path.is_file()
    assert video.frames == len(GREYS) and video.size_px == (W_PX, H_PX)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # no temp file left
    frames = _read_back(path)
    assert len(frames) == len(GREYS)
    assert all(f.shape == (H_PX, W_PX, 3) for f in frames)
    # flat grey frames survive lossy coding within a few levels, in order
    np.testing.assert_allclose([f.mean() for f in frames], GREYS, atol=4.0)
    cap = cv2.VideoCapture(str(path))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0, abs=0.01)
    cap.release()


def test_exception_inside_the_block_leaves_no_file(tmp_path):
    path = tmp_path / "clip.mp4"
    with pytest.raises(RuntimeError, match="boom"):
        with AtomicVideoWriter(path, fps=5.0) as video:
            video.write(_frame(100))
            video.write(_frame(120))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_abort_keeps_an_earlier_file(tmp_path):
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"earlier")
    video = AtomicVideoWriter(path, fps=5.0)
    video.write(_frame(100))
    video.abort()
    video.abort()  # twice is fine
    assert path.read_bytes() == b"earlier"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]


def test_close_without_frames_is_an_error_and_writes_nothing(tmp_path):
    video = AtomicVideoWriter(tmp_path / "clip.mp4", fps=5.0)
    with pytest.raises(DockError, match="no frame was written"):
        video.close()
    assert list(tmp_path.iterdir()) == []


def test_write_after_close_is_an_error(tmp_path):
    with AtomicVideoWriter(tmp_path / "clip.mp4", fps=5.0) as video:
        video.write(_frame(50))
    with pytest.raises(DockError, match="already closed"):
        video.write(_frame(50))


def test_bad_suffix_and_fps_are_rejected(tmp_path):
    with pytest.raises(DockError) as err:
        AtomicVideoWriter(tmp_path / "clip.mkv", fps=5.0)
    assert "\n" not in str(err.value) and ".mp4 or .avi" in str(err.value)
    with pytest.raises(ValueError, match="fps"):
        AtomicVideoWriter(tmp_path / "clip.mp4", fps=0.0)


def test_unopenable_writer_is_a_one_line_dock_error(tmp_path):
    video = AtomicVideoWriter(tmp_path / "clip.mp4", fps=5.0)
    with pytest.raises(DockError) as err:
        video.write(np.zeros((0, 0, 3), np.uint8))  # OpenCV cannot open a 0x0 video
    assert "\n" not in str(err.value) and "cannot open a video writer" in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_frame_size_change_raises_unless_resizing(tmp_path):
    with pytest.raises(ValueError, match="differs"):
        with AtomicVideoWriter(tmp_path / "a.mp4", fps=5.0) as video:
            video.write(_frame(100))
            video.write(_frame(100, w=2 * W_PX, h=2 * H_PX))
    assert list(tmp_path.iterdir()) == []
    with AtomicVideoWriter(tmp_path / "b.mp4", fps=5.0, resize=True) as video:
        video.write(_frame(100))
        video.write(_frame(200, w=2 * W_PX, h=2 * H_PX))
    frames = _read_back(tmp_path / "b.mp4")
    assert [f.shape for f in frames] == [(H_PX, W_PX, 3)] * 2
    assert frames[1].mean() == pytest.approx(200, abs=4.0)


def test_annotated_writer_keeps_its_extras(tmp_path):
    video = AnnotatedVideoWriter(tmp_path / "annotated.mp4", None)
    assert video.fps == 10.0  # no container rate -> 10 Hz
    assert video.close() is None  # no frame: nothing written, no error
    with AnnotatedVideoWriter(tmp_path / "annotated.avi", 7.0) as video:
        video.write(_frame(100))
        video.write(_frame(100, w=W_PX // 2, h=H_PX // 2))  # resized to the first
    assert len(_read_back(tmp_path / "annotated.avi")) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["annotated.avi"]


def test_open_video_gives_the_first_frame_and_fails_in_one_line(tmp_path):
    path = tmp_path / "clip.avi"
    with AtomicVideoWriter(path, fps=5.0) as video:
        for level in GREYS[:3]:
            video.write(_frame(level))
    cap, first, leading = open_video(path)
    assert leading == 0
    try:
        assert first.shape == (H_PX, W_PX, 3)
        assert first.mean() == pytest.approx(GREYS[0], abs=4.0)
        ok, second = cap.read()  # positioned after the first frame
        assert ok and second.mean() == pytest.approx(GREYS[1], abs=4.0)
    finally:
        cap.release()
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    with pytest.raises(DockError) as err:
        open_video(bad)
    assert "\n" not in str(err.value) and "cannot read video" in str(err.value)


def test_quiet_native_stderr_silences_fd2_and_restores_it(capfd):
    level = cv2.utils.logging.getLogLevel()
    with quiet_native_stderr():
        os.write(2, b"hidden\n")
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_SILENT
    os.write(2, b"shown\n")
    assert capfd.readouterr().err == "shown\n"
    assert cv2.utils.logging.getLogLevel() == level


def test_dockcore_media_imports_without_opencv():
    code = "import sys; sys.modules['cv2'] = None; import uwdock.dockcore.media; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ok"
