"""Loaders: labelled datasets (``datasets synth`` / ``sim render`` output) and plain footage.

* :class:`LabelledDataset`: a ``uwdock.dataset`` folder (format in :mod:`perception.groundtruth`),
  validated on open; ``len``, indexing and iteration give :class:`Sample` (image + ground truth),
  with the camera model, ``T_body_cam`` and the marker set.
* :class:`FootageSource`: an image folder, a single image or a video, iterable any number of
  times; a thin wrapper over :func:`perception.video.open_frames`.
* :func:`check_dataset_labels` / :func:`load_checked_dataset`: the labels checked against their
  dataset (defined in :mod:`perception.groundtruth`, which ``perception eval`` shares).
* :func:`load_poses_csv`: vehicle poses to render (``datasets render --poses``);
  :func:`load_pose_track_csv` / :func:`write_pose_track_csv` with their sequence labels.

Example:
    >>> ds = LabelledDataset("data/synth_coastal")
    >>> for s in ds:
    ...     detections = detector.detect(s.image)          # BGR uint8
    ...     s.truth.T_cam_ds, s.truth.visible_ids
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import CameraModel, load_camera
from uwdock.calibration.frames import R_from_quat_wxyz, R_from_rpy, make_T, pos_quat_from_T
from uwdock.datasets.sequences import (
    SEQUENCE_COLUMNS,
    FrameSequences,
    check_sequences,
    sequences_from_manifest,
)
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, read_text
from uwdock.markers.markerset import MarkerSet, load_marker_set
from uwdock.perception.groundtruth import (
    MAX_LABEL_TRANSLATION_M,
    FrameTruth,
    check_dataset_labels,
    csv_number,
    load_checked_dataset,
)
from uwdock.perception.video import FrameSource, open_frames, read_image

__all__ = [
    "MAX_LABEL_TRANSLATION_M",
    "FootageSource",
    "LabelledDataset",
    "Sample",
    "check_dataset_labels",
    "load_checked_dataset",
    "load_pose_track_csv",
    "load_poses_csv",
    "write_pose_track_csv",
]


@dataclass(frozen=True)
class Sample:
    """One labelled frame.

    Attributes:
        index: position in the dataset (0..len-1).
        image: (H, W, 3) uint8 BGR image (as ``cv2.imread`` gives it).
        truth: the frame's ground truth (``T_cam_ds``, marker corners and visibility, water).
        path: the image file.
    """

    index: int
    image: np.ndarray
    truth: FrameTruth
    path: Path


class LabelledDataset:
    """A labelled dataset folder, opened and validated.

    Args:
        path: the dataset folder (holding ``dataset.json``).

    Raises:
        DockError: one line on a missing or malformed ``dataset.json``, a wrong format or
            version, missing files, malformed labels, an unreadable camera or marker set file,
            or a labelled image missing from the folder.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        raw = load_checked_dataset(path)
        self.root: Path = raw.root
        self.manifest: dict[str, Any] = raw.manifest
        self.camera: CameraModel
        self.camera, T_body_cam = load_camera(raw.camera_path)
        self.T_body_cam: np.ndarray | None = T_body_cam
        self.marker_set: MarkerSet = load_marker_set(raw.marker_set_path)
        self.images_dir: Path = raw.images_dir
        self.frames: list[FrameTruth] = [raw.frames[k] for k in sorted(raw.frames)]
        #: which frames follow each other in time (frame k is entry k), or None
        self.sequences: FrameSequences | None = sequences_from_manifest(
            self.manifest, len(self.frames), str(self.root / "dataset.json")
        )

    @property
    def config(self) -> dict[str, Any]:
        """The generator config recorded in ``dataset.json``."""
        return dict(self.manifest.get("config") or {})

    def __len__(self) -> int:
        return len(self.frames)

    def image_path(self, index: int) -> Path:
        """The image file of the ``index``-th frame."""
        return self.root / str(self.frames[index].image)

    def __getitem__(self, index: int) -> Sample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range (dataset has {len(self)})")
        index %= len(self)
        path = self.image_path(index)
        image = read_image(path)
        if image is None:
            raise DockError(f"cannot read image {path} (corrupt or not an image)")
        return Sample(index, image, self.frames[index], path)

    def __iter__(self) -> Iterator[Sample]:
        for index in range(len(self)):
            yield self[index]

    def __repr__(self) -> str:
        return f"LabelledDataset({str(self.root)!r}, frames={len(self)})"


