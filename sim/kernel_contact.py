"""The docking station's contact in the numba kernel: the hull as spheres, the DS as prisms.

The batched simulator's third way of stepping a vehicle that touches the docking station
(``[env.world] batch_contact = "kernel"``, :class:`uwdock.sim.batch.BatchVehicles`): no PhysX at
all. The tank planes' contact model (:func:`uwdock.sim.fastpath.plane_contacts`: a spring and
damper along the normal, regularised Coulomb friction along it) is applied against every static
collision shape of the vehicle's scene, integrated with the rest of the control step
(:func:`uwdock.sim.fastpath.kernel_flight_all`):

* **the hull** (:func:`hull_contact_spheres`): a capsule is a row of spheres of its radius
  along its axis, spaced at most half a radius apart (a flat face then sinks at most 3 % of the
  radius between two of them: 4.5 mm for the 0.15 m hull, 0.6 mm for a 20 mm peg); a box is
  a layer of spheres on its mid-plane across its thin axis, of its half thickness, at most that
  far apart (the hull's 40 mm frame plates: 20 mm spheres 20 mm apart, faces within 2.7 mm of
  flat: a thin box with rounded edges);
* **the docking station** (:class:`StaticPrisms`): every box, and every convex mesh that is an
  extruded convex polygon (the X-guides' trapezoidal prisms), as a convex polygon extruded along
  an axis, whose signed distance to a point is exact
  (:func:`uwdock.sim.fastpath.prism_distance`).

What it does not model: a hull box's sharp edges (rounded by its half thickness: meant for
thin plates; a thick box becomes coarse spheres), PhysX's contact offsets (contact starts at
zero distance) and restitution (the damping is critical, as for the planes). The
penetration under full thrust is about a millimetre (:data:`uwdock.sim.physics.
PLANE_STIFFNESS_N_PER_M`). It is a different contact model from PhysX's, not a copy of it:
trajectories in contact differ, and a policy trained on one is checked on the other
(``tests/test_kernel_contact.py``, ``bench/bench_train_speed.py --simulators
batched,batched-kernel``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import sapien

from uwdock.calibration.frames import T_from_pos_quat
from uwdock.sim.fastpath import PRISM_COLS, PRISM_MAX_VERTICES, StaticsWatch

__all__ = [
    "BOX_TILE",
    "CHUNK_SPHERES",
    "PrismSet",
    "StaticPrisms",
    "hull_contact_spheres",
    "prism_rows",
]

#: A hull box's spheres are culled in square tiles of this many a side.
BOX_TILE = 4
#: Spheres per culling run (:func:`hull_contact_spheres`).
CHUNK_SPHERES = 4
_S_BODY = np.array([1.0, -1.0, -1.0])  # FRD <-> FLU component signs
_AXES = {"x": 0, "y": 1, "z": 2}


def _chunks(rows: list[list[float]], first: int, out: list[list[float]], size: int = 0) -> None:
    """Split ``rows[first:]`` (neighbouring spheres, in order) into runs of at most ``size``
    (default :data:`CHUNK_SPHERES`), each with the ball around it (body frame)."""
    size = size or CHUNK_SPHERES
    for a in range(first, len(rows), size):
        b = min(len(rows), a + size)
        pts = np.array(rows[a:b], dtype=float)
        lo, hi = pts[:, :3].min(axis=0), pts[:, :3].max(axis=0)
        c = 0.5 * (lo + hi)
        r = float(np.max(np.linalg.norm(pts[:, :3] - c, axis=1) + pts[:, 3]))
        out.append([a, b, *c, r])


def hull_contact_spheres(shapes) -> tuple[np.ndarray, np.ndarray, int]:
    """The hull's collision shapes (body FRD :class:`uwdock.sim.vehicle.CollisionShape`) as
    spheres in the body FLU frame (module docstring).

    Returns:
        ``(spheres, chunks, shapes)``: (s, 4) centre (m) and radius (m); (c, 6) runs of
        neighbouring spheres (first and end row, the centre (3) and radius (m) of a ball
        around them); (h, 6) per shape the first and end row of its chunks and a ball around
        them: :func:`uwdock.sim.fastpath.prism_contacts` culls shapes, then chunks, and
        averages per shape.
    """
    rows: list[list[float]] = []
    chunks: list[list[float]] = []
    table: list[list[float]] = []
    for sh in shapes:
        first_chunk = len(chunks)
        _shape_spheres(sh, rows, chunks)
        pts = np.array(rows[int(chunks[first_chunk][0]) :], dtype=float)
        lo, hi = pts[:, :3].min(axis=0), pts[:, :3].max(axis=0)
        c = 0.5 * (lo + hi)
        r = float(np.max(np.linalg.norm(pts[:, :3] - c, axis=1) + pts[:, 3]))
        table.append([first_chunk, len(chunks), *c, r])
    return (
        np.ascontiguousarray(np.array(rows, dtype=float).reshape(-1, 4)),
        np.ascontiguousarray(np.array(chunks, dtype=float).reshape(-1, 6)),
        np.ascontiguousarray(np.array(table, dtype=float).reshape(-1, 6)),
    )


def _shape_spheres(sh, rows: list[list[float]], chunks: list[list[float]]) -> None:
    """Append one hull shape's spheres (body FLU) to ``rows`` and their runs to ``chunks``."""
    c = np.asarray(sh.center_m, dtype=float)
    if sh.kind == "capsule":
        r, half = float(sh.size_m[0]), float(sh.size_m[1])
        axis = np.zeros(3)
        axis[_AXES[sh.axis]] = 1.0
        n = max(2, math.ceil(2.0 * half / (0.5 * r)) + 1)
        first = len(rows)
        for t in np.linspace(-half, half, n):
            rows.append([*((c + t * axis) * _S_BODY), r])
        _chunks(rows, first, chunks)
        return
    h = np.asarray(sh.size_m, dtype=float)
    k = int(np.argmin(h))  # the thin axis: one layer of spheres on the mid-plane
    r = float(h[k])
    a, b = [j for j in range(3) if j != k]
    # the rectangle the spheres' centres span (the box less the radius), at most r apart
    na = max(1, math.ceil(2.0 * max(h[a] - r, 0.0) / r) + 1)
    nb = max(1, math.ceil(2.0 * max(h[b] - r, 0.0) / r) + 1)
    ua = np.linspace(-(h[a] - r), h[a] - r, na) if na > 1 else np.zeros(1)
    ub = np.linspace(-(h[b] - r), h[b] - r, nb) if nb > 1 else np.zeros(1)
    for ta in range(0, na, BOX_TILE):  # tiles of BOX_TILE x BOX_TILE spheres, one chunk each
        for tb in range(0, nb, BOX_TILE):
            first = len(rows)
            for ia in range(ta, min(na, ta + BOX_TILE)):
                for ib in range(tb, min(nb, tb + BOX_TILE)):
                    p = np.zeros(3)
                    p[a], p[b] = ua[ia], ub[ib]
                    rows.append([*((c + p) * _S_BODY), r])
            _chunks(rows, first, chunks, len(rows) - first)


