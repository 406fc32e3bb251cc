"""Frames in and out: sources (an image, a folder of images, a video file), annotated frames,
the contact sheet, and the annotated-video writer.

Example:
    >>> source = open_frames("dive_03.mp4")       # raises DockError if it cannot be read at all
    >>> for index, name, image in source:          # image is None for a corrupt frame
    ...     if image is None:
    ...         continue
    >>> source.corrupt                              # frames that could not be decoded

Inputs:
    * an image file (``IMAGE_SUFFIXES``): one frame, index 0, named after the file;
    * a folder: its image files sorted by name, frame index = position in that order (this is
      the index a ground-truth CSV refers to); other files are ignored;
    * a Motion-JPEG AVI with an index: frame k is the k-th indexed frame, decoded on its own
      (:mod:`perception.avi`), so damage to one frame cannot shift the others;
    * a ROS bag (``.bag``, ``.db3``, ``.mcap`` or a ROS 2 recording folder,
      :mod:`dockcore.bags`) with an image topic: frame k is the topic's k-th message in
      recorded order, named ``frame_000000`` ...; its time (header stamp, ns) is kept in
      :attr:`FrameSource.timestamps_ns`;
    * anything else is opened with ``cv2.VideoCapture``: frame index = stream position (from
      the decoded frames' timestamps when they are consistent, else decode order), names
      ``frame_000000`` ...

Frames that cannot be decoded, or that the decoder skipped, are yielded as None at their index
and counted (:attr:`FrameSource.corrupt`); a video ending early is padded to its container's
frame count with such frames, with a warning (:attr:`FrameSource.warnings`).

Annotations (:func:`annotate`): marker outlines, IDs, a dot on the TL corner, the DS board axes
when a pose was solved (x red, y green, z blue), small axes on single-marker poses; line widths
and text scale with the image, so any resolution works.

Images are returned as OpenCV reads them (``IMREAD_ANYDEPTH | IMREAD_ANYCOLOR``): (H, W) grey or
(H, W, 3) BGR, uint8 or uint16; :func:`perception.preprocess.as_uint8` accepts all of them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.dockcore.bags import Bag, is_bag
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_bytes, check_regular_file
from uwdock.dockcore.media import (
    IMAGE_SUFFIXES,
    MAX_CONSECUTIVE_VIDEO_FAILURES,
    AtomicVideoWriter,
    ascii_text,
    display_name,
    open_video,
    quiet_native_stderr,
    read_image,
)
from uwdock.perception.avi import AviIndex, mjpeg_avi_index
from uwdock.perception.preprocess import MIN_IMAGE_PX, as_uint8

__all__ = [
    "IMAGE_SUFFIXES",
    "AnnotatedVideoWriter",
    "FrameSource",
    "ThumbnailBuffer",
    "annotate",
    "encode_image",
    "open_frames",
    "read_image",
    "write_contact_sheet",
]


#: A decoded frame's timestamp is trusted to place it when the first two frames lie one frame
#: interval apart within this fraction of an interval (constant frame rate, sane timestamps).
_PTS_TOLERANCE = 0.25

Frame = tuple[int, str, "np.ndarray | None"]


@dataclass
class FrameSource:
    """An opened input. Iterate it once for ``(index, name, image | None)``.

    A frame that cannot be used is yielded as None at its index and counted in
    :attr:`corrupt`: an image file that cannot be decoded or is smaller than
    ``MIN_IMAGE_PX`` on a side (it cannot hold a marker), a video frame the decoder rejects,
    and a video frame the decoder skipped without saying so (found from the timestamps of the
    frames around it, or at the end when fewer frames than the container lists were decoded).

    Attributes:
        path: the input as given.
        kind: "image", "folder", "video" or "bag".
        total: number of frames expected (a video's container count may be wrong or 0), or None.
        fps: a video's frame rate (Hz) when the container states one, else None.
        corrupt: frames that could not be decoded so far (yielded as None).
        warnings: one-line remarks about the input found while reading it (frames too small,
            frames missing from a video), for the caller to show.
        topic: a bag's image topic, else None.
        timestamps_ns: a bag's frame times (ns), filled as the frames are read.
    """

    path: Path
    kind: str
    total: int | None
    fps: float | None = None
    corrupt: int = 0
    warnings: list[str] = field(default_factory=list)
    _files: list[Path] = field(default_factory=list, repr=False)
    _cap: cv2.VideoCapture | None = field(default=None, repr=False)
    _first: np.ndarray | None = field(default=None, repr=False)
    _leading: int = field(default=0, repr=False)
    _avi: AviIndex | None = field(default=None, repr=False)
    topic: str | None = None
    timestamps_ns: list[int] = field(default_factory=list)

    def __iter__(self) -> Iterator[Frame]:
        if self.kind == "bag":
            yield from self._bag()
            return
        if self.kind == "video":
            yield from (self._indexed() if self._avi is not None else self._video())
            return
        small: list[str] = []
        for index, file in enumerate(self._files):
            image = read_image(file)
            if image is not None and min(image.shape[:2]) < MIN_IMAGE_PX:
                small.append(f"{display_name(file.name)} ({image.shape[1]}x{image.shape[0]} px)")
                image = None
            if image is None:
                self.corrupt += 1
            yield index, file.name, image
        if small:
            self.warnings.append(
                f"{len(small)} image(s) smaller than {MIN_IMAGE_PX} px on a side counted as "
                f"corrupt: {', '.join(small[:5])}{' ...' if len(small) > 5 else ''}"
            )

    def close(self) -> None:
        """Release a video that was opened but not (fully) iterated; safe to call twice."""
        if self._cap is not None:
            self._cap.release()
            self._cap, self._first = None, None
        self._avi = None

    def _bag(self) -> Iterator[Frame]:
        """A bag's image topic, message by message (:mod:`dockcore.bags`)."""
        with Bag(self.path) as bag:
            for k, (stamp_ns, image) in enumerate(bag.images(str(self.topic))):
                if image is not None and min(image.shape[:2]) < MIN_IMAGE_PX:
                    image = None
                if image is None:
                    self.corrupt += 1
                self.timestamps_ns.append(stamp_ns)
                yield k, f"frame_{k:06d}", image

    def _indexed(self) -> Iterator[Frame]:
        """A Motion-JPEG AVI frame by frame through its index (:mod:`perception.avi`): frame k
        is the k-th indexed frame, None when its data cannot be decoded."""
        index, self._avi = self._avi, None
        with index.path.open("rb") as fh:
            for k in range(len(index.frames)):
                image = index.decode(fh, k)
                if image is None:
                    self.corrupt += 1
                yield k, f"frame_{k:06d}", image

    def _video(self) -> Iterator[Frame]:
        """Frames in stream order, each at its true index.

        A failed read is a corrupt frame. When the container states a frame rate and the first
        two frames' timestamps lie one interval apart, each decoded frame is placed by its
        timestamp, so frames the decoder skipped silently are yielded as None where they were.
        Reading ends at the end of the stream, at the container's frame count or after
        ``MAX_CONSECUTIVE_VIDEO_FAILURES`` failed reads in a row; frames the container lists
        beyond the last decoded one are yielded as None then (with a warning).
        """
        cap, frame = self._cap, self._first
        self._cap, self._first = None, None
        if cap is None:
            raise DockError(f"video {self.path} can only be iterated once")
        next_index, failures = 0, self._leading
        clock = _FrameClock(self.fps, self.total, cap.get(cv2.CAP_PROP_POS_MSEC), failures)
        try:
            while True:
                if frame is not None:
                    index = clock.index(cap.get(cv2.CAP_PROP_POS_MSEC), next_index + failures)
                    for k in range(next_index, index):  # failed reads and skipped frames
                        self.corrupt += 1
                        yield k, f"frame_{k:06d}", None
                    yield index, f"frame_{index:06d}", frame
                    next_index, failures = index + 1, 0
                else:
                    failures += 1
                    if failures >= MAX_CONSECUTIVE_VIDEO_FAILURES or (
                        self.total is not None and next_index + failures >= self.total
                    ):
                        break
                with quiet_native_stderr():
                    ok, frame = cap.read()
                if not ok:
                    frame = None
        finally:
            cap.release()
        if self.total is not None and next_index < self.total:
            missing = self.total - next_index
            self.warnings.append(
                f"video {self.path.name}: the container lists {self.total} frames but only "
                f"{next_index} could be read; the last {missing} are counted as corrupt (if frames "
                "were lost inside the video, the indices after them are shifted)"
            )
            for k in range(next_index, self.total):
                self.corrupt += 1
                yield k, f"frame_{k:06d}", None


class _FrameClock:
    """Frame index of a decoded video frame from its timestamp (``CAP_PROP_POS_MSEC``).

    The timestamps are trusted once two frames decoded one after the other lie one frame
    interval apart (within ``_PTS_TOLERANCE``): a constant frame rate and sane timestamps. A
    frame is never placed before ``at_least`` (the frames read so far) nor at or beyond the
    container's frame count.

    Args:
        fps: the container's frame rate (Hz), or None (no timestamps used).
        total: the container's frame count, or None.
        first_ms: timestamp of the first decoded frame (ms).
        first_index: index of the first decoded frame (the failed reads before it).
    """

    def __init__(
        self, fps: float | None, total: int | None, first_ms: float, first_index: int = 0
    ) -> None:
        self.fps, self.total, self.t0, self.k0 = fps, total, first_ms, first_index
        self.trusted: bool | None = None if fps else False  # None: not decided yet
        self.last = (first_index, first_ms)  # (index, timestamp) of the last decoded frame

    def index(self, t_ms: float, at_least: int) -> int:
        """The index of the frame just decoded (timestamp ``t_ms``): ``at_least`` unless the
        trusted timestamps place it later."""
        if self.trusted is None and at_least == self.last[0] + 1:
            self.trusted = abs((t_ms - self.last[1]) * self.fps / 1000.0 - 1.0) < _PTS_TOLERANCE
        k = at_least
        if self.trusted:
            est = round(self.k0 + (t_ms - self.t0) * self.fps / 1000.0)
            if at_least < est and (self.total is None or est < self.total):
                k = est
        self.last = (k, t_ms)
        return k


def _open_indexed_avi(path: Path) -> FrameSource | None:
    """A Motion-JPEG AVI read through its index (:mod:`perception.avi`), or None when the file
    is not one or none of its first frames decodes (then ``cv2.VideoCapture`` reads it)."""
    index = mjpeg_avi_index(path)
    if index is None:
        return None
    with path.open("rb") as fh:
        n = min(len(index.frames), MAX_CONSECUTIVE_VIDEO_FAILURES)
        if all(index.decode(fh, k) is None for k in range(n)):
            return None
    return FrameSource(path, "video", len(index.frames), index.fps, _avi=index)


def _open_video(path: Path) -> FrameSource:
    """A video through :func:`dockcore.media.open_video`: corrupt leading frames are yielded
    as corrupt frames 0, 1, ... (DockError: not a video, or no decodable frame)."""
    cap, first, leading = open_video(path)
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    fps = float(cap.get(cv2.CAP_PROP_FPS))
    return FrameSource(
        path,
        "video",
        count if count > 0 else None,
        fps if np.isfinite(fps) and fps > 0 else None,
        _cap=cap,
        _first=first,
        _leading=leading,
    )


def open_frames(path: str | os.PathLike[str], topic: str | None = None) -> FrameSource:
    """Open an image, a folder of images, a video or a bag's image ``topic`` (see the module
    docstring; :func:`dockcore.bags.resolve_image_topic` picks the topic).

    Raises:
        DockError: one line when the path is missing or a special file (a FIFO, a device:
            refused before it is opened), a folder holds no image files, a single image cannot
            be decoded, a video cannot be opened or has no decodable frame, or a bag has no
            such image topic (or none was named). Corrupt images in a folder and
            corrupt frames in a video or bag are not errors: they are yielded as None and
            counted in :attr:`FrameSource.corrupt`.
    """
    path = Path(path)
    if not path.exists():
        raise DockError(f"input not found: {path}")
    if not path.is_dir():
        check_regular_file(path, "input")
    if is_bag(path):
        if topic is None:
            raise DockError(f"{path} is a bag: name its image topic (--topic)")
        with Bag(path) as bag:
            t = bag.topic(topic, ("image",))
            stamps = np.array(bag.stamps(topic, limit=30), np.int64)  # the rate, cheaply
        fps = None
        if stamps.size > 1 and np.median(np.diff(stamps)) > 0:
            fps = 1e9 / float(np.median(np.diff(stamps)))
        return FrameSource(path, "bag", t.count, fps, topic=topic)
    if path.is_dir():
        # anything named as an image but a folder: a FIFO or a broken link among the frames is
        # a corrupt frame (counted), not a frame silently left out
        files = sorted(
            p for p in path.iterdir() if not p.is_dir() and p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not files:
            raise DockError(f"no images in folder {path} (looked for {', '.join(IMAGE_SUFFIXES)})")
        return FrameSource(path, "folder", len(files), _files=files)
    if path.suffix.lower() in IMAGE_SUFFIXES:
        if read_image(path) is None:
            raise DockError(f"cannot read image {path} (corrupt or not an image)")
        return FrameSource(path, "image", 1, _files=[path])
    return _open_indexed_avi(path) or _open_video(path)


class AnnotatedVideoWriter(AtomicVideoWriter):
    """The annotated-frame video: an :class:`dockcore.media.AtomicVideoWriter` (``.mp4`` with
    H.264 or ``.avi`` with Motion-JPEG, written to a temporary file and renamed on close) that
    resizes later frames of another size to the first one's.

    Args:
        path: output video file (.mp4 or .avi).
        fps: frame rate written into the container (Hz); None or <= 0 gives 10 Hz (a video
            whose container states no rate).
    """

    def __init__(self, path: str | os.PathLike[str], fps: float | None) -> None:
        super().__init__(path, fps if fps and fps > 0 else 10.0, resize=True)

    def close(self) -> Path | None:
        """Finish the file and move it onto ``path``; None when no frame was written."""
        if self.frames == 0:
            self.abort()
            return None
        return super().close()


# --------------------------------------------------------------------------- drawing


_GREEN, _RED, _YELLOW, _WHITE, _BLACK = (
    (60, 220, 60),
    (40, 40, 230),
    (0, 215, 255),
    (255,) * 3,
    (0,) * 3,
)


def _bgr(image: np.ndarray) -> np.ndarray:
    img = as_uint8(image)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, colour) -> None:
    text = ascii_text(text)  # a name that is not UTF-8 would crash OpenCV (exit 139)
    thick = max(1, round(2 * scale))
    cv2.putText(
        img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, _BLACK, thick + 2, cv2.LINE_AA
    )
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, colour, thick, cv2.LINE_AA)


