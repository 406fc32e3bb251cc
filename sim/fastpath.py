"""Numba kernels of the vehicle's 300 Hz loop, and the free-flight fast path that skips PhysX.

One implementation of the model serves both ways of stepping :class:`sim.physics.VehicleBody`:

* :func:`hydro_accel` is the scalar Fossen model (``Hydrodynamics.acceleration``, NumPy, is the
  readable reference it is tested against); :func:`accel_fn` binds a vehicle's constants to it.
* :func:`physx_wrench` turns the PhysX state of one substep into the world force and torque that
  make PhysX's body reach that acceleration (the PhysX path calls it before every
  ``scene.step()``).
* :func:`free_flight` runs a whole control step without PhysX: the same :func:`physx_wrench`
  maths, then what PhysX (TGS solver, no constraints) does with it, checked against SAPIEN
  3.0.3 / PhysX 5 (``tests/test_fastpath.py``)::

      v     <- v + dt F / m_e                                  (external force)
      w'    <- w + dt R I_e^-1 R^T T                           (external torque)
      w'    <- w' clamped to the body's max angular velocity
      L     =  I_e R^T w'; L' = L - dt (R^T w') x L, rescaled to |L|   (gyroscopic, momentum-norm
      w     <- R I_e^-1 L'                                      preserving; SAPIEN enables it)
      p_cg  <- p_cg + dt v;  q <- normalise(exp(dt w / 2) q)   (closed-form rotation)

  in float64 where PhysX uses float32, so the two paths agree to float32 round-off (~1e-5 m
  over seconds), not bit for bit.

The fast path is only valid while PhysX would generate no contact. :func:`free_flight` bounds
the swept volume of every hull shape over the step (the box of the origin's positions at the
substeps, the shape's box at the start attitude, grown by ``rho * theta`` for the rotation,
``theta`` = integral of ``|w|``, ``rho`` = the shape's farthest point from the origin) and
reports whether any grown box (plus a margin above PhysX's contact offsets) may touch a static
obstacle: their world boxes first, then, where those overlap, the separating-axis test against
the obstacle's oriented box (so a tilted guide plate no longer hands PhysX every vehicle inside
the box around it); it then integrates again chunk by chunk (:data:`CHUNK_SUBSTEPS`) up to the
first chunk that may touch, and the caller steps PhysX from there. Planes given to
:func:`plane_contacts` (a docking world's tank floor and walls) are not obstacles: their
contact is computed in the kernel.
:class:`StaticObstacles` collects those boxes, one per collision shape of the scene's static
actors, and refreshes them when a static actor moves (e.g. the docking station per episode).

Frames: SAPIEN z-up world, body FLU, CoM at ``cg`` (see ``sim.physics``); the hydrodynamics
works in body FRD, so FLU <-> FRD negates y and z.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import sapien
from numba import njit

from uwdock.calibration.frames import T_from_pos_quat
from uwdock.sim.vehicle import Hydrodynamics

__all__ = [
    "HYDRO_PARAMS",
    "OBSTACLE_COLS",
    "PRISM_COLS",
    "PRISM_MAX_VERTICES",
    "AccelFn",
    "StaticObstacles",
    "StaticsWatch",
    "accel_fn",
    "body_params",
    "free_flight",
    "free_flight_all",
    "hull_boxes",
    "hydro_accel",
    "hydro_params",
    "kernel_flight_all",
    "physx_wrench",
    "physx_wrenches",
    "plane_contacts",
    "prism_contacts",
    "prism_distance",
    "prism_pairs",
]

#: Length of :func:`hydro_params`'s vector: m, W-B, W r_g - B r_b (3), r_g (3), added mass (6),
#: linear (6) and quadratic (6) damping, I_O (9, row-major), (M_RB + M_A)^-1 (36, row-major),
#: then the free surface: B, r_b (3), the surface band (m).
HYDRO_PARAMS = 76
#: Columns of an obstacle row (:meth:`StaticObstacles.boxes`): the world box [min xyz, max xyz],
#: then 1.0 if an oriented box follows (0.0: a plane, only the world box counts), its centre (3),
#: half size (3) and rotation (9, row-major: its axes are the columns), z-up world, m.
OBSTACLE_COLS = 22
#: Most vertices of a prism's cross-section (:data:`PRISM_COLS`).
PRISM_MAX_VERTICES = 8
#: Columns of a prism row (:func:`prism_contacts`), a static collision shape as a convex polygon
#: extruded along an axis (a box is a rectangle's), z-up world: its world box [min xyz, max
#: xyz] (6), centre (3), rotation (9, row-major; column 0 the extrusion axis, columns 1 and 2
#: the polygon's plane), half length along the extrusion (m), Coulomb friction with the hull,
#: vertex count, the polygon's box (u min, u max, v min, v max; m), then its (u, v) vertices,
#: counter-clockwise (m).
PRISM_COLS = 25 + 2 * PRISM_MAX_VERTICES
#: At most this share of a contact's sliding speed is taken by its friction in one substep
#: (the cap of :func:`prism_contacts`' friction slope: regularised Coulomb friction near rest
#: is a viscous force whose explicit integration needs it).
PRISM_FRICTION_STEP = 0.2
#: (m/s^2, rad/s^2 times the hull's reach) A bound on how much the hull's speed can change
#: within a control step (full thrust gives about 1 m/s^2), for the pairs a step tests.
PRISM_ACCEL_BOUND = 5.0
#: (m) Within a control step, the pairs of :func:`prism_pairs`, and their spheres, farther
#: than this from their prism's box are set aside until the hull may have moved this far
#: (:func:`near_pairs`): what is set aside cannot touch, so the contact is the same to the bit
#: as with every pair and sphere tested at every substep (``near_m = inf``;
#: ``tests/test_kernel_contact.py``), in about 0.7x the kernel's time on the steps a policy
#: flies (``bench/bench_kernel_cull.py``).
PRISM_NEAR_M = 0.02
#: (m) What the test of a pair set aside keeps for round-off (the positions' is ~1e-14 m).
PRISM_NEAR_SLACK_M = 1e-6
#: No prisms (free flight's :func:`_advance`: the station is PhysX's there); numba freezes
#: these as read-only constants (the pairs buffer, written to, is made per call).
_NO_SPHERES = np.zeros((0, 4))
_NO_CHUNKS = np.zeros((0, 6))
_NO_PRISMS = np.zeros((0, PRISM_COLS))
#: Unbounded side of an obstacle box (a half-space, or a shape we cannot bound).
_FAR = 1e30
#: Substeps per chunk when a step that may touch is retried chunk by chunk (:func:`free_flight`).
CHUNK_SUBSTEPS = 6


# --------------------------------------------------------------------------- parameters


#: A vehicle's scalar ``nu_dot`` (:func:`accel_fn`).
AccelFn = Callable[..., tuple[float, float, float, float, float, float]]


def accel_fn(hydro: Hydrodynamics) -> AccelFn:
    """Scalar version of :meth:`sim.vehicle.Hydrodynamics.acceleration`: the compiled kernel the
    300 Hz loop runs (:func:`hydro_accel`) with this vehicle's constants bound.

    Returns:
        ``f(dx, dy, dz, u, v, w, p, q, r, cu, cv, cw, X, Y, Z, K, M, N, depth_cb) -> nu_dot``
        (6-tuple) where (dx, dy, dz) is the NED down direction in body FRD (row 2 of
        ``R_ned_frd``), (u..r) the body velocity, (cu, cv, cw) the current in body FRD, (X..N)
        the applied wrench and ``depth_cb`` the CB's depth (m, ``inf``: deep); all floats.
    """
    params = hydro_params(hydro)

    def accel(*args: float) -> tuple[float, float, float, float, float, float]:
        return hydro_accel(params, *args)

    return accel


def hydro_params(hydro: Hydrodynamics) -> np.ndarray:
    """Pack a vehicle's hydrodynamic constants for :func:`hydro_accel` ((76,) float64)."""
    c = hydro.config
    rg = np.asarray(c.cg_m, dtype=float)
    rb = np.asarray(c.cb_m, dtype=float)
    h = c.weight_n * rg - c.buoyancy_n * rb
    P = np.concatenate(
        [
            [c.mass_kg, c.weight_n - c.buoyancy_n],
            h,
            rg,
            np.asarray(c.added_mass, dtype=float),
            np.asarray(c.linear_damping, dtype=float),
            np.asarray(c.quadratic_damping, dtype=float),
            np.asarray(hydro.I_O, dtype=float).ravel(),
            np.asarray(hydro.M_inv, dtype=float).ravel(),
            [c.buoyancy_n],
            rb,
            [c.surface_band_m],
        ]
    )
    assert P.shape == (HYDRO_PARAMS,)
    return np.ascontiguousarray(P)