def _ccw(pts2: np.ndarray) -> np.ndarray:
    """The convex hull of 2-D points, counter-clockwise (no collinear points)."""
    from scipy.spatial import ConvexHull  # only when a convex mesh is read, once per shape

    return pts2[ConvexHull(pts2).vertices]


def _extrusion(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:
    """A convex mesh's vertices (n, 3) as an extruded convex polygon: ``(R, centre, half
    length, polygon)`` in the mesh frame (R's columns: the extrusion axis and the polygon's
    plane), or None when no axis makes it one."""
    from scipy.spatial import ConvexHull

    tol = 1e-6 * max(1.0, float(np.ptp(v, axis=0).max()))
    for eq in ConvexHull(v).equations:
        n = eq[:3] / np.linalg.norm(eq[:3])
        s = v @ n
        lo, hi = s.min(), s.max()
        at_lo, at_hi = np.abs(s - lo) < tol, np.abs(s - hi) < tol
        if not (at_lo | at_hi).all() or at_lo.sum() != at_hi.sum() or hi - lo < tol:
            continue
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(n, u)
        a2, b2 = v[at_lo] @ np.stack([u, w], 1), v[at_hi] @ np.stack([u, w], 1)
        if not np.allclose(np.sort(a2, axis=0), np.sort(b2, axis=0), atol=tol):
            continue  # the two ends differ: not an extrusion along n
        poly = _ccw(a2)
        mid = 0.5 * (lo + hi)
        return np.stack([n, u, w], axis=1), mid * n, 0.5 * (hi - lo), poly
    return None


def _local_prism(shape) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:
    """``(R, centre, half length, polygon)`` of a static collision shape in its entity's frame;
    None for a plane (the kernel's tank planes hold those)."""
    px = sapien.physx
    T = T_from_pos_quat(
        np.asarray(shape.get_local_pose().p, float), np.asarray(shape.get_local_pose().q, float)
    )
    if isinstance(shape, px.PhysxCollisionShapePlane):
        return None
    if isinstance(shape, px.PhysxCollisionShapeBox):
        h = np.asarray(shape.get_half_size(), dtype=float)
        R, c, ht = np.eye(3), np.zeros(3), float(h[0])
        poly = np.array([[-h[1], -h[2]], [h[1], -h[2]], [h[1], h[2]], [-h[1], h[2]]])
    elif isinstance(shape, px.PhysxCollisionShapeConvexMesh):
        v = np.asarray(shape.get_vertices(), dtype=float) * np.asarray(shape.get_scale(), float)
        got = _extrusion(v)
        if got is None:
            raise ValueError(
                "kernel contact: a static convex mesh that is not an extruded polygon "
                f"({len(v)} vertices); use batch_contact = 'shared'"
            )
        R, c, ht, poly = got
    else:
        raise ValueError(
            f"kernel contact: cannot model a static {type(shape).__name__}; use batch_contact = "
            "'shared'"
        )
    if len(poly) > PRISM_MAX_VERTICES:
        raise ValueError(f"kernel contact: a prism of {len(poly)} > {PRISM_MAX_VERTICES} sides")
    return T[:3, :3] @ R, T[:3, :3] @ c + T[:3, 3], ht, poly


def prism_rows(
    T_world_entity: np.ndarray,
    prisms: Sequence[tuple[np.ndarray, np.ndarray, float, np.ndarray]],
    friction: Sequence[float],
) -> np.ndarray:
    """(m, :data:`PRISM_COLS`) world rows of an entity's prisms (``(R, centre, half length,
    polygon)`` in its frame, :func:`uwdock.sim.fastpath.prism_contacts`), each with its
    Coulomb friction (:class:`PrismSet` once for the prisms, then its world rows)."""
    return PrismSet(prisms).rows(T_world_entity, friction)


class PrismSet:
    """An entity's prisms (``(R, centre, half length, polygon)`` in its frame) made ready
    once for their world rows at any pose (:meth:`rows`, the docking station's at every
    episode): what does not depend on the pose (half length, polygon, its extent, the
    corners in the prism's frame) is kept, and a pose costs a few stacked products instead
    of a dozen NumPy calls per prism. Each row is the one a prism alone would give, to the
    last bit: the same products in the same order (a stack of 3x3 products is the 3x3
    product per matrix; tested against the prism-by-prism rows)."""

    def __init__(self, prisms: Sequence[tuple[np.ndarray, np.ndarray, float, np.ndarray]]):
        m = len(prisms)
        self.n = m
        self._R = np.zeros((m, 3, 3))
        self._c = np.zeros((m, 3, 1))
        self._fixed = np.zeros((m, PRISM_COLS))
        by_sides: dict[int, list[int]] = {}
        corners: dict[int, list[np.ndarray]] = {}
        for j, (R, c, ht, poly) in enumerate(prisms):
            pg = np.asarray(poly, dtype=float)
            self._R[j], self._c[j, :, 0] = R, c
            ends = np.repeat([-ht, ht], len(pg))[:, None]
            by_sides.setdefault(len(pg), []).append(j)
            corners.setdefault(len(pg), []).append(
                np.concatenate([ends, np.tile(pg, (2, 1))], axis=1)
            )
            row = self._fixed[j]
            row[18], row[20] = ht, len(pg)
            row[21:25] = pg[:, 0].min(), pg[:, 0].max(), pg[:, 1].min(), pg[:, 1].max()
            row[25 : 25 + 2 * len(pg)] = pg.reshape(-1)
        # prisms of one polygon size in one stack: (k,) indices, (k, 2 sides, 3) corners
        self._groups = [(np.array(by_sides[n]), np.stack(corners[n])) for n in by_sides]

    def rows(self, T_world_entity: np.ndarray, friction: Sequence[float]) -> np.ndarray:
        """(m, :data:`PRISM_COLS`) the prisms' world rows with the entity at
        ``T_world_entity``, each with its Coulomb friction (m values)."""
        if len(friction) != self.n:
            raise ValueError(f"friction: one per prism ({self.n}), got {len(friction)}")
        out = self._fixed.copy()
        if self.n == 0:
            return out
        T = np.asarray(T_world_entity, dtype=float)
        Rw, tw = T[:3, :3], T[:3, 3]
        Rj = np.matmul(Rw, self._R)  # per prism: Rw @ R
        cj = np.matmul(Rw, self._c)[:, :, 0] + tw  # per prism: Rw @ c + tw
        for idx, local in self._groups:
            corners = np.matmul(local, Rj[idx].transpose(0, 2, 1)) + cj[idx][:, None, :]
            out[idx, 0:3], out[idx, 3:6] = corners.min(axis=1), corners.max(axis=1)
        out[:, 6:9] = cj
        out[:, 9:18] = Rj.reshape(self.n, 9)
        out[:, 19] = np.asarray(friction, dtype=float)
        return out


class StaticPrisms:
    """The static collision shapes of a vehicle's scene as world prisms (z-up, m), for
    :func:`uwdock.sim.fastpath.prism_contacts`.

    Shapes are read once per set of static actors; their world rows are recomputed when an
    actor's pose changes (the docking station, per episode).

    Args:
        body: the vehicle (:class:`uwdock.sim.physics.VehicleBody`): its scene's statics are
            read, the scene it is in now (a world's reset may move its entities into a fresh
            physics system).
        hull_friction: the hull's Coulomb friction; a pair's friction is the average of the
            hull's and the shape's dynamic friction (PhysX's "average" combine, as the tank
            planes').
    """

    def __init__(self, body, hull_friction: float) -> None:
        self.body = body
        self.hull_friction = float(hull_friction)
        self._watch = StaticsWatch(self._read)
        self._made_with = math.nan  # the hull friction of the rows
        self._rows = np.zeros((0, PRISM_COLS))

    def rows(self) -> np.ndarray:
        """(m, :data:`PRISM_COLS`) the world prisms now."""
        system = self.body.scene.physx_system
        statics = [c for c in system.get_rigid_static_components() if c.get_collision_shapes()]
        if self._watch.update(statics) or self._made_with != self.hull_friction:
            parts = []
            for comp, (prisms, shape_mu) in zip(
                self._watch.statics, self._watch.local, strict=True
            ):
                pose = comp.get_entity_pose()
                T = T_from_pos_quat(np.asarray(pose.p, float), np.asarray(pose.q, float))
                mu = [0.5 * (self.hull_friction + m) for m in shape_mu]
                parts.append(prisms.rows(T, mu))
            self._rows = (
                np.ascontiguousarray(np.concatenate(parts)) if parts else np.zeros((0, PRISM_COLS))
            )
            self._made_with = self.hull_friction
        return self._rows

    @staticmethod
    def _read(comp) -> tuple[PrismSet, list[float]]:
        """A component's prisms (its frame, :class:`PrismSet`) and their shapes' dynamic
        friction."""
        prisms, mu = [], []
        for shape in comp.get_collision_shapes():
            p = _local_prism(shape)
            if p is None:
                continue
            prisms.append(p)
            mu.append(float(shape.get_physical_material().dynamic_friction))
        return PrismSet(prisms), mu
