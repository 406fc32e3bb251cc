"""The docking station (DS) and the test tank as static SAPIEN actors (collision + visual).

Frames (see :mod:`calibration.frames`):
    ds:        x forward, y starboard, z down, origin on the top of the DS floor plate; heights
               above the floor are negative z (docs/reference-system.md section 4).
    world_ned: x north, y east, z down, origin on the water surface at the tank centre; the tank
               floor is at z = ``tank_depth_m``.
    SAPIEN's world is ``world_zup``. The one conversion happens in :func:`sapien_pose`: every
    actor here is built in a NED-like frame (ds or world_ned) whose pose in world_zup is
    ``T_WORLDZUP_WORLDNED @ T_worldned_frame`` (a proper rotation, so SAPIEN accepts it), and all
    shapes are placed inside it with their DS (or NED) coordinates unchanged.

Geometry (defaults from docs/reference-system.md section 4; all editable in
:class:`DockingStationConfig`):
    * floor plate and an open-top cage frame (corner posts, rim beams) of 1.94 x 2.28 m, rim at
      1.64 m (the rim markers' pedestals stand on brackets at that height; their faces at 1.756 m);
    * X-guides: vertical plates at x = +-0.57 m over y in [-0.85, 0.85] whose top edge is a
      zig-zag through the peaks (1.277 m at y = 0, +-0.85) and notches (1.081 m at y = +-0.425),
      built exactly as four convex trapezoidal prisms per plate, so pegs can sit in the notches;
    * Y-guide cradles at y = +-0.65 m: a central support 0.38 m high and posts whose inner faces
      are at x = +-0.50 m up to 1.22 m;
    * inclined entry guides (flat plates leaning outward) along the rim;
    * the 3D markers: each marker's GLB render mesh (white insert with openings on a black
      enclosure) at ``T_ds_marker``, boxes for their collision, and a plinth (floor markers) or a
      bracket to the nearest cage side (rim markers) underneath.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import sapien
from numpy.typing import ArrayLike

from uwdock.calibration.frames import T_WORLDZUP_WORLDNED, check_T, make_T, pos_quat_from_T
from uwdock.dockcore.config import to_dict, validated
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.markers.config import MarkerConfig
from uwdock.markers.generate import MARKER_SET_NAME, generate
from uwdock.markers.geometry import RENDER_MESH_VERSION
from uwdock.markers.markerset import MarkerSet, load_marker_set
from uwdock.sim.cache import build_once, cache_root
from uwdock.sim.domains import RGB, TANK_SIZE_M, Friction, TankSide_m

__all__ = [
    "DockingStation",
    "DockingStationConfig",
    "build_chessboard",
    "build_docking_station",
    "build_tank",
    "default_T_worldned_ds",
    "default_marker_set",
    "resolve_marker_set",
    "sapien_pose",
]

#: A dimension of the docking station (m).
_DsLength = Annotated[float, Interval(gt=0, le=50)]
#: A coordinate in the DS frame (m).
_DsCoord = Annotated[float, Interval(ge=-50, le=50)]


@dataclass(frozen=True)
class DockingStationConfig:
    """Docking station, marker supports and test tank geometry and looks.

    Lengths in metres in the DS frame (x forward, y starboard, z down); "height" is measured up
    from the DS floor (= -z). Colours are linear RGB albedo in [0, 1].

    Attributes:
        cage_length_x_m: outer cage footprint along DS x (m).
        cage_width_y_m: outer cage footprint along DS y (m).
        cage_height_m: height of the top of the rim beams (m).
        frame_tube_m: side of the square tubes of the cage posts and rim beams (m).
        floor_thickness_m: DS floor plate thickness, below the DS origin (m).
        x_guide_x_m: |x| of the X-guide plates' mid-planes (m).
        x_guide_half_span_y_m: the plates span y in [-this, +this] (m).
        x_guide_peak_height_m: top-edge height at y = 0 and at the plate ends (m).
        x_guide_notch_height_m: top-edge height at the notches (m).
        x_guide_notch_y_m: |y| of the two notches (m).
        x_guide_thickness_m: plate thickness (m).
        y_guide_y_m: y positions of the Y-guide cradles (m).
        y_guide_thickness_m: thickness of a cradle along y (m).
        y_guide_support_height_m: height of a cradle's central support (m).
        y_guide_support_half_width_m: half width along x of the central support (m).
        y_guide_post_inner_x_m: |x| of the inner faces of a cradle's two posts (m).
        y_guide_post_width_m: post width along x (m).
        y_guide_post_height_m: post height (m).
        entry_guides: add inclined entry guides along the rim.
        entry_guide_length_m: slant length of an entry-guide plate (m).
        entry_guide_angle_deg: entry-guide lean outward from vertical (deg).
        marker_set_path: marker set file (TOML/JSON) placed on the DS; None: the default set,
            generated once into the cache folder (see :func:`default_marker_set`).
        marker_supports: add plinths / brackets under face-up markers.
        bracket_min_height_m: markers whose pedestal stands higher than this get a bracket to
            the nearest cage side instead of a plinth from the floor (m).
        frame_rgb: cage frame colour (yellowish painted metal).
        guide_rgb: guides, floor plate, plinths and brackets colour (grey metal).
        tank_length_m: tank size along world x (m).
        tank_width_m: tank size along world y (m).
        tank_depth_m: water depth: the tank floor is at world_ned z = this (m).
        tank_wall_thickness_m: wall and floor slab thickness (m).
        tank_floor_rgb: tank floor colour (sandy).
        tank_wall_rgb: tank wall colour (grey).
        static_friction: static friction of every DS and tank surface.
        dynamic_friction: dynamic friction.
        restitution: restitution (0 = no bounce).
    """

    cage_length_x_m: _DsLength = 1.94
    cage_width_y_m: _DsLength = 2.28
    cage_height_m: _DsLength = 1.64
    frame_tube_m: _DsLength = 0.06
    floor_thickness_m: _DsLength = 0.02
    x_guide_x_m: _DsLength = 0.57
    x_guide_half_span_y_m: _DsLength = 0.85
    x_guide_peak_height_m: _DsLength = 1.277
    x_guide_notch_height_m: _DsLength = 1.081
    x_guide_notch_y_m: _DsLength = 0.425
    x_guide_thickness_m: _DsLength = 0.02
    y_guide_y_m: tuple[_DsCoord, ...] = (-0.65, 0.65)
    y_guide_thickness_m: _DsLength = 0.03
    y_guide_support_height_m: _DsLength = 0.38
    y_guide_support_half_width_m: _DsLength = 0.15
    y_guide_post_inner_x_m: _DsLength = 0.50
    y_guide_post_width_m: _DsLength = 0.05
    y_guide_post_height_m: _DsLength = 1.22
    entry_guides: bool = True
    entry_guide_length_m: _DsLength = 0.25
    entry_guide_angle_deg: Annotated[float, Interval(ge=0, lt=90)] = 40.0
    marker_set_path: str | None = None
    marker_supports: bool = True
    bracket_min_height_m: Annotated[float, Interval(ge=0, le=50)] = 0.8
    frame_rgb: RGB = (0.78, 0.66, 0.22)
    guide_rgb: RGB = (0.55, 0.56, 0.58)
    tank_length_m: TankSide_m = TANK_SIZE_M[0]
    tank_width_m: TankSide_m = TANK_SIZE_M[1]
    tank_depth_m: TankSide_m = TANK_SIZE_M[2]
    tank_wall_thickness_m: Annotated[float, Interval(gt=0, le=10)] = 0.2
    tank_floor_rgb: RGB = (0.58, 0.52, 0.40)
    tank_wall_rgb: RGB = (0.50, 0.53, 0.56)
    static_friction: Friction = 0.6
    dynamic_friction: Friction = 0.5
    restitution: Annotated[float, Interval(ge=0, le=1)] = 0.0

    @property
    def tank_size_m(self) -> tuple[float, float, float]:
        """Tank length, width, depth (m)."""
        return (self.tank_length_m, self.tank_width_m, self.tank_depth_m)

    def validate(self) -> None:
        """Raise ValueError naming the first inconsistent field (comparisons fail on NaN; each
        field's own range is its declared domain, checked by the loader and by
        :func:`dockcore.config.validated` in :func:`build_docking_station` and
        :func:`build_tank`)."""
        if not self.x_guide_notch_y_m < self.x_guide_half_span_y_m:
            raise ValueError("x_guide_notch_y_m: must be < x_guide_half_span_y_m")
        if not self.x_guide_notch_height_m < self.x_guide_peak_height_m:
            raise ValueError("x_guide_notch_height_m: must be < x_guide_peak_height_m")
        if not self.x_guide_x_m < self.cage_length_x_m / 2:
            raise ValueError("x_guide_x_m: the X-guides must be inside the cage")
        if not self.y_guide_post_inner_x_m > self.y_guide_support_half_width_m:
            raise ValueError("y_guide_post_inner_x_m: posts must be outside the central support")
        if not len(self.y_guide_y_m) <= 16:
            raise ValueError(f"y_guide_y_m: at most 16 cradles, got {len(self.y_guide_y_m)}")
        if not self.frame_tube_m < min(self.cage_length_x_m, self.cage_width_y_m) / 2:
            raise ValueError("frame_tube_m: must be < half the cage's length and width")
        if not self.frame_tube_m < self.cage_height_m:
            raise ValueError("frame_tube_m: must be < cage_height_m")
        if not (
            self.cage_length_x_m < self.tank_length_m and self.cage_width_y_m < self.tank_width_m
        ):
            raise ValueError("tank_length_m / tank_width_m: the DS must fit in the tank")
        if not self.cage_height_m + self.floor_thickness_m < self.tank_depth_m:
            raise ValueError(
                f"tank_depth_m: the DS ({self.cage_height_m + self.floor_thickness_m:g} m high) "
                f"must fit below the water surface, got {self.tank_depth_m:g} m"
            )

    def x_guide_profile(self) -> tuple[np.ndarray, np.ndarray]:
        """Top edge of an X-guide plate: (y_m (5,), height_m (5,)) from -y to +y."""
        s, n = self.x_guide_half_span_y_m, self.x_guide_notch_y_m
        peak, notch = self.x_guide_peak_height_m, self.x_guide_notch_height_m
        return np.array([-s, -n, 0.0, n, s]), np.array([peak, notch, peak, notch, peak])


@dataclass(frozen=True)
class DockingStation:
    """A docking station built into a scene.

    Attributes:
        entity: the static SAPIEN entity (pose ``T_worldzup_ds``).
        marker_set: the markers placed on it.
        T_worldned_ds: (4, 4) DS pose in world_ned.
        cfg: the geometry it was built from.
    """

    entity: sapien.Entity
    marker_set: MarkerSet
    T_worldned_ds: np.ndarray
    cfg: DockingStationConfig

    def set_pose(self, T_worldned_ds: ArrayLike) -> None:
        """Move the (static) DS, e.g. per episode; ``T_worldned_ds`` is updated in place."""
        T = check_T(T_worldned_ds, "T_worldned_ds")
        self.entity.set_pose(sapien_pose(T))
        self.T_worldned_ds[...] = T


# ----------------------------------------------------------------------------- frames


def sapien_pose(T_worldned_x: ArrayLike) -> sapien.Pose:
    """SAPIEN pose of a NED-like frame x given in world_ned (the module's one conversion).

    Args:
        T_worldned_x: (4, 4) pose of frame x in world_ned (validated).

    Returns:
        ``sapien.Pose`` of ``T_worldzup_x = T_WORLDZUP_WORLDNED @ T_worldned_x``.
    """
    T = T_WORLDZUP_WORLDNED @ check_T(T_worldned_x, "T_worldned_x")
    p, q = pos_quat_from_T(T)
    return sapien.Pose(p.astype(np.float32), q.astype(np.float32))


def _local_pose(T_frame_shape: np.ndarray) -> sapien.Pose:
    p, q = pos_quat_from_T(T_frame_shape)
    return sapien.Pose(p.astype(np.float32), q.astype(np.float32))


def default_T_worldned_ds(cfg: DockingStationConfig | None = None) -> np.ndarray:
    """DS standing on the tank floor at the tank centre, DS axes along world_ned's."""
    cfg = cfg or DockingStationConfig()
    return make_T(t=[0.0, 0.0, cfg.tank_depth_m - cfg.floor_thickness_m])


# ----------------------------------------------------------------------------- marker set


def default_marker_set(cache_dir: str | os.PathLike[str] | None = None) -> MarkerSet:
    """The reference marker set (``MarkerConfig()`` defaults) with its render meshes.

    Generated once with :func:`markers.generate.generate` (deterministic, offline, ~3 s) into
    ``<cache>/markers-<hash of the config>/`` (through a temporary folder renamed when complete;
    those of killed processes are removed) and loaded from there afterwards. The cache is
    ``cache_dir``, else ``$UWDOCK_CACHE_DIR``, else ``$XDG_CACHE_HOME/uwdock`` or
    ``~/.cache/uwdock``.
    """
    cfg = MarkerConfig()
    key = {"config": to_dict(cfg), "render_mesh": RENDER_MESH_VERSION}
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    final = build_once(root / f"markers-{digest}", MARKER_SET_NAME, lambda tmp: generate(cfg, tmp))
    return load_marker_set(final / MARKER_SET_NAME)


def resolve_marker_set(
    cfg: DockingStationConfig,
    marker_set: MarkerSet | str | os.PathLike[str] | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
) -> MarkerSet:
    """The marker set to use: ``marker_set`` (object or file), else ``cfg.marker_set_path``,
    else :func:`default_marker_set`."""
    if isinstance(marker_set, MarkerSet):
        return marker_set
    if marker_set is not None:
        return load_marker_set(marker_set)
    if cfg.marker_set_path is not None:
        return load_marker_set(cfg.marker_set_path)
    return default_marker_set(cache_dir)


# ----------------------------------------------------------------------------- shape helpers


class _StaticBody:
    """Collects visual and collision shapes (poses in the body frame) of one static entity.

    With ``visual=False`` only collision shapes are made, for physics-only scenes (a scene
    without a render system cannot hold render components).
    """

    def __init__(self, physx_material: sapien.physx.PhysxMaterial, visual: bool = True) -> None:
        self.render = sapien.render.RenderBodyComponent() if visual else None
        self.physx = sapien.physx.PhysxRigidStaticComponent()
        self.material = physx_material
        self._looks: dict[_Material, sapien.render.RenderMaterial] = {}

    def _look(self, material: _Material) -> sapien.render.RenderMaterial:
        """The render material of ``material``, made once per body."""
        if material not in self._looks:
            self._looks[material] = material.render()
        return self._looks[material]

    def box(
        self,
        center: Sequence[float],
        half_size: Sequence[float],
        material: _Material,
        T_rot: np.ndarray | None = None,
        collision: bool = True,
    ) -> None:
        """An axis-aligned (or ``T_rot``-rotated) box; ``center`` in the body frame (m)."""
        T = make_T(None if T_rot is None else T_rot[:3, :3], center)
        pose = _local_pose(T)
        if self.render is not None:
            shape = sapien.render.RenderShapeBox(
                np.asarray(half_size, np.float32), self._look(material)
            )
            shape.local_pose = pose
            self.render.attach(shape)
        if collision:
            col = sapien.physx.PhysxCollisionShapeBox(
                np.asarray(half_size, np.float32), self.material
            )
            col.local_pose = pose
            self.physx.attach(col)

    def convex(self, vertices: np.ndarray, material: _Material) -> None:
        """A convex polyhedron (the hull of ``vertices`` (N, 3), body frame), flat shaded."""
        v = np.asarray(vertices, np.float64)
        self.physx.attach(
            sapien.physx.PhysxCollisionShapeConvexMesh(
                v.astype(np.float32), np.ones(3, np.float32), self.material
            )
        )
        if self.render is None:
            return
        from scipy.spatial import ConvexHull  # half a second to import, only needed here

        hull = ConvexHull(v)
        tris = []
        for simplex, eq in zip(hull.simplices, hull.equations, strict=True):
            a, b, c = v[simplex]
            tris.append((a, b, c) if np.dot(np.cross(b - a, c - a), eq[:3]) > 0 else (a, c, b))
        corners = np.asarray(tris, np.float32).reshape(-1, 3)
        normals = np.repeat(hull.equations[:, :3].astype(np.float32), 3, axis=0)
        faces = np.arange(len(corners), dtype=np.uint32).reshape(-1, 3)
        uvs = np.zeros((len(corners), 2), np.float32)
        self.render.attach(
            sapien.render.RenderShapeTriangleMesh(
                corners, faces, normals, uvs, self._look(material)
            )
        )

    def mesh_file(self, path: Path, T_body_mesh: np.ndarray) -> None:
        """A visual mesh file (its own materials) placed at ``T_body_mesh``."""
        if self.render is None:
            return
        shape = sapien.render.RenderShapeTriangleMesh(str(path))
        shape.local_pose = _local_pose(T_body_mesh)
        self.render.attach(shape)

    def build(self, scene: sapien.Scene, pose: sapien.Pose, name: str) -> sapien.Entity:
        entity = sapien.Entity()
        entity.name = name
        self.physx.name = name
        if self.render is not None:
            self.render.name = name
            entity.add_component(self.render)
        entity.add_component(self.physx)
        entity.pose = pose
        scene.add_entity(entity)
        return entity


@dataclass(frozen=True)
class _Material:
    """A surface's look; made into a SAPIEN render material only by bodies that render (a
    ``RenderMaterial`` costs ~20 ms, wasted on the physics-only worlds of training)."""

    rgb: tuple[float, ...]
    roughness: float
    metallic: float

    def render(self) -> sapien.render.RenderMaterial:
        return sapien.render.RenderMaterial(
            base_color=[*self.rgb, 1.0], roughness=self.roughness, metallic=self.metallic
        )


def _render_material(rgb: RGB, roughness: float = 0.7, metallic: float = 0.0) -> _Material:
    return _Material(tuple(map(float, rgb)), float(roughness), float(metallic))


def _physx_material(cfg: DockingStationConfig) -> sapien.physx.PhysxMaterial:
    return sapien.physx.PhysxMaterial(cfg.static_friction, cfg.dynamic_friction, cfg.restitution)


def _rot_x(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return make_T(np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]))


