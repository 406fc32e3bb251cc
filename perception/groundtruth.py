"""Ground truth for ``perception eval``: the labelled dataset folder, or a per-frame pose CSV.

(a) Labelled dataset folder, format ``uwdock.dataset`` version 1 (written by ``datasets synth``
with :func:`write_dataset_json` and :func:`write_labels`; read by :func:`load_dataset`)::

    DATASET/dataset.json     {"format": "uwdock.dataset", "version": 1, "frames": N,
                              "camera": "camera.yaml", "marker_set": "markerset.toml",
                              "images": "images", "config": {...}}
                             (paths relative to DATASET; optional "labels", default
                             "labels.jsonl"; "config" is the resolved generator config)
    DATASET/camera.yaml      + camera.json twin (calibration.camera.save_camera)
    DATASET/markerset.toml   (markers.markerset.save_marker_set)
    DATASET/images/000000.png ...
    DATASET/labels.jsonl     one JSON object per line, one line per frame:

    frame           int >= 0, unique: the frame index (its image's position in sorted order).
    image           str: the frame's image, relative to DATASET ("images/000000.png").
    T_cam_ds        4x4 list: the docking-station frame in the OpenCV camera frame (cam_cv: x
                    right, y down, z forward), metres.
    T_world_body    4x4 list or null: the vehicle body (FRD) in the world (NED), metres.
    range_m         float: distance from the camera's optical centre to the DS origin,
                    ``|t|`` with ``t = T_cam_ds[:3, 3]`` (m).
    view_angle_deg  float in [0, 180]: angle between the camera's optical axis (+z of cam_cv)
                    and the ray from the optical centre to the DS origin,
                    ``atan2(hypot(t_x, t_y), t_z)``: 0 when the DS origin is at the principal
                    point, 90 at the image plane's horizon, more when it is behind the camera.
    water           {"preset": str, ...parameters} or null (clear water / unknown).
    markers         list of {"id": int, "corners_px": [[u, v] x 4] (TL, TR, BR, BL; OpenCV
                    pixels, lens distortion applied), "in_image": bool (all four corners in
                    front of the camera and inside the image), "visible": bool (in_image and
                    not occluded)}; may be empty.

    ``range_m`` and ``view_angle_deg`` are derived from ``T_cam_ds``: readers recompute them when
    they are missing.

(b) Pose CSV, e.g. from motion capture (read by :func:`load_pose_csv`)::

    frame,x_m,y_m,z_m,qw,qx,qy,qz[,any other columns, e.g. timestamp_s]
    0,0.12,-0.05,2.31,0.0,0.7071,0.7071,0.0

    One row per frame: ``T_cam_ds`` as the DS origin in the camera frame (m) and its
    orientation as a unit (w, x, y, z) quaternion. A quaternion whose norm differs from 1 by
    more than ``QUAT_NORM_TOL`` is an error (normalising it would hide a wrong or swapped
    column: a 3 deg error became 17 deg); one within it is normalised. ``frame`` is the video
    frame index, or the position of the image in the sorted folder. UTF-8 (a byte-order mark
    is accepted).

:func:`load_ground_truth` reads either (a folder, ``labels.jsonl`` or ``.csv``) into
``{frame index: FrameTruth}``; every problem is a one-line :class:`DockError` naming the file
and the line. :func:`load_checked_dataset` (what ``perception eval`` and the readers of
``datasets.loaders`` open) also checks a dataset's labels against it
(:func:`check_dataset_labels`: image paths inside the folder and regular files, poses in range).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import R_from_quat_wxyz, pos_quat_from_T, transform_points
from uwdock.dockcore.bags import Bag, nearest_in_time
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_json, read_text, special_file_kind
from uwdock.markers.view import markers_in_view

__all__ = [
    "CSV_COLUMNS",
    "DATASET_FORMAT",
    "DATASET_VERSION",
    "MAX_LABEL_TRANSLATION_M",
    "QUAT_NORM_TOL",
    "FrameTruth",
    "LabelledDataset",
    "MarkerTruth",
    "check_dataset_labels",
    "frame_truth_to_json",
    "is_dataset",
    "label_frame",
    "load_checked_dataset",
    "load_dataset",
    "load_ground_truth",
    "load_labels",
    "load_pose_csv",
    "range_m",
    "view_angle_deg",
    "write_dataset_json",
    "write_labels",
    "write_pose_csv",
]

DATASET_FORMAT = "uwdock.dataset"
DATASET_VERSION = 1
#: Required columns of the pose CSV, in this order of meaning (extra columns are ignored).
CSV_COLUMNS: tuple[str, ...] = ("frame", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz")

#: Largest accepted | |q| - 1 | of a pose CSV quaternion. A unit quaternion written with d
#: decimals per component is off by at most 2 * 0.5e-d (the rounding errors of 4 components,
#: norm <= 2 * half a unit): 1e-3 accepts every CSV written with 3 or more decimals (4-6 are
#: usual: <= 1e-4) and refuses a quaternion that is not one (a mistyped or swapped component).
QUAT_NORM_TOL = 1e-3


# --------------------------------------------------------------------------- records


def range_m(T_cam_ds: ArrayLike) -> float:
    """Distance from the camera's optical centre to the DS origin (m)."""
    return float(np.linalg.norm(np.asarray(T_cam_ds, np.float64)[:3, 3]))


