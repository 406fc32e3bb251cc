"""``markers generate``: printable 3DBM parts, render meshes, a flat sheet, the marker set file."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uwdock.dockcore.config import validated
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_bytes
from uwdock.dockcore.outdir import claim_output_dir, tracked_outputs
from uwdock.dockcore.provenance import write_provenance
from uwdock.markers.config import MarkerConfig
from uwdock.markers.dictionary import marker_cells, normalise_dictionary_name
from uwdock.markers.geometry import (
    ENCLOSURE_RGBA,
    INSERT_RGBA,
    PRINT_RATE_MM3_PER_S,
    MarkerSolids,
    build_solids,
    print_estimate,
    rasterise_top_view,
    render_mesh_glb,
)
from uwdock.markers.markerset import MarkerSet, marker_set_from_config, save_marker_set
from uwdock.markers.meshcheck import CHECK_EXTRA_HINT, check_printable, open3d_available
from uwdock.markers.sheet import SheetEntry, render_sheet

MARKER_SET_NAME = "markerset.toml"

#: The tool name that claims ``markers generate``'s output folder.
TOOL = "markers generate"

#: Largest side of a preview's top view (px): large parts are rasterised more coarsely.
PREVIEW_MAX_PX = 2000


@dataclass(frozen=True)
class GenerateResult:
    """What ``generate`` wrote (absolute paths), and whether the STL parts were checked.

    Attributes:
        out_dir: the output folder.
        marker_set: the marker set file.
        files: every file written.
        mesh_checked: the STL parts passed :func:`markers.meshcheck.check_printable` (False:
            the check was skipped, open3d is not installed).
    """

    out_dir: Path
    marker_set: Path
    files: tuple[Path, ...]
    mesh_checked: bool = False


def file_stem(dictionary: str, marker_id: int) -> str:
    """``3dbm_DICT_4X4_50_13``: the stem every per-marker file starts with."""
    return f"3dbm_{dictionary}_{marker_id}"


def write_preview(path: Path, solids: MarkerSolids, cfg: MarkerConfig) -> Path:
    """PNG: top view of the assembled marker (from the meshes) beside an isometric view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    half = cfg.base_side / 2 * 1.05
    top = rasterise_top_view(
        [(solids.enclosure, ENCLOSURE_RGBA[0]), (solids.insert, INSERT_RGBA[0])],
        px_per_mm=min(4.0, PREVIEW_MAX_PX / (2 * half)),
        half_extent_mm=half,
        background=110,
    )
    fig = plt.figure(figsize=(9, 4.6), dpi=100)
    ax = fig.add_subplot(1, 2, 1)
    ax.imshow(top, cmap="gray", vmin=0, vmax=255, extent=(-half, half, -half, half))
    ax.set_title(f"top view (camera sees this): ID {solids.marker_id}")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    polys, colours = [], []
    for mesh, rgba in ((solids.enclosure, ENCLOSURE_RGBA), (solids.insert, INSERT_RGBA)):
        # small faces: matplotlib sorts whole faces by depth, large ones show through each other
        # (relative to the whole part, so a small tag on a large base stays a few 1000 faces)
        v, f = trimesh.remesh.subdivide_to_size(
            mesh.vertices, mesh.faces, max_edge=max(cfg.size_mm, cfg.base_side / 1.62) / 12
        )
        normals = trimesh.Trimesh(v, f, process=False).face_normals
        light = np.clip(0.35 + 0.65 * np.abs(normals @ np.array([0.3, -0.4, 0.87])), 0, 1)
        polys.extend(v[f])
        colours.append(np.clip(np.asarray(rgba[:3], float) / 255.0 * light[:, None] + 0.08, 0, 1))
    # one collection, so matplotlib depth-sorts the faces of both parts together
    ax3.add_collection3d(
        Poly3DCollection(
            polys, facecolors=np.vstack(colours), edgecolors="none", linewidths=0, antialiased=False
        )
    )
    lim = cfg.base_side / 2
    z0 = -(cfg.enclosure_height_mm + cfg.base_height_mm)
    ax3.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(z0, 0))
    ax3.set_box_aspect((1, 1, (-z0) / (2 * lim)))
    ax3.view_init(elev=35, azim=-60)
    ax3.set_title(f"{cfg.size_mm:g} mm insert on {cfg.enclosure_side:g} mm column")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def check_parts(stl: dict[str, bytes], check_meshes: bool | None = None) -> tuple[bool, str]:
    """Run the printability check on the STL parts (file name -> bytes) when open3d is
    installed (or ``check_meshes`` is True).

    Returns:
        ``(ran, line)``: whether the check ran, and one line saying what was done.

    Raises:
        DockError: one line naming the first part that fails, or ``check_meshes`` is True and
            open3d is missing.
    """
    if check_meshes is None:
        check_meshes = open3d_available()
    if not check_meshes:
        return False, f"mesh check skipped: open3d is not installed ({CHECK_EXTRA_HINT})"
    if not open3d_available():
        raise DockError(f"the mesh check needs open3d: {CHECK_EXTRA_HINT}")
    t0 = time.perf_counter()
    reports = check_printable(stl)
    return True, (
        f"mesh check: {len(reports)} STL parts watertight, manifold, consistently oriented, "
        f"no self-intersections ({time.perf_counter() - t0:.2f} s)"
    )


