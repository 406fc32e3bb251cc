"""The marker set file: the single source of truth for which markers exist and where they sit.

Written by ``markers generate``; read by perception (board geometry for PnP) and the simulator
(which meshes to place where). TOML (``.toml``) or JSON (``.json``), same content::

    format = "uwdock.markerset"
    version = 1
    [[markers]]
    id = 13
    dictionary = "DICT_4X4_50"
    side_m = 0.1
    corners_marker_m = [[-0.05, 0.05, 0.0], ...]   # TL, TR, BR, BL in the marker frame
    T_ds_marker = [[1, 0, 0, 0.87], ...]           # 4x4, marker frame in the DS frame
    render_mesh = "3dbm_DICT_4X4_50_13.glb"        # optional, relative to the file

Frames: marker = OpenCV ArUco (z out of the face, x right, y up, origin at the face centre);
ds = docking station, x forward, y starboard, z down (the reference's convention).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from uwdock.calibration.frames import check_T, make_T, transform_points
from uwdock.dockcore.config import read_toml, validated
from uwdock.dockcore.domains import Finite, check, describe, split_annotated
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.dockcore.io import atomic_write_text, read_text
from uwdock.markers.config import MAX_DS_COORD_M, MarkerConfig, MarkerSideM, PartSideMm
from uwdock.markers.dictionary import check_ids, normalise_dictionary_name

FORMAT = "uwdock.markerset"
VERSION = 1


def corners_marker_m(side_m: float) -> np.ndarray:
    """(4, 3) corners TL, TR, BR, BL of a square marker of side ``side_m`` in the marker frame."""
    h = side_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def T_ds_marker_face_up(x_m: float, y_m: float, z_m: float, yaw_deg: float) -> np.ndarray:
    """Pose of a face-up marker on the DS: marker z = -z_ds (up), marker x at ``yaw_deg`` from DS x.

    The rotation is a 180 degree turn about the DS x axis (so marker y = -y_ds) followed by
    the in-plane yaw about the DS z axis.
    """
    yaw = math.radians(yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    flip = np.diag([1.0, -1.0, -1.0])
    return make_T(Rz @ flip, [x_m, y_m, z_m])


@dataclass(frozen=True)
class MarkerSpec:
    """One marker of the set.

    Attributes:
        marker_id: ID in ``dictionary``.
        dictionary: canonical OpenCV dictionary name.
        side_m: side of the tag (outer edge of its border), metres.
        T_ds_marker: (4, 4) marker frame in the DS frame.
        render_mesh: path of the render mesh (GLB, metres), relative to the set file, or None.
    """

    marker_id: int
    dictionary: str
    side_m: float
    T_ds_marker: np.ndarray
    render_mesh: str | None = None

    @property
    def corners_marker_m(self) -> np.ndarray:
        """(4, 3) corners TL, TR, BR, BL in the marker frame (m)."""
        return corners_marker_m(self.side_m)

    @property
    def corners_ds_m(self) -> np.ndarray:
        """(4, 3) corners TL, TR, BR, BL in the DS frame (m)."""
        return transform_points(self.T_ds_marker, self.corners_marker_m)


@dataclass(frozen=True)
class MarkerSet:
    """All markers of a docking station, plus the geometry they were generated with."""

    markers: tuple[MarkerSpec, ...]
    geometry: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(m.marker_id for m in self.markers)

    @property
    def dictionary(self) -> str:
        """The dictionary shared by all markers (a set mixing dictionaries is rejected on load)."""
        return self.markers[0].dictionary

    def __getitem__(self, marker_id: int) -> MarkerSpec:
        for m in self.markers:
            if m.marker_id == marker_id:
                return m
        raise KeyError(marker_id)

    def corners_ds(self) -> dict[int, np.ndarray]:
        """Board geometry for PnP: ID -> (4, 3) corners TL, TR, BR, BL in the DS frame (m)."""
        return {m.marker_id: m.corners_ds_m for m in self.markers}

    def render_mesh_path(self, marker_id: int) -> Path | None:
        """Absolute path of a marker's render mesh, if the set names one."""
        rel = self[marker_id].render_mesh
        if rel is None:
            return None
        base = self.path.parent if self.path is not None else Path.cwd()
        return (base / rel).resolve()

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "geometry": dict(self.geometry),
            "markers": [
                {
                    "id": m.marker_id,
                    "dictionary": m.dictionary,
                    "side_m": m.side_m,
                    "corners_marker_m": m.corners_marker_m.tolist(),
                    "T_ds_marker": np.asarray(m.T_ds_marker).tolist(),
                    **({"render_mesh": m.render_mesh} if m.render_mesh else {}),
                }
                for m in self.markers
            ],
        }


