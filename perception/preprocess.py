"""Named preprocessing pipelines: camera image -> grey candidate images for the ArUco detector.

A pipeline is a callable ``pipeline(image) -> list[np.ndarray]``: it takes a BGR, BGRA or grey
image (uint8, uint16, or float in [0, 1]) and returns one or more uint8 grey images of the same
size. The detector runs ArUco on each candidate and merges the results (see
:mod:`perception.detector`). Several candidates stand for several polarities or thresholds.

Each pipeline also carries the ArUco ``DetectorParameters`` it was designed or tuned with
(``aruco_preset``) and how results from several candidates are merged (``merge``):

* ``default`` (2-5 ms at 968x732 for its own pass; OpenCV's pass on top): noise-aware
  contrast stretch (noise floor from JPEG blocking; 3x3 median on impulse noise) + Gaussian
  (3x3 up to 1280 px wide, scaled with the width above), one candidate (a second when an
  outlier widens the range); ArUco decodes both polarities itself (``detectInvertedMarker``),
  one 23 px threshold window, sub-pixel corners;
  the quads ArUco rejects are read again by shading-corrected cell splits
  (:mod:`perception.rescue`). Plus OpenCV's own detector with its default parameters on the
  plain grey image (``opencv_pass``), whose IDs come first: ``default`` decodes every flat tag
  plain OpenCV decodes (on real footage the stretch, blur and single window lose small tags
  and tags whose margin a rope crosses), at about OpenCV's own time more
  (``bench/bench_real.py``). On a block-compressed frame (JPEG, intra-coded video:
  :func:`block_grid_fraction`), two more views (:class:`CompressedViews`): the candidate
  inverted and the brightest channel inverted, each with its own threshold window; an
  uncompressed frame never runs them.
* ``reference_3dbm`` (5-8 ms): the published 3DBM pipeline (the authors' detector, its "CLAHE
  method"): min-max normalise, grey (RGB2GRAY on the BGR frame, as published), CLAHE (clip 2.0,
  32x32 tiles), float inverted rescale to [-127, 127], 3x3 binomial filter, + 127.5, clip to
  [1, 254], uint8; OpenCV's default ArUco parameters.
* ``threshold_sweep`` (35-120 ms): the published "iterative threshold method": inverse binary
  thresholds 90..185 step 5 of the same normalised grey, each smoothed by a 3x3 box filter; keep
  the threshold with the most detections.
* ``normalise_invert`` (2-6 ms): the published "normalization method": the same grey, inverted
  rescale, clip to [1, 254].
* ``plain`` (2-5 ms): grey only (flat printed tags).

(ms: median per 968x732 frame on one core, ``cv2.setNumThreads(1)``, synthetic 3DBM views with
6 markers, contrast 8-255 grey levels, noise 1-2.5 levels.)

Polarity: ``default`` decodes the 3DBM (a photometric negative) and flat printed tags alike.
The published pipelines keep OpenCV's default parameters, as published: they decode the polarity
they were designed for (the three 3DBM pipelines invert the image; ``plain`` expects flat tags).
``DetectorConfig(detect_inverted=True)`` makes any of them decode the other polarity too, at a
price: with ``detectInvertedMarker`` OpenCV keeps the *smallest* of nested contours, which biases
the corners of normal-polarity markers by ~3 px (measured, 25-110 px markers; sub-pixel
refinement removes most of it, not all). ``default`` never sees that case for the 3DBM (its image is
not inverted, so the smallest contour is the tag's outer edge).

Why ``default`` looks like this (measured on synthetic 968x732 3DBM views, 22-110 px markers,
green cast, blur, sensor noise 1-2.5 grey levels, contrast 8-255 grey levels):

* ArUco's cost is dominated by contour tracing of the thresholded image; in turbid, noisy
  frames most contours are noise speckles, and their number depends only on the adaptive
  threshold constant relative to the noise. Min-max normalisation (the reference) amplifies
  noise together with the signal, so a fixed constant either loses low-contrast markers or
  drowns in speckles (25-40 ms per frame). ``default`` therefore limits its contrast gain so
  that the noise (estimated robustly from second differences, ~0.1 ms) is at most
  ``noise_target`` grey levels: the ArUco constant 7 then sits at a fixed multiple of the noise.
* A single 23 px adaptive-threshold window finds about as many markers as OpenCV's three
  windows (3, 13, 23) at a third of the cost; the 3 px window finds only noise at low contrast.
* ``perspectiveRemovePixelPerCell`` 8 and ``perspectiveRemoveIgnoredMarginPerCell`` 0.3 decode
  blurred markers near the 20-26 px size limit that the defaults (4, 0.13) miss.
* No inversion: ``detectInvertedMarker`` decodes the negative from the same contours, so the
  3DBM and flat tags share one candidate image.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import scale_to_uint8

__all__ = [
    "MIN_IMAGE_PX",
    "PIPELINES",
    "CompressedViews",
    "NoiseAwareStretch",
    "Pipeline",
    "as_uint8",
    "block_grid_fraction",
    "brightest_channel",
    "estimate_blocking",
    "estimate_noise_sigma",
    "get_pipeline",
    "impulse_fraction",
    "published_grey",
    "to_grey",
]


#: Smallest image side (px) the detector accepts: a smaller image cannot hold a marker.
MIN_IMAGE_PX = 8


# --------------------------------------------------------------------------- input handling


def as_uint8(image: Any) -> np.ndarray:
    """Validate a camera image and return it as uint8 (grey or BGR, contiguous).

    Args:
        image: (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA array; uint8, uint16
            (scaled by 1/257), float in [0, 1] (scaled by 255) or float of another range
            (by its range; NaN as 0: :func:`dockcore.media.scale_to_uint8`).

    Returns:
        (H, W) or (H, W, 3) uint8 array (alpha dropped; a single channel squeezed).

    Raises:
        DockError: None, not an array, empty, wrong shape, or an unsupported dtype.
    """
    if image is None:
        raise DockError("no image given (got None)")
    if not isinstance(image, np.ndarray):
        raise DockError(f"image must be a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise DockError(f"image is empty (shape {image.shape})")
    if image.ndim == 3 and image.shape[2] in (1, 3, 4):
        if image.shape[2] == 1:
            image = image[:, :, 0]
        elif image.shape[2] == 4:
            image = image[:, :, :3]
    elif image.ndim != 2:
        raise DockError(f"image must be (H, W), (H, W, 3) or (H, W, 4), got shape {image.shape}")
    if image.shape[0] < MIN_IMAGE_PX or image.shape[1] < MIN_IMAGE_PX:
        raise DockError(f"image is too small to hold a marker (shape {image.shape})")
    if image.dtype not in (np.uint8, np.uint16) and not np.issubdtype(image.dtype, np.floating):
        raise DockError(f"unsupported image dtype {image.dtype} (use uint8, uint16 or float)")
    return np.ascontiguousarray(scale_to_uint8(image))


def to_grey(image: np.ndarray) -> np.ndarray:
    """Grey (H, W) uint8 from a grey or BGR uint8 image (OpenCV's BT.601 luma weights)."""
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _minmax(image: np.ndarray) -> np.ndarray:
    """Min-max normalise to 0..255 (all channels together, as ``cv2.normalize`` does)."""
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)


# --------------------------------------------------------------------------- statistics


def estimate_noise_sigma(grey: np.ndarray, row_step: int = 8) -> float:
    """Robust estimate of the white-noise standard deviation of a grey image (grey levels).

    Median of the absolute horizontal second difference ``I[x-1] - 2 I[x] + I[x+1]`` on every
    ``row_step``-th row, divided by 0.6745 * sqrt(6). Smooth shading cancels, edges are outliers
    the median ignores. Costs ~0.1 ms on a 968x732 frame.

    Args:
        grey: (H, W) uint8 image.
        row_step: use every ``row_step``-th row.

    Returns:
        Estimated sigma in grey levels (0 for a noise-free synthetic image).
    """
    rows = np.ascontiguousarray(grey[::row_step])
    d2 = cv2.convertScaleAbs(cv2.Sobel(rows, cv2.CV_16S, 2, 0, ksize=1))
    hist = cv2.calcHist([d2[:, 1:-1]], [0], None, [256], [0, 256]).ravel()
    cum = np.cumsum(hist)
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half))
    if k == 0:  # most second differences vanish: no measurable noise
        return 0.0
    # linear interpolation inside the bin: integer |d2| = k stands for [k - 0.5, k + 0.5)
    median = k - 0.5 + (half - float(cum[k - 1])) / max(float(hist[k]), 1.0)
    return float(median / (0.6745 * np.sqrt(6.0)))


