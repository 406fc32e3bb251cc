"""Camera files of other tools in and out: ROS ``camera_info`` YAML and Kalibr camchain YAML.

All three sources use OpenCV's pixel convention (integer coordinates at pixel centres) and the
``cam_cv`` frame, so their numbers carry over to :class:`CameraModel` unchanged.

* ROS ``camera_info`` YAML, as ``camera_calibration`` (``ost.yaml``) and
  ``camera_calibration_parsers`` write it in ROS 1 and ROS 2: ``image_width``,
  ``image_height``, ``camera_name``, ``camera_matrix``, ``distortion_model``,
  ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix`` (matrices as
  ``{rows, cols, data}``). Distortion models ``plumb_bob`` (k1 k2 p1 p2 k3) and
  ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6); ``equidistant`` (fisheye) has no
  equivalent in :class:`CameraModel` and is refused. A single camera exports with R = I and
  P = [K | 0]; import keeps the R and P it read (``ImportedCamera.R`` / ``P``), so that a
  stereo pair's two files make a stereo file (:mod:`calibration.stereo_formats`).
* A ``sensor_msgs/CameraInfo`` message (``height``, ``width``, ``k``, ``d``,
  ``distortion_model``, ``r``, ``p``; ROS 1 spells ``K``, ``D``, ``R``, ``P``): an object with
  those attributes, a mapping (``dockcore.bags``), or ``rostopic echo`` output saved as YAML.
* Kalibr camchain YAML: ``camN: {camera_model: pinhole, intrinsics: [fu, fv, pu, pv],
  distortion_model: radtan | none, distortion_coeffs: [k1, k2, p1, p2], resolution: [w, h],
  T_cam_imu (optional), rostopic}``. ``T_cam_imu`` (``T_camcv_imu``: the IMU frame expressed in
  the camera frame) is returned as read, never turned into ``T_body_cam``: where the IMU sits in
  the body frame is the caller's to state. ``T_cn_cnm1`` (a stereo link to the previous
  camera) is returned too (``ImportedCamera.T_cn_cnm1``); ``calibration import`` writes the
  pair it links as a stereo file, or refuses in one line when the pair cannot be represented
  (:mod:`calibration.stereo_formats`). Radtan has no k3, so a model with k3 (or higher)
  non-zero is refused on export.

MATLAB's ``cameraParameters`` is not handled: it has no text file (a ``.mat`` class object that
scipy cannot read), and its 1-based pixels and transposed K would be guesses about how it was
saved.

The YAML is read with ``ruamel.yaml``'s safe loader (OpenCV's FileStorage, which reads the
toolkit's own camera files, refuses the block lists PyYAML (Kalibr) writes); anything it cannot
parse is a one-line :class:`DockError` naming the file and line. Written numbers are Python's
shortest round-trip form, with a ``.`` in every float so that YAML 1.1 readers (PyYAML) read
them as floats.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from ruamel.yaml import YAML
from ruamel.yaml.error import MarkedYAMLError, YAMLError
from ruamel.yaml.events import AliasEvent

from uwdock.calibration.camera import (
    MAX_IMAGE_PX,
    CameraModel,
    camera_file_bytes,
    check_camera,
    load_camera,
    twin_paths,
)
from uwdock.calibration.frames import check_T
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, read_text

__all__ = [
    "IMPORT_FORMATS",
    "MAX_FILE_BYTES",
    "ImportedCamera",
    "camera_from_camera_info_msg",
    "camera_from_kalibr",
    "camera_from_ros",
    "camera_import_bytes",
    "detect_format",
    "import_camera_file",
    "read_camera_yaml",
    "read_yaml_mapping",
    "show_value",
]

#: ``--format`` of ``calibration import``: ``ros`` covers ost.yaml and a saved CameraInfo.
IMPORT_FORMATS = ("auto", "ros", "kalibr")
#: Largest file read (bytes): camera files are a few kB.
MAX_FILE_BYTES = 1 << 20
#: Deepest nesting of YAML collections read (a camera file needs 3).
_MAX_DEPTH = 32
_CAM_KEY = re.compile(r"cam[0-9]+")
#: Names of the OpenCV distortion coefficients after p2, for messages.


@dataclass(frozen=True, eq=False)
class ImportedCamera:
    """A camera read from another tool's file.

    Attributes:
        camera: the intrinsics.
        source_format: "ros" (camera_info YAML), "camera_info" (a CameraInfo message) or
            "kalibr".
        T_cam_imu: Kalibr only: (4, 4) float64 ``T_camcv_imu`` (maps IMU points to camera
            points, metres) when the camchain has one, else None. Not a ``T_body_cam``.
        notes: what was read but not carried over, one line each.
        R: ROS only: (3, 3) float64 rectification matrix as read (the identity for a single
            camera; a stereo pair's R1 or R2), else None.
        P: ROS only: (3, 4) float64 projection matrix as read, or None when the file has none
            (or only a placeholder).
        T_cn_cnm1: Kalibr only: (4, 4) float64 ``T_cn_cnm1`` of this camera (the previous
            camera of the chain in this camera's frame, m) when the camchain has one, else None.
    """

    camera: CameraModel
    source_format: str
    T_cam_imu: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    R: np.ndarray | None = None
    P: np.ndarray | None = None
    T_cn_cnm1: np.ndarray | None = None


# ---------------------------------------------------------------------------- YAML


def show_value(value: Any) -> str:
    text = " ".join(repr(value).split())  # one line, even for an array
    return text if len(text) <= 60 else text[:57] + "..."


def _kind(value: Any) -> str:
    return "nothing" if value is None else show_value(value)


def _plain_data(value: Any) -> Any:
    """ruamel's safe-loaded containers as plain dicts and lists (keys as strings)."""
    if isinstance(value, Mapping):
        return {str(k): _plain_data(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain_data(v) for v in value]
    return value


def _refuse_anchors(text: str, where: str) -> None:
    """Refuse YAML anchors and aliases (``&a`` / ``*a``) before anything is built from ``text``.

    A camera file has no use for them, and they are how a small file becomes a huge or endless
    structure: ``a: &a [*a]`` refers to itself, and nine levels of nine aliases each ("billion
    laughs") expand a 1 kB file to 10^9 values. The check walks the parser's event stream, which
    is linear in the text and expands nothing; a file the parser refuses is left to the loader
    (which reports the line).

    Raises:
        DockError: one line naming the file, the line and the anchor.
    """
    try:
        for event in YAML(typ="safe", pure=True).parse(text):
            anchor = getattr(event, "anchor", None)
            if anchor is None:
                continue
            sign = "*" if isinstance(event, AliasEvent) else "&"
            mark = event.start_mark
            line = f"line {mark.line + 1}: " if mark is not None else ""
            raise DockError(
                f"{where}: {line}YAML anchors and aliases ({sign}{anchor}) are not accepted in a "
                "camera file (they can expand without bound): write the values out"
            )
    except (YAMLError, RecursionError, ValueError):
        return


def read_yaml_mapping(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The top-level mapping of a YAML camera file of another tool (``ruamel.yaml``, safe
    loader: plain data only, no tags or objects).

    Raises:
        DockError: one line naming the file (and the line where the YAML parser stopped) when
            it is missing, a special file (FIFO, device), larger than ``MAX_FILE_BYTES``, not
            UTF-8, an OpenCV FileStorage file, not YAML, uses anchors or aliases (refused
            before anything is expanded), holds several documents, or is not a mapping at the
            top level.
    """
    path = Path(path)
    with contextlib.suppress(OSError):
        if path.is_file() and path.stat().st_size > MAX_FILE_BYTES:
            raise DockError(f"{path}: larger than {MAX_FILE_BYTES} bytes: not a camera file")
    text = read_text(path, "camera file")
    where = str(path)
    if re.match(r"\s*%YAML:", text) or "!!opencv-matrix" in text:
        raise DockError(
            f"{where}: an OpenCV FileStorage file (the toolkit's own camera format): "
            "use it as the camera file directly"
        )
    _refuse_anchors(text, where)
    try:
        docs = list(YAML(typ="safe", pure=True).load_all(text))
    except MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f"line {mark.line + 1}: " if mark is not None else ""
        problem = " ".join(str(exc.problem or exc.context or "not YAML").split())
        raise DockError(f"{where}: {line}{problem}") from None
    except (YAMLError, RecursionError, ValueError) as exc:
        raise DockError(f"{where}: not YAML ({' '.join(str(exc).split())[:120]})") from None
    docs = [d for d in docs if d is not None]  # an empty document (a trailing '---' of echo)
    if not docs:
        raise DockError(f"{where}: the file holds no YAML content")
    if len(docs) > 1:
        raise DockError(f"{where}: {len(docs)} YAML documents (a camera file holds one)")
    doc = docs[0]
    if not isinstance(doc, Mapping):
        raise DockError(f"{where}: the top level must be a mapping, got {_kind(doc)}")
    return _plain_data(doc)


# ---------------------------------------------------------------------------- values


def _get(m: Mapping[str, Any], key: str, where: str, parent: str = "") -> Any:
    if key not in m:
        raise DockError(f"{where}: missing key '{parent}{key}'")
    return m[key]


def _mapping(value: Any, where: str, key: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise DockError(f"{where}: key '{key}' must be a mapping, got {_kind(value)}")
    return value


def _numbers(value: Any, where: str, key: str, counts: tuple[int, ...] | None = None) -> np.ndarray:
    """(N,) float64 of a flat list of numbers (or an array), finite, N in ``counts``."""
    items = value.ravel().tolist() if isinstance(value, np.ndarray) else value
    if not isinstance(items, (list, tuple)):
        raise DockError(f"{where}: key '{key}' must be a list of numbers, got {_kind(value)}")
    for v in items:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)):
            raise DockError(f"{where}: key '{key}' must hold numbers only, got {_kind(v)}")
    try:
        arr = np.array(items, dtype=np.float64).reshape(-1)
    except OverflowError:
        raise DockError(f"{where}: key '{key}' holds a number too large for a float") from None
    if not np.all(np.isfinite(arr)):
        raise DockError(f"{where}: key '{key}' holds a non-finite value (nan or inf)")
    if counts is not None and arr.size not in counts:
        want = " or ".join(str(n) for n in counts)
        raise DockError(f"{where}: key '{key}' must hold {want} numbers, got {arr.size}")
    return arr


def _integer(value: Any, where: str, key: str, lo: int, hi: int) -> int:
    ok = isinstance(value, (int, float, np.number)) and not isinstance(value, (bool, np.bool_))
    if not (ok and lo <= value <= hi and float(value).is_integer()):  # nan fails lo <= value
        raise DockError(
            f"{where}: key '{key}' must be an integer in [{lo}, {hi}], got {_kind(value)}"
        )
    return int(value)


def _size_px(value: Any, where: str, key: str) -> int:
    return _integer(value, where, key, 1, MAX_IMAGE_PX)


def _string(value: Any, where: str, key: str) -> str:
    if not isinstance(value, str):
        raise DockError(f"{where}: key '{key}' must be a string, got {_kind(value)}")
    return value


def _model(where: str, **fields: Any) -> CameraModel:
    try:
        cam = CameraModel(**fields)
        check_camera(cam)
        return cam
    except ValueError as exc:
        raise DockError(f"{where}: {exc}") from None


def _from_K(
    K: np.ndarray, dist: tuple[float, ...], size: tuple[int, int], name: str, where: str, key: str
) -> CameraModel:
    """A camera from a (3, 3) K, refusing skew and K that is not [[fx,0,cx],[0,fy,cy],[0,0,1]]."""
    if not K.any():
        raise DockError(f"{where}: key '{key}' is all zeros: the camera is not calibrated")
    if K[0, 1] != 0.0:
        raise DockError(f"{where}: key '{key}' has skew {K[0, 1]:g}; the camera model has none")
    if K[1, 0] != 0.0 or not np.array_equal(K[2], (0.0, 0.0, 1.0)):
        raise DockError(f"{where}: key '{key}' must be [fx, 0, cx, 0, fy, cy, 0, 0, 1]")
    for label, f_px in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if f_px <= 0.0:
            raise DockError(f"{where}: key '{key}': {label} must be > 0 px, got {f_px:g}")
    return _model(
        where,
        width_px=size[0],
        height_px=size[1],
        fx_px=float(K[0, 0]),
        fy_px=float(K[1, 1]),
        cx_px=float(K[0, 2]),
        cy_px=float(K[1, 2]),
        dist=dist,
        name=name or "camera",
    )


def _dist_from_ros(model: Any, d: np.ndarray, where: str, key: str) -> tuple[float, ...]:
    """OpenCV coefficients of a ROS distortion model and its D."""
    model = _string(model, where, key)
    if model in ("equidistant", "fisheye"):
        raise DockError(
            f"{where}: distortion model '{model}' (fisheye) cannot be held by the toolkit's "
            "camera model (pinhole with OpenCV radial-tangential distortion)"
        )
    counts = {"plumb_bob": (0, 4, 5), "rational_polynomial": (8, 12, 14), "": (0,)}
    if model not in counts:
        raise DockError(
            f"{where}: unknown distortion model {show_value(model)} "
            "(expected plumb_bob or rational_polynomial)"
        )
    if d.size not in counts[model]:
        want = " or ".join(str(n) for n in counts[model])
        raise DockError(
            f"{where}: distortion model '{model}' takes {want} coefficients, got {d.size}"
        )
    return tuple(d.tolist()) if d.size else (0.0,) * 5


def _rectification_note(R: np.ndarray) -> tuple[str, ...]:
    if R.size == 9 and R.any() and not np.array_equal(R.reshape(3, 3), np.eye(3)):
        return (
            "the rectification matrix is not the identity (one camera of a stereo pair): "
            "K and D of the raw image were imported, R and P were not",
        )
    return ()


# ---------------------------------------------------------------------------- import


def camera_from_ros(doc: Mapping[str, Any], where: str = "camera_info") -> ImportedCamera:
    """A camera from a ROS ``camera_info`` YAML mapping (``camera_calibration``'s ost.yaml).

    Args:
        doc: the file's top-level mapping (:func:`read_yaml_mapping`).
        where: the file, for messages.

    Returns:
        The camera (``source_format`` "ros"); K and D describe the raw image, as in ROS.

    Raises:
        DockError: one line naming ``where`` and the key at fault.
    """

    def matrix(key: str, shape: tuple[int, int] | None) -> np.ndarray:
        m = _mapping(_get(doc, key, where), where, key)
        rows = _integer(_get(m, "rows", where, f"{key}."), where, f"{key}.rows", 0, 1000)
        cols = _integer(_get(m, "cols", where, f"{key}."), where, f"{key}.cols", 0, 1000)
        data = _numbers(_get(m, "data", where, f"{key}."), where, f"{key}.data")
        if data.size != rows * cols:
            raise DockError(
                f"{where}: key '{key}': rows x cols is {rows} x {cols} but data holds "
                f"{data.size} numbers"
            )
        if shape is not None and (rows, cols) != shape:
            raise DockError(
                f"{where}: key '{key}' must be {shape[0]} x {shape[1]}, got {rows} x {cols}"
            )
        if shape is None and min(rows, cols) > 1:
            raise DockError(f"{where}: key '{key}' must be one row, got {rows} x {cols}")
        return data

    size = (
        _size_px(_get(doc, "image_width", where), where, "image_width"),
        _size_px(_get(doc, "image_height", where), where, "image_height"),
    )
    K = matrix("camera_matrix", (3, 3)).reshape(3, 3)
    d = matrix("distortion_coefficients", None)
    dist = _dist_from_ros(_get(doc, "distortion_model", where), d, where, "distortion_model")
    R = matrix("rectification_matrix", (3, 3)) if "rectification_matrix" in doc else np.eye(3)
    P = matrix("projection_matrix", (3, 4)) if "projection_matrix" in doc else None
    name = doc.get("camera_name") or "camera"
    name = _string(name, where, "camera_name") if not isinstance(name, (int, float)) else str(name)
    cam = _from_K(K, dist, size, name, where, "camera_matrix")
    return ImportedCamera(
        cam,
        "ros",
        notes=_rectification_note(R),
        R=R.reshape(3, 3),
        P=None if P is None else P.reshape(3, 4),
    )


def _field(msg: Any, names: tuple[str, ...], where: str, required: bool = True) -> Any:
    for n in names:
        if isinstance(msg, Mapping):
            if n in msg:
                return msg[n]
        elif hasattr(msg, n):
            return getattr(msg, n)
    if required:
        raise DockError(f"{where}: missing field '{names[0]}'")
    return None


def _from_msg(msg_like: Any, where: str) -> ImportedCamera:
    size = (
        _size_px(_field(msg_like, ("width",), where), where, "width"),
        _size_px(_field(msg_like, ("height",), where), where, "height"),
    )
    K = _numbers(_field(msg_like, ("k", "K"), where), where, "k", (9,)).reshape(3, 3)
    d = _numbers(_field(msg_like, ("d", "D"), where), where, "d")
    dist = _dist_from_ros(
        _field(msg_like, ("distortion_model",), where), d, where, "distortion_model"
    )
    R = _field(msg_like, ("r", "R"), where, required=False)
    R = np.eye(3) if R is None else _numbers(R, where, "r", (0, 9))
    P = _field(msg_like, ("p", "P"), where, required=False)
    if P is not None:
        P = _numbers(P, where, "p", (0, 12))
    header = _field(msg_like, ("header",), where, required=False)
    frame_id = None if header is None else _field(header, ("frame_id",), where, required=False)
    name = frame_id.lstrip("/") if isinstance(frame_id, str) and frame_id.strip("/ ") else "camera"
    cam = _from_K(K, dist, size, name, where, "k")
    return ImportedCamera(
        cam,
        "camera_info",
        notes=_rectification_note(R),
        R=R.reshape(3, 3) if R.size == 9 else np.eye(3),
        P=P.reshape(3, 4) if P is not None and P.size == 12 else None,
    )


def camera_from_camera_info_msg(msg_like: Any, where: str = "camera_info message") -> CameraModel:
    """A camera from a ``sensor_msgs/CameraInfo`` message (ROS 1 or ROS 2).

    Args:
        msg_like: an object with attributes, or a mapping, having ``height``, ``width`` (px),
            ``k`` (9 numbers, row-major K, px), ``d`` and ``distortion_model``; ``r`` and ``p``
            are checked when present. ROS 1's ``K`` / ``D`` / ``R`` / ``P`` are accepted too.
            The name is ``header.frame_id`` when there is one, else "camera".
        where: what to call the message in errors (a bag and topic, say).

    Returns:
        The camera model of the raw image.

    Raises:
        DockError: one line naming ``where`` and the field at fault (a missing field, a wrong
            count, a non-finite value, K of an uncalibrated camera, a fisheye model ...).
    """
    return _from_msg(msg_like, where).camera


def camera_from_kalibr(
    doc: Mapping[str, Any], cam_key: str = "cam0", where: str = "camchain"
) -> ImportedCamera:
    """A camera of a Kalibr camchain mapping.

    Args:
        doc: the file's top-level mapping (:func:`read_yaml_mapping`).
        cam_key: which camera: "cam0", "cam1", ...
        where: the file, for messages.

    Returns:
        The camera (named ``cam_key``, ``source_format`` "kalibr") with ``T_cam_imu`` when the
        camchain has one.

    Raises:
        DockError: one line naming ``where`` and the key at fault; also for a camera model other
            than pinhole and a distortion model other than radtan or none.
    """
    if not isinstance(cam_key, str) or not _CAM_KEY.fullmatch(cam_key):
        raise DockError(f"camera key must be cam0, cam1, ..., got {show_value(cam_key)}")
    cams = sorted((k for k in doc if _CAM_KEY.fullmatch(str(k))), key=lambda k: int(k[3:]))
    if cam_key not in doc:
        raise DockError(
            f"{where}: no '{cam_key}' (cameras in the file: {', '.join(cams) or 'none'})"
        )
    c = _mapping(doc[cam_key], where, cam_key)
    k = f"{cam_key}."
    model = _string(_get(c, "camera_model", where, k), where, f"{k}camera_model")
    if model != "pinhole":
        raise DockError(
            f"{where}: camera model {show_value(model)} of '{cam_key}' cannot be held by the "
            "toolkit's camera model (pinhole only)"
        )
    dmodel = _string(_get(c, "distortion_model", where, k), where, f"{k}distortion_model")
    coeffs = _numbers(_get(c, "distortion_coeffs", where, k), where, f"{k}distortion_coeffs")
    if dmodel in ("equidistant", "equi", "fov"):
        raise DockError(
            f"{where}: distortion model '{dmodel}' of '{cam_key}' cannot be held by the "
            "toolkit's camera model (pinhole with OpenCV radial-tangential distortion)"
        )
    if dmodel not in ("radtan", "none"):
        raise DockError(f"{where}: unknown distortion model {show_value(dmodel)} (expected radtan)")
    want = 4 if dmodel == "radtan" else 0
    if coeffs.size != want:
        raise DockError(
            f"{where}: key '{k}distortion_coeffs' of '{dmodel}' must hold {want} numbers, "
            f"got {coeffs.size}"
        )
    fu, fv, pu, pv = _numbers(_get(c, "intrinsics", where, k), where, f"{k}intrinsics", (4,))
    res = _get(c, "resolution", where, k)
    if not isinstance(res, (list, tuple)) or len(res) != 2:
        raise DockError(f"{where}: key '{k}resolution' must be [width, height], got {_kind(res)}")
    size = (_size_px(res[0], where, f"{k}resolution"), _size_px(res[1], where, f"{k}resolution"))
    K = np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])
    dist = tuple(coeffs.tolist()) if want else (0.0,) * 4
    cam = _from_K(K, dist, size, cam_key, where, f"{k}intrinsics")
    T = _kalibr_T(c, "T_cam_imu", where, k)
    T_chain = _kalibr_T(c, "T_cn_cnm1", where, k)
    notes = (f"the camchain holds {', '.join(cams)}; imported {cam_key}",) if len(cams) > 1 else ()
    return ImportedCamera(cam, "kalibr", T_cam_imu=T, notes=notes, T_cn_cnm1=T_chain)


def _kalibr_T(c: Mapping[str, Any], key: str, where: str, k: str) -> np.ndarray | None:
    """The (4, 4) transform ``key`` of a camchain camera, checked, or None when absent."""
    if c.get(key) is None:
        return None
    rows = c[key]
    if not isinstance(rows, (list, tuple)) or len(rows) != 4:
        raise DockError(f"{where}: key '{k}{key}' must be 4 rows of 4 numbers")
    T = np.stack([_numbers(r, where, f"{k}{key}", (4,)) for r in rows])
    try:
        return check_T(T, f"key '{k}{key}'")
    except ValueError as exc:
        raise DockError(f"{where}: {exc}") from None


def detect_format(doc: Mapping[str, Any], where: str = "camera file") -> str:
    """ "ros", "camera_info" or "kalibr", from the keys of a file's top-level mapping.

    Raises:
        DockError: the keys fit none of them.
    """
    if "camera_matrix" in doc:
        return "ros"
    if "width" in doc and "height" in doc and ("k" in doc or "K" in doc):
        return "camera_info"
    if any(_CAM_KEY.fullmatch(str(k)) and isinstance(v, Mapping) for k, v in doc.items()):
        return "kalibr"
    raise DockError(
        f"{where}: not a ROS camera_info file (camera_matrix ...), a CameraInfo message "
        "(width, height, k, d ...) or a Kalibr camchain (cam0: ...)"
    )


def read_camera_yaml(
    path: str | os.PathLike[str], fmt: str = "auto", cam_key: str = "cam0"
) -> ImportedCamera:
    """Read a ROS camera_info YAML, a saved CameraInfo message or a Kalibr camchain.

    Args:
        path: the YAML file.
        fmt: "auto" (told apart by the keys), "ros" (camera_info YAML or a CameraInfo message)
            or "kalibr".
        cam_key: Kalibr: which camera ("cam0", "cam1", ...).

    Returns:
        The imported camera.

    Raises:
        DockError: one line naming the file and the problem.
    """
    if fmt not in IMPORT_FORMATS:
        raise DockError(f"format must be one of {', '.join(IMPORT_FORMATS)}, got {show_value(fmt)}")
    doc = read_yaml_mapping(path)
    where = str(path)
    try:
        kind = detect_format(doc, where)
    except DockError:
        if fmt == "auto":
            raise
        kind = fmt  # read as told: the missing keys will be named
    if fmt != "auto" and (kind == "kalibr") != (fmt == "kalibr"):
        seen = "a Kalibr camchain" if kind == "kalibr" else "ROS camera_info"
        raise DockError(f"{where}: --format {fmt}, but the keys are those of {seen}")
    if kind == "kalibr":
        return camera_from_kalibr(doc, cam_key, where)
    if kind == "camera_info":
        return _from_msg(doc, where)
    return camera_from_ros(doc, where)


def import_camera_file(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str = "auto",
    cam_key: str = "cam0",
    keep_extrinsics: bool = True,
) -> tuple[ImportedCamera, tuple[Path, Path], bool]:
    """Convert another tool's camera file into the toolkit's camera file (both twins).

    Args:
        source: ROS camera_info YAML, a saved CameraInfo message or a Kalibr camchain.
        out: camera file to write (``.yaml`` / ``.yml`` / ``.json``; :func:`save_camera`).
        fmt: as for :func:`read_camera_yaml`.
        cam_key: Kalibr: which camera.
        keep_extrinsics: when ``out`` already holds a readable camera file with
            ``T_body_cam``, carry it over (new intrinsics do not move the camera).

    Returns:
        (the imported camera, (yaml_path, json_path) written, whether ``T_body_cam`` was
        carried over). Kalibr's ``T_cam_imu`` is returned, never written.

    Raises:
        DockError: one line: the source is malformed, or ``out`` would overwrite it.
    """
    imported, files, kept = camera_import_bytes(source, out, fmt, cam_key, keep_extrinsics)
    atomic_write_files(files)  # the twins as one unit
    yaml_path, json_path = files
    return imported, (yaml_path, json_path), kept


def camera_import_bytes(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str = "auto",
    cam_key: str = "cam0",
    keep_extrinsics: bool = True,
) -> tuple[ImportedCamera, dict[Path, bytes], bool]:
    """What :func:`import_camera_file` writes, not written: for a caller that writes the camera
    file in one unit with other files (``calibration import`` of a stereo pair: the camera and
    the stereo file, :func:`dockcore.io.atomic_write_files`).

    Returns:
        (the imported camera, ``{yaml_path: bytes, json_path: bytes}``, whether ``T_body_cam``
        is carried over from the existing ``out``).

    Raises:
        DockError: one line: the source is malformed, or ``out`` would overwrite it.
    """
    source, out = Path(source), Path(out)
    if source.resolve() in {p.resolve() for p in twin_paths(out)}:
        raise DockError(f"--out {out} would overwrite the file being imported, {source}")
    imported = read_camera_yaml(source, fmt, cam_key)
    T = None
    if keep_extrinsics and out.is_file():
        with contextlib.suppress(DockError):
            T = load_camera(out)[1]
    return imported, camera_file_bytes(out, imported.camera, T), T is not None