def _rot_y(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return make_T(np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]))


# ----------------------------------------------------------------------------- the DS


def _add_cage(body: _StaticBody, cfg: DockingStationConfig) -> None:
    """Floor plate, corner posts, rim beams and entry guides (DS frame, z down)."""
    frame, guide = _render_material(cfg.frame_rgb, 0.6, 0.2), _render_material(cfg.guide_rgb)
    hx, hy, H, t = (
        cfg.cage_length_x_m / 2,
        cfg.cage_width_y_m / 2,
        cfg.cage_height_m,
        cfg.frame_tube_m,
    )
    body.box([0, 0, cfg.floor_thickness_m / 2], [hx, hy, cfg.floor_thickness_m / 2], guide)
    px, py = hx - t / 2, hy - t / 2  # tube centre lines
    for sx in (-1, 1):
        for sy in (-1, 1):
            body.box([sx * px, sy * py, -H / 2], [t / 2, t / 2, H / 2], frame)
    for sy in (-1, 1):  # beams along x at y = +-py
        body.box([0, sy * py, -H + t / 2], [hx, t / 2, t / 2], frame)
    for sx in (-1, 1):  # beams along y at x = +-px
        body.box([sx * px, 0, -H + t / 2], [t / 2, hy - t, t / 2], frame)
    if not cfg.entry_guides:
        return
    a, L, th = math.radians(cfg.entry_guide_angle_deg), cfg.entry_guide_length_m, 0.01
    rise, out = L * math.cos(a) / 2, L * math.sin(a) / 2  # plate centre offsets from the rim
    for sy in (-1, 1):  # plates along x, leaning outward in +-y
        body.box([0, sy * (hy + out), -H - rise], [hx, th, L / 2], guide, _rot_x(sy * a))
    for sx in (-1, 1):  # plates along y, leaning outward in +-x
        body.box([sx * (hx + out), 0, -H - rise], [th, hy, L / 2], guide, _rot_y(-sx * a))


