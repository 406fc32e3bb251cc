"""The water fit's model of a patch's brightness under each lighting, its Jacobian, and one
weighted least-squares fit (used by :mod:`datasets.water_fit`).

Per channel ``c`` a patch of albedo class ``k`` (black or white) at range ``r`` reads::

    I_c = V * (J_kc * exp(-p beta_D_c r) + B_inf_c * (1 - exp(-beta_B_c r)))

with ``V = 1 - s rho**2`` the vignetting, and ``J`` and the path factor ``p`` set by the
lighting model (:data:`LIGHTINGS`):

* ``lamp``: a lamp beside the camera only: ``J = a_k * cos / d**2``, ``p = 2``;
* ``both``: the lamp plus a uniform ambient light, as the renderer lights a scene (its lamp and
  its ambient light, all of it attenuated over ``2 r``): ``J = a_k * (eta + cos / d**2)``,
  ``p = 2`` (``eta`` the ambient-to-lamp ratio);
* ``ambient``: tank or room lights only (no lamp term): ``J = a_k``, ``p = 1``: the light
  reaches the board along a path that does not grow with its range from the camera (the
  renderer's ``artificial_light = false``).

The parameters are the logarithms of ``a_white``, ``a_black`` (per channel), ``eta`` (one),
``beta_D``, ``B_inf``, ``beta_B`` (per channel) and the vignetting ``s`` itself; a parameter a
lighting model lacks is held at a fixed value (its bounds closed). The camera records the mean
of the noisy value clipped at zero (:func:`expected`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwdock.sim.water import PRESETS, WaterConfig

#: The lighting models the fit knows (see the module docstring).
LIGHTINGS = ("lamp", "ambient", "both")
#: Path factor of the direct signal per lighting model.
PATH = {"lamp": 2.0, "both": 2.0, "ambient": 1.0}

#: Parameter blocks of the fit (each per channel), in the order of the parameter vector.
BLOCKS = ("a_white", "a_black", "ambient", "beta_D", "B_inf", "beta_B")
#: Values per block: the ambient-to-lamp ratio is one (one lighting), the rest per channel.
SIZES = {b: 1 if b == "ambient" else 3 for b in BLOCKS}
#: Where each block sits in the parameter vector; the vignetting strength comes last.
SLICES = {
    b: slice(sum(SIZES[q] for q in BLOCKS[:i]), sum(SIZES[q] for q in BLOCKS[: i + 1]))
    for i, b in enumerate(BLOCKS)
}
N_PARAMS = sum(SIZES.values()) + 1
#: log bounds of each block (the values are exp of the parameters).
LOG_BOUNDS = {
    "a_white": (-12.0, 6.0),
    "a_black": (-14.0, 6.0),
    "ambient": (-14.0, 4.0),
    "beta_D": (-9.0, math.log(100.0)),
    "B_inf": (-14.0, 0.0),
    "beta_B": (-9.0, math.log(100.0)),
}
#: Vignetting bounds.
VIG_BOUNDS = (0.0, 0.95)
#: Per-patch uncertainty of the fit: relative and absolute (linear units, white = 1).
SIGMA_REL, SIGMA_ABS = 0.02, 0.002
#: Trust-region solver of :func:`scipy.optimize.least_squares`.
TR_SOLVER = "exact"
#: Steps taken from each of several starts before the best one is finished.
SCREEN_NFEV = 40
#: Log value at which a parameter a model lacks is held (``eta`` of ``lamp``, ``ambient``).
_HELD = -14.0


def unpack(x: np.ndarray) -> tuple[dict[str, np.ndarray], float]:
    """Block -> (3,) values (exp of the parameters) and the vignetting strength."""
    p = {b: np.broadcast_to(np.exp(x[SLICES[b]]), (3,)) for b in BLOCKS}
    return p, float(x[-1])


@dataclass(frozen=True)
class Geometry:
    """What the model needs of the patches (rows of :class:`water_fit.PatchSamples`).

    Attributes:
        white: (N,) True for a white patch.
        range_m: (N,) range of the patch from the camera (m).
        lamp_m: (N,) distance from the lamp (m).
        cos_lamp: (N,) cosine of the lamp's incidence.
        rho2: (N,) squared normalised distance from the image centre.
    """

    white: np.ndarray
    range_m: np.ndarray
    lamp_m: np.ndarray
    cos_lamp: np.ndarray
    rho2: np.ndarray

    @classmethod
    def of(cls, s: Any, rows: np.ndarray | None = None) -> Geometry:
        """The geometry of samples ``s`` (all rows, or ``rows``)."""
        sel = slice(None) if rows is None else rows
        return cls(s.white[sel], s.range_m[sel], s.lamp_m[sel], s.cos_lamp[sel], s.rho2[sel])


def _terms(x: np.ndarray, g: Geometry, lighting: str) -> dict[str, Any]:
    p, vig = unpack(x)
    r = g.range_m[:, None]
    a = np.where(g.white[:, None], p["a_white"], p["a_black"])
    lamp = (g.cos_lamp / g.lamp_m**2)[:, None]
    if lighting == "lamp":
        light = np.broadcast_to(lamp, a.shape)
    elif lighting == "both":
        light = p["ambient"][0] + lamp
    else:
        light = np.ones_like(a)
    E = np.exp(-PATH[lighting] * p["beta_D"] * r)
    F = np.exp(-p["beta_B"] * r)
    direct = a * light * E
    back = p["B_inf"] * (1.0 - F)
    V = (1.0 - vig * g.rho2)[:, None]
    return {"p": p, "r": r, "a": a, "E": E, "F": F, "direct": direct, "back": back, "V": V}


def model(x: np.ndarray, g: Geometry, lighting: str) -> np.ndarray:
    """(N, 3) modelled linear RGB of the patches (before the sensor's clipping)."""
    t = _terms(x, g, lighting)
    return t["V"] * (t["direct"] + t["back"])


def expected(m: np.ndarray, photons: float | None, read: float) -> np.ndarray:
    """The mean of a value ``m`` seen through the sensor's noise and clipped at 0 (the camera
    cannot record negative light: dark patches read brighter than their signal)."""
    from scipy.special import ndtr  # scipy costs 0.5 s to import: only for the fit

    var = read * read + (np.maximum(m, 0.0) / photons if photons else 0.0)
    sd = np.sqrt(np.maximum(var, 1e-18))
    z = m / sd
    return m * ndtr(z) + sd * np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def _expected_and_slope(
    m: np.ndarray, photons: float | None, read: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`expected` and its derivative with respect to ``m``."""
    from scipy.special import ndtr

    var = read * read + (np.maximum(m, 0.0) / photons if photons else 0.0)
    sd = np.sqrt(np.maximum(var, 1e-18))
    z = m / sd
    phi = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    Phi = ndtr(z)
    dsd = np.where(m > 0, 1.0 / (2.0 * sd * photons), 0.0) if photons else 0.0
    return m * Phi + sd * phi, Phi + phi * dsd


def _jacobian_m(x: np.ndarray, g: Geometry, lighting: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) model and (N, 3, P) its derivatives with respect to the parameters."""
    t = _terms(x, g, lighting)
    p, V, direct, back = t["p"], t["V"], t["direct"], t["back"]
    n = len(g.range_m)
    J = np.zeros((n, 3, N_PARAMS))
    ch = np.arange(3)
    for c in ch:
        J[:, c, SLICES["a_white"].start + c] = np.where(g.white, (V * direct)[:, c], 0.0)
        J[:, c, SLICES["a_black"].start + c] = np.where(g.white, 0.0, (V * direct)[:, c])
        J[:, c, SLICES["beta_D"].start + c] = (
            V * direct * (-PATH[lighting] * p["beta_D"] * t["r"])
        )[:, c]
        J[:, c, SLICES["B_inf"].start + c] = (V * back)[:, c]
        J[:, c, SLICES["beta_B"].start + c] = (V * p["B_inf"] * t["F"] * p["beta_B"] * t["r"])[:, c]
    if lighting == "both":
        J[:, :, SLICES["ambient"].start] = V * t["a"] * p["ambient"][0] * t["E"]
    J[:, :, -1] = -g.rho2[:, None] * (direct + back)
    return V * (direct + back), J


def bounds(lighting: str, fit_vignetting: bool, vignetting: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the parameter vector for a lighting model (a parameter the
    model lacks, or the vignetting when it is not fitted, held by closed bounds)."""
    lo = np.concatenate([np.repeat(LOG_BOUNDS[b][0], SIZES[b]) for b in BLOCKS] + [[VIG_BOUNDS[0]]])
    hi = np.concatenate([np.repeat(LOG_BOUNDS[b][1], SIZES[b]) for b in BLOCKS] + [[VIG_BOUNDS[1]]])
    if lighting != "both":
        k = SLICES["ambient"].start
        lo[k], hi[k] = _HELD - 1e-9, _HELD + 1e-9
    if not fit_vignetting:
        lo[-1], hi[-1] = vignetting - 1e-9, vignetting + 1e-9
    return lo, hi


def free_parameters(lighting: str, fit_vignetting: bool) -> int:
    """Number of parameters a lighting model fits."""
    return N_PARAMS - (0 if lighting == "both" else 1) - (0 if fit_vignetting else 1)


def start(s: Any, water: WaterConfig, vig: float, lighting: str) -> np.ndarray:
    """A starting point: the preset's water, albedo scales from the nearest patches."""
    near = s.range_m <= np.quantile(s.range_m, 0.2)
    light = 1.0 / np.maximum(s.lamp_m, 0.1) ** 2 if lighting != "ambient" else np.ones(len(s))
    x = np.zeros(N_PARAMS)
    path = PATH[lighting]

    def scale(mask: np.ndarray) -> np.ndarray:
        m = mask & near
        if not m.any():
            m = mask
        decay = np.exp(-path * np.asarray(water.beta_D_rgb) * s.range_m[m, None])
        v = s.rgb[m] / (light[m, None] * decay)
        return np.log(np.clip(np.median(v, axis=0), 1e-5, 1e2))

    x[SLICES["a_white"]] = scale(s.white)
    x[SLICES["a_black"]] = scale(~s.white) if (~s.white).any() else x[SLICES["a_white"]] - 3
    x[SLICES["ambient"]] = math.log(0.05) if lighting == "both" else _HELD
    x[SLICES["beta_D"]] = np.log(np.clip(water.beta_D_rgb, 1e-3, 50))
    x[SLICES["B_inf"]] = np.log(np.clip(water.B_inf_rgb, 1e-3, 1))
    x[SLICES["beta_B"]] = np.log(np.clip(water.beta_B_rgb, 1e-3, 50))
    x[-1] = vig
    return x


@dataclass
class Solution:
    """One least-squares fit: parameters, cost (half the sum of squared weighted residuals),
    the weighted residuals and their Jacobian."""

    x: np.ndarray
    cost: float
    fun: np.ndarray
    jac: np.ndarray


def solve(
    s: Any,
    lighting: str,
    photons: float | None,
    read: float,
    lo: np.ndarray,
    hi: np.ndarray,
    vig0: float,
    rows: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    x0: np.ndarray | None = None,
    max_nfev: int = 400,
    tol: float = 1e-8,
) -> Solution:
    """Fit one lighting model by weighted least squares (analytic Jacobian).

    Args:
        s: the patches (:class:`water_fit.PatchSamples`).
        lighting: one of :data:`LIGHTINGS`.
        photons, read: the sensor noise (:func:`expected`).
        lo, hi: parameter bounds (:func:`bounds`).
        vig0: starting vignetting.
        rows: (M,) the patches used (all when None).
        weights: (M,) a weight per patch used (a frame's multiplicity in a bootstrap draw).
        x0: start here (one start); None: four starts from the presets, the best kept.
        max_nfev: most function evaluations per start.
        tol: relative change of the cost and the parameters at which a start stops (``ftol``,
            ``xtol`` of :func:`scipy.optimize.least_squares`).
    """
    from scipy.optimize import least_squares  # scipy costs 0.5 s to import: only for the fit

    sel = np.arange(len(s)) if rows is None else np.asarray(rows)
    g = Geometry.of(s, sel)
    obs = s.rgb[sel]
    sigma = SIGMA_REL * obs + SIGMA_ABS
    w = np.ones(len(sel)) if weights is None else np.asarray(weights, float)
    scale = (np.sqrt(w)[:, None] / sigma).ravel()
    free = hi - lo > 1e-6

    held = np.where(free, 0.0, 0.5 * (lo + hi))  # a parameter the model lacks: held here

    def full(z: np.ndarray) -> np.ndarray:
        x = held.copy()
        x[free] = z
        return x

    def residual(z: np.ndarray) -> np.ndarray:
        return (expected(model(full(z), g, lighting), photons, read) - obs).ravel() * scale

    def jac(z: np.ndarray) -> np.ndarray:
        m, dm = _jacobian_m(full(z), g, lighting)
        _, slope = _expected_and_slope(m, photons, read)
        return (dm[:, :, free] * slope[:, :, None]).reshape(len(scale), -1) * scale[:, None]

    starts = (
        [x0]
        if x0 is not None
        else [
            start(s, PRESETS[n], vig0, lighting)
            for n in ("clear_tank", "coastal", "turbid", "very_turbid")
        ]
    )

    def run(x_start: np.ndarray, nfev: int) -> Any:
        z0 = np.clip(x_start[free], lo[free] + 1e-7, hi[free] - 1e-7)
        return least_squares(residual, z0, jac=jac, bounds=(lo[free], hi[free]), x_scale="jac",
                             max_nfev=nfev, ftol=tol, xtol=tol, tr_solver=TR_SOLVER)  # fmt: skip

    if len(starts) == 1:
        best = run(starts[0], max_nfev)
    else:  # several starts: a few steps from each, then the best one finished
        best = min((run(x, SCREEN_NFEV) for x in starts), key=lambda r: r.cost)
        if best.status == 0:  # stopped by the step limit
            best = run(full(best.x), max_nfev)
    J = np.zeros((best.fun.size, N_PARAMS))
    J[:, free] = best.jac
    return Solution(full(best.x), float(best.cost), best.fun, J)


def log_std(J: np.ndarray, scale: float) -> np.ndarray:
    """Standard errors of the (log) parameters from the Jacobian of the weighted residuals: a
    parameter the residuals do not depend on (a backscatter already saturated at the nearest
    range) gets a huge one, not the zero a pseudo-inverse would give it."""
    JtJ = J.T @ J
    ridge = 1e-12 * max(float(np.abs(np.diag(JtJ)).max()), 1e-300)
    try:
        cov = np.linalg.inv(JtJ + ridge * np.eye(len(JtJ))) * scale
    except np.linalg.LinAlgError:  # pragma: no cover - the ridge keeps it invertible
        return np.full(len(JtJ), np.inf)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))
