"""The ``camera`` observation source: render -> underwater model -> 3DBM detector -> board PnP.

Each control step renders the downward camera at the vehicle's pose, applies the water model,
detects the markers, solves the docking-station pose from the board (the filter's prediction
breaks the two-fold ambiguity of coplanar markers) and turns it into a world-frame measurement
with the PnP covariance (inflated by a model-mismatch factor, floored). The DS is known to
stand level and the vehicle knows its roll and pitch, so the board pose is re-solved with the
DS's tilt fixed (x, y, z, yaw): with a few coplanar markers in view this removes errors of
several centimetres and degrees (see :func:`perception.pose.refine_level_board`).
"""

from __future__ import annotations

import numpy as np

from uwdock.calibration.frames import inv_T
from uwdock.perception.detector import Detector, DetectorConfig
from uwdock.perception.pose import BoardPoseConfig, refine_level_board, solve_board
from uwdock.rl.config import EnvConfig
from uwdock.rl.obs_sources import Measurement, SourceNeeds, StepContext
from uwdock.sim.water import apply_water, preset

#: PnP's first-order covariance is optimistic (corner bias, blur): scale it by this.
COVARIANCE_INFLATION = 4.0
#: Lower bounds of the measurement standard deviations: position (m), yaw (rad).
SIGMA_FLOOR_M = 0.01
SIGMA_FLOOR_YAW_RAD = 0.005


class CameraSource:
    """Measure the DS pose from the rendered camera image (module docstring)."""

    name = "camera"
    needs = SourceNeeds(camera=True, fusion=True, acoustic_fixes=True)

    def __init__(self, world, cfg: EnvConfig) -> None:
        if world.render_scene is None:
            raise ValueError("the camera source needs a world built with a camera")
        self.world = world
        rs = world.render_scene
        ms = rs.ds.marker_set
        self.board = ms.corners_ds()
        self.detector = Detector(DetectorConfig(dictionary=ms.dictionary, ids=tuple(ms.ids)))
        self.camera = rs.rig.camera
        self.T_body_cam = rs.rig.T_bodyfrd_camcv
        self.water = preset(cfg.water_preset)
        self.board_cfg = BoardPoseConfig()
        self.rng = np.random.default_rng(0)
        self.last_image: np.ndarray | None = None
        self.last_detections: list = []

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.last_image = None

    def measure(self, ctx: StepContext) -> Measurement | None:
        res = self.world.render()
        img = apply_water(res.rgb, res.range_m, self.water, self.rng)
        self.last_image = img
        m, self.last_detections = measure_from_image(
            img,
            self.detector,
            self.board,
            self.camera,
            ctx.T_world_body @ self.T_body_cam,
            ctx.T_world_ds_estimate,
            self.board_cfg,
        )
        return m


def measure_from_image(
    image: np.ndarray,
    detector: Detector,
    board: dict,
    camera,
    T_world_cam: np.ndarray,
    T_world_ds_prior: np.ndarray | None = None,
    board_cfg: BoardPoseConfig | None = None,
) -> tuple[Measurement | None, list]:
    """Detect the DS markers in ``image`` and turn the board pose into a world measurement.

    Shared by the simulated camera source and the deployment runner.

    Args:
        image: camera frame (BGR, grey or RGB; the default pipeline accepts any).
        detector: the 3DBM detector (its ID allow-list = the board's markers).
        board: ID -> (4, 3) marker corners in the DS frame (m).
        camera: the :class:`~calibration.camera.CameraModel` of ``image``.
        T_world_cam: (4, 4) camera pose (OpenCV frame) in the world at the frame's time.
        T_world_ds_prior: the filter's DS estimate, to resolve coplanar-marker ambiguity.
        board_cfg: PnP settings.

    Returns:
        (measurement or None, the detections).
    """
    dets = detector.detect(image)
    if not dets:
        return None, dets
    prior = None if T_world_ds_prior is None else inv_T(T_world_cam) @ T_world_ds_prior
    pose = solve_board(dets, board, camera.K, camera.dist_coeffs, board_cfg, T_cam_ds_prior=prior)
    if pose is None:
        return None, dets
    # the DS stands level and the vehicle knows its attitude: solve x, y, z, yaw only
    level = refine_level_board(pose, dets, board, camera.K, camera.dist_coeffs, T_world_cam)
    cov = COVARIANCE_INFLATION * level.covariance + np.diag(
        [SIGMA_FLOOR_M**2] * 3 + [SIGMA_FLOOR_YAW_RAD**2]
    )
    return Measurement(level.T_world_ds, cov, True), dets
