"""One PhysX scene for the docking-station contact of many vehicles (the batched simulator's).

:class:`uwdock.sim.batch.BatchVehicles` hands a vehicle to PhysX only while its hull may touch a
static shape (the docking station). Stepping each such vehicle in its own scene pays PhysX's
per-scene cost of a step once per vehicle, and that fixed cost is about half of it: on the
2-core development machine PhysX steps a vehicle resting on its station in 18.9 us per 300 Hz
substep alone in its scene (7.8 us with nothing to touch), in 8.3 us as one of 32 in one scene
(``bench/bench_train_speed.py`` measures what it gives training: 1.55x from a trained policy).
Here every vehicle has a *twin*: a dynamic body with copies of its collision shapes, in one
shared scene, beside a copy of its own scene's static shapes; one ``step()`` advances every
vehicle in contact.

Layout: slot ``i``'s statics are copied with a horizontal offset (x, y; never the depth, which
the hydrodynamics reads) that puts their centre on grid point ``i``, ``spacing_m`` apart, more
than the statics' extent plus twice the hull's reach plus a few metres, so nothing of one slot
can touch another's. Grid points follow a square spiral out from the origin by the slot's id
(its env index in the whole training batch), so an env sits at the same place whichever worker
process holds it. The offset follows the slot's statics when they move (a new episode's docking
station pose, :meth:`SharedContactScene.load`).

Twins that are not stepped sleep far above their slot, put to sleep again after the next
substep (PhysX skips sleeping bodies, but wakes one whose contacts were lost: a twin put to
sleep beside its station would be woken and simulated for nothing). A twin that continues from
its own last PhysX substep keeps PhysX's contact state; any other is placed from the batch state
just before its first substep. The per-substep work is one ``pack()`` (all twins' states in one
buffer, read in place), one numba call for every stepped twin's hydrodynamic wrench
(:func:`uwdock.sim.fastpath.physx_wrenches`), one ``add_force_torque`` per stepped twin and one
``step()``.

What differs from stepping every vehicle in its own scene: positions live in the shared scene
with the slot's offset (float32 round-off of ~1e-6 m at the grid's size), and PhysX's contact
cache lives in one system for the whole run instead of a fresh one per episode; so trajectories
agree within stated tolerances, not bit for bit (``tests/test_batch_physics.py``). A run is
deterministic, but a vehicle's contacts also round off differently when other twins join or
leave the scene in the same substep (a twin alone in its slot with a neighbour stepping beside
it is bit-equal; with neighbours placed and parked, ~1e-5 m after a contact episode, with
PhysX's enhanced determinism on or off), so splitting a batch over another number of processes
changes the rollouts at round-off; ``batch_contact = "own"`` does not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import sapien

from uwdock.sim.fastpath import physx_wrenches
from uwdock.sim.physics import VehicleBody, make_physics_scene

__all__ = ["SharedContactScene", "spiral_point"]

#: Room (m) between two slots' reach, on top of the statics' extent and twice the hull's reach:
#: a vehicle in contact moves far less than this in one control step.
SLOT_CLEARANCE_M = 4.0
#: Height (m, z-up) above its slot's grid point where a sleeping twin waits, touching nothing
#: (PhysX wakes a body whose contacts were lost, so one left asleep beside its station would be
#: woken and simulated for nothing).
PARK_HEIGHT_M = 50.0
_PACK_FLOATS = 13  # a rigid body in PhysxSystem.pack(): attitude (w x y z), position, v, w


def spiral_point(k: int) -> tuple[int, int]:
    """Integer grid point number ``k`` (>= 0) of a square spiral out from (0, 0): 0 -> (0, 0),
    1 -> (1, 0), 2 -> (1, 1), 3 -> (0, 1), 4 -> (-1, 1), ...; ring ``r`` holds points
    ``(2r - 1)^2 .. (2r + 1)^2 - 1``, so ``n`` points fit in a square of side ~sqrt(n)."""
    if k == 0:
        return 0, 0
    r = math.ceil((math.sqrt(k + 1) - 1) / 2)  # the ring
    j = k - (2 * r - 1) ** 2  # position along the ring, 0 .. 8r - 1
    side, t = divmod(j, 2 * r)
    if side == 0:
        return r, -r + 1 + t
    if side == 1:
        return r - 1 - t, r
    if side == 2:
        return -r, r - 1 - t
    return -r + 1 + t, -r


def _copy_shape(shape: sapien.physx.PhysxCollisionShape) -> sapien.physx.PhysxCollisionShape:
    """A new collision shape equal to ``shape`` (geometry, material, pose, offsets, groups)."""
    px = sapien.physx
    mat = shape.get_physical_material()
    if isinstance(shape, px.PhysxCollisionShapeBox):
        new = px.PhysxCollisionShapeBox(np.asarray(shape.get_half_size(), np.float32), mat)
    elif isinstance(shape, px.PhysxCollisionShapeCapsule):
        new = px.PhysxCollisionShapeCapsule(shape.get_radius(), shape.get_half_length(), mat)
    elif isinstance(shape, px.PhysxCollisionShapeSphere):
        new = px.PhysxCollisionShapeSphere(shape.get_radius(), mat)
    elif isinstance(shape, px.PhysxCollisionShapeConvexMesh):
        new = px.PhysxCollisionShapeConvexMesh(
            np.asarray(shape.get_vertices(), np.float32),
            np.asarray(shape.get_scale(), np.float32),
            mat,
        )
    else:
        raise ValueError(f"shared contact scene: cannot copy a {type(shape).__name__}")
    new.set_local_pose(shape.get_local_pose())
    new.set_contact_offset(shape.get_contact_offset())
    new.set_rest_offset(shape.get_rest_offset())
    new.set_collision_groups(shape.get_collision_groups())
    return new


def _statics(body: VehicleBody) -> list[sapien.Entity]:
    """The static entities of the body's scene (what PhysX lets it touch)."""
    return [c.entity for c in body.scene.physx_system.get_rigid_static_components()]


