"""OpenCV ArUco / AprilTag dictionaries by name, and marker bitmaps as cell grids."""

from __future__ import annotations

from collections.abc import Iterable
from functools import cache

import cv2
import numpy as np

from uwdock.dockcore.errors import DockError

#: Every predefined dictionary OpenCV offers, by its ``cv2.aruco`` constant name.
DICTIONARY_NAMES: tuple[str, ...] = tuple(
    sorted(name for name in dir(cv2.aruco) if name.startswith("DICT_"))
)


def normalise_dictionary_name(name: str) -> str:
    """Accept ``DICT_4X4_50``, ``4x4_50`` or ``dict_apriltag_36h11``; return the canonical name."""
    key = name.strip().upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    canonical = {n.upper(): n for n in DICTIONARY_NAMES}.get(key)
    if canonical is None:
        raise DockError(
            f"unknown marker dictionary {name!r} (try one of: "
            f"DICT_4X4_50, DICT_5X5_100, DICT_ARUCO_ORIGINAL, DICT_APRILTAG_36h11; "
            f"`markers dictionaries` lists all)"
        )
    return canonical


@cache
def get_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The OpenCV dictionary called ``name`` (see :func:`normalise_dictionary_name`)."""
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, normalise_dictionary_name(name)))


def dictionary_size(name: str) -> int:
    """Number of markers (valid IDs are ``0 .. size-1``) in dictionary ``name``."""
    return int(get_dictionary(name).bytesList.shape[0])


def bits_per_side(name: str) -> int:
    """Data bits per marker side (4 for ``DICT_4X4_*``), without the border."""
    return int(get_dictionary(name).markerSize)


def check_ids(name: str, ids: Iterable[int]) -> tuple[int, ...]:
    """Validate marker IDs for dictionary ``name``: in range and without duplicates.

    Raises:
        DockError: one line naming the first bad ID.
    """
    ids = tuple(int(i) for i in ids)
    if not ids:
        raise DockError("no marker IDs given")
    n = dictionary_size(name)
    for i in ids:
        if not 0 <= i < n:
            raise DockError(f"marker ID {i} is outside dictionary {name} (valid IDs: 0..{n - 1})")
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise DockError(f"marker ID {dup[0]} is listed more than once")
    return ids


def marker_cells(name: str, marker_id: int) -> np.ndarray:
    """The flat tag as a cell grid.

    Returns:
        (n+2, n+2) bool array, ``True`` = black cell, row 0 at the top of the tag, including the
        one-cell black border (n = :func:`bits_per_side`).
    """
    check_ids(name, [marker_id])
    n = bits_per_side(name) + 2
    img = cv2.aruco.generateImageMarker(get_dictionary(name), int(marker_id), n)
    return img < 128
