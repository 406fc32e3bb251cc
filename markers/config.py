"""Configuration of the marker component: which markers, their 3D geometry and their DS layout."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: The docking-station marker set of the reference system (reference.md, section 4).
DS_MARKER_IDS: tuple[int, ...] = (13, 14, 15, 28, 34)

#: Marker centres on the reference DS, in the DS frame (x forward, y starboard, z down; metres)
#: and the marker's in-plane yaw (degrees, about the DS z axis). The reference gives positions only;
#: we take every marker's x axis along the DS x axis. Source: reference.md section 4.
REFERENCE_DS_LAYOUT: dict[str, tuple[float, float, float, float]] = {
    "13": (0.87, -1.05, -1.756, 0.0),
    "34": (0.87, 1.05, -1.756, 0.0),
    "14": (0.0, -0.30, -0.26, 0.0),
    "15": (0.25, 0.50, -0.26, 0.0),
    "28": (-0.25, 0.50, -0.26, 0.0),
}


@dataclass(frozen=True)
class MarkerConfig:
    """3D Binary Marker set: dictionary, IDs, printable geometry and pose on the docking station.

    The 3DBM is a white insert with through-openings where the ArUco tag is white, seated in a
    pocket on top of a black enclosure (a square column on a wider base). Seen from above it is
    the photometric negative of the flat tag. Defaults: reference.md section 5.

    Attributes:
        dictionary: OpenCV dictionary name (``DICT_4X4_50``; any ``cv2.aruco.DICT_*``).
        ids: marker IDs to generate (default: the docking-station set 13, 14, 15, 28, 34).
        size_mm: side of the tag = side of the white insert (mm); the detector's marker side.
        insert_thickness_mm: thickness of the white insert (mm).
        relief_depth_mm: depth of the openings seen from above, insert top to the black surface
            below (mm). Equal to the insert thickness (default) the openings show the pocket
            floor; smaller, black bosses rise inside the openings to that depth.
        clearance_mm: gap between insert and enclosure in the seat and around bosses (mm);
            openings are also widened by half of it so that diagonal cells never share an edge.
        enclosure_side_mm: side of the black column (mm); ``None``: 1.26 x ``size_mm`` (126 mm).
        enclosure_height_mm: height of the column above the base (mm).
        base_side_mm: side of the base plate (mm); ``None``: 1.62 x ``size_mm`` (162 mm).
        base_height_mm: thickness of the base plate (mm).
        paper: paper size of the flat printable sheet: ``A4``, ``A3`` or ``letter``.
        layout: marker pose on the DS by ID (a string key): ``[x_m, y_m, z_m, yaw_deg]`` of the
            marker's face centre in the DS frame, face up. IDs not listed are placed on a grid on
            the DS floor.
    """

    dictionary: str = "DICT_4X4_50"
    ids: tuple[int, ...] = DS_MARKER_IDS
    size_mm: float = 100.0
    insert_thickness_mm: float = 5.0
    relief_depth_mm: float = 5.0
    clearance_mm: float = 0.1
    enclosure_side_mm: float | None = None
    enclosure_height_mm: float = 98.0
    base_side_mm: float | None = None
    base_height_mm: float = 10.0
    paper: str = "A4"
    layout: dict[str, tuple[float, float, float, float]] = field(
        default_factory=lambda: dict(REFERENCE_DS_LAYOUT)
    )

    @property
    def enclosure_side(self) -> float:
        """Resolved column side (mm)."""
        return self.enclosure_side_mm if self.enclosure_side_mm is not None else 1.26 * self.size_mm

    @property
    def base_side(self) -> float:
        """Resolved base plate side (mm)."""
        return self.base_side_mm if self.base_side_mm is not None else 1.62 * self.size_mm

    @property
    def size_m(self) -> float:
        """Marker side in metres."""
        return self.size_mm / 1000.0

    def validate(self) -> None:
        """Raise ValueError (naming the field) on an impossible geometry."""
        for name in (
            "size_mm",
            "insert_thickness_mm",
            "relief_depth_mm",
            "clearance_mm",
            "enclosure_height_mm",
            "base_height_mm",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be > 0, got {v}")
        if self.relief_depth_mm > self.insert_thickness_mm:
            raise ValueError(
                f"relief_depth_mm: must be <= insert_thickness_mm ({self.insert_thickness_mm}), "
                f"got {self.relief_depth_mm}"
            )
        wall = (self.enclosure_side - self.size_mm) / 2 - self.clearance_mm
        if wall < 1.0:
            raise ValueError(
                f"enclosure_side_mm: {self.enclosure_side:g} leaves a {wall:.2f} mm wall around a "
                f"{self.size_mm:g} mm insert (need >= 1 mm)"
            )
        if self.base_side < self.enclosure_side:
            raise ValueError(f"base_side_mm: must be >= enclosure side {self.enclosure_side:g}")
        if self.insert_thickness_mm >= self.enclosure_height_mm:
            raise ValueError("enclosure_height_mm: must exceed insert_thickness_mm")
        if self.paper not in ("A4", "A3", "letter"):
            raise ValueError(f"paper: must be A4, A3 or letter, got {self.paper!r}")
        for key, pose in self.layout.items():
            if not key.isdigit():
                raise ValueError(f"layout: keys are marker IDs, got {key!r}")
            if len(pose) != 4 or not all(math.isfinite(float(v)) for v in pose):
                raise ValueError(f"layout.{key}: expected [x_m, y_m, z_m, yaw_deg]")