def body_params(
    mass_kg: float,
    inertia_kgm2: Sequence[float],
    component: sapien.physx.PhysxRigidDynamicComponent,
) -> np.ndarray:
    """Pack the PhysX body's parameters ((9,) float64).

    Args:
        mass_kg: the folded mass ``m_e`` the bridge uses (kg; ``VehicleBody.engine_mass_kg``).
        inertia_kgm2: (3,) the folded principal inertia ``I_e`` at the CG (kg m^2).
        component: the body, already given that mass and inertia: its angular speed limit and
            its own (float32) copies of them are what PhysX integrates with.
    """
    return np.array(
        [
            mass_kg,
            *inertia_kgm2,
            component.get_max_angular_velocity(),
            component.get_mass(),
            *np.asarray(component.get_inertia(), dtype=float),
        ],
        dtype=float,
    )


# --------------------------------------------------------------------------- model (scalar)


@njit(cache=True)
def hydro_accel(P, dx, dy, dz, u, v, w, p, q, r, cu, cv, cw, X, Y, Z, K, M, N, depth_cb):
    """Body acceleration ``nu_dot`` of the Fossen model (``Hydrodynamics.acceleration``).

    Args:
        P: (76,) :func:`hydro_params`.
        dx, dy, dz: NED down direction in body FRD (row 2 of ``R_ned_frd``).
        u, v, w, p, q, r: body velocity of the origin, FRD (m/s, rad/s).
        cu, cv, cw: water velocity in body FRD (m/s).
        X, Y, Z, K, M, N: applied wrench about the origin, FRD (N, N m).
        depth_cb: depth of the centre of buoyancy below the surface (m; ``inf``: deep).

    Returns:
        6-tuple ``nu_dot`` (m/s^2, rad/s^2), FRD.
    """
    m = P[0]
    wb = P[1]
    hx, hy, hz = P[2], P[3], P[4]
    band = P[75]
    if band > 0.0 and depth_cb < 0.5 * band:  # the free surface: the buoyancy lost above it
        lost = P[71] * (1.0 - max(0.0, 0.5 + depth_cb / band))
        wb += lost
        hx += lost * P[72]
        hy += lost * P[73]
        hz += lost * P[74]
    gx, gy, gz = P[5], P[6], P[7]
    a0, a1, a2, a3, a4, a5 = P[8], P[9], P[10], P[11], P[12], P[13]
    ur = u - cu
    vr = v - cv
    wr = w - cw
    # restoring (weight at CG, buoyancy at CB) and damping on the relative velocity
    X += wb * dx - (P[14] + P[20] * abs(ur)) * ur
    Y += wb * dy - (P[15] + P[21] * abs(vr)) * vr
    Z += wb * dz - (P[16] + P[22] * abs(wr)) * wr
    K += hy * dz - hz * dy - (P[17] + P[23] * abs(p)) * p
    M += hz * dx - hx * dz - (P[18] + P[24] * abs(q)) * q
    N += hx * dy - hy * dx - (P[19] + P[25] * abs(r)) * r
    # added mass: -C_A(nu_r) nu_r + M_A nu_c_dot with nu_c_dot = -omega x v_c
    p1x = a0 * ur
    p1y = a1 * vr
    p1z = a2 * wr
    p2x = a3 * p
    p2y = a4 * q
    p2z = a5 * r
    X -= q * p1z - r * p1y + a0 * (q * cw - r * cv)
    Y -= r * p1x - p * p1z + a1 * (r * cu - p * cw)
    Z -= p * p1y - q * p1x + a2 * (p * cv - q * cu)
    K -= vr * p1z - wr * p1y + q * p2z - r * p2y
    M -= wr * p1x - ur * p1z + r * p2x - p * p2z
    N -= ur * p1y - vr * p1x + p * p2y - q * p2x
    # rigid body: -C_RB(nu) nu = -[m(w x v + w x (w x rg)), m rg x (w x v) + w x I_O w]
    tx = q * w - r * v  # omega x v
    ty = r * u - p * w
    tz = p * v - q * u
    sx = q * gz - r * gy  # omega x rg
    sy = r * gx - p * gz
    sz = p * gy - q * gx
    X -= m * (tx + q * sz - r * sy)
    Y -= m * (ty + r * sx - p * sz)
    Z -= m * (tz + p * sy - q * sx)
    jx = P[26] * p + P[27] * q + P[28] * r
    jy = P[29] * p + P[30] * q + P[31] * r
    jz = P[32] * p + P[33] * q + P[34] * r
    K -= m * (gy * tz - gz * ty) + q * jz - r * jy
    M -= m * (gz * tx - gx * tz) + r * jx - p * jz
    N -= m * (gx * ty - gy * tx) + p * jy - q * jx
    return (  # (M_RB + M_A)^-1 @ tau
        P[35] * X + P[36] * Y + P[37] * Z + P[38] * K + P[39] * M + P[40] * N,
        P[41] * X + P[42] * Y + P[43] * Z + P[44] * K + P[45] * M + P[46] * N,
        P[47] * X + P[48] * Y + P[49] * Z + P[50] * K + P[51] * M + P[52] * N,
        P[53] * X + P[54] * Y + P[55] * Z + P[56] * K + P[57] * M + P[58] * N,
        P[59] * X + P[60] * Y + P[61] * Z + P[62] * K + P[63] * M + P[64] * N,
        P[65] * X + P[66] * Y + P[67] * Z + P[68] * K + P[69] * M + P[70] * N,
    )


@njit(cache=True)
def _bridge(P, B, pz, qw, qx, qy, qz, vx, vy, vz, ox, oy, oz, ax_, ay_, az_, X, Y, Z, K, M, N):
    """World force and torque (6-tuple, z-up) PhysX needs to realise the model's acceleration.

    ``pz``: the entity origin's height (z-up world, m; the surface at 0); ``q``: body FLU
    attitude (w, x, y, z); ``v``: CoM velocity and ``o``: angular velocity (z-up world);
    ``a_``: water velocity (z-up world); ``X..N``: thruster wrench (FRD).
    ``F = m_e a_cg`` and ``T = I_e omega_dot + omega x I_e omega`` (see ``sim.physics``).
    """
    me = B[0]
    ie0, ie1, ie2 = B[1], B[2], B[3]
    cx, cy, cz = P[5], P[6], P[7]
    # R_zup_flu from the unit quaternion
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    r00 = 1.0 - 2.0 * (yy + zz)
    r01 = 2.0 * (xy - wz)
    r02 = 2.0 * (xz + wy)
    r10 = 2.0 * (xy + wz)
    r11 = 1.0 - 2.0 * (xx + zz)
    r12 = 2.0 * (yz - wx)
    r20 = 2.0 * (xz - wy)
    r21 = 2.0 * (yz + wx)
    r22 = 1.0 - 2.0 * (xx + yy)
    # world -> body FLU (R^T) -> body FRD (negate y, z)
    p = r00 * ox + r10 * oy + r20 * oz
    q = -(r01 * ox + r11 * oy + r21 * oz)
    r = -(r02 * ox + r12 * oy + r22 * oz)
    ug = r00 * vx + r10 * vy + r20 * vz
    vg = -(r01 * vx + r11 * vy + r21 * vz)
    wg = -(r02 * vx + r12 * vy + r22 * vz)
    cu = r00 * ax_ + r10 * ay_ + r20 * az_
    cv = -(r01 * ax_ + r11 * ay_ + r21 * az_)
    cw = -(r02 * ax_ + r12 * ay_ + r22 * az_)
    # the CB's depth: -(z-up height of origin + R (CB in FLU)), CB in FLU = (bx, -by, -bz)
    depth_cb = -(pz + r20 * P[72] - r21 * P[73] - r22 * P[74])
    # origin velocity v_O = v_cg - omega x c; NED down in FRD = (-r20, r21, r22)
    ud, vd, wd, pd, qd, rd = hydro_accel(
        P, -r20, r21, r22,
        ug - (q * cz - r * cy), vg - (r * cx - p * cz), wg - (p * cy - q * cx),
        p, q, r, cu, cv, cw, X, Y, Z, K, M, N, depth_cb,
    )  # fmt: skip
    # CoM acceleration in body FRD: v_O_dot + omega_dot x c + omega x v_cg
    fx = me * (ud + qd * cz - rd * cy + q * wg - r * vg)
    fy = -me * (vd + rd * cx - pd * cz + r * ug - p * wg)
    fz = -me * (wd + pd * cy - qd * cx + p * vg - q * ug)
    # torque about the CoM: I_e omega_dot + omega x I_e omega (FRD), then FLU signs
    tx = ie0 * pd + (ie2 - ie1) * q * r
    ty = -(ie1 * qd + (ie0 - ie2) * r * p)
    tz = -(ie2 * rd + (ie1 - ie0) * p * q)
    return (
        r00 * fx + r01 * fy + r02 * fz, r10 * fx + r11 * fy + r12 * fz,
        r20 * fx + r21 * fy + r22 * fz,
        r00 * tx + r01 * ty + r02 * tz, r10 * tx + r11 * ty + r12 * tz,
        r20 * tx + r21 * ty + r22 * tz,
    )  # fmt: skip


