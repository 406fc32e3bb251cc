"""3D geometry of a 3D Binary Marker: the white insert, the black enclosure, their meshes.

Frame of every mesh here: the **marker frame** (OpenCV ArUco convention): origin at the centre of
the insert's top face (the face the camera sees), x right, y toward the top row of the tag, z up
out of the face. Printable STL files are in millimetres (what slicers expect); render meshes for
the simulator are in metres.

Construction (manifold3d, so every solid is manifold by construction):

* insert: the tag square extruded by ``insert_thickness_mm`` from z = -t to 0, minus openings at
  the tag's white cells (each widened by ``clearance/2``, so cells that touch only diagonally
  never leave a zero-width bridge);
* enclosure: base plate + column, with a pocket (the seat) of depth t that holds the insert with
  ``clearance_mm`` all round; where ``relief_depth_mm < t``, black bosses (white cells shrunk by
  ``clearance/2``) rise from the pocket floor to depth ``relief_depth_mm``.

The ``published`` style (``MarkerConfig.style``) follows the construction of the published,
tank-proven marker (docs/reference-system.md section 5: a thin insert over a hollow shell,
its openings looking into a dark cavity), in our own geometry:

* insert: a plate ``plate_thickness_mm`` thick with the same openings, and four locating tabs
  (a press fit) under the tag's border cells, one per side;
* enclosure: a hollow box ``enclosure_side`` wide and ``enclosure_height_mm`` tall with a closed
  floor and ``shell_wall_mm`` walls: the plate lies in a pocket on a ledge ``lip_mm`` wide under
  the border cells (slotted for the tabs); below the ledge the walls lean in at 45 deg, so the
  box prints upright without supports; four corner posts with blind screw holes from below.
  Seen from above, the openings look into the closed black cavity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import manifold3d as mf
import numpy as np

from uwdock.markers.config import MarkerConfig
from uwdock.markers.dictionary import marker_cells

if TYPE_CHECKING:
    import trimesh

# trimesh (about a second to import: scipy, networkx) is imported by the functions that make
# meshes, so importing this module (and every command that reaches it) does not pay for it.

#: Colours of the two printed parts (RGBA, 0-255), also used by the render meshes.
INSERT_RGBA = (235, 235, 230, 255)
ENCLOSURE_RGBA = (20, 20, 22, 255)

#: Version of the render meshes' construction (part of the simulator's marker cache key):
#: 2 = every triangle its own corners, so the exported vertex normals are the face normals.
RENDER_MESH_VERSION = 2


@dataclass(frozen=True)
class MarkerSolids:
    """The two printable parts of one marker, in the marker frame, millimetres."""

    marker_id: int
    insert: trimesh.Trimesh
    enclosure: trimesh.Trimesh


def _cell_squares(cells: np.ndarray, size_mm: float) -> list[np.ndarray]:
    """One CCW square contour (4, 2) in mm for every ``True`` cell (row 0 = top of the tag)."""
    n = cells.shape[0]
    a = size_mm / n
    half = size_mm / 2
    out = []
    for r, c in zip(*np.nonzero(cells), strict=True):
        x0, y1 = -half + c * a, half - r * a
        x1, y0 = x0 + a, y1 - a
        out.append(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64))
    return out


def _square(side: float) -> mf.CrossSection:
    return mf.CrossSection.square((side, side), center=True)


def _slab(cs: mf.CrossSection, z0: float, z1: float) -> mf.Manifold:
    """Extrude a cross-section between heights z0 < z1."""
    return mf.Manifold.extrude(cs, z1 - z0).translate((0.0, 0.0, z0))


def _to_trimesh(m: mf.Manifold) -> trimesh.Trimesh:
    import trimesh

    mesh = m.to_mesh()
    tm = trimesh.Trimesh(
        vertices=np.asarray(mesh.vert_properties)[:, :3].astype(np.float64),
        faces=np.asarray(mesh.tri_verts).astype(np.int64),
        process=True,
    )
    tm.fix_normals()
    return tm


def white_openings(cells: np.ndarray, size_mm: float, grow_mm: float) -> mf.CrossSection:
    """Union of the tag's white cells, offset by ``grow_mm`` (negative shrinks), in mm."""
    squares = _cell_squares(~cells, size_mm)
    if not squares:
        return mf.CrossSection()
    cs = mf.CrossSection(squares)
    return cs.offset(grow_mm, mf.JoinType.Miter) if grow_mm else cs


