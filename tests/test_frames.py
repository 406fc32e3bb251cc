"""Frames and transforms: known rotations, round trips and the axis-convention constants."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwdock.calibration import frames as F

C45 = math.cos(math.pi / 4)


def _random_rotations(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return F.R_from_quat_wxyz(q)


# ----------------------------------------------------------------------- known rotations


@pytest.mark.parametrize(
    ("quat", "src", "dst"),
    [
        # 90 deg about x: y -> z, z -> -y
        ((C45, C45, 0, 0), (0, 1, 0), (0, 0, 1)),
        ((C45, C45, 0, 0), (0, 0, 1), (0, -1, 0)),
        # 90 deg about y: z -> x, x -> -z
        ((C45, 0, C45, 0), (0, 0, 1), (1, 0, 0)),
        ((C45, 0, C45, 0), (1, 0, 0), (0, 0, -1)),
        # 90 deg about z: x -> y, y -> -x
        ((C45, 0, 0, C45), (1, 0, 0), (0, 1, 0)),
        ((C45, 0, 0, C45), (0, 1, 0), (-1, 0, 0)),
    ],
)
def test_quat_90_deg_about_each_axis(quat, src, dst):
    R = F.R_from_quat_wxyz(quat)
    np.testing.assert_allclose(R @ np.array(src, float), dst, atol=1e-12)


@pytest.mark.parametrize(
    ("rpy", "src", "dst"),
    [
        ((math.pi / 2, 0, 0), (0, 1, 0), (0, 0, 1)),
        ((0, math.pi / 2, 0), (0, 0, 1), (1, 0, 0)),
        ((0, 0, math.pi / 2), (1, 0, 0), (0, 1, 0)),
    ],
)
def test_rpy_90_deg_about_each_axis(rpy, src, dst):
    np.testing.assert_allclose(F.R_from_rpy(*rpy) @ np.array(src, float), dst, atol=1e-12)


def test_rpy_is_zyx_composition():
    roll, pitch, yaw = 0.3, -0.4, 2.0
    Rx = F.R_from_quat_wxyz((math.cos(roll / 2), math.sin(roll / 2), 0, 0))
    Ry = F.R_from_quat_wxyz((math.cos(pitch / 2), 0, math.sin(pitch / 2), 0))
    Rz = F.R_from_quat_wxyz((math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)))
    np.testing.assert_allclose(F.R_from_rpy(roll, pitch, yaw), Rz @ Ry @ Rx, atol=1e-12)


def test_quat_normalised_and_zero_norm_rejected():
    np.testing.assert_allclose(
        F.R_from_quat_wxyz((2.0, 0, 0, 2.0)), F.R_from_rpy(0, 0, math.pi / 2), atol=1e-12
    )
    with pytest.raises(ValueError, match="zero norm"):
        F.R_from_quat_wxyz((0, 0, 0, 0))


# ----------------------------------------------------------------------- round trips


def test_quat_round_trip_random_rotations():
    Rs = _random_rotations(200, seed=1)
    for R in Rs:
        q = F.quat_wxyz_from_R(R)
        assert q[0] >= 0.0
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        np.testing.assert_allclose(F.R_from_quat_wxyz(q), R, atol=1e-12)


def test_quat_canonical_sign():
    # q and -q are the same rotation; the canonical one has w >= 0.
    q = np.array([-0.5, 0.5, -0.5, 0.5])
    np.testing.assert_allclose(F.quat_wxyz_from_R(F.R_from_quat_wxyz(q)), -q, atol=1e-12)


def test_pos_quat_round_trip():
    rng = np.random.default_rng(2)
    for R in _random_rotations(20, seed=3):
        t = rng.normal(size=3)
        T = F.make_T(R, t)
        pos, q = F.pos_quat_from_T(T)
        np.testing.assert_allclose(pos, t, atol=1e-15)
        np.testing.assert_allclose(F.T_from_pos_quat(pos, q), T, atol=1e-12)


def test_rpy_round_trip_away_from_gimbal_lock():
    rng = np.random.default_rng(4)
    for _ in range(200):
        roll, yaw = rng.uniform(-math.pi, math.pi, size=2)
        pitch = rng.uniform(-1.5, 1.5)
        out = F.rpy_from_R(F.R_from_rpy(roll, pitch, yaw))
        np.testing.assert_allclose(out, (roll, pitch, yaw), atol=1e-9)


def test_rpy_at_gimbal_lock_reconstructs_rotation():
    R = F.R_from_rpy(0.4, math.pi / 2, 1.0)
    np.testing.assert_allclose(F.R_from_rpy(*F.rpy_from_R(R)), R, atol=1e-9)


# ----------------------------------------------------------------------- transforms


def test_inv_T_times_T_is_identity():
    rng = np.random.default_rng(5)
    for R in _random_rotations(20, seed=6):
        T = F.make_T(R, rng.normal(size=3) * 10)
        np.testing.assert_allclose(F.inv_T(T) @ T, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(T @ F.inv_T(T), np.eye(4), atol=1e-12)


def test_transform_points_composition_and_shapes():
    rng = np.random.default_rng(7)
    R1, R2 = _random_rotations(2, seed=8)
    T_a_b = F.make_T(R1, rng.normal(size=3))
    T_b_c = F.make_T(R2, rng.normal(size=3))
    p_c = rng.normal(size=(10, 3))
    via_b = F.transform_points(T_a_b, F.transform_points(T_b_c, p_c))
    np.testing.assert_allclose(F.transform_points(T_a_b @ T_b_c, p_c), via_b, atol=1e-12)
    single = F.transform_points(T_a_b, p_c[0])
    assert single.shape == (3,)
    np.testing.assert_allclose(single, T_a_b[:3, :3] @ p_c[0] + T_a_b[:3, 3], atol=1e-12)
    with pytest.raises(ValueError, match="p_b"):
        F.transform_points(T_a_b, np.zeros((4, 2)))


def test_make_T_known_values():
    T = F.make_T(F.R_from_rpy(0, 0, math.pi / 2), (1.0, 2.0, 3.0))
    np.testing.assert_allclose(F.transform_points(T, (1.0, 0, 0)), (1.0, 3.0, 3.0), atol=1e-12)
    np.testing.assert_array_equal(F.make_T(), np.eye(4))


# ----------------------------------------------------------------------- check_T


def _bad(kind: str) -> np.ndarray:
    T = np.eye(4)
    if kind == "shape":
        return np.eye(3)
    if kind == "nan":
        T[0, 3] = np.nan
    elif kind == "bottom":
        T[3, 0] = 0.1
    elif kind == "scale":
        T[:3, :3] *= 1.01
    elif kind == "reflection":
        T[2, 2] = -1.0
    return T


@pytest.mark.parametrize(
    ("kind", "fragment"),
    [
        ("shape", "shape"),
        ("nan", "non-finite"),
        ("bottom", "bottom row"),
        ("scale", "orthonormal"),
        ("reflection", "determinant"),
    ],
)
def test_check_T_rejects_with_argument_name(kind, fragment):
    with pytest.raises(ValueError, match=rf"^T_cam_marker: .*{fragment}") as info:
        F.check_T(_bad(kind), name="T_cam_marker")
    assert "\n" not in str(info.value)


def test_check_T_returns_float_copy():
    T_int = np.eye(4, dtype=int)
    out = F.check_T(T_int)
    assert out.dtype == np.float64 and out.shape == (4, 4)
    out[0, 3] = 5.0
    assert T_int[0, 3] == 0
    # tolerance: a rotation off by 1e-9 is accepted
    T = F.make_T(F.R_from_rpy(0.1, 0.2, 0.3))
    T[:3, :3] *= 1 + 1e-9
    F.check_T(T)
    with pytest.raises(ValueError, match=r"^T: "):
        F.check_T("not a matrix")


# ----------------------------------------------------------------------- angles


@pytest.mark.parametrize(
    ("a", "expected"),
    [
        (math.pi, -math.pi),
        (-math.pi, -math.pi),
        (3 * math.pi, -math.pi),
        (0.0, 0.0),
        (2 * math.pi, 0.0),
        (-3 * math.pi / 2, math.pi / 2),
        (7.0, 7.0 - 2 * math.pi),
    ],
)
def test_wrap_angle_scalar(a, expected):
    out = F.wrap_angle_rad(a)
    assert isinstance(out, float)
    assert out == pytest.approx(expected, abs=1e-12)
    assert -math.pi <= out < math.pi


def test_wrap_angle_array_half_open():
    a = np.array([math.pi, -math.pi, 3 * math.pi, np.nextafter(math.pi, 0.0), 1.0, -20.0])
    out = F.wrap_angle_rad(a)
    assert out.shape == a.shape
    assert np.all(out >= -math.pi) and np.all(out < math.pi)
    # same angle modulo 2*pi
    np.testing.assert_allclose(np.exp(1j * out), np.exp(1j * a), atol=1e-12)
    np.testing.assert_allclose(
        out[[0, 1, 2, 4, 5]], [-math.pi, -math.pi, -math.pi, 1.0, -20.0 + 6 * math.pi], atol=1e-12
    )


def test_rotation_angle_deg_known_values():
    I = np.eye(3)
    assert F.rotation_angle_deg(I, I) == pytest.approx(0.0, abs=1e-12)
    assert F.rotation_angle_deg(I, F.R_from_rpy(0, 0, math.radians(30))) == pytest.approx(30.0)
    assert F.rotation_angle_deg(I, F.R_from_rpy(math.pi, 0, 0)) == pytest.approx(180.0)
    assert F.rotation_angle_deg(I, F.R_from_rpy(0, math.radians(1e-5), 0)) == pytest.approx(
        1e-5, rel=1e-6
    )
    # relative angle is independent of a common rotation
    R0 = _random_rotations(1, seed=9)[0]
    Rb = R0 @ F.R_from_rpy(0, math.radians(45), 0)
    assert F.rotation_angle_deg(R0, Rb) == pytest.approx(45.0)
    # transforms accepted
    assert F.rotation_angle_deg(F.make_T(R0), F.make_T(Rb)) == pytest.approx(45.0)


# ----------------------------------------------------------------------- axis conventions


@pytest.mark.parametrize(
    "name", ["T_CAMCV_CAMSAPIEN", "T_CAMCV_CAMGL", "T_WORLDZUP_WORLDNED", "T_BODYFLU_BODYFRD"]
)
def test_constants_are_read_only_rotations(name):
    T = getattr(F, name)
    F.check_T(T, name)
    np.testing.assert_array_equal(T[:3, 3], 0.0)
    with pytest.raises(ValueError):
        T[0, 0] = 2.0


def test_camcv_camsapien_axes():
    T = F.T_CAMCV_CAMSAPIEN
    # SAPIEN forward (+x) is OpenCV +z, SAPIEN left (+y) is OpenCV -x, SAPIEN up (+z) is -y.
    np.testing.assert_array_equal(F.transform_points(T, (1, 0, 0)), (0, 0, 1))
    np.testing.assert_array_equal(F.transform_points(T, (0, 1, 0)), (-1, 0, 0))
    np.testing.assert_array_equal(F.transform_points(T, (0, 0, 1)), (0, -1, 0))


def test_camcv_camgl_axes():
    T = F.T_CAMCV_CAMGL
    # OpenGL looks along -z and has y up.
    np.testing.assert_array_equal(F.transform_points(T, (0, 0, -1)), (0, 0, 1))
    np.testing.assert_array_equal(F.transform_points(T, (0, 1, 0)), (0, -1, 0))
    np.testing.assert_array_equal(F.transform_points(T, (1, 0, 0)), (1, 0, 0))


def test_world_and_body_flips():
    # NED east (+y) is z-up west's negative; NED down is z-up -z.
    np.testing.assert_array_equal(F.transform_points(F.T_WORLDZUP_WORLDNED, (0, 1, 0)), (0, -1, 0))
    np.testing.assert_array_equal(F.transform_points(F.T_WORLDZUP_WORLDNED, (0, 0, 1)), (0, 0, -1))
    np.testing.assert_array_equal(F.transform_points(F.T_BODYFLU_BODYFRD, (0, 1, 0)), (0, -1, 0))


def test_sapien_camera_looking_down_quat_and_optical_axis():
    # SAPIEN camera entity in a z-up world: forward (x) -> world -z, left (y) -> world +y,
    # up (z) -> world +x (image top toward north).
    R_world_camsapien = np.column_stack([(0, 0, -1), (0, 1, 0), (1, 0, 0)]).astype(float)
    q = F.quat_wxyz_from_R(R_world_camsapien)
    np.testing.assert_allclose(q, (C45, 0, C45, 0), atol=1e-12)
    T_world_camsapien = F.T_from_pos_quat((1.0, 2.0, 3.0), q)
    T_world_camcv = F.T_world_camcv_from_sapien(T_world_camsapien)
    np.testing.assert_allclose(T_world_camcv[:3, 2], (0, 0, -1), atol=1e-12)  # optical axis
    np.testing.assert_allclose(T_world_camcv[:3, 3], (1.0, 2.0, 3.0))  # same origin
    # image top (-y_cv) is SAPIEN up, i.e. world +x here
    np.testing.assert_allclose(-T_world_camcv[:3, 1], (1, 0, 0), atol=1e-12)
    # a point 2 m below the camera is straight ahead in cam_cv
    p_cv = F.transform_points(F.inv_T(T_world_camcv), (1.0, 2.0, 1.0))
    np.testing.assert_allclose(p_cv, (0, 0, 2.0), atol=1e-12)
    np.testing.assert_allclose(
        F.T_world_camsapien_from_cv(T_world_camcv), T_world_camsapien, atol=1e-12
    )


def test_ned_zup_pose_round_trip_and_down_is_minus_z():
    rng = np.random.default_rng(10)
    for R in _random_rotations(10, seed=11):
        T_ned_frd = F.make_T(R, rng.normal(size=3))
        T_zup_flu = F.ned_pose_to_zup(T_ned_frd)
        F.check_T(T_zup_flu)
        np.testing.assert_allclose(F.zup_pose_to_ned(T_zup_flu), T_ned_frd, atol=1e-12)

    # A vehicle yawed 90 deg in NED (nose east) at 1 m depth.
    T_ned_frd = F.make_T(F.R_from_rpy(0, 0, math.pi / 2), (1.0, 2.0, 1.0))
    T_zup_flu = F.ned_pose_to_zup(T_ned_frd)
    np.testing.assert_allclose(T_zup_flu[:3, 3], (1.0, -2.0, -1.0), atol=1e-12)
    # nose points east = world zup -y; body FLU z (up) points world +z.
    np.testing.assert_allclose(T_zup_flu[:3, 0], (0, -1, 0), atol=1e-12)
    np.testing.assert_allclose(T_zup_flu[:3, 2], (0, 0, 1), atol=1e-12)
    # moving 0.5 m "down" in NED moves -0.5 m in zup z.
    T_deeper = T_ned_frd.copy()
    T_deeper[2, 3] += 0.5
    dz = F.ned_pose_to_zup(T_deeper)[2, 3] - T_zup_flu[2, 3]
    assert dz == pytest.approx(-0.5)
    # a body point ahead of the vehicle (FRD +x) maps to the same world point either way
    p_frd = np.array([0.7, 0.2, 0.1])
    p_flu = F.transform_points(F.T_BODYFLU_BODYFRD, p_frd)
    np.testing.assert_allclose(
        F.transform_points(T_zup_flu, p_flu),
        F.transform_points(F.T_WORLDZUP_WORLDNED @ T_ned_frd, p_frd),
        atol=1e-12,
    )


def test_wrap_angle_scalar_path_is_the_array_path_bit_for_bit():
    rng = np.random.default_rng(0)
    edges = [math.pi, -math.pi, 0.0, -0.0, math.nextafter(math.pi, 0.0), 3 * math.pi, -7.0]
    xs = np.concatenate([rng.uniform(-50.0, 50.0, 20000), edges])
    scalar = np.array([F.wrap_angle_rad(float(x)) for x in xs])
    np.testing.assert_array_equal(scalar, F.wrap_angle_rad(xs))
    assert np.all((scalar >= -math.pi) & (scalar < math.pi))


def test_batched_inverse_equals_the_checked_one():
    rng = np.random.default_rng(4)
    Ts = np.stack(
        [F.make_T(F.R_from_rpy(*rng.uniform(-3, 3, 3)), rng.normal(0, 5, 3)) for _ in range(5)]
    )
    assert np.allclose(F.inv_T_b(Ts), [F.inv_T(T) for T in Ts], atol=1e-12)


def test_cross3_is_np_cross_bit_for_bit():
    rng = np.random.default_rng(4)
    for _ in range(200):
        a, b = rng.normal(size=3) * 10.0 ** rng.integers(-6, 6), rng.normal(size=3)
        assert F.cross3(a, b).tobytes() == np.cross(a, b).tobytes()
    assert F.cross3([1.0, 0.0, 0.0], (0.0, 1.0, 0.0)).tolist() == [0.0, 0.0, 1.0]


def test_quat_of_a_matrix_is_scipys_to_the_bit():
    """quat_wxyz_from_R does SciPy's conversion in scalar arithmetic: the same bits on random
    rotations, on Euler compositions with right angles (ties between the diagonal and the
    trace), on the half turns, and on matrices SciPy orthogonalises first (which go to it)."""
    from scipy.spatial.transform import Rotation

    def scipy_wxyz(R):
        q = Rotation.from_matrix(R).as_quat()[[3, 0, 1, 2]]
        return -q if q[0] < 0 else q

    rng = np.random.default_rng(7)
    mats = list(Rotation.random(3000, random_state=rng).as_matrix())
    right = [0.0, math.pi / 2, math.pi, -math.pi / 2]
    mats += [F.R_from_rpy(*rng.choice(right, 3)) for _ in range(300)]
    mats += [F.R_from_rpy(0.0, 0.0, y) for y in rng.uniform(-math.pi, math.pi, 300)]
    mats += [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    skewed = [R + rng.normal(0.0, 3e-8, (3, 3)) for R in Rotation.random(300, rng).as_matrix()]
    assert all(F._needs_orthogonalising(R.tolist()) for R in skewed)  # SciPy's own branch
    for R in mats + skewed:
        assert F.quat_wxyz_from_R(R).tobytes() == scipy_wxyz(R).tobytes()
