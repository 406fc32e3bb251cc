"""The docking station's contact in the numba kernel (``batch_contact = "kernel"``): exact prism
distances, the hull's spheres, the contact law against hand-computed forces, free flight equal
to the PhysX paths, and a policy trained with PhysX contact still docking on it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import sapien
from scipy.optimize import minimize
from scipy.spatial import ConvexHull

from uwdock.dockcore.config import from_dict, read_toml, replace
from uwdock.sim.fastpath import PRISM_COLS, prism_contacts, prism_distance, prism_pairs
from uwdock.sim.kernel_contact import (
    PrismSet,
    StaticPrisms,
    _local_prism,
    hull_contact_spheres,
    prism_rows,
)
from uwdock.sim.vehicle import DEFAULT_COLLISION, CollisionShape

ROOT = Path(__file__).resolve().parent.parent
POLICY = ROOT / "rl" / "policies" / "realistic_ppo"


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_the_distance_to_a_rotated_box_is_exact():
    h = np.array([0.3, 0.2, 0.05])
    poly = np.array([[-h[1], -h[2]], [h[1], -h[2]], [h[1], h[2]], [-h[1], h[2]]])
    R = _rot([1.0, 2.0, -0.5], 0.7)
    t = np.array([1.0, -2.0, 3.0])
    row = prism_rows(_T(R, t), [(np.eye(3), np.zeros(3), h[0], poly)], [0.3])[0]
    rng = np.random.default_rng(0)
    for _ in range(500):
        local = rng.uniform(-0.6, 0.6, 3)
        q = np.abs(local) - h
        want = np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0)
        d, nx, ny, nz = prism_distance(row, *(R @ local + t))
        assert d == pytest.approx(want, abs=1e-12)
        n_local = R.T @ np.array([nx, ny, nz])
        assert np.linalg.norm(n_local) == pytest.approx(1.0)
        if want > 1e-6:  # outside: the normal points from the closest point to the point
            closest = np.clip(local, -h, h)
            assert np.allclose(n_local, (local - closest) / want, atol=1e-9)


def _guide_prism_vertices() -> np.ndarray:
    """An X-guide segment as the docking station builds it: a trapezoid (y, height) extruded
    along x (docking_station._add_x_guides)."""
    pts = []
    for yy, hh in ((0.0, 0.196), (0.425, 0.0)):
        for xx in (-0.01, 0.01):
            pts += [(xx, yy, 0.0), (xx, yy, -(hh + 0.08))]
    return np.array(pts)


def test_the_distance_to_an_x_guide_prism_is_exact():
    """Against a numerical minimisation over the prism (outside) and the least face distance
    (inside), for a convex mesh read as SAPIEN holds it."""
    v = _guide_prism_vertices()
    mesh = sapien.physx.PhysxCollisionShapeConvexMesh(
        v, [1.0, 1.0, 1.0], sapien.physx.PhysxMaterial(0.3, 0.3, 0.0)
    )
    local = _local_prism(mesh)
    assert local is not None and local[2] == pytest.approx(0.01)
    R = _rot([0.2, -1.0, 0.4], 1.1)
    t = np.array([0.5, 0.5, -4.0])
    row = prism_rows(_T(R, t), [local], [0.3])[0]
    hull = ConvexHull(v)
    A, b = hull.equations[:, :3], -hull.equations[:, 3]  # A x <= b inside
    rng = np.random.default_rng(1)
    for _ in range(60):
        p = v.mean(axis=0) + rng.uniform(-0.4, 0.4, 3)
        s = A @ p - b
        if (s <= 0).all():
            want = s.max()
        else:
            res = minimize(
                lambda x, p=p: np.sum((x - p) ** 2),
                v.mean(axis=0),
                constraints=[{"type": "ineq", "fun": lambda x: b - A @ x}],
                method="SLSQP",
                options={"ftol": 1e-14, "maxiter": 500},
            )
            want = math.sqrt(res.fun)
        d = prism_distance(row, *(R @ p + t))[0]
        assert d == pytest.approx(want, abs=2e-6)


def test_a_convex_mesh_that_is_not_an_extrusion_is_refused():
    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    mesh = sapien.physx.PhysxCollisionShapeConvexMesh(
        tet, [1.0, 1.0, 1.0], sapien.physx.PhysxMaterial(0.3, 0.3, 0.0)
    )
    with pytest.raises(ValueError, match="not an extruded polygon"):
        _local_prism(mesh)


def test_the_hull_spheres_sample_every_shape():
    spheres, chunks, shapes = hull_contact_spheres(DEFAULT_COLLISION)
    assert len(shapes) == len(DEFAULT_COLLISION)
    # shapes partition the chunks, chunks partition the spheres, in order
    assert shapes[0, 0] == 0 and shapes[-1, 1] == len(chunks)
    assert np.array_equal(shapes[1:, 0], shapes[:-1, 1])
    assert chunks[0, 0] == 0 and chunks[-1, 1] == len(spheres)
    assert np.array_equal(chunks[1:, 0], chunks[:-1, 1])
    flu = np.array([1.0, -1.0, -1.0])
    for sh, (c0, c1) in zip(DEFAULT_COLLISION, shapes[:, :2].astype(int), strict=True):
        rows = spheres[int(chunks[c0, 0]) : int(chunks[c1 - 1, 1])]
        centre = np.asarray(sh.center_m) * flu
        if sh.kind == "capsule":
            r, half = sh.size_m[0], sh.size_m[1]
            assert np.all(rows[:, 3] == r)
            k = "xyz".index(sh.axis)
            t = np.sort(rows[:, k] * flu[k] - sh.center_m[k])
            assert t[0] == pytest.approx(-half) and t[-1] == pytest.approx(half)
            assert np.diff(t).max() <= 0.5 * r + 1e-12  # a flat face sinks <= 3 % of r
            off = np.delete(rows[:, :3] - centre, k, axis=1)
            assert np.abs(off).max() < 1e-12  # on the axis
        else:  # a layer of spheres of the half thickness on the mid-plane, at most r apart
            h = np.asarray(sh.size_m)
            k = int(np.argmin(h))
            local = (rows[:, :3] - centre) * flu
            assert np.all(rows[:, 3] == h[k]) and np.abs(local[:, k]).max() < 1e-12
            for j in {0, 1, 2} - {k}:
                u = np.unique(np.round(local[:, j], 12))
                assert u[0] == pytest.approx(-(h[j] - h[k])) and u[-1] == pytest.approx(h[j] - h[k])
                assert np.diff(u).max() <= h[k] + 1e-12
    # every chunk's ball holds its spheres
    for g in chunks:
        pts = spheres[int(g[0]) : int(g[1])]
        reach = np.linalg.norm(pts[:, :3] - g[2:5], axis=1) + pts[:, 3]
        assert reach.max() <= g[5] + 1e-12


def _contact(k=2.0e5, c=500.0, v_eps=0.01, reach=2.0):
    return np.array([k, c, 0.0, v_eps, reach])


def _floor(mu=0.4, top=0.0):
    """A 4 x 4 x 0.2 m slab whose top face is at z = ``top`` (z-up world)."""
    h = np.array([2.0, 2.0, 0.1])
    poly = np.array([[-h[1], -h[2]], [h[1], -h[2]], [h[1], h[2]], [-h[1], h[2]]])
    return prism_rows(
        _T(np.eye(3), [0.0, 0.0, top - h[2]]), [(np.eye(3), np.zeros(3), 2.0, poly)], [mu]
    )


def _forces(spheres, chunks, shapes, prisms, contact, p, v, w, g=None, visc_max=1e9):
    R = np.eye(3)
    g = p if g is None else g
    pairs = np.empty((len(chunks) * len(prisms), 3), dtype=np.int64)
    n = prism_pairs(chunks, shapes, prisms, *p, R, 0.0, pairs)
    out = np.zeros(6)
    prism_contacts(
        spheres, chunks, shapes, prisms, pairs, n, contact, visc_max, *p, R, *g, *v, *w, out
    )
    return out


def test_the_pairs_a_step_tests_hold_every_sphere_within_the_margin_of_a_prism():
    """prism_pairs keeps the (chunk, prism) pair of every sphere whose surface comes within the
    margin of a prism (brute force over every sphere and prism) at hull poses around the docking
    station's shapes, so a pair it drops cannot touch while the hull moves less than the
    margin."""
    from uwdock.rl.env.batch_env import BatchDockingEnv

    spheres, chunks, shapes = hull_contact_spheres(DEFAULT_COLLISION)
    env = BatchDockingEnv(_env_cfg("kernel"), 1, seed=5)
    try:
        env.reset()
        prisms = env.physics.prisms[0, : env.physics.n_prisms[0]].copy()
    finally:
        env.close()
    lo, hi = prisms[:, :3].min(axis=0), prisms[:, 3:6].max(axis=0)
    chunk_of = np.empty(len(spheres), dtype=int)
    for g, (i0, i1) in enumerate(chunks[:, :2].astype(int)):
        chunk_of[i0:i1] = g
    rng = np.random.default_rng(5)
    pairs = np.empty((len(chunks) * len(prisms), 3), dtype=np.int64)
    near = 0
    for _ in range(12):
        R = _rot(rng.normal(size=3), rng.uniform(0.0, 0.5))
        p = rng.uniform(lo - 0.3, hi + 0.3)
        margin = rng.uniform(0.01, 0.15)
        n = prism_pairs(chunks, shapes, prisms, *p, R, margin, pairs)
        got = {(int(g), int(j)) for g, j, _ in pairs[:n]}
        w = spheres[:, :3] @ R.T + p
        need = {
            (int(chunk_of[i]), j)
            for i in range(len(spheres))
            for j in range(len(prisms))
            if prism_distance(prisms[j], *w[i])[0] - spheres[i, 3] <= margin
        }
        assert need <= got
        assert len(got) < len(chunks) * len(prisms) / 20  # and it culls
        assert (np.diff(pairs[:n, 2]) >= 0).all()  # shape by shape (averaged per shape)
        near += len(need)
    assert near > 0


def test_one_sphere_pressed_into_a_face_gets_the_spring_and_damper_force():
    spheres = np.array([[0.3, 0.0, 0.0, 0.05]])  # body frame, 0.3 m ahead of the origin
    chunks = np.array([[0, 1, 0.3, 0.0, 0.0, 0.05]])
    shapes = np.array([[0, 1, 0.3, 0.0, 0.0, 0.05]])
    k, c = 2.0e5, 500.0
    p = np.array([0.0, 0.0, 0.05 - 0.002])  # the sphere 2 mm into the floor
    vz = -0.01
    out = _forces(spheres, chunks, shapes, _floor(), _contact(k, c), p, [0, 0, vz], [0, 0, 0])
    fn = k * 0.002 - c * vz
    assert out[:3] == pytest.approx([0.0, 0.0, fn])
    # torque about the CoM (at the origin) of a force at the sphere's deepest point
    arm = np.array([0.3, 0.0, -0.002])
    assert out[3:] == pytest.approx(np.cross(arm, [0.0, 0.0, fn]), abs=1e-9)
    # clear of the floor: nothing
    p_clear = np.array([0.0, 0.0, 0.0501])
    assert not _forces(
        spheres, chunks, shapes, _floor(), _contact(), p_clear, [0] * 3, [0] * 3
    ).any()


def test_sliding_friction_is_coulomb_and_its_slope_at_rest_is_capped():
    spheres = np.array([[0.0, 0.0, 0.0, 0.05]])
    chunks = np.array([[0, 1, 0.0, 0.0, 0.0, 0.05]])
    shapes = chunks.copy()
    k, mu = 2.0e5, 0.4
    p = np.array([0.0, 0.0, 0.048])
    fn = k * 0.002
    out = _forces(spheres, chunks, shapes, _floor(mu), _contact(k, 0.0), p, [0.5, 0, 0], [0] * 3)
    assert out[0] == pytest.approx(-mu * fn) and out[2] == pytest.approx(fn)
    # creeping at 1 mm/s (below v_eps): regularised, then capped
    slow = [0.001, 0.0, 0.0]
    out = _forces(spheres, chunks, shapes, _floor(mu), _contact(k, 0.0), p, slow, [0] * 3)
    assert out[0] == pytest.approx(-mu * fn * 0.001 / 0.01)
    out = _forces(
        spheres, chunks, shapes, _floor(mu), _contact(k, 0.0), p, slow, [0] * 3, visc_max=1000.0
    )
    assert out[0] == pytest.approx(-1000.0 * 0.001)


def test_a_capsule_lying_on_a_face_is_as_stiff_as_its_end_alone():
    """The contacts of one hull shape are averaged: the force of a capsule lying flat 2 mm deep
    is that of one sphere 2 mm deep, at the capsule's middle."""
    cap = (CollisionShape("capsule", (0.0, 0.0, 0.0), (0.05, 0.3, 0.0), "x"),)
    spheres, chunks, shapes = hull_contact_spheres(cap)
    k = 2.0e5
    p = np.array([0.0, 0.0, 0.048])
    out = _forces(spheres, chunks, shapes, _floor(), _contact(k, 0.0), p, [0] * 3, [0] * 3)
    assert out[2] == pytest.approx(k * 0.002) and abs(out[4]) < 1e-9


