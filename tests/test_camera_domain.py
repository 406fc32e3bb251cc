"""Every value in its domain (issue 54, part 4): a camera is checked by one validator
(:func:`calibration.camera.check_camera`) wherever it is read, and the board config against the
marker set it describes.

Before: a pixel aspect of 20:1, a ``T_body_cam`` 10^6 m from the vehicle (``extrinsics set``
refuses > 100 m, but ``datasets synth`` put the vehicle 997 km away) and a tangential
distortion p1 = 5 (markers found, poses silently dropped) were accepted; ``board.min_markers =
100`` with a 5-marker set was accepted (no frame could ever give a pose); a marker set holding
one ID the frames do not show was told to "check the camera, exposure, focus".
"""

from __future__ import annotations

import json
import typing
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import (
    MAX_CAMERA_OFFSET_M,
    REFERENCE_T_BODYFRD_CAMCV,
    check_camera,
    load_camera,
    reference_camera,
    save_camera,
)
from uwdock.datasets import cli as datasets_cli
from uwdock.dockcore.domains import bounds
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import marker_set_from_config, save_marker_set
from uwdock.perception import cli as perception_cli

REF = reference_camera()  # 968 x 732, f = 929.755 px


def _one_line(res) -> str:
    assert res.code == 2, (res.code, res.out, res.err)
    assert res.out == "" and "Traceback" not in res.err, res.err
    assert res.err.count("\n") == 1 and res.err.startswith("error: "), res.err
    return res.err.strip()


def _camera_json(path: Path, fx=None, dist=(0.0,) * 5, T_body_cam=None) -> Path:
    K = REF.K
    if fx is not None:
        K[0, 0] = fx
    doc = {
        "format_version": 1,
        "name": "c",
        "image_width": REF.width_px,
        "image_height": REF.height_px,
        "camera_matrix": K.tolist(),
        "distortion_coefficients": list(dist),
    }
    if T_body_cam is not None:
        doc["T_body_cam"] = np.asarray(T_body_cam).tolist()
    path.write_text(json.dumps(doc))
    return path


def _far() -> np.ndarray:
    T = np.array(REFERENCE_T_BODYFRD_CAMCV)
    T[:3, 3] = (1e6, 0.0, 0.45)
    return T


#: (file content, what the one line must say)
BAD_CAMERAS = {
    "aspect_20": (dict(fx=20 * REF.fy_px), "the pixel aspect 18595.1 / 929.755 = 20 is outside"),
    "p1_5": (dict(dist=(0.0, 0.0, 5.0, 0.0, 0.0)), "tangential distortion p1 = 5 is beyond +-0.5"),
    "p2_minus_1": (dict(dist=(0.0, 0.0, 0.0, -1.0, 0.0)), "tangential distortion p2 = -1 is"),
    "T_1e6_m": (
        dict(T_body_cam=_far()),
        "key T_body_cam: the camera is at (1e+06, 0, 0.45) m in the body frame",
    ),
}


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("frames")
    cv2.imwrite(str(folder / "a.png"), np.full((REF.height_px, REF.width_px), 128, np.uint8))
    return folder


