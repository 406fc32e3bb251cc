"""Underwater image formation in PyTorch: :func:`sim.water.apply_water` on any torch device.

When SAPIEN renders on a GPU, its colour and range pictures can stay there: this module runs
the same model (see :mod:`sim.water` for the physics and the parameters)::

    I_c = V * (J_c * blur(r) * exp(-beta_D_c * path * r) * F(r)
               + B_inf_c * (1 - exp(-beta_B_c * r)))

then the exposure, the Poisson-Gaussian noise, the gamma encoding, the uint8 rounding and the
optional JPEG, with torch operations, and gives the same image as :func:`~sim.water.apply_water`
to within one grey level (float32 rounding in a different order can move a value across a
rounding boundary).
How each step is matched:

* the decoding table, the vignetting and the veiling-light coefficients are the numpy values of
  ``sim.water`` (float32, the per-channel products rounded to float32 as ``_row`` does), moved to
  the device once and cached per device;
* forward scatter blends the same pre-blurred levels with OpenCV's ``blendLinear`` formula
  ``(a1 x1 + a2 x2) / (a1 + a2 + 1e-5)``; each level is blurred as ``sim.water.blur_level``
  does: an area downsample by the same integer factor (``avg_pool2d`` where OpenCV takes its
  integer-scale path, otherwise OpenCV's fractional ``INTER_AREA`` weights, ported), the
  Gaussian kernel of ``cv2.GaussianBlur(img, (0, 0), sigma)`` (``cv2.getGaussianKernel`` with
  OpenCV's size rule ``round(8 sigma + 1) | 1`` for float images) applied separably with
  reflect-101 borders, and a bilinear upsample (``align_corners=False``, OpenCV's
  ``INTER_LINEAR`` pixel grid);
* the noise is the same fixed-seed standard-normal bank (``noise_bank``, moved to the device
  once per (H, W, device)) cropped at the offsets and signed with the sign that
  ``noise_draw`` takes from ``rng``: the generator advances exactly as in ``apply_water``, so a
  sequence of frames from one generator is the same sequence;
* the JPEG round trip runs on the CPU with OpenCV, as in ``apply_water`` (so it is exact on
  the image it gets; where that image differs from ``apply_water``'s by one level at a pixel,
  the compression spreads the difference over the 8 x 8 block: a few levels, rarely).

torch is an optional dependency (the ``rl`` extra): it is imported inside the functions, so
importing this module, and ``sim.water``, works without it.

Example:
    >>> rng = np.random.default_rng(0)
    >>> out = apply_water_torch(rgb_cuda, range_cuda, PRESETS["coastal"], rng)  # a cuda tensor
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from uwdock.sim.water import (
    FAR_M,
    RGB,
    WaterConfig,
    decode_lut,
    exposure_for,
    jpeg_roundtrip,
    meter_rank,
    meter_step,
    noise_bank,
    noise_draw,
    vignette,
)

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = ["apply_water_torch"]

_DTYPES_NP = (np.dtype(np.uint8), np.dtype(np.float32), np.dtype(np.float64))


def _float_dtypes() -> tuple[object, ...]:
    """The tensor dtypes an image may have (uint8 display-encoded, or float radiance)."""
    import torch

    return (torch.uint8, torch.float32, torch.float64, torch.float16)


def _f32(value: float) -> float:
    """``value`` rounded to float32 (what numpy's ``np.float32(value)`` holds), as a Python float:
    torch then multiplies a float32 tensor by exactly that number."""
    return float(np.float32(value))


# ----------------------------------------------------------------------------- cached constants


@functools.lru_cache(maxsize=16)
def _lut(gamma: float, device: torch.device) -> torch.Tensor:
    """(256,) float32 decoding table of ``sim.water`` on ``device``."""
    import torch

    return torch.from_numpy(decode_lut(gamma).copy()).to(device)


@functools.lru_cache(maxsize=16)
def _vignette_t(height: int, width: int, strength: float, device: torch.device) -> torch.Tensor:
    """(1, H, W) float32 vignetting factor of ``sim.water`` on ``device``."""
    import torch

    v = vignette(height, width, strength)[:, :, 0].copy()
    return torch.from_numpy(v).to(device)[None]


@functools.lru_cache(maxsize=4)
def _noise_bank_t(height: int, width: int, device: torch.device) -> torch.Tensor:
    """``sim.water``'s (H + m, 3 (W + m)) float32 noise bank on ``device`` (cached)."""
    import torch

    return torch.from_numpy(noise_bank(height, width).copy()).to(device)


@functools.lru_cache(maxsize=64)
def _coef(rgb: RGB, scale: float, device: torch.device) -> torch.Tensor:
    """(3, 1, 1) float32 ``scale * rgb``, rounded to float32 as ``sim.water._row`` rounds it."""
    import torch

    c = (np.asarray(rgb, np.float64) * scale).astype(np.float32)
    return torch.from_numpy(c).to(device).view(3, 1, 1)


# ----------------------------------------------------------------------------- OpenCV's filters


@functools.lru_cache(maxsize=64)
def _reflect101(n: int, pad: int, device: torch.device) -> torch.Tensor:
    """Source indices of ``n`` samples padded by ``pad`` on each side, OpenCV's default border
    (BORDER_REFLECT_101: ``gfedcb|abcdefgh|gfedcba``), repeated for pads longer than ``n``."""
    import torch

    i = np.arange(-pad, n + pad)
    if n == 1:
        i = np.zeros_like(i)
    else:
        period = 2 * (n - 1)
        i = np.mod(i, period)
        i = np.where(i < n, i, period - i)
    return torch.from_numpy(i.astype(np.int64)).to(device)


def _gaussian_kernel(sigma: float) -> list[float]:
    """The 1-D kernel of ``cv2.GaussianBlur(float_img, (0, 0), sigma)``: float32 values (as
    Python floats), odd size."""
    ksize = round(sigma * 4 * 2 + 1) | 1  # OpenCV's rule for non-uint8 images
    return cv2.getGaussianKernel(ksize, sigma, cv2.CV_32F).ravel().tolist()


def _pad_reflect101(x: torch.Tensor, pad: int, dim: int) -> torch.Tensor:
    """(C, 1, H, W) ``x`` padded by ``pad`` on both sides of ``dim`` (2 or 3), reflect-101."""
    import torch.nn.functional as F

    n = x.shape[dim]
    if pad < n:  # torch's "reflect" is OpenCV's BORDER_REFLECT_101
        return F.pad(x, (pad, pad, 0, 0) if dim == 3 else (0, 0, pad, pad), mode="reflect")
    return x.index_select(dim, _reflect101(n, pad, x.device))


def _filter_1d(x: torch.Tensor, kernel: list[float], dim: int) -> torch.Tensor:
    """Symmetric odd ``kernel`` along ``dim`` of (C, 1, H, W) ``x``, reflect-101 borders.

    Shifted slices added in symmetric pairs (as OpenCV's symmetric row filter adds them): on the
    CPU many times faster than torch's convolution of a single-channel image.
    """
    k = len(kernel)
    pad = k // 2
    n = x.shape[dim]
    xp = _pad_reflect101(x, pad, dim)
    out = xp.narrow(dim, pad, n) * kernel[pad]
    for i in range(pad):
        pair = xp.narrow(dim, i, n) + xp.narrow(dim, k - 1 - i, n)
        out.add_(pair, alpha=kernel[i])
    return out


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """``cv2.GaussianBlur(x, (0, 0), sigma)`` of (C, 1, H, W) float32 planes: rows, then
    columns, reflect-101 borders."""
    kernel = _gaussian_kernel(sigma)
    return _filter_1d(_filter_1d(x, kernel, 3), kernel, 2)


@functools.lru_cache(maxsize=64)
def _area_table(ssize: int, dsize: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV's ``INTER_AREA`` weights for ``ssize`` -> ``dsize`` samples (``dsize <= ssize``):
    source indices (K, dsize) and float32 weights (K, dsize, 1), K the most taps of an output
    sample (unused taps have weight 0). A port of ``computeResizeAreaTab``
    (imgproc/resize.cpp)."""
    import torch

    scale = 1.0 / (dsize / ssize)  # OpenCV: scale_x = 1. / inv_scale_x
    taps: list[list[tuple[int, float]]] = []
    for dx in range(dsize):
        fsx1 = dx * scale
        fsx2 = fsx1 + scale
        cell = min(scale, ssize - fsx1)
        sx1, sx2 = math.ceil(fsx1), math.floor(fsx2)
        sx2 = min(sx2, ssize - 1)
        sx1 = min(sx1, sx2)
        row: list[tuple[int, float]] = []
        if sx1 - fsx1 > 1e-3:
            row.append((sx1 - 1, (sx1 - fsx1) / cell))
        row.extend((sx, 1.0 / cell) for sx in range(sx1, sx2))
        if fsx2 - sx2 > 1e-3:
            row.append((sx2, min(min(fsx2 - sx2, 1.0), cell) / cell))
        taps.append(row)
    k = max(len(row) for row in taps)
    idx = np.zeros((k, dsize), np.int64)
    wts = np.zeros((k, dsize, 1), np.float32)
    for dx, row in enumerate(taps):
        for j, (sx, alpha) in enumerate(row):
            idx[j, dx], wts[j, dx] = sx, alpha
    return torch.from_numpy(idx).to(device), torch.from_numpy(wts).to(device)


def _area_rows(x: torch.Tensor, dsize: int) -> torch.Tensor:
    """The rows of 2-D ``x`` resampled to ``dsize`` rows with OpenCV's fractional INTER_AREA
    weights (whole rows gathered: on the CPU far faster than gathering along the last axis)."""
    idx, wts = _area_table(x.shape[0], dsize, x.device)
    out = x.index_select(0, idx[0]).mul_(wts[0])
    for j in range(1, idx.shape[0]):
        out.add_(x.index_select(0, idx[j]).mul_(wts[j]))
    return out


def _area_down(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``cv2.resize(x, (width, height), interpolation=cv2.INTER_AREA)`` of (C, 1, H, W) planes,
    a reduction in both axes."""
    h, w = x.shape[-2:]
    if h % height == 0 and w % width == 0:  # OpenCV's integer-scale path: block means
        fy, fx = h // height, w // width
        # strided slices summed: on the CPU several times faster than avg_pool2d
        cols = x[..., 0::fx].clone()
        for i in range(1, fx):
            cols.add_(x[..., i::fx])
        out = cols[..., 0::fy, :].clone()
        for i in range(1, fy):
            out.add_(cols[..., i::fy, :])
        return out.mul_(1.0 / (fy * fx))
    c = x.shape[0]
    cols = _area_rows(x.permute(3, 0, 1, 2).reshape(w, c * h), width)  # (width, C H)
    rows = cols.view(width, c, h).permute(2, 1, 0).reshape(h, c * width)
    return _area_rows(rows, height).view(height, c, width).permute(1, 0, 2).unsqueeze(1)


def _blur_level(J: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """``sim.water.blur_level`` of (3, H, W) planes: the same approximate Gaussian blur."""
    import torch.nn.functional as F

    h, w = J.shape[-2:]
    x = J.unsqueeze(1)
    factor = max(1, int(sigma_px / 0.8))
    if factor == 1:
        return _gaussian_blur(x, sigma_px)[:, 0]
    small = _area_down(x, max(1, h // factor), max(1, w // factor))
    residual = math.sqrt(max(sigma_px**2 - (0.5 * factor) ** 2, 0.09 * factor**2)) / factor
    small = _gaussian_blur(small, residual)
    return F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)[:, 0]


def _forward_scatter(J: torch.Tensor, r: torch.Tensor, cfg: WaterConfig) -> torch.Tensor:
    """``sim.water._forward_scatter`` of (3, H, W) planes ``J`` with (H, W) range ``r``."""
    import torch

    width = J.shape[-1]
    k_px_per_m = cfg.blur_sigma_per_m * width
    near = torch.where(r < FAR_M, r, torch.zeros((), dtype=r.dtype, device=r.device))
    r_top = min(float(near.max()) if near.numel() else 0.0, cfg.blur_max_range_m)
    sigma_max = k_px_per_m * r_top
    if sigma_max < 0.3:
        return J
    step = sigma_max / (cfg.blur_levels - 1)
    t = torch.clamp_max(r, _f32(cfg.blur_max_range_m)).mul_(_f32(k_px_per_m / step))
    out = J
    for level in range(1, cfg.blur_levels):
        a = torch.sub(t, float(level - 1)).clamp_(0.0, 1.0)
        b = torch.sub(1.0, a)
        den = torch.add(b, a).add_(_f32(1e-5))
        blurred = _blur_level(J, level * step).mul_(a)
        # cv2.blendLinear: (w1 src1 + w2 src2) / (w1 + w2 + 1e-5)
        out = (out * b if out is J else out.mul_(b)).add_(blurred).div_(den)
    return out


# ----------------------------------------------------------------------------- the model


def _describe(shape: tuple[int, ...], dtype: object) -> str:
    """``shape dtype`` as ``apply_water``'s messages print a numpy array's."""
    return f"{tuple(shape)} {str(dtype).removeprefix('torch.')}"


def apply_water_torch(
    image: np.ndarray | torch.Tensor,
    range_m: np.ndarray | torch.Tensor,
    cfg: WaterConfig,
    rng: np.random.Generator | None = None,
    device: str | torch.device | None = None,
) -> np.ndarray | torch.Tensor:
    """Apply the underwater image formation model of :func:`sim.water.apply_water` with torch.

    Args:
        image: (H, W, 3) RGB in air: float linear radiance (>= 0, unclipped) or uint8
            display-encoded with ``cfg.gamma``; a numpy array or a torch tensor (which is
            processed on its own device).
        range_m: (H, W) range along each pixel's ray (m), >= 0; ``inf`` (or any value above
            1e4 m) where nothing was hit. A numpy array or a tensor (moved to the image's
            device).
        cfg: water and sensor parameters (validated here).
        rng: random generator for the sensor noise; required when ``cfg.noise_enabled``. It is
            advanced exactly as ``apply_water`` advances it, and the same generator state gives
            the same image as ``apply_water`` (to within one grey level).
        device: the torch device for a numpy image ("cpu" when None); ignored for a tensor.

    Returns:
        (H, W, 3) uint8 RGB image, display-encoded with ``cfg.gamma`` (new memory): a numpy
        array for a numpy image, a tensor on the image's device for a tensor.

    Raises:
        ValueError: wrong shapes or dtypes, a negative, infinite or nan radiance, a negative or
            nan range, an invalid ``cfg``, or noise enabled without ``rng`` (the messages of
            ``apply_water``).
    """
    import torch

    cfg.validate()
    as_tensor = isinstance(image, torch.Tensor)
    if as_tensor:
        img = image.detach()
        dev = img.device
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype not in _float_dtypes():
            raise ValueError(
                "image: expected (H, W, 3) uint8 or float radiance, got "
                f"{_describe(img.shape, img.dtype)}"
            )
    else:
        img_np = np.ascontiguousarray(image)
        if img_np.ndim != 3 or img_np.shape[2] != 3 or img_np.dtype not in _DTYPES_NP:
            raise ValueError(
                "image: expected (H, W, 3) uint8 or float radiance, got "
                f"{img_np.shape} {img_np.dtype}"
            )
        dev = torch.device(device if device is not None else "cpu")
        img = torch.from_numpy(np.require(img_np, requirements=["C", "W"])).to(dev)
    if img.dtype != torch.uint8:
        img = img.to(torch.float32)
        lo, hi = float(img.min()), float(img.max())
        if not (lo >= 0.0 and hi < math.inf):  # also catches nan
            raise ValueError(f"image: radiance must be finite and >= 0, got range [{lo}, {hi}]")
    hw = tuple(img.shape[:2])
    if isinstance(range_m, torch.Tensor):
        r_in = range_m.detach().to(device=dev, dtype=torch.float32)
    else:
        r_in = torch.from_numpy(np.require(range_m, np.float32, requirements=["C", "W"]))
    if tuple(r_in.shape) != hw:
        raise ValueError(f"range_m: expected shape {hw}, got {tuple(r_in.shape)}")
    r_in = r_in.to(dev)
    if not bool((r_in >= 0).all()):  # also catches nan
        raise ValueError("range_m: must be >= 0 and not nan")
    if cfg.noise_enabled and rng is None:
        raise ValueError("rng: a numpy Generator is required when noise is enabled")

    with torch.no_grad():
        out = _model(img, r_in, cfg, rng)
    result = out.permute(1, 2, 0).contiguous()  # (H, W, 3) uint8
    if cfg.jpeg_quality is not None:
        jpeg = jpeg_roundtrip(result.cpu().numpy(), int(cfg.jpeg_quality))
        return torch.from_numpy(jpeg).to(dev) if as_tensor else jpeg
    return result if as_tensor else result.cpu().numpy()


def _model(
    img: torch.Tensor, r_in: torch.Tensor, cfg: WaterConfig, rng: np.random.Generator | None
) -> torch.Tensor:
    """The model on checked inputs: (H, W, 3) uint8 or float32 radiance and (H, W) float32 on
    one device -> (3, H, W) uint8 planes (before JPEG)."""
    import torch

    dev = img.device
    h, w = r_in.shape
    r = torch.clamp_max(r_in, FAR_M)
    if img.dtype == torch.uint8:
        idx = img.permute(2, 0, 1).reshape(-1).int()
        J = _lut(float(cfg.gamma), dev).index_select(0, idx).view(3, h, w)  # linear float32
    else:
        J = img.permute(2, 0, 1)  # read only below
    if cfg.blur_sigma_per_m > 0.0:
        J = _forward_scatter(J, r, cfg)

    # in place where possible: a fresh 8 MB tensor per step costs more than the arithmetic
    path = 2.0 if cfg.artificial_light else 1.0
    out = torch.mul(r, _coef(cfg.beta_D_rgb, -path, dev)).exp_()  # direct attenuation
    if cfg.artificial_light and cfg.light_falloff_exponent > 0.0:
        ref = torch.tensor(_f32(cfg.light_ref_range_m), dtype=torch.float32, device=dev)
        falloff = torch.div(ref, torch.clamp_min(r, _f32(1e-6)))  # a true division, as numpy's
        falloff = falloff.pow_(_f32(cfg.light_falloff_exponent)).clamp_max_(1.0)
        out.mul_(falloff)
    out.mul_(J)
    back = torch.mul(r, _coef(cfg.beta_B_rgb, -1.0, dev)).exp_()
    out.add_(back.mul_(_coef(cfg.B_inf_rgb, -1.0, dev)).add_(_coef(cfg.B_inf_rgb, 1.0, dev)))
    if cfg.vignetting > 0.0:
        out.mul_(_vignette_t(h, w, float(cfg.vignetting), dev))
    if cfg.auto_exposure:  # the pixels sim.water.meter_level meters, the same rank
        step = meter_step(h, w)
        s = out[:, ::step, ::step].amax(dim=0).reshape(-1)
        level = float(torch.kthvalue(s, meter_rank(s.numel(), cfg.exposure_percentile) + 1)[0])
    else:
        level = 0.0
    e = exposure_for(level, cfg)
    if e != 1.0:
        out.mul_(_f32(e))

    if cfg.noise_enabled:
        assert rng is not None and cfg.photons_at_white is not None
        dy, dx, sign = noise_draw(rng)
        bank = _noise_bank_t(h, w, dev)
        z = bank[dy : dy + h, dx : dx + 3 * w].view(h, w, 3).permute(2, 0, 1)
        sd = torch.mul(out, _f32(1.0 / cfg.photons_at_white)).add_(_f32(cfg.read_noise**2))
        sd.sqrt_().mul_(z)
        out = out.add_(sd) if sign > 0 else out.sub_(sd)
        out.clamp_min_(0.0)

    if cfg.gamma != 1.0:
        out.pow_(_f32(1.0 / cfg.gamma))
    # cv2.convertScaleAbs: round half to even, saturate to uint8
    return out.mul_(255.0).round_().clamp_(0.0, 255.0).to(torch.uint8)