def _env_cfg(contact: str):
    from uwdock.rl.train.training import TrainConfig

    cfg = from_dict(TrainConfig, read_toml(POLICY / "config.toml")["train"])
    return replace(cfg.env, world=replace(cfg.env.world, batch_contact=contact))


def test_the_station_reads_as_prisms_where_physx_has_its_shapes():
    """Every static collision shape of a docking world becomes a prism at its PhysX pose (the
    prisms' world boxes span the station's tight PhysX box), and the rows follow the station
    when a reset moves it."""
    from uwdock.rl.env.batch_env import BatchDockingEnv

    env = BatchDockingEnv(_env_cfg("kernel"), 1, seed=5)
    try:
        for _ in range(2):  # the second reset moves the station (and its physics system)
            env.reset()
            body = env.physics.bodies[0]
            rows = env.physics.prisms[0, : env.physics.n_prisms[0]]
            assert np.array_equal(rows, StaticPrisms(body, 0.3).rows())
            assert rows.shape == (42, PRISM_COLS)  # 34 boxes and 8 X-guide prisms
            assert (rows[:, 20] == 4).all()
            (comp,) = [
                c
                for c in body.scene.physx_system.get_rigid_static_components()
                if c.get_collision_shapes()
            ]
            lo, hi = (np.asarray(x, float) for x in comp.compute_global_aabb_tight())
            assert np.allclose(rows[:, :3].min(axis=0), lo, atol=1e-4)
            assert np.allclose(rows[:, 3:6].max(axis=0), hi, atol=1e-4)
    finally:
        env.close()


