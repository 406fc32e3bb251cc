"""Frames and rigid transforms: the one place where axis conventions are converted.

Convention:
    A pose is a 4x4 float64 homogeneous matrix named ``T_a_b``: frame ``b`` expressed in frame
    ``a``. It maps a point given in ``b`` to the same point given in ``a``::

        p_a = T_a_b @ [p_b, 1]        (see transform_points)

    Compose by matching the inner letters: ``T_world_marker = T_world_cam @ T_cam_marker``;
    invert by swapping them: ``T_b_a = inv_T(T_a_b)``. Rotations are 3x3 ``R_a_b`` with the same
    meaning. Quaternions are (w, x, y, z) everywhere (SAPIEN's order); scipy's (x, y, z, w) order
    is converted here and nowhere else. Angles are radians unless the name ends in ``_deg``.

Named frames used in the toolkit (all right-handed):
    world_ned:   NED world of the reference: x north, y east, z down.
    world_zup:   SAPIEN's world: x north, y west, z up (``T_WORLDZUP_WORLDNED``: 180 deg about x).
    ds:          docking station, NED-like as the reference numbers are given: x forward,
                 y starboard, z down (the markers sit at negative z, above the DS origin).
    body_frd:    vehicle body as marine vehicles use it (Fossen): x forward, y right (starboard),
                 z down. Pairs with world_ned.
    body_flu:    vehicle body as SAPIEN actors use it: x forward, y left, z up. Pairs with
                 world_zup (``T_BODYFLU_BODYFRD``: 180 deg about x).
    cam_cv:      OpenCV camera: x right, y down, z forward (optical axis). Intrinsics, PnP and
                 ``cv2.projectPoints`` live here; ``solvePnP`` returns ``T_camcv_marker``.
    cam_sapien:  SAPIEN camera entity: x forward (optical axis), y left, z up.
    cam_gl:      OpenGL camera, as in SAPIEN's "Position" picture and model matrix: x right,
                 y up, z backward (the camera looks along -z).
    marker:      OpenCV ArUco marker frame: origin at the marker centre, z out of the marker face
                 toward the viewer, x right, y up (as seen by a viewer facing the marker). The
                 corners of a marker of side s, in detection order TL, TR, BR, BL, are
                 (-s/2, s/2, 0), (s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0).

Example:
    >>> T_world_camcv = T_world_camcv_from_sapien(T_world_camsapien)
    >>> p_world = transform_points(T_world_camcv @ T_camcv_marker, corners_marker)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

# scipy.spatial (half a second to import) is imported by the two batch conversions that use it,
# so every module that handles poses (and every command) does not pay for it.

__all__ = [
    "T_BODYFLU_BODYFRD",
    "T_CAMCV_CAMGL",
    "T_CAMCV_CAMSAPIEN",
    "T_WORLDZUP_WORLDNED",
    "R_from_quat_wxyz",
    "R_from_rpy",
    "T_from_pos_quat",
    "T_world_camcv_from_sapien",
    "T_world_camsapien_from_cv",
    "check_R",
    "check_T",
    "cross3",
    "inv_T",
    "make_T",
    "ned_pose_to_zup",
    "pos_quat_from_T",
    "quat_wxyz_from_R",
    "rotation_angle_deg",
    "rpy_from_R",
    "transform_points",
    "wrap_angle_rad",
    "zup_pose_to_ned",
]

#: Tolerance on ``R.T @ R - I`` (max abs entry) and on ``det(R) - 1`` for a valid rotation.
ORTHONORMAL_TOL = 1e-6


# --------------------------------------------------------------------------- validation


def _as_float_array(x: ArrayLike, name: str) -> np.ndarray:
    """Return ``x`` as a float64 array copy, or raise ValueError naming ``name``."""
    try:
        return np.array(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a numeric array, got {type(x).__name__}") from None


def _check_rotation_block(R: np.ndarray, name: str) -> None:
    """Raise ValueError naming ``name`` unless the finite (3,3) ``R`` is a proper rotation.

    In scalar arithmetic on the nine entries: a pose is checked at every reset and frame
    change, where NumPy's per-call overhead on a 3x3 (the product, ``linalg.det``) would cost
    several times the arithmetic."""
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    err = max(
        abs(a * a + d * d + g * g - 1.0),
        abs(b * b + e * e + h * h - 1.0),
        abs(c * c + f * f + i * i - 1.0),
        abs(a * b + d * e + g * h),
        abs(a * c + d * f + g * i),
        abs(b * c + e * f + h * i),
    )
    if not err <= ORTHONORMAL_TOL:
        raise ValueError(f"{name}: rotation is not orthonormal (max |R^T R - I| = {err:.3g})")
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if abs(det - 1.0) > ORTHONORMAL_TOL:
        raise ValueError(f"{name}: rotation determinant must be +1, got {det:.6g}")


_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])


def check_R(R: ArrayLike, name: str = "R") -> np.ndarray:
    """Validate a rotation matrix.

    Args:
        R: (3, 3) array-like, a proper rotation (orthonormal to 1e-6, det +1).
        name: argument name used in the error message.

    Returns:
        A float64 (3, 3) copy of ``R``.

    Raises:
        ValueError: one line naming ``name`` on a wrong shape, a non-finite entry, a
            non-orthonormal matrix or a reflection.
    """
    arr = _as_float_array(R, name)
    if arr.shape != (3, 3):
        raise ValueError(f"{name}: expected shape (3, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains non-finite values")
    _check_rotation_block(arr, name)
    return arr


def check_T(T: ArrayLike, name: str = "T") -> np.ndarray:
    """Validate a rigid transform.

    Args:
        T: (4, 4) array-like homogeneous transform ``[[R, t], [0, 0, 0, 1]]``.
        name: argument name used in the error message.

    Returns:
        A float64 (4, 4) copy of ``T``.

    Raises:
        ValueError: one line naming ``name`` on a wrong shape, a non-finite entry, a bottom row
            other than [0, 0, 0, 1], a non-orthonormal rotation (tol 1e-6) or det(R) != +1.
    """
    arr = _as_float_array(T, name)
    if arr.shape != (4, 4):
        raise ValueError(f"{name}: expected shape (4, 4), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains non-finite values")
    if not float(np.abs(arr[3] - _BOTTOM).max()) <= 1e-12:
        raise ValueError(f"{name}: bottom row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    _check_rotation_block(arr[:3, :3], name)
    return arr


def _vec3(v: ArrayLike, name: str) -> np.ndarray:
    arr = _as_float_array(v, name)
    if arr.shape != (3,):
        raise ValueError(f"{name}: expected shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains non-finite values")
    return arr


def _shape_4x4(T: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name}: expected shape (4, 4), got {arr.shape}")
    return arr


# --------------------------------------------------------------------------- transforms


def cross3(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """``a x b`` of two 3-vectors, the arithmetic of ``np.cross`` without its axis handling
    (which costs tens of microseconds a call on single small vectors)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def make_T(R: ArrayLike | None = None, t: ArrayLike | None = None) -> np.ndarray:
    """Build a transform from a rotation and a translation.

    Args:
        R: (3, 3) rotation ``R_a_b`` (validated); identity if None.
        t: (3,) translation, the origin of b expressed in a (m); zero if None.

    Returns:
        (4, 4) float64 ``T_a_b``.
    """
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = check_R(R, "R")
    if t is not None:
        T[:3, 3] = _vec3(t, "t")
    return T