def build_solids(cfg: MarkerConfig, marker_id: int) -> MarkerSolids:
    """The insert and enclosure of marker ``marker_id`` as watertight meshes (mm, marker frame),
    in the config's ``style``."""
    if cfg.style == "published":
        return _published_solids(cfg, marker_id)
    cells = marker_cells(cfg.dictionary, marker_id)
    s, t, c = cfg.size_mm, cfg.insert_thickness_mm, cfg.clearance_mm

    insert_cs = _square(s) - white_openings(cells, s, +c / 2)
    insert = _slab(insert_cs, -t, 0.0)

    h_col, h_base = cfg.enclosure_height_mm, cfg.base_height_mm
    column = _slab(_square(cfg.enclosure_side), -h_col, 0.0)
    base = _slab(_square(cfg.base_side), -h_col - h_base, -h_col)
    pocket = _slab(_square(s + 2 * c), -t, 1.0)  # cut through the top face
    enclosure = (column + base) - pocket
    boss_height = t - cfg.relief_depth_mm
    if boss_height > 1e-9:
        bosses = _slab(white_openings(cells, s, -c / 2), -t, -cfg.relief_depth_mm)
        enclosure = enclosure + bosses
    return MarkerSolids(marker_id, _to_trimesh(insert), _to_trimesh(enclosure))


def _four_sides(part: mf.Manifold) -> mf.Manifold:
    """``part`` and its copies turned 90, 180 and 270 deg about the marker's z axis."""
    return mf.Manifold.batch_boolean(
        [part.rotate((0.0, 0.0, 90.0 * k)) for k in range(4)], mf.OpType.Add
    )


def _published_solids(cfg: MarkerConfig, marker_id: int) -> MarkerSolids:
    """The ``published`` style: a thin plate insert on a hollow shell (module docstring)."""
    cells = marker_cells(cfg.dictionary, marker_id)
    s, c = cfg.size_mm, cfg.clearance_mm
    t, lip, lip_t = cfg.plate_thickness_mm, cfg.lip_mm, cfg.lip_thickness_mm
    side, h = cfg.enclosure_side, cfg.enclosure_height_mm
    seat = s + 2 * c  # the pocket the plate lies in
    # the cavity's opening inside the ledge, and 45 deg from the walls in to it: prints upright
    inner, window, chamfer = cfg.shell_mm()
    z_ledge = -t - lip_t  # underside of the ledge
    z_chamfer = z_ledge - chamfer  # where the walls start to lean in
    z_floor = -h + cfg.shell_floor_mm

    # insert: the plate with the openings, and a locating tab under each side's border cells
    plate = _slab(_square(s) - white_openings(cells, s, +c / 2), -t, 0.0)
    tab_len, tab_w = min(8.0, s / 4), min(2.0, lip / 2)
    tab_off = s / 2 - lip / 2  # the tabs stand on the ledge's centre line
    tab = _slab(mf.CrossSection.square((tab_w, tab_len), center=True), z_ledge, -t)
    insert = plate + _four_sides(tab.translate((tab_off, 0.0, 0.0)))

    # enclosure: a box, hollowed: pocket, ledge window, 45 deg chamfer, cavity, closed floor
    box = _slab(_square(side), -h, 0.0)
    pocket = _slab(_square(seat), -t, 1.0)
    window_cut = _slab(_square(window), z_ledge - 1e-3, -t + 1e-3)
    lean = mf.Manifold.extrude(_square(inner), chamfer, scale_top=(window / inner, window / inner))
    lean = lean.translate((0.0, 0.0, z_chamfer))
    cavity = _slab(_square(inner), z_floor, z_chamfer + 1e-3)
    slot_cs = mf.CrossSection.square((tab_w + 2 * c, tab_len + 2 * c), center=True)
    slot = _slab(slot_cs, z_ledge - 1e-3, -t + 1e-3).translate((tab_off, 0.0, 0.0))
    shell = box - pocket - window_cut - lean - cavity - _four_sides(slot)  # the tabs' slots
    if cfg.post_side_mm > 0:  # corner posts from the floor up into the chamfer
        p = cfg.post_side_mm
        q = inner / 2 - p / 2
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            post = _slab(_square(p), z_floor - 1e-3, z_chamfer + 1e-3).translate(
                (sx * q, sy * q, 0)
            )
            shell = shell + post
            if cfg.post_hole_mm > 0:
                depth = min(20.0, z_chamfer - (-h) - 1.0)
                hole = mf.Manifold.cylinder(depth + 1.0, cfg.post_hole_mm / 2, circular_segments=24)
                shell = shell - hole.translate((sx * q, sy * q, -h - 1.0))
    return MarkerSolids(marker_id, _to_trimesh(insert), _to_trimesh(shell))


