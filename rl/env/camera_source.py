"""The ``camera`` observation source: capture (render + water) -> DS-pose estimator -> filter.

Each control step captures the downward camera at the vehicle's pose through the water
(:meth:`uwdock.sim.world.DockingWorld.capture`), converts the RGB frame to perception's BGR once
(:meth:`uwdock.sim.camera.Frame.img_bgr`, the sim -> perception seam) and runs the one DS-pose
estimator (:class:`uwdock.perception.ds_pose.DSPoseEstimator`): detector, board PnP (the filter's
estimate breaks the two-fold ambiguity of coplanar markers) and, since the DS stands level and
the vehicle knows its roll and pitch, the level-DS re-solve (x, y, z, yaw). The result becomes a
world-frame measurement with the fit's covariance (inflated by a model-mismatch factor, floored:
:func:`uwdock.rl.env.obs_sources.measurement`, shared with the vehicle node).
"""

from __future__ import annotations

import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.perception.detector import Detection, rendered_3dbm_config
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.rl.env.obs_sources import Measurement, SourceNeeds, StepContext, measurement
from uwdock.sim.camera import Frame


class CameraSource:
    """Measure the DS pose from the captured camera frame (module docstring).

    Args:
        world: a :class:`uwdock.sim.world.DockingWorld` built with a camera.
    """

    name = "camera"
    needs = SourceNeeds(camera=True, fusion=True, acoustic_fixes=True, nav_frame=True)

    def __init__(self, world) -> None:
        if world.camera is None:
            raise ValueError("the camera source needs a world built with a camera")
        self.world = world
        self.estimator = DSPoseEstimator.from_marker_set(
            world.ds.marker_set, rendered_3dbm_config()
        )
        self.camera: CameraModel = world.camera.model
        self.T_body_cam = world.camera.T_body_cam
        self.rng = np.random.default_rng(0)
        self.last_frame: Frame | None = None
        self.last_detections: list[Detection] = []

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.last_frame = None

    def measure(self, ctx: StepContext) -> Measurement | None:
        frame = self.world.capture(self.rng, ctx.T_world_body)  # the true camera mounting
        return self.measure_frame(frame, ctx)

    def measure_frame(self, frame: Frame, ctx: StepContext) -> Measurement | None:
        """The measurement from one captured frame (RGB; converted to BGR here, once), in the
        navigation frame: the estimate uses the camera pose the vehicle believes it has."""
        self.last_frame = frame
        est = self.estimator.estimate(
            frame.img_bgr(),
            self.camera,
            ctx.T_world_body_believed @ self.T_body_cam,
            ctx.T_world_ds_estimate,
        )
        self.last_detections = est.detections
        return measurement(est)
