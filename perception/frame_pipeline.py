"""The per-frame pipeline that ``perception detect`` and ``perception eval`` share: their config
(:class:`PerceptionConfig`), the markers and camera they resolve before any output is made
(:func:`resolve_markers`, :class:`CameraResolver`), one frame through the detector and the pose
solver (:class:`FrameProcessor` -> :class:`FrameResult`), a frame's row in the detection files
and its annotated image. :mod:`perception.evaluate` runs the two commands over the frames.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tqdm import tqdm

from uwdock.calibration.camera import CameraModel, reference_camera
from uwdock.calibration.frames import pos_quat_from_T
from uwdock.dockcore.domains import check, split_annotated
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import display_name
from uwdock.markers.config import MarkerConfig, MarkerSideM
from uwdock.markers.dictionary import normalise_dictionary_name
from uwdock.markers.markerset import load_marker_set, marker_set_from_config
from uwdock.perception.detector import Detection, DetectorConfig
from uwdock.perception.ds_pose import DSPoseConfig, DSPoseEstimator
from uwdock.perception.pose import BoardPose, BoardPoseConfig, MarkerPose, solve_marker
from uwdock.perception.report_plots import (
    ReportConfig,
)
from uwdock.perception.video import (
    FrameSource,
    annotate,
)

__all__ = [
    "CSV_HEADER",
    "CameraResolver",
    "FrameProcessor",
    "FrameResult",
    "MarkerSetup",
    "Note",
    "PerceptionConfig",
    "detection_csv_row",
    "detection_row",
    "draw_result",
    "frame_label",
    "progress_frames",
    "resolve_markers",
    "silent_note",
]

#: A callable that reports one line of progress or a warning.
Note = Callable[[str], None]


@dataclass(frozen=True)
class PerceptionConfig:
    """Everything ``perception detect`` / ``eval`` resolve (the ``--config`` TOML's tables).

    Attributes:
        detector: marker detector (``[detector]``); dictionary and IDs come from the marker set.
        board: DS board pose solver (``[board]``).
        pose: the DS-pose estimator's refinement (``[pose]``: ``level_ds``, applied to frames
            whose vehicle attitude is known, i.e. labelled datasets with ``T_world_body``).
        report: evaluation report (``[report]``).
    """

    detector: DetectorConfig = field(default_factory=DetectorConfig)
    board: BoardPoseConfig = field(default_factory=BoardPoseConfig)
    pose: DSPoseConfig = field(default_factory=DSPoseConfig)
    report: ReportConfig = field(default_factory=ReportConfig)


# --------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class MarkerSetup:
    """Which markers to detect and how to turn them into poses.

    Attributes:
        dictionary: canonical dictionary name.
        ids: allow-listed IDs (None: every ID of the dictionary).
        corners_ds: board geometry, ID -> (4, 3) corners in the DS frame (m); None for
            single-marker poses.
        marker_size_m: side for single-marker poses (m), or None (no pose at all).
        description: one line for reports.
    """

    dictionary: str
    ids: tuple[int, ...] | None
    corners_ds: dict[int, np.ndarray] | None
    marker_size_m: float | None
    description: str


def resolve_markers(
    markers_path: str | os.PathLike[str] | None = None,
    dictionary: str | None = None,
    marker_size_m: float | None = None,
) -> MarkerSetup:
    """A marker set file, or a dictionary and a side (single markers), or the default DS set.

    Raises:
        DockError: both a marker set and ``dictionary``/``marker_size_m``, an unknown
            dictionary, a non-positive size, or an invalid marker set file.
    """
    if markers_path is not None and (dictionary is not None or marker_size_m is not None):
        raise DockError("--markers cannot be combined with --dictionary / --marker-size-m")
    if marker_size_m is not None:
        reason = check(marker_size_m, *split_annotated(MarkerSideM), "--marker-size-m")
        if reason:
            raise DockError(reason)
    if dictionary is not None or marker_size_m is not None:
        name = normalise_dictionary_name(dictionary or "DICT_4X4_50")
        what = f"single markers of {name}" + (
            f", side {marker_size_m:g} m" if marker_size_m else " (no side given: no poses)"
        )
        return MarkerSetup(name, None, None, marker_size_m, what)
    if markers_path is not None:
        ms = load_marker_set(markers_path)
        what = f"marker set {markers_path}"
    else:
        ms = marker_set_from_config(MarkerConfig())
        what = "default DS marker set"
    ids = ", ".join(str(i) for i in ms.ids)
    return MarkerSetup(
        ms.dictionary, ms.ids, ms.corners_ds(), None, f"{what} ({ms.dictionary}: {ids})"
    )


class CameraResolver:
    """The camera model for a frame size: the given camera (scaled if the size differs, same
    aspect ratio only) or, without one, the reference camera scaled to the frame size.

    Args:
        camera: intrinsics from a camera file, or None.
        note: called once per new situation with a one-line message for stderr.
    """

    def __init__(self, camera: CameraModel | None, note: Note) -> None:
        self.camera = camera
        self.note = note
        self._cache: dict[tuple[int, int], CameraModel] = {}

    def __call__(self, width_px: int, height_px: int) -> CameraModel:
        key = (int(width_px), int(height_px))
        if key in self._cache:
            return self._cache[key]
        base = self.camera
        if base is None:
            cam = reference_camera().scaled(*key)  # any frame size: aspect ratio as the frames
            self.note(
                f"no camera file: using the reference camera (968x732, HFOV 55 deg) scaled to "
                f"{key[0]}x{key[1]}; poses are approximate"
            )
        elif (base.width_px, base.height_px) == key:
            cam = base
        else:
            aspect = (key[0] / key[1]) / (base.width_px / base.height_px)
            if abs(aspect - 1.0) > 0.01:
                raise DockError(
                    f"camera file is {base.width_px}x{base.height_px} but the frames are "
                    f"{key[0]}x{key[1]} (another aspect ratio: calibrate this resolution)"
                )
            cam = base.scaled(*key)
            self.note(
                f"camera file is {base.width_px}x{base.height_px}: scaled to the "
                f"{key[0]}x{key[1]} frames"
            )
        self._cache[key] = cam
        return cam

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """Frame sizes (width, height) seen so far."""
        return list(self._cache)


# --------------------------------------------------------------------------- processing


@dataclass
class FrameResult:
    """Detector and pose output for one frame.

    Attributes:
        detections: markers found, sorted by ID.
        board: the DS pose from the board (unconstrained PnP), or None.
        marker_poses: single-marker mode: ID -> both IPPE solutions.
        ms: detection + pose time (ms).
        level_T_cam_ds: (4, 4) the level-DS solution in the camera frame when the frame's
            attitude was known (:class:`~uwdock.perception.ds_pose.DSPoseEstimator`), or None.
        level_rms_px: its RMS reprojection error (px), or None.
    """

    detections: list[Detection]
    board: BoardPose | None
    marker_poses: dict[int, MarkerPose]
    ms: float
    level_T_cam_ds: np.ndarray | None = None
    level_rms_px: float | None = None

    @property
    def T_cam_ds(self) -> np.ndarray | None:
        """The estimator's DS pose: the level solution when there is one, else the board's."""
        if self.level_T_cam_ds is not None:
            return self.level_T_cam_ds
        return None if self.board is None else self.board.T_cam_ds

    @property
    def reprojection_rms_px(self) -> float | None:
        """RMS corner reprojection error of :attr:`T_cam_ds` (px), or None."""
        if self.level_rms_px is not None:
            return self.level_rms_px
        return None if self.board is None else self.board.reprojection_rms_px


class FrameProcessor:
    """The DS-pose estimator (or single-marker poses) for one pipeline.

    Args:
        setup: markers to detect and their geometry.
        detector_cfg: detector settings; dictionary and IDs are taken from ``setup``.
        board_cfg: board solver settings.
        pose_cfg: the estimator's refinement (level DS when the attitude is known).
    """

    def __init__(
        self,
        setup: MarkerSetup,
        detector_cfg: DetectorConfig,
        board_cfg: BoardPoseConfig,
        pose_cfg: DSPoseConfig | None = None,
    ) -> None:
        cfg = dataclasses.replace(detector_cfg, dictionary=setup.dictionary, ids=setup.ids)
        self.estimator = DSPoseEstimator(setup.corners_ds or {}, cfg, board_cfg, pose_cfg)
        self.detector = self.estimator.detector
        self.board_cfg = self.estimator.board_cfg
        self.setup = setup

    def process(
        self,
        img_bgr: np.ndarray,
        camera: CameraModel,
        T_world_cam: np.ndarray | None = None,
        T_cam_ds_prior: np.ndarray | None = None,
    ) -> FrameResult:
        """Detect markers and solve the pose(s) of one BGR (or grey) image.

        Args:
            img_bgr: the frame.
            camera: its camera model.
            T_world_cam: (4, 4) camera pose in a z-down gravity-aligned world (the vehicle's
                attitude and mounting), when known: enables the level-DS refinement.
            T_cam_ds_prior: (4, 4) predicted DS pose in the camera frame (the previous video
                frame's), used with ``pose.search_from_prior``.
        """
        t0 = time.perf_counter()
        if self.setup.corners_ds is not None:
            est = self.estimator.estimate(
                img_bgr, camera, T_world_cam, T_cam_ds_prior=T_cam_ds_prior
            )
            level = est.level
            return FrameResult(
                est.detections,
                est.board,
                {},
                (time.perf_counter() - t0) * 1e3,
                None if level is None else est.T_cam_ds,
                None if level is None else level.reprojection_rms_px,
            )
        dets = self.detector.detect(img_bgr)
        board, singles = None, {}
        if self.setup.marker_size_m:
            for d in dets:
                try:
                    singles[d.marker_id] = solve_marker(
                        d.corners_px,
                        self.setup.marker_size_m,
                        camera.K,
                        camera.dist_coeffs,
                        d.marker_id,
                    )
                except DockError:
                    pass
        return FrameResult(dets, board, singles, (time.perf_counter() - t0) * 1e3)


def _T(T: np.ndarray | None) -> list | None:
    return None if T is None else np.asarray(T, np.float64).tolist()


def detection_row(index: int, name: str, res: FrameResult | None) -> dict[str, Any]:
    """The ``detections.jsonl`` object of a frame (``corrupt`` when it could not be decoded)."""
    name = display_name(name)  # a name that is not UTF-8: its bytes as \\xNN (valid text)
    if res is None:
        return {"frame": index, "name": name, "corrupt": True}
    markers = []
    for d in res.detections:
        m: dict[str, Any] = {"id": d.marker_id, "corners_px": d.corners_px.tolist()}
        mp = res.marker_poses.get(d.marker_id)
        if mp is not None:
            m["T_cam_marker"] = _T(mp.T_cam_marker)
            m["reprojection_rms_px"] = mp.best.reprojection_rms_px
            m["ambiguity_ratio"] = mp.ambiguity_ratio
        markers.append(m)
    b = res.board
    return {
        "frame": index,
        "name": name,
        "corrupt": False,
        "ids": [d.marker_id for d in res.detections],
        "markers": markers,
        "T_cam_ds": _T(res.T_cam_ds),
        "reprojection_rms_px": res.reprojection_rms_px,
        "used_ids": None if b is None else list(b.used_ids),
        "rejected_ids": None if b is None else list(b.rejected_ids),
        "ms": res.ms,
    }


#: Columns of ``detections.csv`` (the pose columns as in a ground-truth CSV).
CSV_HEADER: tuple[str, ...] = tuple(
    "frame name corrupt n_markers ids pose x_m y_m z_m qw qx qy qz reprojection_rms_px ms "
    "corners_px".split()
)


def detection_csv_row(row: dict[str, Any]) -> list[Any]:
    """``detections.csv`` cells of a :func:`detection_row` (pose as in a ground-truth CSV)."""
    if row["corrupt"]:
        return [row["frame"], row["name"], 1, *[""] * (len(CSV_HEADER) - 3)]
    pose = [""] * 7
    if row["T_cam_ds"] is not None:
        pos, quat = pos_quat_from_T(np.array(row["T_cam_ds"]))
        pose = [f"{v:.6f}" for v in (*pos, *quat)]
    corners = {str(m["id"]): np.round(m["corners_px"], 3).tolist() for m in row["markers"]}
    rms = row["reprojection_rms_px"]
    return [
        row["frame"],
        row["name"],
        0,
        len(row["ids"]),
        " ".join(map(str, row["ids"])),
        int(row["T_cam_ds"] is not None),
        *pose,
        "" if rms is None else f"{rms:.4f}",
        f"{row['ms']:.3f}",
        json.dumps(corners, separators=(",", ":")),
    ]


def frame_label(name: str, res: FrameResult) -> str:
    text = f"{name}  {len(res.detections)} markers  {res.ms:.1f} ms"
    if res.T_cam_ds is not None:
        text += f"  range {np.linalg.norm(res.T_cam_ds[:3, 3]):.2f} m"
    return text


def draw_result(image, res: FrameResult, camera: CameraModel, setup: MarkerSetup, cfg, name: str):
    return annotate(
        image,
        res.detections,
        camera,
        res.T_cam_ds,
        {k: v.T_cam_marker for k, v in res.marker_poses.items()},
        cfg.axis_length_m,
        setup.marker_size_m or 0.1,
        frame_label(name, res),
    )


def progress_frames(source: FrameSource, show: bool | None, desc: str) -> Iterable:
    disable = None if show is None else not show  # None: only on a terminal
    return tqdm(source, total=source.total, desc=desc, unit="frame", disable=disable, leave=False)


def silent_note(_: str) -> None:
    pass
