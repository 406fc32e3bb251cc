"""SAPIEN rendering of the docking station: intrinsics, ranges, ground truth and the PnP seam.

One scene (tank + reference DS + markers) is built per module; the camera rigs are added to it.
Marked ``render``: needs SAPIEN's Vulkan renderer (Mesa >= 24.3 lavapipe on the CPU, or a GPU).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from uwdock.perception.detector import Detector, DetectorConfig

sapien = pytest.importorskip("sapien")

from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV, CameraModel, reference_camera  # noqa: E402
from uwdock.calibration.frames import (  # noqa: E402
    T_WORLDZUP_WORLDNED,
    R_from_rpy,
    inv_T,
    make_T,
    rotation_angle_deg,
    transform_points,
)
from uwdock.sim.docking_station import sapien_pose  # noqa: E402
from uwdock.sim.render import CameraRig, RenderConfig, make_render_scene, project_markers  # noqa: E402
from uwdock.sim.water import apply_water, preset  # noqa: E402

pytestmark = pytest.mark.render

#: Small camera: the reference camera scaled to 320 x 240 (fx != fy), principal point moved off
#: the centre so that a half-pixel convention error in the SAPIEN intrinsics would show.
SMALL = dataclasses.replace(
    reference_camera().scaled(320, 240), cx_px=163.3, cy_px=115.6, name="small"
)


@pytest.fixture(scope="module")
def rs(tmp_path_factory):
    """Render scene with the small camera; the default marker set generated into a tmp cache."""
    return make_render_scene(camera_model=SMALL, cache_dir=tmp_path_factory.mktemp("uwdock_cache"))


def _use(rs, rig: CameraRig) -> CameraRig:
    """Light the scene with ``rig``'s lamp only."""
    rs.rig.set_lamp(rig is rs.rig)
    if rig is not rs.rig:
        rig.set_lamp(True)
    return rig


def _camera_above(rs, marker_id: int, height_m: float, yaw_rad: float = 0.0) -> np.ndarray:
    """Vehicle pose (T_worldned_bodyfrd) whose reference camera looks straight down at a marker
    face centre from ``height_m`` above it, image x along the marker's x rotated by ``yaw``."""
    T_ds_marker = rs.ds.marker_set[marker_id].T_ds_marker
    # cam_cv: z down (= -marker z), x = marker x rotated by yaw in the face plane
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R_marker_cam = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])
    T_marker_cam = make_T(R_marker_cam, [0.0, 0.0, height_m])
    T_worldned_camcv = rs.ds.T_worldned_ds @ T_ds_marker @ T_marker_cam
    return T_worldned_camcv @ inv_T(REFERENCE_T_BODYFRD_CAMCV)


