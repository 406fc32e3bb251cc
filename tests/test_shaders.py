"""The derived shaders (uwdock.sim.shaders): the fast edits of the ``minimal`` variant skip only
work whose result is exactly nothing in the toolkit's scenes, picture for picture."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sapien = pytest.importorskip("sapien")

from uwdock.calibration.camera import reference_camera  # noqa: E402
from uwdock.calibration.frames import make_T  # noqa: E402
from uwdock.datasets.synth import PoseSamplingConfig, frame_rng, sample_pose  # noqa: E402
from uwdock.sim.render import CameraRig, RenderConfig, make_render_scene  # noqa: E402
from uwdock.sim.shaders import EDITS, FAST_EDITS, hdr_shader_dir  # noqa: E402

SMALL = reference_camera().scaled(320, 240)


def _text(folder: str, name: str) -> str:
    return (Path(folder) / name).read_text(encoding="utf-8")


def test_fast_variant_holds_every_edit_and_the_reference_only_the_linear_ones() -> None:
    fast, ref = hdr_shader_dir("minimal"), hdr_shader_dir("minimal", fast=False)
    assert fast != ref
    for (shader, name), edits in FAST_EDITS.items():
        assert shader == "minimal"
        for old, new in edits:
            assert new in _text(fast, name) and old not in _text(fast, name)
            assert old in _text(ref, name)
    assert "outPositionSegmentation" not in _text(fast, "gbuffer.frag")
    for (shader, name), edits in EDITS.items():
        if shader == "minimal":
            for _, new in edits:
                assert new in _text(ref, name)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_render_scene(camera_model=SMALL, cache_dir=tmp_path_factory.mktemp("cache"))


@pytest.mark.parametrize("lamp", [False, True])
def test_fast_minimal_shader_renders_the_same_pictures(scene, lamp: bool) -> None:
    """Aimed views of the DS (1-6 m) and one out of the tank, lamp on and off: the fast variant's
    radiance equals the reference variant's exactly, its depth (read from the colour's alpha)
    within a millimetre."""
    scene.rig.set_lamp(False)
    rigs = [
        CameraRig(scene.scene, SMALL, cfg=RenderConfig(shader=s, lamp=True), name=f"r{k}")
        for k, s in enumerate(("minimal", hdr_shader_dir("minimal", fast=False)))
    ]
    T_bc = rigs[0].T_bodyfrd_camcv
    poses = [
        sample_pose(PoseSamplingConfig(aimed_fraction=1.0), frame_rng(7, k), SMALL, T_bc,
                    scene.ds.T_worldned_ds)[0]
        for k in range(4)
    ]  # fmt: skip
    # the vehicle pitched up 100 deg: the downward camera looks out of the open tank, so part of
    # the picture is background (range inf), the composite pass's other branch
    pitch = Rotation.from_euler("y", 100.0, degrees=True).as_matrix()
    poses.append(scene.ds.T_worldned_ds @ make_T(pitch, [-3.0, 0.0, -1.5]))
    pictures = []
    for rig in rigs:
        for other in rigs:
            other.set_lamp(lamp and other is rig)
        pictures.append([rig.render(T) for T in poses])
    lit = 0.0
    for a, b in zip(*pictures, strict=True):
        np.testing.assert_array_equal(a.radiance, b.radiance)
        # the depth: the fast variant's float depth from the depth buffer against the
        # reference's whole millimetres (+ 0.5 mm): the same pixels hit, within a millimetre
        hit = np.isfinite(b.range_m)
        np.testing.assert_array_equal(np.isfinite(a.range_m), hit)
        np.testing.assert_allclose(a.depth_m[hit], b.depth_m[hit], rtol=0, atol=1e-3)
        lit = max(lit, float(a.radiance.max()))
    assert lit > 0.1  # the views see something lit
    assert 0.05 < np.isinf(pictures[0][-1].range_m).mean() < 0.95  # and background