def inv_T(T: ArrayLike) -> np.ndarray:
    """Invert a rigid transform using ``R.T`` (not a general matrix inverse).

    Args:
        T: (4, 4) ``T_a_b`` (shape checked, rotation assumed valid).

    Returns:
        (4, 4) float64 ``T_b_a``.
    """
    T = _shape_4x4(T, "T")
    R_t = T[:3, :3].T
    out = np.eye(4)
    out[:3, :3] = R_t
    out[:3, 3] = -R_t @ T[:3, 3]
    return out


def inv_T_b(T: np.ndarray) -> np.ndarray:
    """(N, 4, 4) inverses of N rigid transforms (no checks: the batched simulator's hot path;
    :func:`inv_T` checks one)."""
    out = np.zeros_like(T)
    R_t = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = R_t
    out[:, :3, 3] = -np.einsum("nij,nj->ni", R_t, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def transform_points(T_a_b: ArrayLike, p_b: ArrayLike) -> np.ndarray:
    """Map points from frame b to frame a.

    Args:
        T_a_b: (4, 4) transform.
        p_b: (3,) point or (N, 3) points in frame b.

    Returns:
        float64 array of the same shape as ``p_b``, the points in frame a.
    """
    T = _shape_4x4(T_a_b, "T_a_b")
    p = np.asarray(p_b, dtype=np.float64)
    if p.shape == (3,):
        return T[:3, :3] @ p + T[:3, 3]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"p_b: expected shape (3,) or (N, 3), got {p.shape}")
    return p @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- quaternions