class FootageSource:
    """Real footage: a folder of images, one image or a video file (see
    :func:`perception.video.open_frames`). Each iteration reopens the input.

    Args:
        path: the input.

    Raises:
        DockError: one line when the input is missing, empty or unreadable as a whole.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        probe = open_frames(self.path)
        self.kind: str = probe.kind
        self.total: int | None = probe.total
        self.fps: float | None = probe.fps
        self._close(probe)

    @staticmethod
    def _close(source: FrameSource) -> None:
        cap = getattr(source, "_cap", None)
        if cap is not None:
            cap.release()

    def __len__(self) -> int:
        """Frames expected (a video container's count may be wrong; 0 when unknown)."""
        return int(self.total or 0)

    def __iter__(self) -> Iterator[tuple[int, str, np.ndarray | None]]:
        """``(index, name, BGR or grey image, or None for a corrupt frame)``."""
        yield from open_frames(self.path)

    def __repr__(self) -> str:
        return f"FootageSource({str(self.path)!r}, kind={self.kind!r}, frames={self.total})"


#: Largest position (m, |x|, |y|, |z|), Euler angle (deg; unwrapped logs of many turns pass) and
#: time (s) a pose CSV may hold: beyond, a value is a wrong column or a corrupt file (a yaw of
#: 1e300 deg has no meaningful sine).
MAX_POSE_COORD_M = 1e6
MAX_POSE_ANGLE_DEG = 1e5
MAX_POSE_TIME_S = 1e9
_POSE_BOUNDS = {
    "x_m": MAX_POSE_COORD_M,
    "y_m": MAX_POSE_COORD_M,
    "z_m": MAX_POSE_COORD_M,
    "roll_deg": MAX_POSE_ANGLE_DEG,
    "pitch_deg": MAX_POSE_ANGLE_DEG,
    "yaw_deg": MAX_POSE_ANGLE_DEG,
    "time_s": MAX_POSE_TIME_S,
}


def _pose_value(text: object, column: str, where: str) -> float:
    """One cell of a pose CSV as a finite number within the column's bound (``_POSE_BOUNDS``).

    Raises:
        DockError: one line naming ``where`` (file and line) and the column.
    """
    return csv_number(text, column, where, _POSE_BOUNDS.get(column))


def load_poses_csv(path: str | os.PathLike[str]) -> np.ndarray:
    """Vehicle poses (N, 4, 4) ``T_world_body`` from a CSV (see :func:`load_pose_track_csv`)."""
    return load_pose_track_csv(path)[0]


def load_pose_track_csv(
    path: str | os.PathLike[str],
) -> tuple[np.ndarray, FrameSequences | None]:
    """Vehicle poses (N, 4, 4) ``T_world_body`` from a CSV, with their sequence labels.

    Columns (header required, extra columns ignored): ``x_m, y_m, z_m`` (body origin in world
    NED: x north, y east, z down from the surface; the DS origin is at (0, 0, 4.98) by default)
    and either ``qw, qx, qy, qz`` (body FRD orientation, normalised on load) or ``roll_deg,
    pitch_deg, yaw_deg`` (ZYX Euler angles of body FRD in world NED). One frame per row.
    Optionally ``sequence, step, time_s`` (all three): the frames form time sequences
    (:mod:`uwdock.datasets.sequences`), as :func:`write_pose_track_csv` writes them.

    Returns:
        ``(poses, sequences)``: (N, 4, 4) float64 and the sequence labels, or None without
        the sequence columns.

    Raises:
        DockError: one line naming the file and line on a missing file, missing columns, a
            non-numeric value, no rows or inconsistent sequence labels.
    """
    path = Path(path)
    text = read_text(path, "poses file")
    reader = csv.DictReader(text.splitlines())
    header = [h.strip() for h in reader.fieldnames or []]
    reader.fieldnames = header
    quat, euler = ("qw", "qx", "qy", "qz"), ("roll_deg", "pitch_deg", "yaw_deg")
    rot = quat if all(c in header for c in quat) else euler
    need = ("x_m", "y_m", "z_m", *rot)
    missing = [c for c in need if c not in header]
    if missing:
        raise DockError(
            f"{path} line 1: missing column(s) {', '.join(missing)} (need x_m,y_m,z_m and "
            "qw,qx,qy,qz or roll_deg,pitch_deg,yaw_deg)"
        )
    seq_cols = [c for c in SEQUENCE_COLUMNS if c in header]
    if seq_cols and len(seq_cols) < len(SEQUENCE_COLUMNS):
        absent = [c for c in SEQUENCE_COLUMNS if c not in header]
        raise DockError(
            f"{path} line 1: sequence columns need all of {', '.join(SEQUENCE_COLUMNS)} "
            f"(missing {', '.join(absent)})"
        )
    poses, seq_rows = [], []
    for row in reader:
        where = f"{path} line {reader.line_num}"
        v = [_pose_value(row.get(c), c, where) for c in (*need, *seq_cols)]
        seq_rows.append(v[len(need) :])
        if rot is quat:
            q = np.array(v[3:7])
            with np.errstate(over="ignore"):
                norm = float(np.linalg.norm(q))
            if not 1e-9 <= norm < math.inf:
                raise DockError(f"{where}: quaternion (qw, qx, qy, qz) has norm {norm:g}")
            R = R_from_quat_wxyz(q / norm)
        else:
            R = R_from_rpy(*np.radians(v[3:6]))
        poses.append(make_T(R, v[:3]))
    if not poses:
        raise DockError(f"{path}: no pose rows")
    if not seq_cols:
        return np.stack(poses), None
    cols = np.asarray(seq_rows, np.float64).T
    return np.stack(poses), check_sequences(*cols, len(poses), str(path))


def write_pose_track_csv(
    path: str | os.PathLike[str], poses: ArrayLike, sequences: FrameSequences | None = None
) -> Path:
    """Write vehicle poses (N, 4, 4) ``T_world_body`` (body FRD in world NED, m) as the CSV
    :func:`load_pose_track_csv` reads (``x_m,y_m,z_m,qw,qx,qy,qz`` + ``sequence,step,time_s``
    when given), atomically; values at full float64 precision (they read back exactly)."""
    pose_arr = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    if sequences is not None and len(sequences) != len(pose_arr):
        raise DockError(f"{len(pose_arr)} poses but {len(sequences)} sequence labels")
    path = Path(path)
    header = ["x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]
    with atomic_path(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(header + (list(SEQUENCE_COLUMNS) if sequences is not None else []))
        for f, T in enumerate(pose_arr):
            pos, quat = pos_quat_from_T(T)
            row = [repr(float(v)) for v in (*pos, *quat)]
            if sequences is not None:
                s = sequences
                row += [str(int(s.sequence[f])), str(int(s.step[f])), repr(float(s.time_s[f]))]
            writer.writerow(row)
    return path
