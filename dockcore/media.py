"""Video plumbing shared by the packages that read or write video through OpenCV.

* :func:`quiet_native_stderr` silences OpenCV's log and the native decoder/encoder libraries
  (libjpeg, FFmpeg) that write straight to file descriptor 2;
* :func:`open_video` opens a video file and decodes its first frame, quietly;
* :func:`read_image` decodes an image file (``IMAGE_SUFFIXES``), None when it cannot;
* :func:`scale_to_uint8` brings an image of any real pixel type (16-bit, float, with NaN or
  infinities) to uint8, the one scaling every reader shares;
* :func:`native_path` gives OpenCV a name it can open for any path (OpenCV's Python binding
  crashes, exit 139, on a name that is not UTF-8; :mod:`dockcore.names` shows such a name as
  text, re-exported here);
* :class:`AtomicVideoWriter` writes BGR frames to a video that appears at its path only when
  it is closed successfully (like :func:`dockcore.io.atomic_path` for files): ``.mp4`` is
  H.264 (libx264 through PyAV), ``yuv420p``, with the index in front (``+faststart``), which
  browsers, GitHub and TensorBoard play; ``.avi`` is Motion-JPEG through OpenCV (a frame-indexed
  recording format for test footage, not for the toolkit's own outputs).

OpenCV and PyAV are imported inside the functions, so ``dockcore`` stays importable without
them.

Example:
    >>> with AtomicVideoWriter("out/episode.mp4", fps=5.0) as video:
    ...     for frame_bgr in frames:
    ...         video.write(frame_bgr)
    >>> video.path      # exists now; after an exception inside the block nothing was written
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import output_target, replace_checked, special_file_kind, temp_sibling
from uwdock.dockcore.names import ascii_text, display_name

__all__ = [
    "H264_CRF",
    "H264_PRESET",
    "IMAGE_SUFFIXES",
    "MAX_CONSECUTIVE_VIDEO_FAILURES",
    "VIDEO_CODECS",
    "AtomicVideoWriter",
    "ascii_text",
    "display_name",
    "native_path",
    "open_video",
    "quiet_native_stderr",
    "read_image",
    "scale_to_uint8",
    "silence_opencv_log",
]

# FFmpeg (behind cv2.VideoCapture) logs decoding errors of damaged videos from its decoder
# threads, outside any quiet_native_stderr() block: silence its log (read once, when OpenCV first
# opens a video; a user's OPENCV_FFMPEG_LOGLEVEL or OPENCV_FFMPEG_DEBUG wins). The readers report
# damaged frames as corrupt frames instead.
if "OPENCV_FFMPEG_DEBUG" not in os.environ:
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

#: Video container suffix -> the codec written into it (FFmpeg name).
VIDEO_CODECS: dict[str, str] = {".mp4": "h264", ".avi": "mjpeg"}

#: libx264 constant rate factor of the MP4 videos (x264's default; lower: better quality and
#: larger files). With :data:`H264_PRESET` it gives a higher PSNR than OpenCV's MPEG-4 Part 2
#: (``mp4v``) writer did, at about the same file size (``bench/bench_media.py``).
H264_CRF = 23

#: libx264 speed preset of the MP4 videos (``ultrafast`` writes 2-3x faster, at 4-5x the size).
H264_PRESET = "veryfast"

#: A video read gives up after this many consecutive undecodable frames.
MAX_CONSECUTIVE_VIDEO_FAILURES = 25

#: File suffixes read as images (case-insensitive).
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@contextlib.contextmanager
def native_path(path: str | os.PathLike[str]) -> Iterator[str]:
    """A name of ``path`` that OpenCV's file functions can take, for the length of the block.

    OpenCV's Python binding converts a path to UTF-8 and crashes the process (a segfault) on a
    name that is not UTF-8. Such a path is given to OpenCV as a symbolic link with an ASCII
    name (and the path's suffix, which OpenCV's writers choose the container by) in a private
    temporary folder, removed when the block ends (OpenCV and FFmpeg hold the file open by
    then); any other path is given as it is.

    Raises:
        DockError: the temporary folder's own path is not UTF-8 either.
    """
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        pass
    else:
        yield text
        return
    suffix = os.path.splitext(text)[1]
    suffix = suffix if suffix[1:].isascii() and suffix[1:].isalnum() else ""
    folder = tempfile.mkdtemp(prefix="uwdock-path-")
    try:
        link = os.path.join(folder, "file" + suffix)
        try:
            link.encode("utf-8")
        except UnicodeEncodeError:
            raise DockError(
                f"cannot open {display_name(text)}: its name is not UTF-8 and neither is the "
                f"temporary folder {display_name(folder)} (set TMPDIR)"
            ) from None
        os.symlink(os.path.abspath(text), link)
        yield link
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def scale_to_uint8(image: np.ndarray) -> np.ndarray:
    """An image of any real pixel type as uint8, same shape: the one scaling of every reader.

    * uint8: unchanged;
    * uint16: ``v / 257`` rounded (65535 -> 255);
    * bool: 0 / 255;
    * float and other integers, by the range of their finite values: float within [-0.5, 1.5]
      is an image in [0, 1] (``v * 255``, clipped: a filter's overshoot is not another scale);
      else within [0, 255] they are taken as they are; else min-max normalised to [0, 255] (a
      camera's raw counts, signed data). NaN and -inf pixels become 0 and +inf 255 (a pixel
      without a value is dark, a saturated one bright), so a frame full of NaN is black.

    Raises:
        DockError: a pixel type that is not a real number (complex, object, text).
    """
    image = np.asarray(image)
    kind = image.dtype.kind
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image.astype(np.float32) * (1.0 / 257.0) + 0.5).astype(np.uint8)
    if kind == "b":
        return image.astype(np.uint8) * np.uint8(255)
    if kind not in "iuf":
        raise DockError(f"unsupported image pixel type {image.dtype} (use uint8, uint16 or float)")
    x = image.astype(np.float64 if image.dtype.itemsize > 4 else np.float32)
    finite = np.isfinite(x) if kind == "f" else None
    vals = x if finite is None else x[finite]
    if vals.size == 0:
        return np.where(x == np.inf, 255, 0).astype(np.uint8)
    lo, hi = float(vals.min()), float(vals.max())
    if kind == "f" and lo >= -0.5 and hi <= 1.5:
        scale, offset = 255.0, 0.0
    elif lo >= 0.0 and hi <= 255.0:
        scale, offset = 1.0, 0.0
    else:
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        offset = -lo * scale
    out = np.clip(np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0) * scale + offset + 0.5, 0, 255)
    out = out.astype(np.uint8)
    if finite is not None and not finite.all():
        out[~finite] = 0
        out[x == np.inf] = 255
    return out


def silence_opencv_log() -> None:
    """Turn OpenCV's own log off for the rest of the process (its ``[ WARN:0@...]`` and
    ``[ERROR:0@...]`` lines): the footage commands (``perception``, ``calibration``,
    ``markers``) check what OpenCV returns and say what went wrong in their own line. A user's
    ``OPENCV_LOG_LEVEL`` wins. Native libraries that write to file descriptor 2 themselves
    (libpng, libjpeg) are silenced where they decode (:func:`quiet_native_stderr`)."""
    if "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


@contextlib.contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Silence OpenCV's log and native decoder warnings (libjpeg, FFmpeg) on file descriptor 2.

    The OpenCV log level and file descriptor 2 are restored on exit. Without a real file
    descriptor 2 (embedded interpreters) only the log level is changed.
    """
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    saved = None
    try:
        sys.stderr.flush()
        saved = os.dup(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
    except OSError:
        saved = None
    try:
        yield
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)
        cv2.utils.logging.setLogLevel(level)


