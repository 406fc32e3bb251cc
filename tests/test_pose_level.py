"""Level-DS refinement: with the DS known level, few coplanar markers give a precise pose."""

from __future__ import annotations

import math

import cv2
import numpy as np

from uwdock.calibration.camera import reference_camera
from uwdock.calibration.frames import R_from_rpy, inv_T, make_T, rotation_angle_deg
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import marker_set_from_config
from uwdock.perception.pose import refine_level_board, solve_board


def test_level_refinement_beats_free_pnp_on_two_floor_markers():
    cam = reference_camera()
    board = marker_set_from_config(MarkerConfig()).corners_ds()
    floor = {i: board[i] for i in (15, 28)}  # two coplanar markers only
    rng = np.random.default_rng(0)
    T_world_ds = make_T(R_from_rpy(0, 0, 0.4), [1.0, -0.5, 5.0])
    free_pos, free_rot, lvl_pos, lvl_rot = [], [], [], []
    for _ in range(40):
        # camera about 1.8 m above the floor markers, looking down with a few degrees of tilt
        R_wc = R_from_rpy(*rng.uniform(-0.08, 0.08, 2), rng.uniform(-math.pi, math.pi))
        R_wc = R_wc @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])  # optical axis down
        p_c = T_world_ds[:3, 3] + [rng.uniform(-0.2, 0.2), 0.3 + rng.uniform(-0.2, 0.2), -2.0]
        T_world_cam = make_T(R_wc, p_c)
        T_cam_ds = inv_T(T_world_cam) @ T_world_ds
        dets = {}
        for i, c in floor.items():
            p = (T_cam_ds[:3, :3] @ c.T).T + T_cam_ds[:3, 3]
            px, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
            dets[i] = px.reshape(4, 2) + rng.normal(0, 0.5, (4, 2))
        pose = solve_board(dets, floor, cam.K, cam.dist_coeffs)
        assert pose is not None
        T_free = T_world_cam @ pose.T_cam_ds
        free_pos.append(np.linalg.norm(T_free[:3, 3] - T_world_ds[:3, 3]))
        free_rot.append(rotation_angle_deg(T_free[:3, :3], T_world_ds[:3, :3]))
        lv = refine_level_board(pose, dets, floor, cam.K, cam.dist_coeffs, T_world_cam)
        lvl_pos.append(np.linalg.norm(lv.T_world_ds[:3, 3] - T_world_ds[:3, 3]))
        lvl_rot.append(rotation_angle_deg(lv.T_world_ds[:3, :3], T_world_ds[:3, :3]))
        assert lv.covariance.shape == (4, 4) and np.all(np.diag(lv.covariance) > 0)
    assert np.median(lvl_pos) < 0.01 and np.median(lvl_rot) < 0.3
    assert max(lvl_rot) < 1.0
    assert np.median(lvl_rot) < np.median(free_rot) / 2