@njit(cache=True)
def physx_wrench(P, B, pos, quat, vel, omega, currents, wrenches, k, spheres, planes, contact):
    """The PhysX path's per-substep call: world force and torque for substep ``k``.

    Args:
        P: (76,) :func:`hydro_params`; B: (9,) :func:`body_params`.
        pos: (3,) entity position, z-up world (m; the surface at z = 0).
        quat: (4,) entity attitude (w, x, y, z) as PhysX returns it (float32 is fine).
        vel: (3,) CoM velocity, z-up world (m/s); omega: (3,) angular velocity (rad/s).
        currents: (n, 3) water velocity per substep, z-up world (m/s).
        wrenches: (n, 6) thruster wrench per substep, FRD about the origin (N, N m).
        k: substep index.
        spheres, planes, contact: the tank planes' contact (:func:`plane_contacts`; no planes:
            none).

    Returns:
        ``((Fx, Fy, Fz), (Tx, Ty, Tz))`` for ``add_force_torque`` (N, N m, z-up world).
    """
    f = _bridge(
        P, B, np.float64(pos[2]),
        np.float64(quat[0]), np.float64(quat[1]), np.float64(quat[2]), np.float64(quat[3]),
        np.float64(vel[0]), np.float64(vel[1]), np.float64(vel[2]),
        np.float64(omega[0]), np.float64(omega[1]), np.float64(omega[2]),
        currents[k, 0], currents[k, 1], currents[k, 2],
        wrenches[k, 0], wrenches[k, 1], wrenches[k, 2],
        wrenches[k, 3], wrenches[k, 4], wrenches[k, 5],
    )  # fmt: skip
    if planes.shape[0] == 0:
        return (f[0], f[1], f[2]), (f[3], f[4], f[5])
    R = np.empty((3, 3))
    _rot(R, np.float64(quat[0]), np.float64(quat[1]), np.float64(quat[2]), np.float64(quat[3]))
    x, y, z = np.float64(pos[0]), np.float64(pos[1]), np.float64(pos[2])
    cx, cy, cz = P[5], -P[6], -P[7]  # CoM in body FLU
    gx = x + R[0, 0] * cx + R[0, 1] * cy + R[0, 2] * cz
    gy = y + R[1, 0] * cx + R[1, 1] * cy + R[1, 2] * cz
    gz = z + R[2, 0] * cx + R[2, 1] * cy + R[2, 2] * cz
    out = np.zeros(6)
    plane_contacts(
        spheres, planes, contact, x, y, z, R, gx, gy, gz,
        np.float64(vel[0]), np.float64(vel[1]), np.float64(vel[2]),
        np.float64(omega[0]), np.float64(omega[1]), np.float64(omega[2]), out,
    )  # fmt: skip
    return (f[0] + out[0], f[1] + out[1], f[2] + out[2]), (
        f[3] + out[3],
        f[4] + out[4],
        f[5] + out[5],
    )


@njit(cache=True)
def physx_wrenches(
    P, B, packed, rows, slots, offsets, currents, wrenches, k, spheres, planes, contact, out
):
    """:func:`physx_wrench` for several vehicles of one shared PhysX scene at substep ``k``.

    Args:
        P: (N, 76) and B: (N, 9) every vehicle's parameters; contact: (N, 5).
        packed: (13 M,) float32, the scene's ``PhysxSystem.pack()`` as it lays its M bodies
            out, 13 floats each: attitude (w, x, y, z), entity position in the shared scene,
            CoM velocity, angular velocity.
        rows: (K,) int64 the stepped vehicles' bodies in ``packed``; slots: (K,) int64 their
            vehicle indices; offsets: (N, 3) where each vehicle's world sits in the shared
            scene (its positions there are world + offset).
        currents: (N, n, 3), wrenches: (N, n, 6) per vehicle and substep.
        out: (K, 6) world force and torque per row (N, N m, z-up world).
    """
    pos = np.empty(3)
    for j in range(rows.shape[0]):
        i = slots[j]
        b = rows[j] * 13
        for a in range(3):
            pos[a] = np.float64(packed[b + 4 + a]) - offsets[i, a]
        f, t = physx_wrench(
            P[i], B[i], pos, packed[b : b + 4], packed[b + 7 : b + 10], packed[b + 10 : b + 13],
            currents[i], wrenches[i], k, spheres, planes, contact[i],
        )  # fmt: skip
        out[j, 0], out[j, 1], out[j, 2] = f
        out[j, 3], out[j, 4], out[j, 5] = t


# --------------------------------------------------------------------------- tank planes


@njit(cache=True)
def _penalty(
    k, c, mu, v_eps, visc_max, delta, nx, ny, nz, cx_, cy_, cz_, vx, vy, vz, ox, oy, oz, out
):  # fmt: skip
    """The contact law of :func:`plane_contacts` and :func:`prism_contacts` for one contact (a
    spring-damper and regularised Coulomb friction), its friction's slope at rest capped at
    ``visc_max`` (N s/m, which keeps the
    explicit substep stable): penetration ``delta`` (m) along the unit normal ``n`` (pushing
    the hull out), at ``c_`` relative to the CoM; adds the force and torque about the CoM to
    ``out``."""
    ux = vx + oy * cz_ - oz * cy_
    uy = vy + oz * cx_ - ox * cz_
    uz = vz + ox * cy_ - oy * cx_
    vn = ux * nx + uy * ny + uz * nz
    fn = k * delta - c * vn
    if fn <= 0.0:
        return
    tx_, ty_, tz_ = ux - vn * nx, uy - vn * ny, uz - vn * nz
    vt = math.sqrt(tx_ * tx_ + ty_ * ty_ + tz_ * tz_)
    ft = min(mu * fn / max(vt, v_eps), visc_max)
    fx = fn * nx - ft * tx_
    fy = fn * ny - ft * ty_
    fz = fn * nz - ft * tz_
    out[0] += fx
    out[1] += fy
    out[2] += fz
    out[3] += cy_ * fz - cz_ * fy
    out[4] += cz_ * fx - cx_ * fz
    out[5] += cx_ * fy - cy_ * fx


@njit(cache=True)
def plane_contacts(
    spheres, planes, contact, px, py, pz, R, gx, gy, gz, vx, vy, vz, ox, oy, oz, out
):
    """Add the tank planes' contact force and torque on the hull to ``out`` (6,) (world z-up,
    force on the CoM and torque about it).

    Every hull shape is a set of spheres that touch a plane exactly where the shape does (a
    capsule: its two end spheres; a box: its eight corners, radius 0). A sphere that reaches
    past a plane by ``delta`` pushes back along the plane's normal with a spring and damper
    ``k delta - c v_n`` (never pulling) and rubs along it with regularised Coulomb friction
    ``-mu F_n v_t / max(|v_t|, v_eps)``, at its deepest point.

    Args:
        spheres: (s, 4) centre in the body FLU frame (m) and radius (m).
        planes: (k, 4) unit normal into the water (z-up world) and offset ``d``: a point ``p``
            is in the water while ``n . p >= d``.
        contact: (5,) stiffness ``k`` (N/m), damping ``c`` (N s/m), friction ``mu``, ``v_eps``
            (m/s) and the hull's reach (m: no sphere reaches farther from the entity origin),
            which skips the planes out of reach.
        px, py, pz: entity origin; R: (3, 3) attitude (body FLU -> world); gx, gy, gz: CoM;
        vx, vy, vz: CoM velocity; ox, oy, oz: angular velocity (all z-up world).
        out: (6,) accumulated into.
    """
    k, c, mu, v_eps, reach = contact[0], contact[1], contact[2], contact[3], contact[4]
    for j in range(planes.shape[0]):
        nx, ny, nz, d = planes[j, 0], planes[j, 1], planes[j, 2], planes[j, 3]
        if nx * px + ny * py + nz * pz - d > reach:
            continue  # the whole hull is clear of this plane
        for i in range(spheres.shape[0]):
            bx, by, bz, rad = spheres[i, 0], spheres[i, 1], spheres[i, 2], spheres[i, 3]
            wx = px + R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz
            wy = py + R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz
            wz = pz + R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz
            delta = d - (nx * wx + ny * wy + nz * wz) + rad
            if delta <= 0.0:
                continue
            # at the deepest point of the sphere, relative to the CoM; no cap on friction
            _penalty(
                k, c, mu, v_eps, math.inf, delta, nx, ny, nz,
                wx - rad * nx - gx, wy - rad * ny - gy, wz - rad * nz - gz,
                vx, vy, vz, ox, oy, oz, out,
            )  # fmt: skip


