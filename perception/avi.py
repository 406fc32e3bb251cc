"""Motion-JPEG AVI files read frame by frame through their index, so a damaged frame is a
corrupt frame at its own index.

FFmpeg (behind ``cv2.VideoCapture``) reads an AVI chunk after chunk; when a chunk's header is
damaged it resynchronises on the next chunk and numbers the frames it finds consecutively: the
lost frames vanish and every later frame gets an earlier index (a ground-truth CSV indexed by
frame then matches the wrong frames). An AVI 1.0 file ends with an index (``idx1``) holding the
position and size of every frame: each Motion-JPEG frame is a JPEG image that decodes on its own,
so reading frame k from there places it at index k whatever happened to the others.

Only plain AVI 1.0 files whose first video stream is Motion-JPEG and whose index lists every
frame are read this way (``cv2.VideoWriter``'s MJPG files, most tank and USB cameras'); anything
else (other codecs, no index because the recording was cut, OpenDML files over 1 GB) is left to
``cv2.VideoCapture``: :func:`mjpeg_avi_index` returns None for them.

Layout read (RIFF, little-endian)::

    RIFF <size> 'AVI '
      LIST <size> 'hdrl'  avih, LIST 'strl' (strh: fccType 'vids', dwScale, dwRate;
                          strf: BITMAPINFOHEADER width, height, biCompression 'MJPG') ...
      LIST <size> 'movi'  '00dc' <size> <JPEG> ...
      idx1 <size>         16-byte entries: ckid, flags, offset (from 'movi' or the file start),
                          size
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.media import quiet_native_stderr

__all__ = ["AviIndex", "mjpeg_avi_index"]

#: ``biCompression`` / ``fccHandler`` codes of Motion-JPEG.
_MJPEG = {b"MJPG", b"mjpg", b"AVRn", b"dmb1", b"JPEG", b"jpeg"}
#: Largest index read (16 bytes an entry): 4 M frames, beyond what an AVI 1.0 file (< 4 GB)
#: holds at any useful frame size; a larger one is left to ``cv2.VideoCapture``.
_MAX_INDEX_BYTES = 16 * 4_000_000


@dataclass(frozen=True)
class AviIndex:
    """Where every frame of a Motion-JPEG AVI lies.

    Attributes:
        path: the file.
        frames: ``(offset, size)`` of each frame's chunk header in the file (bytes), in order.
        fps: frame rate (Hz) from the stream header, or None.
        width_px, height_px: frame size from the stream format.
    """

    path: Path
    frames: tuple[tuple[int, int], ...]
    fps: float | None
    width_px: int
    height_px: int

    def decode(self, fh, k: int) -> np.ndarray | None:
        """Frame ``k`` as (H, W, 3) uint8 BGR from the open file ``fh``; None when its data
        cannot be read or decoded, or decodes to another size."""
        offset, size = self.frames[k]
        try:
            fh.seek(offset + 8)
            data = fh.read(size)
        except (OSError, ValueError):
            return None
        if len(data) < size or size == 0:
            return None
        with quiet_native_stderr():
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None or img.shape[:2] != (self.height_px, self.width_px):
            return None
        return img


def _chunks(data: bytes, start: int, end: int):
    """``(fourcc, payload offset, payload size)`` of the chunks between ``start`` and ``end``."""
    pos = start
    while pos + 8 <= end:
        fourcc, size = data[pos : pos + 4], struct.unpack("<I", data[pos + 4 : pos + 8])[0]
        yield fourcc, pos + 8, size
        pos += 8 + size + (size & 1)


def _video_stream(header: bytes) -> tuple[int, float | None, int, int] | None:
    """(stream number, fps, width, height) of the first video stream of an ``hdrl`` list's
    payload when it is Motion-JPEG, else None."""
    stream = 0
    for fourcc, off, size in _chunks(header, 0, len(header)):
        if fourcc != b"LIST" or header[off : off + 4] != b"strl":
            continue
        strh = strf = None
        for cc, o, n in _chunks(header, off + 4, off + size):
            if cc == b"strh" and n >= 32:
                strh = header[o : o + n]
            elif cc == b"strf" and n >= 20:
                strf = header[o : o + n]
        if strh is not None and strh[:4] == b"vids":
            if strf is None or not ({strh[4:8], strf[16:20]} & _MJPEG):
                return None
            scale, rate = struct.unpack("<II", strh[20:28])
            width, height = struct.unpack("<ii", strf[4:12])
            fps = rate / scale if scale > 0 and rate > 0 else None
            return stream, fps, abs(width), abs(height)
        stream += 1
    return None


def mjpeg_avi_index(path: str | os.PathLike[str]) -> AviIndex | None:
    """The frame index of a Motion-JPEG AVI 1.0 file, or None for any other file (see the
    module docstring); never raises for a damaged or foreign file."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(12)
            if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"AVI ":
                return None
            return _read_index(fh, path)
    except (OSError, struct.error, ValueError):
        return None


def _read_index(fh, path: Path) -> AviIndex | None:
    """The index of an open AVI whose 12-byte RIFF header was read."""
    file_size = os.fstat(fh.fileno()).st_size
    pos, stream, movi, idx1 = 12, None, None, None
    while pos + 8 <= file_size:
        fh.seek(pos)
        fourcc, size = struct.unpack("<4sI", fh.read(8))
        if fourcc == b"LIST":
            kind = fh.read(4)
            if kind == b"hdrl" and size <= 1 << 20:
                stream = _video_stream(fh.read(size - 4))
                if stream is None:
                    return None
            elif kind == b"movi":
                movi = pos + 8  # offsets in idx1 count from the 'movi' fourcc
        elif fourcc == b"idx1" and size <= _MAX_INDEX_BYTES:
            idx1 = fh.read(size)
        elif fourcc == b"RIFF":  # an OpenDML 'AVIX' extension: idx1 covers only the first part
            return None
        pos += 8 + size + (size & 1)
    if stream is None or movi is None or idx1 is None:
        return None
    number, fps, width, height = stream
    ids = {f"{number:02d}dc".encode(), f"{number:02d}db".encode()}
    entries = [
        (off, n)
        for ckid, _flags, off, n in struct.iter_unpack("<4sIII", idx1[: len(idx1) // 16 * 16])
        if ckid in ids
    ]
    if not entries:
        return None
    base = _offset_base(fh, entries, movi, ids)
    if base is None:
        return None
    frames = tuple((base + off, n) for off, n in entries)
    if any(off + 8 + n > file_size for off, n in frames):
        return None
    return AviIndex(path, frames, fps, width, height)


def _offset_base(fh, entries: list[tuple[int, int]], movi: int, ids: set[bytes]) -> int | None:
    """Whether index offsets count from the 'movi' fourcc (usual) or from the file start: the
    base under which most of the first frames' chunk headers are found."""
    votes = {movi: 0, 0: 0}
    for off, _ in entries[:9]:
        for base in votes:
            fh.seek(base + off)
            if fh.read(4) in ids:
                votes[base] += 1
    best = max(votes, key=votes.get)
    return best if votes[best] > 0 else None