def estimate_blocking(grey: np.ndarray, block_px: int = 8, row_step: int = 8) -> float:
    """Strength of block-compression artefacts (JPEG, intra-coded video) in grey levels.

    Mean absolute horizontal step across the ``block_px`` grid's column boundaries minus the
    mean step elsewhere, on every ``row_step``-th row. Image content falls on both kinds of
    columns alike and cancels; the steps between independently quantised blocks add to the
    boundary columns only. Block compression flattens the inside of each block, so
    :func:`estimate_noise_sigma` reads ~0 there while the block steps, a grey level or two,
    are what an adaptive threshold then traces. Measured on the 968x732 views of
    ``bench/bench_degradations.py``: 0.35-1.66 (median 0.96) at JPEG quality 20; <= 0.03 on
    uncompressed views, blurred or not, and <= 0.11 on rendered water (never negative: clipped
    at 0). ~0.07 ms at 1920x1080.
    """
    rows = np.ascontiguousarray(grey[::row_step])
    steps = cv2.absdiff(rows[:, 1:], rows[:, :-1])  # |I[x+1] - I[x]|, column x
    per_column = cv2.reduce(steps, 0, cv2.REDUCE_AVG, dtype=cv2.CV_32F).ravel()
    on_grid = (np.arange(per_column.size) + 1) % block_px == 0
    if not on_grid.any() or on_grid.all():
        return 0.0
    return max(float(per_column[on_grid].mean()) - float(per_column[~on_grid].mean()), 0.0)