def _insert_outline(grey: np.ndarray, around_px: np.ndarray, half_px: int) -> np.ndarray:
    """Filled outer contour (uint8 0/1 mask) of the bright insert around ``around_px``: the
    smallest bright region whose outline encloses that pixel (the black column rings it)."""
    mask = (grey > 230).astype(np.uint8)
    u, v = np.rint(around_px).astype(int)
    window = np.zeros_like(mask)
    window[v - half_px : v + half_px, u - half_px : u + half_px] = 1
    contours, hierarchy = cv2.findContours(mask * window, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    point = (float(around_px[0]), float(around_px[1]))
    outer = [c for c, h in zip(contours, hierarchy[0], strict=True) if h[3] < 0]  # not holes
    enclosing = [c for c in outer if cv2.pointPolygonTest(c, point, False) >= 0]
    filled = np.zeros_like(mask)
    cv2.drawContours(filled, [min(enclosing, key=cv2.contourArea)], -1, 1, cv2.FILLED)
    return filled


def _negative_aruco(rgb: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """The project's detector (``default`` pipeline) on the rendered frame, converted to BGR as
    every caller does; all IDs."""
    det = Detector(DetectorConfig())
    found = det.detect(np.ascontiguousarray(rgb[..., ::-1]))
    return [d.corners_px for d in found], np.array([d.marker_id for d in found], int)


# ----------------------------------------------------------------------------- DS geometry


def _ray_down_height_m(rs, x_m: float, y_m: float) -> float:
    """Height above the DS floor of the first surface under DS (x, y), by a physics ray."""
    T = T_WORLDZUP_WORLDNED @ rs.ds.T_worldned_ds
    origin = transform_points(T, [x_m, y_m, -3.0]).astype(np.float32)
    hit = rs.scene.physx_system.raycast(origin, np.array([0.0, 0.0, -1.0], np.float32), 10.0)
    assert hit is not None
    return 3.0 - float(hit.distance)


def test_x_guide_top_edge_is_the_wavy_profile(rs) -> None:
    y_prof, h_prof = rs.ds.cfg.x_guide_profile()
    for x in (-0.57, 0.57):
        for y in np.linspace(-0.84, 0.84, 15):
            assert _ray_down_height_m(rs, x, y) == pytest.approx(
                np.interp(y, y_prof, h_prof), abs=2e-3
            )
    notch = _ray_down_height_m(rs, 0.57, 0.425)
    assert notch == pytest.approx(1.081, abs=2e-3)
    assert _ray_down_height_m(rs, 0.57, 0.325) > notch + 0.03 < _ray_down_height_m(rs, 0.57, 0.525)


def test_cradle_markers_and_rim_collide_where_the_reference_says(rs) -> None:
    assert _ray_down_height_m(rs, 0.0, 0.65) == pytest.approx(0.38, abs=2e-3)  # central support
    assert _ray_down_height_m(rs, 0.52, -0.65) == pytest.approx(1.22, abs=2e-3)  # cradle post
    for spec in rs.ds.marker_set.markers:  # marker faces (collision boxes of the pedestals)
        x, y, z = spec.T_ds_marker[:3, 3]
        assert _ray_down_height_m(rs, x + 0.03, y + 0.03) == pytest.approx(-z, abs=2e-3)
    assert _ray_down_height_m(rs, 0.3, -0.3) == pytest.approx(0.0, abs=2e-3)  # DS floor


# ----------------------------------------------------------------------------- intrinsics


def test_marker_below_the_camera_lands_on_the_principal_point(rs) -> None:
    rig = _use(rs, rs.rig)
    res = rig.render(_camera_above(rs, 14, 1.2))
    gt = rs.ground_truth(res)[14]
    # the 3D marker centre projects to the principal point (the frame chain)
    np.testing.assert_allclose(gt.centre_px, [SMALL.cx_px, SMALL.cy_px], atol=1e-6)
    # ... and the rendered insert is centred there (the SAPIEN intrinsics and pose)
    grey = cv2.cvtColor(res.rgb, cv2.COLOR_RGB2GRAY)
    m = cv2.moments(_insert_outline(grey, gt.centre_px, 30), binaryImage=True)
    centroid = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
    assert np.linalg.norm(centroid - gt.centre_px) < 0.5
    side_px = np.sqrt(m["m00"])  # the square's area gives its side
    expected_side = np.linalg.norm(gt.corners_px[1] - gt.corners_px[0])
    assert side_px == pytest.approx(expected_side, abs=1.0)


def test_range_and_depth_images_are_metric(rs) -> None:
    rig = _use(rs, rs.rig)
    T_body = _camera_above(rs, 14, 1.2, yaw_rad=0.4)
    res = rig.render(T_body)
    T_cam_marker = rs.T_camcv_ds(res.T_worldned_camcv) @ rs.ds.marker_set[14].T_ds_marker
    side = rs.ds.marker_set[14].side_m
    n, p0 = T_cam_marker[:3, 2], T_cam_marker[:3, 3]
    for pt in ([-side / 2 + side / 12, 0.0, 0.0], [0.0, side / 2 - side / 12, 0.0]):  # border cells
        u, v = np.rint(SMALL.project(transform_points(T_cam_marker, pt))).astype(int)
        ray = np.linalg.solve(SMALL.K, [u, v, 1.0])
        t = n @ p0 / (n @ ray)  # ray parameter where the pixel's ray meets the face plane
        assert res.range_m[v, u] == pytest.approx(t * np.linalg.norm(ray), abs=0.01)
        assert res.depth_m[v, u] == pytest.approx(t, abs=0.01)
    assert res.range_m.dtype == np.float32 and np.all(np.isfinite(res.range_m))  # tank all round
    assert np.all(res.range_m >= res.depth_m)


def test_ground_truth_corners_match_the_detected_marker(rs) -> None:
    rig = _use(rs, rs.rig)
    res = rig.render(_camera_above(rs, 15, 0.9, yaw_rad=0.5))
    gt = rs.ground_truth(res)
    corners, ids = _negative_aruco(res.rgb)
    assert 15 in ids
    detected = corners[list(ids).index(15)]
    assert np.abs(detected - gt[15].corners_px).max() < 2.0
    assert gt[15].visible and not gt[15].occluded
    assert all(gt[i].visible for i in ids if i in gt)  # every detected marker is flagged visible


def test_occluded_marker_is_flagged(rs) -> None:
    rig = _use(rs, rs.rig)
    T_body = _camera_above(rs, 14, 1.5)
    assert rs.ground_truth(rig.render(T_body))[14].visible
    # a plate 0.5 m above marker 14 hides it
    builder = rs.scene.create_actor_builder()
    builder.add_box_visual(half_size=[0.2, 0.2, 0.01], material=[0.5, 0.5, 0.5])
    T_ds_plate = rs.ds.marker_set[14].T_ds_marker @ make_T(t=[0.0, 0.0, 0.5])
    builder.set_initial_pose(sapien_pose(rs.ds.T_worldned_ds @ T_ds_plate))
    plate = builder.build_static("occluder")
    try:
        res = rig.render(T_body)
        proj = rs.ground_truth(res)[14]
        assert proj.in_image and proj.occluded and not proj.visible
    finally:
        rs.scene.remove_entity(plate)


def test_distorted_camera_matches_project_markers(rs) -> None:
    cam = CameraModel(
        width_px=320, height_px=240, fx_px=300.0, fy_px=300.0, cx_px=160.5, cy_px=118.0,
        dist=(-0.25, 0.08, 0.0, 0.0, 0.0), name="distorted",
    )  # fmt: skip
    rig = _use(rs, CameraRig(rs.scene, cam, cfg=RenderConfig()))
    T_body = _camera_above(rs, 28, 0.8) @ make_T(t=[0.0, 0.3, 0.0])  # marker off-centre
    res = rig.render(T_body)
    gt = project_markers(cam, rs.T_camcv_ds(res.T_worldned_camcv), rs.ds.marker_set)[28]
    pinhole = dataclasses.replace(cam, dist=(0.0,) * 5)
    gt_pinhole = project_markers(pinhole, rs.T_camcv_ds(res.T_worldned_camcv), rs.ds.marker_set)
    assert np.linalg.norm(gt.centre_px - gt_pinhole[28].centre_px) > 3.0  # distortion matters
    grey = cv2.cvtColor(res.rgb, cv2.COLOR_RGB2GRAY)
    m = cv2.moments(_insert_outline(grey, gt.centre_px, 28), binaryImage=True)
    centroid = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
    assert np.linalg.norm(centroid - gt.centre_px) < 1.0
    rig.set_lamp(False)  # its lamp would light the later tests' scenes too
    _use(rs, rs.rig)


# ----------------------------------------------------------------------------- the seam


@pytest.fixture(scope="module")
def reference_rig(rs) -> CameraRig:
    return CameraRig(rs.scene, reference_camera(), REFERENCE_T_BODYFRD_CAMCV)


@pytest.mark.parametrize("water", [None, "clear_tank"])
def test_seam_render_detect_pnp_recovers_the_ds_pose(rs, reference_rig, water) -> None:
    """Render at 968 x 732 (camera ~2 m above the DS rim, 3.3-3.5 m above the floor markers),
    optionally through clear tank water with noise and JPEG, detect the negative markers, solve
    the board pose with SQPNP from the marker set's corners: within 2 cm and 1 deg of the truth."""
    rig = _use(rs, reference_rig)
    T_body = rs.ds.T_worldned_ds @ make_T(R_from_rpy(0.0, 0.0, 0.0), [0.1, 0.1, -4.2])
    res = rig.render(T_body)
    rgb = res.rgb
    if water is not None:
        cfg = preset(water, jpeg_quality=90)
        rgb = apply_water(res.radiance, res.range_m, cfg, np.random.default_rng(0))
    truth = rs.T_camcv_ds(res.T_worldned_camcv)
    visible = {m for m, p in rs.ground_truth(res).items() if p.visible}
    corners, ids = _negative_aruco(rgb)
    board = rs.ds.marker_set.corners_ds()
    found = [(i, c) for i, c in zip(ids, corners, strict=True) if i in board]
    assert len(found) >= 4 and {i for i, _ in found} <= visible
    obj = np.vstack([board[i] for i, _ in found])
    img = np.vstack([c for _, c in found])
    ok, rvec, tvec = cv2.solvePnP(
        obj, img, res.camera.K, res.camera.dist_coeffs, flags=cv2.SOLVEPNP_SQPNP
    )
    assert ok
    R, _ = cv2.Rodrigues(rvec)
    assert np.linalg.norm(tvec.ravel() - truth[:3, 3]) < 0.02
    assert rotation_angle_deg(R, truth[:3, :3]) < 1.0
    _use(rs, rs.rig)


# ----------------------------------------------------------------------------- linear light


def test_the_render_is_linear_radiance_and_the_sensor_alone_clips() -> None:
    """A white diffuse plate 0.5 m in front of the camera under the default lamp: the render
    holds the radiance albedo * I * cos / (pi d**2) + ambient * albedo (about 14, not clipped at
    1), and through water with the camera's auto exposure no pixel of the plate saturates."""
    scene = sapien.Scene()
    cfg = RenderConfig()
    scene.ambient_light = list(cfg.ambient_rgb)
    albedo, dist_m = 0.8, 0.5
    builder = scene.create_actor_builder()
    mat = sapien.render.RenderMaterial(
        base_color=[albedo, albedo, albedo, 1.0], roughness=1.0, metallic=0.0, specular=0.0
    )
    builder.add_box_visual(half_size=[1.0, 1.0, 0.01], material=mat)
    T_cam = make_T(None, [0.0, 0.0, 0.0])  # cam_cv at the world origin, looking along +z (NED down)
    builder.set_initial_pose(sapien_pose(make_T(None, [0.0, 0.0, dist_m + 0.01])))
    builder.build_static("plate")
    cam = reference_camera().scaled(160, 120)
    rig = CameraRig(scene, cam, cfg=cfg)
    res = rig.render(T_worldned_camcv=T_cam)
    u, v = round(cam.cx_px), round(cam.cy_px)
    lamp = np.asarray(cfg.lamp_offset_camcv_m)
    to_lamp = lamp - np.array([0.0, 0.0, dist_m])
    d = np.linalg.norm(to_lamp)
    cos = np.dot([0.0, 0.0, -1.0], to_lamp) / d  # the plate's normal points at the camera
    expected = albedo * cfg.lamp_intensity * np.asarray(cfg.lamp_rgb) * cos / (
        np.pi * d**2
    ) + albedo * np.asarray(cfg.ambient_rgb)
    assert res.radiance.dtype == np.float32
    np.testing.assert_allclose(res.radiance[v, u], expected, rtol=0.02)
    assert res.radiance.max() > 10.0  # nothing clipped at 1 before the water
    assert res.rgb[v, u].min() == 255  # the in-air display image does clip
    for name in ("clear_tank", "coastal"):
        img = apply_water(res.radiance, res.range_m, preset(name), np.random.default_rng(0))
        plate = res.range_m < 1.0
        assert plate.mean() > 0.9 and img[plate].max() < 255, name
        fixed = preset(name, auto_exposure=False)
        assert (
            apply_water(res.radiance, res.range_m, fixed, np.random.default_rng(0)) == 255
        ).any()
