"""The pairs of views of a stereo calibration (:mod:`calibration.stereo`): two image folders
paired by file stem, two videos paired by frame index, or one ROS bag's two image topics paired
by header stamp. Every view comes out 8-bit grey, converted one way whatever the input (16-bit
shifted to 8 bits, BGR to grey with OpenCV's weights).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from uwdock.calibration.intrinsics import to_grey
from uwdock.dockcore.bags import Bag, is_bag, nearest_in_time
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import check_regular_file
from uwdock.dockcore.media import (
    IMAGE_SUFFIXES,
    MAX_CONSECUTIVE_VIDEO_FAILURES,
    display_name,
    native_path,
    open_video,
    quiet_native_stderr,
    read_image,
)

if TYPE_CHECKING:
    from uwdock.calibration.stereo_config import StereoConfig

__all__ = ["View", "stereo_pairs"]


#: One view as read: a grey image, or None when it cannot be decoded.
View = np.ndarray | None


def _folder_pairs(
    left: Path, right: Path, skip_unpaired: bool, notes: list[str]
) -> tuple[int, Iterator[tuple[str, View, View]]]:
    """Pairs of two image folders by file stem (``left/0001.png`` with ``right/0001.jpg``)."""
    stems: list[dict[str, Path]] = []
    for folder in (left, right):
        files: dict[str, Path] = {}
        for p in sorted(folder.iterdir()):
            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
                if p.stem in files:
                    raise DockError(
                        f"{folder}: two images named {p.stem!r} ({files[p.stem].name}, {p.name})"
                    )
                files[p.stem] = p
        if not files:
            raise DockError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder {folder}")
        stems.append(files)
    common = sorted(set(stems[0]) & set(stems[1]))
    only = [sorted(set(stems[i]) - set(stems[1 - i])) for i in (0, 1)]
    if not common:
        raise DockError(
            f"no image of {left} has a partner of the same name in {right} "
            f"({len(stems[0])} and {len(stems[1])} images; e.g. {next(iter(stems[0]))!r} "
            f"and {next(iter(stems[1]))!r}): pairs are matched by file name"
        )
    if only[0] or only[1]:
        what = (
            f"{len(stems[0])} images in {left} and {len(stems[1])} in {right}, "
            f"{len(only[0]) + len(only[1])} without a partner of the same name "
            f"(e.g. {(only[0] or only[1])[0]!r})"
        )
        if not skip_unpaired:
            raise DockError(
                f"{what}: pairs are matched by file name (--skip-unpaired to skip them)"
            )
        notes.append(f"{what}: skipped")

    def pairs() -> Iterator[tuple[str, View, View]]:
        for stem in common:
            pair = read_image(stems[0][stem]), read_image(stems[1][stem])
            yield display_name(stem), to_grey(pair[0]), to_grey(pair[1])  # not UTF-8: \\xNN

    return len(common), pairs()


def _video_count(path: Path) -> int:
    with quiet_native_stderr(), native_path(path) as name:
        cap = cv2.VideoCapture(name)
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        cap.release()
    return n


def _video_pairs(
    left: Path, right: Path, cfg: StereoConfig, notes: list[str]
) -> tuple[int, Iterator[tuple[str, View, View]]]:
    """Pairs of two videos by frame index: every ``stride``-th frame of both, at most
    ``video_max_frames`` pairs, up to the end of the shorter video."""
    counts = [_video_count(p) for p in (left, right)]
    if counts[0] != counts[1] and min(counts) > 0:
        what = f"{left} has {counts[0]} frames and {right} {counts[1]}"
        if not cfg.skip_unpaired:
            raise DockError(
                f"{what}: pairs are matched by frame index (--skip-unpaired to stop at the "
                "end of the shorter one)"
            )
        notes.append(f"{what}: pairs stop at the end of the shorter one")
    count = min(counts)
    max_frames = cfg.intrinsics.video_max_frames
    stride = max(1, math.ceil(count / max_frames)) if count > 0 else 1
    total = min(max_frames, math.ceil(count / stride)) if count > 0 else max_frames

    def frames(path: Path) -> Iterator[View]:
        """Frames 0, stride, 2 stride, ... (None where one cannot be decoded), until
        ``MAX_CONSECUTIVE_VIDEO_FAILURES`` reads in a row fail."""
        cap, first, leading = open_video(path)
        try:
            index, position, failures = 0, leading + 1, 0  # position: next frame decoded
            while failures < MAX_CONSECUTIVE_VIDEO_FAILURES:
                if index <= leading:
                    frame = first if index == leading else None
                else:
                    with quiet_native_stderr():
                        for _ in range(index - position):
                            cap.grab()
                        ok, frame = cap.read()
                    frame, position = (frame if ok else None), index + 1
                failures = failures + 1 if frame is None else 0
                yield to_grey(frame)
                index += stride
        finally:
            cap.release()

    def pairs() -> Iterator[tuple[str, View, View]]:
        n = 0
        for k, (a, b) in enumerate(zip(frames(left), frames(right), strict=False)):
            if n >= total or (count > 0 and k * stride >= count):
                break
            yield f"frame_{k * stride:06d}", a, b
            n += 1

    return total, pairs()


def _bag_pairs(
    path: Path, topics: tuple[str, str], cfg: StereoConfig, notes: list[str]
) -> tuple[int, Iterator[tuple[str, View, View]]]:
    """Pairs of a bag's two image topics by header stamp (within ``pair_tolerance_ms``), at
    most ``video_max_frames``, evenly spaced. Each topic is read once; only the messages of
    the chosen pairs are decoded and kept (grey)."""
    with Bag(path) as bag:
        for t in topics:
            bag.topic(t, ("image",))
        stamps = [np.array(bag.stamps(t), dtype=np.int64) for t in topics]
    tol = round(cfg.pair_tolerance_ms * 1e6)
    order = np.argsort(stamps[1], kind="stable")
    right_sorted = stamps[1][order]
    best: dict[int, tuple[int, int]] = {}  # right index -> (|dt|, left index)
    for i, s in enumerate(stamps[0]):
        j = nearest_in_time(right_sorted, int(s), tol)
        if j is None:
            continue
        dt = abs(int(right_sorted[j]) - int(s))
        r = int(order[j])
        if r not in best or dt < best[r][0]:
            best[r] = (dt, i)
    matched = sorted((i, r) for r, (_, i) in best.items())
    if not matched:
        raise DockError(
            f"bag {path.name}: no message of {topics[0]} has one of {topics[1]} within "
            f"{cfg.pair_tolerance_ms:g} ms ({len(stamps[0])} and {len(stamps[1])} messages; "
            "raise pair_tolerance_ms)"
        )
    unmatched = len(stamps[0]) + len(stamps[1]) - 2 * len(matched)
    if unmatched:
        notes.append(
            f"{unmatched} of {len(stamps[0]) + len(stamps[1])} messages have no partner within "
            f"{cfg.pair_tolerance_ms:g} ms: skipped"
        )
    max_frames = cfg.intrinsics.video_max_frames
    stride = max(1, math.ceil(len(matched) / max_frames))
    chosen = matched[::stride][:max_frames]

    def pairs() -> Iterator[tuple[str, View, View]]:
        wanted = [{i for i, _ in chosen}, {r for _, r in chosen}]
        images: list[dict[int, View]] = [{}, {}]
        with Bag(path) as bag:
            for side in (0, 1):
                for k, (_, img) in enumerate(bag.images(topics[side])):
                    if k in wanted[side]:
                        images[side][k] = to_grey(img)
        for i, r in chosen:
            yield f"msg_{i:06d}", images[0].pop(i, None), images[1].pop(r, None)

    return len(chosen), pairs()


def stereo_pairs(
    left: Path,
    right: Path | None,
    topics: tuple[str | None, str | None],
    cfg: StereoConfig,
    notes: list[str],
) -> tuple[int, Iterator[tuple[str, View, View]]]:
    """The pairs of views of a stereo calibration's inputs.

    Args:
        left: the left camera's image folder or video, or a bag holding both cameras.
        right: the right camera's folder or video; None for a bag.
        topics: a bag's (left, right) image topics; (None, None) otherwise.
        cfg: ``pair_tolerance_ms``, ``skip_unpaired`` and ``intrinsics.video_max_frames``.
        notes: remarks for the user are appended here (pairs skipped).

    Returns:
        (pairs expected, iterator of (name, left grey uint8 or None, right grey or None)).

    Raises:
        DockError: one line: missing inputs, special files (FIFO, device), inputs of two
            kinds, unpaired images (unless ``skip_unpaired``), no pair within the stamp
            tolerance, bag topics not named.
    """
    for p in (left, right):  # a FIFO or device would block the reader: refused first
        if p is not None and p.exists() and not p.is_dir():
            check_regular_file(p, "input")
    if left.exists() and is_bag(left):
        if right is not None:
            raise DockError(f"{left} is a bag: give it alone, with --left-topic and --right-topic")
        if topics[0] is None or topics[1] is None:
            with Bag(left) as bag:
                images = [t.name for t in bag.topics() if t.kind == "image"]
            raise DockError(
                f"{left} is a bag: name its two image topics with --left-topic and "
                f"--right-topic (image topics: {', '.join(images) or 'none'})"
            )
        if topics[0] == topics[1]:
            raise DockError(f"--left-topic and --right-topic are the same topic {topics[0]!r}")
        return _bag_pairs(left, (topics[0], topics[1]), cfg, notes)
    if topics != (None, None):
        raise DockError(f"--left-topic and --right-topic are for a bag; {left} is not one")
    if right is None:
        raise DockError(f"give the right camera's input after {left} (or one bag with two topics)")
    for p in (left, right):
        if not p.exists():
            raise DockError(f"input not found: {p}")
    if left.is_dir() != right.is_dir():
        raise DockError(f"{left} and {right}: give two image folders or two videos")
    if left.resolve() == right.resolve():
        raise DockError(f"the left and right inputs are the same: {left}")
    if left.is_dir():
        return _folder_pairs(left, right, cfg.skip_unpaired, notes)
    return _video_pairs(left, right, cfg, notes)
