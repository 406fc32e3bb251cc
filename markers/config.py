"""Configuration of the marker component: which markers, their 3D geometry and their DS layout."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.markers.dictionary import bits_per_side, check_ids, normalise_dictionary_name

#: Largest ID of any OpenCV predefined dictionary (``DICT_APRILTAG_36h10`` holds 2320 markers);
#: the dictionary a set uses narrows it further (:func:`markers.dictionary.check_ids`).
MAX_MARKER_ID = 2319

#: A marker ID (any dictionary).
MarkerId = Annotated[int, Interval(ge=0, le=MAX_MARKER_ID)]
#: The side of a marker (m) in a marker set file or for single-marker poses: up to 1 m, as
#: ``MarkerConfig.size_mm``.
MarkerSideM = Annotated[float, Interval(gt=0.0, le=1.0)]
#: Largest distance of a marker from the DS origin along each axis (m).
MAX_DS_COORD_M = 100.0
#: A coordinate of a marker on the docking station (m): a DS is a few metres across.
DsCoordM = Annotated[float, Interval(ge=-MAX_DS_COORD_M, le=MAX_DS_COORD_M)]
#: An in-plane rotation (deg).
YawDeg = Annotated[float, Interval(ge=-360.0, le=360.0)]
#: A side of a printed part (mm): up to 2 m (a 3D printer's bed is far smaller).
PartSideMm = Annotated[float, Interval(gt=0.0, le=2000.0)]
#: A height or thickness of a printed part (mm): at least one 0.2 mm layer, at most 1 m.
PartHeightMm = Annotated[float, Interval(ge=0.2, le=1000.0)]

#: Construction styles of the printed marker (:func:`markers.geometry.build_solids`).
MARKER_STYLES = ("solid", "published")

#: The docking-station marker set of the reference system (docs/reference-system.md, section 4).
DS_MARKER_IDS: tuple[int, ...] = (13, 14, 15, 28, 34)

#: Marker centres on the reference DS, in the DS frame (x forward, y starboard, z down; metres)
#: and the marker's in-plane yaw (degrees, about the DS z axis). The reference gives positions only;
#: we take every marker's x axis along the DS x axis. Source: docs/reference-system.md section 4.
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
    the photometric negative of the flat tag. Defaults: docs/reference-system.md section 5.

    Attributes:
        dictionary: OpenCV dictionary name (``DICT_4X4_50``; any ``cv2.aruco.DICT_*``).
        ids: marker IDs to generate (default: the docking-station set 13, 14, 15, 28, 34), each
            in the dictionary, none twice.
        size_mm: side of the tag = side of the white insert (mm, 5 ... 1000); the detector's
            marker side. The flat sheet must fit the paper (about 200 mm on A4).
        insert_thickness_mm: thickness of the white insert (mm, 0.2 ... 100).
        relief_depth_mm: depth of the openings seen from above, insert top to the black surface
            below (mm, 0.2 ... insert thickness). Equal to the insert thickness (default) the
            openings show the pocket floor; smaller, black bosses rise inside the openings to
            that depth.
        clearance_mm: gap between insert and enclosure in the seat and around bosses (mm, 0.01
            ... a quarter of a tag cell); openings are also widened by half of it so that
            diagonal cells never share an edge.
        enclosure_side_mm: side of the black column (mm, up to 2000, leaving a wall of >= 1 mm
            around the insert); ``None``: 1.26 x ``size_mm`` (126 mm).
        enclosure_height_mm: height of the column above the base (mm, 0.2 ... 1000, more than
            the insert thickness).
        base_side_mm: side of the base plate (mm, enclosure side ... 2000); ``None``: 1.62 x
            ``size_mm`` (162 mm).
        base_height_mm: thickness of the base plate (mm, 0.2 ... 1000).
        paper: paper size of the flat printable sheet: ``A4``, ``A3`` or ``letter``.
        style: ``solid`` (a solid column with a pocket for a thick insert; the fields above) or
            ``published`` (the construction of the published, tank-proven marker: a thin
            plate insert with locating tabs on a hollow shell, so the openings look into a dark
            cavity; the fields below; ``insert_thickness_mm``, ``relief_depth_mm``, the base
            plate fields do not apply). See :mod:`markers.geometry`.
        plate_thickness_mm: ``published``: thickness of the insert plate (mm, 0.4 ... 20).
        shell_wall_mm: ``published``: the shell's wall thickness (mm, 0.8 ... 50).
        shell_floor_mm: ``published``: the shell's floor thickness (mm, 0.4 ... 50); a closed
            floor keeps the cavity dark.
        lip_mm: ``published``: width of the ledge the plate rests on, under the tag's border
            cells (mm, 1 ... less than a cell).
        lip_thickness_mm: ``published``: thickness of that ledge (mm, 0.4 ... 50).
        post_side_mm: ``published``: side of the four corner posts inside the shell (mm, 0
            for none); each takes a blind screw hole from below.
        post_hole_mm: ``published``: diameter of the posts' screw holes (mm, 0 for none; less
            than the post side minus 2 mm).
        layout: marker pose on the DS by ID (a string key): ``[x_m, y_m, z_m, yaw_deg]`` of the
            marker's face centre in the DS frame (m, each within +-100), face up, yaw in
            [-360, 360] deg. IDs not listed are placed on a grid on the DS floor.
    """

    dictionary: str = "DICT_4X4_50"
    ids: tuple[MarkerId, ...] = DS_MARKER_IDS
    size_mm: Annotated[float, Interval(ge=5.0, le=1000.0)] = 100.0
    insert_thickness_mm: Annotated[float, Interval(ge=0.2, le=100.0)] = 5.0
    relief_depth_mm: Annotated[float, Interval(ge=0.2, le=100.0)] = 5.0
    clearance_mm: Annotated[float, Interval(ge=0.01, le=10.0)] = 0.1
    enclosure_side_mm: PartSideMm | None = None
    enclosure_height_mm: PartHeightMm = 98.0
    base_side_mm: PartSideMm | None = None
    base_height_mm: PartHeightMm = 10.0
    paper: str = "A4"
    style: str = "solid"
    plate_thickness_mm: Annotated[float, Interval(ge=0.4, le=20.0)] = 1.0
    shell_wall_mm: Annotated[float, Interval(ge=0.8, le=50.0)] = 2.4
    shell_floor_mm: Annotated[float, Interval(ge=0.4, le=50.0)] = 1.2
    lip_mm: Annotated[float, Interval(ge=1.0, le=100.0)] = 4.0
    lip_thickness_mm: Annotated[float, Interval(ge=0.4, le=50.0)] = 2.0
    post_side_mm: Annotated[float, Interval(ge=0.0, le=200.0)] = 10.0
    post_hole_mm: Annotated[float, Interval(ge=0.0, le=100.0)] = 3.4
    layout: dict[str, tuple[DsCoordM, DsCoordM, DsCoordM, YawDeg]] = field(
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

    def shell_mm(self) -> tuple[float, float, float]:
        """``published`` style: the shell's inner side, the window under the plate (inside the
        ledge) and the height of the 45 deg chamfer between them (mm)."""
        inner = self.enclosure_side - 2 * self.shell_wall_mm
        window = self.size_mm + 2 * self.clearance_mm - 2 * self.lip_mm
        return inner, window, (inner - window) / 2

    def _validate_published(self, cell_mm: float) -> None:
        """The published style's fields against each other (mm)."""
        if not self.lip_mm < cell_mm - self.clearance_mm:
            raise ValueError(
                f"lip_mm: the ledge must stay under the tag's border cells ({cell_mm:.2f} mm), "
                f"got {self.lip_mm:g}"
            )
        inner, window, chamfer = self.shell_mm()
        if not inner > window + 2.0:
            raise ValueError(
                f"shell_wall_mm: {self.shell_wall_mm:g} mm walls leave no cavity wider than the "
                f"tag inside a {self.enclosure_side:g} mm shell"
            )
        if not self.post_hole_mm <= max(self.post_side_mm - 2.0, 0.0):
            raise ValueError(
                f"post_hole_mm: {self.post_hole_mm:g} mm needs posts of at least "
                f"{self.post_hole_mm + 2:g} mm (post_side_mm is {self.post_side_mm:g})"
            )
        top = self.plate_thickness_mm + self.lip_thickness_mm + chamfer
        if not self.enclosure_height_mm >= top + self.shell_floor_mm + 2.0:
            raise ValueError(
                f"enclosure_height_mm: a shell of {self.enclosure_height_mm:g} mm cannot hold the "
                f"plate, the ledge and its 45 deg chamfer ({top:.1f} mm) above a cavity"
            )

    @property
    def size_m(self) -> float:
        """Marker side in metres."""
        return self.size_mm / 1000.0

    def validate(self) -> None:
        """Raise ValueError (naming the field) on an impossible geometry or marker set.

        Each field's own range is its declared domain (checked by the loader and
        :func:`dockcore.config.validated`); this checks the fields against each other.
        """
        try:
            name = normalise_dictionary_name(self.dictionary)
        except DockError as exc:
            raise ValueError(f"dictionary: {exc}") from None
        try:
            check_ids(name, self.ids)
        except DockError as exc:
            raise ValueError(f"ids: {exc}") from None
        if not self.relief_depth_mm <= self.insert_thickness_mm:
            raise ValueError(
                f"relief_depth_mm: must be <= insert_thickness_mm ({self.insert_thickness_mm:g}), "
                f"got {self.relief_depth_mm:g}"
            )
        cell_mm = self.size_mm / (bits_per_side(name) + 2)
        if not self.clearance_mm <= cell_mm / 4:
            raise ValueError(
                f"clearance_mm: {self.clearance_mm:g} mm would close the openings of "
                f"{cell_mm:.2f} mm cells (at most a quarter of a cell: {cell_mm / 4:.2f} mm)"
            )
        wall = (self.enclosure_side - self.size_mm) / 2 - self.clearance_mm
        if not wall >= 1.0:  # NaN-proof
            raise ValueError(
                f"enclosure_side_mm: {self.enclosure_side:g} leaves a {wall:.2f} mm wall around a "
                f"{self.size_mm:g} mm insert (need >= 1 mm)"
            )
        if not self.base_side >= self.enclosure_side:
            raise ValueError(
                f"base_side_mm: must be >= the enclosure side {self.enclosure_side:g}, "
                f"got {self.base_side:g}"
            )
        if not self.insert_thickness_mm < self.enclosure_height_mm:
            raise ValueError("enclosure_height_mm: must exceed insert_thickness_mm")
        if self.style not in MARKER_STYLES:
            raise ValueError(
                f"style: must be one of {', '.join(MARKER_STYLES)}, got {self.style!r}"
            )
        if self.style == "published":
            self._validate_published(cell_mm)
        if self.paper not in ("A4", "A3", "letter"):
            raise ValueError(f"paper: must be A4, A3 or letter, got {self.paper!r}")
        for key in self.layout:  # (each pose's length and domains are its declared type)
            if not (key.isascii() and key.isdigit() and str(int(key)) == key):
                raise ValueError(f"layout: keys are marker IDs such as '13', got {key!r}")
        # a layout of one's own places only markers that are generated (the default one, for
        # the DS set, may stand beside other ids: its entries then place nothing)
        stray = sorted((k for k in self.layout if int(k) not in self.ids), key=int)
        if stray and self.layout != REFERENCE_DS_LAYOUT:
            raise ValueError(
                f"layout: entries for marker ID(s) {', '.join(stray)} that are not generated "
                f"(ids = {list(self.ids)}): add them to ids or remove them from the layout"
            )