def block_grid_fraction(grey: np.ndarray, block_px: int = 8) -> float:
    """Evidence of block-transform compression (JPEG, intra-coded video) at any grid offset, as
    a fraction (-): 0 on an image that was never block-coded.

    A step between two neighbouring pixels is a *peak* when it is larger than both steps beside
    it (``|I[x+1] - I[x]|`` against those at ``x - 1`` and ``x + 1``). Block coding flattens
    each block and puts its quantisation error at the block edges, so peaks pile up on one
    phase of the ``block_px`` grid; content puts them on every phase alike. Per column, the
    fraction of rows (every odd ``step``-th: a diagonal edge does not alias onto one phase)
    with a peak there; per phase, the median over the grid's columns (a long straight edge
    fills one column, which the median ignores); the strongest phase's median minus the mean of
    the others' medians. Computed across columns and across rows; the smaller of the two is
    returned (compression marks both, a structure seldom does). Unlike
    :func:`estimate_blocking`, it finds the grid of a cropped or shifted JPEG too, and it reads
    how often, not how much, so a textured view does not drown it.

    Measured on 603 rendered frames (``datasets synth``, 320-1920 px wide, every water preset,
    none, and random water without JPEG): <= 0.013 as rendered; after OpenCV's JPEG at quality
    95 0.002-0.12 (median 0.04), 85 0.022-0.27 (0.20), 25 0.040-0.51 (0.16), 15 0.014-0.34
    (0.11: 1.5 % of the frames under 0.03, their blocks so flat that block edges step by 0).
    On the shared real frames: 0.07 on the sea photo of the docking station (a crop of a JPEG
    figure, its grid off by 4 px), 0.05-0.10 on the 1080p tank frames (PNG from compressed
    video), 0.09-0.38 on the tank JPEG photos, 0.006-0.044 on the small video crops. ~0.5 ms at
    968x732, ~1.2 ms at 1920x1080.

    Args:
        grey: (H, W) uint8 image.
        block_px: the block side of the coding (px).

    Returns:
        The excess fraction of peaks on the strongest phase, >= 0 (0 for images smaller than
        four blocks a side).
    """
    if min(grey.shape) < 4 * block_px:
        return 0.0
    return max(min(_grid_excess(grey, block_px, 0), _grid_excess(grey, block_px, 1)), 0.0)


