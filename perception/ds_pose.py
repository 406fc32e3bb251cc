"""The one docking-station pose estimator: detector + board PnP + optional level-DS refinement.

Every path that turns a camera image into a DS pose goes through :class:`DSPoseEstimator`: the
env's camera source, the error-model fit, the deployment runner and ``perception eval``; so the
policy is trained, fitted and scored on the same estimator.

Steps of :meth:`DSPoseEstimator.estimate`:

1. detect the board's markers in the BGR image (:class:`~uwdock.perception.detector.Detector`);
2. solve the DS pose from all of them jointly (:func:`~uwdock.perception.pose.solve_board`);
   a prior DS pose (e.g. a filter's estimate) picks between the two mirror solutions of
   coplanar markers;
3. when the camera's attitude is known (``T_world_cam`` in a z-down gravity-aligned world) and
   ``level_ds`` is on, re-solve with the DS known to stand level (x, y, z, yaw only;
   :func:`~uwdock.perception.pose.refine_level_board`).

Channel order: the image is BGR (OpenCV's order) or grey; a simulator's RGB frame is converted
once at the seam (``uwdock.sim.camera.Frame.img_bgr``).

Example:
    >>> est = DSPoseEstimator.from_marker_set(marker_set)
    >>> e = est.estimate(img_bgr, camera, T_world_cam=T_world_body @ T_body_cam)
    >>> e.T_cam_ds, e.T_world_ds, e.covariance_xyzyaw
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import check_T, inv_T
from uwdock.dockcore.config import validated
from uwdock.dockcore.errors import ConfigError
from uwdock.markers.markerset import MarkerSet
from uwdock.perception.detector import Detection, Detector, DetectorConfig
from uwdock.perception.pose import (
    BoardPose,
    BoardPoseConfig,
    LevelBoardPose,
    refine_level_board,
    solve_board,
)

__all__ = ["DSPoseConfig", "DSPoseEstimate", "DSPoseEstimator"]


@dataclass(frozen=True)
class DSPoseConfig:
    """How the DS pose is estimated beyond the board PnP (the ``[pose]`` table).

    Attributes:
        level_ds: when the camera's attitude is known, re-solve with the DS level (x, y, z,
            yaw): with a few coplanar markers in view this removes errors of several
            centimetres and degrees. The env's camera source, the error-model fit and the
            deployment runner always know the attitude; ``perception eval`` knows it for
            labelled datasets that record ``T_world_body``.
        search_from_prior: with a DS pose prior (:meth:`DSPoseEstimator.estimate`'s
            ``T_world_ds_prior`` or ``T_cam_ds_prior``), detect first around the markers the
            prior projects into the image, the whole frame only when too few are found
            (:meth:`~uwdock.perception.detector.Detector.detect`'s ``predicted``). Off by
            default: the env's camera rows and the error model were measured with whole-frame
            detection.
    """

    level_ds: bool = True
    search_from_prior: bool = False


@dataclass(frozen=True)
class DSPoseEstimate:
    """The estimator's output for one image.

    Attributes:
        detections: markers found (sorted by ID).
        board: the unconstrained board solution, or None (too few markers, no solution).
        level: the level-DS solution (world frame), or None when not refined.
        T_world_cam: (4, 4) camera pose used for the refinement, or None.
        ms: detection + pose time (ms).
    """

    detections: list[Detection]
    board: BoardPose | None = None
    level: LevelBoardPose | None = None
    T_world_cam: np.ndarray | None = None
    ms: float = 0.0
    _cache: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def T_cam_ds(self) -> np.ndarray | None:
        """(4, 4) float64 DS pose in the OpenCV camera frame: the level solution when there is
        one, else the board's; None without a pose."""
        if self.level is not None:
            if "T_cam_ds" not in self._cache:
                self._cache["T_cam_ds"] = inv_T(self.T_world_cam) @ self.level.T_world_ds
            return self._cache["T_cam_ds"]
        return None if self.board is None else self.board.T_cam_ds

    @property
    def T_world_ds(self) -> np.ndarray | None:
        """(4, 4) float64 DS pose in the world (needs ``T_world_cam``); None without one."""
        if self.level is not None:
            return self.level.T_world_ds
        if self.board is None or self.T_world_cam is None:
            return None
        return self.T_world_cam @ self.board.T_cam_ds

    @property
    def covariance_xyzyaw(self) -> np.ndarray | None:
        """(4, 4) covariance of the level solution's [x, y, z (m), yaw (rad)] in the world, or
        None when not refined."""
        return None if self.level is None else self.level.covariance

    @property
    def reprojection_rms_px(self) -> float | None:
        """RMS corner reprojection error of the final pose (px), or None without a pose."""
        if self.level is not None:
            return self.level.reprojection_rms_px
        return None if self.board is None else self.board.reprojection_rms_px


class DSPoseEstimator:
    """Detector + board PnP + optional level-DS refinement (module docstring).

    Args:
        corners_ds: the board: marker ID -> (4, 3) corners TL, TR, BR, BL in the DS frame (m).
        detector_cfg: detector settings (its ``dictionary`` and ``ids`` are used as given; see
            :meth:`from_marker_set`).
        board_cfg: board PnP settings.
        pose_cfg: refinement settings.

    Raises:
        ConfigError: ``board_cfg.min_markers`` is more than the board's markers.
    """

    def __init__(
        self,
        corners_ds: dict[int, np.ndarray],
        detector_cfg: DetectorConfig | None = None,
        board_cfg: BoardPoseConfig | None = None,
        pose_cfg: DSPoseConfig | None = None,
    ) -> None:
        self.corners_ds = corners_ds
        self.detector = Detector(detector_cfg or DetectorConfig())
        self.board_cfg = validated(board_cfg or BoardPoseConfig())
        self.pose_cfg = validated(pose_cfg or DSPoseConfig())
        n = len(corners_ds)
        if n and self.board_cfg.min_markers > n:  # the config checked against its set
            ids = ", ".join(str(i) for i in sorted(corners_ds))
            raise ConfigError(
                f"board.min_markers: {self.board_cfg.min_markers} is more than the {n} markers "
                f"of the marker set (IDs {ids}): no frame could give a DS pose; use at most {n}"
            )

    @classmethod
    def from_marker_set(
        cls,
        marker_set: MarkerSet,
        detector_cfg: DetectorConfig | None = None,
        board_cfg: BoardPoseConfig | None = None,
        pose_cfg: DSPoseConfig | None = None,
    ) -> DSPoseEstimator:
        """The estimator of a marker set's board (dictionary and ID allow-list from the set)."""
        det = dataclasses.replace(
            detector_cfg or DetectorConfig(),
            dictionary=marker_set.dictionary,
            ids=tuple(marker_set.ids),
        )
        return cls(marker_set.corners_ds(), det, board_cfg, pose_cfg)

    def estimate(
        self,
        img_bgr: Any,
        camera: CameraModel,
        T_world_cam: ArrayLike | None = None,
        T_world_ds_prior: ArrayLike | None = None,
        T_cam_ds_prior: ArrayLike | None = None,
        compressed: bool | None = None,
    ) -> DSPoseEstimate:
        """Estimate the DS pose in one image.

        Args:
            img_bgr: (H, W, 3) BGR or (H, W) grey image (uint8, uint16 or float in [0, 1]).
            camera: the image's camera model (intrinsics and distortion, same size).
            T_world_cam: (4, 4) camera (OpenCV frame) pose in a z-down gravity-aligned world at
                the frame's time; enables the level-DS refinement (``pose_cfg.level_ds``) and
                :attr:`DSPoseEstimate.T_world_ds`.
            T_world_ds_prior: (4, 4) predicted DS pose in the same world (needs
                ``T_world_cam``), to resolve the coplanar-marker ambiguity (and, with
                ``pose_cfg.search_from_prior``, to search around the predicted markers first).
            T_cam_ds_prior: (4, 4) predicted DS pose in the camera frame (e.g. the previous
                video frame's estimate); used as ``T_world_ds_prior`` is, when that is not given.
            compressed: whether the frame was block-coded (``Detector.detect``'s): None
                measures it on the frame; True for a JPEG frame resized before it came here.

        Returns:
            The :class:`DSPoseEstimate`.
        """
        t0 = time.perf_counter()
        T_wc = None if T_world_cam is None else check_T(T_world_cam, "T_world_cam")
        prior = None
        if T_world_ds_prior is not None:
            if T_wc is None:
                raise ValueError("T_world_ds_prior: needs T_world_cam")
            prior = inv_T(T_wc) @ check_T(T_world_ds_prior, "T_world_ds_prior")
        elif T_cam_ds_prior is not None:
            prior = check_T(T_cam_ds_prior, "T_cam_ds_prior")
        predicted = None
        if prior is not None and self.pose_cfg.search_from_prior:
            predicted = self.predicted_corners(prior, camera)
        if compressed is None:  # the detector measures it (and a stand-in needs no such argument)
            dets = self.detector.detect(img_bgr, predicted)
        else:
            dets = self.detector.detect(img_bgr, predicted, compressed=compressed)
        board = level = None
        if dets:
            K, dist = camera.K, camera.dist_coeffs
            board = solve_board(dets, self.corners_ds, K, dist, self.board_cfg, prior)
            if board is not None and T_wc is not None and self.pose_cfg.level_ds:
                level = refine_level_board(board, dets, self.corners_ds, K, dist, T_wc)
        ms = (time.perf_counter() - t0) * 1e3
        return DSPoseEstimate(dets, board, level, T_wc, ms)

    def predicted_corners(
        self, T_cam_ds: np.ndarray, camera: CameraModel, min_depth_m: float = 0.05
    ) -> dict[int, np.ndarray]:
        """Marker ID -> (4, 2) pixel corners of the board seen from ``T_cam_ds`` (markers with a
        corner less than ``min_depth_m`` in front of the camera left out)."""
        out = {}
        R, t = T_cam_ds[:3, :3], T_cam_ds[:3, 3]
        for marker_id, corners in self.corners_ds.items():
            p = np.asarray(corners, dtype=np.float64) @ R.T + t
            if np.all(p[:, 2] > min_depth_m):
                out[int(marker_id)] = camera.project(p)
        return out
