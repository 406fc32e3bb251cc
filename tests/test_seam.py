"""The sim -> perception seam: one camera resolution, channel order, one DS-pose estimator."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from uwdock.calibration.camera import (
    REFERENCE_T_BODYFRD_CAMCV,
    CameraModel,
    reference_camera,
    resolve_camera,
    save_camera,
    scaled_to_width,
)
from uwdock.calibration.frames import R_from_rpy, inv_T, make_T
from uwdock.dockcore.config import from_dict, read_toml, replace, to_dict
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import marker_set_from_config
from uwdock.markers.view import markers_in_view
from uwdock.perception.detector import Detector
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.error_model import count_in_view
from uwdock.rl.env.obs_sources import StepContext

ROOT = Path(__file__).resolve().parent.parent
MARKERS = marker_set_from_config(MarkerConfig())


# ----------------------------------------------------------------------------- camera


def test_resolve_camera_falls_back_to_the_reference_and_scales_to_a_width(tmp_path):
    cam, T = resolve_camera(None, 480)
    ref = reference_camera()
    assert (cam.width_px, cam.height_px) == (480, round(732 * 480 / 968))
    assert cam.fx_px == pytest.approx(ref.fx_px * 480 / 968, rel=1e-12)
    np.testing.assert_array_equal(T, REFERENCE_T_BODYFRD_CAMCV)
    assert resolve_camera(None, 0)[0] == ref  # 0 keeps the size
    # a file with its own mounting: the mounting is the file's, the intrinsics scaled
    T_file = make_T(R_from_rpy(0.0, 0.1, np.pi / 2), [0.4, 0.05, 0.5])
    path, _ = save_camera(tmp_path / "cam.yaml", ref.scaled(640, 484), T_file)
    cam, T = resolve_camera(path, 320)
    assert (cam.width_px, cam.height_px) == (320, 242)
    np.testing.assert_allclose(T, T_file, atol=1e-12)
    # a file without one: the reference mounting
    path, _ = save_camera(tmp_path / "bare.yaml", ref)
    np.testing.assert_array_equal(resolve_camera(path)[1], REFERENCE_T_BODYFRD_CAMCV)


def test_world_config_is_built_from_the_flat_env_keys_of_existing_run_folders():
    """The shipped policy's run config (flat keys) loads and gives its world config."""
    env = read_toml(ROOT / "rl/policies/error_model_ppo/config.toml")["train"]["env"]
    assert "world" not in env and "camera_width_px" in env  # the layout before [env.world]
    w = from_dict(EnvConfig, env).world
    assert w.camera_width_px == env["camera_width_px"]
    assert list(w.tank_size_m) == env["tank_size_m"]
    assert w.water_preset == env["water_preset"] and w.physics_hz == env["physics_hz"]
    vehicle = to_dict(w.vehicle)
    assert {k: vehicle[k] for k in env["vehicle"]} == env["vehicle"]  # fields added since: defaults
    assert to_dict(w.current) == env["current"]
    with pytest.raises(ValueError, match="camera_width_px: must be 0 or >= 16"):
        replace(EnvConfig(), world={"camera_width_px": 8})


# ----------------------------------------------------------------------------- in view


def _distorted() -> CameraModel:
    return dataclasses.replace(
        reference_camera().scaled(640, 484), dist=(-0.35, 0.1, 0.0, 0.0, 0.0)
    )


def test_markers_in_view_applies_lens_distortion():
    """A marker just outside the pinhole image is pulled inside by barrel distortion: the in-view
    test must agree with cv2.projectPoints of the distorted camera, not with the pinhole one."""
    cam = _distorted()
    corners = np.stack([MARKERS.corners_ds()[i] for i in sorted(MARKERS.corners_ds())])
    # slide the board sideways until some marker is in view with distortion only
    found = False
    for dx in np.linspace(0.0, 3.0, 301):
        T_cam_ds = make_T(np.eye(3), [dx, 0.0, 4.0])
        got = markers_in_view(cam, T_cam_ds, corners)
        p = corners.reshape(-1, 3) + T_cam_ds[:3, 3]
        px, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
        px = px.reshape(-1, 4, 2)
        truth = np.all(
            (px[..., 0] >= -0.5)
            & (px[..., 0] < cam.width_px - 0.5)
            & (px[..., 1] >= -0.5)
            & (px[..., 1] < cam.height_px - 0.5),
            axis=1,
        )
        np.testing.assert_array_equal(got, truth)
        pin = cam.K @ p.T
        u = (pin[0] / pin[2]).reshape(-1, 4)
        pinhole = np.all((u >= -0.5) & (u < cam.width_px - 0.5), axis=1)
        found |= bool(np.any(truth & ~pinhole))
        assert count_in_view(cam, T_cam_ds, corners) == int(truth.sum())
    assert found  # the case that the pinhole copy got wrong was exercised


# ----------------------------------------------------------------------------- channel order