#: Extrusion rate of the print-time estimate (mm^3 / s): a 0.4 mm nozzle laying 0.2 mm layers
#: at 100 mm/s, parts printed solid.
PRINT_RATE_MM3_PER_S = 8.0


def print_estimate(solids: MarkerSolids) -> dict[str, float]:
    """Plastic volume (cm^3) of each part and an estimated print time (h) at
    :data:`PRINT_RATE_MM3_PER_S`, printed solid (a slicer's infill prints sparser and faster)."""
    v_insert = float(solids.insert.volume) / 1e3
    v_enclosure = float(solids.enclosure.volume) / 1e3
    hours = (v_insert + v_enclosure) * 1e3 / PRINT_RATE_MM3_PER_S / 3600.0
    return {
        "insert_cm3": v_insert,
        "enclosure_cm3": v_enclosure,
        "print_hours_estimate": hours,
    }


def render_scene(solids: MarkerSolids) -> trimesh.Scene:
    """Both parts with PBR materials (white insert, black enclosure), in **metres**, for SAPIEN.

    The parts are made of flat faces meeting at sharp edges, so they are exported flat shaded:
    each triangle keeps its own corners and its vertex normals are its face normal. Shared
    corners would average the normals of the top and the side faces, and on a 1 mm plate that
    shades the whole top dark toward its edges."""
    import trimesh

    scene = trimesh.Scene()
    for name, mesh, rgba in (
        ("insert", solids.insert, INSERT_RGBA),
        ("enclosure", solids.enclosure, ENCLOSURE_RGBA),
    ):
        m = mesh.copy()
        m.apply_scale(1e-3)
        m.unmerge_vertices()  # flat shading (see above)
        m.visual = trimesh.visual.TextureVisuals(
            material=trimesh.visual.material.PBRMaterial(
                name=f"3dbm_{name}", baseColorFactor=rgba, metallicFactor=0.0, roughnessFactor=0.9
            )
        )
        scene.add_geometry(m, node_name=name, geom_name=name)
    return scene


def render_mesh_glb(solids: MarkerSolids) -> bytes:
    """The render mesh file (GLB, metres) of :func:`render_scene`, with its flat vertex normals
    written out (a GLB without normals gets smooth ones from the loader)."""
    return bytes(render_scene(solids).export(file_type="glb", include_normals=True))


def rasterise_top_view(
    parts: list[tuple[trimesh.Trimesh, int]],
    px_per_mm: float,
    half_extent_mm: float,
    background: int = 128,
) -> np.ndarray:
    """Orthographic top view (looking down -z) of meshes, rasterised from their triangles.

    Upward-facing triangles are painted from the lowest to the highest (a painter's algorithm
    that is exact for the horizontal faces these parts are made of).

    Args:
        parts: (mesh in mm, grey level 0-255) pairs.
        px_per_mm: image resolution.
        half_extent_mm: the image spans [-h, h] mm in x and y, centred on the marker frame origin.
        background: grey level where no part is seen.

    Returns:
        (N, N) uint8 image, row 0 at +y (top of the tag), column 0 at -x.
    """
    n = round(2 * half_extent_mm * px_per_mm)
    img = np.full((n, n), background, np.uint8)
    faces = []
    for mesh, grey in parts:
        up = mesh.face_normals[:, 2] > 1e-6
        tris = mesh.vertices[mesh.faces[up]]
        for tri in tris:
            faces.append((float(tri[:, 2].mean()), tri, grey))
    faces.sort(key=lambda f: f[0])
    shift = 4  # sub-pixel precision bits for cv2.fillPoly
    scale = px_per_mm * (1 << shift)
    for _, tri, grey in faces:
        u = (tri[:, 0] + half_extent_mm) * scale
        v = (half_extent_mm - tri[:, 1]) * scale
        pts = np.round(np.stack([u, v], axis=1) - 0.5 * (1 << shift)).astype(np.int32)
        cv2.fillPoly(img, [pts], int(grey), lineType=cv2.LINE_8, shift=shift)
    return img
