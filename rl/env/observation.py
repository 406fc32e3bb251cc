"""The observation vector, built in one place for the env and the deployment runner.

Layout of one frame (float32, every entry clipped to +-``OBS_BOUND``)::

    [e_x, e_y, e_z] / 5 m (clipped to +-5 m first), e_psi / pi,
    v_x, v_y, v_z (m/s), omega_psi (rad/s), acc_x, acc_y, acc_z / 5 (m/s^2, gravity removed),
    + the previous action (6)                         if ``obs_last_action``
    + [sigma_xy (m, <= 2), detected (0/1)]             if ``obs_uncertainty``
    + [collision trace, rest share]                     if ``obs_contact``
    + tanh([e_x, e_y, e_z] / 0.1 m)                     if ``obs_fine_error``

e is the docking point relative to the AUV in the body frame, from the *estimated* DS pose.
The contact values (:class:`ContactMemory`) are what a vehicle can tell of its own contacts:
the IMU's collision detector (the reward's: a jump of the specific force above an adaptive
threshold) as a trace that is 1 at a detected collision and decays with
:data:`CONTACT_TAU_S`, and how long the DVL's speed has stayed below :data:`REST_SPEED_MPS`, as
a share of :data:`REST_FULL_S` (a vehicle resting on the station, seated or not, or pushing
against its frame).

The fine error (``obs_fine_error``) is the same estimated error again, squashed at
:data:`FINE_ERROR_SCALE_M`: the first entries scale it by 5 m so that the approach from metres
away fits the bound, which leaves the seat's last centimetres as a few hundredths of the
observation (the strict test's 5 cm is 0.01 there), while tanh(e / 0.1 m) is 0.46 at 5 cm and
saturates to +-1 beyond a few decimetres.

With ``obs_privileged`` (asymmetric actor-critic), :data:`PRIVILEGED_DIM` values follow the
stacked frames, for the critic only: the true error ``[e_x, e_y, e_z] / 5 m``, ``e_psi / pi``,
the estimate's error ``(e_hat - e_true) / 5 m`` (3), the share of the episode left and the
share of the strict hold done. Only the training envs fill them
(``DockingEnv(privileged=True)``); every other env, ``rl eval`` and the deployment runner give
zeros there, and the actor of :class:`rl.policy.asymmetric.AsymmetricPolicy` never reads them.
"""

from __future__ import annotations

import math

import numpy as np

from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.estimator import DSPoseFilter
from uwdock.rl.env.task import docking_errors

POS_SCALE_M = 5.0
ACC_SCALE_MPS2 = 5.0
OBS_BOUND = 5.0
BASE_OBS_DIM = 11
PRIVILEGED_DIM = 9
#: ``obs_contact``: the collision trace's time constant (s), the speed below which the vehicle
#: counts as at rest (m/s: the DVL's noise, 0.01 m/s per axis, crosses 0.03 in ~3 % of the
#: steps of a vehicle at rest, 0.05 almost never), and the rest time at which the rest share
#: reaches 1 (s).
CONTACT_TAU_S = 1.0
REST_SPEED_MPS = 0.05
REST_FULL_S = 5.0
#: ``obs_fine_error``: the length at which tanh squashes the fine error (m).
FINE_ERROR_SCALE_M = 0.1


def frame_dim(cfg: EnvConfig) -> int:
    """Length of one observation frame for ``cfg``."""
    return (
        BASE_OBS_DIM
        + (6 if cfg.obs_last_action else 0)
        + (2 if cfg.obs_uncertainty else 0)
        + (2 if cfg.obs_contact else 0)
        + (3 if cfg.obs_fine_error else 0)
    )


def actor_observation_size(cfg: EnvConfig) -> int:
    """Length of what the actor reads: ``obs_frames`` frames (no privileged block)."""
    return frame_dim(cfg) * cfg.obs_frames


def observation_size(cfg: EnvConfig) -> int:
    """Length of the whole observation for ``cfg`` (frames, then the privileged block)."""
    return actor_observation_size(cfg) + (PRIVILEGED_DIM if cfg.obs_privileged else 0)


