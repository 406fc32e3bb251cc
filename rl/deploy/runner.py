"""Deployment: camera frames + odometry in, body wrench out, at 5 Hz (no ROS, no simulator).

:class:`DockingRunner` is the policy's path onto a vehicle: each control tick it takes the latest
downward-camera frame and the navigation solution (pose in a local NED frame, body velocities,
yaw rate, gravity-free acceleration), runs the same 3DBM detector, board PnP and DS filter as the
simulator's camera source, builds the same observation and runs the exported ONNX policy. A
USBL fix (or a surveyed DS position) can be fed in whenever one arrives.

Example::

    runner = DockingRunner("docking.onnx", camera_file="girona_cam.yaml")
    runner.reset(T_world_ds_prior)              # e.g. from the USBL / the mission plan
    while docking:
        wrench = runner.step(frame_bgr, Odometry(T_world_body, v, r, acc))
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import cv2
import numpy as np

from uwdock.calibration.camera import resolve_camera
from uwdock.dockcore.errors import DockError
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import load_marker_set, marker_set_from_config
from uwdock.perception.detector import DetectorConfig
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.estimator import DSPoseFilter
from uwdock.rl.env.obs_sources import measurement
from uwdock.rl.env.observation import (
    PRIVILEGED_DIM,
    ContactMemory,
    observation_frame,
    observation_size,
)
from uwdock.rl.env.rewards import DockingReward
from uwdock.rl.policy.env_settings import policy_training_env
from uwdock.rl.policy.policy_io import OnnxPolicy


@dataclass(frozen=True)
class Odometry:
    """The vehicle's navigation solution at a control tick.

    Attributes:
        T_world_body: (4, 4) body FRD pose in a local NED frame (m).
        velocity_frd_mps: (3,) body velocity (DVL) (m/s).
        yaw_rate_radps: yaw rate (rad/s).
        acceleration_frd_mps2: (3,) gravity-free acceleration (IMU) (m/s^2).
        specific_force_frd_mps2: (3,) the accelerometer's own output (gravity included, a
            level vehicle at rest reads (0, 0, -g)), for the contact sense (``obs_contact``);
            None: derived from ``acceleration_frd_mps2`` with the attitude of
            ``T_world_body``.
    """

    T_world_body: np.ndarray
    velocity_frd_mps: np.ndarray
    yaw_rate_radps: float
    acceleration_frd_mps2: np.ndarray
    specific_force_frd_mps2: np.ndarray | None = None


class DockingRunner:
    """Run a docking policy on real frames and odometry (module docstring).

    Args:
        policy: an exported ONNX policy (``rl export``) or any object with ``act(obs)``.
        camera_file: the camera YAML/JSON (intrinsics + ``T_body_cam``); None: the reference
            camera. Resolved as the simulated world resolves it
            (:func:`uwdock.calibration.camera.resolve_camera` at ``env_cfg.world.camera_width_px``):
            frames of the file's size are resized to that width before detection, so the
            policy sees the estimator it was trained with.
        marker_set: the DS marker set file; None: the reference DS set.
        env_cfg: the environment the policy was trained in (observation layout, limits, filter,
            camera width, USBL); None: the training env stored beside an exported policy
            (``rl export``'s .json; an older .json holds only the observation layout and
            limits, the rest is the EnvConfig defaults).
        detector: the 3DBM detector's settings; None: the defaults (3DBMs and flat markers).
            The simulator's camera source uses :func:`rendered_3dbm_config` (3DBMs only).
    """

    def __init__(
        self,
        policy,
        camera_file: str | os.PathLike[str] | None = None,
        marker_set: str | os.PathLike[str] | None = None,
        env_cfg: EnvConfig | None = None,
        detector: DetectorConfig | None = None,
    ) -> None:
        #: the file the env settings came from (an exported policy's .json), None: given/defaults
        self.env_from: str | None = None
        if env_cfg is None:  # an exported policy carries the env it was trained in
            exported = isinstance(policy, (str, os.PathLike))
            trained = policy_training_env(str(policy)) if exported else None
            env_cfg = trained.cfg if trained is not None else EnvConfig()
            self.env_from = trained.policy_config if trained is not None else None
        self.cfg = env_cfg
        self.policy = OnnxPolicy(policy) if isinstance(policy, (str, os.PathLike)) else policy
        self.camera, self.T_body_cam = resolve_camera(camera_file, self.cfg.world.camera_width_px)
        ms = (
            load_marker_set(marker_set)
            if marker_set is not None
            else marker_set_from_config(MarkerConfig())
        )
        self.estimator = DSPoseEstimator.from_marker_set(ms, detector)
        self.limits = self.cfg.action_limits
        self.dt_s = 1.0 / self.cfg.control_hz
        self.filter = DSPoseFilter(self.cfg.estimator)
        self.prev_action = np.zeros(6)
        self.detected = False
        self.last_measurement = None
        self.last_detections: list = []
        self._frames: list[np.ndarray] = []
        # obs_contact: the env's collision detector on the accelerometer, and the rest time
        self._collisions = DockingReward(self.cfg.reward, actuated=np.ones(6, dtype=bool))
        self.gravity_mps2 = self.cfg.world.vehicle.gravity_mps2
        self._prev_sf: np.ndarray | None = None
        self.contact = ContactMemory(1, self.dt_s)

    def reset(
        self,
        T_world_ds_prior: np.ndarray,
        sigma_xy_m: float | None = None,
        var_xyzyaw: np.ndarray | None = None,
    ) -> None:
        """Start a docking run from a prior DS pose (USBL / survey), no motion yet: with the
        filter's prior uncertainty, ``sigma_xy_m`` horizontally, or the variances
        ``var_xyzyaw`` (m^2, m^2, m^2, rad^2) as a mission message carries them."""
        if var_xyzyaw is not None:
            self.filter.set_prior_variances(T_world_ds_prior, var_xyzyaw)
        else:
            self.filter.set_prior(T_world_ds_prior, sigma_xy_m)
        self.prev_action = np.zeros(6)
        self.detected = False
        self._frames = []
        self._collisions.reset()
        self._prev_sf = None
        self.contact.reset()

    def usbl_fix(self, p_world_ds_m: np.ndarray, sigma_m: float) -> None:
        """Fuse an acoustic position fix of the DS (world NED, m; ``sigma_m`` per axis)."""
        self.filter.update_position(p_world_ds_m, sigma_m)

    def frame_for_camera(self, img_bgr: np.ndarray) -> np.ndarray:
        """``img_bgr`` at the resolved camera's size: resized (area averaging) when it has the
        same aspect ratio at another size, as the simulated camera renders it.

        Raises:
            DockError: a frame of another aspect ratio (another camera or a crop).
        """
        h, w = img_bgr.shape[:2]
        cam = self.camera
        if (w, h) == (cam.width_px, cam.height_px):
            return img_bgr
        if abs((w / h) / (cam.width_px / cam.height_px) - 1.0) > 0.01:
            raise DockError(
                f"frame is {w}x{h} but the camera is {cam.width_px}x{cam.height_px} "
                "(another aspect ratio)"
            )
        size = (cam.width_px, cam.height_px)
        return cv2.resize(img_bgr, size, interpolation=cv2.INTER_AREA)

    def observe(
        self,
        img_bgr: np.ndarray | None,
        odom: Odometry,
        predict: bool = True,
        T_world_body_frame: np.ndarray | None = None,
        moved: bool | None = None,
        compressed: bool | None = None,
    ) -> np.ndarray:
        """Update the DS estimate from a BGR frame and return the policy's observation.

        ``predict``: grow the filter's uncertainty over one control period first (False: the
        caller did, or the run has just started). ``T_world_body_frame``: the navigation pose
        at the frame's own stamp (the vehicle node's navigation buffer), None: ``odom``'s.
        ``moved``: a control period has passed since the last call (the contact sense compares
        accelerometer readings across it); None: ``predict``. ``compressed``: the frame was
        JPEG-coded (a ``CompressedImage``; the detector's extra views then run even when the
        resize to the policy's width has blurred the block grid away); None: the detector
        measures it. The measurement made is kept in :attr:`last_measurement` (None without
        one)."""
        if predict:
            self.filter.predict(self.dt_s)
        self.detected = False
        self.last_measurement = None
        if img_bgr is not None:
            T_frame = odom.T_world_body if T_world_body_frame is None else T_world_body_frame
            est = self.estimator.estimate(
                self.frame_for_camera(img_bgr),
                self.camera,
                T_frame @ self.T_body_cam,
                self.filter.T_world_ds,
                compressed=compressed,
            )
            self.last_detections = est.detections
            m = self.last_measurement = measurement(est)
            if m is not None:
                self.filter.update(m.T_world_ds, m.cov_xyzyaw)
                self.detected = True
        if self.cfg.obs_contact:
            self._sense_contact(odom, moved=predict if moved is None else moved)
        frame = observation_frame(
            self.cfg,
            odom.T_world_body,
            self.filter,
            odom.velocity_frd_mps,
            odom.yaw_rate_radps,
            odom.acceleration_frd_mps2,
            self.prev_action,
            self.detected,
            self.contact.features()[0] if self.cfg.obs_contact else None,
        )
        if not self._frames:
            self._frames = [frame] * self.cfg.obs_frames
        else:
            self._frames = [*self._frames[1:], frame]
        if self.cfg.obs_privileged:  # the critic's block: never filled on a vehicle
            return np.concatenate([*self._frames, np.zeros(PRIVILEGED_DIM, np.float32)])
        return np.concatenate(self._frames)

    def _sense_contact(self, odom: Odometry, moved: bool) -> None:
        """``obs_contact``: the accelerometer's specific force (given, or the odometry's
        gravity-free acceleration minus gravity in the body frame), the env's collision test
        on its jump, and the rest time from the DVL velocity; a first tick (or ``moved``
        False) only remembers the specific force."""
        if odom.specific_force_frd_mps2 is not None:
            sf = np.asarray(odom.specific_force_frd_mps2, dtype=np.float64)
        else:
            R = np.asarray(odom.T_world_body, dtype=np.float64)[:3, :3]
            g_body = R.T @ np.array([0.0, 0.0, self.gravity_mps2])
            sf = np.asarray(odom.acceleration_frd_mps2, dtype=np.float64) - g_body
        if self._prev_sf is not None and moved:
            hit = self._collisions.collision(sf, self._prev_sf)
            self.contact.update([hit], odom.velocity_frd_mps)
        self._prev_sf = sf

    def step(self, img_bgr: np.ndarray | None, odom: Odometry) -> np.ndarray:
        """One 5 Hz tick on a BGR frame: returns the body wrench (6,) [N, N m] to send to the
        allocator."""
        return self.act(self.observe(img_bgr, odom))

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The policy's body wrench (6,) [N, N m] for an observation of :meth:`observe`, its
        action clipped to [-1, 1] and scaled by the limits as the env scales it.

        Raises:
            ValueError: an observation of another layout, or a policy output that is not
                finite (the caller holds; the previous action is kept).
        """
        if obs.shape[0] != observation_size(self.cfg):
            raise ValueError("observation layout does not match the environment config")
        raw = np.asarray(self.policy.act(obs), dtype=np.float64)
        if raw.shape != (6,) or not np.all(np.isfinite(raw)):
            raise ValueError(f"the policy's action is not 6 finite numbers: {raw.tolist()}")
        action = np.clip(raw, -1.0, 1.0)
        self.prev_action = action
        return action * self.limits