def _grid_excess(grey: np.ndarray, block_px: int, axis: int) -> float:
    """:func:`block_grid_fraction` in one direction: steps along rows (``axis`` 0: across
    columns) or along columns (1)."""
    n_lines = grey.shape[axis]
    step = 2 * (n_lines // 540) + 1  # odd: 1 up to 539 lines, 3 at 1080, ...
    if axis == 0:
        lines = grey[::step] if step > 1 else grey
    else:
        lines = cv2.transpose(np.ascontiguousarray(grey[:, ::step]))
    s = cv2.absdiff(lines[:, 1:], lines[:, :-1])  # s[:, x] = |I[x + 1] - I[x]|
    mid = s[:, 1:-1]
    peak = cv2.bitwise_and(
        cv2.compare(mid, s[:, :-2], cv2.CMP_GT), cv2.compare(mid, s[:, 2:], cv2.CMP_GT)
    )
    per_column = cv2.reduce(peak, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
    n = (per_column.size // block_px) * block_px
    phases = np.median(per_column[:n].reshape(-1, block_px), axis=0) / (255.0 * len(lines))
    top = float(phases.max())
    return top - (float(phases.sum()) - top) / (block_px - 1)


def brightest_channel(image: np.ndarray) -> np.ndarray:
    """Per pixel the largest of B, G and R ((H, W) uint8; a grey image is returned as it is)."""
    if image.ndim == 2:
        return image
    b, g, r = cv2.split(image)
    return cv2.max(cv2.max(b, g), r)


def _percentiles(grey: np.ndarray, clip_fraction: float) -> tuple[int, int, int]:
    """Grey levels below which ``clip_fraction`` and above which ``clip_fraction`` of a 1/16
    pixel sample lie (a robust min and max), and its median, from one histogram."""
    sample = np.ascontiguousarray(grey[::4, ::4])
    cum = np.cumsum(cv2.calcHist([sample], [0], None, [256], [0, 256]).ravel())
    lo, hi, median = (
        int(v)
        for v in np.searchsorted(cum, cum[-1] * np.array([clip_fraction, 1.0 - clip_fraction, 0.5]))
    )
    return lo, max(hi, lo + 1), median


# --------------------------------------------------------------------------- pipelines


#: 3x3 ring (the 8 neighbours without the centre) for the impulse-noise test.
_RING_3X3 = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8)


def impulse_fraction(grey: np.ndarray, levels: float, step: int = 4) -> float:
    """Fraction of isolated extreme pixels (impulse, "salt and pepper" noise) in a grey image.

    On every ``step``-th row and column, a pixel counts when it is brighter than all 8 of its
    neighbours (in the subsample) by more than ``levels``, or darker than all by more. Edges,
    corners and marker cells are not isolated at that spacing, impulse noise is. Measured
    (``step`` 4, 48 levels): <= 0.03 % on synthetic DS views at full contrast, 640-1920 px, 0.6-3.5
    m; up to 0.10 % on rendered clear-tank frames at 480 px (lit particles), 0 in turbid water;
    0.8-1.0 % with 1 % salt; 3.2-3.5 % with 5 %. Costs ~0.05 ms at 968x732.
    """
    s = np.ascontiguousarray(grey[::step, ::step])
    t = int(min(max(levels, 0), 254))
    bright = cv2.subtract(s, cv2.dilate(s, _RING_3X3)) > t
    dark = cv2.subtract(cv2.erode(s, _RING_3X3), s) > t
    return float(np.count_nonzero(bright | dark)) / s.size


@dataclass(frozen=True)
class NoiseAwareStretch:
    """The ``default`` pipeline: grey, (3x3 median on impulse noise), noise-limited contrast
    stretch, 3x3 Gaussian.

    gain = min(255 / (p_hi - p_lo), noise_target / sigma), with p_lo, p_hi the robust min and max
    and sigma from :func:`estimate_noise_sigma`; the stretched image is centred on 128.

    Impulse noise: with 1 % of the pixels white (salt), the robust maximum lands on the salt, the
    gain collapses and the isolated white pixels break the markers' contours. When
    :func:`impulse_fraction` exceeds ``impulse_fraction``, a 3x3 median replaces the Gaussian and
    comes first (the statistics are then measured on the filtered image). Not always: a median
    rounds the markers' corners (mean corner error per marker up to 0.61 px, against 0.36 px
    with the Gaussian, on the detector tests' views). Measured on the same 24 synthetic 968x732
    views (``bench/bench_degradations.py``): recall with 1 % / 5 % salt 0.56 / 0.23 without the
    median, 1.00 / 1.00 with it.

    A second candidate when the range, not the noise, limits the gain: something dark or bright
    far from the markers' grey levels (a strut or a cable across the view, a lamp's hot spot, the
    vehicle's shadow) widens the robust range, and the markers get a fraction of the contrast the
    noise allows (a dark bar across the test views: range 15-124 grey levels against 110-124
    without it, gain 2.3 against 11.6). When the noise-limited gain is more than
    ``second_gain_ratio`` times the range-limited one, a second image is stretched by the
    noise-limited gain about the median grey level (the far extremes saturate); ArUco runs on
    both and the detections are merged. Only where the median sits lopsided in the range (an
    outlier on one side) or the range is under 128 grey levels: a full-contrast frame decodes
    as it is, and a second pass there doubled its time for nothing. Measured on the same 24
    views (``bench/bench_degradations.py``): recall under the bar 0.77 -> 0.81 and with 15 px
    motion blur 0.19 -> 0.27; 57 of 240 frames take the second pass (all 24 with the bar, none
    of the clean ones), and 4 of 18 full-contrast frames of ``bench/bench_perception.py``.

    Attributes:
        noise_target: largest noise standard deviation allowed after the stretch (grey levels);
            with ArUco's threshold constant 7 this fixes the speckle rate (cost) and the lowest
            decodable contrast. 12 measured best: 8 loses low-contrast markers, 16+ costs
            > 5 ms per noisy 968x732 frame.
        clip_fraction: fraction of pixels clipped at each end when measuring the range (-).
        blur_ksize: Gaussian kernel side (px, odd; 0 or 1 disables) for images up to
            ``blur_ref_width_px`` wide.
        blur_ref_width_px: wider images get a kernel scaled with their width (nearest odd
            side to ``blur_ksize * width / blur_ref_width_px``: 5 px at 1920, 9 px at 3840).
            Markers and the optics' blur span more pixels there, while the noise speckles
            that ArUco traces (its cost) stay one pixel wide. Measured on the 1920x1080 views
            of ``bench/bench_perception.py``: 12.5 ms -> 9.4 ms a frame, recall 1.00 both; at
            5-9 m (markers 25-45 px) recall 0.32 both; a 7 px kernel: 8.0 ms, 0.26 far.
        min_sigma: floor on the noise estimate (grey levels), caps the gain on noise-free input.
        median_ksize: median filter side used on impulse noise (px, odd; 0 or 1 disables).
        impulse_levels: how far an isolated pixel must stand out to count as impulse noise
            (grey levels).
        impulse_fraction: fraction of isolated pixels above which the median is used (-).
        second_gain_ratio: when the noise-limited gain exceeds the range-limited one by more
            than this factor, a second candidate image is stretched by the noise-limited gain
            about the median grey level (0 disables; see above).
        blocking_weight: the noise estimate is at least this times :func:`estimate_blocking`
            (0 disables). Block compression flattens each 8x8 block, the second-difference
            estimate reads ~0 noise, and the gain then turns one-level block steps into
            edges that the adaptive threshold traces across the markers. Measured on the 24
            views of ``bench/bench_degradations.py`` at JPEG quality 20: recall 0.96 without,
            0.99 at weight 1, 1.00 at 1.5; unchanged on the other degradations (motion blur
            also reads ~0 noise but has no block steps: a flat floor of 1 grey level instead
            cost it 0.27 -> 0.19).
    """

    noise_target: float = 12.0
    clip_fraction: float = 0.005
    blur_ksize: int = 3
    blur_ref_width_px: int = 1280
    min_sigma: float = 0.25
    median_ksize: int = 3
    impulse_levels: float = 48.0
    impulse_fraction: float = 0.004
    second_gain_ratio: float = 3.0
    blocking_weight: float = 1.5

    def __call__(self, image: np.ndarray) -> list[np.ndarray]:
        grey = to_grey(as_uint8(image))
        blur = self.blur_ksize
        if blur > 1 and grey.shape[1] > self.blur_ref_width_px:
            scaled = blur * grey.shape[1] / self.blur_ref_width_px
            blur = max(blur, 2 * round((scaled - 1) / 2) + 1)
        if self.median_ksize > 1 and (
            impulse_fraction(grey, self.impulse_levels) > self.impulse_fraction
        ):
            grey = cv2.medianBlur(grey, self.median_ksize)
            blur = 0
        lo, hi, median = _percentiles(grey, self.clip_fraction)
        gain_range = 255.0 / (hi - lo)
        gain_noise = np.inf
        if self.noise_target > 0:
            row_step = max(8, grey.shape[0] // 96)  # ~100 rows: enough for a median
            sigma = estimate_noise_sigma(grey, row_step)
            if self.blocking_weight > 0:
                sigma = max(sigma, self.blocking_weight * estimate_blocking(grey, 8, row_step))
            gain_noise = self.noise_target / max(sigma, self.min_sigma)
        out = [self._stretch(grey, min(gain_range, gain_noise), 0.5 * (lo + hi), blur)]
        if (
            self.second_gain_ratio > 0
            and np.isfinite(gain_noise)  # noise_target 0: no noise-limited gain to use
            and gain_noise > self.second_gain_ratio * gain_range
        ):
            below, above = max(median - lo, 1), max(hi - median, 1)
            lopsided = max(below, above) > self.second_gain_ratio * min(below, above)
            if lopsided or hi - lo < 128:  # not a full-contrast frame (those decode as they are)
                out.append(self._stretch(grey, gain_noise, float(median), blur))
        return out

    @staticmethod
    def _stretch(grey: np.ndarray, gain: float, centre: float, blur: int) -> np.ndarray:
        """``grey`` scaled by ``gain`` about ``centre`` (mapped to 128), saturating, blurred."""
        # a saturating lookup table: convertScaleAbs would fold values below 0 back up
        lut = np.clip((np.arange(256) - centre) * gain + 128.5, 0, 255).astype(np.uint8)
        out = cv2.LUT(grey, lut)
        if blur > 1:
            out = cv2.GaussianBlur(out, (blur, blur), 0)
        return out


@dataclass(frozen=True)
class CompressedViews:
    """``default``'s extra candidate images for block-compressed frames (a vehicle's
    ``CompressedImage``, a JPEG photo, intra-coded video), run only where
    :func:`block_grid_fraction` finds a block grid, so an uncompressed frame (a render) takes
    the pipeline's path and nothing else.

    Each view has its own ArUco parameters (:meth:`presets`): ``default``'s, with one threshold
    window, ``detectInvertedMarker`` off and contour corner refinement. The detector adds the
    IDs a view decodes that the pipeline's candidates missed, away from the markers already
    found (:class:`perception.detector.Detector`).

    1. **The candidate, inverted** (``candidate_window_px``, ``candidate_constant``). At JPEG
       quality 25 the 3DBM's white border (one cell, 3-5 px on a 20-30 px marker) blurs into its
       dark cells and its dark enclosure; in ``default``'s candidate the border is then the
       *hole* of a dark region, and ArUco traces no quad where one dark cell leaks through it.
       Inverted, the border is the dark ring of a normal marker, whose outer contour does not
       care what touches it inside. A wider window (45 px, not 23) keeps the ring whole.
       Measured on 383 rendered frames at JPEG quality 25 (640-1920 px, the development set,
       not the benchmark's): recall of the pipeline's own pass 0.59 -> 0.66, 0 false IDs.
       ``detectInvertedMarker`` stays off: the inverted 3DBM is a normal marker here, and the
       negative's nested contours bias corners; contour refinement: median corner error of the
       added markers 0.8-1.1 px against 1.2-2.0 px with sub-pixel refinement.
    2. **The brightest channel, inverted** (``brightest_window_px``, ``brightest_constant``;
       window 0 disables): per pixel the largest of B, G, R (:func:`brightest_channel`).
       Luma weights red, which sea water absorbs, and puts a coloured object as dark as a
       marker's dark cells; the brightest channel keeps the marker's white cells white under
       a blue or green cast and under coloured drawing. On the shared sea photo of the
       docking station (markers 15-20 px, labels drawn across them in blue) it is what decodes
       a marker; on rendered JPEG frames it adds a few (0.656 -> 0.662 on the set above).

    Attributes:
        min_grid_fraction: the views run when :func:`block_grid_fraction` of the grey frame is
            at least this (-): 0.03 sits above every uncompressed render measured (<= 0.013)
            and below every frame at JPEG quality 25 (>= 0.040).
        candidate_window_px: ArUco threshold window on the inverted candidate (px, odd).
        candidate_constant: ArUco threshold constant there (grey levels).
        brightest_window_px: ... on the inverted brightest channel (px, odd; 0: no such view).
        brightest_constant: ... constant there (grey levels).
    """

    min_grid_fraction: float = 0.03
    candidate_window_px: int = 45
    candidate_constant: float = 7.0
    brightest_window_px: int = 23
    brightest_constant: float = 7.0

    def applies(self, grey: np.ndarray) -> bool:
        """True when ``grey`` (the whole frame) shows a block grid: ``block_grid_fraction(grey)
        >= min_grid_fraction``, the second direction measured only when the first passes."""
        t = self.min_grid_fraction
        if min(grey.shape) < 32:  # under four 8 px blocks a side: no grid to measure
            return block_grid_fraction(grey) >= t
        return _grid_excess(grey, 8, 0) >= t and _grid_excess(grey, 8, 1) >= t

    def presets(self, base: Mapping[str, Any]) -> list[dict[str, Any]]:
        """ArUco parameter overrides of each view, in :meth:`views`' order, from ``base`` (the
        pipeline's preset)."""
        out = []
        for window, constant in self._windows():
            out.append(
                {
                    **base,
                    "detectInvertedMarker": False,
                    "adaptiveThreshConstant": float(constant),
                    "adaptiveThreshWinSizeMin": int(window),
                    "adaptiveThreshWinSizeMax": int(window),
                    "adaptiveThreshWinSizeStep": 10,
                    "cornerRefinementMethod": int(cv2.aruco.CORNER_REFINE_CONTOUR),
                }
            )
        return out

    def views(self, image: np.ndarray, candidates: list[np.ndarray]) -> list[np.ndarray]:
        """The extra candidate images of one uint8 frame (BGR or grey) whose pipeline
        candidates are ``candidates``."""
        out = [cv2.bitwise_not(candidates[0])]
        if self.brightest_window_px > 0:
            out.append(cv2.bitwise_not(brightest_channel(image)))
        return out

    def _windows(self) -> list[tuple[int, float]]:
        out = [(self.candidate_window_px, self.candidate_constant)]
        if self.brightest_window_px > 0:
            out.append((self.brightest_window_px, self.brightest_constant))
        return out


def published_grey(image: np.ndarray) -> np.ndarray:
    """The published detector's grey image: min-max normalise (all channels together), then
    OpenCV's ``COLOR_RGB2GRAY`` applied to the BGR frame, as the published code does.

    The published code reads frames with OpenCV (BGR) and converts them as if they were RGB, so
    its grey weights blue by 0.299 and red by 0.114 (the BT.601 weights swapped). The pipelines
    named after it keep that. A grey input is only normalised.
    """
    norm = _minmax(as_uint8(image))
    return norm if norm.ndim == 2 else cv2.cvtColor(norm, cv2.COLOR_RGB2GRAY)


def _inverted_rescale(grey: np.ndarray) -> np.ndarray:
    """float32 image mapping the darkest pixel to +127 and the brightest to -127 (linear), in the
    published code's float32 arithmetic; zeros for a constant image (the published code divides
    by zero there), which the last step turns into a uniform 127."""
    g = grey.astype(np.float32)
    lo, hi = g.min(), g.max()
    if hi == lo:
        return np.zeros_like(g)
    scale = np.float32(254.0) / (hi - lo)  # float32, as the published (254 / (max - min))
    return (hi - g) * scale - np.float32(127.0)


def _to_published_uint8(x: np.ndarray) -> np.ndarray:
    """Shift by 127.5, clip to [1, 254], truncate to uint8 (the published code's last step)."""
    return np.clip(x + np.float32(127.5), 1.0, 254.0).astype(np.uint8)


#: The published code's 3x3 smoothing kernel: the binomial [1 2 1] (x) [1 2 1] / 16.
_BINOMIAL_3X3 = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0]).astype(np.float32) / np.float32(16.0)


def reference_3dbm(image: np.ndarray) -> list[np.ndarray]:
    """The published 3DBM pipeline ("CLAHE method"), operation by operation.

    min-max normalise; grey (:func:`published_grey`: RGB2GRAY on BGR); CLAHE (clip 2.0, 32x32
    tiles); float32 inverted min-max rescale to [-127, 127]; 3x3 binomial filter in float32
    (``filter2D``, reflected border); + 127.5; clip to [1, 254]; truncate to uint8. A constant
    image (no contrast) gives a uniform 127.
    """
    grey = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(32, 32)).apply(published_grey(image))
    return [_to_published_uint8(cv2.filter2D(_inverted_rescale(grey), -1, _BINOMIAL_3X3))]


