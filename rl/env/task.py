"""The docking task: target pose, error vector, visibility test, success criteria, spawn ranges.

Frames: world = NED, body = FRD, ds = docking station (x forward, y starboard, z down, origin on
the DS floor). The **docking target** is the body pose of a docked AUV in the DS frame: its origin
``dock_height_m`` above the DS origin, yawed ``dock_yaw_deg`` to the DS (reference: 0.91 m, 90 deg),
which puts the four pegs in the notches of the X-guides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Annotated

import numpy as np

from uwdock.calibration.frames import R_from_rpy, inv_T, make_T, rpy_from_R, wrap_angle_rad
from uwdock.dockcore.domains import Interval

_Tolerance = Annotated[float, Interval(gt=0, le=10)]  # m
_HalfAngle = Annotated[float, Interval(gt=0, lt=90)]  # deg
_Coord = Annotated[float, Interval(ge=-10, le=10)]  # m, on the vehicle or the DS
_Point = tuple[_Coord, _Coord, _Coord]


@dataclass(frozen=True)
class DockingTaskConfig:
    """Geometry and criteria of the docking task (docs/reference-system.md sections 1, 2 and 4).

    Attributes:
        dock_height_m: AUV origin above the DS origin when docked (m).
        dock_yaw_deg: AUV yaw relative to the DS when docked (deg).
        success_xy_m: paper criterion, |e_x| and |e_y| below this (m).
        success_z_m: paper criterion, |e_z| below this (m) (the end of the reference curriculum).
        success_yaw_deg: paper criterion, |e_psi| below this (deg).
        success_requires_visible: paper criterion also asks the DS to be visible.
        strict_peg_xy_m: strict criterion, each peg within this of its notch, horizontally (m).
        strict_peg_z_m: strict criterion, each peg within this of its seated height (m).
        strict_hold_s: strict criterion, both of the above held this long (s).
        visibility_range_m: proxy visibility: DS within this distance below the AUV (m).
        visibility_half_angles_deg: proxy visibility: elliptic cone half-angles about body +z,
            along body x and body y (deg).
        peg_positions_body_m: the four docking pegs in the body frame (m).
        notch_positions_ds_m: the four notch seats in the DS frame, where the pegs rest (m).
    """

    dock_height_m: Annotated[float, Interval(gt=0, le=10)] = 0.91
    dock_yaw_deg: Annotated[float, Interval(ge=-180, le=180)] = 90.0
    success_xy_m: _Tolerance = 0.07
    success_z_m: _Tolerance = 0.10
    success_yaw_deg: Annotated[float, Interval(gt=0, le=180)] = 10.0
    success_requires_visible: bool = True
    strict_peg_xy_m: _Tolerance = 0.05
    strict_peg_z_m: _Tolerance = 0.04
    strict_hold_s: Annotated[float, Interval(gt=0, le=60)] = 1.0
    visibility_range_m: Annotated[float, Interval(gt=0, le=100)] = 5.0
    visibility_half_angles_deg: tuple[_HalfAngle, _HalfAngle] = (31.0, 38.7)
    peg_positions_body_m: tuple[_Point, ...] = (
        (0.42, 0.57, -0.195),
        (0.42, -0.57, -0.195),
        (-0.42, 0.57, -0.195),
        (-0.42, -0.57, -0.195),
    )
    notch_positions_ds_m: tuple[_Point, ...] = (
        (-0.57, 0.425, -1.105),
        (0.57, 0.425, -1.105),
        (-0.57, -0.425, -1.105),
        (0.57, -0.425, -1.105),
    )

    def validate(self) -> None:
        if len(self.peg_positions_body_m) != len(self.notch_positions_ds_m):
            raise ValueError(
                f"notch_positions_ds_m: {len(self.notch_positions_ds_m)} notches for "
                f"{len(self.peg_positions_body_m)} pegs"
            )
        if not self.peg_positions_body_m:
            raise ValueError("peg_positions_body_m: needs at least one peg")

    @cached_property
    def T_ds_target(self) -> np.ndarray:
        """(4, 4) body pose of a docked AUV in the DS frame (do not modify in place)."""
        return make_T(
            R_from_rpy(0.0, 0.0, math.radians(self.dock_yaw_deg)), [0.0, 0.0, -self.dock_height_m]
        )


def yaw_of(T: np.ndarray) -> float:
    """Yaw (rad, ZYX convention) of the rotation of a 4x4 pose (``rpy_from_R``'s yaw, computed
    alone: this runs several times per env step). ``math.atan2``: the same bits as NumPy's
    ``arctan2`` on some CPUs, within one unit in the last place where NumPy uses its AVX-512
    kernels."""
    if math.hypot(T[2, 1], T[2, 2]) < 1e-9:  # gimbal lock: rpy_from_R's convention
        return rpy_from_R(T[:3, :3])[2]
    return math.atan2(T[1, 0], T[0, 0])


def docking_errors(
    T_world_body: np.ndarray, T_world_ds: np.ndarray, cfg: DockingTaskConfig
) -> tuple[np.ndarray, float]:
    """The paper's error: the docking target relative to the AUV.

    Returns:
        e_xyz_m: (3,) target position in the body frame (m).
        e_psi_rad: target yaw minus AUV yaw, wrapped to [-pi, pi) (rad).
    """
    T_world_target = T_world_ds @ cfg.T_ds_target
    e_xyz = (inv_T(T_world_body) @ np.append(T_world_target[:3, 3], 1.0))[:3]
    e_psi = float(wrap_angle_rad(yaw_of(T_world_target) - yaw_of(T_world_body)))
    return e_xyz, e_psi


def ds_visible(T_body_ds: np.ndarray, cfg: DockingTaskConfig) -> bool:
    """Reference visibility test: DS origin below the AUV, in range, inside the elliptic cone."""
    p = T_body_ds[:3, 3]
    if p[2] <= 0 or np.linalg.norm(p) > cfg.visibility_range_m:
        return False
    ax, ay = (math.tan(math.radians(a)) for a in cfg.visibility_half_angles_deg)
    return bool((p[0] / (p[2] * ax)) ** 2 + (p[1] / (p[2] * ay)) ** 2 <= 1.0)


def paper_success_b(
    e_xyz: np.ndarray, e_psi: np.ndarray, visible: np.ndarray, cfg: DockingTaskConfig
) -> np.ndarray:
    """(N,) bool: the paper's docking condition (reference code) of N envs: position (N, 3),
    yaw (N,) and visibility (N,). The one definition: :func:`paper_success` is a batch of one."""
    ok = (
        (np.abs(e_xyz[:, 0]) < cfg.success_xy_m)
        & (np.abs(e_xyz[:, 1]) < cfg.success_xy_m)
        & (np.abs(e_xyz[:, 2]) < cfg.success_z_m)
        & (np.abs(e_psi) < math.radians(cfg.success_yaw_deg))
    )
    return ok & (visible | (not cfg.success_requires_visible))


def paper_success(e_xyz: np.ndarray, e_psi: float, visible: bool, cfg: DockingTaskConfig) -> bool:
    """The paper's docking condition (reference code): position, yaw and visibility
    (:func:`paper_success_b` of one env)."""
    one = paper_success_b(np.asarray(e_xyz)[None], np.asarray([e_psi]), np.asarray([visible]), cfg)
    return bool(one[0])


def pegs_seated(T_world_body: np.ndarray, T_world_ds: np.ndarray, cfg: DockingTaskConfig) -> bool:
    """Strict criterion (one instant): every peg within tolerance of a notch seat."""
    T_ds_body = inv_T(T_world_ds) @ T_world_body
    pegs = (T_ds_body[:3, :3] @ np.asarray(cfg.peg_positions_body_m).T).T + T_ds_body[:3, 3]
    notches = np.asarray(cfg.notch_positions_ds_m)
    for peg in pegs:
        d = notches - peg
        k = int(np.argmin(np.linalg.norm(d[:, :2], axis=1)))
        if np.linalg.norm(d[k, :2]) > cfg.strict_peg_xy_m or abs(d[k, 2]) > cfg.strict_peg_z_m:
            return False
    return True