# --------------------------------------------------------------------------- static prisms


@njit(cache=True)
def prism_distance(o, wx, wy, wz):
    """Signed distance (m; negative inside) from the point ``w`` (z-up world) to prism row ``o``
    (:data:`PRISM_COLS`), and the unit outward normal there (world): exact, from the
    cross-section's closest edge point combined with the extrusion's end faces; inside, the
    face of least penetration.

    Returns:
        ``(d, nx, ny, nz)``.
    """
    dx, dy, dz = wx - o[6], wy - o[7], wz - o[8]
    a = o[9] * dx + o[12] * dy + o[15] * dz  # R^T d: along the extrusion axis, then (u, v)
    u = o[10] * dx + o[13] * dy + o[16] * dz
    v = o[11] * dx + o[14] * dy + o[17] * dz
    m = int(o[20])
    inside = True
    best_e, bnu, bnv = -1e300, 0.0, 0.0
    best_d2, qu_, qv_ = 1e300, 0.0, 0.0
    for j in range(m):
        u0, v0 = o[25 + 2 * j], o[26 + 2 * j]
        j1 = j + 1 if j + 1 < m else 0
        eu, ev = o[25 + 2 * j1] - u0, o[26 + 2 * j1] - v0
        ll = eu * eu + ev * ev
        inv = 1.0 / math.sqrt(ll)
        nu, nv = ev * inv, -eu * inv  # outward for a counter-clockwise polygon
        e = nu * (u - u0) + nv * (v - v0)
        if e > 0.0:
            inside = False
        if e > best_e:
            best_e, bnu, bnv = e, nu, nv
        t = ((u - u0) * eu + (v - v0) * ev) / ll
        t = min(1.0, max(0.0, t))
        cu, cv = u0 + t * eu, v0 + t * ev
        d2 = (u - cu) * (u - cu) + (v - cv) * (v - cv)
        if d2 < best_d2:
            best_d2, qu_, qv_ = d2, cu, cv
    if inside:
        dp, pu, pv = best_e, bnu, bnv
    else:
        dp = math.sqrt(best_d2)
        pu, pv = (u - qu_) / dp, (v - qv_) / dp
    da = abs(a) - o[18]
    sa = 1.0 if a >= 0.0 else -1.0
    if dp > 0.0 and da > 0.0:
        d = math.sqrt(dp * dp + da * da)
        la, lu, lv = sa * da / d, pu * dp / d, pv * dp / d
    elif dp > 0.0 or (dp <= 0.0 and da <= 0.0 and dp >= da):
        d, la, lu, lv = dp, 0.0, pu, pv
    else:
        d, la, lu, lv = da, sa, 0.0, 0.0
    return (
        d,
        o[9] * la + o[10] * lu + o[11] * lv,
        o[12] * la + o[13] * lu + o[14] * lv,
        o[15] * la + o[16] * lu + o[17] * lv,
    )


@njit(cache=True)
def _outside(o, wx, wy, wz, rad):
    """Whether a ball (centre ``w``, z-up world; radius ``rad``) is clear of prism row ``o``'s
    box in the prism's own frame (extrusion and polygon box)."""
    dx, dy, dz = wx - o[6], wy - o[7], wz - o[8]
    a = o[9] * dx + o[12] * dy + o[15] * dz
    if abs(a) > o[18] + rad:
        return True
    u = o[10] * dx + o[13] * dy + o[16] * dz
    if u < o[21] - rad or u > o[22] + rad:
        return True
    v = o[11] * dx + o[14] * dy + o[17] * dz
    return v < o[23] - rad or v > o[24] + rad


@njit(cache=True)
def prism_pairs(chunks, shapes, prisms, px, py, pz, R, margin, pairs):
    """The (chunk, prism, shape) triples that may touch while the hull stays within ``margin``
    (m) of the pose (``p``, ``R``; z-up world): each shape's ball, then each of its chunks'
    balls, grown by ``margin``, against the prisms' boxes in their own frames. Writes them to
    ``pairs`` (at least chunks x prisms rows, 3) int64, shape by shape; returns how many."""
    n = 0
    for sh in range(shapes.shape[0]):
        bx, by, bz, rs = shapes[sh, 2], shapes[sh, 3], shapes[sh, 4], shapes[sh, 5] + margin
        csx = px + R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz
        csy = py + R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz
        csz = pz + R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz
        for j in range(prisms.shape[0]):
            o = prisms[j]
            if _outside(o, csx, csy, csz, rs):
                continue
            for g in range(int(shapes[sh, 0]), int(shapes[sh, 1])):
                bx, by, bz, rg = chunks[g, 2], chunks[g, 3], chunks[g, 4], chunks[g, 5]
                cxg = px + R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz
                cyg = py + R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz
                czg = pz + R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz
                if not _outside(o, cxg, cyg, czg, rg + margin):
                    pairs[n, 0], pairs[n, 1], pairs[n, 2] = g, j, sh
                    n += 1
    return n


@njit(cache=True)
def _gap(o, wx, wy, wz, rad):
    """How far (m) a ball (centre ``w``, radius ``rad``) is clear of prism row ``o``'s box in
    the prism's frame, along the axis that separates them most (negative: no axis does;
    positive exactly when :func:`_outside`)."""
    dx, dy, dz = wx - o[6], wy - o[7], wz - o[8]
    a = o[9] * dx + o[12] * dy + o[15] * dz
    u = o[10] * dx + o[13] * dy + o[16] * dz
    v = o[11] * dx + o[14] * dy + o[17] * dz
    g = abs(a) - (o[18] + rad)
    g = max(g, (o[21] - rad) - u, u - (o[22] + rad))
    return max(g, (o[23] - rad) - v, v - (o[24] + rad))


@njit(cache=True)
def near_pairs(spheres, chunks, prisms, pairs, n_pairs, px, py, pz, R, near, active, listed):
    """The pairs (:func:`prism_pairs`) with a sphere within ``near`` (m) of the pair's prism
    box at the pose (``p``, ``R``), in their order, and those spheres: ``active`` gets each
    such pair's row of ``pairs`` and the span of its spheres in ``listed`` (5 columns: chunk,
    prism, shape, first, end), ``listed`` the spheres' rows, in order; returns how many pairs.
    While the hull moves less than ``near`` from this pose, the spheres left out stay clear
    of their prisms (a point that moves ``d`` moves along each of a prism's axes by at most
    ``d``), so :func:`_listed_contacts` over ``active`` is :func:`prism_contacts` over
    ``pairs``."""
    m = 0
    n = 0
    for q in range(n_pairs):
        g, o = pairs[q, 0], prisms[pairs[q, 1]]
        bx, by, bz = chunks[g, 2], chunks[g, 3], chunks[g, 4]
        cx = px + R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz
        cy = py + R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz
        cz = pz + R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz
        if _gap(o, cx, cy, cz, chunks[g, 5]) >= near:
            continue
        first = n
        for i in range(int(chunks[g, 0]), int(chunks[g, 1])):
            sx, sy, sz = spheres[i, 0], spheres[i, 1], spheres[i, 2]
            wx = px + R[0, 0] * sx + R[0, 1] * sy + R[0, 2] * sz
            wy = py + R[1, 0] * sx + R[1, 1] * sy + R[1, 2] * sz
            wz = pz + R[2, 0] * sx + R[2, 1] * sy + R[2, 2] * sz
            if _gap(o, wx, wy, wz, spheres[i, 3]) < near:
                listed[n] = i
                n += 1
        if n > first:
            active[m, 0], active[m, 1], active[m, 2] = pairs[q, 0], pairs[q, 1], pairs[q, 2]
            active[m, 3], active[m, 4] = first, n
            m += 1
    return m