#: Thresholds of the published inverse-threshold sweep (grey levels).
SWEEP_THRESHOLDS: tuple[int, ...] = tuple(range(90, 186, 5))

#: The published sweep's 3x3 box filter, applied to each thresholded image (uint8 result).
_BOX_3X3 = np.full((3, 3), 1.0 / 9.0)


def threshold_sweep(image: np.ndarray) -> list[np.ndarray]:
    """The published iterative threshold method: for each threshold in
    :data:`SWEEP_THRESHOLDS`, an inverse binary threshold of the published grey image
    (:func:`published_grey`, min-max normalised) smoothed by a 3x3 box filter; the detector keeps
    the candidate with the most detections (``merge="best"``)."""
    grey = published_grey(image)
    return [
        cv2.filter2D(cv2.threshold(grey, t, 255, cv2.THRESH_BINARY_INV)[1], -1, _BOX_3X3)
        for t in SWEEP_THRESHOLDS
    ]


def normalise_invert(image: np.ndarray) -> list[np.ndarray]:
    """The published "normalization method": the published grey image, inverted min-max
    rescale, + 127.5, clip to [1, 254], truncate to uint8 (no CLAHE, no blur)."""
    return [_to_published_uint8(_inverted_rescale(published_grey(image)))]


def plain(image: np.ndarray) -> list[np.ndarray]:
    """Grey only: flat printed tags in good light."""
    return [to_grey(as_uint8(image))]