def generate(
    cfg: MarkerConfig,
    out_dir: str | os.PathLike[str],
    progress: Callable[[str], None] | None = None,
    check_meshes: bool | None = None,
) -> GenerateResult:
    """Write everything for the markers of ``cfg`` into ``out_dir``.

    The config is validated (:func:`dockcore.config.validated`), every solid is built and the
    sheet rendered before the output folder is claimed (:func:`dockcore.outdir.claim_output_dir`:
    a folder of another tool is refused) and the first file is written; each file is written
    atomically, the marker set file last. Per ID: ``<stem>_insert.stl`` (white part),
    ``<stem>_enclosure.stl`` (black part), ``<stem>.glb`` (render mesh, metres, with materials),
    ``<stem>_preview.png``; then ``sheet.pdf`` / ``sheet.svg``, ``markerset.toml``,
    ``config.toml`` and ``provenance.json``. A rerun into the same folder removes the files of
    the previous run that it does not write again (:func:`dockcore.outdir.tracked_outputs`: the
    parts of IDs no longer in the set).

    Before anything is written, the STL parts are checked for printability
    (:mod:`markers.meshcheck`: watertight, edge/vertex-manifold, no self-intersections) when
    open3d is installed (the ``check`` extra); otherwise ``progress`` is told it was skipped.

    Args:
        cfg: the marker config.
        out_dir: the output folder (claimed for ``markers generate``).
        progress: called with one line per step (None: silent).
        check_meshes: run the mesh check (True: open3d required), skip it (False), or run it
            when open3d is installed (None).

    Raises:
        ConfigError: an invalid config (one line naming the field).
        DockError: the markers do not fit on the paper, a part fails the mesh check, or the
            folder cannot be claimed.
    """
    say = progress or (lambda _msg: None)
    cfg = validated(cfg)
    parts = _build_parts(cfg)
    checked, check_line = check_parts(parts.stl, check_meshes)  # once every value is known to work

    written: list[Path] = []  # tracked: a rerun removes the files of IDs no longer in the set
    with claim_output_dir(out_dir, TOOL) as claimed, tracked_outputs(claimed, written):
        out = claimed.resolve()
        say(check_line)
        for i in cfg.ids:
            _write_marker(out, cfg, parts, i, written, say)
        sheets = [atomic_write_bytes(out / path, data) for path, data in parts.sheet_files]
        written.extend(sheets)
        say(f"flat sheet: {', '.join(p.name for p in sheets)}")
        written.append(save_marker_set(out / MARKER_SET_NAME, parts.marker_set))
        write_provenance(out, {"marker": cfg})
        written.extend([out / "config.toml", out / "provenance.json"])
    say(f"marker set: {out / MARKER_SET_NAME}")
    return GenerateResult(out, out / MARKER_SET_NAME, tuple(written), checked)


@dataclass(frozen=True)
class _Parts:
    """What :func:`generate` writes, built in memory before the folder is claimed."""

    dictionary: str  # the normalised dictionary name
    solids: dict[int, MarkerSolids]  # marker ID -> its printable parts
    mesh_names: dict[int, str]  # marker ID -> its render mesh's file name
    marker_set: MarkerSet
    stl: dict[str, bytes]  # file name -> STL part
    sheet_files: list[tuple[Path, bytes]]  # the flat sheet's files


def _build_parts(cfg: MarkerConfig) -> _Parts:
    """Every solid, STL part and sheet page of ``cfg``'s markers, and their marker set."""
    dictionary = normalise_dictionary_name(cfg.dictionary)
    ids = cfg.ids
    solids = {i: build_solids(cfg, i) for i in ids}
    mesh_names = {i: f"{file_stem(dictionary, i)}.glb" for i in ids}
    ms = marker_set_from_config(cfg, mesh_names)
    entries = [
        SheetEntry(i, marker_cells(dictionary, i), f"{dictionary} id {i}  {cfg.size_mm:g} mm")
        for i in ids
    ]
    stl = {
        f"{file_stem(dictionary, i)}_{part}.stl": mesh.export(file_type="stl")
        for i in ids
        for part, mesh in (("insert", solids[i].insert), ("enclosure", solids[i].enclosure))
    }
    title = f"3D Binary Marker flat test tags ({dictionary})"
    sheet_files = render_sheet(
        entries, cfg.size_mm, Path("sheet.pdf"), Path("sheet.svg"), paper=cfg.paper, title=title
    )
    return _Parts(dictionary, solids, mesh_names, ms, stl, sheet_files)


def _write_marker(
    out: Path,
    cfg: MarkerConfig,
    parts: _Parts,
    marker_id: int,
    written: list[Path],
    say: Callable[[str], None],
) -> None:
    """Marker ``marker_id``'s STL parts, render mesh and preview, each added to ``written`` as
    it is written; then its line (files, plastic, print time) to ``say``."""
    stem = file_stem(parts.dictionary, marker_id)
    s = parts.solids[marker_id]
    for part in ("insert", "enclosure"):
        name = f"{stem}_{part}.stl"
        written.append(atomic_write_bytes(out / name, parts.stl[name]))
    written.append(atomic_write_bytes(out / parts.mesh_names[marker_id], render_mesh_glb(s)))
    written.append(write_preview(out / f"{stem}_preview.png", s, cfg))
    est = print_estimate(s)
    say(
        f"marker {marker_id}: {stem}_insert.stl, {stem}_enclosure.stl, {stem}.glb, "
        f"{stem}_preview.png; plastic: insert {est['insert_cm3']:.0f} cm3, enclosure "
        f"{est['enclosure_cm3']:.0f} cm3, ~{est['print_hours_estimate']:.0f} h to print "
        f"solid at {PRINT_RATE_MM3_PER_S:g} mm3/s"
    )