def read_image(path: str | os.PathLike[str], grey: bool = False) -> np.ndarray | None:
    """Decode an image file, quietly; None when it is missing, empty or not decodable.

    Returns:
        (H, W) uint8 grey when ``grey``; else (H, W) grey or (H, W, 3) BGR, uint8, uint16 or
        float as decoded (a TIFF; may hold NaN), other integer types brought to uint8 by
        :func:`scale_to_uint8` (alpha dropped).
    """
    if special_file_kind(path) is not None:  # a FIFO would block the read
        return None
    try:
        data = np.fromfile(Path(path), dtype=np.uint8)
    except OSError:
        return None
    if data.size == 0:
        return None
    flags = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR
    with quiet_native_stderr():
        img = cv2.imdecode(data, flags)
    if img is None or img.size == 0:
        return None
    if img.ndim == 3 and img.shape[2] == 4:
        img = np.ascontiguousarray(img[:, :, :3])
    if img.dtype != np.uint16 and img.dtype.kind in "iub":  # signed (TIFF): 8-bit by its range
        img = scale_to_uint8(img)
    return img


def open_video(path: str | os.PathLike[str]) -> tuple[Any, np.ndarray, int]:
    """Open a video file with ``cv2.VideoCapture`` and decode its first decodable frame
    (quietly); up to :data:`MAX_CONSECUTIVE_VIDEO_FAILURES` corrupt leading frames are skipped.

    Returns:
        ``(capture, first_frame, leading)``: the open capture, positioned after that frame (the
        caller releases it), the frame as decoded ((H, W, 3) BGR, usually uint8), and how many
        frames before it could not be decoded.

    Raises:
        DockError: one line when the file is not a video or holds no decodable frame among the
            first ones.
    """
    with quiet_native_stderr(), native_path(path) as name:
        cap = cv2.VideoCapture(name)
        ok, first, leading = False, None, 0
        while cap.isOpened() and leading < MAX_CONSECUTIVE_VIDEO_FAILURES:
            ok, first = cap.read()
            if ok and first is not None:
                break
            leading += 1
    if not ok or first is None:
        cap.release()
        raise DockError(f"cannot read video {path} (not a video, or no decodable frame)")
    return cap, first, leading