def test_free_flight_is_the_same_with_and_without_physx_contact():
    """Far from the station both contact models leave the kernel's free flight alone: the
    states of a kernel batch equal a shared-scene batch's bit for bit."""
    from uwdock.rl.env.batch_env import BatchDockingEnv

    rng = np.random.default_rng(3)
    envs = {m: BatchDockingEnv(_env_cfg(m), 3, seed=11) for m in ("shared", "kernel")}
    try:
        for e in envs.values():
            e.reset()
        for _ in range(8):
            a = rng.uniform(-0.3, 0.3, (3, envs["shared"].action_space.shape[0]))
            for e in envs.values():
                e.step(a)
            assert not envs["shared"].physics.last_physx.any()
            assert np.array_equal(envs["shared"].physics.state, envs["kernel"].physics.state)
    finally:
        for e in envs.values():
            e.close()


def test_the_shipped_policy_trained_on_the_kernels_contact_docks_on_physx():
    """Across the seam (policy -> batched env -> contact model -> strict docking): the shipped
    policy, trained with the kernel's contact, docks in 16 episodes with PhysX's contact (one
    shared scene) about as it does on the kernel's (held out on the per-env PhysX env with the
    camera: docs/results/shipped_heldout_policy.json)."""
    from uwdock.rl.evaluate.batched import batched_episodes
    from uwdock.rl.policy.policy_io import load_policy

    model, vn = load_policy(POLICY)
    rows = batched_episodes(model, _env_cfg("shared"), 16, 91000, vecnorm=vn)
    docked = sum(bool(r["success_strict"]) for r in rows)
    assert docked >= 14, [r.get("failure_mode") for r in rows]


