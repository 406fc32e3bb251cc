"""Synthetic error-model files for the tests of the error-model source (with and without
memory): the same bias and covariance in every range bin, and a vehicle pose above the DS."""

from __future__ import annotations

import numpy as np

from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV, reference_camera
from uwdock.calibration.frames import make_T
from uwdock.dockcore.config import to_dict
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import marker_set_from_config
from uwdock.rl.env.error_model import FORMAT, VERSION, ErrorModelConfig
from uwdock.rl.env.task import DockingTaskConfig

N_BINS = 16
STEP_S = 0.2


def synthetic_model(
    p_detect: float,
    bias: np.ndarray,
    cov: np.ndarray,
    rho: list | None = None,
    version: int = VERSION,
    p_outlier: float = 0.0,
) -> dict:
    """A model dict with the same bias and covariance in every range bin (``rho``: its fitted
    memory, written as a version-2 file's ``ar1``)."""
    cam = reference_camera().scaled(640, 484)
    board = marker_set_from_config(MarkerConfig()).corners_ds()
    p = np.full((N_BINS, 4), p_detect)
    p[:, 0] = 0.0
    outliers = [[0.3, 0.0, 0.0, 0.5, 0.0, 0.0]] if p_outlier else []
    bins = [
        {
            "range_m": [k * 0.5, k * 0.5 + 0.5],
            "detections": 100,
            "pooled_inliers": 100,
            "bias": bias.tolist(),
            "cov": cov.tolist(),
            "p_outlier": p_outlier,
            "outliers": outliers,
        }
        for k in range(N_BINS)
    ]
    table = {"p_detect": p.tolist(), "frames": (p * 0 + 10).tolist(), "bins": bins}
    data = {
        "format": FORMAT,
        "version": version,
        "config": to_dict(ErrorModelConfig()),
        "camera": {**to_dict(cam), "T_body_cam": np.asarray(REFERENCE_T_BODYFRD_CAMCV).tolist()},
        "board_corners_ds_m": np.stack([board[i] for i in sorted(board)]).tolist(),
        "tables": {"all": table},
    }
    if rho is not None:
        data["sequences"] = {"sequences": 1, "frames": 10, "consecutive_pairs": 9, "step_s": STEP_S}
        table["ar1"] = {"rho": rho, "rho_ci95": None, "pairs": 100}
    return data


def above_ds(height_m: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """(T_world_ds, T_world_body): the vehicle ``height_m`` above its docked pose."""
    task = DockingTaskConfig()
    T_world_ds = make_T(t=[0.0, 0.0, 5.0])
    T_target = T_world_ds @ task.T_ds_target
    return T_world_ds, make_T(T_target[:3, :3], T_target[:3, 3] - [0.0, 0.0, height_m])
