"""dockcore.media: the atomic video writer and the native-stderr silencer."""

from __future__ import annotations

import os
from fractions import Fraction

import av
import cv2
import numpy as np
import pytest

from uwdock.dockcore import media
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


# colour squares (BGR) on a gradient: blue, green, red, yellow; each 24 px, far from the edges
SQUARES_BGR = ((255, 0, 0), (0, 255, 0), (0, 0, 255), (0, 255, 255))


def _square_origin(h: int, k: int, j: int) -> tuple[int, int]:
    """Top-left (x, y) px of square j in frame k: on the 2-px grid that yuv420p's chroma uses
    (a colour edge off that grid is blurred by chroma subsampling, not by the writer)."""
    return 8 + 2 * k + 28 * j, (h // 2 - 12) // 2 * 2


def _scene(w: int, h: int, k: int) -> np.ndarray:
    """Frame k: a horizontal grey gradient with four coloured squares moving right by 2k px."""
    img = np.empty((h, w, 3), np.uint8)
    img[:] = np.linspace(30, 220, w).astype(np.uint8)[None, :, None]
    for j, colour in enumerate(SQUARES_BGR):
        x0, y0 = _square_origin(h, k, j)
        img[y0 : y0 + 24, x0 : x0 + 24] = colour
    return img


def _decode(path) -> tuple[av.video.stream.VideoStream, list[np.ndarray]]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="bgr24") for f in container.decode(stream)]
    return stream, frames


def _atom_offsets(path) -> dict[str, int]:
    """Byte offset of each top-level MP4 box (ISO BMFF: 4-byte size, 4-byte type)."""
    data, pos, out = path.read_bytes(), 0, {}
    while pos + 8 <= len(data):
        size = int.from_bytes(data[pos : pos + 4], "big")
        kind = data[pos + 4 : pos + 8].decode("latin-1")
        if size == 1:  # 64-bit size follows
            size = int.from_bytes(data[pos + 8 : pos + 16], "big")
        out.setdefault(kind, pos)
        if size < 8:
            break
        pos += size
    return out


@pytest.mark.parametrize("size_px", [(480, 364), (480, 363), (161, 63)])
def test_mp4_is_browser_playable_h264(tmp_path, size_px):
    """H.264, yuv420p, faststart MP4 at the given rate; pixels and colour order survive; an odd
    width or height is padded to even by repeating the last column / row."""
    w, h = size_px
    path = tmp_path / "clip.mp4"
    n = 9
    with AtomicVideoWriter(path, fps=12.0) as video:
        for k in range(n):
            video.write(_scene(w, h, k))
    even = (w + w % 2, h + h % 2)
    assert video.size_px == (w, h) and video.encoded_size_px == even
    stream, frames = _decode(path)
    assert stream.codec_context.name == "h264"
    assert stream.codec_context.pix_fmt == "yuv420p"
    assert stream.average_rate == Fraction(12) and stream.frames == n
    assert (stream.width, stream.height) == even
    assert len(frames) == n
    atoms = _atom_offsets(path)
    assert atoms["ftyp"] == 0 and atoms["moov"] < atoms["mdat"]  # +faststart
    for k, got in enumerate(frames):
        want = _scene(w, h, k)
        assert got.shape == (even[1], even[0], 3)
        inside = got[:h, :w].astype(float)
        error = np.abs(inside - want)
        psnr_db = 10 * np.log10(255.0**2 / np.mean(error**2))
        assert error.mean() < 2.0 and psnr_db > 36.0  # the whole frame
        _, y0 = _square_origin(h, k, 0)
        far = np.r_[0 : max(y0 - 16, 1), min(y0 + 40, h - 1) : h]  # rows a macroblock away
        assert error[far].max() <= 6.0  # the gradient, away from the squares
        for j, colour in enumerate(SQUARES_BGR):  # BGR in -> the same colour out
            x0, y0 = _square_origin(h, k, j)
            core = inside[y0 + 4 : y0 + 20, x0 + 4 : x0 + 20].reshape(-1, 3).mean(axis=0)
            np.testing.assert_allclose(core, colour, atol=8.0)
        if w % 2:  # the padding column repeats the last one
            np.testing.assert_allclose(got[:h, w].astype(float), want[:, -1], atol=6.0)
        if h % 2:
            assert np.abs(got[h, :w].astype(float) - want[-1]).mean() < 3.0


@pytest.mark.parametrize(
    "fps,rate",
    [(5.0, Fraction(5)), (29.97, Fraction(2997, 100)), (30000 / 1001, Fraction(30000, 1001))],
)
def test_mp4_keeps_the_frame_rate(tmp_path, fps, rate):
    path = tmp_path / "clip.mp4"
    with AtomicVideoWriter(path, fps=fps) as video:
        for k in range(4):
            video.write(_scene(64, 48, k))
    stream, frames = _decode(path)
    assert stream.average_rate == rate and len(frames) == 4
    assert float(stream.duration * stream.time_base) == pytest.approx(4 / fps, abs=0.5 / fps)


def test_failure_mid_write_leaves_nothing_and_keeps_an_earlier_file(tmp_path):
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"earlier")
    with pytest.raises(ValueError, match="uint8"):
        with AtomicVideoWriter(path, fps=5.0) as video:
            for k in range(5):
                video.write(_scene(64, 48, k))
            video.write(np.zeros((48, 64, 3), np.float32))  # a bad frame half-way
    assert path.read_bytes() == b"earlier"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]
    with pytest.raises(KeyboardInterrupt):  # an interruption is cleaned up the same way
        with AtomicVideoWriter(tmp_path / "b.mp4", fps=5.0) as video:
            video.write(_scene(64, 48, 0))
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]


def test_failure_while_finishing_leaves_nothing(tmp_path, monkeypatch):
    def full_disk(self):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(media._H264, "finish", full_disk)
    path = tmp_path / "clip.mp4"
    with pytest.raises(OSError, match="No space"):
        with AtomicVideoWriter(path, fps=5.0) as video:
            for k in range(3):
                video.write(_scene(64, 48, k))
    assert list(tmp_path.iterdir()) == []


def test_missing_encoder_is_a_one_line_dock_error(tmp_path, monkeypatch):
    real = media._H264.__init__

    def no_x264(self, tmp, fps, size_px):
        real(self, tmp, fps, size_px)
        self.container.close()
        raise av.codec.codec.UnknownCodecError("libx264")

    monkeypatch.setattr(media._H264, "__init__", no_x264)
    with pytest.raises(DockError) as err:
        AtomicVideoWriter(tmp_path / "clip.mp4", fps=5.0).write(_scene(64, 48, 0))
    assert "\n" not in str(err.value) and "cannot open a video writer" in str(err.value)
    assert list(tmp_path.iterdir()) == []


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
