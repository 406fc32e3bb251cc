"""The simulated downward camera: resolved once, captured as render + water, frames that name
their channel order.

* Resolution: a camera is (camera file or the reference camera, render width, mounting
  ``T_body_cam``); :func:`uwdock.calibration.camera.resolve_camera` is the one place that turns
  those into a model (perception needs it too, so it lives in ``calibration``).
* :meth:`SimCamera.capture` renders the scene from a vehicle pose and applies the water model
  (:func:`uwdock.sim.water.apply_water`); every simulated camera image (the env's camera source,
  the labelled datasets, the episode videos, the benchmarks) is made here.
* :class:`Frame`: the renderer's channel order is RGB (``img_rgb``); perception's contract is
  OpenCV's BGR: :meth:`Frame.img_bgr` is the one conversion at the sim -> perception seam.

Example:
    >>> cam = SimCamera(render_scene.rig, water=PRESETS["coastal"])
    >>> frame = cam.capture(T_world_body, rng)
    >>> estimate = estimator.estimate(frame.img_bgr(), cam.model)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike

from uwdock.calibration.camera import CameraModel
from uwdock.sim.render import CameraRig, RenderResult
from uwdock.sim.water import WaterConfig, apply_water
from uwdock.sim.water_torch import apply_water_torch

__all__ = ["Frame", "SimCamera", "render_cuda_device"]

#: Keep the current water of a :class:`SimCamera` (``capture(..., water=KEEP)``).
KEEP: Literal["keep"] = "keep"


@dataclass(frozen=True)
class Frame:
    """One simulated camera frame (water applied when the camera has water).

    Attributes:
        img_rgb: (H, W, 3) uint8 image in RGB channel order (the renderer's).
        range_m: (H, W) float32 range along each pixel's ray (m); ``inf`` where nothing was hit.
        T_world_cam: (4, 4) float64 pose of the OpenCV camera frame in world NED.
        camera: the camera model the image follows.
        channels: the channel order of ``img_rgb`` ("RGB"), for code that checks it.
    """

    img_rgb: np.ndarray
    range_m: np.ndarray
    T_world_cam: np.ndarray
    camera: CameraModel
    channels: Literal["RGB"] = "RGB"

    def img_bgr(self) -> np.ndarray:
        """(H, W, 3) uint8 image in OpenCV's BGR order (a new array): perception's input."""
        return cv2.cvtColor(self.img_rgb, cv2.COLOR_RGB2BGR)


def render_cuda_device(rig: CameraRig) -> str | None:
    """The torch device of the CUDA GPU the rig's scene renders on (``"cuda:N"``), or None
    where SAPIEN renders without one (lavapipe on the CPU, a GPU CUDA cannot see) or torch has
    no CUDA: the water then stays with numpy on the CPU, next to the picture."""
    device = rig.entity.scene.render_system.device
    if not device.is_cuda() or device.cuda_id < 0:
        return None
    import torch  # only where SAPIEN renders on a CUDA GPU

    return f"cuda:{device.cuda_id}" if torch.cuda.is_available() else None


class SimCamera:
    """A camera rig of a render scene plus the water between it and the scene.

    Args:
        rig: the SAPIEN camera (:class:`uwdock.sim.render.CameraRig`), posed by the vehicle.
        water: water and sensor model applied to each capture; None: the image in air.
        water_device: None applies the water with numpy/OpenCV (:func:`sim.water.apply_water`);
            a torch device ("cuda", "cpu") with torch there
            (:func:`sim.water_torch.apply_water_torch`, the same image within one grey level);
            "auto": :func:`render_cuda_device` (the renderer's GPU, or None).
    """

    def __init__(
        self, rig: CameraRig, water: WaterConfig | None = None, water_device: str | None = None
    ) -> None:
        self.rig = rig
        self.water = water
        self.water_device = render_cuda_device(rig) if water_device == "auto" else water_device

    @property
    def model(self) -> CameraModel:
        """The camera model of the captured images."""
        return self.rig.camera

    @property
    def T_body_cam(self) -> np.ndarray:
        """(4, 4) float64 camera mounting ``T_bodyfrd_camcv``."""
        return self.rig.T_bodyfrd_camcv

    def render(self, T_world_body: ArrayLike) -> RenderResult:
        """Render in air (no water) from a vehicle pose (body FRD in world NED)."""
        return self.rig.render(T_world_body)

    def capture(
        self,
        T_world_body: ArrayLike,
        rng: np.random.Generator | None = None,
        water: WaterConfig | Literal["keep"] | None = KEEP,
    ) -> Frame:
        """Render from a vehicle pose and apply the water model.

        Args:
            T_world_body: (4, 4) vehicle pose, body FRD in world NED (m).
            rng: generator for the sensor noise (required when the water has noise).
            water: this frame's water instead of the camera's (None: in air).

        Returns:
            The :class:`Frame` (RGB; :meth:`Frame.img_bgr` for perception).
        """
        return self.through_water(self.rig.render(T_world_body), rng, water)

    def through_water(
        self,
        res: RenderResult,
        rng: np.random.Generator | None = None,
        water: WaterConfig | Literal["keep"] | None = KEEP,
    ) -> Frame:
        """The frame of a render already taken, with the water applied: one render seen through
        several waters (e.g. the tank report) takes the same path as :meth:`capture`.

        Args:
            res: a render of this camera's rig (in air).
            rng: generator for the sensor noise (required when the water has noise).
            water: the water instead of the camera's (None: in air).
        """
        w = self.water if water is KEEP else water
        if w is None:
            img = res.rgb
        elif self.water_device is None:
            img = apply_water(res.radiance, res.range_m, w, rng)
        else:
            img = apply_water_torch(res.radiance, res.range_m, w, rng, device=self.water_device)
        return Frame(img, res.range_m, res.T_worldned_camcv, res.camera)