def view_angle_deg(T_cam_ds: ArrayLike) -> float:
    """Angle between the optical axis and the ray to the DS origin (deg, in [0, 180])."""
    t = np.asarray(T_cam_ds, np.float64)[:3, 3]
    return float(math.degrees(math.atan2(math.hypot(t[0], t[1]), t[2])))


@dataclass(frozen=True)
class MarkerTruth:
    """One marker's ground truth in one frame.

    Attributes:
        marker_id: dictionary ID.
        corners_px: (4, 2) float64 pixel corners TL, TR, BR, BL (OpenCV pixels).
        in_image: all corners in front of the camera and inside the image.
        visible: in the image and not occluded.
    """

    marker_id: int
    corners_px: np.ndarray
    in_image: bool
    visible: bool


@dataclass(frozen=True)
class FrameTruth:
    """Ground truth of one frame.

    Attributes:
        frame: frame index.
        T_cam_ds: (4, 4) DS frame in the OpenCV camera frame (m).
        image: image path relative to the dataset folder, or None (CSV ground truth).
        T_world_body: (4, 4) vehicle body (FRD) in the world (NED), or None.
        range_m: camera to DS origin distance (m), see :func:`range_m`.
        view_angle_deg: off-axis angle of the DS origin (deg), see :func:`view_angle_deg`.
        water: water preset and parameters, or None.
        markers: per-marker truth (empty for CSV ground truth).
    """

    frame: int
    T_cam_ds: np.ndarray
    image: str | None = None
    T_world_body: np.ndarray | None = None
    range_m: float = float("nan")
    view_angle_deg: float = float("nan")
    water: dict[str, Any] | None = None
    markers: tuple[MarkerTruth, ...] = field(default_factory=tuple)

    @property
    def visible_ids(self) -> frozenset[int]:
        """IDs of the markers labelled visible."""
        return frozenset(m.marker_id for m in self.markers if m.visible)


def label_frame(
    frame: int,
    T_cam_ds: ArrayLike,
    camera: CameraModel,
    corners_ds: Mapping[int, ArrayLike],
    image: str | None = None,
    T_world_body: ArrayLike | None = None,
    water: Mapping[str, Any] | None = None,
    occluded_ids: Collection[int] = (),
) -> FrameTruth:
    """Ground truth of a frame from its pose: project the board markers through ``camera``.

    Args:
        frame: frame index.
        T_cam_ds: (4, 4) DS frame in the OpenCV camera frame (m).
        camera: intrinsics (with distortion) of the image.
        corners_ds: ID -> (4, 3) corners TL, TR, BR, BL in the DS frame (m), e.g.
            ``MarkerSet.corners_ds()``.
        image: image path relative to the dataset folder.
        T_world_body: optional (4, 4) vehicle pose.
        water: optional water preset and parameters.
        occluded_ids: markers hidden by something (e.g. found by the renderer's segmentation):
            labelled ``visible = False`` even when inside the image.

    Returns:
        A :class:`FrameTruth` with ``range_m``, ``view_angle_deg`` and one
        :class:`MarkerTruth` per board marker (corners are nan behind the camera).
    """
    T = np.asarray(T_cam_ds, np.float64)
    markers = []
    ids = sorted(corners_ds)
    in_view = (
        markers_in_view(  # all markers in one call
            camera, T, np.stack([np.asarray(corners_ds[i], np.float64) for i in ids])
        )
        if ids
        else np.zeros(0, bool)
    )
    for marker_id, inside in zip(ids, in_view.tolist(), strict=True):
        corners = np.asarray(corners_ds[marker_id], np.float64)
        px = camera.project(transform_points(T, corners))
        markers.append(
            MarkerTruth(int(marker_id), px, inside, inside and marker_id not in occluded_ids)
        )
    return FrameTruth(
        frame=int(frame),
        T_cam_ds=T,
        image=image,
        T_world_body=None if T_world_body is None else np.asarray(T_world_body, np.float64),
        range_m=range_m(T),
        view_angle_deg=view_angle_deg(T),
        water=None if water is None else dict(water),
        markers=tuple(markers),
    )