@njit(cache=True)
def prism_contacts(
    spheres, chunks, shapes, prisms, pairs, n_pairs, contact, visc_max, px, py, pz, R,
    gx, gy, gz, vx, vy, vz, ox, oy, oz, out,
):  # fmt: skip
    """Add the static prisms' contact force and torque on the hull to ``out`` (6,), the model
    of :func:`plane_contacts` against convex prisms (the docking station's boxes and guide
    plates) instead of planes: a sphere that reaches ``delta`` into a prism (exact distance,
    :func:`prism_distance`) pushes back along the prism's normal at its deepest point. Each
    hull shape's contacts are averaged (its spheres sample one shape, which touches as one
    body: a capsule lying on a face is as stiff as one touching it with its end), so the
    stiffness and damping added up over the hull stay within what the explicit substep holds.

    Args:
        spheres: (s, 4) centre in the body FLU frame (m) and radius (m): the hull's shapes as
            overlapping spheres (:func:`uwdock.sim.kernel_contact.hull_contact_spheres`).
        chunks: (c, 6) runs of neighbouring spheres: first and end row, the body-frame centre
            (3) and radius (m) of a ball holding them.
        shapes: (h, 6) the hull's shapes, the averaging unit: first and end row of their
            chunks, and a ball around them (centre (3), radius; m).
        prisms: (m, :data:`PRISM_COLS`) world prisms.
        pairs, n_pairs: the (chunk, prism, shape) triples to test, shape by shape
            (:func:`prism_pairs`).
        contact: (5,) as for :func:`plane_contacts` (stiffness, damping, friction unused: each
            prism has its own, ``v_eps``, reach); visc_max: cap of the friction's slope at rest
            (N s/m).
        Others as for :func:`plane_contacts`.
    """
    # every pair with all its chunk's spheres: the kernel's listed pairs, none left out
    active = np.empty((n_pairs, 5), dtype=np.int64)
    n = 0
    for q in range(n_pairs):
        g = pairs[q, 0]
        active[q, 0], active[q, 1], active[q, 2] = g, pairs[q, 1], pairs[q, 2]
        active[q, 3], active[q, 4] = n, n + int(chunks[g, 1]) - int(chunks[g, 0])
        n = active[q, 4]
    listed = np.empty(n, dtype=np.int64)
    for q in range(n_pairs):
        for t in range(active[q, 3], active[q, 4]):
            listed[t] = int(chunks[pairs[q, 0], 0]) + t - active[q, 3]
    _listed_contacts(
        spheres, chunks, prisms, active, n_pairs, listed, contact, visc_max, px, py, pz, R,
        gx, gy, gz, vx, vy, vz, ox, oy, oz, np.empty(6), out,
    )  # fmt: skip


@njit(cache=True)
def _listed_contacts(
    spheres, chunks, prisms, active, n_active, listed, contact, visc_max, px, py, pz, R,
    gx, gy, gz, vx, vy, vz, ox, oy, oz, part, out,
):  # fmt: skip
    """:func:`prism_contacts` over the pairs of :func:`near_pairs` (``active``), each pair's
    spheres those ``listed`` for it; ``part``: a (6,) buffer."""
    k, c, v_eps = contact[0], contact[1], contact[3]
    q = 0
    while q < n_active:
        sh = active[q, 2]
        part[:] = 0.0
        count = 0
        while q < n_active and active[q, 2] == sh:
            g, o = active[q, 0], prisms[active[q, 1]]
            s0, s1 = active[q, 3], active[q, 4]
            q += 1
            bx, by, bz, rg = chunks[g, 2], chunks[g, 3], chunks[g, 4], chunks[g, 5]
            cxg = px + R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz
            cyg = py + R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz
            czg = pz + R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz
            if _outside(o, cxg, cyg, czg, rg):
                continue
            for t in range(s0, s1):
                count += _sphere_contact(
                    spheres, listed[t], o, k, c, o[19], v_eps, visc_max, px, py, pz, R,
                    gx, gy, gz, vx, vy, vz, ox, oy, oz, part,
                )  # fmt: skip
        if count > 0:
            for a in range(6):
                out[a] += part[a] / count


@njit(cache=True)
def _sphere_contact(
    spheres, i, o, k, c, mu, v_eps, visc_max, px, py, pz, R, gx, gy, gz,
    vx, vy, vz, ox, oy, oz, part,
):  # fmt: skip
    """Sphere ``i`` against prism row ``o``: its contact added to ``part``; 1 if it
    touches, else 0."""
    sx, sy, sz, rad = spheres[i, 0], spheres[i, 1], spheres[i, 2], spheres[i, 3]
    wx = px + R[0, 0] * sx + R[0, 1] * sy + R[0, 2] * sz
    wy = py + R[1, 0] * sx + R[1, 1] * sy + R[1, 2] * sz
    wz = pz + R[2, 0] * sx + R[2, 1] * sy + R[2, 2] * sz
    if _outside(o, wx, wy, wz, rad):
        return 0
    d, nx, ny, nz = prism_distance(o, wx, wy, wz)
    delta = rad - d
    if delta <= 0.0:
        return 0
    _penalty(
        k, c, mu, v_eps, visc_max, delta, nx, ny, nz,
        wx - rad * nx - gx, wy - rad * ny - gy, wz - rad * nz - gz,
        vx, vy, vz, ox, oy, oz, part,
    )  # fmt: skip
    return 1


# --------------------------------------------------------------------------- free flight


@njit(cache=True)
def _rot(R, qw, qx, qy, qz):
    """Write the (3, 3) rotation matrix of a unit quaternion (w, x, y, z) into ``R``."""
    R[0, 0] = 1.0 - 2.0 * (qy * qy + qz * qz)
    R[0, 1] = 2.0 * (qx * qy - qw * qz)
    R[0, 2] = 2.0 * (qx * qz + qw * qy)
    R[1, 0] = 2.0 * (qx * qy + qw * qz)
    R[1, 1] = 1.0 - 2.0 * (qx * qx + qz * qz)
    R[1, 2] = 2.0 * (qy * qz - qw * qx)
    R[2, 0] = 2.0 * (qx * qz - qw * qy)
    R[2, 1] = 2.0 * (qy * qz + qw * qx)
    R[2, 2] = 1.0 - 2.0 * (qx * qx + qy * qy)


@njit(cache=True)
def _separated(ax, ay, az, d, rh, R0, sweep_h, grow, obs):
    """Whether axis (ax, ay, az) (any length) separates a swept hull box from an obstacle's
    oriented box: ``d`` the centres' offset (obstacle minus hull, world), ``rh`` the hull
    box's half size along the body axes ``R0``'s columns, ``sweep_h`` the origin path's
    half extent per world axis, ``grow`` the radius of the ball added (m)."""
    ln = math.sqrt(ax * ax + ay * ay + az * az)
    if ln < 1e-9:
        return False  # a degenerate cross product: no axis
    dist = abs(ax * d[0] + ay * d[1] + az * d[2])
    r = grow * ln + abs(ax) * sweep_h[0] + abs(ay) * sweep_h[1] + abs(az) * sweep_h[2]
    for i in range(3):
        r += rh[i] * abs(ax * R0[0, i] + ay * R0[1, i] + az * R0[2, i])
        r += obs[10 + i] * abs(
            ax * obs[13 + i] + ay * obs[16 + i] + az * obs[19 + i]
        )  # obstacle half size along its own axis i (column i of its rotation)
    return dist > r


@njit(cache=True)
def _apart(d, rh, R0, sweep_h, grow, obs):
    """Whether one of the separating axes (the obstacle's three, the hull box's three, their
    nine cross products) keeps the swept hull box off the obstacle (:func:`_separated`)."""
    for k in range(3):
        if _separated(obs[13 + k], obs[16 + k], obs[19 + k], d, rh, R0, sweep_h, grow, obs):
            return True
        if _separated(R0[0, k], R0[1, k], R0[2, k], d, rh, R0, sweep_h, grow, obs):
            return True
    for k in range(3):  # hull axis k x obstacle axis m
        hx, hy, hz = R0[0, k], R0[1, k], R0[2, k]
        for m in range(3):
            ox, oy, oz = obs[13 + m], obs[16 + m], obs[19 + m]
            if _separated(
                hy * oz - hz * oy, hz * ox - hx * oz, hx * oy - hy * ox,
                d, rh, R0, sweep_h, grow, obs,
            ):  # fmt: skip
                return True
    return False


