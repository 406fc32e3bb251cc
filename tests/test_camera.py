"""Camera model, reference camera and extrinsics, camera file round trips and errors."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from uwdock.calibration import frames as F
from uwdock.calibration.camera import (
    REFERENCE_T_BODYFRD_CAMCV,
    CameraModel,
    load_camera,
    reference_camera,
    save_camera,
)
from uwdock.dockcore.errors import DockError


def _calibrated() -> CameraModel:
    return CameraModel(
        width_px=1280,
        height_px=960,
        fx_px=1012.345678901234,
        fy_px=1009.87654321,
        cx_px=641.123456789,
        cy_px=478.987654321,
        dist=(-0.21, 0.034, 0.0012, -0.0007, 0.0123),
        rms_px=0.318,
        name="tank cam: left",
    )


# ----------------------------------------------------------------------- model


def test_reference_camera_numbers():
    cam = reference_camera()
    assert (cam.width_px, cam.height_px) == (968, 732)
    f_expected = (968 / 2) / math.tan(math.radians(55 / 2))
    assert cam.fx_px == pytest.approx(f_expected, rel=1e-12)
    assert cam.fx_px == pytest.approx(929.76, abs=0.01)
    assert cam.fy_px == cam.fx_px
    assert (cam.cx_px, cam.cy_px) == (483.5, 365.5)
    assert cam.hfov_deg == pytest.approx(55.0, abs=1e-9)
    assert cam.vfov_deg == pytest.approx(42.97, abs=0.01)
    np.testing.assert_allclose(
        cam.K, [[cam.fx_px, 0, 483.5], [0, cam.fx_px, 365.5], [0, 0, 1]], rtol=0, atol=0
    )
    assert cam.dist_coeffs.shape == (5,) and not cam.dist_coeffs.any()


def test_point_on_optical_axis_projects_to_principal_point():
    for cam in (reference_camera(), _calibrated()):
        px = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 7.5]]))
        np.testing.assert_allclose(px, [[cam.cx_px, cam.cy_px]] * 2, atol=1e-9)
    single = reference_camera().project((0.0, 0.0, 2.0))
    assert single.shape == (2,)


def test_hfov_edge_projects_to_outer_pixel_edges():
    cam = reference_camera()
    half = math.radians(55.0 / 2)
    z = 3.0
    px = cam.project([[-z * math.tan(half), 0.0, z], [z * math.tan(half), 0.0, z]])
    np.testing.assert_allclose(px[:, 0], [-0.5, cam.width_px - 0.5], atol=1e-9)
    np.testing.assert_allclose(px[:, 1], cam.cy_px, atol=1e-9)
    vhalf = math.radians(cam.vfov_deg / 2)
    pv = cam.project([[0.0, -z * math.tan(vhalf), z], [0.0, z * math.tan(vhalf), z]])
    np.testing.assert_allclose(pv[:, 1], [-0.5, cam.height_px - 0.5], atol=1e-9)


def test_marker_size_in_pixels_matches_reference():
    # docs/reference-system.md section 3: a 0.10 m marker spans about 93 px at 1 m, 46 px at
    # 2 m, 19 px at 5 m
    cam = reference_camera()
    for z, span in ((1.0, 93), (2.0, 46), (5.0, 19)):
        px = cam.project([[-0.05, 0.0, z], [0.05, 0.0, z]])
        assert px[1, 0] - px[0, 0] == pytest.approx(span, abs=1.0)


def test_project_behind_camera_is_nan_and_in_image():
    cam = reference_camera()
    px = cam.project([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 1.0], [10.0, 0.0, 1.0]])
    assert np.isnan(px[:2]).all() and np.isfinite(px[2:]).all()
    np.testing.assert_array_equal(cam.in_image(px), [False, False, True, False])
    edges = np.array([[-0.5, -0.5], [967.49, 731.49], [967.5, 0.0], [0.0, -0.51]])
    np.testing.assert_array_equal(cam.in_image(edges), [True, True, False, False])
    np.testing.assert_array_equal(cam.in_image(edges, margin_px=1.0), [False] * 4)
    assert bool(cam.in_image(np.array([483.5, 365.5])))


def test_project_matches_manual_distortion_model():
    cam = _calibrated()
    p = np.array([0.3, -0.2, 1.5])
    x, y = p[0] / p[2], p[1] / p[2]
    k1, k2, p1, p2, k3 = cam.dist
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    expected = (cam.fx_px * xd + cam.cx_px, cam.fy_px * yd + cam.cy_px)
    np.testing.assert_allclose(cam.project(p), expected, atol=1e-9)


def test_scaled_halves_intrinsics():
    cam = reference_camera().scaled(484, 366)
    assert cam.fx_px == pytest.approx(929.7553494540443 / 2)
    assert (cam.cx_px, cam.cy_px) == (241.5, 182.5)  # still the image centre
    assert cam.hfov_deg == pytest.approx(55.0)
    # same ray, half the pixel coordinates (about the -0.5 corner)
    full = reference_camera().project((0.2, 0.1, 1.0))
    np.testing.assert_allclose(cam.project((0.2, 0.1, 1.0)), (full + 0.5) / 2 - 0.5, atol=1e-9)


@pytest.mark.parametrize(
    ("field", "value", "fragment"),
    [
        ("width_px", 0, "width_px"),
        ("height_px", 10.5, "height_px"),
        ("fx_px", -1.0, "fx_px"),
        ("fy_px", float("nan"), "fy_px"),
        ("dist", (0.0, 0.0, 0.0), "dist"),
        ("rms_px", -0.1, "rms_px"),
        ("name", "", "name"),
    ],
)
def test_validate_rejects(field, value, fragment):
    kwargs = dict(width_px=640, height_px=480, fx_px=500.0, fy_px=500.0, cx_px=320, cy_px=240)
    kwargs[field] = value
    with pytest.raises(ValueError, match=fragment):
        CameraModel(**kwargs)


def test_from_hfov_rejects_bad_angle():
    with pytest.raises(ValueError, match="hfov_deg"):
        CameraModel.from_hfov(640, 480, 180.0)


# ----------------------------------------------------------------------- extrinsics


def test_reference_extrinsics():
    T = F.check_T(REFERENCE_T_BODYFRD_CAMCV, "REFERENCE_T_BODYFRD_CAMCV")
    np.testing.assert_array_equal(T[:3, 3], (0.535, 0.0, 0.45))
    np.testing.assert_array_equal(T[:3, 2], (0, 0, 1))  # optical axis = body down
    cam = reference_camera()
    T_cam_body = F.inv_T(T)
    below = F.transform_points(T_cam_body, (0.535, 0.0, 0.45 + 2.0))
    np.testing.assert_allclose(below, (0, 0, 2.0), atol=1e-12)
    np.testing.assert_allclose(cam.project(below), (cam.cx_px, cam.cy_px), atol=1e-9)
    ahead = cam.project(F.transform_points(T_cam_body, (0.535 + 0.5, 0.0, 2.45)))
    assert ahead[1] < cam.cy_px - 100 and ahead[0] == pytest.approx(cam.cx_px)
    starboard = cam.project(F.transform_points(T_cam_body, (0.535, 0.5, 2.45)))
    assert starboard[0] > cam.cx_px + 100 and starboard[1] == pytest.approx(cam.cy_px)


# ----------------------------------------------------------------------- camera file


@pytest.mark.parametrize("with_T", [False, True])
def test_save_load_round_trip_yaml_and_json(tmp_path, with_T):
    cam = _calibrated()
    T = F.make_T(F.R_from_rpy(0.01, -0.02, math.pi / 2), (0.535, 0.001, 0.45)) if with_T else None
    yaml_path, json_path = save_camera(tmp_path / "sub" / "cam.yaml", cam, T)
    assert yaml_path == tmp_path / "sub" / "cam.yaml"
    assert json_path == tmp_path / "sub" / "cam.json"
    assert sorted(p.name for p in yaml_path.parent.iterdir()) == ["cam.json", "cam.yaml"]
    for path in (yaml_path, json_path):
        loaded, T_loaded = load_camera(path)
        assert loaded == cam  # exact, every field
        if with_T:
            np.testing.assert_array_equal(T_loaded, T)
        else:
            assert T_loaded is None


def test_round_trip_without_rms_and_with_8_coeffs(tmp_path):
    cam = CameraModel(640, 480, 500.0, 501.0, 319.5, 239.5, dist=tuple(np.arange(8) * 1e-3))
    for suffix in (".yaml", ".json"):
        save_camera(tmp_path / f"c{suffix}", cam)
        loaded, _ = load_camera(tmp_path / f"c{suffix}")
        assert loaded == cam and loaded.rms_px is None


def test_opencv_filestorage_reads_written_yaml(tmp_path):
    cam = _calibrated()
    T = np.array(REFERENCE_T_BODYFRD_CAMCV)
    yaml_path, json_path = save_camera(tmp_path / "cam.yaml", cam, T)
    fs = cv2.FileStorage(str(yaml_path), cv2.FILE_STORAGE_READ)
    try:
        np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), cam.K)
        np.testing.assert_array_equal(
            fs.getNode("distortion_coefficients").mat().ravel(), cam.dist_coeffs
        )
        assert int(fs.getNode("image_width").real()) == 1280
        assert int(fs.getNode("image_height").real()) == 960
        assert fs.getNode("rms_px").real() == cam.rms_px
        assert fs.getNode("name").string() == cam.name
        np.testing.assert_array_equal(fs.getNode("T_body_cam").mat(), T)
    finally:
        fs.release()
    doc = json.loads(json_path.read_text())
    assert doc["camera_matrix"] == cam.K.tolist()
    assert doc["distortion_coefficients"] == list(cam.dist)
    assert doc["T_body_cam"] == T.tolist()


def test_opencv_style_yaml_without_optional_keys(tmp_path):
    path = tmp_path / "ocv.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 800)
    fs.write("image_height", 600)
    fs.write("camera_matrix", np.array([[900.0, 0, 400], [0, 905, 300], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((5, 1)))
    fs.release()
    cam, T = load_camera(path)
    assert (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px) == (900.0, 905.0, 400.0, 300.0)
    assert cam.name == "camera" and cam.rms_px is None and T is None


def test_save_rejects_bad_extrinsics_and_suffix(tmp_path):
    bad_T = np.eye(4)
    bad_T[0, 0] = 2.0
    with pytest.raises(ValueError, match="T_body_cam"):
        save_camera(tmp_path / "cam.yaml", reference_camera(), bad_T)
    with pytest.raises(DockError, match=r"cam\.txt"):
        save_camera(tmp_path / "cam.txt", reference_camera())
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def _json_doc() -> dict:
    return {
        "format_version": 1,
        "name": "cam",
        "image_width": 640,
        "image_height": 480,
        "camera_matrix": [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]],
        "distortion_coefficients": [0, 0, 0, 0, 0],
    }


@pytest.mark.parametrize(
    ("mutate", "fragment"),
    [
        (lambda d: d.pop("camera_matrix"), "missing key 'camera_matrix'"),
        (lambda d: d.pop("image_height"), "missing key 'image_height'"),
        (lambda d: d.update(camera_matrix=[[1, 0], [0, 1]]), "key 'camera_matrix'"),
        (lambda d: d.update(camera_matrix="K"), "key 'camera_matrix'"),
        (lambda d: d.update(image_width=640.5), "key 'image_width'"),
        (lambda d: d.update(image_width=-640), "width_px"),
        (lambda d: d.update(distortion_coefficients=[0, 0, 0]), "dist"),
        (lambda d: d.update(format_version=2), "key 'format_version'"),
        (lambda d: d.update(T_body_cam=np.diag([1, 1, -1, 1]).tolist()), "key T_body_cam"),
        (lambda d: d.update(rms_px="small"), "key 'rms_px'"),
    ],
)
def test_bad_json_raises_dockerror_naming_file_and_key(tmp_path, mutate, fragment):
    doc = _json_doc()
    mutate(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(DockError) as info:
        load_camera(path)
    msg = str(info.value)
    assert str(path) in msg and fragment in msg and "\n" not in msg


def test_bad_yaml_raises_dockerror(tmp_path):
    good_yaml, _ = save_camera(tmp_path / "good.yaml", reference_camera())
    text = good_yaml.read_text()

    missing = tmp_path / "missing_key.yaml"
    missing.write_text(text.replace("image_height:", "image_heightx:"))
    with pytest.raises(DockError, match=r"missing_key\.yaml: missing key 'image_height'"):
        load_camera(missing)

    broken = tmp_path / "broken.yaml"
    broken.write_text("%YAML:1.0\n---\ncamera_matrix: [1, 2\n  foo: }\n")
    with pytest.raises(DockError, match=r"malformed camera file .*broken\.yaml") as info:
        load_camera(broken)
    assert "\n" not in str(info.value)

    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(DockError, match=r"empty\.yaml"):
        load_camera(empty)


def test_missing_or_unreadable_file_raises_dockerror(tmp_path):
    with pytest.raises(DockError, match=r"camera file not found: .*nope\.yaml"):
        load_camera(tmp_path / "nope.yaml")
    with pytest.raises(DockError, match=r"nope\.txt"):
        load_camera(tmp_path / "nope.txt")
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    with pytest.raises(DockError, match=r"malformed camera file .*bad\.json"):
        load_camera(bad_json)
    bad_json.write_text("[1, 2]")
    with pytest.raises(DockError, match=r"bad\.json: top level is not an object"):
        load_camera(bad_json)
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(DockError, match=r"dir\.yaml"):
        load_camera(tmp_path / "dir.yaml")
