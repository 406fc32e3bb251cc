"""Camera files for other tools, written: a ROS ``camera_info`` YAML and a Kalibr camchain
(:func:`export_camera_file`, ``calibration export``). :mod:`calibration.formats` reads them.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import (
    CameraModel,
    load_camera,
    twin_paths,
)
from uwdock.calibration.formats import show_value
from uwdock.calibration.frames import check_T
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_text

__all__ = [
    "EXPORT_FORMATS",
    "export_camera_file",
    "kalibr_camchain_yaml",
    "kalibr_camera_lines",
    "ros_camera_info_yaml",
    "ros_distortion_model",
]

#: ``--format`` of ``calibration export``.
EXPORT_FORMATS = ("ros", "kalibr")

_HIGHER = ("k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")


def _num(x: float) -> str:
    """Shortest round-trip text of ``x`` with a '.' before any exponent (PyYAML's floats)."""
    text = repr(float(x))
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text


def _yaml_str(text: str) -> str:
    """``text`` as a YAML scalar: plain where every reader keeps it a string, else quoted."""
    keyword = text.lower() in ("y", "n", "yes", "no", "on", "off", "true", "false", "null")
    if re.fullmatch(r"[A-Za-z_/][A-Za-z0-9_./-]*", text) and not keyword:
        return text
    return json.dumps(text)


def _flow_list(values: ArrayLike) -> str:
    return "[" + ", ".join(_num(v) for v in np.asarray(values, dtype=np.float64).ravel()) + "]"


def _padded(cam: CameraModel) -> list[float]:
    return list(cam.dist) + [0.0] * (14 - len(cam.dist))


def ros_distortion_model(cam: CameraModel, where: str = "camera") -> str:
    """``plumb_bob`` or ``rational_polynomial``: the ROS distortion model ``cam`` exports as.

    Raises:
        DockError: thin-prism or tilt coefficients are not zero.
    """
    return _ros_distortion(cam, where)[0]


def _ros_distortion(cam: CameraModel, where: str) -> tuple[str, list[float]]:
    d = _padded(cam)
    if not any(d[5:]):
        return "plumb_bob", d[:5]
    if not any(d[8:]):
        return "rational_polynomial", d[:8]
    raise DockError(
        f"{where}: thin-prism or tilt coefficients (s1..s4, tx, ty) are not zero: ROS "
        "camera_info has no distortion model for them"
    )


def ros_camera_info_yaml(
    cam: CameraModel,
    where: str | None = None,
    R: ArrayLike | None = None,
    P: ArrayLike | None = None,
) -> str:
    """``cam`` as ROS camera_info YAML, laid out as ``camera_calibration`` writes it.

    The distortion model is ``plumb_bob`` (5 coefficients) when k4 and higher are zero, else
    ``rational_polynomial`` (8). A single camera has R = I and P = [K | 0] (the rectified image
    keeps K); one camera of a stereo pair has the pair's R1 / P1 (left) or R2 / P2 (right, whose
    ``P[0, 3] = -fx' * baseline`` is ROS's Tx; :mod:`calibration.stereo_formats`).

    Args:
        cam: the camera.
        where: what to call the camera in errors (default: its name).
        R: (3, 3) rectification matrix (default the identity).
        P: (3, 4) projection matrix (default [K | 0]).

    Raises:
        DockError: thin-prism or tilt coefficients are not zero.
    """
    model, d = _ros_distortion(cam, where or f"camera {cam.name!r}")

    def matrix(key: str, values: np.ndarray) -> list[str]:
        rows, cols = values.shape
        return [f"{key}:", f"  rows: {rows}", f"  cols: {cols}", f"  data: {_flow_list(values)}"]

    lines = [
        f"image_width: {cam.width_px}",
        f"image_height: {cam.height_px}",
        f"camera_name: {_yaml_str(cam.name)}",
        *matrix("camera_matrix", cam.K),
        f"distortion_model: {model}",
        *matrix("distortion_coefficients", np.array([d])),
        *matrix("rectification_matrix", np.eye(3) if R is None else np.reshape(R, (3, 3))),
        *matrix(
            "projection_matrix",
            np.hstack([cam.K, np.zeros((3, 1))]) if P is None else np.reshape(P, (3, 4)),
        ),
    ]
    return "\n".join(lines) + "\n"


def kalibr_camchain_yaml(
    cam: CameraModel,
    T_cam_imu: ArrayLike | None = None,
    rostopic: str = "/cam0/image_raw",
    where: str | None = None,
) -> str:
    """``cam`` as a one-camera Kalibr camchain (``cam0``, pinhole-radtan), keys sorted as
    Kalibr writes them.

    Args:
        cam: the camera; its coefficients after p2 must be zero (radtan has no k3).
        T_cam_imu: optional (4, 4) ``T_camcv_imu`` (IMU frame in the camera frame, m).
        rostopic: the image topic Kalibr's tools read the camera from.
        where: what to call the camera in errors (default: its name).

    Raises:
        DockError: k3 (or a higher coefficient) is not zero, ``T_cam_imu`` is not a rigid
            transform, or ``rostopic`` is not a non-empty single line.
    """
    lines = kalibr_camera_lines(
        "cam0", cam, rostopic, where or f"camera {cam.name!r}", T_cam_imu=T_cam_imu
    )
    return "\n".join(lines) + "\n"


def kalibr_camera_lines(
    key: str,
    cam: CameraModel,
    rostopic: str,
    where: str,
    T_cam_imu: ArrayLike | None = None,
    T_cn_cnm1: ArrayLike | None = None,
    overlaps: tuple[int, ...] = (),
) -> list[str]:
    """One camera of a camchain: ``camN:`` and its keys (sorted as PyYAML writes them).

    Args:
        key: "cam0", "cam1", ...
        cam: the camera; its coefficients after p2 must be zero (radtan has no k3).
        rostopic: the image topic.
        where: what to call the camera in errors.
        T_cam_imu: optional (4, 4) ``T_camcv_imu`` (m).
        T_cn_cnm1: optional (4, 4) previous camera's frame in this one's (m).
        overlaps: ``cam_overlaps``: indices of the cameras that see what this one sees.

    Raises:
        DockError: k3 (or higher) not zero, a transform that is not rigid, a bad topic.
    """
    higher = [f"{n} = {v:g}" for n, v in zip(_HIGHER, _padded(cam)[4:], strict=True) if v]
    if higher:
        raise DockError(
            f"{where}: {', '.join(higher)} not zero: Kalibr's radtan holds k1 k2 p1 p2 only "
            "(calibrate with --distortion-model k1k2p1p2, or export --format ros)"
        )
    if not isinstance(rostopic, str) or not rostopic.strip() or "\n" in rostopic:
        raise DockError(f"rostopic must be a non-empty single line, got {show_value(rostopic)}")
    lines = [f"{key}:"]
    for name, value in (("T_cam_imu", T_cam_imu), ("T_cn_cnm1", T_cn_cnm1)):
        if value is not None:
            try:
                T = check_T(value, name)
            except ValueError as exc:
                raise DockError(str(exc)) from None
            lines += [f"  {name}:", *(f"  - {_flow_list(row)}" for row in T)]
    lines += [
        f"  cam_overlaps: [{', '.join(str(i) for i in overlaps)}]",
        "  camera_model: pinhole",
        f"  distortion_coeffs: {_flow_list(cam.dist[:4])}",
        "  distortion_model: radtan",
        f"  intrinsics: {_flow_list([cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px])}",
        f"  resolution: [{cam.width_px}, {cam.height_px}]",
        f"  rostopic: {_yaml_str(rostopic)}",
    ]
    return lines


def export_camera_file(
    camera_file: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str,
    rostopic: str = "/cam0/image_raw",
) -> tuple[Path, str]:
    """Write a camera file's intrinsics as ROS camera_info YAML or a Kalibr camchain, atomically.

    ``T_body_cam`` is not exported: camera_info has no extrinsics, and Kalibr's ``T_cam_imu``
    is relative to the IMU, not the body frame.

    Args:
        camera_file: the toolkit's camera file (:func:`load_camera`).
        out: the YAML file to write (``.yaml`` or ``.yml``).
        fmt: "ros" or "kalibr".
        rostopic: Kalibr: the image topic.

    Returns:
        (the path written, the distortion model written: plumb_bob, rational_polynomial or
        radtan).

    Raises:
        DockError: one line: a malformed camera file, an unknown format, a suffix other than
            .yaml / .yml, ``out`` being the camera file, or coefficients the format cannot hold.
    """
    camera_file, out = Path(camera_file), Path(out)
    if fmt not in EXPORT_FORMATS:
        raise DockError(f"format must be one of {', '.join(EXPORT_FORMATS)}, got {show_value(fmt)}")
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise DockError(f"--out must end in .yaml or .yml: {out}")
    if out.resolve() in {p.resolve() for p in twin_paths(camera_file)}:
        raise DockError(f"--out {out} would overwrite the camera file {camera_file}")
    cam, _ = load_camera(camera_file)
    where = str(camera_file)
    if fmt == "ros":
        text, model = ros_camera_info_yaml(cam, where), _ros_distortion(cam, where)[0]
    else:
        text, model = kalibr_camchain_yaml(cam, rostopic=rostopic, where=where), "radtan"
    return atomic_write_text(out, text), model
