"""The observation vector, built in one place for the env and the deployment runner.

Layout of one frame (float32, every entry clipped to +-``OBS_BOUND``)::

    [e_x, e_y, e_z] / 5 m (clipped to +-5 m first), e_psi / pi,
    v_x, v_y, v_z (m/s), omega_psi (rad/s), acc_x, acc_y, acc_z / 5 (m/s^2, gravity removed),
    + the previous action (6)                         if ``obs_last_action``
    + [sigma_xy (m, <= 2), detected (0/1)]             if ``obs_uncertainty``

e is the docking point relative to the AUV in the body frame, from the *estimated* DS pose.

With ``obs_privileged`` (asymmetric actor-critic), :data:`PRIVILEGED_DIM` values follow the
stacked frames, for the critic only: the true error ``[e_x, e_y, e_z] / 5 m``, ``e_psi / pi``,
the estimate's error ``(e_hat - e_true) / 5 m`` (3), the share of the episode left and the
share of the strict hold done. Only the training envs fill them
(``DockingEnv(privileged=True)``); every other env, ``rl eval`` and the deployment runner give
zeros there, and the actor of :class:`rl.asymmetric.AsymmetricPolicy` never reads them.
"""

from __future__ import annotations

import math

import numpy as np

from uwdock.rl.config import EnvConfig
from uwdock.rl.estimator import DSPoseFilter
from uwdock.rl.task import docking_errors

POS_SCALE_M = 5.0
ACC_SCALE_MPS2 = 5.0
OBS_BOUND = 5.0
BASE_OBS_DIM = 11
PRIVILEGED_DIM = 9


def frame_dim(cfg: EnvConfig) -> int:
    """Length of one observation frame for ``cfg``."""
    return BASE_OBS_DIM + (6 if cfg.obs_last_action else 0) + (2 if cfg.obs_uncertainty else 0)


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
) -> np.ndarray:
    """One observation frame (module docstring) from navigation data and the DS filter."""
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
    return np.clip(np.concatenate(parts), -OBS_BOUND, OBS_BOUND).astype(np.float32)
