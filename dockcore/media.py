"""Video plumbing shared by the packages that read or write video through OpenCV.

* :func:`quiet_native_stderr` silences OpenCV's log and the native decoder/encoder libraries
  (libjpeg, FFmpeg) that write straight to file descriptor 2;
* :func:`open_video` opens a video file and decodes its first frame, quietly;
* :func:`read_image` decodes an image file (``IMAGE_SUFFIXES``), None when it cannot;
* :class:`AtomicVideoWriter` writes BGR frames to a video that appears at its path only when
  it is closed successfully (like :func:`dockcore.io.atomic_path` for files).

OpenCV is imported inside the functions, so ``dockcore`` stays importable without it.

Example:
    >>> with AtomicVideoWriter("out/episode.mp4", fps=5.0) as video:
    ...     for frame_bgr in frames:
    ...         video.write(frame_bgr)
    >>> video.path      # exists now; after an exception inside the block nothing was written
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import temp_sibling

__all__ = [
    "IMAGE_SUFFIXES",
    "MAX_CONSECUTIVE_VIDEO_FAILURES",
    "VIDEO_FOURCC",
    "AtomicVideoWriter",
    "open_video",
    "quiet_native_stderr",
    "read_image",
]

# FFmpeg (behind cv2.VideoCapture) logs decoding errors of damaged videos from its decoder
# threads, outside any quiet_native_stderr() block: silence its log (read once, when OpenCV first
# opens a video; a user's OPENCV_FFMPEG_LOGLEVEL or OPENCV_FFMPEG_DEBUG wins). The readers report
# damaged frames as corrupt frames instead.
if "OPENCV_FFMPEG_DEBUG" not in os.environ:
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

#: Video container suffix -> OpenCV FourCC of the codec written into it.
VIDEO_FOURCC: dict[str, str] = {".mp4": "mp4v", ".avi": "MJPG"}

#: A video read gives up after this many consecutive undecodable frames.
MAX_CONSECUTIVE_VIDEO_FAILURES = 25

#: File suffixes read as images (case-insensitive).
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@contextlib.contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Silence OpenCV's log and native decoder warnings (libjpeg, FFmpeg) on file descriptor 2.

    The OpenCV log level and file descriptor 2 are restored on exit. Without a real file
    descriptor 2 (embedded interpreters) only the log level is changed.
    """
    import cv2

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
        (H, W) uint8 grey when ``grey``; else (H, W) grey or (H, W, 3) BGR, uint8 or uint16
        (alpha dropped).
    """
    import cv2

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
    import cv2

    with quiet_native_stderr():
        cap = cv2.VideoCapture(str(path))
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


class AtomicVideoWriter:
    """BGR frames -> a video that appears at ``path`` only when :meth:`close` succeeds.

    The codec follows the container suffix (:data:`VIDEO_FOURCC`: ``.mp4`` -> ``mp4v``,
    ``.avi`` -> ``MJPG``). The frame size is fixed by the first frame. Frames go to a hidden
    temporary file beside ``path`` that keeps the suffix (OpenCV picks the container from it);
    :meth:`close` renames it onto ``path``. :meth:`abort`, or an exception inside a ``with``
    block, removes it and leaves any earlier file at ``path`` untouched. Nothing is created on
    disk before the first frame.

    Args:
        path: output video file (``.mp4`` or ``.avi``); its folder is created on the first frame.
        fps: frame rate written into the container (frames per second, Hz), > 0.
        resize: resize frames whose size differs from the first one (``INTER_AREA``) instead of
            raising ValueError.

    Attributes:
        path: the output path.
        fps: the frame rate (Hz).
        frames: frames written so far.
        size_px: (width, height) of the frames (px), None before the first frame.

    Raises:
        DockError: (one line) an unsupported suffix, or no video writer can be opened.
    """

    def __init__(self, path: str | os.PathLike[str], fps: float, *, resize: bool = False) -> None:
        self.path = Path(path)
        if self.path.suffix.lower() not in VIDEO_FOURCC:
            raise DockError(f"video must end in {' or '.join(VIDEO_FOURCC)}: {self.path}")
        if not fps > 0:
            raise ValueError(f"fps: must be > 0, got {fps}")
        self.fps = float(fps)
        self.resize = resize
        self.frames = 0
        self.size_px: tuple[int, int] | None = None
        self._writer: Any = None
        self._tmp: Path | None = None

    def _open(self, size_px: tuple[int, int]) -> None:
        import cv2

        suffix = self.path.suffix
        self._tmp = temp_sibling(self.path, suffix)
        fourcc = cv2.VideoWriter_fourcc(*VIDEO_FOURCC[suffix.lower()])
        with quiet_native_stderr():
            writer = cv2.VideoWriter(str(self._tmp), fourcc, self.fps, size_px)
        if not writer.isOpened():
            self.abort()
            raise DockError(f"cannot open a video writer for {self.path}")
        self._writer, self.size_px = writer, size_px

    def write(self, frame_bgr: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 BGR frame.

        Raises:
            ValueError: the frame size differs from the first frame's and ``resize`` is off.
            DockError: the writer was closed or aborted, or cannot be opened.
        """
        size_px = (int(frame_bgr.shape[1]), int(frame_bgr.shape[0]))
        if self._writer is None:
            if self.frames:
                raise DockError(f"video {self.path} is already closed")
            self._open(size_px)
        if size_px != self.size_px:
            if not self.resize:
                raise ValueError(f"frame size {size_px} px differs from {self.size_px} px")
            import cv2

            frame_bgr = cv2.resize(frame_bgr, self.size_px, interpolation=cv2.INTER_AREA)
        self._writer.write(np.ascontiguousarray(frame_bgr))
        self.frames += 1

    def close(self) -> Path:
        """Finish the video and move it onto ``path``.

        Raises:
            DockError: no frame was written (nothing is created then).
        """
        if self._writer is None or self._tmp is None:
            raise DockError(f"no frame was written to {self.path}")
        self._writer.release()
        self._writer = None
        try:
            os.chmod(self._tmp, 0o644)
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._tmp = None
        return self.path

    def abort(self) -> None:
        """Drop the partial video (nothing appears at ``path``); safe to call twice."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
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