class SharedContactScene:
    """Twins of ``bodies`` and copies of their scenes' statics in one PhysX scene (module
    docstring).

    Args:
        bodies: the batch's vehicles, each in its own scene (as :class:`BatchVehicles` gets
            them); their scenes' statics may only be boxes, capsules, spheres or convex meshes.
        slot_ids: each body's id in the whole batch (its grid point); default 0, 1, ...
    """

    def __init__(
        self, bodies: Sequence[VehicleBody], slot_ids: Sequence[int] | None = None
    ) -> None:
        self.bodies = list(bodies)
        n = len(self.bodies)
        ids = list(range(n)) if slot_ids is None else [int(i) for i in slot_ids]
        if len(ids) != n or len(set(ids)) != n or min(ids) < 0:
            raise ValueError(f"slot_ids: {n} distinct ids >= 0 expected, got {slot_ids!r}")
        b0 = self.bodies[0]
        self.scene = make_physics_scene(b0.dt_s)
        self.system = self.scene.physx_system
        self.offsets = np.zeros((n, 3))  # z-up world -> shared scene, per slot
        self._copies: list[list[tuple[sapien.Entity, sapien.Entity]]] = []
        self._twins: list[sapien.physx.PhysxRigidDynamicComponent] = []
        extent, reach = 0.0, 0.0
        for b in self.bodies:
            pairs = []
            for src in _statics(b):
                comp = sapien.physx.PhysxRigidStaticComponent()
                for sh in src.find_component_by_type(
                    sapien.physx.PhysxRigidStaticComponent
                ).get_collision_shapes():
                    comp.attach(_copy_shape(sh))
                ent = sapien.Entity()
                ent.name = f"{src.name}_copy"
                ent.add_component(comp)
                self.scene.add_entity(ent)
                pairs.append((src, ent))
            self._copies.append(pairs)
            self._twins.append(self._twin(b))
            lo, hi = self._statics_box(b)
            extent = max(extent, float(np.max(hi[:2] - lo[:2])))
            reach = max(reach, float(np.max(b.hull[:, 6])) if len(b.hull) else 0.0)
        #: (m) grid spacing of the slots
        self.spacing_m = extent + 2.0 * reach + SLOT_CLEARANCE_M
        g = max(1, math.ceil(math.sqrt(n)))
        idx = np.arange(n)
        self._grid = (
            np.stack([(idx % g - (g - 1) / 2.0), (idx // g - (g - 1) / 2.0), np.zeros(n)], axis=1)
            * self.spacing_m
        )
        self._rows = self._pack_rows()
        self._awake = np.zeros(n, dtype=bool)
        self._resleep: list[int] = []
        self._out = np.zeros((n, 6), dtype=np.float32)  # PhysX takes float32
        for i in range(n):
            self.load(i)

    # ------------------------------------------------------------------ construction

    def _twin(self, b: VehicleBody) -> sapien.physx.PhysxRigidDynamicComponent:
        """A dynamic body with ``b``'s collision shapes and body settings (mass: :meth:`load`)."""
        src = b.component
        comp = sapien.physx.PhysxRigidDynamicComponent()
        for sh in src.get_collision_shapes():
            comp.attach(_copy_shape(sh))
        ent = sapien.Entity()
        ent.name = f"{b.entity.name}_twin"
        ent.add_component(comp)
        self.scene.add_entity(ent)
        comp.set_disable_gravity(src.get_disable_gravity())
        comp.set_linear_damping(src.get_linear_damping())
        comp.set_angular_damping(src.get_angular_damping())
        comp.set_sleep_threshold(src.get_sleep_threshold())
        comp.set_max_angular_velocity(src.get_max_angular_velocity())
        comp.set_max_linear_velocity(src.get_max_linear_velocity())
        comp.set_max_depenetration_velocity(src.get_max_depenetration_velocity())
        comp.set_max_contact_impulse(src.get_max_contact_impulse())
        comp.set_solver_position_iterations(src.get_solver_position_iterations())
        comp.set_solver_velocity_iterations(src.get_solver_velocity_iterations())
        comp.set_locked_motion_axes(src.get_locked_motion_axes())
        return comp

    @staticmethod
    def _statics_box(b: VehicleBody) -> tuple[np.ndarray, np.ndarray]:
        """World (z-up) box of the body's scene's static shapes (zeros when there are none)."""
        boxes = [
            np.asarray(c.compute_global_aabb_tight(), dtype=float)
            for c in b.scene.physx_system.get_rigid_static_components()
            if c.get_collision_shapes()
        ]
        if not boxes:
            return np.zeros(3), np.zeros(3)
        return np.min([x[0] for x in boxes], axis=0), np.max([x[1] for x in boxes], axis=0)

    def _pack_rows(self) -> np.ndarray:
        """Each twin's row in ``system.pack()``, checked against its own getters."""
        dyn = self.system.get_rigid_dynamic_components()
        index = {id(c): r for r, c in enumerate(dyn)}
        rows = np.array([index[id(c)] for c in self._twins], dtype=np.int64)
        for j, c in enumerate(self._twins):  # distinct poses, then read them back packed
            c.entity.set_pose(sapien.Pose([float(j), 0.5 * j, -1.0 - j], [1.0, 0.0, 0.0, 0.0]))
        packed = self._packed()
        for j, c in enumerate(self._twins):
            p = np.asarray(c.get_entity_pose().p, dtype=np.float32)
            if not np.array_equal(packed[rows[j], 4:7], p):
                raise RuntimeError(
                    "shared contact scene: PhysxSystem.pack() no longer lays a body out as "
                    "(q, p, v, w); this SAPIEN version needs contact='own'"
                )
        return rows

    def _packed(self) -> np.ndarray:
        """(bodies, 13) float32 states of every dynamic body of the scene."""
        buf = np.frombuffer(self.system.pack(), dtype=np.float32)
        m = len(self._twins)
        return buf[: m * _PACK_FLOATS].reshape(m, _PACK_FLOATS)

    # ------------------------------------------------------------------ slots

    def load(self, i: int) -> None:
        """Follow slot ``i``'s body after a reset: its mass properties, its statics' poses
        (the new offset) and a sleeping twin."""
        b = self.bodies[i]
        src, twin = b.component, self._twins[i]
        twin.set_mass(src.get_mass())
        twin.set_inertia(src.get_inertia())
        twin.set_cmass_local_pose(src.get_cmass_local_pose())
        srcs = _statics(b)
        pairs = self._copies[i]
        if [s for s, _ in pairs] != srcs:
            raise ValueError("shared contact scene: a vehicle's scene gained or lost static actors")
        lo, hi = self._statics_box(b)
        centre = (lo + hi) / 2.0
        self.offsets[i] = self._grid[i] - np.array([centre[0], centre[1], 0.0])
        off = self.offsets[i]
        for s, copy in pairs:
            pose = s.get_pose()
            copy.set_pose(sapien.Pose((np.asarray(pose.p, float) + off).tolist(), pose.q))
        self._park(i)

    def _park(self, i: int) -> None:
        """Put twin ``i`` to sleep high above its slot, where nothing touches (and wakes) it."""
        twin = self._twins[i]
        p = self._grid[i] + np.array([0.0, 0.0, PARK_HEIGHT_M])
        twin.entity.set_pose(sapien.Pose(p.tolist(), [1.0, 0.0, 0.0, 0.0]))
        twin.put_to_sleep()
        self._awake[i] = False
        # PhysX wakes a body whose contacts are lost in the next step: sleep again after it
        self._resleep.append(i)

    # ------------------------------------------------------------------ stepping

    def _place(self, i: int, state: np.ndarray) -> None:
        twin = self._twins[i]
        twin.wake_up()
        twin.entity.set_pose(sapien.Pose((state[:3] + self.offsets[i]).tolist(), state[3:7]))
        twin.set_linear_velocity(np.asarray(state[7:10], dtype=np.float32))
        twin.set_angular_velocity(np.asarray(state[10:13], dtype=np.float32))
        self._awake[i] = True

    def _active(self, active: list[int]) -> tuple[np.ndarray, np.ndarray, list]:
        """The stepped twins' slots, their rows in ``pack()`` and, per twin, its
        ``add_force_torque`` with its views of the force and torque rows of ``self._out``
        (made once per set of stepped twins, not per substep)."""
        act = np.array(active, dtype=np.int64)
        out = self._out
        adds = [
            (self._twins[i].add_force_torque, out[j, :3], out[j, 3:]) for j, i in enumerate(active)
        ]
        return act, self._rows[act], adds

    def step(
        self,
        slots: np.ndarray,
        starts: np.ndarray,
        held: np.ndarray,
        state: np.ndarray,
        P: np.ndarray,
        B: np.ndarray,
        contact: np.ndarray,
        wrenches: np.ndarray,
        currents: np.ndarray,
        spheres: np.ndarray,
        planes: np.ndarray,
    ) -> None:
        """Step vehicles ``slots`` through PhysX, each from its substep ``starts[j]`` to the end
        of the control step (``wrenches.shape[1]`` substeps), together.

        Args:
            slots: (K,) vehicle indices; starts: (K,) their first PhysX substep.
            held: (N,) whether a twin still holds its vehicle's state (its last PhysX substep
                ended the previous control step and nothing moved it since).
            state: (N, 13) the batch state (:class:`BatchVehicles`); the rows of ``slots``
                are read at their start and overwritten with the end state.
            P, B, contact, wrenches, currents, spheres, planes: as for
                :func:`uwdock.sim.fastpath.physx_wrenches`.
        """
        slots = np.asarray(slots, dtype=np.int64)
        starts = np.asarray(starts, dtype=np.int64)
        n_sub = wrenches.shape[1]
        k0 = int(starts.min())
        keep = {int(i) for i, k in zip(slots, starts, strict=True) if k == k0 and held[i]}
        for i in np.flatnonzero(self._awake):  # the rest sleeps until its start
            if int(i) not in keep:
                self._park(int(i))
        pending: dict[int, list[int]] = {}
        for i, k in zip(slots, starts, strict=True):
            if int(i) not in keep:
                pending.setdefault(int(k), []).append(int(i))
        active = sorted(keep)
        system, out = self.system, self._out
        act, rows, adds = self._active(active)
        m = len(self._twins) * _PACK_FLOATS
        for k in range(k0, n_sub):
            joining = pending.get(k)
            if joining:
                for i in joining:
                    self._place(i, state[i])
                active += joining
                act, rows, adds = self._active(active)
            packed = np.frombuffer(system.pack(), dtype=np.float32, count=m)
            physx_wrenches(
                P, B, packed, rows, act, self.offsets, currents, wrenches, k, spheres, planes,
                contact, out,
            )  # fmt: skip
            for add, force, torque in adds:
                add(force, torque)
            system.step()
            if self._resleep:
                for i in self._resleep:
                    if not self._awake[i]:
                        self._twins[i].put_to_sleep()
                self._resleep = []
        packed = self._packed()[self._rows[slots]]
        # what a scene of its own would hold: float32 positions
        pos = packed[:, 4:7].astype(np.float64) - self.offsets[slots]
        state[slots, :3] = pos.astype(np.float32)
        state[slots, 3:7] = packed[:, 0:4]
        state[slots, 7:13] = packed[:, 7:13]