class _H264:
    """H.264 / yuv420p / MP4 with ``+faststart`` through PyAV (libx264); frames of an odd width
    or height are padded to even by repeating the last column / row (yuv420p stores one chroma
    sample per 2x2 block; repeating the edge keeps the border's colour, where black padding would
    bleed into it, and no pixel of the frame is dropped as cropping would)."""

    def __init__(self, tmp: Path, fps: float, size_px: tuple[int, int]) -> None:
        import av

        w, h = size_px
        self.pad = (w % 2, h % 2)
        self.container = av.open(str(tmp), "w", format="mp4", options={"movflags": "+faststart"})
        try:
            self.stream = self.container.add_stream("libx264", rate=_rate(fps))
            self.stream.width, self.stream.height = w + self.pad[0], h + self.pad[1]
            self.stream.pix_fmt = "yuv420p"
            self.stream.options = {"crf": str(H264_CRF), "preset": H264_PRESET}
            cc = self.stream.codec_context  # tag what the frames are converted to: BT.709
            cc.colorspace = cc.color_primaries = cc.color_trc = _BT709
            cc.color_range = _LIMITED_RANGE
            self.stream.codec_context.open()
        except BaseException:
            self.container.close()
            raise
        self.size_px = (self.stream.width, self.stream.height)
        self.index = 0
        self._frame = av.VideoFrame
        flags = av.video.reformatter.Interpolation
        self._interpolation = flags.AREA | flags.ACCURATE_RND

    def write(self, frame_bgr: np.ndarray) -> None:
        if self.pad != (0, 0):
            frame_bgr = np.pad(frame_bgr, ((0, self.pad[1]), (0, self.pad[0]), (0, 0)), "edge")
        frame = self._frame.from_ndarray(np.ascontiguousarray(frame_bgr), format="bgr24")
        # sRGB frames -> BT.709 matrix, limited range (what players assume for web video);
        # swscale's fast path rounds grey to a 2-4 level colour cast, ACCURATE_RND does not;
        # AREA averages each 2x2 block for its chroma sample, so colour does not bleed across
        # an edge on the 2-pixel grid
        frame = frame.reformat(
            format="yuv420p",
            dst_colorspace="ITU709",
            dst_color_range="MPEG",
            interpolation=self._interpolation,
        )
        frame.pts = self.index
        self.index += 1
        self.container.mux(self.stream.encode(frame))

    def finish(self) -> None:
        try:
            self.container.mux(self.stream.encode(None))  # flush the encoder's delayed frames
        finally:
            self.container.close()  # writes the index; +faststart moves it before the data

    def drop(self) -> None:
        self.container.close()


class _Mjpeg:
    """Motion-JPEG AVI through ``cv2.VideoWriter`` (frame-indexed, what tank cameras record)."""

    def __init__(self, tmp: Path, fps: float, size_px: tuple[int, int]) -> None:
        with quiet_native_stderr(), native_path(tmp) as name:
            self.writer = cv2.VideoWriter(name, cv2.VideoWriter_fourcc(*"MJPG"), fps, size_px)
        if not self.writer.isOpened():
            raise RuntimeError("OpenCV's MJPG writer did not open")
        self.size_px = size_px

    def write(self, frame_bgr: np.ndarray) -> None:
        self.writer.write(np.ascontiguousarray(frame_bgr))

    def finish(self) -> None:
        self.writer.release()

    def drop(self) -> None:
        self.writer.release()


_BT709 = 1  # the ISO/IEC 23091-4 code of BT.709 (matrix, primaries, transfer)
_LIMITED_RANGE = 1  # "MPEG" range: Y in [16, 235]


def _rate(fps: float) -> Fraction:
    """A frame rate as the exact fraction a container stores (29.97 -> 30000/1001)."""
    return Fraction(fps).limit_denominator(1001)