def test_a_bar_under_the_middle_of_a_plate_holds_it_up():
    """A station edge across a hull plate's face, far from the plate's edges, is felt: a 20 mm
    bar under the middle of a horizontal 40 mm plate, 2 mm into it, pushes it up with the
    spring force (the plate as edge points alone would fall through it)."""
    plate = (CollisionShape("box", (0.0, 0.0, 0.0), (0.45, 0.25, 0.02), "x"),)
    spheres, chunks, shapes = hull_contact_spheres(plate)
    hb = np.array([0.01, 1.0, 0.05])  # the bar: thin along x, long along y, top at z = 0
    poly = np.array([[-hb[1], -hb[2]], [hb[1], -hb[2]], [hb[1], hb[2]], [-hb[1], hb[2]]])
    bar = prism_rows(
        _T(np.eye(3), [0.0, 0.0, -hb[2]]), [(np.eye(3), np.zeros(3), hb[0], poly)], [0.3]
    )
    k = 2.0e5
    p = np.array([0.0, 0.0, 0.02 - 0.002])
    out = _forces(spheres, chunks, shapes, bar, _contact(k, 0.0), p, [0] * 3, [0] * 3)
    assert out[2] == pytest.approx(k * 0.002) and abs(out[0]) < 1e-9 and abs(out[1]) < 1e-9


