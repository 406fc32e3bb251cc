"""True-scale printable sheets (PDF, SVG) of flat ArUco markers for quick tests in air or a tank.

Each page is a matplotlib figure whose size in inches is the paper size, with one axes spanning
the whole figure whose data coordinates are millimetres from the top-left corner of the paper
(x right, y down). Saved without bbox tightening, 1 data mm is 1 physical mm on the printed page
when it is printed at 100 % ("actual size").

Per marker the sheet draws:
- the black square of side ``marker_size_mm`` (the ArUco cells including the 1-cell black border),
  as one filled path of merged black runs (small files, no hairline seams between cells);
- a white quiet zone one cell wide around it (paper left blank);
- thin corner cut marks just outside the quiet zone;
- a label under it (ID, dictionary, size).

Per page: the title, the line "print at 100 % / actual size, do not fit to page", a 100 mm scale
bar with 10 mm ticks, and the page number.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_bytes

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from matplotlib.patches import PathPatch

# matplotlib (a few tenths of a second to import) is imported by the functions that draw, so
# importing this module (and the ``markers`` command line) does not pay for it.

MM_PER_INCH = 25.4
MM_PER_PT = MM_PER_INCH / 72.0

#: Paper sizes, portrait, (width_mm, height_mm).
PAPER_SIZES_MM: dict[str, tuple[float, float]] = {
    "A4": (210.0, 297.0),
    "A3": (297.0, 420.0),
    "letter": (215.9, 279.4),
}

MARGIN_MM = 10.0  # blank border of the page
HEADER_MM = 14.0  # title + print-at-100-% line
FOOTER_MM = 12.0  # scale bar
GUTTER_MM = 2.0  # between marker slots
CUT_GAP_MM = 1.0  # gap between a cut-square corner and its tick
CUT_LEN_MM = 4.0  # length of a cut tick
LABEL_PT = 7.0  # label font size
LABEL_GAP_MM = 0.5  # between the cut-mark band and the label
SCALE_BAR_MM = 100.0
SCALE_TICK_MM = 10.0

FONT_FAMILY = "DejaVu Sans"  # ships with matplotlib: no dependence on system fonts
RC_PARAMS = {
    "font.family": FONT_FAMILY,
    "svg.fonttype": "path",  # glyphs as paths: the SVG needs no font installed
    "svg.hashsalt": "uwdock-marker-sheet",  # deterministic ids in the SVG
    "pdf.fonttype": 42,  # embedded TrueType: text stays searchable in the PDF
}


@dataclass(frozen=True)
class SheetEntry:
    """One marker to print.

    Attributes:
        marker_id: the marker's ID in its dictionary.
        cells: (n, n) bool array, True = black cell, including the 1-cell black border
            (n = bits + 2), row 0 at the top; the flat (positive) ArUco tag.
        label: text printed under the marker, e.g. ``"DICT_4X4_50 id 13  100 mm"``.
    """

    marker_id: int
    cells: np.ndarray
    label: str


@dataclass(frozen=True)
class _Layout:
    """Geometry of one page grid, all in mm (x right, y down from the paper's top-left)."""

    paper_w_mm: float
    paper_h_mm: float
    cell_mm: float  # side of one cell (quiet zone width)
    cut_mm: float  # side of the cut square = marker + 2 quiet zones
    slot_w_mm: float
    slot_h_mm: float
    cols: int
    rows: int
    x0_mm: float  # left edge of the grid
    y0_mm: float  # top edge of the grid

    @property
    def per_page(self) -> int:
        return self.cols * self.rows

    def slot_origin(self, k: int) -> tuple[float, float]:
        """Top-left corner (mm) of slot ``k`` (row-major) on a page."""
        row, col = divmod(k, self.cols)
        return (
            self.x0_mm + col * (self.slot_w_mm + GUTTER_MM),
            self.y0_mm + row * (self.slot_h_mm + GUTTER_MM),
        )


def write_sheet(*args: Any, **kwargs: Any) -> list[Path]:
    """Write a true-scale printable sheet of flat markers as PDF and/or SVG.

    All pages are rendered in memory first (:func:`render_sheet`, same arguments and errors),
    then each file is written atomically, so an error while rendering leaves no file behind.

    Returns:
        Every path written: the PDF first, then the SVG pages in order.
    """
    return [atomic_write_bytes(path, data) for path, data in render_sheet(*args, **kwargs)]


def render_sheet(
    entries: Sequence[SheetEntry],
    marker_size_mm: float,
    pdf_path: Path | None,
    svg_path: Path | None,
    *,
    paper: str = "A4",
    title: str = "",
) -> list[tuple[Path, bytes]]:
    """Render a true-scale printable sheet of flat markers as PDF and/or SVG, in memory.

    Args:
        entries: markers to draw, in order (row-major over the pages).
        marker_size_mm: side of each black square including its border (mm), exact on paper.
        pdf_path: multi-page PDF to write, or None.
        svg_path: SVG of the first page, or None; page k >= 2 goes to ``<stem>_p<k>.svg``.
        paper: "A4", "A3" or "letter" (case-insensitive), portrait.
        title: printed at the top of every page.

    Returns:
        ``(path, file contents)`` of every file: the PDF first, then the SVG pages in order.

    Raises:
        DockError: unknown paper, no entries, or one marker (with quiet zone, cut marks and
            label) does not fit on the paper.
        ValueError: an entry's cells are not a square bool-like (n, n) array with n >= 3.
    """
    if not entries:
        raise DockError("no markers to put on the sheet")
    paper_w_mm, paper_h_mm, paper_name = _paper_size(paper)
    if not (math.isfinite(marker_size_mm) and marker_size_mm > 0):
        raise DockError(f"marker size must be a positive number of mm, got {marker_size_mm}")
    cells = [_check_cells(e) for e in entries]
    n_cells = {c.shape[0] for c in cells}
    if len(n_cells) != 1:
        raise ValueError(f"all markers on a sheet must have the same cell count, got {n_cells}")
    layout = _layout(
        paper_w_mm,
        paper_h_mm,
        paper_name,
        marker_size_mm,
        n_cells.pop(),
        [e.label for e in entries],
    )
    pages = [
        list(range(i, min(i + layout.per_page, len(entries))))
        for i in range(0, len(entries), layout.per_page)
    ]
    title = title or "uwdock marker sheet"

    import matplotlib

    with matplotlib.rc_context(RC_PARAMS):
        figures = [
            _draw_page(
                layout,
                [entries[i] for i in idx],
                [cells[i] for i in idx],
                marker_size_mm,
                title,
                page_no,
                len(pages),
            )
            for page_no, idx in enumerate(pages, start=1)
        ]
        outputs: list[tuple[Path, bytes]] = []
        if pdf_path is not None:
            outputs.append((Path(pdf_path), _render_pdf(figures, title)))
        if svg_path is not None:
            outputs += [
                (svg_page_path(Path(svg_path), k), _render_svg(fig, paper_w_mm, paper_h_mm))
                for k, fig in enumerate(figures, start=1)
            ]
    return outputs


def svg_page_path(svg_path: Path, page_no: int) -> Path:
    """Path of SVG page ``page_no`` (1-based): ``svg_path`` itself, then ``<stem>_p<k><suffix>``."""
    if page_no == 1:
        return svg_path
    return svg_path.with_name(f"{svg_path.stem}_p{page_no}{svg_path.suffix}")


def _paper_size(paper: str) -> tuple[float, float, str]:
    """(width_mm, height_mm, canonical name) of a paper name, case-insensitive."""
    for name, (w_mm, h_mm) in PAPER_SIZES_MM.items():
        if name.lower() == paper.strip().lower():
            return w_mm, h_mm, name
    raise DockError(f"unknown paper {paper!r}; choose one of {', '.join(PAPER_SIZES_MM)}")


def _check_cells(entry: SheetEntry) -> np.ndarray:
    """The entry's cells as a (n, n) bool array; ValueError if malformed."""
    cells = np.asarray(entry.cells)
    if cells.ndim != 2 or cells.shape[0] != cells.shape[1] or cells.shape[0] < 3:
        raise ValueError(
            f"marker {entry.marker_id}: cells must be a square (n, n) array with n >= 3, "
            f"got shape {cells.shape}"
        )
    return cells.astype(bool)


def _label_width_mm(label: str) -> float:
    """Width of ``label`` at the label font size (mm), measured on the font's glyph outlines."""
    if not label:
        return 0.0
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextPath

    path = TextPath((0.0, 0.0), label, size=LABEL_PT, prop=FontProperties(family=FONT_FAMILY))
    return float(path.get_extents().width) * MM_PER_PT


def _layout(
    paper_w_mm: float,
    paper_h_mm: float,
    paper_name: str,
    marker_size_mm: float,
    n_cells: int,
    labels: Sequence[str],
) -> _Layout:
    """Grid of equal slots (cut square + cut-mark band + label) centred in the printable area."""
    cell_mm = marker_size_mm / n_cells
    cut_mm = marker_size_mm + 2.0 * cell_mm
    band_mm = CUT_GAP_MM + CUT_LEN_MM
    label_h_mm = LABEL_PT * MM_PER_PT * 1.3 + LABEL_GAP_MM
    label_w_mm = max(_label_width_mm(t) for t in labels)
    slot_w_mm = max(cut_mm + 2.0 * band_mm, label_w_mm)
    slot_h_mm = cut_mm + 2.0 * band_mm + label_h_mm

    area_w_mm = paper_w_mm - 2.0 * MARGIN_MM
    area_h_mm = paper_h_mm - 2.0 * MARGIN_MM - HEADER_MM - FOOTER_MM
    if slot_w_mm > area_w_mm or slot_h_mm > area_h_mm:
        raise DockError(
            f"a {marker_size_mm:g} mm marker with its quiet zone, cut marks and label needs "
            f"{slot_w_mm:.0f} x {slot_h_mm:.0f} mm but {paper_name} leaves "
            f"{area_w_mm:.0f} x {area_h_mm:.0f} mm; use a bigger --paper or a smaller marker size"
        )
    cols = int((area_w_mm + GUTTER_MM) // (slot_w_mm + GUTTER_MM))
    rows = int((area_h_mm + GUTTER_MM) // (slot_h_mm + GUTTER_MM))
    grid_w_mm = cols * slot_w_mm + (cols - 1) * GUTTER_MM
    grid_h_mm = rows * slot_h_mm + (rows - 1) * GUTTER_MM
    return _Layout(
        paper_w_mm=paper_w_mm,
        paper_h_mm=paper_h_mm,
        cell_mm=cell_mm,
        cut_mm=cut_mm,
        slot_w_mm=slot_w_mm,
        slot_h_mm=slot_h_mm,
        cols=cols,
        rows=rows,
        x0_mm=MARGIN_MM + 0.5 * (area_w_mm - grid_w_mm),
        y0_mm=MARGIN_MM + HEADER_MM + 0.5 * (area_h_mm - grid_h_mm),
    )


def black_rectangles(cells: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Cover the black cells with few rectangles: runs per row, merged down identical runs.

    Args:
        cells: (n, m) bool, True = black, row 0 at the top.

    Returns:
        Rectangles (row, col, n_rows, n_cols) in cells, disjoint, covering exactly the black cells.
    """
    done: list[tuple[int, int, int, int]] = []
    open_runs: dict[tuple[int, int], int] = {}  # (col, n_cols) -> first row
    for r, row in enumerate(np.asarray(cells, dtype=bool)):
        padded = np.concatenate(([False], row, [False])).astype(np.int8)
        edges = np.flatnonzero(np.diff(padded))
        runs = {(int(a), int(b - a)) for a, b in zip(edges[::2], edges[1::2], strict=True)}
        for run in [k for k in open_runs if k not in runs]:
            r0 = open_runs.pop(run)
            done.append((r0, run[0], r - r0, run[1]))
        for run in runs:
            open_runs.setdefault(run, r)
    n_rows = np.asarray(cells).shape[0]
    done += [(r0, c, n_rows - r0, w) for (c, w), r0 in open_runs.items()]
    return sorted(done)


def _marker_patch(cells: np.ndarray, x_mm: float, y_mm: float, side_mm: float) -> PathPatch:
    """One filled path of the black cells, top-left of the marker at (x_mm, y_mm)."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    cell_mm = side_mm / cells.shape[0]
    verts: list[tuple[float, float]] = []
    codes: list[int] = []
    for r, c, h, w in black_rectangles(cells):
        xa, ya = x_mm + c * cell_mm, y_mm + r * cell_mm
        xb, yb = x_mm + (c + w) * cell_mm, y_mm + (r + h) * cell_mm
        # same winding for every rectangle, so the nonzero fill is their union without seams
        verts += [(xa, ya), (xb, ya), (xb, yb), (xa, yb), (xa, ya)]
        codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
    return PathPatch(MplPath(verts, codes), facecolor="black", edgecolor="none", linewidth=0.0)


def _cut_marks(x_mm: float, y_mm: float, side_mm: float) -> list[list[tuple[float, float]]]:
    """Two outward ticks at each corner of the cut square with top-left (x_mm, y_mm)."""
    segs = []
    a, b = CUT_GAP_MM, CUT_GAP_MM + CUT_LEN_MM
    for cx, sx in ((x_mm, -1.0), (x_mm + side_mm, 1.0)):
        for cy, sy in ((y_mm, -1.0), (y_mm + side_mm, 1.0)):
            segs.append([(cx + sx * a, cy), (cx + sx * b, cy)])  # along the horizontal edge
            segs.append([(cx, cy + sy * a), (cx, cy + sy * b)])  # along the vertical edge
    return segs


def _scale_bar(ax, x_mm: float, y_mm: float) -> None:
    """A SCALE_BAR_MM bar with ticks every SCALE_TICK_MM, its left end at (x_mm, y_mm)."""
    from matplotlib.collections import LineCollection

    segs = [[(x_mm, y_mm), (x_mm + SCALE_BAR_MM, y_mm)]]
    n_ticks = round(SCALE_BAR_MM / SCALE_TICK_MM)
    for i in range(n_ticks + 1):
        x = x_mm + i * SCALE_TICK_MM
        tall = i in (0, n_ticks) or 2 * i == n_ticks
        segs.append([(x, y_mm), (x, y_mm - (3.0 if tall else 2.0))])
        if tall:
            ax.text(x, y_mm + 1.0, f"{i * SCALE_TICK_MM:g}", ha="center", va="top", fontsize=6)
    ax.add_collection(LineCollection(segs, colors="black", linewidths=0.6))
    ax.text(
        x_mm + SCALE_BAR_MM + 4.0,
        y_mm,
        f"scale check: this bar is {SCALE_BAR_MM:g} mm",
        ha="left",
        va="center",
        fontsize=7,
    )


def _draw_page(
    layout: _Layout,
    entries: Sequence[SheetEntry],
    cells: Sequence[np.ndarray],
    marker_size_mm: float,
    title: str,
    page_no: int,
    n_pages: int,
) -> Figure:
    """One page as a figure whose data coordinates are paper mm (y down)."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    w_mm, h_mm = layout.paper_w_mm, layout.paper_h_mm
    fig = Figure(figsize=(w_mm / MM_PER_INCH, h_mm / MM_PER_INCH), dpi=72, facecolor="white")
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, w_mm)
    ax.set_ylim(h_mm, 0.0)
    ax.set_axis_off()

    ax.text(MARGIN_MM, MARGIN_MM, title, ha="left", va="top", fontsize=11, fontweight="bold")
    ax.text(
        MARGIN_MM,
        MARGIN_MM + 6.0,
        f"print at 100 % / actual size, do not fit to page. Marker side {marker_size_mm:g} mm "
        "(black square incl. border); cut along the corner marks.",
        ha="left",
        va="top",
        fontsize=7.5,
    )
    ax.text(
        w_mm - MARGIN_MM, MARGIN_MM, f"page {page_no}/{n_pages}", ha="right", va="top", fontsize=8
    )

    q_mm = layout.cell_mm
    cut_segs: list[list[tuple[float, float]]] = []
    band_mm = CUT_GAP_MM + CUT_LEN_MM
    for k, (entry, cell) in enumerate(zip(entries, cells, strict=True)):
        sx, sy = layout.slot_origin(k)
        cut_x = sx + 0.5 * (layout.slot_w_mm - layout.cut_mm)
        cut_y = sy + band_mm
        ax.add_patch(_marker_patch(cell, cut_x + q_mm, cut_y + q_mm, marker_size_mm))
        cut_segs += _cut_marks(cut_x, cut_y, layout.cut_mm)
        ax.text(
            cut_x + 0.5 * layout.cut_mm,
            cut_y + layout.cut_mm + band_mm + LABEL_GAP_MM,
            entry.label,
            ha="center",
            va="top",
            fontsize=LABEL_PT,
        )
    ax.add_collection(LineCollection(cut_segs, colors="black", linewidths=0.4))
    _scale_bar(ax, MARGIN_MM, h_mm - MARGIN_MM - 5.0)
    return fig


def _render_pdf(figures: Sequence[Figure], title: str) -> bytes:
    """All figures as one multi-page PDF (no bbox tightening: the page is the paper)."""
    from matplotlib.backends.backend_pdf import PdfPages

    buf = io.BytesIO()
    metadata = {"Title": title, "Creator": "uwdock markers generate", "CreationDate": None}
    with PdfPages(buf, metadata=metadata) as pdf:
        for fig in figures:
            pdf.savefig(fig)
    return buf.getvalue()


_SVG_ROOT = re.compile(rb"<svg\b[^>]*>")
_SVG_SIZE = re.compile(rb'\s(width|height)="[^"]*"')


def _render_svg(fig: Figure, paper_w_mm: float, paper_h_mm: float) -> bytes:
    """One figure as a self-contained SVG whose width/height are declared in mm.

    matplotlib writes the size in pt with a viewBox in pt; the viewBox is kept (1 unit = 1 pt
    = 25.4/72 mm) and the declared size is rewritten in mm so viewers and cutters read it exactly.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="svg", metadata={"Date": None})
    data = buf.getvalue()
    root = _SVG_ROOT.search(data)
    if root is None:  # pragma: no cover - matplotlib always writes a root element
        raise RuntimeError("matplotlib wrote an SVG without a root element")
    sizes = {b"width": f"{paper_w_mm:g}mm".encode(), b"height": f"{paper_h_mm:g}mm".encode()}
    new_root = _SVG_SIZE.sub(lambda m: b' %s="%s"' % (m[1], sizes[m[1]]), root[0])
    return data[: root.start()] + new_root + data[root.end() :]