def _finite_or_none(a: np.ndarray) -> list:
    return [[None if not math.isfinite(v) else float(v) for v in row] for row in a.tolist()]


def frame_truth_to_json(ft: FrameTruth) -> dict[str, Any]:
    """The ``labels.jsonl`` object of a frame (non-finite corners become null)."""
    return {
        "frame": int(ft.frame),
        "image": ft.image,
        "T_cam_ds": np.asarray(ft.T_cam_ds, np.float64).tolist(),
        "T_world_body": None if ft.T_world_body is None else np.asarray(ft.T_world_body).tolist(),
        "range_m": float(ft.range_m) if math.isfinite(ft.range_m) else range_m(ft.T_cam_ds),
        "view_angle_deg": float(ft.view_angle_deg)
        if math.isfinite(ft.view_angle_deg)
        else view_angle_deg(ft.T_cam_ds),
        "water": ft.water,
        "markers": [
            {
                "id": int(m.marker_id),
                "corners_px": _finite_or_none(np.asarray(m.corners_px, np.float64)),
                "in_image": bool(m.in_image),
                "visible": bool(m.visible),
            }
            for m in ft.markers
        ],
    }


# --------------------------------------------------------------------------- writers


def write_labels(path: str | os.PathLike[str], frames: Iterable[FrameTruth]) -> Path:
    """Write ``labels.jsonl`` atomically, one line per frame, streaming ``frames``.

    Args:
        path: the labels file (normally ``DATASET/labels.jsonl``).
        frames: frame truths, e.g. from :func:`label_frame` (a generator is fine).

    Returns:
        The path written.
    """
    path = Path(path)
    with atomic_path(path) as tmp, tmp.open("w", encoding="utf-8") as fh:
        for ft in frames:
            fh.write(json.dumps(frame_truth_to_json(ft), separators=(",", ":")) + "\n")
    return path


def write_dataset_json(
    root: str | os.PathLike[str],
    frames: int,
    config: Mapping[str, Any] | None = None,
    camera: str = "camera.yaml",
    marker_set: str = "markerset.toml",
    images: str = "images",
    **extra: Any,
) -> Path:
    """Write ``DATASET/dataset.json`` atomically (call it last: it marks the folder complete).

    Args:
        root: the dataset folder.
        frames: number of frames (lines of ``labels.jsonl``).
        config: the resolved generator config (JSON-serialisable).
        camera, marker_set, images: paths relative to ``root``.
        **extra: further JSON-serialisable keys (e.g. ``provenance``).
    """
    doc = {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        "frames": int(frames),
        "camera": camera,
        "marker_set": marker_set,
        "images": images,
        "labels": "labels.jsonl",
        "config": dict(config or {}),
        **extra,
    }
    return atomic_write_json(Path(root) / "dataset.json", doc)


