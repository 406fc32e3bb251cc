"""The water fitted to the user's tank: ``sim fit-water``.

The simulator's underwater model (:func:`uwdock.sim.water.apply_water`) gives, per colour
channel ``c``, the linear intensity of a surface point at range ``r``::

    I_c = V(rho) * (J_c * exp(-p beta_D_c r) + B_inf_c * (1 - exp(-beta_B_c r)))

with ``J`` the in-air radiance, ``p = 2`` when a lamp beside the camera lights the scene (the
light travels to the target and back) and 1 under ambient light, and ``V = 1 - s rho**2`` the
vignetting. A known target (a chessboard, or the DS marker board) posed by PnP gives, in every
frame, black and white patches of known geometry: their range ``r``, their distance ``d`` to
the lamp and the cosine of the lamp's incidence. Three lighting models give the in-air radiance
of a patch of albedo class ``k`` (:mod:`datasets.water_fit_model`): ``lamp`` (``a_kc cos /
d**2``), ``both`` (``a_kc (eta + cos / d**2)``: the lamp plus a uniform ambient light ``eta``,
one ratio for the three channels, as the renderer lights a scene) and ``ambient`` (``a_kc``,
``p = 1``: tank or room lights only). The difference white - black carries the direct signal
(``beta_D``), the black level the backscatter (``B_inf``, ``beta_B``), the spread of patch
positions in the image the vignetting; all parameters are fitted jointly by weighted least
squares (:func:`scipy.optimize.least_squares` with the model's analytic Jacobian, 2 % relative
+ 0.002 absolute uncertainty per patch, a few starts).

What the frames can tell (:mod:`datasets.water_fit_judge`): with ``lighting = "auto"`` every
model is fitted and the one with the least error on held-out frames (folds of whole frames,
no random draw) is chosen; the uncertainty is the larger of the Jacobian's standard error and
the spread over a bootstrap of whole frames; and each of ``beta_D``, ``B_inf``, ``beta_B`` per
channel is *determined* unless it sits at a bound, its backscatter is not separable over the
ranges seen (:func:`backscatter_separable`: in clear water only ``B_inf * beta_B`` is), its
uncertainty is large, the modelled contrast misses the frames', or another lighting model that
fits the held-out frames about as well gives a value beyond the uncertainties. The report says
what to film to pin an undetermined value down; the command writes no water file when
``beta_D`` is undetermined.

It lives in ``datasets``: it crosses the sim -> perception seam (the water model of ``sim``,
the detector and PnP of ``perception``); ``sim fit-water`` is its command.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from uwdock.datasets import water_fit_model as wm
from uwdock.datasets.water_fit_config import FitWaterConfig
from uwdock.datasets.water_fit_judge import (
    ModelResult,
    Verdict,
    block_std,
    frame_folds,
    judge,
    lamp_not_seen,
    lamp_share,
)
from uwdock.datasets.water_fit_model import Geometry, expected
from uwdock.datasets.water_fit_samples import PatchSamples, estimate_noise, sample_frames
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.errors import DockError
from uwdock.sim.water import PRESETS, WaterConfig

__all__ = [
    "FitWaterConfig",
    "PatchSamples",
    "WaterFit",
    "backscatter_separable",
    "contrast_error",
    "estimate_noise",
    "fit_water",
    "sample_frames",
]

CHANNELS = ("R", "G", "B")

#: The sensor model (kept under its old name for callers).
_expected = expected


# ----------------------------------------------------------------------------- the fit


@dataclass
class WaterFit:
    """The fitted water, how well it explains the frames and what the frames determine.

    Attributes:
        water: the fitted model as a :class:`WaterConfig` (the base preset's other fields).
        params: block -> (R, G, B) fitted values (``a_white``, ``a_black``, ``ambient``,
            ``beta_D``, ``B_inf``, ``beta_B``) of the chosen lighting model.
        rel_std: block -> (R, G, B) relative uncertainty used in the decisions: the larger of
            the Jacobian's standard error and the bootstrap's spread.
        vignetting: the vignetting strength (fitted or given).
        residual_rms: RMS of the patch residuals (linear units, white = 1).
        residual_rms_8bit: the same in 8-bit display levels at the patches' brightness.
        contrast_error: per channel, the modelled against the measured contrast (white - black
            neighbours) by range (:func:`contrast_error`).
        range_m: (min, max) range of the patches (m).
        samples: the patches used.
        config: the fit's settings.
        separable: per channel, whether B_inf and beta_B are told apart over the ranges seen
            (:func:`backscatter_separable`).
        warnings: one-line remarks (ranges too narrow, parameters not determined).
        lighting: the chosen lighting model.
        models: lighting -> its fit, held-out error and uncertainty (every model fitted).
        verdict: per judged parameter and channel, determined or not, why, what to film.
    """

    water: WaterConfig
    params: dict[str, tuple[float, float, float]]
    rel_std: dict[str, tuple[float, float, float]]
    vignetting: float
    residual_rms: float
    residual_rms_8bit: float
    contrast_error: tuple[float, float, float]
    range_m: tuple[float, float]
    samples: PatchSamples
    config: FitWaterConfig
    separable: tuple[bool, bool, bool] = (True, True, True)
    warnings: list[str] = field(default_factory=list)
    lighting: str = "both"
    models: dict[str, ModelResult] = field(default_factory=dict)
    verdict: Verdict | None = None
    _x: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    @property
    def determined(self) -> dict[str, list[bool]]:
        """Judged block -> (R, G, B) whether the frames determine the value."""
        assert self.verdict is not None
        return self.verdict.determined

    @property
    def beta_D_determined(self) -> bool:
        """Whether the attenuation is determined in every channel."""
        return all(self.determined["beta_D"])

    @property
    def to_film(self) -> list[str]:
        """What to film (or state) to pin the undetermined values down."""
        return list(self.verdict.to_film) if self.verdict else []

    def undetermined_names(self) -> dict[str, list[str]]:
        """Judged block -> channels it is not determined in (blocks with none left out)."""
        return {b: [ch for ch, ok in zip(CHANNELS, v, strict=True) if not ok]
                for b, v in self.determined.items() if not all(v)}  # fmt: skip

    def model(self, s: PatchSamples | None = None) -> np.ndarray:
        """(N, 3) modelled linear RGB of the patches as the camera records them (mean of the
        noisy values clipped at 0)."""
        noise = (self.water.photons_at_white, self.water.read_noise)
        g = Geometry.of(s or self.samples)
        return _expected(wm.model(self._x, g, self.lighting), *noise)

    def contrast_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(range_m (G,), measured (G, 3), modelled (G, 3)) white - mean(black neighbours)."""
        return _contrast(self.samples, self.model())

    def summary(self) -> dict[str, Any]:
        """What the report JSON holds (no per-patch arrays)."""
        s = self.samples
        chosen = self.models[self.lighting]
        boot = chosen.rel_std_bootstrap
        return {
            "water": to_dict(self.water),
            "lighting": {
                "requested": self.config.lighting if self.config.artificial_light else "ambient",
                "chosen": self.lighting,
                "chosen_by": "least error on held-out frames"
                if len(self.models) > 1
                else "requested",
                "cv_folds": _n_folds(s, self.config) if len(self.models) > 1 else 0,
                "plausible_tolerance": self.config.plausible_tolerance,
                "models": {k: m.summary() for k, m in self.models.items()},
            },
            "params": {k: list(v) for k, v in self.params.items()},
            "rel_std": {k: list(v) for k, v in self.rel_std.items()},
            "rel_std_jacobian": {
                k: [float(x) for x in v] for k, v in chosen.rel_std_jacobian.items()
            },
            "rel_std_bootstrap": {k: [float(x) for x in v] for k, v in boot.items()},
            "bootstrap": {
                "resamples": chosen.resamples,
                "seed": self.config.bootstrap_seed,
                "what": "whole frames resampled with replacement; half the 16-84 % interval of "
                "each log parameter",
                "beta_D_q16": [float(v) for v in chosen.quantiles["beta_D"][0]]
                if chosen.quantiles
                else None,
                "beta_D_q84": [float(v) for v in chosen.quantiles["beta_D"][1]]
                if chosen.quantiles
                else None,
            },
            "determined": {
                b: dict(zip(CHANNELS, v, strict=True)) for b, v in self.determined.items()
            },
            "undetermined": self.verdict.undetermined() if self.verdict else [],
            "to_film": self.to_film,
            "vignetting": self.vignetting,
            "backscatter_separable": dict(zip(CHANNELS, self.separable, strict=True)),
            "residual_rms": self.residual_rms,
            "residual_rms_8bit": self.residual_rms_8bit,
            "contrast_error": dict(zip(CHANNELS, self.contrast_error, strict=True)),
            "range_m": list(self.range_m),
            "patches": len(s),
            "white_patches": int(s.white.sum()),
            "contrast_pairs": len(s.groups),
            "frames_read": s.frames_read,
            "frames_used": s.frames_used,
            "frames_corrupt": s.frames_corrupt,
            "patches_dropped_saturated": s.dropped_saturated,
            "warnings": list(self.warnings),
            "config": to_dict(self.config),
        }


def _contrast(s: PatchSamples, model: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not s.groups:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    w = np.array([g[0] for g in s.groups])
    meas = np.array([s.rgb[g[0]] - s.rgb[g[1]].mean(axis=0) for g in s.groups])
    mod = np.array([model[g[0]] - model[g[1]].mean(axis=0) for g in s.groups])
    return s.range_m[w], meas, mod


#: Width of the range bins over which measured and modelled contrast are compared (m).
CONTRAST_BIN_M = 0.25


def contrast_error(
    range_m: np.ndarray, measured: np.ndarray, modelled: np.ndarray
) -> tuple[float, float, float]:
    """Per channel, how far the modelled contrast is from the measured one: the mean contrasts
    of the white/black pairs in each range bin (``CONTRAST_BIN_M``) compared, as
    ``sum_bins n |modelled - measured| / sum_bins n |measured|`` (binning averages out the
    sensor noise of single pairs; what is left is the model's error)."""
    if len(range_m) == 0:
        return (float("nan"),) * 3
    bins = np.floor(range_m / CONTRAST_BIN_M).astype(int)
    num, den = np.zeros(3), np.zeros(3)
    for b in np.unique(bins):
        m = bins == b
        n = m.sum()
        num += n * np.abs(modelled[m].mean(axis=0) - measured[m].mean(axis=0))
        den += n * np.abs(measured[m].mean(axis=0))
    return tuple(float(a / max(d, 1e-12)) for a, d in zip(num, den, strict=True))  # type: ignore[return-value]


#: Change and bend (linear, white = 1) the backscatter must show over the ranges seen for its
#: veiling light and coefficient to be told apart (on rendered films, below it the fit's
#: standard errors understate their error several times).
SEPARABLE_CHANGE = 0.03


def backscatter_separable(
    B_inf: np.ndarray, beta_B: np.ndarray, r_min_m: float, r_max_m: float
) -> list[bool]:
    """Per channel, whether ``B_inf`` and ``beta_B`` are determined separately by patches from
    ``r_min_m`` to ``r_max_m``: the backscatter ``B_inf (1 - exp(-beta_B r))`` must change by
    :data:`SEPARABLE_CHANGE` over those ranges *and* bend by as much away from its initial
    slope ``B_inf beta_B r`` (in clear water only the product is seen; in turbid water a
    backscatter already saturated at the nearest range hides its coefficient)."""
    B_inf, beta_B = np.asarray(B_inf, float), np.asarray(beta_B, float)
    change = B_inf * np.abs(np.exp(-beta_B * r_min_m) - np.exp(-beta_B * r_max_m))
    bend = B_inf * (beta_B * r_max_m - (1.0 - np.exp(-beta_B * r_max_m)))
    return [bool(v) for v in (change >= SEPARABLE_CHANGE) & (bend >= SEPARABLE_CHANGE)]


#: A residual above this (8-bit grey levels) means no lighting model explains the frames (on
#: rendered films, with their noise, the fit leaves 0.3-0.6).
MISFIT_8BIT = 3.0


def _n_folds(s: PatchSamples, cfg: FitWaterConfig) -> int:
    n = len(np.unique(s.frame))
    return n if cfg.cv_folds == 0 else min(cfg.cv_folds, n)


def _to_8bit(v: np.ndarray, gamma: float) -> np.ndarray:
    return 255.0 * (np.clip(v, 1e-6, None) ** (1.0 / gamma))


def _fit_model(
    s: PatchSamples, cfg: FitWaterConfig, lighting: str, photons: float | None, read: float
) -> ModelResult:
    """One lighting model on all frames (four starts), its Jacobian standard errors."""
    vig0 = cfg.vignetting if not cfg.fit_vignetting else 0.1
    lo, hi = wm.bounds(lighting, cfg.fit_vignetting, cfg.vignetting)
    sol = wm.solve(s, lighting, photons, read, lo, hi, vig0)
    n_free = wm.free_parameters(lighting, cfg.fit_vignetting)
    sd = wm.log_std(sol.jac[:, hi - lo > 1e-6], 2.0 * sol.cost / max(sol.fun.size - n_free, 1))
    full = np.zeros(wm.N_PARAMS)
    full[hi - lo > 1e-6] = sd
    rel = {b: np.broadcast_to(full[wm.SLICES[b]], (3,)).astype(float) for b in wm.BLOCKS}
    m = _expected(wm.model(sol.x, Geometry.of(s), lighting), photons, read)
    fit_rms = float(np.sqrt(np.mean((_to_8bit(m, cfg.gamma) - _to_8bit(s.rgb, cfg.gamma)) ** 2)))
    return ModelResult(lighting, sol.x, sol.cost, n_free, rel, fit_rms_8bit=fit_rms,
                       lamp_share=lamp_share(sol.x, s, lighting))  # fmt: skip


def _cross_validate(
    s: PatchSamples, cfg: FitWaterConfig, m: ModelResult, photons: float | None, read: float
) -> None:
    """Held-out error of a model: each fold of frames predicted by a fit to the others."""
    folds = frame_folds(s.frame, s.range_m, cfg.cv_folds)
    lo, hi = wm.bounds(m.lighting, cfg.fit_vignetting, cfg.vignetting)
    pred = np.zeros_like(s.rgb)
    for f in np.unique(folds):
        train, test = np.flatnonzero(folds != f), np.flatnonzero(folds == f)
        sol = wm.solve(s, m.lighting, photons, read, lo, hi, 0.1, rows=train, x0=m.x,
                       max_nfev=100, tol=1e-6)  # fmt: skip
        pred[test] = _expected(wm.model(sol.x, Geometry.of(s, test), m.lighting), photons, read)
    sigma = wm.SIGMA_REL * s.rgb + wm.SIGMA_ABS
    m.heldout_rms = float(np.sqrt(np.mean(((pred - s.rgb) / sigma) ** 2)))
    diff = _to_8bit(pred, cfg.gamma) - _to_8bit(s.rgb, cfg.gamma)
    m.heldout_rms_8bit = float(np.sqrt(np.mean(diff**2)))


def _bootstrap(
    s: PatchSamples, cfg: FitWaterConfig, m: ModelResult, photons: float | None, read: float
) -> None:
    """Resample whole frames with replacement (seeded) and refit: the spread of each log
    parameter (half its 16-84 % interval) and its 16 % and 84 % values."""
    if cfg.bootstrap_resamples <= 0:
        return
    frames = np.unique(s.frame)
    index = np.searchsorted(frames, s.frame)
    lo, hi = wm.bounds(m.lighting, cfg.fit_vignetting, cfg.vignetting)
    rng = np.random.default_rng(cfg.bootstrap_seed)
    draws = []
    for _ in range(cfg.bootstrap_resamples):
        count = np.bincount(rng.integers(0, len(frames), len(frames)), minlength=len(frames))
        w = count[index].astype(float)
        rows = np.flatnonzero(w > 0)
        sol = wm.solve(s, m.lighting, photons, read, lo, hi, 0.1, rows=rows, weights=w[rows],
                       x0=m.x, max_nfev=60, tol=1e-5)  # fmt: skip
        draws.append(sol.x)
    m.rel_std_bootstrap, m.quantiles = block_std(np.asarray(draws))
    m.resamples = len(draws)


def fit_water(samples: PatchSamples, cfg: FitWaterConfig | None = None) -> WaterFit:
    """Fit the water model to the patches under each lighting model asked for, choose one by
    its error on held-out frames, and judge what the frames determine (see the module
    docstring and :mod:`datasets.water_fit_judge`).

    Raises:
        DockError: too few patches, no white or no black patch, ranges spanning less than
            ``cfg.min_range_spread_m``.
    """
    cfg = cfg or FitWaterConfig()
    cfg.validate()
    s = samples
    _check_samples(s, cfg)
    photons, read = estimate_noise(s, cfg.gamma)
    models, chosen = _fit_lightings(s, cfg, photons, read)
    x = chosen.x
    lighting = chosen.lighting
    p, vig = wm.unpack(x)
    rel = chosen.rel_std()
    rel_std = {b: tuple(float(v) for v in rel[b]) for b in wm.BLOCKS}
    params = {b: tuple(float(v) for v in p[b]) for b in wm.BLOCKS}
    model = _expected(wm.model(x, Geometry.of(s), lighting), photons, read)
    resid = model - s.rgb
    cerr = contrast_error(*_contrast(s, model))
    r_lo, r_hi = float(s.range_m.min()), float(s.range_m.max())
    separable = backscatter_separable(p["B_inf"], p["beta_B"], r_lo, r_hi)
    verdict = _verdict(chosen, models, (r_lo, r_hi), separable, cerr, cfg)
    warnings = _fit_warnings(verdict, params, chosen, cfg)
    water = _water_config(p, vig, lighting, photons, read, cfg)
    return WaterFit(
        water=water,
        params=params,
        rel_std=rel_std,
        vignetting=vig,
        residual_rms=float(np.sqrt(np.mean(resid**2))),
        residual_rms_8bit=float(
            np.sqrt(np.mean((_to_8bit(model, cfg.gamma) - _to_8bit(s.rgb, cfg.gamma)) ** 2))
        ),
        contrast_error=cerr,  # type: ignore[arg-type]
        range_m=(r_lo, r_hi),
        samples=s,
        config=cfg,
        separable=tuple(separable),  # type: ignore[arg-type]
        warnings=warnings,
        lighting=lighting,
        models=models,
        verdict=verdict,
        _x=x,
    )


def _check_samples(s: PatchSamples, cfg: FitWaterConfig) -> None:
    """Refuse patches without both albedo classes, too few of them, or too narrow a range."""
    if len(s) < 20 or s.white.all() or not s.white.any():
        raise DockError(
            f"the water fit needs black and white patches of the target: found {len(s)} "
            f"({int(s.white.sum())} white) in {s.frames_used} of {s.frames_read} frames"
        )
    spread = float(s.range_m.max() - s.range_m.min())
    if spread < cfg.min_range_spread_m:
        raise DockError(
            f"the target was seen from {s.range_m.min():.2f} to {s.range_m.max():.2f} m only: "
            f"the fit needs ranges spanning {cfg.min_range_spread_m:g} m or more (film it from "
            f"near and far)"
        )


def _fit_lightings(
    s: PatchSamples, cfg: FitWaterConfig, photons: float | None, read: float
) -> tuple[dict[str, ModelResult], ModelResult]:
    """Every lighting model asked for, fitted; the chosen one (by held-out error when there
    are several); the plausible ones bootstrapped."""
    lightings = cfg.lightings()
    models = {L: _fit_model(s, cfg, L, photons, read) for L in lightings}
    auto = len(lightings) > 1
    if auto and len(np.unique(s.frame)) < 3:
        raise DockError(
            f"choosing the lighting needs the target in 3 or more frames (found it in "
            f"{len(np.unique(s.frame))}): film more, or state it with --lighting"
        )
    if auto:
        chosen = _choose_lighting(s, cfg, models, photons, read)
    else:
        chosen = models[lightings[0]]
    for m in models.values():
        if m.plausible:
            _bootstrap(s, cfg, m, photons, read)
    return models, chosen


def _choose_lighting(
    s: PatchSamples,
    cfg: FitWaterConfig,
    models: dict[str, ModelResult],
    photons: float | None,
    read: float,
) -> ModelResult:
    """The models cross-validated and marked degenerate or plausible; the non-degenerate one
    with the least held-out error (any one when all are degenerate)."""
    for m in models.values():
        _cross_validate(s, cfg, m, photons, read)
        m.degenerate = lamp_not_seen(m)
    candidates = [m for m in models.values() if not m.degenerate] or list(models.values())
    best = min(m.heldout_rms for m in candidates)
    for m in models.values():
        m.plausible = not m.degenerate and (m.heldout_rms <= best * (1.0 + cfg.plausible_tolerance))
    return min(candidates, key=lambda m: m.heldout_rms)


def _verdict(
    chosen: ModelResult,
    models: dict[str, ModelResult],
    range_m: tuple[float, float],
    separable: list[bool],
    cerr: tuple[float, float, float],
    cfg: FitWaterConfig,
) -> Verdict:
    """What the frames determine (:func:`judge`); with the marker board, never beta_D."""
    verdict = judge(chosen, [m for m in models.values() if m is not chosen], range_m,
                    separable, cfg.max_rel_std, cfg.disagree_sigmas, cerr,
                    cfg.max_contrast_error)  # fmt: skip
    if cfg.target == "markers":  # rendered films: attenuation 18-173 % off, contrast within 3.4 %
        for ch in CHANNELS:
            verdict.reasons.setdefault(("beta_D", ch), []).append(
                "the marker board is an approximate target (on rendered films its attenuation "
                "came out 18-173 % off)"
            )
        verdict.determined["beta_D"] = [False, False, False]
        verdict.to_film.append("film a flat chessboard (--target chessboard) for the water file")
    return verdict


def _fit_warnings(
    verdict: Verdict,
    params: dict[str, tuple[float, ...]],
    chosen: ModelResult,
    cfg: FitWaterConfig,
) -> list[str]:
    """One line per undetermined value, then a poor fit and the marker board's caveat."""
    warnings = []
    for (b, ch), why in verdict.reasons.items():
        warnings.append(f"{b} {ch} = {params[b][CHANNELS.index(ch)]:.3g} is not determined by "
                        f"these frames: {'; '.join(why)}")  # fmt: skip
    if chosen.fit_rms_8bit > MISFIT_8BIT:
        warnings.append(
            f"no lighting model explains these frames well (residual {chosen.fit_rms_8bit:.1f} "
            f"grey levels; rendered films fit within 0.6): uneven or changing light (automatic "
            "exposure, room lights), a board that is not flat or glare; treat every value as "
            "approximate"
        )
    if cfg.target == "markers":
        warnings.append(
            "the marker board is an approximate target (small 3D markers, shaded): on rendered "
            "films its attenuation came out 18-173 % off where a chessboard's was within 10 % "
            "(bench/results/water_fit.json); film a flat chessboard for the water file"
        )
    return warnings


def _water_config(
    p: dict[str, np.ndarray],
    vig: float,
    lighting: str,
    photons: float | None,
    read: float,
    cfg: FitWaterConfig,
) -> WaterConfig:
    """The fitted values as a water file's config (the base preset's other fields), checked."""
    base = PRESETS[cfg.base]
    water = dataclasses.replace(
        base,
        beta_D_rgb=_rgb(np.clip(p["beta_D"], 0.0, 100.0)),
        beta_B_rgb=_rgb(np.clip(p["beta_B"], 0.0, 100.0)),
        B_inf_rgb=_rgb(np.clip(p["B_inf"], 0.0, 1.0)),
        vignetting=float(min(vig, 0.95)),
        artificial_light=lighting != "ambient",
        gamma=cfg.gamma,
        photons_at_white=photons if photons is not None else base.photons_at_white,
        read_noise=read,
    )
    water.validate()
    return water


def _rgb(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))
