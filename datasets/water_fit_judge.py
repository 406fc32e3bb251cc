"""What the footage can and cannot tell (used by :mod:`datasets.water_fit`): the lighting
models compared on held-out frames, the uncertainty from a bootstrap over frames, and per
parameter and channel whether the frames determine it, with what to film where they do not.

* **Held-out frames.** The frames are sorted by their median range and dealt round-robin into
  ``k`` folds (leave-one-frame-out when there are no more frames than folds): each fold then
  spans the ranges seen, and there is no random draw. Each lighting model is fitted on the
  other folds (started from its fit on all frames) and predicts the fold's patches; its
  held-out error is the RMS of those residuals in units of the patch uncertainty (and, for the
  reader, in 8-bit grey levels).
* **Plausible models**: those whose held-out error is within ``plausible_tolerance`` of the
  best; the one with the least held-out error is chosen. A lamp-plus-ambient fit whose
  ambient-to-lamp ratio runs to its upper bound (the lamp's share of the light then only a few
  per cent and free to vanish), or whose lamp gives less than :data:`LAMP_SEEN_SHARE` of the
  light at every patch, is *not* a lamp model (a uniform light attenuated over twice the range,
  which no lamp gives) and is left out. On rendered lamp-off films the ratio always ran to its
  bound; a weak real lamp (10 % of the light at the nearest patch) left it well inside.
* **Bootstrap over frames**: whole frames are resampled with replacement (seeded), each
  resample refitted (started from the fit on all frames); the spread of each parameter's
  logarithm (half the 16-84 % interval) is its relative uncertainty. The decisions use the
  larger of that and the Jacobian's standard error: on a real tank the Jacobian said +-1 %
  where the lighting models disagreed tenfold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from uwdock.datasets import water_fit_model as wm

CHANNELS = ("R", "G", "B")
#: The parameters whose determination is judged (the water file's, per channel).
JUDGED = ("beta_D", "B_inf", "beta_B")
#: A lamp-plus-ambient fit is a lamp model only when the lamp gives at least this share of the
#: light at the nearest patch (and its ambient-to-lamp ratio is not at its bound).
LAMP_SEEN_SHARE = 0.02
#: A log parameter within this of its bound sits at the bound.
AT_BOUND = 0.01
#: Below this veiling light (linear, white = 1) a channel shows no backscatter to speak of.
NO_BACKSCATTER = 0.01


def frame_folds(frame: np.ndarray, range_m: np.ndarray, k: int) -> np.ndarray:
    """(N,) fold of each patch: frames sorted by their median range, dealt round-robin into
    ``min(k, frames)`` folds (``k = 0``: one fold per frame)."""
    frames = np.unique(frame)
    med = np.array([np.median(range_m[frame == f]) for f in frames])
    order = frames[np.lexsort((frames, med))]
    n_folds = len(frames) if k <= 0 else min(k, len(frames))
    fold_of = {int(f): i % n_folds for i, f in enumerate(order)}
    return np.array([fold_of[int(f)] for f in frame], int)


@dataclass
class ModelResult:
    """One lighting model fitted to all frames, its held-out error and its uncertainty.

    Attributes:
        lighting: the model (:data:`water_fit_model.LIGHTINGS`).
        x: fitted parameter vector (all frames).
        cost: half the sum of squared weighted residuals (all frames).
        n_free: parameters fitted.
        rel_std_jacobian: block -> (3,) relative standard errors from the Jacobian.
        rel_std_bootstrap: block -> (3,) half the 16-84 % interval of the log parameter over
            the bootstrap resamples (empty when not bootstrapped).
        quantiles: block -> (q16 (3,), q84 (3,)) over the resamples.
        heldout_rms: RMS held-out residual (units of the patch uncertainty); nan without
            cross-validation.
        heldout_rms_8bit: the same in 8-bit grey levels.
        fit_rms_8bit: in-sample residual RMS (8-bit grey levels).
        lamp_share: largest share of the light the lamp gives at a patch (1 for ``lamp``, 0 for
            ``ambient``).
        degenerate: why the model is not what it says (empty when it is).
        plausible: held-out error within the tolerance of the best (and not degenerate).
        resamples: bootstrap resamples fitted.
    """

    lighting: str
    x: np.ndarray
    cost: float
    n_free: int
    rel_std_jacobian: dict[str, np.ndarray]
    rel_std_bootstrap: dict[str, np.ndarray] = field(default_factory=dict)
    quantiles: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    heldout_rms: float = float("nan")
    heldout_rms_8bit: float = float("nan")
    fit_rms_8bit: float = float("nan")
    lamp_share: float = 0.0
    degenerate: str = ""
    plausible: bool = True
    resamples: int = 0

    @property
    def params(self) -> dict[str, np.ndarray]:
        """Block -> (3,) values."""
        p, _ = wm.unpack(self.x)
        return {b: np.array(v, float) for b, v in p.items()}

    def rel_std(self) -> dict[str, np.ndarray]:
        """Block -> (3,) the larger of the Jacobian's and the bootstrap's relative uncertainty."""
        out = {}
        for b, v in self.rel_std_jacobian.items():
            boot = self.rel_std_bootstrap.get(b)
            out[b] = np.maximum(v, boot) if boot is not None else np.asarray(v, float)
        return out

    def summary(self) -> dict[str, Any]:
        """JSON-ready record of the model."""
        p = self.params
        return {
            "plausible": self.plausible,
            "degenerate": self.degenerate or None,
            "heldout_rms": _num(self.heldout_rms),
            "heldout_rms_8bit": _num(self.heldout_rms_8bit),
            "fit_rms_8bit": _num(self.fit_rms_8bit),
            "free_parameters": self.n_free,
            "lamp_share_max": round(float(self.lamp_share), 4),
            "params": {b: [float(v) for v in p[b]] for b in (*JUDGED, "ambient")},
            "rel_std": {b: [float(v) for v in self.rel_std()[b]] for b in JUDGED},
            "rel_std_jacobian": {b: [float(v) for v in self.rel_std_jacobian[b]] for b in JUDGED},
            "rel_std_bootstrap": {
                b: [float(v) for v in self.rel_std_bootstrap[b]]
                for b in JUDGED
                if b in self.rel_std_bootstrap
            },
            "bootstrap_resamples": self.resamples,
        }


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def lamp_not_seen(m: ModelResult) -> str:
    """Why a lamp-plus-ambient fit is not a lamp model ("" when it is one)."""
    if m.lighting != "both":
        return ""
    at_bound = float(m.x[wm.SLICES["ambient"]][0]) >= wm.LOG_BOUNDS["ambient"][1] - 0.05
    if at_bound or m.lamp_share < LAMP_SEEN_SHARE:
        return (
            f"the lamp's share of the light runs to nothing (at most {100 * m.lamp_share:.1f} % "
            "at any patch, the ambient light at its bound): a uniform light attenuated over twice "
            "the range, which no lamp gives"
        )
    return ""


def lamp_share(x: np.ndarray, s: Any, lighting: str) -> float:
    """The largest share of the light the lamp gives at a patch under a model."""
    if lighting == "ambient":
        return 0.0
    if lighting == "lamp":
        return 1.0
    eta = float(np.exp(x[wm.SLICES["ambient"]])[0])
    lamp = s.cos_lamp / s.lamp_m**2
    return float(np.max(lamp / (eta + lamp)))


def block_std(x_draws: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, tuple]]:
    """Half the 16-84 % interval of each log parameter over resamples ``x_draws`` (B, P) and
    the 16 % and 84 % values themselves."""
    q16, q84 = np.percentile(x_draws, [15.865, 84.135], axis=0)
    std, quant = {}, {}
    for b in wm.BLOCKS:
        sl = wm.SLICES[b]
        std[b] = np.broadcast_to(0.5 * (q84[sl] - q16[sl]), (3,)).astype(float)
        quant[b] = (
            np.broadcast_to(np.exp(q16[sl]), (3,)).astype(float),
            np.broadcast_to(np.exp(q84[sl]), (3,)).astype(float),
        )
    return std, quant


def _q84(m: ModelResult, block: str, c: int) -> float:
    """The 84 % value of a parameter over the resamples (the value itself without them)."""
    return float(m.quantiles[block][1][c]) if m.quantiles else float(m.params[block][c])


@dataclass
class Verdict:
    """Whether each judged parameter is determined, why not, and what to film.

    Attributes:
        determined: block -> (3,) bools.
        reasons: (block, channel) -> reasons it is not determined.
        to_film: what to film (or state) to pin the undetermined values down, one line each.
    """

    determined: dict[str, list[bool]]
    reasons: dict[tuple[str, str], list[str]]
    to_film: list[str]

    def undetermined(self) -> list[dict[str, Any]]:
        """JSON-ready list of the undetermined values and why."""
        return [{"param": b, "channel": c, "why": why} for (b, c), why in self.reasons.items()]


def judge(
    chosen: ModelResult,
    others: list[ModelResult],
    range_m: tuple[float, float],
    separable: list[bool],
    max_rel_std: float,
    disagree_sigmas: float,
    contrast_error: tuple[float, ...] = (0.0, 0.0, 0.0),
    max_contrast_error: float = 1.0,
) -> Verdict:
    """Per judged parameter and channel of the chosen model: determined unless it sits at a
    bound, its backscatter is not separable over the ranges seen (or there is none), its
    uncertainty exceeds ``max_rel_std``, or a plausible other lighting model gives a value
    more than ``disagree_sigmas`` combined uncertainties away; and the attenuation of a channel
    whose modelled contrast misses the measured one by more than ``max_contrast_error`` (the
    model does not explain the frames)."""
    p, u = chosen.params, chosen.rel_std()
    lo_r, hi_r = range_m
    reasons: dict[tuple[str, str], list[str]] = {}
    film: list[str] = []
    far_back: dict[str, float] = {}  # channel -> where its backscatter levels off (m)
    near_back: list[str] = []  # channels whose backscatter is saturated at the nearest range
    misfit: list[str] = []  # channels whose contrast the model misses
    cover_to = 0.0  # how far the board should be filmed for an uncertain beta_D (m)
    disagree_models: set[str] = set()
    for c, ch in enumerate(CHANNELS):
        for b in JUDGED:
            why: list[str] = []
            v = float(p[b][c])
            lv = math.log(max(v, 1e-300))
            lo_b, hi_b = wm.LOG_BOUNDS[b]
            no_back = float(p["B_inf"][c]) < NO_BACKSCATTER
            if lv >= hi_b - AT_BOUND or (lv <= lo_b + AT_BOUND and b != "B_inf"):
                why.append(f"sits at its bound {v:.3g}")
                if b == "B_inf":
                    far_back[ch] = max(far_back.get(ch, 0.0), 1.5 * hi_r)
            if b == "beta_B" and no_back:
                why.append("no backscatter seen (B_inf < 0.01): it does not matter in renders")
            if b in ("B_inf", "beta_B") and not no_back and not separable[c]:
                beta_b = float(p["beta_B"][c])
                if beta_b * lo_r > 2.0:
                    why.append("not separable: the backscatter is saturated at the nearest range")
                    near_back.append(ch)
                else:
                    why.append("not separable: the backscatter hardly bends over the ranges seen")
                    far = min(max(2.0 / max(beta_b, 1e-3), hi_r * 1.5), max(4 * hi_r, hi_r + 2))
                    far_back[ch] = max(far_back.get(ch, 0.0), far)
            # no veiling light to speak of: B_inf is ~0 (its logarithm is free) unless the
            # resamples put it higher
            near_zero = b == "B_inf" and no_back and _q84(chosen, "B_inf", c) < 2 * NO_BACKSCATTER
            if not (b == "beta_B" and no_back) and not near_zero and u[b][c] > max_rel_std:
                why.append(f"uncertain: +-{100 * u[b][c]:.0f} %")
                if b == "beta_D":
                    # two attenuation lengths of the direct signal, at most four times the
                    # farthest range seen (a value near 0 asks for "much farther", not 1/0)
                    want = max(2.0 * (hi_r - lo_r), 2.0 / (wm.PATH[chosen.lighting] * max(v, 1e-3)))
                    cover_to = max(cover_to, min(lo_r + want, max(4.0 * hi_r, hi_r + 2.0)))
            for o in others:
                if not o.plausible or ((b == "beta_B" or near_zero) and no_back):
                    continue
                vo, uo = float(o.params[b][c]), float(o.rel_std()[b][c])
                gap = abs(lv - math.log(max(vo, 1e-300)))
                if gap > disagree_sigmas * math.hypot(u[b][c], uo) and gap > 0.05:
                    why.append(
                        f"the {o.lighting} lighting model fits the held-out frames about as well "
                        f"and gives {vo:.3g} (+-{100 * uo:.0f} %)"
                    )
                    disagree_models.add(o.lighting)
            if b == "beta_D" and contrast_error[c] > max_contrast_error:
                why.append(
                    f"the model misses the measured contrast by {100 * contrast_error[c]:.0f} %"
                )
                misfit.append(ch)
            if why:
                reasons[(b, ch)] = why
    if disagree_models:
        names = sorted({chosen.lighting, *disagree_models})
        if "ambient" in names:
            film.insert(
                0,
                "the frames do not tell the lighting apart ("
                + ", ".join(names)
                + "): film again with the tank and room lights off and only the lamp on "
                "(or the lamp off), from as near as the board fits the image, or state the "
                "lighting with --lighting lamp|ambient|both",
            )
        else:
            film.insert(
                0,
                "the frames do not tell a lamp alone from a lamp plus ambient light apart: film "
                "once with the tank and room lights off, or state it with --lighting lamp|both",
            )
    determined = {b: [(b, ch) not in reasons for ch in CHANNELS] for b in JUDGED}
    if cover_to > 0.0:
        film.append(
            f"film the board over a wider range of distances: seen at {lo_r:.2f}-{hi_r:.2f} m, "
            f"cover {max(lo_r * 0.7, 0.3):.1f}-{cover_to:.1f} m"
        )
    if misfit:
        film.append(
            f"no lighting model explains the contrast of {', '.join(misfit)}: film with steady "
            "light (automatic exposure and gain off), a flat matte board without glare, the "
            "lighting stated with --lighting"
        )
    if far_back:
        film.append(
            f"film farther (towards {max(far_back.values()):.1f} m, as far as the board is "
            f"found; seen to {hi_r:.2f} m) so that the black level of "
            f"{', '.join(sorted(far_back, key=CHANNELS.index))} levels off towards its veiling "
            "light"
        )
    if near_back:
        film.append(
            f"film nearer than {lo_r:.2f} m to see the backscatter of "
            f"{', '.join(dict.fromkeys(near_back))} grow"
        )
    return Verdict(determined, reasons, list(dict.fromkeys(film)))
