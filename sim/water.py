"""Underwater image formation: a fast post-process of a rendered RGB image and its range image.

Model (Akkaynak & Treibitz's revised image formation model, per colour channel c, per pixel with
range ``r`` along the viewing ray, in linear RGB)::

    I_c = V * (J_c * blur(r) * exp(-beta_D_c * r * (1 + lamp)) * F(r)
               + B_inf_c * (1 - exp(-beta_B_c * r)))

* ``J`` is the scene radiance as rendered (in air), ``exp(-beta_D r)`` the direct attenuation and
  ``B_inf (1 - exp(-beta_B r))`` the backscatter (veiling light); pixels where nothing was hit
  (``r = inf``) get pure veiling light ``B_inf``.
* ``blur(r)``: forward scatter, a Gaussian blur whose sigma grows linearly with range; cheap:
  a few pre-blurred levels (computed at reduced resolution) blended per pixel by range.
* ``lamp``: 1 when the scene is lit by the vehicle's lamp beside the camera (``artificial_light``):
  the light then also travels lamp -> object through the water, so the direct signal is attenuated
  over ``2 r``. ``F(r) = min(1, (r_ref / r) ** p)`` is an extra geometric falloff for renders made
  without a physical lamp (``p = 2``); render.py's lamp already falls off as ``1 / d**2``
  (SAPIEN point light), hence ``p = 0`` by default.
* ``V``: lens vignetting ``1 - s * rho**2`` (``rho`` = distance from the image centre, 1 at the
  corners).
* the camera's exposure ``e`` scales what reaches the sensor: fixed, or set per frame by a
  highlight-protecting auto exposure (the 99.5th percentile of the frame's brightest channel
  lands at 85 % of full scale, ``e`` never above its maximum; :func:`exposure_for`);
* then Poisson-Gaussian sensor noise (Gaussian approximation with the Poisson variance:
  ``sigma**2 = I / photons_at_white + read_noise**2``), the sensor's clipping at full scale,
  gamma encoding and optional JPEG.

The input is the render's linear radiance, float and unclipped (``sim.render`` keeps the light
linear: the sensor is the only place it clips), or a uint8 image display-encoded with ``gamma``
(decoded first). The output is uint8, display-encoded with ``gamma``.

Presets (beta values from the Jerlov tables in docs/anchors.md; beta_D = diffuse attenuation
K_d of the type, beta_B = beam attenuation c of the type, an upper bound suited to backscatter):

=============  =================================  =========================================
preset         Jerlov type                         B_inf (linear RGB; our choice, fit to footage)
=============  =================================  =========================================
clear_tank     I  (clearest ocean; a clean pool)   (0.02, 0.15, 0.14)  dim bluish
coastal        3C (coastal)                        (0.00, 0.31, 0.24)  anchors.md's greenish
turbid         7C (turbid coastal)                 (0.03, 0.34, 0.25)
very_turbid    9C (most turbid coastal)            (0.05, 0.36, 0.26)
=============  =================================  =========================================

Example:
    >>> rng = np.random.default_rng(0)
    >>> out = apply_water(result.radiance, result.range_m, PRESETS["coastal"], rng)
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
from dataclasses import dataclass
from typing import Annotated

import cv2
import numpy as np

from uwdock.dockcore.config import check_fields, from_dict, read_toml
from uwdock.dockcore.domains import Fraction, Interval
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.sim.domains import RGB as ColourRGB

__all__ = [
    "FAR_M",
    "JERLOV_BEAM_C_RGB",
    "JERLOV_KD_RGB",
    "PRESETS",
    "PRESET_ORDER",
    "WATER_FILE_NOTES",
    "Water",
    "WaterConfig",
    "WaterRandomisation",
    "apply_water",
    "blur_level",
    "decode_lut",
    "exposure_for",
    "is_water_file",
    "jpeg_roundtrip",
    "load_water_file",
    "meter_level",
    "meter_rank",
    "meter_step",
    "noise_bank",
    "noise_draw",
    "preset",
    "resolve_water",
    "vignette",
    "water_choice",
    "water_file_notes",
    "water_spec_error",
]

RGB = tuple[float, float, float]

#: Effective RGB diffuse attenuation K_d (1/m) of the Jerlov water types (anchors.md).
JERLOV_KD_RGB: dict[str, RGB] = {
    "I": (0.24, 0.06, 0.02),
    "II": (0.27, 0.10, 0.07),
    "III": (0.31, 0.14, 0.13),
    "1C": (0.32, 0.16, 0.21),
    "3C": (0.35, 0.23, 0.33),
    "5C": (0.43, 0.35, 0.48),
    "7C": (0.53, 0.53, 0.76),
    "9C": (0.67, 0.80, 1.31),
}

#: RGB beam attenuation c = a + b (1/m) of the Jerlov water types (anchors.md).
JERLOV_BEAM_C_RGB: dict[str, RGB] = {
    "I": (0.46, 0.06, 0.02),
    "II": (0.71, 0.42, 0.55),
    "III": (1.15, 1.05, 1.47),
    "1C": (0.73, 0.44, 0.65),
    "3C": (1.23, 1.14, 1.74),
    "5C": (1.45, 1.45, 2.29),
    "7C": (2.22, 2.55, 4.05),
    "9C": (2.79, 3.47, 5.62),
}

#: Range (m) standing in for "nothing hit" (r = inf) in the exponentials.
FAR_M = 1.0e4

#: Largest attenuation or backscatter coefficient (1/m): the most turbid Jerlov type (9C) has
#: 5.6/m in blue; at 100/m nothing beyond 5 cm is seen.
_BETA_MAX = 100.0
#: An attenuation or backscatter coefficient (1/m).
_Beta = Annotated[float, Interval(ge=0, le=_BETA_MAX)]
#: Photo-electrons at white: below 1 the shot noise swamps the image; sensors collect 1e3-1e5.
_Photons = Annotated[float, Interval(ge=1, le=1e9)]
#: A JPEG quality.
_JpegQuality = Annotated[int, Interval(ge=1, le=100)]
#: A vignetting strength (-): 1 would black out the corners.
_Vignetting = Annotated[float, Interval(ge=0, lt=1)]
#: Standard deviation of the read noise (linear units, white = 1).
_ReadNoise = Annotated[float, Interval(ge=0, le=1)]
#: A random scale factor on a water parameter (-).
_Scale = Annotated[float, Interval(ge=0, le=10)]


@dataclass(frozen=True)
class WaterConfig:
    """Water and camera-sensor effects applied to a rendered frame.

    Attributes:
        beta_D_rgb: direct-signal attenuation coefficient per channel R, G, B (1/m), in
            [0, 100].
        beta_B_rgb: backscatter coefficient per channel (1/m), in [0, 100].
        B_inf_rgb: veiling light (backscatter at infinite range), linear RGB in [0, 1].
        blur_sigma_per_m: forward-scatter blur: Gaussian sigma per metre of range as a fraction
            of the image width (1/m), in [0, 0.1]; 0.001 gives ~1 px per metre at 968 px. 0
            disables the blur.
        blur_max_range_m: range (m) beyond which the blur stops growing (also bounds the cost).
        blur_levels: number of pre-blurred levels blended by range (2-16; the first is
            unblurred).
        artificial_light: the scene is lit by a lamp beside the camera: the direct signal is
            attenuated over the lamp -> object -> camera path (2 r) instead of r.
        light_falloff_exponent: extra geometric falloff ``min(1, (r_ref / r) ** p)`` of the direct
            signal when ``artificial_light`` is on (dimensionless p >= 0; 0 for renders that
            already contain a physical lamp, 2 for renders lit by ambient light only).
        light_ref_range_m: r_ref (m) at which the extra falloff is 1.
        vignetting: vignetting strength s in [0, 1): brightness ``1 - s * rho**2`` with rho the
            normalised distance from the image centre (1 at the corners).
        exposure: the camera's exposure: the factor from the light reaching the sensor (linear
            radiance) to the sensor's full scale, in (0, 1e4]; 1 fills the sensor at radiance 1.
            With ``auto_exposure`` it is the longest exposure the camera may use.
        auto_exposure: the camera sets its exposure per frame, as a highlight-protecting auto
            exposure does: the ``exposure_percentile`` of the frame's brightest channel (before
            noise) lands at ``exposure_target`` of full scale, never above ``exposure``. Off:
            the exposure is ``exposure`` on every frame (what a water fit needs).
        exposure_target: full-scale fraction the metered level is exposed to, in (0, 1].
        exposure_percentile: percentile of the pixels metered (per pixel its brightest channel),
            in [50, 100].
        photons_at_white: photo-electrons collected at linear value 1.0 (sets the Poisson shot
            noise, variance I / photons_at_white), in [1, 1e9]; None disables all noise.
        read_noise: standard deviation of the Gaussian read noise in linear units (0-1).
        gamma: display gamma of the output image and of a uint8 input image (2.2 for the usual
            display encoding, 1.0 for linear images), in [0.2, 5]; a float input (a render's
            linear radiance) is not decoded.
        jpeg_quality: JPEG quality 1-100 applied last (encode + decode), or None for no JPEG.
    """

    beta_D_rgb: tuple[_Beta, _Beta, _Beta] = JERLOV_KD_RGB["3C"]
    beta_B_rgb: tuple[_Beta, _Beta, _Beta] = JERLOV_BEAM_C_RGB["3C"]
    B_inf_rgb: ColourRGB = (0.0, 0.31, 0.24)
    blur_sigma_per_m: Annotated[float, Interval(ge=0, le=0.1)] = 0.0003
    blur_max_range_m: Annotated[float, Interval(gt=0, le=1000)] = 8.0
    blur_levels: Annotated[int, Interval(ge=2, le=16)] = 2
    artificial_light: bool = True
    light_falloff_exponent: Annotated[float, Interval(ge=0, le=10)] = 0.0
    light_ref_range_m: Annotated[float, Interval(gt=0, le=1000)] = 1.0
    vignetting: _Vignetting = 0.2
    exposure: Annotated[float, Interval(gt=0, le=1e4)] = 1.0
    auto_exposure: bool = True
    exposure_target: Annotated[float, Interval(gt=0, le=1)] = 0.85
    exposure_percentile: Annotated[float, Interval(ge=50, le=100)] = 99.5
    photons_at_white: _Photons | None = 2000.0
    read_noise: _ReadNoise = 0.003
    gamma: Annotated[float, Interval(ge=0.2, le=5)] = 2.2
    jpeg_quality: _JpegQuality | None = None

    def validate(self) -> None:
        """Raise ValueError naming the first field outside its declared domain (NaN and
        infinity included). The fields are independent, so that is all there is to check; it
        runs on every frame (:func:`apply_water`), for configs built in Python too."""
        check_fields(self)

    @property
    def noise_enabled(self) -> bool:
        """True when sensor noise is applied (needs a random generator)."""
        return self.photons_at_white is not None


def _check(ok: bool, name: str, rule: str, value: object) -> None:
    if not ok:
        raise ValueError(f"{name}: must be {rule}, got {value!r}")


def preset(name: str, **changes: object) -> WaterConfig:
    """A named preset with optional field overrides (validated)."""
    try:
        base = PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown water preset {name!r}; known: {', '.join(PRESET_ORDER)}"
        ) from None
    cfg = dataclasses.replace(base, **changes)  # type: ignore[arg-type]
    cfg.validate()
    return cfg


def is_water_file(spec: str) -> bool:
    """True when a water argument names a water file (``*.toml``, e.g. from ``sim fit-water``)
    rather than a preset."""
    return str(spec).lower().endswith(".toml")


#: Tables a water file may hold beside ``[water]``: ``[fit]``, what ``sim fit-water`` records
#: about the fit (lighting model, uncertainty, values the frames did not determine); not read
#: here (see :func:`water_file_notes`).
WATER_FILE_NOTES = ("fit",)


def load_water_file(path: str | os.PathLike[str]) -> WaterConfig:
    """The ``[water]`` table of a TOML file (fields of :class:`WaterConfig`; those left out keep
    their defaults), validated; a ``[fit]`` table beside it is ignored. Raises a one-line
    :class:`ConfigError` (a missing file, bad TOML, a file that sets no water value, an unknown
    key or a value outside its domain)."""
    data = read_toml(path)
    if isinstance(data.get("water"), dict) and set(data) <= {"water", *WATER_FILE_NOTES}:
        data = data["water"]
    if not data:  # an empty file (or a bare [water]) would be the default water, unsaid
        raise ConfigError(
            f"{path}: sets no water value (expected a [water] table such as `datasets "
            "fit-water` writes, or WaterConfig fields); name a preset instead for its water"
        )
    return from_dict(WaterConfig, data)


def water_file_notes(path: str | os.PathLike[str]) -> dict:
    """The ``[fit]`` table of a water file (empty when it has none)."""
    notes = read_toml(path).get("fit", {})
    return dict(notes) if isinstance(notes, dict) else {}


def resolve_water(spec: str | None) -> WaterConfig | None:
    """The water a command's argument or a config's ``water_preset`` names: a preset, a water
    file (``*.toml``) or "none" (None)."""
    if spec is None or spec == "none":
        return None
    if is_water_file(spec):
        return load_water_file(spec)
    return preset(spec)


def water_spec_error(spec: str, allow_random: bool = False, allow_none: bool = True) -> str | None:
    """Why ``spec`` names no water, or None when it does: a preset name, a water file
    (``*.toml``, read and validated here), "none" (``allow_none``) or "random"
    (``allow_random``, where a water is drawn per frame). The one check behind every water
    argument and config field (commands, ``WorldConfig``, ``SynthConfig``)."""
    if is_water_file(spec):
        try:
            load_water_file(spec)
        except DockError as exc:
            return str(exc)
        return None
    known = [*PRESETS, *(["random"] if allow_random else []), *(["none"] if allow_none else [])]
    if spec in known:
        return None
    return f"unknown {str(spec)[:100]!r} (known: {', '.join(known)} or a water file, *.toml)"


@dataclasses.dataclass(frozen=True)
class Water:
    """A water as a command or a config names it, read once: ``spec`` (a preset of
    :data:`PRESETS`, a water file ``*.toml`` or "none") and the :class:`WaterConfig` it names
    (None for "none"). Commands turn their ``--water`` argument into one at their edge
    (:meth:`named`); a config keeps the spec (``WorldConfig.water_preset``) and gives the
    object (``WorldConfig.water``)."""

    spec: str
    config: WaterConfig | None

    @classmethod
    def named(cls, spec: str, allow_none: bool = True) -> Water:
        """The water ``spec`` names (a water file is read and validated here).

        Raises:
            DockError: one line, what is wrong (an unknown name, a file that is missing or
                holds no valid water).
        """
        if is_water_file(spec):  # read once
            try:
                return cls(spec, load_water_file(spec))
            except DockError as exc:
                raise DockError(f"water: {exc}") from None
        why = water_spec_error(spec, allow_none=allow_none)
        if why is not None:
            raise DockError(f"water: {why}")
        return cls(spec, resolve_water(spec))


def water_choice(name: str | None, allow_random: bool = False) -> str:
    """A command's water argument checked (:func:`water_spec_error`; None is "none"). Raises
    a one-line :class:`DockError` naming what is wrong."""
    name = name or "none"
    why = water_spec_error(name, allow_random)
    if why is not None:
        raise DockError(f"water: {why}")
    return name


#: Presets from the clearest to the most turbid (see the module docstring for the Jerlov types).
PRESETS: dict[str, WaterConfig] = {
    "clear_tank": WaterConfig(
        beta_D_rgb=JERLOV_KD_RGB["I"],
        beta_B_rgb=JERLOV_BEAM_C_RGB["I"],
        B_inf_rgb=(0.02, 0.15, 0.14),
        blur_sigma_per_m=0.0001,
    ),
    "coastal": WaterConfig(
        beta_D_rgb=JERLOV_KD_RGB["3C"],
        beta_B_rgb=JERLOV_BEAM_C_RGB["3C"],
        B_inf_rgb=(0.0, 0.31, 0.24),
        blur_sigma_per_m=0.0003,
    ),
    "turbid": WaterConfig(
        beta_D_rgb=JERLOV_KD_RGB["7C"],
        beta_B_rgb=JERLOV_BEAM_C_RGB["7C"],
        B_inf_rgb=(0.03, 0.34, 0.25),
        blur_sigma_per_m=0.0006,
    ),
    "very_turbid": WaterConfig(
        beta_D_rgb=JERLOV_KD_RGB["9C"],
        beta_B_rgb=JERLOV_BEAM_C_RGB["9C"],
        B_inf_rgb=(0.05, 0.36, 0.26),
        blur_sigma_per_m=0.001,
    ),
}

#: Preset names ordered by turbidity (clearest first).
PRESET_ORDER: tuple[str, ...] = ("clear_tank", "coastal", "turbid", "very_turbid")

#: A turbidity on the scale of ``PRESET_ORDER`` (0 = clear_tank ... 3 = very_turbid).
_Turbidity = Annotated[float, Interval(ge=0, le=len(PRESET_ORDER) - 1)]


# ----------------------------------------------------------------------------- randomisation


@dataclass(frozen=True)
class WaterRandomisation:
    """Per-episode random water: a turbidity between presets, then per-parameter jitter.

    ``sample`` draws a turbidity ``t`` uniformly in ``turbidity_range`` on the scale of
    ``PRESET_ORDER`` (0 = clear_tank, 1 = coastal, 2 = turbid, 3 = very_turbid), interpolates the
    two neighbouring presets (log-linear for the coefficients, linear otherwise), then jitters.

    Attributes:
        turbidity_range: (lo, hi) on the preset scale, 0 <= lo <= hi <= len(PRESET_ORDER) - 1.
        beta_log_sigma: std of the log-normal jitter of each beta_D / beta_B channel (ln units).
        B_inf_scale_range: (lo, hi) uniform factor on the veiling light (result clipped to 1).
        blur_scale_range: (lo, hi) uniform factor on ``blur_sigma_per_m``.
        vignetting_range: (lo, hi) uniform vignetting strength.
        photons_at_white_range: (lo, hi) log-uniform photons at white.
        read_noise_range: (lo, hi) uniform read noise (linear units).
        jpeg_probability: probability that a frame stream is JPEG-compressed.
        jpeg_quality_range: (lo, hi) uniform integer JPEG quality when compressed.
        artificial_light_probability: probability that the lamp model is on.
    """

    turbidity_range: tuple[_Turbidity, _Turbidity] = (0.0, 2.0)
    beta_log_sigma: Annotated[float, Interval(ge=0, le=2)] = 0.15
    B_inf_scale_range: tuple[_Scale, _Scale] = (0.6, 1.4)
    blur_scale_range: tuple[_Scale, _Scale] = (0.5, 1.5)
    vignetting_range: tuple[_Vignetting, _Vignetting] = (0.0, 0.35)
    photons_at_white_range: tuple[_Photons, _Photons] = (500.0, 5000.0)
    read_noise_range: tuple[_ReadNoise, _ReadNoise] = (0.001, 0.006)
    jpeg_probability: Fraction = 0.5
    jpeg_quality_range: tuple[_JpegQuality, _JpegQuality] = (60, 95)
    artificial_light_probability: Fraction = 1.0

    def validate(self) -> None:
        """Raise ValueError naming the first field outside its domain or range with lo > hi."""
        check_fields(self)
        for name in (
            "turbidity_range",
            "B_inf_scale_range",
            "blur_scale_range",
            "vignetting_range",
            "photons_at_white_range",
            "read_noise_range",
            "jpeg_quality_range",
        ):
            lo, hi = getattr(self, name)
            _check(lo <= hi, name, "(lo, hi) with lo <= hi", (lo, hi))

    def sample(self, rng: np.random.Generator) -> WaterConfig:
        """Draw one water configuration (validated) from ``rng``."""
        t = float(rng.uniform(*self.turbidity_range))
        k = min(math.floor(t), len(PRESET_ORDER) - 2)
        a = t - k
        p0, p1 = PRESETS[PRESET_ORDER[k]], PRESETS[PRESET_ORDER[k + 1]]

        def log_mix(v0: RGB, v1: RGB) -> RGB:
            mixed = np.exp(
                (1 - a) * np.log(np.maximum(v0, 1e-6)) + a * np.log(np.maximum(v1, 1e-6))
            )
            jitter = np.exp(rng.normal(0.0, self.beta_log_sigma, 3))
            return _rgb(np.minimum(mixed * jitter, _BETA_MAX))  # a 10-sigma draw stays valid

        B_inf = (1 - a) * np.asarray(p0.B_inf_rgb) + a * np.asarray(p1.B_inf_rgb)
        B_inf = np.clip(B_inf * rng.uniform(*self.B_inf_scale_range), 0.0, 1.0)
        blur = ((1 - a) * p0.blur_sigma_per_m + a * p1.blur_sigma_per_m) * rng.uniform(
            *self.blur_scale_range
        )  # <= 0.001 * 10, inside the domain
        photons = math.exp(rng.uniform(*np.log(self.photons_at_white_range)))
        jpeg = (
            int(rng.integers(self.jpeg_quality_range[0], self.jpeg_quality_range[1] + 1))
            if rng.random() < self.jpeg_probability
            else None
        )
        cfg = dataclasses.replace(
            p0,
            beta_D_rgb=log_mix(p0.beta_D_rgb, p1.beta_D_rgb),
            beta_B_rgb=log_mix(p0.beta_B_rgb, p1.beta_B_rgb),
            B_inf_rgb=_rgb(B_inf),
            blur_sigma_per_m=float(blur),
            vignetting=float(rng.uniform(*self.vignetting_range)),
            photons_at_white=float(photons),
            read_noise=float(rng.uniform(*self.read_noise_range)),
            jpeg_quality=jpeg,
            artificial_light=bool(rng.random() < self.artificial_light_probability),
        )
        cfg.validate()
        return cfg


def _rgb(v: np.ndarray) -> RGB:
    return (float(v[0]), float(v[1]), float(v[2]))


# ----------------------------------------------------------------------------- the model


@functools.lru_cache(maxsize=8)
def decode_lut(gamma: float) -> np.ndarray:
    """(256,) float32: uint8 display value -> linear value in [0, 1]."""
    return ((np.arange(256, dtype=np.float64) / 255.0) ** gamma).astype(np.float32)


@functools.lru_cache(maxsize=8)
def vignette(height: int, width: int, strength: float) -> np.ndarray:
    """(H, W, 3) float32 vignetting factor 1 - s * rho**2 (rho = 1 at the image corners)."""
    v = (np.arange(height, dtype=np.float32) - (height - 1) / 2.0) / ((height - 1) / 2.0 or 1.0)
    u = (np.arange(width, dtype=np.float32) - (width - 1) / 2.0) / ((width - 1) / 2.0 or 1.0)
    rho2 = (u[None, :] ** 2 + v[:, None] ** 2) / 2.0
    out = 1.0 - np.float32(strength) * rho2
    out = np.repeat(out[:, :, None], 3, axis=2).astype(np.float32)
    out.setflags(write=False)
    return out


#: Margin (px) of the cached noise field around a frame: the number of distinct offsets per axis.
_NOISE_MARGIN_PX = 97


@functools.lru_cache(maxsize=4)
def noise_bank(height: int, width: int) -> np.ndarray:
    """(H + m, 3 (W + m)) float32 standard normal field, fixed seed, read-only (cached)."""
    m = _NOISE_MARGIN_PX
    shape = (height + m, 3 * (width + m))
    bank = np.random.default_rng(0x5EA).standard_normal(shape, np.float32)
    bank.setflags(write=False)
    return bank


def _unit_noise(height: int, width: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """N(0, 1) noise for one frame drawn from ``rng``: a (H, W, 3) float32 view and a sign.

    Drawing 2 M normals per frame costs 5-15 ms; instead a cached standard-normal field is
    cropped (no copy) at a random row offset and a random element offset within the rows (so the
    channels shift too), and multiplied by a random sign: 97 x 291 x 2 variants. Shifted white
    noise is uncorrelated with itself, so the noises of two frames are independent to any
    detector; the draw is fully determined by ``rng``.
    """
    bank = noise_bank(height, width)
    dy, dx, sign = noise_draw(rng)
    z = bank[dy : dy + height, dx : dx + 3 * width].reshape(height, width, 3)
    return z, sign


def noise_draw(rng: np.random.Generator) -> tuple[int, int, float]:
    """One frame's draw from ``rng`` for :func:`_unit_noise` (shared with ``sim.water_torch``):
    the row offset, the element offset into :func:`noise_bank` and the sign (+1.0 or -1.0)."""
    m = _NOISE_MARGIN_PX
    dy, dx, sign = (int(v) for v in rng.integers(0, (m, 3 * m, 2)))
    return dy, dx, (1.0 if sign else -1.0)


def blur_level(img: np.ndarray, sigma_px: float, dst: np.ndarray) -> np.ndarray:
    """Approximate Gaussian blur of ``img`` with ``sigma_px``, computed at reduced size.

    The image is area-downsampled by an integer factor ~ sigma / 0.8, blurred with the residual
    sigma there and upsampled bilinearly: about 1 ms at 968 x 732 whatever the sigma.
    """
    h, w = img.shape[:2]
    factor = max(1, int(sigma_px / 0.8))
    if factor == 1:
        return cv2.GaussianBlur(img, (0, 0), sigma_px, dst=dst)
    size = (max(1, w // factor), max(1, h // factor))
    small = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    # area averaging plus bilinear upsampling blur by roughly 0.5 * factor already
    residual = math.sqrt(max(sigma_px**2 - (0.5 * factor) ** 2, 0.09 * factor**2)) / factor
    small = cv2.GaussianBlur(small, (0, 0), residual)
    return cv2.resize(small, (w, h), dst=dst, interpolation=cv2.INTER_LINEAR)


@functools.lru_cache(maxsize=32)
def _row(rgb: RGB, scale: float, width: int) -> np.ndarray:
    """(3 W,) float32 read-only row ``scale * rgb`` tiled W times (pixel-interleaved RGB)."""
    row = np.tile(np.asarray(rgb, np.float64) * scale, width).astype(np.float32)
    row.setflags(write=False)
    return row


class _Workspace:
    """Preallocated float32 buffers for one image size: fresh 8 MB arrays per frame cost more
    (page faults) than the arithmetic done in them."""

    def __init__(self, height: int, width: int) -> None:
        shape3 = (height, width, 3)
        self.r = np.empty((height, width), np.float32)
        self.weight = np.empty((height, width), np.float32)
        self.weight_c = np.empty((height, width), np.float32)
        self.J = np.empty(shape3, np.float32)
        self.level = np.empty(shape3, np.float32)
        self.blend = np.empty(shape3, np.float32)
        self.r3 = np.empty(shape3, np.float32)
        self.a = np.empty(shape3, np.float32)
        self.b = np.empty(shape3, np.float32)


_LOCAL = threading.local()


def _workspace(height: int, width: int) -> _Workspace:
    """The calling thread's workspace for this image size (one per size used: an episode video
    alternates the downward and the outside view)."""
    cache = getattr(_LOCAL, "by_size", None)
    if cache is None:
        cache = _LOCAL.by_size = {}
    ws = cache.get((height, width))
    if ws is None:
        ws = cache[(height, width)] = _Workspace(height, width)
    return ws


def _forward_scatter(J: np.ndarray, r: np.ndarray, cfg: WaterConfig, ws: _Workspace) -> np.ndarray:
    """Blend ``cfg.blur_levels`` blurred copies of ``J`` by per-pixel range (sigma = k * r)."""
    width = J.shape[1]
    k_px_per_m = cfg.blur_sigma_per_m * width
    r_top = min(float(r[r < FAR_M].max(initial=0.0)), cfg.blur_max_range_m)
    sigma_max = k_px_per_m * r_top
    if sigma_max < 0.3:  # below a third of a pixel the blur is invisible
        return J
    step = sigma_max / (cfg.blur_levels - 1)
    t = np.minimum(r, np.float32(cfg.blur_max_range_m), out=ws.weight_c)
    t *= np.float32(k_px_per_m / step)  # fractional level index per pixel
    out = J
    for level in range(1, cfg.blur_levels):
        a = np.clip(t - np.float32(level - 1), 0.0, 1.0, out=ws.weight)
        # ping-pong between two buffers apply_water does not reuse while J is alive
        dst = ws.blend if out is not ws.blend else ws.b
        out = cv2.blendLinear(out, blur_level(J, level * step, ws.level), 1.0 - a, a, dst=dst)
    return out


def meter_level(out: np.ndarray, percentile: float) -> float:
    """The auto exposure's metered level of a linear (H, W, 3) frame: the ``percentile`` of its
    pixels' brightest channel, on a regular subsample of about 128 rows (shared with
    ``sim.water_torch``, which meters the same pixels)."""
    h, w = out.shape[:2]
    step = meter_step(h, w)
    sub = out[::step, ::step]  # the channel maximum by slices: 5x faster than max(axis=2)
    s = np.maximum(np.maximum(sub[:, :, 0], sub[:, :, 1]), sub[:, :, 2]).ravel()
    k = meter_rank(s.size, percentile)
    return float(np.partition(s, k)[k])


def meter_step(height: int, width: int) -> int:
    """Row and column step of the metered subsample."""
    return max(1, min(height, width) // 128)


def meter_rank(n: int, percentile: float) -> int:
    """0-based rank of the ``percentile`` among ``n`` metered values."""
    return min(n - 1, max(0, round(percentile / 100.0 * (n - 1))))


def exposure_for(level: float, cfg: WaterConfig) -> float:
    """The exposure the camera uses for a frame metered at ``level`` (at exposure 1):
    ``min(exposure, exposure_target / level)`` with ``auto_exposure``, else ``exposure``."""
    if not cfg.auto_exposure or not level > 0.0:
        return float(cfg.exposure)
    return float(min(cfg.exposure, cfg.exposure_target / level))


def _linear_input(image: np.ndarray, cfg: WaterConfig, ws: _Workspace) -> np.ndarray:
    """(H, W, 3) float32 linear radiance from a float image (checked) or a uint8 one (decoded)."""
    img = np.asarray(image)
    if img.dtype not in (np.uint8, np.float32, np.float64):
        raise ValueError(
            f"image: expected (H, W, 3) uint8 or float radiance, got {img.shape} {img.dtype}"
        )
    if img.dtype == np.uint8:
        return cv2.LUT(np.ascontiguousarray(img), decode_lut(float(cfg.gamma)), dst=ws.J)
    lo, hi = float(img.min(initial=np.inf)), float(img.max(initial=0.0))
    if not (lo >= 0.0 and hi < np.inf):  # also catches nan
        raise ValueError(f"image: radiance must be finite and >= 0, got range [{lo}, {hi}]")
    if img.dtype == np.float32 and img.flags.c_contiguous:
        return img  # read only below
    np.copyto(ws.J, img, casting="same_kind")
    return ws.J


def apply_water(
    image: np.ndarray,
    range_m: np.ndarray,
    cfg: WaterConfig,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Apply the underwater image formation model and the camera to a rendered frame.

    Args:
        image: (H, W, 3) RGB in air: float32/float64 linear radiance (a render's
            ``RenderResult.radiance``: >= 0, unclipped) or uint8 display-encoded with
            ``cfg.gamma``. Not modified.
        range_m: (H, W) range along each pixel's ray (m), >= 0; ``inf`` (or any value above
            1e4 m) where nothing was hit: such pixels become pure veiling light.
        cfg: water and sensor parameters (validated here).
        rng: random generator for the sensor noise; required when ``cfg.noise_enabled``. The
            same generator state gives the same image.

    Returns:
        (H, W, 3) uint8 RGB image, display-encoded with ``cfg.gamma`` (a new array).

    Raises:
        ValueError: wrong shapes or dtypes, a negative, infinite or nan radiance, a negative or
            nan range, an invalid ``cfg``, or noise enabled without ``rng``.
    """
    cfg.validate()
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(
            f"image: expected (H, W, 3) uint8 or float radiance, got {img.shape} {img.dtype}"
        )
    r_in = np.asarray(range_m, dtype=np.float32)
    if r_in.shape != img.shape[:2]:
        raise ValueError(f"range_m: expected shape {img.shape[:2]}, got {r_in.shape}")
    if not (r_in >= 0).all():  # also catches nan
        raise ValueError("range_m: must be >= 0 and not nan")
    if cfg.noise_enabled and rng is None:
        raise ValueError("rng: a numpy Generator is required when noise is enabled")
    h, w = r_in.shape
    ws = _workspace(h, w)
    r = np.minimum(r_in, np.float32(FAR_M), out=ws.r)

    J = _linear_input(img, cfg, ws)
    if cfg.blur_sigma_per_m > 0.0:
        J = _forward_scatter(J, r, cfg, ws)

    # direct signal J * exp(-beta_D * path * r) [* falloff], into ws.a. Per-channel vectors are
    # tiled along a row and applied to (H, 3 W) views: numpy broadcasts a (3,) vector slowly.
    path = 2.0 if cfg.artificial_light else 1.0
    r3 = cv2.merge([r, r, r], dst=ws.r3).reshape(h, 3 * w)
    direct = np.multiply(r3, _row(cfg.beta_D_rgb, -path, w), out=ws.a.reshape(h, 3 * w))
    np.exp(direct, out=direct)  # numpy's SIMD float32 exp, ~4x faster than cv2.exp
    direct = direct.reshape(h, w, 3)
    if cfg.artificial_light and cfg.light_falloff_exponent > 0.0:
        falloff = np.maximum(r, np.float32(1e-6), out=ws.weight)
        np.divide(np.float32(cfg.light_ref_range_m), falloff, out=falloff)
        np.power(falloff, np.float32(cfg.light_falloff_exponent), out=falloff)
        np.minimum(falloff, np.float32(1.0), out=falloff)
        cv2.multiply(direct, cv2.merge([falloff, falloff, falloff], dst=ws.level), dst=direct)
    out = np.multiply(direct, J, out=ws.a)
    # backscatter B_inf * (1 - exp(-beta_B * r)) = B_inf - B_inf * exp(...), added to out
    back = np.multiply(r3, _row(cfg.beta_B_rgb, -1.0, w), out=ws.b.reshape(h, 3 * w))
    np.exp(back, out=back)
    back *= _row(cfg.B_inf_rgb, -1.0, w)
    back += _row(cfg.B_inf_rgb, 1.0, w)
    out += back.reshape(h, w, 3)
    if cfg.vignetting > 0.0:
        out *= vignette(h, w, float(cfg.vignetting))
    level = meter_level(out, cfg.exposure_percentile) if cfg.auto_exposure else 0.0
    e = exposure_for(level, cfg)
    if e != 1.0:
        out *= np.float32(e)

    if cfg.noise_enabled:
        assert rng is not None and cfg.photons_at_white is not None
        z, sign = _unit_noise(h, w, rng)
        # out >= 0 here; sigma**2 = I / photons + read_noise**2
        sd = np.multiply(out, np.float32(1.0 / cfg.photons_at_white), out=ws.b)
        sd += np.float32(cfg.read_noise**2)
        np.sqrt(sd, out=sd)
        sd *= z
        if sign > 0:
            out += sd
        else:
            out -= sd
        np.maximum(out, np.float32(0.0), out=out)

    if cfg.gamma != 1.0:
        out = cv2.pow(out, 1.0 / cfg.gamma, dst=ws.b)
    result = cv2.convertScaleAbs(out, alpha=255.0)  # out >= 0: rounds and saturates to uint8

    if cfg.jpeg_quality is not None:
        result = jpeg_roundtrip(result, int(cfg.jpeg_quality))
    return result


def jpeg_roundtrip(rgb_uint8: np.ndarray, quality: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB encoded as JPEG with ``quality`` and decoded (shared with
    ``sim.water_torch``)."""
    bgr = cv2.cvtColor(rgb_uint8, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 image
        raise RuntimeError("JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