def _add_x_guides(body: _StaticBody, cfg: DockingStationConfig) -> None:
    """Each plate: four trapezoidal prisms following the zig-zag top edge exactly."""
    guide = _render_material(cfg.guide_rgb, 0.5, 0.3)
    y, h = cfg.x_guide_profile()
    ht = cfg.x_guide_thickness_m / 2
    for sx in (-1, 1):
        x0, x1 = sx * cfg.x_guide_x_m - ht, sx * cfg.x_guide_x_m + ht
        for k in range(len(y) - 1):
            pts = []
            for yy, hh in ((y[k], h[k]), (y[k + 1], h[k + 1])):
                for xx in (x0, x1):
                    pts += [(xx, yy, 0.0), (xx, yy, -hh)]
            body.convex(np.array(pts), guide)


def _add_y_guides(body: _StaticBody, cfg: DockingStationConfig) -> None:
    guide = _render_material(cfg.guide_rgb)
    ty = cfg.y_guide_thickness_m / 2
    hs, hp = cfg.y_guide_support_height_m, cfg.y_guide_post_height_m
    for yc in cfg.y_guide_y_m:
        body.box([0, yc, -hs / 2], [cfg.y_guide_support_half_width_m, ty, hs / 2], guide)
        xc = cfg.y_guide_post_inner_x_m + cfg.y_guide_post_width_m / 2
        for sx in (-1, 1):
            body.box([sx * xc, yc, -hp / 2], [cfg.y_guide_post_width_m / 2, ty, hp / 2], guide)


