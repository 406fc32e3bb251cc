"""Observation sources: how the DS pose is *measured* each control step.

Every source returns a :class:`Measurement` of ``T_world_ds`` with a covariance of
``[x, y, z, yaw]`` (or ``None`` when nothing is detected); the shared
:class:`rl.env.estimator.DSPoseFilter` turns measurements into the estimate the policy sees.

* ``proxy``: the paper's baseline: the reference visibility cone plus Gaussian noise with
  sigma_k = ||e|| / 6: N(0, (sigma/2)^2) always, plus N(0, sigma^2) when the DS is not visible
  (memoryless: used with a non-fusing filter, exactly as in the paper).
* ``error-model`` and ``camera``: see :mod:`rl.env.error_model` and :mod:`rl.env.camera_source`.
* ``acoustic``: no camera at all: the filter lives on the acoustic (USBL) fixes alone, the
  camera-off row of an ablation.

Each source class declares what it needs from the env in ``needs`` (:class:`SourceNeeds`); the
env reads that declaration and never asks a source for its name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from uwdock.calibration.frames import inv_T
from uwdock.perception.ds_pose import DSPoseEstimate
from uwdock.rl.env.task import DockingTaskConfig, docking_errors, ds_visible

#: PnP's first-order covariance is optimistic (corner bias, blur): scale it by this.
COVARIANCE_INFLATION = 4.0
#: Lower bounds of the measurement standard deviations: position (m), yaw (rad).
SIGMA_FLOOR_M = 0.01
SIGMA_FLOOR_YAW_RAD = 0.005
_COVARIANCE_FLOOR = np.diag([SIGMA_FLOOR_M**2] * 3 + [SIGMA_FLOOR_YAW_RAD**2])


@dataclass(frozen=True)
class Measurement:
    """One DS pose measurement.

    Attributes:
        T_world_ds: (4, 4) measured DS pose in the world (NED).
        cov_xyzyaw: (4, 4) covariance of x, y, z (m^2) and yaw (rad^2).
        detected: True when the camera (or its model) actually saw the DS; the paper's proxy
            always measures, with ``detected`` = its visibility test.
    """

    T_world_ds: np.ndarray
    cov_xyzyaw: np.ndarray
    detected: bool


@dataclass(frozen=True)
class SourceNeeds:
    """What an observation source needs from the env, declared once per source class.

    Attributes:
        camera: the world renders the onboard camera (the source measures in its frames).
        fusion: the DS pose filter fuses measurements over time; False makes every measurement
            replace the estimate (the paper's memoryless proxy), whatever ``estimator.fuse``
            says.
        acoustic_fixes: the env fuses the position-only acoustic (USBL) fixes of the DS that
            ``EnvConfig.usbl_model`` delivers (:mod:`uwdock.sim.usbl`).
        nav_frame: the source turns what it measures into the world with the vehicle's
            navigation pose (``StepContext.T_world_body_nav``), as the vehicle's software does
            (the camera: its DS-pose estimate takes the attitude from the AHRS). False: the
            source models the measurement with the true pose and the env moves it into the
            navigation frame (:func:`uwdock.sim.navigation.correction`).
    """

    camera: bool = False
    fusion: bool = True
    acoustic_fixes: bool = True
    nav_frame: bool = False


@dataclass(frozen=True)
class StepContext:
    """What a source may look at: the true poses (for models), the step time, the filter's
    current DS estimate (a prior for disambiguating the camera's PnP) and the vehicle's
    navigation pose (:mod:`uwdock.sim.navigation`; None: the true pose). The estimate lives in
    the navigation frame."""

    T_world_body: np.ndarray
    T_world_ds: np.ndarray
    time_s: float
    T_world_ds_estimate: np.ndarray | None = None
    T_world_body_nav: np.ndarray | None = None

    @property
    def T_world_body_believed(self) -> np.ndarray:
        """The pose the vehicle believes it has: the navigation pose, else the true one."""
        return self.T_world_body if self.T_world_body_nav is None else self.T_world_body_nav


def measurement(est: DSPoseEstimate) -> Measurement | None:
    """The filter's measurement from a level-DS estimate (None without one).

    Shared by the simulated camera source (:mod:`rl.env.camera_source`) and the vehicle's chain
    (:mod:`rl.deploy.runner`, :mod:`rl.deploy`): the world-frame
    ``T_world_ds`` with the fit's (4, 4) [x, y, z, yaw] covariance scaled by
    ``COVARIANCE_INFLATION`` and floored by ``SIGMA_FLOOR_M`` / ``SIGMA_FLOOR_YAW_RAD``.
    """
    if est.level is None:
        return None
    cov = COVARIANCE_INFLATION * est.level.covariance + _COVARIANCE_FLOOR
    return Measurement(est.level.T_world_ds, cov, True)


class ObservationSource(Protocol):
    name: str
    needs: SourceNeeds

    def reset(self, rng: np.random.Generator) -> None: ...

    def measure(self, ctx: StepContext) -> Measurement | None: ...


class ProxySource:
    """The paper's visibility proxy (module docstring)."""

    name = "proxy"
    #: the paper's proxy is memoryless and has no acoustic fixes
    needs = SourceNeeds(camera=False, fusion=False, acoustic_fixes=False)

    def __init__(self, task: DockingTaskConfig) -> None:
        self.task = task
        self.rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def measure(self, ctx: StepContext) -> Measurement:
        e_xyz, _ = docking_errors(ctx.T_world_body, ctx.T_world_ds, self.task)
        visible = ds_visible(inv_T(ctx.T_world_body) @ ctx.T_world_ds, self.task)
        sigma = float(np.linalg.norm(e_xyz)) / 6.0
        noise_body = self.rng.normal(0.0, sigma / 2.0, 3)
        var = (sigma / 2.0) ** 2
        if not visible:
            noise_body += self.rng.normal(0.0, sigma, 3)
            var += sigma**2
        T = ctx.T_world_ds.copy()
        # the error vector is in the body frame: its noise moves the DS along body axes
        T[:3, 3] += ctx.T_world_body[:3, :3] @ noise_body
        cov = np.diag([var, var, var, 1e-6])
        return Measurement(T, cov, visible)


class AcousticSource:
    """No camera and no model of one: every step measures nothing, so the DS estimate is the
    prior refined by the acoustic fixes alone (the camera-off ablation)."""

    name = "acoustic"
    needs = SourceNeeds(camera=False, fusion=True, acoustic_fixes=True)

    def reset(self, rng: np.random.Generator) -> None:
        """Nothing to draw: the source never measures."""

    def measure(self, ctx: StepContext) -> None:
        """No measurement (the acoustic fixes reach the filter through the env)."""
        return None
