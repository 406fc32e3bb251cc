"""Underwater image formation (sim.water): numbers against the closed-form model, no SAPIEN."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwdock.sim.water import (
    JERLOV_BEAM_C_RGB,
    JERLOV_KD_RGB,
    PRESET_ORDER,
    PRESETS,
    WaterConfig,
    WaterRandomisation,
    apply_water,
    decode_lut,
    exposure_for,
    meter_level,
    preset,
)

#: Everything off but attenuation and backscatter.
PLAIN = dict(
    blur_sigma_per_m=0.0,
    artificial_light=False,
    vignetting=0.0,
    photons_at_white=None,
    jpeg_quality=None,
    auto_exposure=False,
)


def _const(value: int | tuple[int, int, int], h: int = 6, w: int = 8) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, np.uint8), (h, w, 3)).copy()


def _model(v_u8: np.ndarray, r: float, cfg: WaterConfig) -> np.ndarray:
    """The model in float64, for a uniform image: the expected display value (0-255, float)."""
    J = (np.asarray(v_u8, np.float64) / 255.0) ** cfg.gamma
    path = 2.0 if cfg.artificial_light else 1.0
    D = np.exp(-np.asarray(cfg.beta_D_rgb) * path * r)
    B = np.asarray(cfg.B_inf_rgb) * (1.0 - np.exp(-np.asarray(cfg.beta_B_rgb) * r))
    return 255.0 * np.clip(J * D + B, 0.0, 1.0) ** (1.0 / cfg.gamma)


# ----------------------------------------------------------------------------- the formula


@pytest.mark.parametrize("gamma", [1.0, 2.2])
@pytest.mark.parametrize("artificial_light", [False, True])
@pytest.mark.parametrize("r", [0.0, 0.7, 2.5, 6.0])
def test_exact_formula_on_constant_image(gamma: float, artificial_light: bool, r: float) -> None:
    cfg = preset("coastal", **{**PLAIN, "gamma": gamma, "artificial_light": artificial_light})
    img = _const((230, 128, 40))
    out = apply_water(img, np.full(img.shape[:2], r), cfg)
    expected = _model(img[0, 0], r, cfg)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert np.abs(out.astype(np.float64) - expected).max() <= 0.51  # rounding only


@pytest.mark.parametrize("levels", [2, 3, 4, 5])
def test_forward_scatter_leaves_a_uniform_image_on_the_formula(levels: int) -> None:
    """Blurring a uniform image changes nothing, whatever the number of blur levels."""
    cfg = preset("coastal", **{**PLAIN, "blur_sigma_per_m": 0.02, "blur_levels": levels})
    img = _const((230, 128, 40), h=40, w=60)
    r = np.linspace(0.5, 4.0, 40 * 60).reshape(40, 60)
    out = apply_water(img, r, cfg).astype(np.float64)
    expected = np.stack([_model(img[0, 0], float(v), cfg) for v in r.ravel()]).reshape(out.shape)
    assert np.abs(out - expected).max() <= 1.01  # rounding (+ blur float error)


def test_zero_range_returns_scene_unchanged() -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    for name in PRESET_ORDER:  # forward-scatter blur included: sigma is 0 at r = 0
        cfg = preset(
            name, vignetting=0.0, photons_at_white=None, jpeg_quality=None, auto_exposure=False
        )
        out = apply_water(img, np.zeros(img.shape[:2]), cfg)
        np.testing.assert_array_equal(out, img)


def test_no_hit_gives_pure_veiling_light() -> None:
    cfg = preset("turbid", **PLAIN)
    out = apply_water(_const(255), np.full((6, 8), np.inf), cfg)
    expected = 255.0 * np.asarray(cfg.B_inf_rgb) ** (1.0 / cfg.gamma)
    assert np.abs(out[0, 0] - expected).max() <= 0.51


def test_attenuation_is_monotone_in_range_towards_veiling_light() -> None:
    ranges = [0.0, 0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 13.0, 21.0]
    for name in PRESET_ORDER:
        cfg = preset(name, **{**PLAIN, "gamma": 1.0})
        B = 255.0 * np.asarray(cfg.B_inf_rgb)
        dist = np.array(
            [np.abs(apply_water(_const(255), np.full((6, 8), r), cfg)[0, 0] - B) for r in ranges]
        )
        assert np.all(np.diff(dist, axis=0) <= 0.0), name  # per channel, never farther
        assert np.all(dist[-1] < dist[0]), name


def test_red_attenuates_fastest_in_clear_water() -> None:
    cfg = preset("clear_tank", **{**PLAIN, "gamma": 1.0, "B_inf_rgb": (0.0, 0.0, 0.0)})
    for r in (1.0, 3.0, 6.0):
        red, green, blue = apply_water(_const(250), np.full((6, 8), r), cfg)[0, 0].astype(int)
        assert red < green <= blue


def test_lamp_path_and_falloff() -> None:
    base = preset("coastal", **{**PLAIN, "gamma": 1.0, "B_inf_rgb": (0.0, 0.0, 0.0)})
    lamp = dataclasses.replace(base, artificial_light=True, light_falloff_exponent=2.0)
    img, r = _const(200), 2.0
    one_way = apply_water(img, np.full((6, 8), r), base)[0, 0].astype(float)
    two_way = apply_water(img, np.full((6, 8), r), lamp)[0, 0].astype(float)
    expected = 200.0 * np.exp(-2.0 * np.asarray(base.beta_D_rgb) * r) / r**2
    assert np.abs(two_way - expected).max() <= 0.51
    assert np.all(two_way < one_way)


def test_vignetting_darkens_the_corners_only() -> None:
    cfg = preset("coastal", **{**PLAIN, "gamma": 1.0, "vignetting": 0.3})
    out = apply_water(_const(200, 101, 101), np.zeros((101, 101)), cfg).astype(float)
    assert out[50, 50, 0] == pytest.approx(200.0, abs=0.5)
    assert out[0, 0, 0] == pytest.approx(200.0 * 0.7, abs=0.6)
    assert out[0, 50, 0] == pytest.approx(200.0 * (1 - 0.3 / 2), abs=0.6)


def test_forward_scatter_blur_grows_with_range() -> None:
    img = np.zeros((64, 200, 3), np.uint8)
    img[:, 100:] = 255
    cfg = preset("clear_tank", **{**PLAIN, "gamma": 1.0, "beta_D_rgb": (0.0, 0.0, 0.0)})
    cfg = dataclasses.replace(cfg, B_inf_rgb=(0.0, 0.0, 0.0), blur_sigma_per_m=0.01)  # 2 px/m

    def edge_width(r: float) -> int:
        row = apply_water(img, np.full(img.shape[:2], r), cfg)[32, :, 1].astype(int)
        return int(np.count_nonzero((row > 25) & (row < 230)))  # pixels of the 10-90 % ramp

    widths = [edge_width(r) for r in (0.0, 1.0, 3.0, 6.0)]
    assert widths[0] == 0
    assert widths == sorted(widths) and widths[-1] >= widths[1] + 4


# ----------------------------------------------------------------------------- presets


def test_presets_exist_and_are_ordered_by_turbidity() -> None:
    assert set(PRESET_ORDER) == set(PRESETS) and {"clear_tank", "coastal", "turbid"} <= set(PRESETS)
    assert PRESETS["clear_tank"].beta_D_rgb == JERLOV_KD_RGB["I"]
    assert PRESETS["coastal"].beta_B_rgb == JERLOV_BEAM_C_RGB["3C"]
    assert PRESETS["turbid"].beta_D_rgb == JERLOV_KD_RGB["7C"]
    cfgs = [PRESETS[n] for n in PRESET_ORDER]
    for field in ("beta_D_rgb", "beta_B_rgb", "blur_sigma_per_m"):
        values = np.array([np.atleast_1d(getattr(c, field)) for c in cfgs])
        assert np.all(np.diff(values, axis=0) >= 0.0), field
    # the visible consequence: black/white contrast at 3 m drops from preset to preset
    img = np.zeros((6, 8, 3), np.uint8)
    img[:, 4:] = 255
    contrast = []
    for c in cfgs:
        out = apply_water(img, np.full((6, 8), 3.0), dataclasses.replace(c, **PLAIN)).astype(int)
        contrast.append(int((out[0, 7] - out[0, 0]).sum()))
    assert contrast == sorted(contrast, reverse=True) and len(set(contrast)) == len(contrast)


def test_preset_overrides_and_unknown_name() -> None:
    assert preset("turbid", jpeg_quality=70).jpeg_quality == 70
    with pytest.raises(ValueError, match="unknown water preset"):
        preset("murky")
    with pytest.raises(ValueError, match="vignetting"):
        preset("coastal", vignetting=1.5)


# ----------------------------------------------------------------------------- noise, JPEG


def test_same_seed_gives_identical_output_and_noise_has_the_model_variance() -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    r = rng.uniform(0.5, 5.0, img.shape[:2])
    cfg = PRESETS["coastal"]
    a = apply_water(img, r, cfg, np.random.default_rng(42))
    b = apply_water(img, r, cfg, np.random.default_rng(42))
    c = apply_water(img, r, cfg, np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert np.count_nonzero(a != c) > 0.3 * a.size
    # noise statistics on a flat linear image: std = sqrt(I / photons + read^2)
    flat = dataclasses.replace(cfg, **{**PLAIN, "gamma": 1.0, "photons_at_white": 400.0})
    flat = dataclasses.replace(flat, read_noise=0.01)
    clean = apply_water(
        _const(128, 200, 200),
        np.zeros((200, 200)),
        dataclasses.replace(flat, photons_at_white=None),
    ).astype(float)
    noisy = apply_water(_const(128, 200, 200), np.zeros((200, 200)), flat, rng).astype(float)
    expected_sd = 255.0 * np.sqrt(128 / 255 / 400.0 + 0.01**2)
    assert np.std(noisy - clean) == pytest.approx(np.sqrt(expected_sd**2 + 1 / 12), rel=0.05)
    assert abs(np.mean(noisy - clean)) < 0.1


def test_noise_requires_a_generator() -> None:
    with pytest.raises(ValueError, match="rng"):
        apply_water(_const(100), np.ones((6, 8)), PRESETS["coastal"], None)


def test_jpeg_off_and_on() -> None:
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:96, 0:128]
    img = np.stack([xx * 2, yy * 2, (xx + yy)], axis=2).astype(np.uint8)  # smooth ramps
    r = np.full(img.shape[:2], 1.5)
    cfg = preset("clear_tank", **PLAIN)
    off = apply_water(img, r, cfg)
    hi = apply_water(img, r, dataclasses.replace(cfg, jpeg_quality=95))
    lo = apply_water(img, r, dataclasses.replace(cfg, jpeg_quality=10))
    np.testing.assert_array_equal(off, apply_water(img, r, cfg, rng))  # no noise: no rng use
    err_hi = np.abs(hi.astype(int) - off).mean()
    err_lo = np.abs(lo.astype(int) - off).mean()
    assert hi.shape == off.shape and hi.dtype == np.uint8
    assert 0.0 < err_hi < 2.0 and err_lo > err_hi
    # colour order survives the BGR round trip through OpenCV's codec
    assert np.abs(hi.astype(int).mean(axis=(0, 1)) - off.mean(axis=(0, 1))).max() < 1.0


# ----------------------------------------------------------------------------- inputs


def test_invalid_inputs() -> None:
    cfg = preset("coastal", **PLAIN)
    for bad in (np.int16, np.nan, -0.5, np.inf):
        img = np.zeros((6, 8, 3), bad) if bad is np.int16 else np.full((6, 8, 3), bad, np.float32)
        with pytest.raises(ValueError, match="image"):
            apply_water(img, np.ones((6, 8)), cfg)
    with pytest.raises(ValueError, match="image"):
        apply_water(np.zeros((6, 8), np.float32), np.ones((6, 8)), cfg)
    with pytest.raises(ValueError, match="range_m"):
        apply_water(_const(1), np.ones((5, 8)), cfg)
    with pytest.raises(ValueError, match="range_m"):
        apply_water(_const(1), np.full((6, 8), -1.0), cfg)
    with pytest.raises(ValueError, match="range_m"):
        apply_water(_const(1), np.full((6, 8), np.nan), cfg)
    with pytest.raises(ValueError, match="B_inf_rgb"):
        dataclasses.replace(cfg, B_inf_rgb=(0.0, 1.5, 0.0)).validate()


# ----------------------------------------------------------------------------- light and exposure


def test_linear_radiance_input_equals_the_decoded_uint8_image() -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    r = rng.uniform(0.3, 9.0, img.shape[:2])
    for name in PRESET_ORDER:
        cfg = preset(name, jpeg_quality=None)
        linear = decode_lut(cfg.gamma)[img]
        a = apply_water(img, r, cfg, np.random.default_rng(5))
        b = apply_water(linear, r, cfg, np.random.default_rng(5))
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(
            b, apply_water(linear.astype(np.float64), r, cfg, np.random.default_rng(5))
        )


def test_radiance_above_one_reaches_the_sensor_unclipped() -> None:
    """Radiance 2 and 4 (a white board near the lamp) attenuated over 2 x 3 m of turbid water:
    exactly the formula, different grey levels (a renderer that clipped at 1 would make them
    equal)."""
    cfg = preset("turbid", **PLAIN, exposure=1.0)
    cfg = dataclasses.replace(cfg, artificial_light=True)
    r = 3.0
    D = np.exp(-2.0 * np.asarray(cfg.beta_D_rgb) * r)
    B = np.asarray(cfg.B_inf_rgb) * (1.0 - np.exp(-np.asarray(cfg.beta_B_rgb) * r))
    outs = []
    for L in (2.0, 4.0):
        img = np.full((6, 8, 3), L, np.float32)
        out = apply_water(img, np.full((6, 8), r), cfg)
        expected = 255.0 * np.clip(L * D + B, 0.0, 1.0) ** (1.0 / cfg.gamma)
        assert np.abs(out[0, 0] - expected).max() <= 0.51
        outs.append(out[0, 0].astype(int))
    assert np.all(outs[1] > outs[0]) and (outs[1] - outs[0]).max() >= 20


def test_auto_exposure_keeps_a_lamp_lit_white_board_below_full_scale() -> None:
    """Radiance 14 (white diffuse, 0.5 m from the default lamp) at 0.5 m of clear water: with a
    fixed exposure the sensor saturates; the auto exposure puts the metered level at its target
    (85 % of full scale) and nothing saturates. A dim frame keeps the longest exposure."""
    cfg = preset("clear_tank", photons_at_white=None, vignetting=0.0, jpeg_quality=None)
    img = np.full((40, 60, 3), 14.0, np.float32)
    img[:, :20] = 0.05  # a black border beside the board
    r = np.full((40, 60), 0.5)
    fixed = apply_water(img, r, dataclasses.replace(cfg, auto_exposure=False))
    assert (fixed[:, 30:] == 255).all()
    auto = apply_water(img, r, cfg)
    assert auto.max() < 255
    target = 255.0 * cfg.exposure_target ** (1.0 / cfg.gamma)
    assert auto[:, 30:].max() == pytest.approx(target, abs=1.0)
    assert auto[:, :20].max() < 40  # the black border stays black
    # the exposure follows the metered level exactly
    level = meter_level(np.full((40, 60, 3), 2.0, np.float32), 99.5)
    assert level == 2.0 and exposure_for(level, cfg) == pytest.approx(0.85 / 2.0)
    dim = np.full((40, 60, 3), 0.2, np.float32)
    np.testing.assert_array_equal(
        apply_water(dim, r, cfg), apply_water(dim, r, dataclasses.replace(cfg, auto_exposure=False))
    )
    assert exposure_for(0.0, cfg) == cfg.exposure  # a black frame: the longest exposure


# ----------------------------------------------------------------------------- randomisation


def test_randomisation_is_seeded_valid_and_spans_the_presets() -> None:
    rand = WaterRandomisation(turbidity_range=(0.0, 2.0), beta_log_sigma=0.0)
    rand.validate()
    draws = [rand.sample(np.random.default_rng(s)) for s in range(200)]
    assert rand.sample(np.random.default_rng(7)) == draws[7]
    beta_g = np.array([d.beta_D_rgb[1] for d in draws])
    lo, hi = JERLOV_KD_RGB["I"][1], JERLOV_KD_RGB["7C"][1]
    assert beta_g.min() >= lo - 1e-9 and beta_g.max() <= hi + 1e-9
    assert beta_g.min() < 0.08 and beta_g.max() > 0.45  # both ends reached
    jpeg = [d.jpeg_quality for d in draws]
    assert 0.35 < np.mean([q is not None for q in jpeg]) < 0.65
    assert all(60 <= q <= 95 for q in jpeg if q is not None)
    with pytest.raises(ValueError, match="turbidity_range"):
        WaterRandomisation(turbidity_range=(0.0, 9.0)).validate()