def privileged_block(
    e_true: np.ndarray,
    psi_true: float,
    e_hat: np.ndarray,
    time_left: float,
    hold_done: float,
) -> np.ndarray:
    """The critic's privileged values (module docstring), float32, clipped to +-OBS_BOUND."""
    parts = [
        np.clip(e_true, -POS_SCALE_M, POS_SCALE_M) / POS_SCALE_M,
        [psi_true / math.pi],
        np.clip(np.asarray(e_hat) - e_true, -POS_SCALE_M, POS_SCALE_M) / POS_SCALE_M,
        [time_left, hold_done],
    ]
    return np.clip(np.concatenate(parts), -OBS_BOUND, OBS_BOUND).astype(np.float32)


def observation_frame(
    cfg: EnvConfig,
    T_world_body: np.ndarray,
    ds_filter: DSPoseFilter,
    velocity_frd_mps: np.ndarray,
    yaw_rate_radps: float,
    acceleration_frd_mps2: np.ndarray,
    prev_action: np.ndarray,
    detected: bool,
    contact: np.ndarray | None = None,
) -> np.ndarray:
    """One observation frame (module docstring) from navigation data and the DS filter;
    ``contact``: :meth:`ContactMemory.features` of this vehicle (2,), for ``obs_contact``."""
    e_hat, psi_hat = docking_errors(T_world_body, ds_filter.T_world_ds, cfg.task)
    parts = [
        np.clip(e_hat, -POS_SCALE_M, POS_SCALE_M) / POS_SCALE_M,
        [psi_hat / math.pi],
        velocity_frd_mps,
        [yaw_rate_radps],
        np.asarray(acceleration_frd_mps2) / ACC_SCALE_MPS2,
    ]
    if cfg.obs_last_action:
        parts.append(prev_action)
    if cfg.obs_uncertainty:
        P = ds_filter.P
        sigma_xy = float(np.sqrt(0.5 * (P[0, 0] + P[1, 1])))
        parts.append([min(sigma_xy, 2.0), float(detected)])
    if cfg.obs_contact:
        if contact is None:
            raise ValueError("obs_contact: the frame needs the contact values")
        parts.append(np.asarray(contact, dtype=np.float64).reshape(2))
    if cfg.obs_fine_error:
        parts.append(np.tanh(np.asarray(e_hat, dtype=np.float64) / FINE_ERROR_SCALE_M))
    return np.clip(np.concatenate(parts), -OBS_BOUND, OBS_BOUND).astype(np.float32)


class ContactMemory:
    """The ``obs_contact`` values of ``n`` vehicles (module docstring), stepped at ``dt_s``."""

    def __init__(self, n: int, dt_s: float) -> None:
        self.trace = np.zeros(n)
        self.rest = np.zeros(n)
        self.decay = math.exp(-float(dt_s) / CONTACT_TAU_S)
        self.rest_step = float(dt_s) / REST_FULL_S

    def reset(self, i: int | None = None) -> None:
        """Forget vehicle ``i``'s contacts (all vehicles: None)."""
        sl = slice(None) if i is None else i
        self.trace[sl] = 0.0
        self.rest[sl] = 0.0

    def update(self, collided: np.ndarray, velocity_frd_mps: np.ndarray) -> np.ndarray:
        """One control step: this step's detected collisions (n,) and DVL velocities (n, 3);
        returns :meth:`features`."""
        hit = np.asarray(collided, dtype=bool).reshape(-1)
        self.trace = np.where(hit, 1.0, self.trace * self.decay)
        speed = np.linalg.norm(
            np.asarray(velocity_frd_mps, dtype=np.float64).reshape(-1, 3), axis=1
        )
        self.rest = np.where(
            speed < REST_SPEED_MPS, np.minimum(self.rest + self.rest_step, 1.0), 0.0
        )
        return self.features()

    def features(self) -> np.ndarray:
        """(n, 2): the collision trace and the rest share of every vehicle."""
        return np.stack([self.trace, self.rest], axis=1)
