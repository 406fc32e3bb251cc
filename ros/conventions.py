"""World and body axis conventions on the wire, converted in one place.

The toolkit works in a local NED world with FRD bodies (``T_world_body`` = ``T_ned_frd``), as
COLA2, the Girona vehicles' software, publishes its navigation. A plain ROS 2 vehicle follows
REP 103: an ENU world (x east, y north, z up) and FLU bodies (x forward, y left, z up). A
setting names which one a topic uses (:data:`Convention`); these functions take the wire's
values to the toolkit's and back, exactly (the axis swaps are permutations with signs).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from uwdock.calibration.frames import T_BODYFLU_BODYFRD, inv_T

__all__ = [
    "T_ENU_NED",
    "Convention",
    "body_vector_from_wire",
    "body_vector_to_wire",
    "covariance_from_wire",
    "covariance_to_wire",
    "frame_pose_from_wire",
    "frame_pose_to_wire",
    "pose_from_wire",
    "pose_to_wire",
    "world_vector_from_wire",
    "world_vector_to_wire",
]

#: ``"ned"``: NED world, FRD body (COLA2); ``"enu"``: ENU world, FLU body (REP 103).
Convention = Literal["ned", "enu"]

#: NED axes in ENU: x_enu = y_ned (east), y_enu = x_ned (north), z_enu = -z_ned.
T_ENU_NED = np.array(
    [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
_T_NED_ENU = inv_T(T_ENU_NED)
_T_FRD_FLU = inv_T(T_BODYFLU_BODYFRD)


def _check(convention: str) -> None:
    if convention not in ("ned", "enu"):
        raise ValueError(f"axis convention must be 'ned' or 'enu', got {convention!r}")


def pose_from_wire(T_world_body_wire: np.ndarray, convention: Convention) -> np.ndarray:
    """(4, 4) ``T_ned_frd`` of a body pose published in ``convention``."""
    _check(convention)
    T = np.asarray(T_world_body_wire, dtype=np.float64)
    return T.copy() if convention == "ned" else _T_NED_ENU @ T @ T_BODYFLU_BODYFRD


def pose_to_wire(T_ned_frd: np.ndarray, convention: Convention) -> np.ndarray:
    """(4, 4) body pose in ``convention`` (``T_enu_flu`` or the NED pose itself)."""
    _check(convention)
    T = np.asarray(T_ned_frd, dtype=np.float64)
    return T.copy() if convention == "ned" else T_ENU_NED @ T @ _T_FRD_FLU


def frame_pose_from_wire(T_world_x_wire: np.ndarray, convention: Convention) -> np.ndarray:
    """(4, 4) ``T_ned_x`` of a pose of a frame x that is not a body (the DS, a marker): only
    the world changes axes."""
    _check(convention)
    T = np.asarray(T_world_x_wire, dtype=np.float64)
    return T.copy() if convention == "ned" else _T_NED_ENU @ T


def frame_pose_to_wire(T_ned_x: np.ndarray, convention: Convention) -> np.ndarray:
    """Inverse of :func:`frame_pose_from_wire`."""
    _check(convention)
    T = np.asarray(T_ned_x, dtype=np.float64)
    return T.copy() if convention == "ned" else T_ENU_NED @ T


def body_vector_from_wire(v_wire: np.ndarray, convention: Convention) -> np.ndarray:
    """(3,) FRD body vector (velocity, rate, acceleration, force) of one published in
    ``convention``'s body axes."""
    _check(convention)
    v = np.asarray(v_wire, dtype=np.float64)
    return v.copy() if convention == "ned" else _T_FRD_FLU[:3, :3] @ v


def body_vector_to_wire(v_frd: np.ndarray, convention: Convention) -> np.ndarray:
    """Inverse of :func:`body_vector_from_wire`."""
    _check(convention)
    v = np.asarray(v_frd, dtype=np.float64)
    return v.copy() if convention == "ned" else T_BODYFLU_BODYFRD[:3, :3] @ v


def world_vector_from_wire(p_wire: np.ndarray, convention: Convention) -> np.ndarray:
    """(3,) NED world point of one published in ``convention``'s world axes."""
    _check(convention)
    p = np.asarray(p_wire, dtype=np.float64)
    return p.copy() if convention == "ned" else _T_NED_ENU[:3, :3] @ p


def world_vector_to_wire(p_ned: np.ndarray, convention: Convention) -> np.ndarray:
    """Inverse of :func:`world_vector_from_wire`."""
    _check(convention)
    p = np.asarray(p_ned, dtype=np.float64)
    return p.copy() if convention == "ned" else T_ENU_NED[:3, :3] @ p


def covariance_from_wire(cov6: np.ndarray, convention: Convention, body: bool) -> np.ndarray:
    """(6, 6) covariance of a pose or twist in the toolkit's axes: the world's (``body``
    False: a pose's position and orientation errors in the world) or the body's."""
    _check(convention)
    c = np.asarray(cov6, dtype=np.float64)
    if convention == "ned":
        return c.copy()
    R = (_T_FRD_FLU if body else _T_NED_ENU)[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    return J @ c @ J.T


def covariance_to_wire(cov6: np.ndarray, convention: Convention, body: bool) -> np.ndarray:
    """Inverse of :func:`covariance_from_wire`."""
    _check(convention)
    c = np.asarray(cov6, dtype=np.float64)
    if convention == "ned":
        return c.copy()
    R = (T_BODYFLU_BODYFRD if body else T_ENU_NED)[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    return J @ c @ J.T