def _marker_dims_m(ms: MarkerSet) -> tuple[float, float, float, float]:
    """(enclosure side, enclosure height, base side, base height) of the markers (m)."""
    g = ms.geometry
    size_mm = 1000.0 * ms.markers[0].side_m
    return (
        float(g.get("enclosure_side_mm", 1.26 * size_mm)) / 1000.0,
        float(g.get("enclosure_height_mm", 98.0)) / 1000.0,
        float(g.get("base_side_mm", 1.62 * size_mm)) / 1000.0,
        float(g.get("base_height_mm", 10.0)) / 1000.0,
    )


def _add_markers(body: _StaticBody, cfg: DockingStationConfig, ms: MarkerSet) -> None:
    """Render meshes, collision boxes and supports of every marker."""
    guide = _render_material(cfg.guide_rgb)
    enc_side, enc_h, base_side, base_h = _marker_dims_m(ms)
    hx, hy = cfg.cage_length_x_m / 2, cfg.cage_width_y_m / 2
    for spec in ms.markers:
        mesh = ms.render_mesh_path(spec.marker_id)
        if mesh is None or not mesh.is_file():
            raise DockError(
                f"marker {spec.marker_id}: the marker set has no render mesh "
                f"({mesh or 'none named'}); run `markers generate` to make one"
            )
        T = np.asarray(spec.T_ds_marker, np.float64)
        body.mesh_file(mesh, T)
        # collision: column + base, in the marker frame (z out of the face, solid at z < 0)
        for side, z0, z1 in ((enc_side, -enc_h, 0.0), (base_side, -enc_h - base_h, -enc_h)):
            centre = T[:3, :3] @ [0.0, 0.0, (z0 + z1) / 2] + T[:3, 3]
            col = sapien.physx.PhysxCollisionShapeBox(
                np.array([side / 2, side / 2, (z1 - z0) / 2], np.float32), body.material
            )
            col.local_pose = _local_pose(make_T(T[:3, :3], centre))
            body.physx.attach(col)
        face_up = T[2, 2] < -0.999  # marker z = -ds z
        if not (cfg.marker_supports and face_up):
            continue
        bottom_h = -(T[2, 3]) - enc_h - base_h  # height of the pedestal's underside
        x, y = T[0, 3], T[1, 3]
        if bottom_h <= 1e-3:
            continue
        if bottom_h < cfg.bracket_min_height_m:  # plinth from the floor
            body.box([x, y, -bottom_h / 2], [base_side / 2, base_side / 2, bottom_h / 2], guide)
            continue
        th = 0.01  # bracket plate to the nearest cage side, under the pedestal
        if hy - abs(y) <= hx - abs(x):
            y0, y1 = sorted((y - math.copysign(base_side / 2, y), math.copysign(hy, y)))
            body.box([x, (y0 + y1) / 2, -bottom_h + th], [base_side / 2, (y1 - y0) / 2, th], guide)
        else:
            x0, x1 = sorted((x - math.copysign(base_side / 2, x), math.copysign(hx, x)))
            body.box([(x0 + x1) / 2, y, -bottom_h + th], [(x1 - x0) / 2, base_side / 2, th], guide)


