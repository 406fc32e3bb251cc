"""The settings of a stereo calibration (``calibration stereo``, :mod:`calibration.stereo`):
below the pipeline and its inputs (:mod:`calibration.stereo_inputs`), which both read them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from uwdock.calibration.intrinsics import IntrinsicsConfig
from uwdock.dockcore.domains import Interval

__all__ = ["StereoConfig"]


@dataclass(frozen=True)
class StereoConfig:
    """Stereo calibration of two cameras from pairs of views of one planar target.

    Attributes:
        intrinsics: the target and how it is found, as for ``calibration intrinsics`` (a
            ``[intrinsics]`` table): ``pattern``, ``cols``, ``rows``, ``square_mm`` (sets the
            scale of ``T_right_left``), ``marker_mm``, ``dictionary``, ``legacy_charuco``,
            ``min_corners``, ``subpix_win_px``, ``corner_method`` (``auto`` = ``classic``
            here), ``blur_threshold_px`` (pairs with a blurrier board are rejected),
            ``video_max_frames`` (most pairs read from two videos or a bag, evenly spaced) and
            ``distortion_model`` (of a joint fit). Its hold-out, seed, ``max_views`` and
            outlier fields are not used.
        pair_tolerance_ms: bag input: a left and a right image pair when their header stamps
            differ by at most this (ms, [0, 10000]); each right image pairs with one left
            image, the nearest.
        skip_unpaired: folder and video input: images without a partner (a stem only one
            folder has, frames past the end of the shorter video) are skipped with a note;
            False: they are an error.
        outlier_ratio: after each fit, the pair with the largest error (RMS reprojection error
            over both views, px) is rejected (reason ``outlier``) and the fit repeated while
            that error exceeds this multiple of the other pairs' median (and
            ``outlier_min_px``), as long as ``MIN_VIEWS`` pairs remain; 0 disables
            ([0, 1000]). A pair whose two images were not taken at the same moment, or with a
            mis-detected corner, bends ``T_right_left`` toward itself.
        outlier_min_px: pairs at or below this error are never outliers (px, [0, 1000]).
        rectify_alpha: ``cv2.stereoRectify``'s free scaling, [0, 1]: 0 crops the rectified
            images to valid pixels only, 1 keeps every source pixel (with black borders).
    """

    intrinsics: IntrinsicsConfig = field(default_factory=IntrinsicsConfig)
    pair_tolerance_ms: Annotated[float, Interval(ge=0.0, le=10_000.0)] = 5.0
    skip_unpaired: bool = False
    outlier_ratio: Annotated[float, Interval(ge=0.0, le=1000.0)] = 3.0
    outlier_min_px: Annotated[float, Interval(ge=0.0, le=1000.0)] = 0.5
    rectify_alpha: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.0