def _axes(img, camera: CameraModel, T: np.ndarray, length_m: float, thickness: int) -> None:
    rvec = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0]
    try:  # quiet: OpenCV warns on stderr when an axis ends outside the image
        with quiet_native_stderr():
            cv2.drawFrameAxes(
                img, camera.K, camera.dist_coeffs, rvec, T[:3, 3].copy(), length_m, thickness
            )
    except cv2.error:  # axes projecting far outside the image: nothing useful to draw
        pass


def annotate(
    image: np.ndarray,
    detections: Sequence[Any],
    camera: CameraModel | None = None,
    T_cam_ds: np.ndarray | None = None,
    T_cam_markers: Mapping[int, np.ndarray] | None = None,
    axis_length_m: float = 0.3,
    marker_size_m: float = 0.1,
    label: str | None = None,
) -> np.ndarray:
    """An annotated BGR copy of a camera image.

    Args:
        image: the camera image (any layout :func:`as_uint8` accepts).
        detections: objects with ``marker_id`` and (4, 2) ``corners_px`` (TL, TR, BR, BL).
        camera: intrinsics for drawing axes (None: no axes).
        T_cam_ds: (4, 4) solved DS pose: its axes are drawn at the DS origin (x red, y green,
            z blue), ``axis_length_m`` long.
        T_cam_markers: ID -> (4, 4) single-marker poses: small axes on each marker.
        axis_length_m: DS axis length (m).
        marker_size_m: single-marker axis length is half of it (m).
        label: text for the top-left corner.

    Returns:
        (H, W, 3) uint8 BGR image.
    """
    img = _bgr(image)
    h, w = img.shape[:2]
    scale = max(min(w, h) / 720.0, 0.5)
    thick = max(1, round(2 * scale))
    for d in detections:
        c = np.asarray(d.corners_px, np.float64)
        pts = np.round(c * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], True, _GREEN, thick, cv2.LINE_AA, shift=4)
        tl = tuple(int(v) for v in np.round(c[0]))
        cv2.circle(img, tl, thick + 2, _RED, -1, cv2.LINE_AA)
        cx, cy = (int(v) for v in np.round(c.mean(axis=0)))
        _text(img, str(d.marker_id), (cx - int(10 * scale), cy + int(8 * scale)), scale, _YELLOW)
    if camera is not None:
        for T in (T_cam_markers or {}).values():
            _axes(img, camera, T, 0.5 * marker_size_m, thick)
        if T_cam_ds is not None:
            _axes(img, camera, T_cam_ds, axis_length_m, thick + 1)
    if label:
        _text(img, label, (int(8 * scale), int(26 * scale)), scale, _WHITE)
    return img