def build_docking_station(
    scene: sapien.Scene,
    cfg: DockingStationConfig | None = None,
    marker_set: MarkerSet | str | os.PathLike[str] | None = None,
    T_worldned_ds: ArrayLike | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    visual: bool = True,
) -> DockingStation:
    """Add the DS (one static entity: cage, guides, markers, supports) to ``scene``.

    Args:
        scene: SAPIEN scene (with a physics and a render system).
        cfg: geometry (validated); defaults to the reference DS.
        marker_set: the markers (object or file); None: see :func:`resolve_marker_set`.
        T_worldned_ds: (4, 4) DS pose in world_ned; None: :func:`default_T_worldned_ds`.
        cache_dir: where the default marker set is generated (see :func:`default_marker_set`).
        visual: False builds collision shapes only (for a physics-only scene).

    Returns:
        The built :class:`DockingStation`.

    Raises:
        ValueError: invalid ``cfg`` or pose.
        DockError / ConfigError: unreadable marker set or a marker without render mesh.
    """
    cfg = validated(cfg or DockingStationConfig())
    ms = resolve_marker_set(cfg, marker_set, cache_dir)
    T = default_T_worldned_ds(cfg) if T_worldned_ds is None else check_T(T_worldned_ds, "T_ds")
    body = _StaticBody(_physx_material(cfg), visual=visual)
    _add_cage(body, cfg)
    _add_x_guides(body, cfg)
    _add_y_guides(body, cfg)
    _add_markers(body, cfg, ms)
    entity = body.build(scene, sapien_pose(T), "docking_station")
    return DockingStation(entity, ms, T, cfg)


