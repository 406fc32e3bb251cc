"""Second-chance decoding of the quads ArUco found but could not read.

ArUco decodes a candidate quad by Otsu-thresholding its warped pixels: one threshold for the
whole marker. Under a lamp the 3DBM's insert is shaded (one side of the marker 20-40 grey
levels brighter than the other, more than the contrast between its cells), and Otsu splits
the marker along the shading instead of along its cells. ArUco then returns the quad among its
*rejected* candidates. On rendered clear-tank frames (``bench/bench_degradations.py``) 7 of the
8 markers that ``default`` missed were there, at sub-pixel distance from the truth.

:class:`QuadReader` reads such a quad again:

1. warp it to the marker's cell grid (``marker_bits`` + 2 border cells a side) and take the
   mean grey level of each cell's centre (a ``margin`` of each cell left out);
2. remove the shading: the border cells are all one colour, so a plane fitted to their means
   (least squares, ``a + b col + c row``) is the illumination; subtract it;
3. try every split of the cell means that puts the whole border on one side (dark border: a
   normal marker; bright border: the photometric negative, the 3DBM seen as it is), keeping
   splits whose gap is at least ``min_gap`` of the cells' range;
4. look each split's inner bits up in the dictionary with no bit errors allowed (a table of
   every allowed code in its four rotations, built once per reader).

A quad is accepted when exactly one allow-listed ID in one rotation comes out of all its splits
(two mean the split, not the marker, decided), when it is no more oblique than
``max_side_ratio`` (longest over shortest side), and never for codes simpler than
``min_transitions`` (one compact blob). False IDs on the frames of
``bench/bench_degradations.py`` (15 conditions, 24-40 frames each): none with the five-ID DS
allow-list; with all 50 IDs of ``DICT_4X4_50`` allowed, one before the last two rules (ID 17,
a 2x2 square, from a 39 x 23 px block of JPEG q40 artefacts), none with them.
"""

from __future__ import annotations

from collections.abc import Collection

import cv2
import numpy as np

__all__ = ["CELL_PX", "QuadReader", "quad_orientation"]

#: Pixels per cell in the warped marker (ArUco's ``perspectiveRemovePixelPerCell`` of default).
CELL_PX = 8


def quad_orientation(quad: np.ndarray) -> float:
    """Signed area (px^2) of a (4, 2) quad in pixel coordinates (x right, y down): positive for
    OpenCV's marker corner order TL, TR, BR, BL (clockwise on screen)."""
    return float(cv2.contourArea(np.asarray(quad, np.float32).reshape(-1, 1, 2), oriented=True))