@njit(cache=True)
def _overlaps(boxes, obstacles, lo, hi, R0, theta, margin):
    """Whether a hull box may touch an obstacle box during the step.

    Hull box i (``boxes[i]``: centre, half size in the body frame, ``rho``) at attitude ``R0``,
    swept over the origin positions [lo, hi] and grown by ``margin + rho * theta`` for the
    rotation, against the obstacles (z-up world; :data:`OBSTACLE_COLS` per row). First their
    world boxes; where those overlap and the obstacle has an oriented box, the separating-axis
    test of the swept set against it (the obstacle's and the hull box's axes and their cross
    products: an axis that separates proves there is no contact, so the test stays on the safe
    side, and a tilted guide plate no longer claims the whole box around it).
    """
    bmin = np.empty(3)
    bmax = np.empty(3)
    cen = np.empty(3)
    d = np.empty(3)
    rh = np.empty(3)
    sweep_h = np.empty(3)
    for a in range(3):
        sweep_h[a] = 0.5 * (hi[a] - lo[a])
    for i in range(boxes.shape[0]):
        grow = margin + boxes[i, 6] * theta
        for a in range(3):
            c = R0[a, 0] * boxes[i, 0] + R0[a, 1] * boxes[i, 1] + R0[a, 2] * boxes[i, 2]
            h = (
                abs(R0[a, 0]) * boxes[i, 3]
                + abs(R0[a, 1]) * boxes[i, 4]
                + abs(R0[a, 2]) * boxes[i, 5]
                + grow
            )
            bmin[a] = lo[a] + c - h
            bmax[a] = hi[a] + c + h
            cen[a] = 0.5 * (lo[a] + hi[a]) + c
        rh[0], rh[1], rh[2] = boxes[i, 3], boxes[i, 4], boxes[i, 5]
        for j in range(obstacles.shape[0]):
            o = obstacles[j]
            if not (
                bmin[0] <= o[3] and bmax[0] >= o[0]
                and bmin[1] <= o[4] and bmax[1] >= o[1]
                and bmin[2] <= o[5] and bmax[2] >= o[2]
            ):  # fmt: skip
                continue
            if o[6] == 0.0:
                return True  # no oriented box (a plane): the world boxes decide
            for a in range(3):
                d[a] = o[7 + a] - cen[a]
            if not _apart(d, rh, R0, sweep_h, grow, o):
                return True
    return False


@njit(cache=True)
def _advance(
    P, B, state, wrenches, currents, dt, k0, k1, acc, spheres, planes, contact, sweep,
    ksph, kchunks, kshapes, prisms, pairs, near_m,
):  # fmt: skip
    """Integrate substeps ``k0 .. k1 - 1`` in place on ``state`` (:func:`free_flight`'s
    arguments), PhysX's integration without contacts; ``acc`` gets the last substep's
    accelerations and ``sweep`` (7,) the swept origin box [min xyz, max xyz] and the rotation
    angle ``theta`` (rad) of the substeps. ``ksph``, ``kchunks``, ``kshapes``, ``prisms``: the
    static prisms' contact (:func:`prism_contacts`; no prisms: none); ``pairs``: a buffer of
    at least chunks x prisms rows, 3 columns (int64) for :func:`prism_pairs`; ``near_m``: the
    pairs tested at a substep are those within this of their prism when last chosen
    (:data:`PRISM_NEAR_M`, :func:`near_pairs`; ``inf``: every pair)."""
    w_max, me, ie0, ie1, ie2 = B[4], B[5], B[6], B[7], B[8]  # PhysX's copies
    cx, cy, cz = P[5], -P[6], -P[7]  # CoM in body FLU
    px, py, pz = state[0], state[1], state[2]
    qw, qx, qy, qz = state[3], state[4], state[5], state[6]
    vx, vy, vz = state[7], state[8], state[9]
    ox, oy, oz = state[10], state[11], state[12]
    R = np.empty((3, 3))
    _rot(R, qw, qx, qy, qz)
    lo = np.array([px, py, pz])
    hi = lo.copy()
    theta = 0.0
    # the CoM (PhysX's body frame) from the entity pose
    gx = px + R[0, 0] * cx + R[0, 1] * cy + R[0, 2] * cz
    gy = py + R[1, 0] * cx + R[1, 1] * cy + R[1, 2] * cz
    gz = pz + R[2, 0] * cx + R[2, 1] * cy + R[2, 2] * cz
    inv_me = 1.0 / me
    v0x = v0y = v0z = o0x = o0y = o0z = 0.0
    touch = np.zeros(6)
    with_planes = planes.shape[0] > 0
    with_prisms = prisms.shape[0] > 0
    visc_max = PRISM_FRICTION_STEP * me / dt  # a fifth of the sliding speed per substep at most
    n_pairs = 0
    if with_prisms:
        # the pairs that may touch within the substeps: the hull moves at most this far (its
        # speed now, a generous bound on what thrust and contact add over the call, m)
        span = (k1 - k0) * dt
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)
        spin = math.sqrt(ox * ox + oy * oy + oz * oz) * contact[4]
        margin = (speed + spin) * span + 0.5 * PRISM_ACCEL_BOUND * span * span + 0.01
        n_pairs = prism_pairs(kchunks, kshapes, prisms, px, py, pz, R, margin, pairs)
        with_prisms = n_pairs > 0
    # the pairs and spheres near enough to test, chosen again when the hull may have moved
    # near_m: the hull's largest reach from the origin (its shapes' balls) turns the rotation
    # since into a distance
    active = np.empty((n_pairs, 5), dtype=np.int64)
    per_chunk = 0
    for g in range(kchunks.shape[0] if with_prisms else 0):
        per_chunk = max(per_chunk, int(kchunks[g, 1]) - int(kchunks[g, 0]))
    listed = np.empty(n_pairs * per_chunk, dtype=np.int64)
    part = np.empty(6)
    n_active = -1
    reach = 0.0
    for h in range(kshapes.shape[0] if with_prisms else 0):
        b = math.sqrt(kshapes[h, 2] ** 2 + kshapes[h, 3] ** 2 + kshapes[h, 4] ** 2)
        reach = max(reach, b + kshapes[h, 5])
    rx, ry, rz, rtheta = px, py, pz, theta
    for k in range(k0, k1):
        v0x, v0y, v0z, o0x, o0y, o0z = vx, vy, vz, ox, oy, oz
        f = _bridge(
            P, B, pz, qw, qx, qy, qz, vx, vy, vz, ox, oy, oz,
            currents[k, 0], currents[k, 1], currents[k, 2],
            wrenches[k, 0], wrenches[k, 1], wrenches[k, 2],
            wrenches[k, 3], wrenches[k, 4], wrenches[k, 5],
        )  # fmt: skip
        f0, f1, f2, f3, f4, f5 = f[0], f[1], f[2], f[3], f[4], f[5]
        if with_planes:
            touch[:] = 0.0
            plane_contacts(
                spheres, planes, contact, px, py, pz, R, gx, gy, gz,
                vx, vy, vz, ox, oy, oz, touch,
            )  # fmt: skip
            f0, f1, f2 = f0 + touch[0], f1 + touch[1], f2 + touch[2]
            f3, f4, f5 = f3 + touch[3], f4 + touch[4], f5 + touch[5]
        if with_prisms:
            moved = math.sqrt((px - rx) ** 2 + (py - ry) ** 2 + (pz - rz) ** 2)
            moved += (theta - rtheta) * reach
            if n_active < 0 or moved > near_m - PRISM_NEAR_SLACK_M:
                n_active = near_pairs(
                    ksph, kchunks, prisms, pairs, n_pairs, px, py, pz, R, near_m, active, listed
                )
                rx, ry, rz, rtheta = px, py, pz, theta
            touch[:] = 0.0
            _listed_contacts(
                ksph, kchunks, prisms, active, n_active, listed, contact, visc_max,
                px, py, pz, R, gx, gy, gz, vx, vy, vz, ox, oy, oz, part, touch,
            )  # fmt: skip
            f0, f1, f2 = f0 + touch[0], f1 + touch[1], f2 + touch[2]
            f3, f4, f5 = f3 + touch[3], f4 + touch[4], f5 + touch[5]
        # external force and torque: v += dt F / m_e, w += dt R I_e^-1 R^T T
        vx += dt * f0 * inv_me
        vy += dt * f1 * inv_me
        vz += dt * f2 * inv_me
        tlx = R[0, 0] * f3 + R[1, 0] * f4 + R[2, 0] * f5
        tly = R[0, 1] * f3 + R[1, 1] * f4 + R[2, 1] * f5
        tlz = R[0, 2] * f3 + R[1, 2] * f4 + R[2, 2] * f5
        ax_, ay_, az_ = dt * tlx / ie0, dt * tly / ie1, dt * tlz / ie2
        ox += R[0, 0] * ax_ + R[0, 1] * ay_ + R[0, 2] * az_
        oy += R[1, 0] * ax_ + R[1, 1] * ay_ + R[1, 2] * az_
        oz += R[2, 0] * ax_ + R[2, 1] * ay_ + R[2, 2] * az_
        w2 = ox * ox + oy * oy + oz * oz
        if w2 > w_max * w_max:
            s = math.sqrt(w_max * w_max / w2)
            ox, oy, oz = ox * s, oy * s, oz * s
        # gyroscopic term, momentum-norm preserving, in the body frame at the start attitude
        wlx = R[0, 0] * ox + R[1, 0] * oy + R[2, 0] * oz
        wly = R[0, 1] * ox + R[1, 1] * oy + R[2, 1] * oz
        wlz = R[0, 2] * ox + R[1, 2] * oy + R[2, 2] * oz
        lx, ly, lz = ie0 * wlx, ie1 * wly, ie2 * wlz
        nx = lx - dt * (wly * lz - wlz * ly)
        ny = ly - dt * (wlz * lx - wlx * lz)
        nz = lz - dt * (wlx * ly - wly * lx)
        den = math.sqrt(nx * nx + ny * ny + nz * nz)
        ratio = math.sqrt(lx * lx + ly * ly + lz * lz) / den if den > 0.0 else 0.0
        dwx = nx * ratio / ie0 - wlx
        dwy = ny * ratio / ie1 - wly
        dwz = nz * ratio / ie2 - wlz
        ox += R[0, 0] * dwx + R[0, 1] * dwy + R[0, 2] * dwz
        oy += R[1, 0] * dwx + R[1, 1] * dwy + R[1, 2] * dwz
        oz += R[2, 0] * dwx + R[2, 1] * dwy + R[2, 2] * dwz
        # pose: CoM position, then the closed-form rotation q <- normalise(dq * q)
        gx += vx * dt
        gy += vy * dt
        gz += vz * dt
        w = math.sqrt(ox * ox + oy * oy + oz * oz)
        if w != 0.0:
            half = 0.5 * dt * w
            s = math.sin(half) / w
            c = math.cos(half)
            ex, ey, ez = ox * s, oy * s, oz * s
            nw = c * qw - ex * qx - ey * qy - ez * qz
            nqx = c * qx + ex * qw + ey * qz - ez * qy
            nqy = c * qy + ey * qw + ez * qx - ex * qz
            nqz = c * qz + ez * qw + ex * qy - ey * qx
            inv = 1.0 / math.sqrt(nw * nw + nqx * nqx + nqy * nqy + nqz * nqz)
            qw, qx, qy, qz = nw * inv, nqx * inv, nqy * inv, nqz * inv
            _rot(R, qw, qx, qy, qz)
            theta += w * dt
        # the entity origin, for the swept volume
        px = gx - (R[0, 0] * cx + R[0, 1] * cy + R[0, 2] * cz)
        py = gy - (R[1, 0] * cx + R[1, 1] * cy + R[1, 2] * cz)
        pz = gz - (R[2, 0] * cx + R[2, 1] * cy + R[2, 2] * cz)
        lo[0], hi[0] = min(lo[0], px), max(hi[0], px)
        lo[1], hi[1] = min(lo[1], py), max(hi[1], py)
        lo[2], hi[2] = min(lo[2], pz), max(hi[2], pz)
    state[0], state[1], state[2] = px, py, pz
    state[3], state[4], state[5], state[6] = qw, qx, qy, qz
    state[7], state[8], state[9] = vx, vy, vz
    state[10], state[11], state[12] = ox, oy, oz
    if k1 > k0:
        inv_dt = 1.0 / dt
        acc[0], acc[1], acc[2] = (vx - v0x) * inv_dt, (vy - v0y) * inv_dt, (vz - v0z) * inv_dt
        acc[3], acc[4], acc[5] = (ox - o0x) * inv_dt, (oy - o0y) * inv_dt, (oz - o0z) * inv_dt
    sweep[0], sweep[1], sweep[2] = lo[0], lo[1], lo[2]
    sweep[3], sweep[4], sweep[5] = hi[0], hi[1], hi[2]
    sweep[6] = theta