@pytest.mark.parametrize("case", list(BAD_CAMERAS))
def test_bad_cameras_are_refused_by_every_reader(run_cli, tmp_path, frames, case):
    """The same line from perception detect, perception eval, datasets synth and calibration
    extrinsics show; nothing written."""
    content, said = BAD_CAMERAS[case]
    cam = _camera_json(tmp_path / "cam.json", **content)
    runs = [
        (perception_cli.main, "detect", frames, "--camera", cam, "--out", tmp_path / "d"),
        (perception_cli.main, "eval", frames, "--camera", cam, "--out", tmp_path / "e"),
        (datasets_cli.main, "synth", "--n", 1, "--camera", cam, "--out", tmp_path / "s"),
        (calibration_cli.main, "extrinsics", "show", cam),
    ]
    for main, *args in runs:
        msg = _one_line(run_cli(main, *args))
        assert msg.startswith(f"error: {cam}: ") and said in msg, (args[0], msg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam.json"]


@pytest.mark.parametrize("case", ["aspect_20", "p1_5"])
def test_bad_intrinsics_in_other_tools_files_are_refused(run_cli, tmp_path, case):
    """A ROS camera_info YAML (``calibration import``) and the vehicle node's camera_info go
    through the same check."""
    from uwdock.rl.deploy.inputs import read_camera_info

    content, said = BAD_CAMERAS[case]
    K = REF.K
    K[0, 0] = content.get("fx", K[0, 0])
    dist = list(content.get("dist", (0.0,) * 5))
    src = tmp_path / "info.yaml"
    src.write_text(
        f"image_width: {REF.width_px}\nimage_height: {REF.height_px}\ncamera_name: c\n"
        f"camera_matrix: {{rows: 3, cols: 3, data: {K.ravel().tolist()}}}\n"
        f"distortion_model: plumb_bob\n"
        f"distortion_coefficients: {{rows: 1, cols: 5, data: {dist}}}\n"
    )
    msg = _one_line(run_cli(calibration_cli.main, "import", src, "--out", tmp_path / "c.yaml"))
    assert msg.startswith(f"error: {src}: ") and said in msg, msg
    assert not (tmp_path / "c.yaml").exists()
    info = SimpleNamespace(k=K.ravel(), d=dist, width=REF.width_px, height=REF.height_px)
    with pytest.raises(
        ValueError, match="camera_info: .*" + said.split(" is ")[0].replace("+", r"\+")
    ):
        read_camera_info(info)


def test_the_limits_are_those_of_extrinsics_set_and_real_cameras_pass(tmp_path):
    """``extrinsics set`` takes +-MAX_CAMERA_OFFSET_M (one constant); a 2:1 anamorphic camera,
    p1 = 0.05 and a camera 99 m out are read; the writer refuses what no reader accepts."""
    xyz = typing.get_args(calibration_cli.XyzM)
    assert bounds(xyz[1:]) == {"ge": -MAX_CAMERA_OFFSET_M, "le": MAX_CAMERA_OFFSET_M}
    T = np.array(REFERENCE_T_BODYFRD_CAMCV)
    T[:3, 3] = (99.0, -99.0, 0.45)
    cam = _camera_json(tmp_path / "ok.json", fx=2 * REF.fy_px, dist=(-0.1, 0.02, 0.05, -0.05, 0.0))
    _camera_json(cam, fx=2 * REF.fy_px, dist=(-0.1, 0.02, 0.05, -0.05, 0.0), T_body_cam=T)
    model, T_read = load_camera(cam)
    assert model.fx_px == pytest.approx(2 * REF.fy_px) and model.dist[2] == 0.05
    np.testing.assert_allclose(T_read[:3, 3], (99.0, -99.0, 0.45))
    assert check_camera(model, T)[1][0, 3] == 99.0
    with pytest.raises(ValueError, match=r"T_body_cam: the camera is at \(1e\+06, 0, 0.45\) m"):
        save_camera(tmp_path / "far.yaml", REF, _far())
    assert not (tmp_path / "far.yaml").exists()


# --------------------------------------------------------------------------- marker sets


def _tag_frames(folder: Path, marker_id: int, n: int = 2) -> Path:
    """``n`` 320 x 240 frames of one flat DICT_4X4_50 tag."""
    folder.mkdir()
    tag = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), marker_id, 96
    )
    for k in range(n):
        img = np.full((240, 320), 255, np.uint8)
        img[60:156, 40 + 30 * k : 136 + 30 * k] = tag
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    return folder


@pytest.mark.parametrize("command", ["detect", "eval"])
def test_min_markers_beyond_the_set_is_refused(run_cli, tmp_path, command):
    frames = _tag_frames(tmp_path / "f", 13)
    cam = save_camera(tmp_path / "cam.yaml", REF.scaled(320, 240))[0]
    cfg = tmp_path / "p.toml"
    cfg.write_text("[board]\nmin_markers = 100\n")
    args = [command, frames, "--camera", cam, "--config", cfg, "--out", tmp_path / "o"]
    msg = _one_line(run_cli(perception_cli.main, *args))
    assert msg == (
        "error: board.min_markers: 100 is more than the 5 markers of the marker set "
        "(IDs 13, 14, 15, 28, 34): no frame could give a DS pose; use at most 5"
    )
    assert not (tmp_path / "o").exists()
    cfg.write_text("[board]\nmin_markers = 5\n")  # every marker of the set: allowed
    res = run_cli(perception_cli.main, *args)
    assert res.code == 0, res.err


def test_a_set_without_the_ids_in_view_is_told_so(run_cli, tmp_path):
    """A set holding one ID (13) of the frames' dictionary, frames showing ID 7: the warning
    says the frames show markers the set does not list, not "check the camera"."""
    frames = _tag_frames(tmp_path / "f", 7)
    ms = save_marker_set(tmp_path / "one.toml", marker_set_from_config(MarkerConfig(ids=(13,))))
    res = run_cli(perception_cli.main, "detect", frames, "--markers", ms, "--out", tmp_path / "o")
    assert res.code == 0, res.err
    warnings = [line for line in res.err.splitlines() if line.startswith("warning: ")]
    assert warnings == [
        "warning: no marker of the marker set (DICT_4X4_50, 1 ID(s): 13) found in 2 frame(s), "
        "but DICT_4X4_50 markers with IDs the set does not list are in view (IDs 7) in 2 of 2 "
        "sampled frame(s): only the set's IDs are looked for; use a marker set that lists the "
        "markers in view (or --dictionary DICT_4X4_50 for single markers)"
    ], res.err
    # the set's own ID in view: found, nothing to say
    frames13 = _tag_frames(tmp_path / "g", 13)
    res = run_cli(perception_cli.main, "detect", frames13, "--markers", ms, "--out", tmp_path / "p")
    assert res.code == 0 and "warning" not in res.err, res.err