class QuadReader:
    """Reads candidate quads of one dictionary by splits of their shading-corrected cell means.

    Args:
        dictionary: the ArUco dictionary (its ``markerSize``; one border cell a side).
        allowed: IDs that may be reported (None: every ID of the dictionary).
        margin: fraction of each cell's side left out on every side when averaging (-).
        min_gap: smallest gap between the split's two sides, as a fraction of the cells' range.
        min_range: smallest range of the corrected cell means, grey levels (a flat quad holds
            no code).
        max_side_ratio: longest over shortest side of a quad read again (-); more oblique
            quads keep ArUco's verdict.
        min_transitions: codes with fewer cell-edge transitions (neighbouring cells of
            different colour, border included) are never read here. A code that is one compact
            blob is what texture and compression blocks draw most often: ``DICT_4X4_50``'s ID
            17, a 2x2 white square (8 transitions; the next-simplest have 14), came out of 1 in
            ~2,000 random quads on block images, every false read of the tests. ArUco's own
            read still decodes such codes.
    """

    def __init__(
        self,
        dictionary: cv2.aruco.Dictionary,
        allowed: Collection[int] | None = None,
        margin: float = 0.25,
        min_gap: float = 0.15,
        min_range: float = 4.0,
        max_side_ratio: float = 1.6,
        min_transitions: int = 12,
    ) -> None:
        bits = int(dictionary.markerSize)
        self.n = n = bits + 2
        self.side_px = n * CELL_PX
        self.margin_px = round(margin * CELL_PX)
        self.min_gap, self.min_range, self.max_side_ratio = min_gap, min_range, max_side_ratio
        self._dst = np.array(
            [[0, 0], [self.side_px, 0], [self.side_px, self.side_px], [0, self.side_px]],
            np.float32,
        )
        self._border = np.ones((n, n), bool)
        self._border[1:-1, 1:-1] = False
        rows, cols = np.mgrid[0:n, 0:n]
        self._cols, self._rows = cols.astype(np.float32), rows.astype(np.float32)
        design = np.stack(
            [np.ones(int(self._border.sum())), cols[self._border], rows[self._border]], axis=1
        )
        self._plane = np.linalg.pinv(design).astype(np.float32)  # border means -> a, b, c
        self._weights_flat = 1 << np.arange(bits * bits, dtype=np.int64)
        self._weights = self._weights_flat.reshape(bits, bits)
        ids = range(len(dictionary.bytesList)) if allowed is None else sorted(set(allowed))
        self._codes: dict[int, tuple[int, int]] = {}
        for marker_id in ids:
            canonical = dictionary.getBitsFromByteList(
                dictionary.bytesList[int(marker_id)].reshape(1, -1, 4), bits
            )
            framed = np.zeros((n, n), np.int8)
            framed[1:-1, 1:-1] = canonical
            transitions = int(np.count_nonzero(np.diff(framed, axis=0))) + int(
                np.count_nonzero(np.diff(framed, axis=1))
            )
            if transitions < min_transitions:
                continue
            for k in range(4):
                rotated = np.ascontiguousarray(np.rot90(canonical, k)).astype(np.uint8)
                ok, idx, rotation = dictionary.identify(rotated, 0.0)
                if ok and int(idx) == int(marker_id):  # OpenCV's own rotation convention
                    self._codes[int((rotated.astype(np.int64) * self._weights).sum())] = (
                        int(idx),
                        int(rotation),
                    )

    def read(self, grey: np.ndarray, quad: np.ndarray) -> tuple[int, np.ndarray] | None:
        """Decode one candidate quad.

        Args:
            grey: (H, W) uint8 image the quad was found in.
            quad: (4, 2) corner pixels in any cyclic order, either orientation.

        Returns:
            (marker ID, (4, 2) float64 corners TL, TR, BR, BL as OpenCV orders them), or None.
        """
        q = np.asarray(quad, np.float32).reshape(4, 2)
        d = q - q[[1, 2, 3, 0]]
        sides_sq = (d * d).sum(axis=1)
        if sides_sq.min() * self.max_side_ratio**2 < sides_sq.max():
            return None
        if quad_orientation(q) < 0:
            q = q[::-1].copy()
        n, c, m = self.n, CELL_PX, self.margin_px
        warped = cv2.warpPerspective(
            grey,
            cv2.getPerspectiveTransform(q, self._dst),
            (self.side_px, self.side_px),
            flags=cv2.INTER_LINEAR,
        )
        cells = warped.reshape(n, c, n, c)[:, m : c - m, :, m : c - m].mean(axis=(1, 3))
        _, slope_col, slope_row = self._plane @ cells[self._border].astype(np.float32)
        cells = cells - (slope_col * self._cols + slope_row * self._rows)
        spread = float(cells.max() - cells.min())
        if spread < self.min_range:
            return None
        found: set[tuple[int, int]] = set()
        for sign in (1.0, -1.0):  # dark border (normal marker), bright border (negative)
            inner = sign * cells[1:-1, 1:-1].ravel()
            edge = float((sign * cells[self._border]).max())
            above = np.sort(inner[inner > edge])
            below = np.concatenate(([edge], above[:-1]))  # each split: (below, above) values
            keep = above - below >= self.min_gap * spread
            if not keep.any():
                continue
            split = 0.5 * (above[keep] + below[keep])
            keys = (inner[None, :] > split[:, None]) @ self._weights_flat
            for key in keys.tolist():
                if key in self._codes:
                    found.add(self._codes[key])
        if len(found) != 1:  # no ID, or the split decided it (two IDs, or two rotations)
            return None
        marker_id, rotation = found.pop()
        return marker_id, np.roll(q, rotation, axis=0).astype(np.float64)