def R_from_quat_wxyz(q: ArrayLike) -> np.ndarray:
    """Rotation matrix from a (w, x, y, z) quaternion; the quaternion is normalised first.

    Args:
        q: (4,) quaternion (w, x, y, z), or (N, 4) for a batch.

    Returns:
        (3, 3) float64 rotation, or (N, 3, 3) for a batch.

    Raises:
        ValueError: on a wrong shape, a non-finite entry or a (near) zero norm.
    """
    arr = _as_float_array(q, "q")
    if arr.shape == (4,):
        return _R_from_unit_quat(arr)
    if arr.shape[-1:] != (4,) or arr.ndim not in (1, 2):
        raise ValueError(f"q: expected shape (4,) or (N, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("q: contains non-finite values")
    norm = np.linalg.norm(arr, axis=-1)
    if np.any(norm < 1e-12):
        raise ValueError("q: quaternion has zero norm")
    xyzw = arr[..., [1, 2, 3, 0]] / norm[..., None]  # scipy order is (x, y, z, w)
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(xyzw).as_matrix()


def _R_from_unit_quat(q: np.ndarray) -> np.ndarray:
    """The closed-form rotation of one (w, x, y, z) quaternion (the hot path: no scipy)."""
    n = float(np.sqrt(q @ q))
    if not np.isfinite(n):
        raise ValueError("q: contains non-finite values")
    if n < 1e-12:
        raise ValueError("q: quaternion has zero norm")
    w, x, y, z = (q / n).tolist()
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return np.array(
        [
            [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
            [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
            [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
        ]
    )


def quat_wxyz_from_R(R: ArrayLike) -> np.ndarray:
    """(w, x, y, z) unit quaternion of a rotation matrix, canonical with w >= 0.

    The conversion is SciPy's ``Rotation.from_matrix(R).as_quat()`` to the bit (the same
    largest-component choice among the diagonal and the trace, the same sums in the same order,
    the same normalisation), in scalar arithmetic: SciPy's call costs ~0.2 ms on one matrix,
    this ~10 us. A matrix SciPy would first orthogonalise (its Gram matrix off the identity by
    more than ``np.isclose``'s tolerances with ``atol=1e-12``) goes to SciPy itself.

    Args:
        R: (3, 3) proper rotation (validated).

    Returns:
        (4,) float64 quaternion (w, x, y, z) with w >= 0.
    """
    M = check_R(R, "R")
    m = M.tolist()
    if _needs_orthogonalising(m):
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_matrix(M).as_quat().tolist()
    else:
        x, y, z, w = _xyzw_of_orthogonal(m)
    if w < 0.0:
        return np.array([-w, -x, -y, -z])
    return np.array([w, x, y, z])


def _needs_orthogonalising(m: list[list[float]]) -> bool:
    """Whether SciPy's ``from_matrix`` orthogonalises ``m`` first: its Gram matrix ``m m^T``
    off the identity beyond ``np.isclose(..., atol=1e-12)`` (default rtol 1e-5)."""
    for r in range(3):
        for c in range(r, 3):
            dot = m[r][0] * m[c][0] + m[r][1] * m[c][1] + m[r][2] * m[c][2]
            if r == c and not abs(dot - 1.0) <= 1e-12 + 1e-5:
                return True
            if r != c and not abs(dot) <= 1e-12:
                return True
    return False


def _xyzw_of_orthogonal(m: list[list[float]]) -> list[float]:
    """The (x, y, z, w) quaternion of an orthogonal (3, 3) rotation ``m`` (nested lists), from
    its largest of the diagonal and the trace (Shepperd's choice), normalised."""
    trace = m[0][0] + m[1][1] + m[2][2]
    decision = (m[0][0], m[1][1], m[2][2], trace)
    choice = 0
    for c in (1, 2, 3):  # the first largest, as a strict comparison in order
        if decision[c] > decision[choice]:
            choice = c
    q = [0.0, 0.0, 0.0, 0.0]
    if choice != 3:
        i = choice
        j = (i + 1) % 3
        k = (j + 1) % 3
        q[i] = 1 - trace + 2 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    else:
        q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1 + trace]
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm]


def T_from_pos_quat(pos: ArrayLike, quat_wxyz: ArrayLike) -> np.ndarray:
    """Transform from a position (m) and a (w, x, y, z) quaternion (SAPIEN ``Pose`` layout).

    Args:
        pos: (3,) origin of the child frame in the parent frame (m).
        quat_wxyz: (4,) orientation of the child frame in the parent frame.

    Returns:
        (4, 4) float64 ``T_parent_child``.
    """
    T = np.eye(4)
    T[:3, :3] = R_from_quat_wxyz(quat_wxyz)
    T[:3, 3] = _vec3(pos, "pos")
    return T


def pos_quat_from_T(T: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Split a transform into position (3,) and (w, x, y, z) quaternion (4,), w >= 0."""
    T = check_T(T, "T")
    return T[:3, 3].copy(), quat_wxyz_from_R(T[:3, :3])


# --------------------------------------------------------------------------- Euler angles


def R_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Rotation from roll, pitch, yaw (Fossen ZYX): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    The result is body-to-world (``R_world_body``) for a body with Euler angles (phi, theta, psi),
    e.g. ``R_ned_frd``.

    Returns:
        (3, 3) float64 rotation.
    """
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ],
        dtype=np.float64,
    )


def rpy_from_R(R: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`R_from_rpy`.

    Args:
        R: (3, 3) rotation (shape checked).

    Returns:
        (roll_rad, pitch_rad, yaw_rad): roll and yaw in [-pi, pi], pitch in [-pi/2, pi/2].
        At gimbal lock (pitch = +-pi/2) roll is returned as 0 and yaw carries the rest.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"R: expected shape (3, 3), got {R.shape}")
    pitch = float(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    if np.hypot(R[2, 1], R[2, 2]) < 1e-9:  # gimbal lock: only yaw -/+ roll is defined
        return 0.0, pitch, float(np.arctan2(-R[0, 1], R[1, 1]))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def wrap_angle_rad(a: Any) -> Any:
    """Wrap angles to [-pi, pi) elementwise (pi maps to -pi).

    Args:
        a: scalar or array of angles (rad).

    Returns:
        float for a scalar input, float64 array of the same shape otherwise.
    """
    if type(a) is float:  # the scalar path: Python's % is np.mod's fmod-and-adjust, bit for bit
        out_f = (a + math.pi) % (2.0 * math.pi) - math.pi
        return out_f - 2.0 * math.pi if out_f >= math.pi else out_f
    arr = np.asarray(a, dtype=np.float64)
    out = np.mod(arr + np.pi, 2.0 * np.pi) - np.pi
    # np.mod can round up to exactly 2*pi for inputs a hair below pi: keep the half-open range.
    out = np.where(out >= np.pi, out - 2.0 * np.pi, out)
    return float(out) if out.ndim == 0 else out


def rotation_angle_deg(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Geodesic angle between two rotations, in degrees, in [0, 180].

    Uses ``atan2(|sin|, cos)`` of the relative rotation ``R_a.T @ R_b``, which stays accurate near
    0 and 180 degrees. Either argument may also be a (4, 4) transform (its rotation is used).
    """
    Ra = np.asarray(R_a, dtype=np.float64)
    Rb = np.asarray(R_b, dtype=np.float64)
    Ra = Ra[:3, :3] if Ra.shape == (4, 4) else Ra
    Rb = Rb[:3, :3] if Rb.shape == (4, 4) else Rb
    if Ra.shape != (3, 3) or Rb.shape != (3, 3):
        raise ValueError(f"R_a, R_b: expected shape (3, 3), got {Ra.shape} and {Rb.shape}")
    Rd = Ra.T @ Rb
    cos_a = (np.trace(Rd) - 1.0) / 2.0
    sin_a = 0.5 * np.linalg.norm([Rd[2, 1] - Rd[1, 2], Rd[0, 2] - Rd[2, 0], Rd[1, 0] - Rd[0, 1]])
    return float(np.degrees(np.arctan2(sin_a, cos_a)))


# --------------------------------------------------------------------------- axis conventions


def _axes_T(
    x_col: tuple[float, ...], y_col: tuple[float, ...], z_col: tuple[float, ...]
) -> np.ndarray:
    """Read-only (4, 4) pure rotation whose columns are the child axes in the parent frame."""
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_col, y_col, z_col])
    T.setflags(write=False)
    return T


#: ``T_camcv_camsapien``: SAPIEN camera entity (x forward, y left, z up) in the OpenCV camera
#: frame (x right, y down, z forward). Columns: x_sapien = +z_cv, y_sapien = -x_cv,
#: z_sapien = -y_cv. Read-only.
T_CAMCV_CAMSAPIEN = _axes_T((0, 0, 1), (-1, 0, 0), (0, -1, 0))

#: ``T_camcv_camgl``: OpenGL camera (x right, y up, z backward; SAPIEN's "Position" picture) in
#: the OpenCV camera frame (x right, y down, z forward): diag(1, -1, -1). Read-only.
T_CAMCV_CAMGL = _axes_T((1, 0, 0), (0, -1, 0), (0, 0, -1))

#: ``T_worldzup_worldned``: NED world (x north, y east, z down) in SAPIEN's z-up world
#: (x north, y west, z up): 180 deg about x, diag(1, -1, -1). Read-only.
T_WORLDZUP_WORLDNED = _axes_T((1, 0, 0), (0, -1, 0), (0, 0, -1))

#: ``T_bodyflu_bodyfrd``: marine body frame (x forward, y right, z down) in the SAPIEN actor
#: body frame (x forward, y left, z up): 180 deg about x, diag(1, -1, -1). Read-only.
T_BODYFLU_BODYFRD = _axes_T((1, 0, 0), (0, -1, 0), (0, 0, -1))


def T_world_camcv_from_sapien(T_world_camsapien: ArrayLike) -> np.ndarray:
    """OpenCV-camera pose from a SAPIEN camera-entity pose (same world, same origin).

    Args:
        T_world_camsapien: (4, 4) pose of the SAPIEN camera entity (x forward, y left, z up).

    Returns:
        (4, 4) ``T_world_camcv`` = ``T_world_camsapien @ inv(T_CAMCV_CAMSAPIEN)``.
    """
    return check_T(T_world_camsapien, "T_world_camsapien") @ inv_T(T_CAMCV_CAMSAPIEN)


def T_world_camsapien_from_cv(T_world_camcv: ArrayLike) -> np.ndarray:
    """SAPIEN camera-entity pose from an OpenCV-camera pose (inverse of the function above).

    Returns:
        (4, 4) ``T_world_camsapien`` = ``T_world_camcv @ T_CAMCV_CAMSAPIEN``.
    """
    return check_T(T_world_camcv, "T_world_camcv") @ T_CAMCV_CAMSAPIEN


def ned_pose_to_zup(T_ned_x_frd: ArrayLike) -> np.ndarray:
    """Vehicle pose in NED world with an FRD body -> pose in SAPIEN's z-up world with FLU body.

    Args:
        T_ned_x_frd: (4, 4) pose of a body frame x (forward-right-down) in world_ned.

    Returns:
        (4, 4) ``T_zup_x_flu`` = ``T_WORLDZUP_WORLDNED @ T_ned_x_frd @ inv(T_BODYFLU_BODYFRD)``.
    """
    T = check_T(T_ned_x_frd, "T_ned_x_frd")
    return T_WORLDZUP_WORLDNED @ T @ inv_T(T_BODYFLU_BODYFRD)


def zup_pose_to_ned(T_zup_x_flu: ArrayLike) -> np.ndarray:
    """Inverse of :func:`ned_pose_to_zup`.

    Args:
        T_zup_x_flu: (4, 4) pose of a body frame x (forward-left-up) in SAPIEN's z-up world.

    Returns:
        (4, 4) ``T_ned_x_frd`` = ``inv(T_WORLDZUP_WORLDNED) @ T_zup_x_flu @ T_BODYFLU_BODYFRD``.
    """
    T = check_T(T_zup_x_flu, "T_zup_x_flu")
    return inv_T(T_WORLDZUP_WORLDNED) @ T @ T_BODYFLU_BODYFRD