def write_pose_csv(path: str | os.PathLike[str], poses: Mapping[int, ArrayLike]) -> Path:
    """Write a pose CSV (``CSV_COLUMNS``) of frame index -> (4, 4) ``T_cam_ds``, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        for frame in sorted(poses):
            pos, quat = pos_quat_from_T(poses[frame])
            writer.writerow([int(frame), *(f"{v:.9g}" for v in (*pos, *quat))])
    return path


# --------------------------------------------------------------------------- readers


def _pose(value: Any, where: str) -> np.ndarray:
    """A (4, 4) rigid transform; a rotation within 1e-3 of orthonormal is re-orthonormalised."""
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DockError(f"{where}: must be a 4x4 list of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DockError(f"{where}: must be a finite 4x4 matrix, got shape {T.shape}")
    if not np.allclose(T[3], (0, 0, 0, 1), atol=1e-9):
        raise DockError(f"{where}: bottom row must be [0, 0, 0, 1]")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise DockError(f"{where}: the rotation block is not a rotation")
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    return T


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DockError(f"{where}: must be a finite number, got {value!r}")
    return float(value)


def _marker(entry: Any, where: str) -> MarkerTruth:
    if not isinstance(entry, dict):
        raise DockError(f"{where}: must be an object")
    try:
        marker_id = entry["id"]
        corners = entry["corners_px"]
        in_image = entry["in_image"]
        visible = entry["visible"]
    except KeyError as exc:
        raise DockError(f"{where}: missing key {exc}") from None
    if isinstance(marker_id, bool) or not isinstance(marker_id, int) or marker_id < 0:
        raise DockError(f"{where}.id: must be an integer >= 0, got {marker_id!r}")
    try:
        px = np.array([[np.nan if v is None else v for v in row] for row in corners], np.float64)
    except (TypeError, ValueError):
        raise DockError(f"{where}.corners_px: must be 4 [u, v] pairs") from None
    if px.shape != (4, 2):
        raise DockError(f"{where}.corners_px: must be 4 [u, v] pairs, got shape {px.shape}")
    if not isinstance(in_image, bool) or not isinstance(visible, bool):
        raise DockError(f"{where}: in_image and visible must be true or false")
    if in_image and not np.all(np.isfinite(px)):
        raise DockError(f"{where}.corners_px: a marker in the image needs finite corners")
    return MarkerTruth(marker_id, px, in_image, visible and in_image)


def _frame_from_json(obj: Any, where: str) -> FrameTruth:
    if not isinstance(obj, dict):
        raise DockError(f"{where}: each line must be a JSON object")
    for key in ("frame", "T_cam_ds"):
        if key not in obj:
            raise DockError(f"{where}: missing key '{key}'")
    frame = obj["frame"]
    if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
        raise DockError(f"{where}: 'frame' must be an integer >= 0, got {frame!r}")
    T = _pose(obj["T_cam_ds"], f"{where}: T_cam_ds")
    twb = obj.get("T_world_body")
    image = obj.get("image")
    if image is not None and not isinstance(image, str):
        raise DockError(f"{where}: 'image' must be a string or null")
    water = obj.get("water")
    if water is not None and not isinstance(water, dict):
        raise DockError(f"{where}: 'water' must be an object or null")
    markers = obj.get("markers", [])
    if not isinstance(markers, list):
        raise DockError(f"{where}: 'markers' must be a list")
    rng = obj.get("range_m")
    angle = obj.get("view_angle_deg")
    return FrameTruth(
        frame=frame,
        T_cam_ds=T,
        image=image,
        T_world_body=None if twb is None else _pose(twb, f"{where}: T_world_body"),
        range_m=range_m(T) if rng is None else _number(rng, f"{where}: range_m"),
        view_angle_deg=view_angle_deg(T)
        if angle is None
        else _number(angle, f"{where}: view_angle_deg"),
        water=water,
        markers=tuple(_marker(m, f"{where}: markers[{k}]") for k, m in enumerate(markers)),
    )


def _add(out: dict[int, FrameTruth], ft: FrameTruth, where: str) -> None:
    if ft.frame in out:
        raise DockError(f"{where}: frame {ft.frame} appears twice")
    out[ft.frame] = ft


def load_labels(path: str | os.PathLike[str]) -> dict[int, FrameTruth]:
    """Read a ``labels.jsonl`` file (blank lines are skipped).

    Raises:
        DockError: missing/unreadable file, malformed JSON or a bad value (names the line),
            a duplicated frame index, or no frame at all.
    """
    path = Path(path)
    lines = read_text(path, "ground-truth labels").splitlines()
    out: dict[int, FrameTruth] = {}
    for lineno, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        where = f"{path} line {lineno}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise DockError(f"{where}: malformed JSON ({exc.msg})") from None
        _add(out, _frame_from_json(obj, where), where)
    if not out:
        raise DockError(f"{path}: no frames")
    return out


def load_pose_csv(path: str | os.PathLike[str]) -> dict[int, FrameTruth]:
    """Read a pose CSV (see the module docstring) into frame truths without marker labels.

    Raises:
        DockError: missing file, a missing required column, a row with a non-numeric, negative
            or fractional frame, a non-finite or zero-norm value, a duplicated frame, or no rows;
            the message names the file and line.
    """
    path = Path(path)
    fh = io.StringIO(read_text(path, "ground-truth CSV"), newline="")
    out: dict[int, FrameTruth] = {}
    with fh:
        try:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in (reader.fieldnames or [])]
            missing = [c for c in CSV_COLUMNS if c not in header]
            if missing:
                raise DockError(
                    f"{path} line 1: header lacks column(s) {', '.join(missing)} "
                    f"(need {','.join(CSV_COLUMNS)})"
                )
            reader.fieldnames = header
            for row in reader:
                where = f"{path} line {reader.line_num}"
                if not any((v or "").strip() for v in row.values() if isinstance(v, str)):
                    continue
                _add(out, _csv_row(row, where), where)
        except csv.Error as exc:
            raise DockError(f"{path}: malformed CSV ({exc})") from None
    if not out:
        raise DockError(f"{path}: no pose rows")
    return out


#: Largest |x|, |y|, |z| of a ground-truth DS position (m) and frame index a pose CSV may hold:
#: beyond, a value is a wrong column or a corrupt file.
MAX_TRUTH_COORD_M = 1e6
MAX_FRAME_INDEX = 10**9
_CSV_BOUNDS = {
    "frame": MAX_FRAME_INDEX,
    "x_m": MAX_TRUTH_COORD_M,
    "y_m": MAX_TRUTH_COORD_M,
    "z_m": MAX_TRUTH_COORD_M,
}


def csv_number(text: object, column: str, where: str, bound: float | None = None) -> float:
    """One cell of a CSV as a finite number, within ``[-bound, bound]`` when a bound is given
    (the pose CSVs' readers share it).

    Raises:
        DockError: one line naming ``where`` (file and line), the column and the value.
    """
    try:
        v = float(str(text).strip())
    except (TypeError, ValueError):
        raise DockError(f"{where}: column '{column}' is not a number ({text!r})") from None
    if not math.isfinite(v):
        raise DockError(f"{where}: column '{column}' is not finite ({text!r})")
    if bound is not None and abs(v) > bound:
        raise DockError(f"{where}: column '{column}' is {v:g}, outside [-{bound:g}, {bound:g}]")
    return v


def _csv_row(row: Mapping[str, Any], where: str) -> FrameTruth:
    values = []
    for col in CSV_COLUMNS:
        values.append(csv_number(row.get(col), col, where, _CSV_BOUNDS.get(col)))
    frame = values[0]
    if frame < 0 or frame != int(frame):
        raise DockError(f"{where}: frame must be an integer >= 0, got {row.get('frame')!r}")
    return _pose_truth(int(frame), np.array(values[1:8]), where)


def _pose_truth(frame: int, pos_quat: np.ndarray, where: str) -> FrameTruth:
    """Ground truth from a position (m) and a (qw, qx, qy, qz) quaternion (a pose CSV row or a
    bag's pose message): a quaternion whose norm is off by more than ``QUAT_NORM_TOL`` is an
    error, one within it is normalised."""
    if not np.isfinite(pos_quat).all():
        raise DockError(f"{where}: the pose is not finite")
    q = pos_quat[3:7]
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) <= QUAT_NORM_TOL:
        raise DockError(
            f"{where}: quaternion (qw, qx, qy, qz) = ({', '.join(f'{v:g}' for v in q)}) has "
            f"norm {norm:.6g}, not 1 (within {QUAT_NORM_TOL:g}): a wrong or swapped column?"
        )
    T = np.eye(4)
    T[:3, :3] = R_from_quat_wxyz(q)
    T[:3, 3] = pos_quat[:3]
    return FrameTruth(frame=frame, T_cam_ds=T, range_m=range_m(T), view_angle_deg=view_angle_deg(T))


# --------------------------------------------------------------------------- dataset folder


@dataclass(frozen=True)
class LabelledDataset:
    """A labelled dataset folder, read and validated.

    Attributes:
        root: the dataset folder.
        manifest: the parsed ``dataset.json``.
        camera_path: the camera file.
        marker_set_path: the marker set file.
        images_dir: the image folder.
        frames: frame index -> ground truth.
    """

    root: Path
    manifest: dict[str, Any]
    camera_path: Path
    marker_set_path: Path
    images_dir: Path
    frames: dict[int, FrameTruth]


def is_dataset(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` is a folder holding ``dataset.json``."""
    return (Path(path) / "dataset.json").is_file()


def load_dataset(root: str | os.PathLike[str]) -> LabelledDataset:
    """Read ``dataset.json`` and ``labels.jsonl`` of a labelled dataset folder.

    The camera and marker set files are located, not parsed (use ``load_camera`` and
    ``load_marker_set``).

    Raises:
        DockError: missing or malformed manifest, wrong format or version, missing files,
            bad labels, or a frame count that disagrees with the manifest.
    """
    root = Path(root)
    manifest_path = root / "dataset.json"
    if not manifest_path.is_file():
        raise DockError(f"not a labelled dataset folder (no dataset.json): {root}")
    try:
        manifest = json.loads(read_text(manifest_path, "dataset manifest"))
    except json.JSONDecodeError as exc:
        raise DockError(f"{manifest_path}: malformed JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != DATASET_FORMAT:
        raise DockError(f"{manifest_path}: 'format' must be '{DATASET_FORMAT}'")
    if manifest.get("version") != DATASET_VERSION:
        raise DockError(
            f"{manifest_path}: unsupported version {manifest.get('version')!r} "
            f"(this toolkit reads {DATASET_VERSION})"
        )
    paths = {}
    for key, default in (
        ("camera", "camera.yaml"),
        ("marker_set", "markerset.toml"),
        ("images", "images"),
        ("labels", "labels.jsonl"),
    ):
        value = manifest.get(key, default)
        if not isinstance(value, str) or not value:
            raise DockError(f"{manifest_path}: '{key}' must be a relative path")
        paths[key] = root / value
        if not paths[key].exists():
            raise DockError(f"{manifest_path}: '{key}' names a missing path {paths[key]}")
    frames = load_labels(paths["labels"])
    n = manifest.get("frames")
    if isinstance(n, int) and not isinstance(n, bool) and n != len(frames):
        raise DockError(
            f"{manifest_path}: 'frames' is {n} but {paths['labels'].name} holds {len(frames)}"
        )
    return LabelledDataset(
        root, manifest, paths["camera"], paths["marker_set"], paths["images"], frames
    )


#: Largest translation (m) of a label's ``T_cam_ds`` and ``T_world_body``. A camera images the
#: DS board (about a metre across) down to a few pixels at tens of metres, and no water is
#: clear beyond about 100 m; the worlds the toolkit simulates are tanks and harbour basins
#: (tens to hundreds of metres), and an error model's bins end at ``range_max_m`` <= 1000 m.
#: So 1 km leaves an order of magnitude of room over any frame a dataset can mean, while a
#: label at 1e6 m or more is a unit mix-up, a wrong ``T_body_cam`` (one of 1e6 m put vehicles
#: 997 km away) or a corrupt file: read as is, it lands in an error model's last range bin.
MAX_LABEL_TRANSLATION_M = 1000.0
#: Largest difference (m, deg) between a label's ``range_m`` / ``view_angle_deg`` and the
#: values its ``T_cam_ds`` gives (the writer derives them from the same numbers: equal to the
#: bit; the slack is for labels written by other tools in single precision).
_DERIVED_TOL = 1e-3


def _label_line(labels: Path, frame: int) -> str:
    """``"LABELS line N (frame K)"`` for an error message (the labels are read again: only
    on the way to an error)."""
    try:
        lines = read_text(labels, "labels").splitlines()
    except DockError:
        lines = []
    for lineno, line in enumerate(lines, start=1):
        if '"frame"' in line:
            try:
                obj = json.loads(line)
            except ValueError:
                continue
            if isinstance(obj, dict) and obj.get("frame") == frame:
                return f"{labels} line {lineno} (frame {frame})"
    return f"{labels} (frame {frame})"


def _inside(path: Path, folders: tuple[Path, ...]) -> bool:
    return any(path == f or path.is_relative_to(f) for f in folders)


def _relative_name(value: str, what: str) -> str | None:
    """Why ``value`` (a path a dataset file names) is not a plain relative path, or None."""
    if "\x00" in value:
        return f"{what} {value!r} holds a NUL character"
    if not value or os.path.isabs(value) or value.startswith("~"):
        return f"{what} {value!r} is not a path relative to the dataset folder"
    if ".." in Path(value).parts:
        return f"{what} {value!r} leads out of the dataset folder ('..')"
    return None


def check_dataset_labels(ds: LabelledDataset) -> LabelledDataset:
    """Check a labelled dataset's labels against the dataset (``ds`` as :func:`load_dataset`
    reads it), before anything opens an image:

    * the manifest's paths (camera, marker set, images, labels) and every label's ``image`` are
      relative paths inside the dataset folder: no absolute path, no ``..``, and, with
      symbolic links resolved, inside the folder (or inside its images folder, which may be a
      link to another disk): a label naming ``/etc/passwd`` is refused, not read;
    * every label names an image, and it is a regular file that exists (a FIFO would block the
      reader forever, a missing image would silently drop the frame);
    * its poses (``T_cam_ds``, ``T_world_body``) are within :data:`MAX_LABEL_TRANSLATION_M`
      and its ``range_m`` and ``view_angle_deg`` are those of ``T_cam_ds`` (the loader has
      already refused non-finite numbers).

    Returns:
        ``ds`` unchanged.

    Raises:
        DockError: one line naming the labels file, the line and frame, and what is wrong.
    """
    manifest = ds.root / "dataset.json"
    root = ds.root.resolve()
    for key in ("camera", "marker_set", "images", "labels"):
        value = ds.manifest.get(key)
        if value is None:  # the default name (load_dataset has checked the type)
            continue
        why = _relative_name(str(value), f"'{key}'")
        # the images folder may be a link to another disk; the small files stay inside
        if why is None and key != "images" and not _inside((ds.root / value).resolve(), (root,)):
            why = f"'{key}' {value!r} leads out of the dataset folder (a symbolic link)"
        if why is not None:
            raise DockError(f"{manifest}: {why}")
    labels = ds.root / str(ds.manifest.get("labels") or "labels.jsonl")
    folders = (root, ds.images_dir.resolve())
    for k in sorted(ds.frames):
        ft = ds.frames[k]
        why = None
        if ft.image is None:
            why = "names no image"
        else:
            why = _relative_name(ft.image, "image")
        if why is None:
            path = ds.root / ft.image
            kind = special_file_kind(path)
            if not _inside(path.resolve(), folders):
                why = f"image {ft.image!r} leads out of the dataset folder (a symbolic link)"
            elif kind is not None:
                why = f"image {ft.image} is {kind}, not a regular file"
            elif path.is_dir():
                why = f"image {ft.image} is a folder"
            elif not path.is_file():
                why = f"image {ft.image} is missing"
        if why is None:
            why = _pose_range_problem(ft)
        if why is not None:
            raise DockError(f"{_label_line(labels, ft.frame)}: {why}")
    return ds


def _pose_range_problem(ft: FrameTruth) -> str | None:
    """What is out of range in a label's poses (module constants), or None."""
    for key, T in (("T_cam_ds", ft.T_cam_ds), ("T_world_body", ft.T_world_body)):
        if T is None:
            continue
        t = float(np.linalg.norm(np.asarray(T, np.float64)[:3, 3]))
        if not t <= MAX_LABEL_TRANSLATION_M:
            return (
                f"{key} translation is {t:.4g} m (at most {MAX_LABEL_TRANSLATION_M:g} m: a "
                "camera sees the station at tens of metres at most)"
            )
    for key, label, derived, unit in (
        ("range_m", ft.range_m, range_m(ft.T_cam_ds), "m"),
        ("view_angle_deg", ft.view_angle_deg, view_angle_deg(ft.T_cam_ds), "deg"),
    ):
        if not abs(float(label) - derived) <= _DERIVED_TOL:
            return f"{key} is {float(label):.6g} {unit} but T_cam_ds gives {derived:.6g} {unit}"
    return None


def load_checked_dataset(path: str | os.PathLike[str]) -> LabelledDataset:
    """:func:`load_dataset` and :func:`check_dataset_labels`: the labelled dataset every reader
    of the toolkit (``perception eval``, ``datasets.loaders.LabelledDataset``, ``rl
    fit-error-model``) opens."""
    return check_dataset_labels(load_dataset(path))


def _check_label_poses(frames: dict[int, FrameTruth], labels: Path) -> dict[int, FrameTruth]:
    """``frames`` (a ``labels.jsonl`` read without its dataset) when every label's poses are
    in range (:func:`check_dataset_labels`' pose checks: no dataset folder, no images to check).

    Raises:
        DockError: one line naming the labels file, the line and frame, and what is wrong.
    """
    for k in sorted(frames):
        why = _pose_range_problem(frames[k])
        if why is not None:
            raise DockError(f"{_label_line(labels, frames[k].frame)}: {why}")
    return frames


def load_ground_truth(path: str | os.PathLike[str]) -> dict[int, FrameTruth]:
    """Frame index -> ground truth from a dataset folder, a ``labels.jsonl`` or a pose ``.csv``.

    A dataset folder's labels are checked against it (:func:`load_checked_dataset`), a
    ``labels.jsonl``'s poses are checked for range (:data:`MAX_LABEL_TRANSLATION_M`).

    Raises:
        DockError: one line naming the file (and line) on any problem, or an unknown kind of
            path.
    """
    path = Path(path)
    if path.is_dir():
        return load_checked_dataset(path).frames
    suffix = path.suffix.lower()
    if path.name == "dataset.json":
        return load_checked_dataset(path.parent).frames
    if suffix == ".csv":
        return load_pose_csv(path)
    if suffix in (".jsonl", ".json"):
        return _check_label_poses(load_labels(path), path)
    if not path.exists():
        raise DockError(f"ground truth not found: {path}")
    raise DockError(
        f"ground truth must be a dataset folder, a labels .jsonl or a pose .csv: {path}"
    )


# --------------------------------------------------------------------------- bag pose topic


def truth_from_bag(
    path: str | os.PathLike[str],
    image_topic: str,
    pose_topic: str,
    tolerance_ms: float = 10.0,
) -> dict[int, FrameTruth]:
    """Frame index -> ground truth from a bag's pose topic (:mod:`dockcore.bags`).

    Each pose message is ``T_cam_ds`` (the DS in the OpenCV camera frame, m), like the pose CSV.
    Frame k (the image topic's k-th message) takes the pose whose time is nearest its own
    (header stamps where present) when within ``tolerance_ms``; frames without one have no
    ground truth.

    Raises:
        DockError: a missing topic or one of another type, a non-finite pose or one without a
            unit quaternion, a non-positive tolerance, or no frame within the tolerance of a
            pose (one line naming the bag).
    """
    if not (math.isfinite(tolerance_ms) and tolerance_ms > 0):
        raise DockError(f"pose tolerance must be a positive number of ms, got {tolerance_ms!r}")
    with Bag(path) as bag:
        bag.topic(image_topic, ("image",))
        stamps, poses = bag.poses(pose_topic)
        frames = bag.stamps(image_topic)
    tol_ns = round(tolerance_ms * 1e6)
    out: dict[int, FrameTruth] = {}
    for k, t in enumerate(frames):
        j = nearest_in_time(stamps, t, tol_ns)
        if j is not None:
            out[k] = _pose_truth(k, poses[j], f"{Path(path).name} {pose_topic} message {j}")
    if not out:
        raise DockError(
            f"no frame of {image_topic} in {Path(path).name} lies within {tolerance_ms:g} ms of a "
            f"pose on {pose_topic} ({len(poses)} poses, {len(frames)} frames)"
        )
    return out