def _prism_rows_one_by_one(T, prisms, friction):
    """The world rows prism by prism, each from its own NumPy products (the reference
    :class:`PrismSet` is held to)."""
    out = np.zeros((len(prisms), PRISM_COLS))
    Rw, tw = T[:3, :3], T[:3, 3]
    for j, ((R, c, ht, poly), mu) in enumerate(zip(prisms, friction, strict=True)):
        Rj, cj = Rw @ R, Rw @ c + tw
        pg = np.asarray(poly, dtype=float)
        ends = np.repeat([-ht, ht], len(pg))[:, None]
        corners = np.concatenate([ends, np.tile(pg, (2, 1))], axis=1) @ Rj.T + cj
        out[j, 0:3], out[j, 3:6] = corners.min(axis=0), corners.max(axis=0)
        out[j, 6:9], out[j, 9:18] = cj, Rj.reshape(-1)
        out[j, 18], out[j, 19], out[j, 20] = ht, mu, len(poly)
        out[j, 21:25] = pg[:, 0].min(), pg[:, 0].max(), pg[:, 1].min(), pg[:, 1].max()
        out[j, 25 : 25 + 2 * len(pg)] = pg.reshape(-1)
    return out


def test_the_station_rows_at_any_pose_are_each_prisms_own_to_the_bit():
    """PrismSet (prepared once, stacked products per pose) gives, at random poses of the
    station and polygons of 3 to 8 sides, the rows each prism's own products give, byte for
    byte: the kernel's contact is unchanged by how the rows are made."""
    rng = np.random.default_rng(11)
    prisms = []
    for n in (4, 3, 8, 4, 6, 5):
        ang = np.sort(rng.uniform(0, 2 * math.pi, n))
        poly = np.stack([np.cos(ang), np.sin(ang)], axis=1) * rng.uniform(0.05, 0.4)
        prisms.append((_rot(rng.normal(size=3), rng.uniform(0, 3)), rng.normal(size=3),
                       float(rng.uniform(0.01, 0.5)), poly))  # fmt: skip
    ready = PrismSet(prisms)
    for _ in range(300):
        T = _T(_rot(rng.normal(size=3), rng.uniform(0, 3.1)), rng.normal(size=3) * 5)
        mu = list(rng.uniform(0.1, 0.9, len(prisms)))
        got = ready.rows(T, mu)
        assert got.tobytes() == _prism_rows_one_by_one(T, prisms, mu).tobytes()
    assert PrismSet([]).rows(np.eye(4), []).shape == (0, PRISM_COLS)
    with pytest.raises(ValueError, match="one per prism"):
        ready.rows(np.eye(4), [0.5])


def test_a_control_step_over_the_near_pairs_is_the_step_over_every_pair_to_the_bit():
    """The kernel tests only the pairs, and their spheres, near their prism (PRISM_NEAR_M,
    chosen again as the hull moves): over the shipped policy's approaches and landings on the
    station (8 vehicles, noisy actions, 120 steps), every control step gives the state and
    accelerations that testing every pair and sphere at every substep gives (near_m = inf),
    byte for byte, and the station's contact was there (without it, other states)."""
    import uwdock.sim.batch as batch
    from uwdock.rl.env.batch_env import BatchDockingEnv
    from uwdock.rl.evaluate.episodes import as_controller
    from uwdock.rl.policy.policy_io import load_policy

    seen = {"steps": 0, "touched": 0}
    real = batch.kernel_flight_all

    def both(*args):
        copies = [[a.copy() if isinstance(a, np.ndarray) else a for a in args] for _ in "ab"]
        real(*copies[0], math.inf)
        bare = list(copies[1])
        bare[14] = np.zeros_like(bare[14])  # no prisms: no station contact
        real(*bare)
        real(*args)
        assert args[2].tobytes() == copies[0][2].tobytes()  # state
        assert args[6].tobytes() == copies[0][6].tobytes()  # accelerations
        seen["steps"] += 1
        seen["touched"] += int((args[6] != bare[6]).any(axis=1).sum())

    model, vn = load_policy(POLICY)
    ctrl = as_controller(model, vn)
    env = BatchDockingEnv(_env_cfg("kernel"), 8, seed=21)
    batch.kernel_flight_all = both
    try:
        obs = env.reset()
        rng = np.random.default_rng(2)
        for _ in range(120):
            a = np.asarray(ctrl.act_batch(obs), dtype=float).reshape(8, 6)
            env.step(np.clip(a + 0.3 * rng.standard_normal(a.shape), -1, 1))
    finally:
        batch.kernel_flight_all = real
        env.close()
    assert seen["steps"] == 120
    assert seen["touched"] > 50  # vehicle-steps in contact with the station
