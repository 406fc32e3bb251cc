"""Printability check of the STL parts that ``markers generate`` writes, with open3d.

A slicer sees an STL file as a soup of triangles whose corners it welds where their coordinates
are equal. A part prints as intended only when that welded mesh is closed and 2-manifold and
does not cut through itself; :func:`check_stl` checks exactly that on the bytes about to be
written (binary STL, corners welded on their exact float32 coordinates):

* no open edge (an edge used by one triangle: a hole) and no edge shared by more than two
  triangles (``open3d.geometry.TriangleMesh.get_non_manifold_edges``);
* no non-manifold vertex (two sheets touching at one point; ``get_non_manifold_vertices``);
* no pair of triangles that intersect other than along a shared edge or corner
  (``get_self_intersecting_triangles``);
* the triangles are consistently oriented (every edge is walked once each way by its two
  triangles) with their normals outward (positive enclosed volume).

open3d is the ``check`` extra (``pip install 'uwdock[check]'``); :func:`open3d_available`
says whether it is installed, and the base install (footage tools) stays without it.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

import numpy as np

from uwdock.dockcore.errors import DockError

__all__ = [
    "CHECK_EXTRA_HINT",
    "MeshReport",
    "check_printable",
    "check_stl",
    "open3d_available",
    "stl_triangles",
]

#: How to get the check where open3d is missing (shown when it is skipped).
CHECK_EXTRA_HINT = "pip install 'uwdock[check]'"

_STL_HEADER_BYTES = 80
_STL_RECORD = np.dtype(
    [("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")]
)  # 50 bytes per triangle


@dataclass(frozen=True)
class MeshReport:
    """What :func:`check_stl` found in one part.

    Attributes:
        name: the part's file name.
        triangles: triangle count.
        vertices: vertex count after welding equal corners.
        open_edges: edges used by one triangle only (holes).
        non_manifold_edges: edges shared by more than two triangles.
        non_manifold_vertices: vertices where separate sheets of the surface touch.
        self_intersecting_pairs: pairs of triangles that cut through each other.
        misoriented_edges: edges walked the same way by two triangles (a flipped triangle).
        volume: signed enclosed volume (file units cubed, mm^3 for the parts); negative when
            the part is inside out.
    """

    name: str
    triangles: int
    vertices: int
    open_edges: int
    non_manifold_edges: int
    non_manifold_vertices: int
    self_intersecting_pairs: int
    misoriented_edges: int
    volume: float

    @property
    def problems(self) -> list[str]:
        """Each failed check as a short phrase; empty when the part is printable."""
        out = []
        if self.triangles == 0:
            out.append("no triangles")
        for count, one, many in (
            (self.open_edges, "open edge", "open edges"),
            (self.non_manifold_edges, "non-manifold edge", "non-manifold edges"),
            (self.non_manifold_vertices, "non-manifold vertex", "non-manifold vertices"),
            (
                self.self_intersecting_pairs,
                "self-intersecting triangle pair",
                "self-intersecting triangle pairs",
            ),
            (self.misoriented_edges, "flipped edge", "flipped edges"),
        ):
            if count:
                out.append(f"{count} {one if count == 1 else many}")
        if self.triangles and not self.volume > 0:
            out.append(f"inside out (volume {self.volume:.6g})")
        return out

    @property
    def ok(self) -> bool:
        """True when the part is watertight, manifold and free of self-intersections."""
        return not self.problems


def open3d_available() -> bool:
    """Whether open3d (the ``check`` extra) can be imported."""
    try:
        return importlib.util.find_spec("open3d") is not None
    except (ImportError, ValueError):
        return False


def stl_triangles(data: bytes, name: str = "STL") -> tuple[np.ndarray, np.ndarray]:
    """Binary STL bytes -> welded ``(vertices, faces)``.

    Returns:
        ``(V, 3)`` float64 vertex positions (the file's units) and ``(F, 3)`` int32 vertex
        indices per triangle; corners with equal float32 coordinates share one vertex.

    Raises:
        DockError: not a binary STL (too short, or its triangle count disagrees with its size).
    """
    if len(data) < _STL_HEADER_BYTES + 4:
        raise DockError(f"{name}: not a binary STL file ({len(data)} bytes)")
    count = int.from_bytes(data[_STL_HEADER_BYTES : _STL_HEADER_BYTES + 4], "little")
    expected = _STL_HEADER_BYTES + 4 + count * _STL_RECORD.itemsize
    if len(data) != expected:
        raise DockError(
            f"{name}: not a binary STL file (header says {count} triangles, size {len(data)} B)"
        )
    records = np.frombuffer(data, _STL_RECORD, count, offset=_STL_HEADER_BYTES + 4)
    corners = records["corners"].reshape(-1, 3)
    vertices, index = np.unique(corners, axis=0, return_inverse=True)
    return vertices.astype(np.float64), index.reshape(-1, 3).astype(np.int32)


def check_stl(data: bytes, name: str = "STL") -> MeshReport:
    """Check that binary STL bytes describe a printable solid (see the module docstring).

    Args:
        data: a binary STL file's bytes.
        name: the file name, for messages.

    Raises:
        ModuleNotFoundError: open3d is not installed (:func:`open3d_available`).
        DockError: not a binary STL.
    """
    import open3d as o3d

    vertices, faces = stl_triangles(data, name)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces)
    )
    every_bad_edge = len(mesh.get_non_manifold_edges(allow_boundary_edges=False))
    shared_by_3 = len(mesh.get_non_manifold_edges(allow_boundary_edges=True))
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, uses = np.unique(directed, axis=0, return_counts=True)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)  # divergence theorem
    return MeshReport(
        name=name,
        triangles=len(faces),
        vertices=len(vertices),
        open_edges=every_bad_edge - shared_by_3,
        non_manifold_edges=shared_by_3,
        non_manifold_vertices=len(mesh.get_non_manifold_vertices()),
        self_intersecting_pairs=len(mesh.get_self_intersecting_triangles()),
        misoriented_edges=int(np.count_nonzero(uses > 1)),
        volume=volume,
    )


def check_printable(parts: dict[str, bytes]) -> list[MeshReport]:
    """Check every part (file name -> binary STL bytes); raise on the first that fails.

    Returns:
        One report per part, in order, when all pass.

    Raises:
        ModuleNotFoundError: open3d is not installed.
        DockError: one line naming the part and what is wrong with it.
    """
    reports = []
    for name, data in parts.items():
        report = check_stl(data, name)
        if not report.ok:
            problems = ", ".join(report.problems)
            raise DockError(f"printable part {name} failed the mesh check: {problems}")
        reports.append(report)
    return reports
