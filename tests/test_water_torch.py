"""The torch water model (sim.water_torch) gives apply_water's image, to within one grey level.

Each configuration runs both models on the same frame with generators in the same state and
compares every pixel (one grey level allowed: float32 rounding in a different order moves a few
values across a rounding boundary), then checks that both generators were advanced alike.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwdock.sim.water import PRESETS, WaterConfig, apply_water, jpeg_roundtrip

torch = pytest.importorskip("torch")

from uwdock.sim.camera import SimCamera  # noqa: E402
from uwdock.sim.render import make_render_scene  # noqa: E402
from uwdock.sim.water_torch import apply_water_torch  # noqa: E402
from uwdock.sim.world_config import WorldConfig  # noqa: E402

H, W = 120, 160


def _scene(h: int = H, w: int = W) -> tuple[np.ndarray, np.ndarray]:
    """A smooth colour pattern with sharp edges (a checkerboard in blue, a bright square) and a
    range map from 0.5 m to 12 m with a corner of ``inf`` (nothing hit)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.stack(
        [
            128 + 100 * np.sin(xx / 9.0),
            128 + 100 * np.cos(yy / 7.0),
            255.0 * ((xx // 13 + yy // 11) % 2),
        ],
        axis=-1,
    )
    img[h // 3 : h // 2, w // 2 : 2 * w // 3] = 250.0
    rgb = np.clip(img, 0, 255).astype(np.uint8)
    r = 0.5 + 11.5 * (xx / (w - 1)) * (0.5 + 0.5 * yy / (h - 1))
    r[: h // 8, : w // 6] = np.inf
    return rgb, r.astype(np.float32)


def _max_diff(
    cfg: WaterConfig, h: int = H, w: int = W, frames: int = 1, hdr_scale: float | None = None
) -> int:
    """Largest |apply_water - apply_water_torch| over ``frames`` frames drawn from one generator
    each (same seed); asserts both generators end in the same state. ``hdr_scale``: feed the
    scene as float linear radiance times this factor (values above 1, as a render near the
    lamp) instead of uint8."""
    rgb, r = _scene(h, w)
    if hdr_scale is not None:
        rgb = (rgb.astype(np.float32) / 255.0) ** 2.2 * np.float32(hdr_scale)
    rng_np, rng_t = np.random.default_rng(7), np.random.default_rng(7)
    worst = 0
    for _ in range(frames):
        ref = apply_water(rgb, r, cfg, rng_np)
        out = apply_water_torch(rgb, r, cfg, rng_t)
        assert isinstance(out, np.ndarray) and out.dtype == np.uint8 and out.shape == ref.shape
        worst = max(worst, int(np.abs(ref.astype(np.int16) - out.astype(np.int16)).max()))
    assert rng_np.bit_generator.state == rng_t.bit_generator.state
    return worst


_COASTAL = PRESETS["coastal"]
CONFIGS: dict[str, WaterConfig] = {
    **{name: cfg for name, cfg in PRESETS.items()},
    "noise_off": dataclasses.replace(_COASTAL, photons_at_white=None),
    "falloff_2": dataclasses.replace(_COASTAL, light_falloff_exponent=2.0),
    "no_vignetting": dataclasses.replace(_COASTAL, vignetting=0.0),
    "gamma_1": dataclasses.replace(_COASTAL, gamma=1.0),
    "ambient_light": dataclasses.replace(_COASTAL, artificial_light=False),
    # strong blur: sigma up to 0.01 * 160 * 8 = 12.8 px, and 64 px at the largest
    **{
        f"levels_{n}_sigma_{s}": dataclasses.replace(_COASTAL, blur_levels=n, blur_sigma_per_m=s)
        for n in (2, 4)
        for s in (0.01, 0.05)
    },
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_same_image_as_apply_water(name: str) -> None:
    assert _max_diff(CONFIGS[name]) <= 1


@pytest.mark.parametrize(
    "cfg",
    [
        _COASTAL,
        PRESETS["clear_tank"],
        dataclasses.replace(_COASTAL, auto_exposure=False, exposure=0.3),
    ],
    ids=["coastal_auto_exposure", "clear_tank_auto_exposure", "coastal_fixed_exposure"],
)
def test_same_image_on_linear_radiance_above_one(cfg: WaterConfig) -> None:
    assert _max_diff(cfg, hdr_scale=6.0, frames=2) <= 1


def test_strong_blur_is_visible() -> None:
    """The blur configurations above do blur: edges move by tens of grey levels."""
    rgb, r = _scene()
    sharp = dataclasses.replace(_COASTAL, blur_sigma_per_m=0.0, photons_at_white=None)
    blurred = dataclasses.replace(sharp, blur_sigma_per_m=0.01)
    diff = np.abs(
        apply_water_torch(rgb, r, sharp).astype(np.int16)
        - apply_water_torch(rgb, r, blurred).astype(np.int16)
    )
    assert diff.max() > 15


def test_jpeg_is_opencvs_round_trip_of_the_image() -> None:
    """JPEG is the last step, run by OpenCV on the CPU as in apply_water. It is not compared
    with apply_water's JPEG to one grey level: where the images before JPEG differ by one level
    at a pixel (a few pixels per million), the compression spreads that over the 8 x 8 block
    (measured: up to 2-4 levels at a few hundred values per 968 x 732 frame, qualities 60-95)."""
    rgb, r = _scene()
    cfg = dataclasses.replace(_COASTAL, jpeg_quality=80)
    out = apply_water_torch(rgb, r, cfg, np.random.default_rng(4))
    plain = apply_water_torch(
        rgb, r, dataclasses.replace(cfg, jpeg_quality=None), np.random.default_rng(4)
    )
    assert np.array_equal(out, jpeg_roundtrip(plain, 80))


def test_infinite_range_is_pure_veiling_light() -> None:
    rgb, _ = _scene()
    r = np.full((H, W), np.inf, np.float32)
    cfg = dataclasses.replace(_COASTAL, photons_at_white=None, vignetting=0.0)
    out = apply_water_torch(rgb, r, cfg)
    expected = np.round(255.0 * np.asarray(cfg.B_inf_rgb) ** (1 / cfg.gamma))
    assert np.abs(out.astype(np.float64) - expected).max() <= 1
    assert np.array_equal(out, apply_water(rgb, r, cfg))


def test_full_frame_coastal() -> None:
    assert _max_diff(_COASTAL, 732, 968) <= 1


def test_frame_sequence_from_one_generator() -> None:
    assert _max_diff(_COASTAL, frames=3) <= 1


def test_tensor_in_tensor_out() -> None:
    rgb, r = _scene()
    cfg = _COASTAL
    rgb_t, r_t = torch.from_numpy(rgb), torch.from_numpy(r)
    out = apply_water_torch(rgb_t, r_t, cfg, np.random.default_rng(1))
    assert isinstance(out, torch.Tensor) and out.dtype == torch.uint8
    assert out.device.type == "cpu" and tuple(out.shape) == (H, W, 3)
    ref = apply_water(rgb, r, cfg, np.random.default_rng(1))
    assert np.abs(ref.astype(np.int16) - out.numpy().astype(np.int16)).max() <= 1
    # JPEG round trip: a tensor again
    jpeg = dataclasses.replace(cfg, jpeg_quality=70)
    out = apply_water_torch(rgb_t, r, jpeg, np.random.default_rng(1))
    assert isinstance(out, torch.Tensor) and out.dtype == torch.uint8
    assert tuple(out.shape) == (H, W, 3)


def test_inputs_are_not_modified() -> None:
    rgb, r = _scene()
    rgb_t, r_t = torch.from_numpy(rgb.copy()), torch.from_numpy(r.copy())
    apply_water_torch(rgb_t, r_t, _COASTAL, np.random.default_rng(0))
    assert np.array_equal(rgb_t.numpy(), rgb) and np.array_equal(r_t.numpy(), r)


_RGB, _R = _scene(6, 8)
BAD_INPUTS = {
    "int_image": (_RGB.astype(np.int16), _R, _COASTAL, 0),
    "nan_radiance": (np.where(_RGB > 200, np.nan, 0.5).astype(np.float32), _R, _COASTAL, 0),
    "negative_radiance": (np.where(_RGB > 200, -1.0, 0.5).astype(np.float32), _R, _COASTAL, 0),
    "inf_radiance": (np.where(_RGB > 200, np.inf, 0.5).astype(np.float32), _R, _COASTAL, 0),
    "grey_image": (_RGB[:, :, 0], _R, _COASTAL, 0),
    "rgba_image": (np.concatenate([_RGB, _RGB[:, :, :1]], axis=2), _R, _COASTAL, 0),
    "range_shape": (_RGB, _R[:, :-1], _COASTAL, 0),
    "negative_range": (_RGB, np.where(_R > 5, -1.0, _R), _COASTAL, 0),
    "nan_range": (_RGB, np.where(_R > 5, np.nan, _R), _COASTAL, 0),
    "noise_without_rng": (_RGB, _R, _COASTAL, None),
    "invalid_config": (_RGB, _R, dataclasses.replace(_COASTAL, vignetting=1.5), 0),
}


@pytest.mark.parametrize("name", list(BAD_INPUTS))
@pytest.mark.parametrize("as_tensor", [False, True])
def test_invalid_inputs_raise_apply_waters_errors(name: str, as_tensor: bool) -> None:
    rgb, r, cfg, seed = BAD_INPUTS[name]
    rng = None if seed is None else np.random.default_rng(seed)
    with pytest.raises(ValueError) as expected:
        apply_water(rgb, r, cfg, rng)
    if as_tensor:
        rgb, r = torch.from_numpy(np.ascontiguousarray(rgb)), torch.from_numpy(np.asarray(r))
    with pytest.raises(ValueError) as got:
        apply_water_torch(rgb, r, cfg, rng)
    assert str(got.value) == str(expected.value)


@pytest.mark.parametrize(
    ("h", "w", "sigma"),
    [
        (120, 160, 0.77),
        (120, 160, 2.3),
        (121, 157, 5.5),
        (732, 968, 7.7),
        (30, 47, 12.0),
        (7, 5, 12.0),
    ],
)
def test_blur_level_matches_opencv(h: int, w: int, sigma: float) -> None:
    """One forward-scatter level in float: full resolution (sigma < 1.6), the integer-scale and
    the fractional INTER_AREA downsampling, a kernel wider than the reduced image."""
    from uwdock.sim.water import blur_level as blur_np
    from uwdock.sim.water_torch import _blur_level as blur_t

    x = np.random.default_rng(3).random((h, w, 3), dtype=np.float32)
    ref = blur_np(x, sigma, np.empty_like(x))
    out = blur_t(torch.from_numpy(x).permute(2, 0, 1).contiguous(), sigma)
    assert np.abs(out.permute(1, 2, 0).numpy() - ref).max() < 2e-6


@pytest.mark.render
def test_the_sim_camera_runs_the_water_on_a_torch_device():
    """``EnvConfig.water_device`` / ``SimCamera(water_device=...)``: the env's camera frames
    through torch (here on its CPU device) are the numpy frames within one grey level."""
    rs = make_render_scene()
    T = rs.ds.T_worldned_ds.copy()
    T[2, 3] -= 4.0  # 4 m above the DS, level
    T[:3, :3] = np.eye(3)
    numpy_cam = SimCamera(rs.rig, PRESETS["coastal"])
    torch_cam = SimCamera(rs.rig, PRESETS["coastal"], water_device="cpu")
    a = numpy_cam.capture(T, np.random.default_rng(3)).img_rgb
    b = torch_cam.capture(T, np.random.default_rng(3)).img_rgb
    assert a.shape == b.shape and a.dtype == b.dtype == np.uint8
    assert int(np.abs(a.astype(int) - b.astype(int)).max()) <= 1


def test_world_config_checks_the_water_device():
    WorldConfig(water_device="cuda:1").validate()
    with pytest.raises(ValueError, match="water_device"):
        WorldConfig(water_device="gpu0").validate()
    WorldConfig(water_device="auto").validate()


@pytest.mark.render
def test_auto_keeps_the_water_on_numpy_where_sapien_renders_without_cuda():
    """``water_device = "auto"`` on lavapipe (no CUDA GPU): numpy, the default frames exactly."""
    rs = make_render_scene()
    T = rs.ds.T_worldned_ds.copy()
    T[2, 3] -= 4.0
    T[:3, :3] = np.eye(3)
    auto = SimCamera(rs.rig, PRESETS["coastal"], water_device="auto")
    if rs.scene.render_system.device.is_cuda():
        pytest.skip("SAPIEN renders on a CUDA GPU here")
    assert auto.water_device is None
    a = SimCamera(rs.rig, PRESETS["coastal"]).capture(T, np.random.default_rng(3)).img_rgb
    assert np.array_equal(a, auto.capture(T, np.random.default_rng(3)).img_rgb)


def test_auto_picks_the_cuda_gpu_the_renderer_uses(monkeypatch):
    """The renderer's CUDA index becomes the water's torch device, when torch sees CUDA."""
    from types import SimpleNamespace

    from uwdock.sim.camera import render_cuda_device

    def rig(is_cuda: bool, cuda_id: int):
        device = SimpleNamespace(is_cuda=lambda: is_cuda, cuda_id=cuda_id)
        scene = SimpleNamespace(render_system=SimpleNamespace(device=device))
        return SimpleNamespace(entity=SimpleNamespace(scene=scene))

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert render_cuda_device(rig(True, 1)) == "cuda:1"
    assert render_cuda_device(rig(True, -1)) is None  # a GPU CUDA cannot see
    assert render_cuda_device(rig(False, -1)) is None  # lavapipe
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert render_cuda_device(rig(True, 0)) is None  # torch without CUDA