@njit(cache=True)
def free_flight(
    P, B, state, wrenches, currents, dt, boxes, obstacles, margin, acc, spheres, planes, contact
):
    """Integrate ``n`` substeps without PhysX, exactly as PhysX would without contacts, as far
    as no contact with an obstacle is possible.

    The whole step is integrated and its swept volume tested first; when a contact was
    possible, the step is integrated again in chunks of :data:`CHUNK_SUBSTEPS`, each tested on
    its own (a smaller swept volume), up to the first chunk that may touch: PhysX takes over
    from there.

    Args:
        P: (76,) :func:`hydro_params`; B: (9,) :func:`body_params`.
        state: (13,) in/out: entity position (3, z-up, m), attitude (w, x, y, z), CoM velocity
            (3, m/s) and angular velocity (3, rad/s), z-up world. Overwritten with the state
            after the substeps integrated here.
        wrenches: (n, 6) thruster wrench per substep (FRD, N, N m); currents: (n, 3) water
            velocity per substep (z-up world, m/s).
        dt: substep (s).
        boxes: (s, 7) hull shapes in the body FLU frame: centre (3), half size (3), and
            ``rho``, the largest distance of the shape from the body origin (m).
        obstacles: (k, :data:`OBSTACLE_COLS`) static boxes: world box [min xyz, max xyz] and
            oriented box, z-up world (m).
        margin: clearance below which a contact counts as possible (m).
        acc: (6,) out: last integrated substep's CoM and angular acceleration, z-up world.
        spheres, planes, contact: the tank planes, whose contact is ours, not PhysX's
            (:func:`plane_contacts`), added to the force and torque of every substep.

    Returns:
        How many substeps were integrated: ``n`` when no hull shape came within ``margin`` of
        an obstacle box (the result is then what PhysX would have produced), else the
        substeps before the first chunk that may touch (PhysX must run the rest from
        ``state``).
    """
    n = wrenches.shape[0]
    no_pairs = np.empty((0, 3), dtype=np.int64)
    start = state.copy()
    trial = state.copy()
    sweep = np.empty(7)
    a = np.zeros(6)
    R0 = np.empty((3, 3))
    _advance(
        P, B, trial, wrenches, currents, dt, 0, n, a, spheres, planes, contact, sweep,
        _NO_SPHERES, _NO_CHUNKS, _NO_CHUNKS, _NO_PRISMS, no_pairs, 0.0,
    )  # fmt: skip
    _rot(R0, start[3], start[4], start[5], start[6])
    if not _overlaps(boxes, obstacles, sweep[:3], sweep[3:6], R0, sweep[6], margin):
        state[:] = trial
        acc[:] = a
        return n
    # chunk by chunk from the start, up to the first chunk that may touch
    done = 0
    while done < n:
        end = min(n, done + CHUNK_SUBSTEPS)
        trial[:] = start
        _advance(
            P, B, trial, wrenches, currents, dt, done, end, a, spheres, planes, contact, sweep,
            _NO_SPHERES, _NO_CHUNKS, _NO_CHUNKS, _NO_PRISMS, no_pairs, 0.0,
        )  # fmt: skip
        _rot(R0, start[3], start[4], start[5], start[6])
        if _overlaps(boxes, obstacles, sweep[:3], sweep[3:6], R0, sweep[6], margin):
            break
        start[:] = trial
        acc[:] = a
        done = end
    state[:] = start
    return done


@njit(cache=True)
def free_flight_all(
    P, B, state, wrenches, currents, dt, hull, obstacles, n_obstacles, margin, acc,
    spheres, planes, contact,
):  # fmt: skip
    """:func:`free_flight` for every vehicle; (N,) int64: the substeps integrated per vehicle
    (all of them, or PhysX must run the rest from the vehicle's ``state`` row; ``acc`` rows
    of vehicles with none integrated are untouched). ``n_obstacles[i] < 0`` forces PhysX for
    vehicle ``i`` (0 substeps).

    It lives beside :func:`free_flight` on purpose: numba's on-disk cache of a function is
    invalidated by a change of its own file only, not of the functions it compiles in."""
    n = state.shape[0]
    out = np.zeros(n, dtype=np.int64)
    row = np.empty(13)
    a = np.zeros(6)
    for i in range(n):
        k = n_obstacles[i]
        if k < 0:
            continue
        row[:] = state[i]
        done = free_flight(
            P[i], B[i], row, wrenches[i], currents[i], dt, hull, obstacles[i, :k], margin, a,
            spheres, planes, contact[i],
        )  # fmt: skip
        state[i] = row
        if done > 0:
            acc[i] = a
        out[i] = done
    return out


