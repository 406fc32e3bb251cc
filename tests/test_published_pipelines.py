"""The pipelines named after the published 3DBM detector reproduce its operations.

The published detector (Chaarani et al., the authors' public ``3D-binaryMarker`` code) works on
a BGR frame read by OpenCV. Its operations, step by step, as facts: min-max normalise the frame
(all channels together); convert with ``COLOR_RGB2GRAY`` (so blue gets the red weight); then

* CLAHE method: CLAHE (clip 2.0, 32x32 tiles); float32 rescale that maps the darkest pixel to
  +127 and the brightest to -127; a 3x3 binomial filter ([1 2 1] (x) [1 2 1] / 16) in float;
  + 127.5; values above 254 set to 254 and below 1 set to 1; cast to uint8 (truncation);
* normalization method: the same rescale, + 127.5, clip and cast, without CLAHE or filter;
* iterative threshold method: inverse binary thresholds 90, 95, ..., 185 of the normalised grey,
  each smoothed by a 3x3 box filter.

Each is re-derived here independently, in float64 with explicit border handling, and compared
with the pipelines on fixed images: equal, or one grey level apart where float rounding lands
on the other side of an integer.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.test_detector import render
from uwdock.perception.preprocess import (
    SWEEP_THRESHOLDS,
    get_pipeline,
    published_grey,
)


def _fixed_images() -> list[np.ndarray]:
    """A synthetic 3DBM view with a green cast and noise, and a colour gradient whose red and
    blue differ everywhere (channel order shows)."""
    view, _ = render(np.random.default_rng(7), levels=90, noise=2.0, green=True)
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    grad = np.dstack(
        [xx * 255 // (w - 1), (xx + yy) * 127 // (w + h - 2) + 60, yy * 255 // (h - 1)]
    )
    return [view, grad.astype(np.uint8)]


def _conv3x3_reflect101(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Correlation with a 3x3 kernel, OpenCV's default border (reflect without the edge pixel,
    numpy's ``mode="reflect"``), in float64."""
    h, w = x.shape
    pad = np.pad(x.astype(np.float64), 1, mode="reflect")
    return sum(kernel[i, j] * pad[i : i + h, j : j + w] for i in range(3) for j in range(3))


def _published_grey(bgr: np.ndarray) -> np.ndarray:
    norm = cv2.normalize(bgr, None, 0, 255, cv2.NORM_MINMAX)
    return cv2.cvtColor(norm, cv2.COLOR_RGB2GRAY)


def _rescale_clip(x: np.ndarray, blur: bool) -> np.ndarray:
    x = x.astype(np.float64)
    lo, hi = x.min(), x.max()
    r = -((x - hi) * ((-127.0 - 127.0) / (lo - hi)) + 127.0)  # darkest +127, brightest -127
    if blur:
        r = _conv3x3_reflect101(r, np.outer([1, 2, 1], [1, 2, 1]) / 16.0)
    r = r + 127.5
    r[r > 254] = 254
    r[r < 1] = 1
    return r.astype(np.uint8)


def _assert_close(ours: np.ndarray, theirs: np.ndarray) -> None:
    assert ours.shape == theirs.shape and ours.dtype == np.uint8
    diff = np.abs(ours.astype(int) - theirs.astype(int))
    assert diff.max() <= 1, diff.max()
    assert (diff == 0).mean() > 0.99, (diff == 0).mean()


@pytest.mark.parametrize("k", [0, 1], ids=["3dbm_view", "colour_gradient"])
def test_grey_is_rgb2gray_of_the_bgr_frame_as_published(k):
    img = _fixed_images()[k]
    grey = published_grey(img)
    norm = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.float64)
    swapped = 0.299 * norm[..., 0] + 0.587 * norm[..., 1] + 0.114 * norm[..., 2]  # B as R
    assert np.abs(grey - swapped).max() <= 1.0
    if k == 1:  # the BT.601 grey of the true colours differs where red and blue differ
        true_grey = cv2.cvtColor(
            cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX), cv2.COLOR_BGR2GRAY
        )
        assert np.abs(grey.astype(int) - true_grey.astype(int)).max() > 40


@pytest.mark.parametrize("k", [0, 1], ids=["3dbm_view", "colour_gradient"])
def test_reference_3dbm_is_the_published_clahe_method(k):
    img = _fixed_images()[k]
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(32, 32)).apply(_published_grey(img))
    (ours,) = get_pipeline("reference_3dbm")(img)
    _assert_close(ours, _rescale_clip(clahe, blur=True))
    assert ours.min() >= 1 and ours.max() <= 254


@pytest.mark.parametrize("k", [0, 1], ids=["3dbm_view", "colour_gradient"])
def test_normalise_invert_is_the_published_normalization_method(k):
    img = _fixed_images()[k]
    (ours,) = get_pipeline("normalise_invert")(img)
    theirs = _rescale_clip(_published_grey(img), blur=False)
    _assert_close(ours, theirs)
    # a pure inverted rescale: the darkest grey pixel is 254, the brightest 1
    grey = _published_grey(img)
    assert ours[grey == grey.min()].min() == 254 and ours[grey == grey.max()].max() == 1


def test_threshold_sweep_is_the_published_iterative_threshold_method():
    img = _fixed_images()[0]
    grey = _published_grey(img)
    ours = get_pipeline("threshold_sweep")(img)
    assert SWEEP_THRESHOLDS == tuple(range(90, 190, 5)) and len(ours) == len(SWEEP_THRESHOLDS)
    for t, candidate in zip(SWEEP_THRESHOLDS, ours, strict=True):
        binary = np.where(grey > t, 0.0, 255.0)  # inverse binary threshold
        box = np.rint(_conv3x3_reflect101(binary, np.full((3, 3), 1.0 / 9.0)))
        _assert_close(candidate, box.astype(np.uint8))


@pytest.mark.parametrize("name", ["reference_3dbm", "normalise_invert"])
def test_constant_image_gives_a_uniform_candidate(name):
    # the published rescale divides by zero on a flat frame; ours returns a uniform mid grey
    (out,) = get_pipeline(name)(np.full((40, 50, 3), 77, np.uint8))
    assert out.dtype == np.uint8 and (out == 127).all()
