"""The settings of the water fit (``sim fit-water``, the ``[fit_water]`` table): below the fit
(:mod:`datasets.water_fit`) and its measurements (:mod:`datasets.water_fit_samples`), which both
read them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from uwdock.datasets.water_fit_model import LIGHTINGS
from uwdock.dockcore.config import check_fields
from uwdock.dockcore.domains import Interval, Seed
from uwdock.sim.water import PRESETS

__all__ = ["TARGETS", "FitWaterConfig"]

#: The targets a fit reads: a printed chessboard, or the DS marker board.
TARGETS = ("chessboard", "markers")


@dataclass(frozen=True)
class FitWaterConfig:
    """Settings of the water fit (the ``[fit_water]`` table).

    Attributes:
        target: ``"chessboard"`` (a printed board, sized by ``cols``, ``rows``,
            ``square_mm``) or ``"markers"`` (the DS marker board of a marker set file).
        cols: chessboard inner corners along a row.
        rows: chessboard inner corners along a column.
        square_mm: chessboard square side (mm).
        gamma: display gamma of the frames (2.2: sRGB-like cameras and the simulator).
        lamp_offset_camcv_m: the lamp's position in the camera frame (m; the Girona's lamp is
            10 cm above the camera, the renderer's default).
        lighting: the lighting model (:data:`water_fit_model.LIGHTINGS`): ``"lamp"`` (a lamp
            beside the camera: fall-off 1 / d**2, direct signal over 2 r), ``"ambient"`` (tank
            or room lights only: uniform, direct signal over r), ``"both"`` (the lamp plus a
            uniform ambient light, as the renderer lights a scene) or ``"auto"``: each is fitted
            and the one with the least error on held-out frames chosen.
        artificial_light: False is the older spelling of ``lighting = "ambient"``.
        patch_fraction: central fraction of a square (or marker cell) that is sampled: away
            from the edges, where blur mixes black and white.
        saturation_level: patches with any sampled channel at or above this 8-bit level are
            dropped (clipped by the camera).
        fit_vignetting: fit the vignetting strength; False: keep ``vignetting``.
        vignetting: vignetting strength when it is not fitted.
        min_range_spread_m: the fit refuses frames whose target ranges span less (m).
        max_frames: at most this many frames are used (evenly spaced over the input).
        base: the preset whose other fields (blur, sensor noise, gamma) the water file keeps.
        cv_folds: folds of frames for the held-out error (frames sorted by range, dealt
            round-robin); 0, or no more frames than folds: leave one frame out.
        plausible_tolerance: a lighting model whose held-out error is within this fraction of
            the best one's is plausible too (its values are compared with the chosen one's).
        bootstrap_resamples: resamples of whole frames for the uncertainty (0: the Jacobian's
            standard errors only).
        bootstrap_seed: seed of the resampling.
        max_rel_std: a value whose relative uncertainty (the larger of the bootstrap's and the
            Jacobian's) exceeds this is not determined.
        disagree_sigmas: a value is not determined when a plausible other lighting model gives
            one more than this many combined uncertainties away.
        max_contrast_error: a channel's attenuation is not determined when the modelled
            contrast misses the measured one by more than this fraction
            (:func:`contrast_error`; rendered films: within 0.01).
    """

    target: str = "chessboard"
    cols: Annotated[int, Interval(ge=2, le=100)] = 8
    rows: Annotated[int, Interval(ge=2, le=100)] = 6
    square_mm: Annotated[float, Interval(gt=0, le=10_000)] = 100.0
    gamma: Annotated[float, Interval(ge=0.2, le=5)] = 2.2
    lamp_offset_camcv_m: tuple[
        Annotated[float, Interval(ge=-5, le=5)],
        Annotated[float, Interval(ge=-5, le=5)],
        Annotated[float, Interval(ge=-5, le=5)],
    ] = (0.0, -0.10, 0.0)
    lighting: str = "auto"
    artificial_light: bool = True
    patch_fraction: Annotated[float, Interval(gt=0, le=0.9)] = 0.5
    saturation_level: Annotated[int, Interval(ge=1, le=255)] = 250
    fit_vignetting: bool = True
    vignetting: Annotated[float, Interval(ge=0, lt=1)] = 0.0
    min_range_spread_m: Annotated[float, Interval(ge=0, le=100)] = 1.0
    max_frames: Annotated[int, Interval(ge=1, le=100_000)] = 400
    base: str = "coastal"
    cv_folds: Annotated[int, Interval(ge=0, le=1000)] = 5
    plausible_tolerance: Annotated[float, Interval(ge=0, le=10)] = 0.10
    bootstrap_resamples: Annotated[int, Interval(ge=0, le=10_000)] = 100
    bootstrap_seed: Seed = 0
    max_rel_std: Annotated[float, Interval(gt=0, le=100)] = 0.25
    disagree_sigmas: Annotated[float, Interval(gt=0, le=100)] = 2.0
    max_contrast_error: Annotated[float, Interval(gt=0, le=100)] = 0.2

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        check_fields(self)
        if self.target not in TARGETS:
            raise ValueError(f"target: must be one of {', '.join(TARGETS)}, got {self.target!r}")
        if self.base not in PRESETS:
            raise ValueError(f"base: unknown water preset {self.base!r}")
        if self.lighting not in ("auto", *LIGHTINGS):
            raise ValueError(
                f"lighting: must be auto, {', '.join(LIGHTINGS)}, got {self.lighting!r}"
            )
        if not self.artificial_light and self.lighting not in ("auto", "ambient"):
            raise ValueError(
                f"artificial_light: false means lighting 'ambient', not {self.lighting!r}"
            )

    def lightings(self) -> tuple[str, ...]:
        """The lighting models to fit (all of them for ``"auto"``)."""
        if not self.artificial_light:
            return ("ambient",)
        return LIGHTINGS if self.lighting == "auto" else (self.lighting,)
