"""Stereo pairs in other tools' files: a two-camera Kalibr camchain and a ROS camera_info pair,
in and out (the single-camera forms are :mod:`calibration.formats`).

* Kalibr camchain: cam0 is the left camera, cam1 the right one, and cam1's ``T_cn_cnm1`` (cam0
  points into cam1's frame, metres) is ``T_right_left``, written and read as is. Import finds
  the pair of the imported camera by ``T_cn_cnm1`` (:func:`stereo_from_kalibr`); the
  rectification is computed (``stereoRectify``, alpha 0), each camera's ``rostopic`` kept.
* ROS camera_info pair (``camera_calibration``'s stereo output): each file holds its camera's
  raw K and D and the pair's rectification, R1 / P1 in the left file and R2 / P2 in the right
  one, whose ``P[0, 3] = -fx' * baseline`` (ROS's Tx). Import keeps R and P as read and derives
  ``T_right_left`` from them (:meth:`StereoRig.from_rectified`).

Export -> import -> export gives the same bytes in both formats: the numbers are written in
Python's shortest round-trip form and everything an export writes is kept by the import.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from uwdock.calibration.camera import twin_paths
from uwdock.calibration.formats import (
    camera_from_kalibr,
    detect_format,
    read_camera_yaml,
    read_yaml_mapping,
)
from uwdock.calibration.formats_export import (
    EXPORT_FORMATS,
    kalibr_camera_lines,
    ros_camera_info_yaml,
    ros_distortion_model,
)
from uwdock.calibration.stereo_rig import StereoRig, load_stereo, stereo_file_bytes
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, atomic_write_text

__all__ = [
    "DEFAULT_STEREO_TOPICS",
    "export_stereo_file",
    "import_stereo_file",
    "kalibr_stereo_camchain_yaml",
    "ros_stereo_camera_info_yaml",
    "stereo_from_kalibr",
    "stereo_from_ros_pair",
    "stereo_import_bytes",
]


#: Image topics of an exported stereo camchain when the stereo file names none.
DEFAULT_STEREO_TOPICS = ("/cam0/image_raw", "/cam1/image_raw")


def kalibr_stereo_camchain_yaml(
    rig: StereoRig,
    rostopics: tuple[str | None, str | None] = (None, None),
    where: str = "stereo pair",
) -> str:
    """``rig`` as a two-camera Kalibr camchain: cam0 the left camera, cam1 the right one with
    ``T_cn_cnm1 = T_right_left`` (Kalibr's cam1 ``T_cn_cnm1`` maps cam0 points into cam1).

    Args:
        rig: the stereo pair; radtan holds k1 k2 p1 p2 only (k3 and higher must be zero).
        rostopics: (cam0, cam1) image topics; None: the rig's topic, else
            ``DEFAULT_STEREO_TOPICS``.
        where: what to call the pair in errors.

    Raises:
        DockError: a coefficient radtan cannot hold, or a topic that is not one line.
    """
    topics = [
        given or own or default
        for given, own, default in zip(
            rostopics, (rig.left_topic, rig.right_topic), DEFAULT_STEREO_TOPICS, strict=True
        )
    ]
    lines = kalibr_camera_lines("cam0", rig.left, topics[0], f"{where}, left", overlaps=(1,))
    lines += kalibr_camera_lines(
        "cam1", rig.right, topics[1], f"{where}, right", T_cn_cnm1=rig.T_right_left, overlaps=(0,)
    )
    return "\n".join(lines) + "\n"


def ros_stereo_camera_info_yaml(rig: StereoRig, where: str = "stereo pair") -> tuple[str, str]:
    """``rig`` as a ROS camera_info pair (left, right): each camera's raw K and D with the
    rectification R1 / P1 and R2 / P2, as ``camera_calibration``'s stereo calibrator writes
    them (right ``P[0, 3] = -fx' * baseline``)."""
    return (
        ros_camera_info_yaml(rig.left, f"{where}, left", rig.R1, rig.P1),
        ros_camera_info_yaml(rig.right, f"{where}, right", rig.R2, rig.P2),
    )


# ---------------------------------------------------------------------------- stereo import


def stereo_from_kalibr(
    doc: Mapping[str, Any], cam_key: str = "cam0", where: str = "camchain"
) -> tuple[StereoRig, str, str] | None:
    """The stereo pair of a camchain that ``cam_key`` belongs to.

    The pair is (cam N-1, cam N) when ``cam_key`` = cam N has ``T_cn_cnm1``, else (cam N,
    cam N+1) when cam N+1 has one; the earlier camera is the left one and ``T_right_left`` is
    the later camera's ``T_cn_cnm1``, as read. The rectification is computed
    (:meth:`StereoRig.from_cameras`, alpha 0); each camera's ``rostopic`` is kept.

    Returns:
        (rig, left key, right key), or None when neither camera has a ``T_cn_cnm1``.

    Raises:
        DockError: one line when the pair cannot be represented (a partner camera the camera
            model cannot hold, different image sizes, a zero baseline).
    """
    own = camera_from_kalibr(doc, cam_key, where)
    n = int(cam_key[3:])
    if own.T_cn_cnm1 is not None:
        if n == 0:
            raise DockError(f"{where}: cam0 has T_cn_cnm1, but there is no camera before it")
        keys = (f"cam{n - 1}", cam_key)
    elif isinstance(doc.get(f"cam{n + 1}"), Mapping) and doc[f"cam{n + 1}"].get("T_cn_cnm1"):
        keys = (cam_key, f"cam{n + 1}")
    else:
        return None
    hint = f"import with --no-stereo to take {cam_key} alone"
    try:
        left, right = (camera_from_kalibr(doc, k, where) for k in keys)
    except DockError as exc:
        raise DockError(f"{exc} ({keys[0]} and {keys[1]} form a stereo pair: {hint})") from None
    T = right.T_cn_cnm1
    assert T is not None  # the pair was chosen by it
    try:
        rig = StereoRig.from_cameras(
            left.camera,
            right.camera,
            T,
            left_topic=_topic(doc, keys[0]),
            right_topic=_topic(doc, keys[1]),
        )
    except ValueError as exc:
        raise DockError(f"{where}: stereo pair {keys[0]}, {keys[1]}: {exc} ({hint})") from None
    return rig, keys[0], keys[1]


def _topic(doc: Mapping[str, Any], key: str) -> str | None:
    topic = doc[key].get("rostopic")
    return topic if isinstance(topic, str) and topic.strip() and "\n" not in topic else None


def stereo_from_ros_pair(
    left_path: str | os.PathLike[str], right_path: str | os.PathLike[str]
) -> StereoRig:
    """A stereo pair from its two ROS camera_info files (``camera_calibration``'s stereo
    output, or :func:`ros_stereo_camera_info_yaml`'s): K and D of each raw image, and R1, P1,
    R2, P2 as read (``T_right_left`` follows from them, :meth:`StereoRig.from_rectified`).

    Raises:
        DockError: one line: either file is not ROS camera_info, lacks a projection matrix,
            or the two do not form a rectified pair (no baseline in the right P, different
            image sizes, R not a rotation).
    """
    sides = []
    for label, path in (("left", left_path), ("right", right_path)):
        imported = read_camera_yaml(path, "ros")
        if imported.P is None:
            raise DockError(f"{path}: no projection_matrix: the {label} camera of a stereo pair")
        sides.append(imported)
    left, right = sides
    try:
        return StereoRig.from_rectified(left.camera, right.camera, left.R, right.R, left.P, right.P)
    except ValueError as exc:
        raise DockError(f"{left_path} and {right_path} as a stereo pair: {exc}") from None


def _check_not_overwriting(out: Path, sources: list[Path], flag: str = "--out") -> None:
    for src in sources:
        if src.resolve() in {p.resolve() for p in twin_paths(out)}:
            raise DockError(f"{flag} {out} would overwrite {src}")


def import_stereo_file(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str = "auto",
    cam_key: str = "cam0",
    right: str | os.PathLike[str] | None = None,
) -> tuple[StereoRig, str, tuple[Path, Path]] | None:
    """Write the stereo pair another tool's files describe as a stereo file (both twins).

    Args:
        source: a Kalibr camchain, or the left camera's ROS camera_info file.
        out: the stereo file (:func:`calibration.stereo_rig.save_stereo`).
        fmt: as for :func:`read_camera_yaml`.
        cam_key: Kalibr: the camera imported (its stereo partner is found by ``T_cn_cnm1``,
            :func:`stereo_from_kalibr`).
        right: ROS: the right camera's camera_info file (then ``source`` is the left one).

    Returns:
        (the rig, a description such as ``cam0 -> cam1 (T_cn_cnm1)``, (yaml_path, json_path)),
        or None when ``source`` describes no stereo pair (a camchain without ``T_cn_cnm1`` for
        this camera, or ROS camera_info without ``right``).

    Raises:
        DockError: one line: a pair that cannot be represented, ``right`` with a camchain, or
            ``out`` overwriting an input.
    """
    found = stereo_import_bytes(source, out, fmt, cam_key, right)
    if found is None:
        return None
    rig, what, files = found
    atomic_write_files(files)  # the twins as one unit
    yaml_path, json_path = files
    return rig, what, (yaml_path, json_path)


def stereo_import_bytes(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str = "auto",
    cam_key: str = "cam0",
    right: str | os.PathLike[str] | None = None,
) -> tuple[StereoRig, str, dict[Path, bytes]] | None:
    """What :func:`import_stereo_file` writes, not written: for a caller that writes the stereo
    file in one unit with other files (``calibration import``: the stereo file and the camera
    file, :func:`dockcore.io.atomic_write_files`).

    Returns:
        (the rig, its description, ``{yaml_path: bytes, json_path: bytes}``), or None when
        ``source`` describes no stereo pair (as :func:`import_stereo_file`).

    Raises:
        DockError: as :func:`import_stereo_file`.
    """
    source, out = Path(source), Path(out)
    sources = [source] + ([Path(right)] if right is not None else [])
    _check_not_overwriting(out, sources, "--stereo-out")
    doc = read_yaml_mapping(source)
    kind = detect_format(doc, str(source)) if fmt == "auto" else fmt
    if kind == "kalibr":
        if right is not None:
            raise DockError(f"--right is for a ROS camera_info pair; {source} is a Kalibr camchain")
        found = stereo_from_kalibr(doc, cam_key, str(source))
        if found is None:
            return None
        rig, left_key, right_key = found
        what = f"{left_key} -> {right_key} (T_cn_cnm1 of {right_key})"
    else:
        if right is None:
            return None
        rig = stereo_from_ros_pair(source, right)
        what = f"{source.name} -> {Path(right).name} (R and P as read)"
    return rig, what, stereo_file_bytes(out, rig)


# ---------------------------------------------------------------------------- stereo export


def export_stereo_file(
    stereo_file: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str,
    right_out: str | os.PathLike[str] | None = None,
    rostopics: tuple[str | None, str | None] = (None, None),
) -> tuple[list[Path], str]:
    """Write a stereo file as a two-camera Kalibr camchain or a ROS camera_info pair,
    atomically.

    Args:
        stereo_file: the toolkit's stereo file (:func:`calibration.stereo_rig.load_stereo`).
        out: Kalibr: the camchain; ROS: the left camera's camera_info (``.yaml`` / ``.yml``).
        fmt: "ros" or "kalibr".
        right_out: ROS: the right camera's camera_info (required).
        rostopics: Kalibr: (cam0, cam1) image topics; None: the stereo file's, else
            ``DEFAULT_STEREO_TOPICS``.

    Returns:
        (the paths written, the distortion model: plumb_bob, rational_polynomial or radtan).

    Raises:
        DockError: one line: a malformed stereo file, a missing ``right_out``, an output
            overwriting an input, coefficients the format cannot hold.
    """
    stereo_file, out = Path(stereo_file), Path(out)
    if fmt not in EXPORT_FORMATS:
        raise DockError(f"format must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    outs = [out] + ([Path(right_out)] if right_out is not None else [])
    for path in outs:
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise DockError(f"output must end in .yaml or .yml: {path}")
        _check_not_overwriting(path, [stereo_file])
    rig = load_stereo(stereo_file)
    where = str(stereo_file)
    if fmt == "kalibr":
        if right_out is not None:
            raise DockError("--right-out is for --format ros (a camchain holds both cameras)")
        text = kalibr_stereo_camchain_yaml(rig, rostopics, where)
        return [atomic_write_text(out, text)], "radtan"
    if right_out is None:
        raise DockError(
            f"{stereo_file} is a stereo pair: ROS camera_info takes one file per camera: "
            "give --right-out for the right camera"
        )
    if out.resolve() == Path(right_out).resolve():
        raise DockError(f"--out and --right-out are the same file: {out}")
    left_text, right_text = ros_stereo_camera_info_yaml(rig, where)
    models = {ros_distortion_model(c, where) for c in (rig.left, rig.right)}
    # the pair as one unit: both new, or both as they were
    paths = atomic_write_files(
        {out: left_text.encode("utf-8"), Path(right_out): right_text.encode("utf-8")}
    )
    return paths, "/".join(sorted(models))
