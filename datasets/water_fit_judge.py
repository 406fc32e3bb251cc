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
    judging = _Judging(chosen, others, range_m, separable, max_rel_std, disagree_sigmas,
                       contrast_error, max_contrast_error)  # fmt: skip
    reasons: dict[tuple[str, str], list[str]] = {}
    for c, ch in enumerate(CHANNELS):
        for b in JUDGED:
            why = judging.reasons(b, c)
            if why:
                reasons[(b, ch)] = why
    determined = {b: [(b, ch) not in reasons for ch in CHANNELS] for b in JUDGED}
    return Verdict(determined, reasons, judging.to_film())


@dataclass
class _Judging:
    """One :func:`judge` call: its inputs, the reasons of each parameter and channel, and what
    those reasons ask to be filmed (gathered over all of them)."""

    chosen: ModelResult
    others: list[ModelResult]
    range_m: tuple[float, float]
    separable: list[bool]
    max_rel_std: float
    disagree_sigmas: float
    contrast_error: tuple[float, ...]
    max_contrast_error: float
    #: channel -> where its backscatter levels off (m)
    far_back: dict[str, float] = field(default_factory=dict)
    #: channels whose backscatter is saturated at the nearest range
    near_back: list[str] = field(default_factory=list)
    #: channels whose contrast the model misses
    misfit: list[str] = field(default_factory=list)
    #: how far the board should be filmed for an uncertain beta_D (m)
    cover_to: float = 0.0
    #: the lighting models that disagree with the chosen one
    disagree_models: set[str] = field(default_factory=set)
    #: the chosen model's values and relative uncertainties (block -> (3,))
    params: dict[str, np.ndarray] = field(init=False)
    rel_std: dict[str, np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        self.params, self.rel_std = self.chosen.params, self.chosen.rel_std()

    def reasons(self, b: str, c: int) -> list[str]:
        """Why block ``b`` of channel ``c`` is not determined (empty: it is)."""
        v = float(self.params[b][c])
        lv = math.log(max(v, 1e-300))
        no_back = float(self.params["B_inf"][c]) < NO_BACKSCATTER
        why = self._at_bound(b, c, v, lv) + self._backscatter(b, c, no_back)
        # no veiling light to speak of: B_inf is ~0 (its logarithm is free) unless the
        # resamples put it higher
        near_zero = b == "B_inf" and no_back and _q84(self.chosen, "B_inf", c) < 2 * NO_BACKSCATTER
        if not (b == "beta_B" and no_back) and not near_zero:
            why += self._uncertain(b, c, v)
        if not ((b == "beta_B" or near_zero) and no_back):
            why += self._disagreeing(b, c, lv)
        if b == "beta_D" and self.contrast_error[c] > self.max_contrast_error:
            why.append(
                f"the model misses the measured contrast by {100 * self.contrast_error[c]:.0f} %"
            )
            self.misfit.append(CHANNELS[c])
        return why

    def _at_bound(self, b: str, c: int, v: float, lv: float) -> list[str]:
        """The value at its bound (a veiling light at its upper one: film farther)."""
        lo_b, hi_b = wm.LOG_BOUNDS[b]
        if not (lv >= hi_b - AT_BOUND or (lv <= lo_b + AT_BOUND and b != "B_inf")):
            return []
        if b == "B_inf":
            ch = CHANNELS[c]
            self.far_back[ch] = max(self.far_back.get(ch, 0.0), 1.5 * self.range_m[1])
        return [f"sits at its bound {v:.3g}"]

    def _backscatter(self, b: str, c: int, no_back: bool) -> list[str]:
        """No backscatter seen (for beta_B), or B_inf and beta_B not separable: saturated at the
        nearest range (film nearer) or hardly bending over the ranges seen (film farther)."""
        lo_r, hi_r = self.range_m
        ch = CHANNELS[c]
        why = []
        if b == "beta_B" and no_back:
            why.append("no backscatter seen (B_inf < 0.01): it does not matter in renders")
        if b in ("B_inf", "beta_B") and not no_back and not self.separable[c]:
            beta_b = float(self.params["beta_B"][c])
            if beta_b * lo_r > 2.0:
                why.append("not separable: the backscatter is saturated at the nearest range")
                self.near_back.append(ch)
            else:
                why.append("not separable: the backscatter hardly bends over the ranges seen")
                far = min(max(2.0 / max(beta_b, 1e-3), hi_r * 1.5), max(4 * hi_r, hi_r + 2))
                self.far_back[ch] = max(self.far_back.get(ch, 0.0), far)
        return why

    def _uncertain(self, b: str, c: int, v: float) -> list[str]:
        """An uncertainty above ``max_rel_std`` (for beta_D: how far to film to pin it down)."""
        u = self.rel_std[b][c]
        if math.isnan(u):  # neither the Jacobian nor the bootstrap gave one: not determined
            return ["uncertain: no finite uncertainty (the frames do not constrain it)"]
        if not u > self.max_rel_std:
            return []
        if b == "beta_D":
            lo_r, hi_r = self.range_m
            # two attenuation lengths of the direct signal, at most four times the
            # farthest range seen (a value near 0 asks for "much farther", not 1/0)
            want = max(2.0 * (hi_r - lo_r), 2.0 / (wm.PATH[self.chosen.lighting] * max(v, 1e-3)))
            self.cover_to = max(self.cover_to, min(lo_r + want, max(4.0 * hi_r, hi_r + 2.0)))
        return [f"uncertain: +-{100 * self.rel_std[b][c]:.0f} %"]

    def _disagreeing(self, b: str, c: int, lv: float) -> list[str]:
        """The plausible other lighting models whose value lies beyond the uncertainties."""
        why = []
        for o in self.others:
            if not o.plausible:
                continue
            vo, uo = float(o.params[b][c]), float(o.rel_std()[b][c])
            gap = abs(lv - math.log(max(vo, 1e-300)))
            if gap > self.disagree_sigmas * math.hypot(self.rel_std[b][c], uo) and gap > 0.05:
                why.append(
                    f"the {o.lighting} lighting model fits the held-out frames about as well "
                    f"and gives {vo:.3g} (+-{100 * uo:.0f} %)"
                )
                self.disagree_models.add(o.lighting)
        return why

    def to_film(self) -> list[str]:
        """What to film (or state) to pin the undetermined values down, one line each."""
        lo_r, hi_r = self.range_m
        film = [] if not self.disagree_models else [self._lighting_line()]
        if self.cover_to > 0.0:
            film.append(
                f"film the board over a wider range of distances: seen at {lo_r:.2f}-{hi_r:.2f} "
                f"m, cover {max(lo_r * 0.7, 0.3):.1f}-{self.cover_to:.1f} m"
            )
        if self.misfit:
            film.append(
                f"no lighting model explains the contrast of {', '.join(self.misfit)}: film with "
                "steady light (automatic exposure and gain off), a flat matte board without "
                "glare, the lighting stated with --lighting"
            )
        if self.far_back:
            film.append(
                f"film farther (towards {max(self.far_back.values()):.1f} m, as far as the board "
                f"is found; seen to {hi_r:.2f} m) so that the black level of "
                f"{', '.join(sorted(self.far_back, key=CHANNELS.index))} levels off towards its "
                "veiling light"
            )
        if self.near_back:
            film.append(
                f"film nearer than {lo_r:.2f} m to see the backscatter of "
                f"{', '.join(dict.fromkeys(self.near_back))} grow"
            )
        return list(dict.fromkeys(film))

    def _lighting_line(self) -> str:
        """What to film when plausible lighting models disagree on a value."""
        names = sorted({self.chosen.lighting, *self.disagree_models})
        if "ambient" in names:
            return (
                "the frames do not tell the lighting apart ("
                + ", ".join(names)
                + "): film again with the tank and room lights off and only the lamp on "
                "(or the lamp off), from as near as the board fits the image, or state the "
                "lighting with --lighting lamp|ambient|both"
            )
        return (
            "the frames do not tell a lamp alone from a lamp plus ambient light apart: film "
            "once with the tank and room lights off, or state it with --lighting lamp|both"
        )