@njit(cache=True)
def kernel_flight_all(
    P, B, state, wrenches, currents, dt, acc, spheres, planes, contact, ksph, kchunks,
    kshapes, prisms, n_prisms, near_m=PRISM_NEAR_M,
):  # fmt: skip
    """Every vehicle's whole control step in the kernel, the docking station's contact
    included (:func:`prism_contacts` against its ``n_prisms[i]`` rows of ``prisms``), PhysX
    nowhere: ``state`` and ``acc`` (N, 6) rows are overwritten (:func:`free_flight`'s
    arguments per vehicle). Beside :func:`free_flight_all` for numba's cache (its note)."""
    row = np.empty(13)
    a = np.zeros(6)
    sweep = np.empty(7)
    n_sub = wrenches.shape[1]
    pairs = np.empty((kchunks.shape[0] * prisms.shape[1], 3), dtype=np.int64)
    for i in range(state.shape[0]):
        row[:] = state[i]
        _advance(
            P[i], B[i], row, wrenches[i], currents[i], dt, 0, n_sub, a, spheres, planes,
            contact[i], sweep, ksph, kchunks, kshapes, prisms[i, : n_prisms[i]], pairs,
            near_m,
        )  # fmt: skip
        state[i] = row
        acc[i] = a


# --------------------------------------------------------------------------- geometry


def _pose_T(pose: sapien.Pose) -> np.ndarray:
    return T_from_pos_quat(np.asarray(pose.p, dtype=float), np.asarray(pose.q, dtype=float))


def _shape_box(shape: sapien.physx.PhysxCollisionShape) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre and half size (m) of a shape's box in its own frame; None if unbounded."""
    px = sapien.physx
    zero = np.zeros(3)
    if isinstance(shape, px.PhysxCollisionShapeBox):
        return zero, np.asarray(shape.get_half_size(), dtype=float)
    if isinstance(shape, px.PhysxCollisionShapeSphere):
        return zero, np.full(3, float(shape.get_radius()))
    if isinstance(shape, px.PhysxCollisionShapeCapsule):  # axis x
        r, h = float(shape.get_radius()), float(shape.get_half_length())
        return zero, np.array([h + r, r, r])
    if isinstance(shape, px.PhysxCollisionShapeCylinder):  # axis x
        r, h = float(shape.get_radius()), float(shape.get_half_length())
        return zero, np.array([h, r, r])
    if isinstance(shape, (px.PhysxCollisionShapeConvexMesh, px.PhysxCollisionShapeTriangleMesh)):
        v = np.asarray(shape.get_vertices(), dtype=float) * np.asarray(shape.get_scale(), float)
        lo, hi = v.min(axis=0), v.max(axis=0)
        return (lo + hi) / 2.0, (hi - lo) / 2.0
    return None


def hull_boxes(component: sapien.physx.PhysxRigidBaseComponent) -> np.ndarray:
    """(s, 7) boxes of a body's collision shapes in its entity frame (FLU for the vehicle):
    centre (3), half size (3) and ``rho`` (the shape's farthest possible point from the
    entity origin, m), each grown by the shape's contact offset."""
    rows = []
    for shape in component.get_collision_shapes():
        box = _shape_box(shape)
        if box is None:
            raise ValueError(f"cannot bound a {type(shape).__name__} hull shape")
        T = _pose_T(shape.get_local_pose())
        c = T[:3, :3] @ box[0] + T[:3, 3]
        h = np.abs(T[:3, :3]) @ box[1] + float(shape.get_contact_offset())
        rows.append([*c, *h, float(np.linalg.norm(c) + np.linalg.norm(h))])
    return np.ascontiguousarray(np.array(rows, dtype=float).reshape(-1, 7))


def _plane_box(T_world_shape: np.ndarray) -> np.ndarray:
    """World box of a PhysX plane (solid where local x <= 0): a half-space when the normal is
    along a world axis, else everything."""
    n, o = T_world_shape[:3, 0], T_world_shape[:3, 3]
    box = np.array([-_FAR, -_FAR, -_FAR, _FAR, _FAR, _FAR])
    j = int(np.argmax(np.abs(n)))
    if abs(n[j]) > 1.0 - 1e-9:
        if n[j] > 0:
            box[3 + j] = o[j]
        else:
            box[j] = o[j]
    return box


class StaticsWatch:
    """The static components of a PhysX system as last read, each one's shapes read once
    (``read(component)``) per set of components, and whether any moved since the last look:
    what :class:`StaticObstacles` and :class:`uwdock.sim.kernel_contact.StaticPrisms` rebuild
    their world rows from.

    Attributes:
        statics: the components of the last :meth:`update`; local: ``read`` of each.
    """

    def __init__(self, read) -> None:
        self._read = read
        self.statics: list = []
        self.local: list = []
        self._poses: list[tuple[float, ...]] = []

    def update(self, statics: Sequence) -> bool:
        """Look at ``statics`` (the system's components now); whether the world rows must be
        made again (another set of components, or one of them moved)."""
        if len(statics) != len(self.statics) or any(
            a is not b for a, b in zip(statics, self.statics, strict=True)
        ):
            self.statics = list(statics)
            self.local = [self._read(c) for c in self.statics]
            self._poses = [()] * len(self.statics)
        changed = False
        for i, comp in enumerate(self.statics):
            pose = comp.get_entity_pose()
            key = (*pose.p.tolist(), *pose.q.tolist())
            if key != self._poses[i]:
                self._poses[i] = key
                changed = True
        return changed


class StaticObstacles:
    """World boxes of the collision shapes of a scene's static actors (z-up, m).

    Shapes are read once per set of static actors; their world boxes are recomputed when an
    actor's pose changes (checked on every :meth:`boxes` call, ~1 us per actor).

    Args:
        scene: the SAPIEN scene.
        own: the vehicle's component: the fast path needs it to be the only dynamic body.
    """

    def __init__(self, scene: sapien.Scene, own: sapien.physx.PhysxRigidDynamicComponent):
        self.system = scene.physx_system
        self.own = own
        self._watch = StaticsWatch(self._read_shapes)
        self._boxes = np.zeros((0, 6))

    def follow(self, scene: sapien.Scene) -> None:
        """Read the statics of ``scene``'s PhysX system from now on (the same actors moved into
        a fresh system keep their shapes: nothing is read again)."""
        self.system = scene.physx_system

    def boxes(self) -> np.ndarray | None:
        """(k, :data:`OBSTACLE_COLS`) per static shape, each grown by its contact offset; None
        when the fast path cannot stand in for ``scene.step()`` (another dynamic body or an
        articulation, or a GPU PhysX system)."""
        system = self.system
        if not isinstance(system, sapien.physx.PhysxCpuSystem):
            return None
        dyn = system.get_rigid_dynamic_components()
        if len(dyn) != 1 or dyn[0] is not self.own or system.get_articulation_link_components():
            return None
        if self._watch.update(system.get_rigid_static_components()):
            self._boxes = self._world_boxes()
        return self._boxes

    @staticmethod
    def _read_shapes(comp) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per shape: local pose (4, 4), box centre, half size (grown), is-plane flag."""
        Ts, cs, hs, planes = [], [], [], []
        for shape in comp.get_collision_shapes():
            T = _pose_T(shape.get_local_pose())
            box = _shape_box(shape)
            plane = isinstance(shape, sapien.physx.PhysxCollisionShapePlane)
            if box is None:
                box = (np.zeros(3), np.full(3, 0.0 if plane else _FAR))
            Ts.append(T)
            cs.append(box[0])
            hs.append(box[1] + float(shape.get_contact_offset()))
            planes.append(plane)
        return (
            np.array(Ts).reshape(-1, 4, 4),
            np.array(cs).reshape(-1, 3),
            np.array(hs).reshape(-1, 3),
            np.array(planes, dtype=bool),
        )

    def _world_boxes(self) -> np.ndarray:
        out = []
        for comp, (Ts, cs, hs, planes) in zip(self._watch.statics, self._watch.local, strict=True):
            T_we = _pose_T(comp.get_entity_pose())
            T_ws = T_we[None] @ Ts  # (m, 4, 4)
            R = T_ws[:, :3, :3]
            c = np.einsum("mij,mj->mi", R, cs) + T_ws[:, :3, 3]
            h = np.einsum("mij,mj->mi", np.abs(R), hs)
            rows = np.zeros((len(Ts), OBSTACLE_COLS))
            rows[:, :6] = np.concatenate([c - h, c + h], axis=1)
            rows[:, 6] = 1.0
            rows[:, 7:10] = c
            rows[:, 10:13] = hs
            rows[:, 13:22] = R.reshape(-1, 9)
            for i in np.flatnonzero(planes | (hs >= _FAR).any(axis=1)):
                rows[i, 6:] = 0.0  # unbounded: the world box alone
            for i in np.flatnonzero(planes):
                rows[i, :6] = _plane_box(T_ws[i])
                rows[i, :3] -= hs[i]  # the contact offset
                rows[i, 3:6] += hs[i]
            rows[:, :6] = np.clip(rows[:, :6], -_FAR, _FAR)
            out.append(rows)
        if not out:
            return np.zeros((0, OBSTACLE_COLS))
        return np.ascontiguousarray(np.concatenate(out, axis=0))