class AtomicVideoWriter:
    """BGR frames -> a video that appears at ``path`` only when :meth:`close` succeeds.

    The codec follows the container suffix (:data:`VIDEO_CODECS`): ``.mp4`` is H.264
    (``libx264``, :data:`H264_CRF`, :data:`H264_PRESET`), pixel format ``yuv420p``, with the
    ``moov`` index before the media data (``+faststart``), so browsers, GitHub and TensorBoard
    play it and can start before the download ends; yuv420p needs an even width and height, so
    a frame of odd size is padded by repeating its last column / row (:attr:`encoded_size_px`).
    ``.avi`` is Motion-JPEG (OpenCV). The frame size is fixed by the first frame. Frames go to
    a hidden temporary file beside ``path``; :meth:`close` renames it onto ``path``.
    :meth:`abort`, or any exception inside a ``with`` block (KeyboardInterrupt included),
    removes it and leaves any earlier file at ``path`` untouched; so does a failure while the
    video is finished. Nothing is created on disk before the first frame.

    Args:
        path: output video file (``.mp4`` or ``.avi``); its folder is created on the first frame.
        fps: frame rate written into the container (frames per second, Hz), > 0.
        resize: resize frames whose size differs from the first one (``INTER_AREA``) instead of
            raising ValueError.

    Attributes:
        path: the output path.
        fps: the frame rate (Hz).
        frames: frames written so far.
        size_px: (width, height) of the frames given (px), None before the first frame.
        encoded_size_px: (width, height) stored in the file (px): ``size_px`` rounded up to
            even for ``.mp4``; None before the first frame.

    Raises:
        DockError: (one line) an unsupported suffix, or no video writer can be opened.
    """

    def __init__(self, path: str | os.PathLike[str], fps: float, *, resize: bool = False) -> None:
        self.path = Path(path)
        if self.path.suffix.lower() not in VIDEO_CODECS:
            raise DockError(f"video must end in {' or '.join(VIDEO_CODECS)}: {self.path}")
        if not fps > 0:
            raise ValueError(f"fps: must be > 0, got {fps}")
        # what the video replaces: a regular file (a symlink to one is followed) or nothing
        self._target = output_target(self.path, "video")
        self.fps = float(fps)
        self.resize = resize
        self.frames = 0
        self.size_px: tuple[int, int] | None = None
        self.encoded_size_px: tuple[int, int] | None = None
        self._encoder: _H264 | _Mjpeg | None = None
        self._tmp: Path | None = None

    def _open(self, size_px: tuple[int, int]) -> None:
        suffix = self.path.suffix
        if min(size_px) < 1:
            raise DockError(f"cannot open a video writer for {self.path}: frame is {size_px} px")
        self._tmp = temp_sibling(self._target, suffix)
        backend = _H264 if suffix.lower() == ".mp4" else _Mjpeg
        try:
            self._encoder = backend(self._tmp, self.fps, size_px)
        except Exception as exc:  # a missing encoder (PyAV built without libx264), bad size
            self.abort()
            reason = " ".join(str(exc).split()) or type(exc).__name__
            raise DockError(f"cannot open a video writer for {self.path}: {reason}") from None
        self.size_px, self.encoded_size_px = size_px, self._encoder.size_px

    def write(self, frame_bgr: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 BGR frame ((H, W) grey is taken as grey BGR).

        Raises:
            ValueError: not a uint8 image, or the frame size differs from the first frame's
                and ``resize`` is off.
            DockError: the writer was closed or aborted, or cannot be opened.
        """
        frame_bgr = np.asarray(frame_bgr)
        if frame_bgr.ndim == 2:
            frame_bgr = np.repeat(frame_bgr[:, :, None], 3, axis=2)
        if frame_bgr.dtype != np.uint8 or frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3:
            raise ValueError(
                f"frame must be (H, W, 3) uint8 BGR, got {frame_bgr.shape} {frame_bgr.dtype}"
            )
        size_px = (int(frame_bgr.shape[1]), int(frame_bgr.shape[0]))
        if self._encoder is None:
            if self.frames:
                raise DockError(f"video {self.path} is already closed")
            self._open(size_px)
        assert self._encoder is not None and self.size_px is not None
        if size_px != self.size_px:
            if not self.resize:
                raise ValueError(f"frame size {size_px} px differs from {self.size_px} px")
            frame_bgr = cv2.resize(frame_bgr, self.size_px, interpolation=cv2.INTER_AREA)
        self._encoder.write(frame_bgr)
        self.frames += 1

    def close(self) -> Path:
        """Finish the video and move it onto ``path``.

        Raises:
            DockError: no frame was written (nothing is created then).
        """
        if self._encoder is None or self._tmp is None:
            raise DockError(f"no frame was written to {self.path}")
        try:
            encoder, self._encoder = self._encoder, None
            encoder.finish()
            os.chmod(self._tmp, 0o644)
            replace_checked(self._tmp, self._target)  # a node that appeared meanwhile: kept
        except BaseException:
            self.abort()
            raise
        self._tmp = None
        return self.path

    def abort(self) -> None:
        """Drop the partial video (nothing appears at ``path``); safe to call twice."""
        encoder, self._encoder = self._encoder, None
        try:
            if encoder is not None:
                with contextlib.suppress(Exception):
                    encoder.drop()
        finally:
            if self._tmp is not None:
                self._tmp.unlink(missing_ok=True)
                self._tmp = None

    def __enter__(self) -> AtomicVideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
