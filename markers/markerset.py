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

from calibration.frames import check_T, make_T, transform_points
from dockcore.config import read_toml
from dockcore.errors import ConfigError, DockError
from dockcore.io import atomic_write_text
from markers.config import MarkerConfig
from markers.dictionary import check_ids, normalise_dictionary_name

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
    """
    dictionary = normalise_dictionary_name(cfg.dictionary)
    ids = check_ids(dictionary, cfg.ids)
    pitch_m = 1.5 * max(cfg.base_side, cfg.enclosure_side) / 1000.0
    unplaced = [i for i in ids if str(i) not in cfg.layout]
    cols = max(1, math.ceil(math.sqrt(len(unplaced))))
    specs = []
    for marker_id in ids:
        if str(marker_id) in cfg.layout:
            x, y, z, yaw = (float(v) for v in cfg.layout[str(marker_id)])
        else:
            k = unplaced.index(marker_id)
            r, c = divmod(k, cols)
            x, y, z, yaw = (
                (r - (len(unplaced) - 1) // cols / 2) * pitch_m,
                (c - (cols - 1) / 2) * pitch_m,
                -0.26,
                0.0,
            )
        specs.append(
            MarkerSpec(
                marker_id,
                dictionary,
                cfg.size_m,
                T_ds_marker_face_up(x, y, z, yaw),
                (mesh_names or {}).get(marker_id),
            )
        )
    geometry = {
        "size_mm": cfg.size_mm,
        "insert_thickness_mm": cfg.insert_thickness_mm,
        "relief_depth_mm": cfg.relief_depth_mm,
        "clearance_mm": cfg.clearance_mm,
        "enclosure_side_mm": cfg.enclosure_side,
        "enclosure_height_mm": cfg.enclosure_height_mm,
        "base_side_mm": cfg.base_side,
        "base_height_mm": cfg.base_height_mm,
    }
    return MarkerSet(tuple(specs), geometry)


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


def load_marker_set(path: str | os.PathLike[str]) -> MarkerSet:
    """Read and validate a marker set file (TOML or JSON).

    Raises:
        ConfigError: one line naming the file and what is wrong (missing key, bad pose, ID outside
            its dictionary, duplicate ID, corners inconsistent with the side, unknown version).
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError(f"marker set file not found: {path}") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise _fail(path, f"malformed JSON ({exc})") from None
    else:
        data = read_toml(path)
    if data.get("format") != FORMAT:
        raise _fail(path, f"'format' must be '{FORMAT}'")
    if data.get("version") != VERSION:
        raise _fail(
            path, f"unsupported version {data.get('version')!r} (this toolkit reads {VERSION})"
        )
    entries = data.get("markers")
    if not isinstance(entries, list) or not entries:
        raise _fail(path, "no [[markers]] entries")
    specs = []
    for k, e in enumerate(entries):
        where = f"markers[{k}]"
        try:
            marker_id = int(e["id"])
            dictionary = normalise_dictionary_name(str(e["dictionary"]))
            side_m = float(e["side_m"])
            T = check_T(np.asarray(e["T_ds_marker"], dtype=np.float64), f"{where}.T_ds_marker")
        except KeyError as exc:
            raise _fail(path, f"{where}: missing key {exc}") from None
        except (TypeError, ValueError, DockError) as exc:
            raise _fail(path, f"{where}: {exc}") from None
        if not (math.isfinite(side_m) and side_m > 0):
            raise _fail(path, f"{where}.side_m must be > 0, got {side_m}")
        try:
            check_ids(dictionary, [marker_id])
        except DockError as exc:
            raise _fail(path, f"{where}: {exc}") from None
        if "corners_marker_m" in e:
            corners = np.asarray(e["corners_marker_m"], dtype=np.float64)
            if corners.shape != (4, 3) or not np.allclose(
                corners, corners_marker_m(side_m), atol=1e-9
            ):
                raise _fail(path, f"{where}.corners_marker_m disagree with side_m={side_m}")
        specs.append(MarkerSpec(marker_id, dictionary, side_m, T, e.get("render_mesh")))
    ids = [s.marker_id for s in specs]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise _fail(path, f"marker ID {dup[0]} appears twice")
    if len({s.dictionary for s in specs}) > 1:
        raise _fail(path, "markers use different dictionaries")
    return MarkerSet(tuple(specs), dict(data.get("geometry", {})), path.resolve())