def marker_set_from_config(
    cfg: MarkerConfig, mesh_names: dict[int, str] | None = None
) -> MarkerSet:
    """The marker set that ``markers generate`` writes for ``cfg``.

    IDs in ``cfg.layout`` take that pose; others are placed face up on a grid on the DS floor
    (z = -0.26 m, the reference floor markers' height), spaced 1.5 enclosure sides apart.

    Raises:
        ConfigError: an invalid config (:func:`dockcore.config.validated`).
    """
    cfg = validated(cfg)
    dictionary = normalise_dictionary_name(cfg.dictionary)
    ids = cfg.ids
    pitch_m = 1.5 * max(cfg.base_side, cfg.enclosure_side) / 1000.0
    unplaced = [i for i in ids if str(i) not in cfg.layout]
    cols = max(1, math.ceil(math.sqrt(len(unplaced))))
    placed = np.array(
        [[float(v) for v in cfg.layout[str(i)][:3]] for i in ids if str(i) in cfg.layout]
    ).reshape(-1, 3)
    cells = _grid_cells(len(unplaced), cols, pitch_m, placed, cfg.size_m)
    specs = []
    for marker_id in ids:
        if str(marker_id) in cfg.layout:
            x, y, z, yaw = (float(v) for v in cfg.layout[str(marker_id)])
        else:
            x, y, z, yaw = (*cells[unplaced.index(marker_id)], 0.0)
        specs.append(
            MarkerSpec(
                marker_id,
                dictionary,
                cfg.size_m,
                T_ds_marker_face_up(x, y, z, yaw),
                (mesh_names or {}).get(marker_id),
            )
        )
    complaint = overlap_complaint(specs)
    if complaint:
        raise ConfigError(f"layout: {complaint}")
    resolved = {"enclosure_side_mm": cfg.enclosure_side, "base_side_mm": cfg.base_side}
    geometry = {k: resolved.get(k, getattr(cfg, k)) for k in _GEOMETRY_KEYS}
    return MarkerSet(tuple(specs), geometry)