def build_tank(
    scene: sapien.Scene,
    cfg: DockingStationConfig | None = None,
    visual: bool = True,
    surface_lid: bool = False,
    collision: bool = True,
) -> sapien.Entity:
    """Add the tank (floor at world_ned z = depth, four walls up to the surface) to ``scene``.

    Args:
        scene: the scene.
        cfg: tank geometry.
        visual: False builds collision shapes only (for a physics-only scene).
        collision: give the floor and walls PhysX collision shapes; False: visual only (the
            docking world's vehicle touches them through its own plane contact instead:
            :meth:`uwdock.sim.physics.VehicleBody.set_tank_planes`).
        surface_lid: add an invisible collision slab just above the water surface, so a
            positively buoyant vehicle without a free surface (``VehicleConfig.
            surface_band_m = 0``) stops at the surface.

    Returns:
        The static tank entity (frame = world_ned).
    """
    cfg = validated(cfg or DockingStationConfig())
    body = _StaticBody(_physx_material(cfg), visual=visual)
    floor, wall = _render_material(cfg.tank_floor_rgb, 0.95), _render_material(cfg.tank_wall_rgb)
    hx, hy, d, t = (
        cfg.tank_length_m / 2,
        cfg.tank_width_m / 2,
        cfg.tank_depth_m,
        cfg.tank_wall_thickness_m,
    )
    body.box([0, 0, d + t / 2], [hx + t, hy + t, t / 2], floor, collision=collision)
    for s in (-1, 1):
        body.box([s * (hx + t / 2), 0, d / 2], [t / 2, hy + t, d / 2], wall, collision=collision)
        body.box([0, s * (hy + t / 2), d / 2], [hx, t / 2, d / 2], wall, collision=collision)
    if surface_lid:
        lid = sapien.physx.PhysxCollisionShapeBox(
            np.array([hx, hy, t / 2], np.float32), body.material
        )
        lid.local_pose = _local_pose(make_T(t=[0.0, 0.0, -t / 2]))
        body.physx.attach(lid)
    return body.build(scene, sapien_pose(np.eye(4)), "tank")