@dataclass(frozen=True)
class Pipeline:
    """A named preprocessing pipeline and the ArUco settings it goes with.

    Attributes:
        name: registry key.
        fn: ``fn(image) -> list[np.ndarray]`` of uint8 grey candidates (same size as the input).
        aruco_preset: ``cv2.aruco.DetectorParameters`` attribute -> value, applied before the
            explicit fields of ``DetectorConfig``.
        merge: "union": every ID from every candidate, each ID taken from the candidate with
            the most detections; "first": every ID from every candidate, each ID taken from the
            earliest candidate that decoded it (``default``: its second candidate saturates, so
            its corners only stand in for markers the first missed); "best": only the candidate
            with the most detections (the published threshold sweep).
        rescue_rejected: the detector reads the quads ArUco rejected again
            (:mod:`perception.rescue`); ``default`` only, the published pipelines stay as
            published.
        description: one line for listings.
        opencv_pass: the detector also runs OpenCV's ArUco detector with OpenCV's default
            parameters on the plain grey image (:func:`to_grey`); the IDs it decodes come
            from it, the pipeline's candidates add the others (``default`` only; see
            ``DetectorConfig.opencv_pass``).
        compressed: extra candidate images for block-compressed frames (:class:`CompressedViews`;
            ``default`` only; see ``DetectorConfig.compressed_pass``), None for none.
        grey_input: ``fn`` reads only :func:`to_grey` of its image, so the detector may hand
            it the grey image it already has (the same candidates, one colour conversion
            fewer).
    """

    name: str
    fn: Callable[[np.ndarray], list[np.ndarray]]
    aruco_preset: Mapping[str, Any] = field(default_factory=dict)
    merge: str = "union"
    rescue_rejected: bool = False
    description: str = ""
    opencv_pass: bool = False
    compressed: CompressedViews | None = None
    grey_input: bool = False

    def __call__(self, image: np.ndarray) -> list[np.ndarray]:
        return self.fn(image)


