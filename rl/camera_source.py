"""The ``camera`` observation source: render -> underwater model -> 3DBM detector -> board PnP.

Each control step renders the downward camera at the vehicle's pose, applies the water model,
detects the markers, solves the docking-station pose from the board (the filter's prediction
breaks the two-fold ambiguity of coplanar markers) and turns it into a world-frame measurement
with the PnP covariance (inflated by a model-mismatch factor, floored).
"""

from __future__ import annotations

import numpy as np

from calibration.frames import inv_T
from perception.detector import Detector, DetectorConfig
from perception.pose import BoardPoseConfig, solve_board
from rl.config import EnvConfig
from rl.obs_sources import Measurement, StepContext
from sim.water import apply_water, preset

#: PnP's first-order covariance is optimistic (model mismatch, blur): scale it by this.
COVARIANCE_INFLATION = 4.0
#: Lower bounds of the measurement standard deviations: position (m), yaw (rad).
SIGMA_FLOOR_M = 0.01
SIGMA_FLOOR_YAW_RAD = 0.005


def measurement_covariance(
    T_world_cam: np.ndarray, cov_rt: np.ndarray, rotation_std_rad: float
) -> np.ndarray:
    """(4, 4) covariance of [x, y, z, yaw] of the DS in the world from PnP's (rvec, tvec) one.

    The DS origin is ``tvec`` in the camera frame, so its world covariance is the rotated
    translation block; yaw takes the rotation standard deviation.
    """
    R = T_world_cam[:3, :3]
    cov = np.zeros((4, 4))
    cov[:3, :3] = R @ (COVARIANCE_INFLATION * np.asarray(cov_rt)[3:, 3:]) @ R.T
    cov[:3, :3] += np.eye(3) * SIGMA_FLOOR_M**2
    cov[3, 3] = COVARIANCE_INFLATION * rotation_std_rad**2 + SIGMA_FLOOR_YAW_RAD**2
    return cov


class CameraSource:
    """Measure the DS pose from the rendered camera image (module docstring)."""

    name = "camera"

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
        dets = self.detector.detect(img)
        self.last_detections = dets
        if not dets:
            return None
        T_world_cam = ctx.T_world_body @ self.T_body_cam
        prior = None
        if ctx.T_world_ds_estimate is not None:
            prior = inv_T(T_world_cam) @ ctx.T_world_ds_estimate
        pose = solve_board(
            dets,
            self.board,
            self.camera.K,
            self.camera.dist_coeffs,
            self.board_cfg,
            T_cam_ds_prior=prior,
        )
        if pose is None:
            return None
        T_world_ds = T_world_cam @ pose.T_cam_ds
        cov_rt = pose.covariance
        if not np.all(np.isfinite(cov_rt)):  # no covariance: 2 % of the range, 3 degrees
            rng_m = float(np.linalg.norm(pose.T_cam_ds[:3, 3]))
            cov_rt = np.diag([np.deg2rad(3.0) ** 2] * 3 + [(0.02 * rng_m) ** 2] * 3)
        rot_std = float(np.sqrt(np.max(np.diag(cov_rt)[:3])))
        cov = measurement_covariance(T_world_cam, cov_rt, rot_std)
        return Measurement(T_world_ds, cov, True)
