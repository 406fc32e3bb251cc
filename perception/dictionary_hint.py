"""A wrong marker dictionary, said in one line: when no frame of an input holds a marker of the
configured dictionary, a few frames are tried with the other common ArUco / AprilTag
dictionaries (plain OpenCV detection, normal and inverted tags, so 3D Binary Markers count),
and the warning names the one that finds markers, or says that none does.

Used by ``perception eval`` and ``perception detect`` (:mod:`perception.evaluate`), which keep a
few decoded frames spread over the input (:class:`FrameSampler`) for it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import cv2
import numpy as np

from uwdock.markers.dictionary import DICTIONARY_NAMES, get_dictionary
from uwdock.perception.preprocess import as_uint8, to_grey

__all__ = ["CANDIDATES", "FrameSampler", "dictionary_warning", "family"]

#: The dictionaries tried, one per family, each the largest of its family (a 4x4 tag of any
#: ``DICT_4X4_*`` is a ``DICT_4X4_1000`` tag). AprilTag 16h5 is left out: it finds tags in noise.
CANDIDATES: tuple[str, ...] = (
    "DICT_4X4_1000",
    "DICT_5X5_1000",
    "DICT_6X6_1000",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
    "DICT_APRILTAG_25h9",
    "DICT_APRILTAG_36h11",
    "DICT_ARUCO_MIP_36h12",
)
#: Frames kept for the hint (spread over the input).
SAMPLE_FRAMES = 5
#: Longest image side the hint detects on (px): larger frames are reduced first (speed).
MAX_SIDE_PX = 1920


def family(name: str) -> str:
    """A dictionary's family: its name without the trailing size (``DICT_4X4_50`` ->
    ``DICT_4X4``); AprilTag and ArUco-original names are their own family."""
    return re.sub(r"_(\d+)$", "", name).upper()


class FrameSampler:
    """Keep at most ``cap`` frames spread evenly over a stream of unknown length: every
    ``stride``-th frame offered is kept, and when the buffer overflows every other kept frame
    is dropped and the stride doubles."""

    def __init__(self, cap: int = SAMPLE_FRAMES) -> None:
        self.cap = cap
        self.stride = 1
        self.offered = 0
        self.frames: list[np.ndarray] = []

    def offer(self, image: np.ndarray) -> None:
        """Offer the next decoded frame (BGR or grey; uint8, uint16 or float)."""
        if self.offered % self.stride == 0:
            self.frames.append(image)
            if len(self.frames) > self.cap:
                self.frames = self.frames[::2]
                self.stride *= 2
        self.offered += 1


def _smallest_of_family(name: str, ids: set[int]) -> str:
    """The smallest dictionary of ``name``'s family that holds every ID in ``ids``."""
    fam = family(name)
    sized = []
    for cand in DICTIONARY_NAMES:
        if family(cand) == fam and cand.upper() != fam:
            sized.append((int(cand.rsplit("_", 1)[1]), cand))
    for size, cand in sorted(sized):
        if max(ids) < size:
            return cand
    return name


def _detect_ids(name: str, frames: list[np.ndarray]) -> tuple[int, set[int]]:
    """(frames with at least one marker, IDs found) of dictionary ``name`` on ``frames``."""
    params = cv2.aruco.DetectorParameters()
    params.detectInvertedMarker = True  # 3D Binary Markers are the tag's photometric negative
    detector = cv2.aruco.ArucoDetector(get_dictionary(name), params)
    hits, ids = 0, set()
    for img in frames:
        grey = to_grey(as_uint8(img))  # a 16-bit or float frame as the detector sees it
        side = max(grey.shape)
        if side > MAX_SIDE_PX:
            scale = MAX_SIDE_PX / side
            grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        _, found, _ = detector.detectMarkers(grey)
        if found is not None and len(found):
            hits += 1
            ids.update(int(i) for i in np.asarray(found).ravel())
    return hits, ids


def _shown(ids: set[int] | Sequence[int]) -> str:
    ids = sorted(ids)
    return ", ".join(str(i) for i in ids[:10]) + (", ..." if len(ids) > 10 else "")


def _other_ids_warning(
    dictionary: str, ids: Sequence[int], frames: list[np.ndarray], n_frames: int
) -> str | None:
    """The warning for a marker set whose dictionary is the frames' but whose IDs are not the
    ones in view (the detector looks for the set's IDs only), or None when the frames show no
    marker of the set's dictionary family with another ID."""
    fam = [c for c in CANDIDATES if family(c) == family(dictionary)]
    hits, found = _detect_ids(fam[0] if fam else dictionary, frames)
    others = found - set(ids)
    if not others:
        return None
    name = _smallest_of_family(dictionary, found) if fam else dictionary
    return (
        f"warning: no marker of the marker set ({dictionary}, {len(ids)} ID(s): {_shown(ids)}) "
        f"found in {n_frames} frame(s), but {name} markers with IDs the set does not list are "
        f"in view (IDs {_shown(others)}) in {hits} of {len(frames)} sampled frame(s): only the "
        f"set's IDs are looked for; use a marker set that lists the markers in view (or "
        f"--dictionary {name} for single markers)"
    )


def dictionary_warning(
    dictionary: str, frames: list[np.ndarray], n_frames: int, ids: Sequence[int] | None = None
) -> str:
    """The one-line warning for an input where no frame held a marker of ``dictionary`` (of
    the marker set's ``ids``, when given).

    Args:
        dictionary: the configured dictionary (canonical name).
        frames: a few decoded frames of the input (:class:`FrameSampler`).
        n_frames: decoded frames of the input (for the message).
        ids: the marker set's IDs (the detector looks for these only), or None (single
            markers: any ID).

    Returns:
        ``"warning: ..."``: with ``ids``, first whether markers of the set's dictionary with
        other IDs are in view (the set does not list the markers the frames show); else the
        other dictionary that finds the most markers on ``frames`` (the smallest of its family
        holding the IDs found) and what to pass, or that none of :data:`CANDIDATES` finds any.
    """
    if ids:
        other = _other_ids_warning(dictionary, ids, frames, n_frames)
        if other is not None:
            return other
    what = f"{dictionary}" if not ids else f"the marker set ({dictionary}, IDs {_shown(ids)})"
    lead = f"warning: no marker of {what} found in {n_frames} frame(s)"
    best: tuple[int, int, str, set[int]] | None = None
    for cand in CANDIDATES:
        if family(cand) == family(dictionary):
            continue
        hits, cand_ids = _detect_ids(cand, frames)
        if hits and (best is None or (hits, len(cand_ids)) > best[:2]):
            best = (hits, len(cand_ids), cand, cand_ids)
    if best is None:
        tried = ", ".join(
            re.sub(r"_(\d+)$", "", c) for c in CANDIDATES if family(c) != family(dictionary)
        )
        return (
            f"{lead}, and none with the other common dictionaries ({tried}) on "
            f"{len(frames)} sampled frame(s): check the camera, exposure, focus and that "
            "markers are in view"
        )
    hits, _, cand, found = best
    name = _smallest_of_family(cand, found)
    return (
        f"{lead}; {name} finds markers (IDs {_shown(found)}) in {hits} of {len(frames)} sampled "
        f"frame(s): pass --dictionary {name} or a marker set of that dictionary"
    )