def _fake_world(rgb: np.ndarray, camera: CameraModel):
    """A world with a camera whose render is a fixed RGB image (no SAPIEN needed)."""
    from uwdock.sim.camera import SimCamera
    from uwdock.sim.render import RenderResult
    from uwdock.sim.water import decode_lut

    def render(T_world_body):
        T_wc = np.asarray(T_world_body) @ REFERENCE_T_BODYFRD_CAMCV
        rng_m = np.full(rgb.shape[:2], 0.5, np.float32)
        radiance = decode_lut(2.2)[rgb]  # linear radiance whose display image is ``rgb``
        return RenderResult(radiance, rng_m, rng_m.copy(), T_wc, camera)

    rig = SimpleNamespace(camera=camera, T_bodyfrd_camcv=np.array(REFERENCE_T_BODYFRD_CAMCV))
    rig.render = render
    ds = SimpleNamespace(marker_set=MARKERS)
    sim_camera = SimCamera(rig, water=None)
    capture = lambda rng, T_world_body: sim_camera.capture(T_world_body, rng)  # noqa: E731
    return SimpleNamespace(camera=sim_camera, ds=ds, capture=capture)


def test_camera_source_hands_the_detector_bgr(monkeypatch):
    """RGB must not reach the detector's BGR contract: a red-dominant rendered frame arrives
    with red in the last channel. (Before the fix the env passed the rendered RGB frame on.)"""
    from uwdock.rl.env.camera_source import CameraSource

    cam = reference_camera().scaled(96, 73)
    rgb = np.zeros((73, 96, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 90, 20  # R, G, B
    seen = []

    def spy(self, img_bgr, predicted=None):
        seen.append(np.array(img_bgr))
        return []

    monkeypatch.setattr(Detector, "detect", spy)
    source = CameraSource(_fake_world(rgb, cam))
    source.reset(np.random.default_rng(0))
    ctx = StepContext(np.eye(4), np.eye(4), 0.0, None)
    assert source.measure(ctx) is None
    assert len(seen) == 1
    np.testing.assert_array_equal(seen[0], rgb[..., ::-1])  # B, G, R
    grey = cv2.cvtColor(seen[0], cv2.COLOR_BGR2GRAY)
    assert int(grey[0, 0]) == round(0.299 * 200 + 0.587 * 90 + 0.114 * 20)  # BT.601 luma


def test_frame_names_its_channel_order():
    from uwdock.sim.camera import Frame

    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 255
    f = Frame(rgb, np.ones((4, 5), np.float32), np.eye(4), reference_camera().scaled(5, 4))
    assert f.channels == "RGB"
    assert np.all(f.img_bgr()[..., 2] == 255) and np.all(f.img_bgr()[..., :2] == 0)


# ----------------------------------------------------------------------------- rendered


@pytest.mark.render
def test_world_and_runner_resolve_the_same_camera(tmp_path):
    """A camera file at 968 px with camera_width_px 484: the env's world renders at 484 and the
    runner estimates at 484 (it resizes the file-sized frames), with the same model."""
    from uwdock.rl.deploy.runner import DockingRunner
    from uwdock.sim.world import DockingWorld

    T_file = make_T(R_from_rpy(0.0, 0.0, np.pi / 2), [0.5, 0.0, 0.45])
    path, _ = save_camera(tmp_path / "cam.yaml", reference_camera(), T_file)
    cfg = replace(EnvConfig(), camera_file=str(path), camera_width_px=484)
    world = DockingWorld(cfg.world, with_camera=True)
    runner = DockingRunner(SimpleNamespace(act=lambda obs: np.zeros(6)), env_cfg=cfg)
    runner_file = DockingRunner(
        SimpleNamespace(act=lambda obs: np.zeros(6)), camera_file=path, env_cfg=cfg
    )
    assert world.camera.model.width_px == 484
    assert runner_file.camera == world.camera.model
    np.testing.assert_allclose(runner_file.T_body_cam, world.camera.T_body_cam, atol=1e-12)
    assert runner.camera == scaled_to_width(reference_camera(), 484)
    full = np.zeros((732, 968, 3), np.uint8)
    assert runner_file.frame_for_camera(full).shape == (366, 484, 3)
    world.close()


@pytest.mark.render
def test_perception_eval_and_the_camera_source_give_the_same_ds_pose(tmp_path):
    """For the same rendered frames, `perception eval` on a `datasets synth` folder and the env's
    camera source (fed the frame in the renderer's RGB order) give the same detections and the
    same DS pose, with the level-DS refinement on both sides."""
    from uwdock.datasets.synth import SynthConfig, generate
    from uwdock.perception.evaluate import resolve_markers, run_eval
    from uwdock.perception.groundtruth import load_dataset
    from uwdock.rl.env.camera_source import CameraSource
    from uwdock.sim.camera import Frame
    from uwdock.sim.world import DockingWorld

    width = 480
    generate(
        tmp_path / "ds",
        SynthConfig(n_frames=6, seed=11, water="coastal", width_px=width),
        workers=1,
        progress=False,
    )
    ds = load_dataset(tmp_path / "ds")
    camera, T_body_cam = resolve_camera(ds.camera_path)
    run_eval(
        ds.images_dir,
        tmp_path / "eval",
        resolve_markers(ds.marker_set_path),
        camera,
        truth=ds.frames,
        progress=False,
        T_body_cam=T_body_cam,
    )
    rows = [json.loads(line) for line in (tmp_path / "eval/frames.jsonl").read_text().splitlines()]
    by_name = {r["name"]: r for r in rows}

    cfg = replace(EnvConfig(), camera_width_px=width)  # the default DS, as the dataset
    world = DockingWorld(cfg.world, with_camera=True)
    assert world.camera.model == camera  # the env resolves the dataset's camera
    source = CameraSource(world)
    compared = 0
    for ft in ds.frames.values():
        img_bgr = cv2.imread(str(ds.root / ft.image))
        T_world_cam = ft.T_world_body @ T_body_cam
        frame = Frame(np.ascontiguousarray(img_bgr[..., ::-1]), None, T_world_cam, camera)
        ctx = StepContext(ft.T_world_body, T_world_cam @ ft.T_cam_ds, 0.0, None)
        m = source.measure_frame(frame, ctx)
        row = by_name[Path(ft.image).name]
        assert [d.marker_id for d in source.last_detections] == row["ids"]
        if row["T_cam_ds"] is None:
            assert m is None
            continue
        T_cam_ds = inv_T(T_world_cam) @ m.T_world_ds
        np.testing.assert_allclose(T_cam_ds, np.asarray(row["T_cam_ds"]), atol=1e-9)
        err_m = np.linalg.norm(T_cam_ds[:3, 3] - ft.T_cam_ds[:3, 3])
        assert err_m < 0.01 + 0.04 * ft.range_m  # and near the truth (coastal water)
        compared += 1
    assert compared >= 2
    world.close()


def test_search_from_a_pose_prior_gives_the_whole_frame_estimate(tmp_path):
    """Rendered frames, the estimator with ``search_from_prior``: a prior 3 cm / 2 deg off
    (world frame, as the filter gives it, or camera frame, as the last video frame gives it)
    finds the markers the whole frame finds (a region's own stretch sometimes decodes one more:
    1 of 12 frames here) and the same level-DS pose, within 1 cm (corners move up to ~1 px: the
    stretch is measured on the region)."""
    from uwdock.calibration.frames import R_from_rpy
    from uwdock.datasets.synth import SynthConfig, generate
    from uwdock.perception.ds_pose import DSPoseConfig, DSPoseEstimator
    from uwdock.perception.groundtruth import load_dataset

    generate(
        tmp_path / "ds",
        SynthConfig(n_frames=12, seed=5, water="clear_tank", width_px=480),
        workers=1,
        progress=False,
    )
    ds = load_dataset(tmp_path / "ds")
    camera, T_body_cam = resolve_camera(ds.camera_path)
    whole = DSPoseEstimator.from_marker_set(MARKERS)
    near = DSPoseEstimator.from_marker_set(MARKERS, pose_cfg=DSPoseConfig(search_from_prior=True))
    off = make_T(R_from_rpy(0.0, 0.0, np.radians(2.0)), [0.03, -0.02, 0.01])
    searched, extra = [], 0
    for ft in ds.frames.values():
        img = cv2.imread(str(ds.root / ft.image))
        T_world_cam = ft.T_world_body @ T_body_cam
        T_world_ds = T_world_cam @ ft.T_cam_ds
        a = whole.estimate(img, camera, T_world_cam, T_world_ds @ off)
        b = near.estimate(img, camera, T_world_cam, T_world_ds @ off)
        searched.append(near.detector.last_search)
        c = near.estimate(img, camera, T_cam_ds_prior=ft.T_cam_ds @ off)  # no attitude: no level
        assert near.detector.last_search == searched[-1]
        ids_a = [d.marker_id for d in a.detections]
        ids_b = [d.marker_id for d in b.detections]
        assert [d.marker_id for d in c.detections] == ids_b
        if searched[-1] == "frame":
            assert ids_b == ids_a
        else:  # a region's own stretch may decode a marker the whole frame missed, never less
            assert set(ids_a) <= set(ids_b)
            extra += len(ids_b) - len(ids_a)
        corners_b = {d.marker_id: d.corners_px for d in b.detections}
        for d in a.detections:
            assert np.abs(d.corners_px - corners_b[d.marker_id]).max() < 1.5
        if a.level is not None and ids_a == ids_b:
            assert np.abs(b.T_cam_ds[:3, 3] - a.T_cam_ds[:3, 3]).max() < 0.01
    assert "regions" in searched  # frames with the markers in view took the regions
    assert extra <= 2