def encode_image(image: np.ndarray, suffix: str = ".png") -> bytes:
    """Encode an image in the format of ``suffix`` (".png", ".jpg", ...)."""
    ok, buf = cv2.imencode(suffix, image)
    if not ok:
        raise DockError(f"cannot encode an image as {suffix}")
    return buf.tobytes()


class ThumbnailBuffer:
    """Keeps about ``n`` evenly spaced thumbnails of a stream of unknown length.

    Every ``stride``-th frame is kept; when twice ``n`` are held, every other one is dropped and
    the stride doubles. :meth:`pick` returns ``n`` evenly spaced among those kept.

    Args:
        n: thumbnails wanted (>= 1).
        width_px: thumbnail width (px); the height keeps the aspect ratio.
    """

    def __init__(self, n: int = 12, width_px: int = 400) -> None:
        self.n = max(1, int(n))
        self.width_px = int(width_px)
        self.stride = 1
        self.count = 0
        self.items: list[tuple[int, str, np.ndarray]] = []

    def wants(self) -> bool:
        """True when the next offered frame will be kept (annotate it only then)."""
        return self.count % self.stride == 0

    def offer(self, index: int, name: str, image_bgr: np.ndarray | None) -> None:
        """Offer the next frame (None: not rendered because :meth:`wants` was False)."""
        if self.wants() and image_bgr is not None:
            h, w = image_bgr.shape[:2]
            tw = min(self.width_px, w)
            th = max(1, round(h * tw / w))
            thumb = cv2.resize(image_bgr, (tw, th), interpolation=cv2.INTER_AREA)
            self.items.append((index, name, thumb))
            if len(self.items) >= 2 * self.n:
                self.items = self.items[::2]
                self.stride *= 2
        self.count += 1

    def pick(self) -> list[tuple[int, str, np.ndarray]]:
        """About ``n`` thumbnails, evenly spaced over the stream."""
        if len(self.items) <= self.n:
            return list(self.items)
        keep = np.unique(np.round(np.linspace(0, len(self.items) - 1, self.n)).astype(int))
        return [self.items[k] for k in keep]


def write_contact_sheet(
    path: str | os.PathLike[str], thumbs: Sequence[tuple[int, str, np.ndarray]], cols: int = 4
) -> Path | None:
    """A grid of (already annotated) thumbnails as one image (format from the suffix of
    ``path``: .png, .jpg, ...), written atomically.

    Returns:
        The path, or None when there is no thumbnail.
    """
    if not thumbs:
        return None
    tw = max(t[2].shape[1] for t in thumbs)
    th = max(round(t[2].shape[0] * tw / t[2].shape[1]) for t in thumbs)
    cols = min(cols, len(thumbs))
    rows = math.ceil(len(thumbs) / cols)
    pad = 4
    sheet = np.full((rows * (th + pad) + pad, cols * (tw + pad) + pad, 3), 32, np.uint8)
    for k, (_, name, img) in enumerate(thumbs):
        tile = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
        r, c = divmod(k, cols)
        y, x = pad + r * (th + pad), pad + c * (tw + pad)
        sheet[y : y + th, x : x + tw] = tile
        _text(sheet, name, (x + 6, y + th - 8), max(tw / 600.0, 0.45), _WHITE)
    return atomic_write_bytes(path, encode_image(sheet, Path(path).suffix or ".png"))
