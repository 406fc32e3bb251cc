"""Where calibration views come from: a folder of images, a video or a bag's image topic, each
frame converted to grey by the one conversion every input shares (:func:`to_grey`).
:mod:`calibration.intrinsics` calibrates from them; the stereo inputs share :func:`to_grey`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.bags import Bag, is_bag
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import check_regular_file
from uwdock.dockcore.media import (
    IMAGE_SUFFIXES,
    MAX_CONSECUTIVE_VIDEO_FAILURES,
    display_name,
    open_video,
    quiet_native_stderr,
    read_image,
    scale_to_uint8,
)

__all__ = ["iter_views", "to_grey"]


def to_grey(image: np.ndarray | None) -> np.ndarray | None:
    """The one greyscale conversion of every input (folder, video, bag), so that the same
    frames give the same corners whatever their container.

    Args:
        image: a decoded frame: (H, W) or (H, W, 3) BGR, uint8, uint16 or float; None passes
            through.

    Returns:
        (H, W) uint8: 16-bit keeps its top byte (as ``cv2.imread``'s greyscale flag does),
        float is scaled by its range (:func:`dockcore.media.scale_to_uint8`),
        colour goes through ``cv2.COLOR_BGR2GRAY`` (0.299 R + 0.587 G + 0.114 B).
    """
    if image is None:
        return None
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:  # float (a TIFF), NaN as black: by its range
        image = scale_to_uint8(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def _video_frames(
    path: Path, max_frames: int
) -> tuple[int, Iterator[tuple[str, np.ndarray | None]]]:
    """(views expected, views) of a video: every ``stride``-th frame, at most ``max_frames``.

    A frame that cannot be decoded is a view ``None`` (counted as unreadable) and reading goes
    on past it; it stops at the end of the stream or after
    ``dockcore.media.MAX_CONSECUTIVE_VIDEO_FAILURES`` failed reads in a row; corrupt leading
    frames are skipped. Decoding is quiet (:func:`dockcore.media.quiet_native_stderr`).
    """
    cap, first, leading = open_video(path)
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    stride = max(1, math.ceil(count / max_frames)) if count > 0 else 1
    total = min(max_frames, math.ceil(count / stride)) if count > 0 else max_frames

    def read() -> np.ndarray | None:
        with quiet_native_stderr():
            for _ in range(stride - 1):
                cap.grab()
            ok, frame = cap.read()
        return frame if ok else None

    def frames() -> Iterator[tuple[str, np.ndarray | None]]:
        try:
            index, frame, n, failures = leading, first, 0, 0
            while n < max_frames and failures < MAX_CONSECUTIVE_VIDEO_FAILURES:
                if count > 0 and index >= count:
                    break
                if frame is None:
                    failures += 1
                else:
                    failures = 0
                    frame = to_grey(frame)
                yield f"frame_{index:06d}", frame
                n += 1
                index += stride
                frame = read()
        finally:
            cap.release()

    return total, frames()


def _bag_frames(
    path: Path, topic: str, max_frames: int
) -> tuple[int, Iterator[tuple[str, np.ndarray | None]]]:
    """(views expected, views) of a bag's image topic: every ``stride``-th message, at most
    ``max_frames``, greyscale; an undecodable message is a view None."""
    with Bag(path) as bag:
        count = bag.topic(topic, ("image",)).count
    stride = max(1, math.ceil(count / max_frames))
    total = min(max_frames, math.ceil(count / stride))

    def frames() -> Iterator[tuple[str, np.ndarray | None]]:
        with Bag(path) as bag:
            n = 0
            for k, (_, image) in enumerate(bag.images(topic)):
                if k % stride or n >= total:
                    continue
                yield f"frame_{k:06d}", to_grey(image)
                n += 1

    return total, frames()


def iter_views(
    source: str | os.PathLike[str], video_max_frames: int = 300, topic: str | None = None
) -> tuple[int, Iterator[tuple[str, np.ndarray | None]]]:
    """The views of an input: an image folder (sorted by name), a video file (sampled) or a
    ROS bag's image topic (sampled, :mod:`dockcore.bags`).

    Args:
        source: folder of images (``IMAGE_SUFFIXES``), a video file ``cv2.VideoCapture`` reads,
            or a bag (``.bag``, ``.db3``, ``.mcap``, ROS 2 folder).
        video_max_frames: most frames taken from a video or bag, evenly spaced over its length.
        topic: a bag's image topic (required for a bag: see
            :func:`dockcore.bags.resolve_image_topic`).

    Returns:
        (expected number of views, iterator of (name, greyscale uint8 image or None for a file
        that cannot be decoded)).

    Raises:
        DockError: missing input, a special file (FIFO, device: refused before it is opened),
            a folder without images, an unreadable video.
    """
    path = Path(source)
    if not path.is_dir():
        check_regular_file(path, "input")
    if is_bag(path):
        if topic is None:
            raise DockError(f"{path} is a bag: name its image topic (--topic)")
        return _bag_frames(path, topic, video_max_frames)
    if path.is_dir():
        files = sorted(
            p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not files:
            raise DockError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder {path}")
        # views are named as every output can show them (a name that is not UTF-8: \\xNN)
        return len(files), ((display_name(p.name), to_grey(read_image(p))) for p in files)
    return _video_frames(check_regular_file(path, "input"), video_max_frames)