#: OpenCV's DetectorParameters defaults (the published pipelines use them unchanged).
_OPENCV_DEFAULTS: Mapping[str, Any] = MappingProxyType({})

#: Tuned with the ``default`` pipeline (see the module docstring).
_DEFAULT_PRESET: Mapping[str, Any] = MappingProxyType(
    {
        "detectInvertedMarker": True,
        "adaptiveThreshConstant": 7.0,
        "adaptiveThreshWinSizeMin": 23,
        "adaptiveThreshWinSizeMax": 23,
        "adaptiveThreshWinSizeStep": 10,
        "cornerRefinementMethod": int(cv2.aruco.CORNER_REFINE_SUBPIX),
        "perspectiveRemovePixelPerCell": 8,
        "perspectiveRemoveIgnoredMarginPerCell": 0.3,
    }
)

PIPELINES: dict[str, Pipeline] = {
    p.name: p
    for p in (
        Pipeline(
            "default",
            NoiseAwareStretch(),
            _DEFAULT_PRESET,
            merge="first",
            rescue_rejected=True,
            description="noise-aware stretch + blur, both polarities, rejected quads re-read, "
            "+ OpenCV's own pass on the grey image, + two views on block-compressed frames",
            opencv_pass=True,
            compressed=CompressedViews(),
            grey_input=True,
        ),
        Pipeline(
            "reference_3dbm",
            reference_3dbm,
            _OPENCV_DEFAULTS,
            description="published 3DBM: min-max, grey, CLAHE 2.0/32x32, invert, 3x3 blur",
        ),
        Pipeline(
            "threshold_sweep",
            threshold_sweep,
            _OPENCV_DEFAULTS,
            merge="best",
            description="published: inverse thresholds 90..185 step 5, 3x3 box, keep the best",
        ),
        Pipeline(
            "normalise_invert",
            normalise_invert,
            _OPENCV_DEFAULTS,
            description="published: min-max normalise, grey, inverted rescale",
        ),
        Pipeline(
            "plain",
            plain,
            _OPENCV_DEFAULTS,
            description="grey only (flat printed tags)",
            grey_input=True,
        ),
    )
}


def get_pipeline(name: str) -> Pipeline:
    """The pipeline registered as ``name``.

    Raises:
        DockError: unknown name; the message lists the valid names.
    """
    try:
        return PIPELINES[name]
    except KeyError:
        raise DockError(
            f"unknown preprocessing pipeline {name!r} (valid: {', '.join(sorted(PIPELINES))})"
        ) from None