def _grid_cells(
    n: int, cols: int, pitch_m: float, placed: np.ndarray, side_m: float
) -> list[tuple[float, float, float]]:
    """``n`` face-up positions (m, DS frame) on a grid on the DS floor, ``cols`` wide, centred on
    the DS origin, skipping the cells where a marker of the layout (``placed``, (P, 3) centres)
    already sits (closer than a marker side)."""
    cells: list[tuple[float, float, float]] = []
    k = 0
    while len(cells) < n:
        r, c = divmod(k, cols)
        cell = ((r - (n - 1) // cols / 2) * pitch_m, (c - (cols - 1) / 2) * pitch_m, -0.26)
        k += 1
        if len(placed) and np.linalg.norm(placed - np.array(cell), axis=1).min() < side_m:
            continue
        cells.append(cell)
    return cells


def overlap_complaint(specs: tuple[MarkerSpec, ...] | list[MarkerSpec]) -> str | None:
    """One line naming the first two markers that overlap, else None.

    Two markers overlap when their centres are closer than their mean side: then the discs
    inscribed in the two tags intersect (for coplanar tags: the tags themselves do). A set with
    every marker at one pose is the extreme case: PnP on it has no geometry to solve with.
    """
    if len(specs) < 2:
        return None
    centres = np.array([np.asarray(s.T_ds_marker)[:3, 3] for s in specs])
    sides = np.array([s.side_m for s in specs])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    close = d < (sides[:, None] + sides[None]) / 2
    np.fill_diagonal(close, False)
    if not close.any():
        return None
    i, j = (int(v) for v in np.argwhere(close)[0])
    a, b = specs[i], specs[j]
    same = sum(bool(close[i, k]) for k in range(len(specs))) + 1
    what = (
        f"{same} markers, {a.marker_id} and {b.marker_id} among them,"
        if same > 2
        else (f"markers {a.marker_id} and {b.marker_id}")
    )
    return (
        f"{what} overlap: centres {d[i, j]:.3g} m apart, less than a marker side "
        f"({(a.side_m + b.side_m) / 2:g} m); give each marker its own place"
    )


def save_marker_set(path: str | os.PathLike[str], ms: MarkerSet) -> Path:
    """Write ``ms`` atomically as TOML or JSON (by the file's extension)."""
    path = Path(path)
    data = ms.to_dict()
    if path.suffix.lower() == ".json":
        text = json.dumps(data, indent=2) + "\n"
    elif path.suffix.lower() == ".toml":
        text = "# Marker set: written by `markers generate`; read by perception and sim.\n"
        text += tomli_w.dumps(data)
    else:
        raise DockError(f"marker set file must end in .toml or .json: {path}")
    return atomic_write_text(path, text)


def _fail(path: Path, msg: str) -> ConfigError:
    return ConfigError(f"invalid marker set {path}: {msg}")


#: Keys of the file, of a ``[[markers]]`` entry and of the ``[geometry]`` table.
_FILE_KEYS = ("format", "version", "geometry", "markers")
_MARKER_KEYS = ("id", "dictionary", "side_m", "corners_marker_m", "T_ds_marker", "render_mesh")
_GEOMETRY_KEYS = (
    "size_mm",
    "insert_thickness_mm",
    "relief_depth_mm",
    "clearance_mm",
    "enclosure_side_mm",
    "enclosure_height_mm",
    "base_side_mm",
    "base_height_mm",
)
#: Largest distance of a marker from the DS origin along each axis (m) a marker set may state
#: (the domain of ``MarkerConfig.layout``).
MAX_OFFSET_M = MAX_DS_COORD_M
#: Domains of a matrix element and of a ``[geometry]`` dimension (mm).
_FINITE = split_annotated(Finite)
_PART_MM = split_annotated(PartSideMm)


def _unknown_key(table: dict, allowed: tuple[str, ...], where: str) -> str | None:
    """The first key of ``table`` outside ``allowed`` as a one-line complaint, else None."""
    unknown = sorted(str(k) for k in table if k not in allowed)
    if not unknown:
        return None
    return f"{where}unknown key '{unknown[0]}' (valid keys: {', '.join(allowed)})"


def _matrix(value: object, shape: tuple[int, int], where: str) -> np.ndarray:
    """A nested list of finite numbers of ``shape`` as float64 (ValueError naming ``where``)."""
    rows = value if isinstance(value, list) else None
    if (
        rows is None
        or len(rows) != shape[0]
        or not all(isinstance(r, list) and len(r) == shape[1] for r in rows)
    ):
        raise ValueError(f"{where} must be a {shape[0]}x{shape[1]} list of numbers")
    bad = [v for r in rows for v in r if check(v, *_FINITE, where)]
    if bad:
        raise ValueError(f"{where} must hold finite numbers, got {bad[0]!r}")
    return np.array(rows, dtype=np.float64)


def _marker_spec(e: object, where: str) -> MarkerSpec:
    """One ``[[markers]]`` entry, validated (ValueError or DockError naming ``where``)."""
    if not isinstance(e, dict):
        raise ValueError(f"{where} must be a table")
    complaint = _unknown_key(e, _MARKER_KEYS, f"{where}: ")
    if complaint:
        raise ValueError(complaint)
    for key in ("id", "dictionary", "side_m", "T_ds_marker"):
        if key not in e:
            raise ValueError(f"{where}: missing key '{key}'")
    marker_id = e["id"]
    if isinstance(marker_id, bool) or not isinstance(marker_id, int):
        raise ValueError(f"{where}.id must be an integer, got {marker_id!r}")
    if not isinstance(e["dictionary"], str):
        raise ValueError(f"{where}.dictionary must be a string, got {e['dictionary']!r}")
    dictionary = normalise_dictionary_name(e["dictionary"])
    check_ids(dictionary, [marker_id])
    reason = check(e["side_m"], *split_annotated(MarkerSideM), f"{where}.side_m")
    if reason:
        raise ValueError(f"{reason} (m)")
    side_m = float(e["side_m"])
    T = check_T(_matrix(e["T_ds_marker"], (4, 4), f"{where}.T_ds_marker"), f"{where}.T_ds_marker")
    if np.abs(T[:3, 3]).max() > MAX_OFFSET_M:
        raise ValueError(
            f"{where}.T_ds_marker: the marker lies {np.abs(T[:3, 3]).max():g} m from the DS "
            f"origin (at most {MAX_OFFSET_M:g} m)"
        )
    if "corners_marker_m" in e:
        corners = _matrix(e["corners_marker_m"], (4, 3), f"{where}.corners_marker_m")
        if not np.allclose(corners, corners_marker_m(side_m), atol=1e-9):
            raise ValueError(f"{where}.corners_marker_m disagree with side_m={side_m:g}")
    mesh = e.get("render_mesh")
    if mesh is not None and not (isinstance(mesh, str) and mesh):
        raise ValueError(f"{where}.render_mesh must be a file name, got {mesh!r}")
    return MarkerSpec(marker_id, dictionary, side_m, T, mesh)


def _geometry(value: object) -> dict:
    """The optional ``[geometry]`` table: known keys, finite dimensions in (0, 2000] mm."""
    if not isinstance(value, dict):
        raise ValueError("geometry must be a table")
    complaint = _unknown_key(value, _GEOMETRY_KEYS, "geometry: ")
    if complaint:
        raise ValueError(complaint)
    for key, v in value.items():
        if check(v, *_PART_MM, key):
            raise ValueError(f"geometry.{key} must be {describe(_PART_MM[1])} mm, got {v!r}")
    return dict(value)


def _read_marker_file(path: Path) -> object:
    """The parsed TOML or JSON of a marker set file (ConfigError: missing, not UTF-8, malformed)."""
    if path.suffix.lower() != ".json":
        return read_toml(path, what="marker set file")
    text = read_text(path, "marker set file")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise _fail(path, f"malformed JSON ({exc})") from None


def load_marker_set(path: str | os.PathLike[str]) -> MarkerSet:
    """Read and validate a marker set file (TOML or JSON, UTF-8).

    Every key is checked: an unknown key, a wrong type (``id = 13.7`` or ``id = true``), a
    non-finite, zero or negative side, corners or pose is an error, as are an ID outside its
    dictionary, a duplicate ID, corners inconsistent with the side and an unknown version.

    Raises:
        ConfigError: one line naming the file and what is wrong (and the key).
    """
    path = Path(path)
    data = _read_marker_file(path)
    if not isinstance(data, dict):
        raise _fail(path, "the top level must be a table")
    complaint = _unknown_key(data, _FILE_KEYS, "")
    if complaint:
        raise _fail(path, complaint)
    if data.get("format") != FORMAT:
        raise _fail(path, f"'format' must be '{FORMAT}'")
    version = data.get("version")
    if isinstance(version, bool) or version != VERSION:
        raise _fail(path, f"unsupported version {version!r} (this toolkit reads {VERSION})")
    entries = data.get("markers")
    if not isinstance(entries, list) or not entries:
        raise _fail(path, "no [[markers]] entries")
    try:
        geometry = _geometry(data.get("geometry", {}))
        specs = [_marker_spec(e, f"markers[{k}]") for k, e in enumerate(entries)]
    except (ValueError, DockError) as exc:
        raise _fail(path, str(exc)) from None
    ids = [s.marker_id for s in specs]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise _fail(path, f"marker ID {dup[0]} appears twice")
    if len({s.dictionary for s in specs}) > 1:
        raise _fail(path, "markers use different dictionaries")
    complaint = overlap_complaint(specs)
    if complaint:
        raise _fail(path, complaint)
    return MarkerSet(tuple(specs), geometry, path.resolve())


def marker_set_files(path: str | os.PathLike[str]) -> list[str]:
    """A marker set file and the render meshes it names (absolute paths; a mesh that is not
    there is left out, the renderer says so): what a worker on another machine needs of it."""
    ms = load_marker_set(path)
    meshes = (ms.render_mesh_path(m.marker_id) for m in ms.markers)
    return [str(Path(path).resolve()), *sorted({str(p) for p in meshes if p and p.is_file()})]