def build_chessboard(
    scene: sapien.Scene,
    cols: int,
    rows: int,
    square_m: float,
    T_worldned_board: ArrayLike,
    white_rgb: RGB = (0.80, 0.80, 0.80),
    black_rgb: RGB = (0.03, 0.03, 0.03),
    thickness_m: float = 0.004,
) -> sapien.Entity:
    """A flat chessboard target (visual only): a calibration board under water, for the
    water fit (``sim fit-water``) and calibration tests.

    The board frame is OpenCV's chessboard object frame (``calibration.patterns``): origin at
    the first inner corner, x along the ``cols`` inner corners, y along the ``rows``, z into the
    board (the printed face is the plane z = 0, seen from -z). The ``(cols + 1) x (rows + 1)``
    squares alternate, the corner square black; each is a box of ``thickness_m`` behind the
    face.

    Args:
        scene: the scene.
        cols: inner corners along x (>= 2).
        rows: inner corners along y (>= 2).
        square_m: square side (m).
        T_worldned_board: board frame in world NED (e.g. on the tank floor, face up: z down).
        white_rgb: linear albedo of the white squares.
        black_rgb: linear albedo of the black squares.
        thickness_m: depth of the squares behind the face (m).

    Returns:
        The static board entity.
    """
    if int(cols) < 2 or int(rows) < 2 or not 0.0 < float(square_m) <= 10.0:
        raise ValueError(f"chessboard: need >= 2 x 2 inner corners and 0 < square <= 10 m, got "
                         f"{cols} x {rows}, {square_m} m")  # fmt: skip
    T = check_T(T_worldned_board, "T_worldned_board")
    body = _StaticBody(sapien.physx.PhysxMaterial(0.5, 0.5, 0.0))
    materials = (_render_material(black_rgb, 0.9), _render_material(white_rgb, 0.9))
    s, h = float(square_m), float(thickness_m) / 2.0
    for i in range(int(cols) + 1):
        for j in range(int(rows) + 1):
            centre = [(i - 0.5) * s, (j - 0.5) * s, h]
            body.box(centre, [s / 2, s / 2, h], materials[(i + j) % 2], collision=False)
    return body.build(scene, sapien_pose(T), "chessboard")
