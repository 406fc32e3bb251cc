"""markers.sheet: true-scale printable PDF/SVG sheets of flat ArUco markers.

Ground truth: real DICT_4X4_50 bitmaps are drawn, the PDF is rasterised with pypdfium2 at a known
DPI and the markers are detected with OpenCV's ArUco detector; the measured side (px -> mm through
the DPI) must equal the requested side. The SVG is checked by parsing its XML (declared size in mm,
viewBox scale, marker paths' extents).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import matplotlib.figure
import numpy as np
import pytest

from uwdock.dockcore.errors import DockError
from uwdock.markers.sheet import PAPER_SIZES_MM, SheetEntry, black_rectangles, write_sheet

pdfium = pytest.importorskip("pypdfium2")

DPI = 200.0
MM_PER_PT = 25.4 / 72.0
SIDE_TOL = 0.005  # relative: 0.5 %
IDS = [13, 14, 15, 28, 30, 34]
SVG_NS = "{http://www.w3.org/2000/svg}"
DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)


def aruco_entry(marker_id: int, size_mm: float) -> SheetEntry:
    """A sheet entry from OpenCV's own 6x6-cell bitmap (4x4 bits + border), True = black."""
    cells = cv2.aruco.generateImageMarker(DICT, marker_id, 6) == 0
    return SheetEntry(marker_id, cells, f"DICT_4X4_50 id {marker_id}  {size_mm:g} mm")


def render_pdf(path: Path, dpi: float) -> list[np.ndarray]:
    """Every page of a PDF as a grey uint8 image at ``dpi``."""
    doc = pdfium.PdfDocument(str(path))
    try:
        pages = []
        for page in doc:
            rgb = page.render(scale=dpi / 72.0).to_numpy()
            pages.append(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
        return pages
    finally:
        doc.close()


def detect(gray: np.ndarray) -> dict[int, np.ndarray]:
    """ArUco detections {id: (4, 2) corners in px}, sub-pixel refined."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(DICT, params).detectMarkers(gray)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}


def side_mm(corners_px: np.ndarray, dpi: float) -> float:
    """Mean of the 4 edge lengths of a detected marker, in mm on paper."""
    edges = np.linalg.norm(corners_px - np.roll(corners_px, -1, axis=0), axis=1)
    return float(edges.mean()) * 25.4 / dpi


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    """Six 50 mm markers on one A4 page, PDF + SVG, and the PDF rendered at DPI."""
    out = tmp_path_factory.mktemp("sheet")
    written = write_sheet(
        [aruco_entry(i, 50.0) for i in IDS],
        50.0,
        out / "sheet.pdf",
        out / "sheet.svg",
        paper="A4",
        title="Tank test sheet",
    )
    return {"dir": out, "written": written, "pages": render_pdf(out / "sheet.pdf", DPI)}


def test_writes_pdf_and_svg_on_one_page(sheet):
    d = sheet["dir"]
    assert sheet["written"] == [d / "sheet.pdf", d / "sheet.svg"]
    assert len(sheet["pages"]) == 1
    assert sorted(p.name for p in d.iterdir()) == ["sheet.pdf", "sheet.svg"]  # no temp files


def test_every_id_decoded_at_true_scale(sheet):
    found = detect(sheet["pages"][0])
    assert sorted(found) == IDS
    errors = [side_mm(c, DPI) / 50.0 - 1.0 for c in found.values()]
    assert max(abs(e) for e in errors) < SIDE_TOL, errors
    # the markers are axis-aligned squares: opposite edges agree to a fraction of a pixel
    for c in found.values():
        edges = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)
        assert np.ptp(edges) < 1.0


def test_quiet_zone_is_white_and_cut_marks_lie_outside_it(sheet):
    gray = sheet["pages"][0]
    cell_px = 50.0 / 6.0 * DPI / 25.4
    for c in detect(gray).values():
        x0, y0 = c.min(axis=0)
        x1, y1 = c.max(axis=0)
        # the ring one cell wide around the black square (1.5 px kept off both of its edges)
        ox, oy = int(x0 - cell_px + 1.5), int(y0 - cell_px + 1.5)
        outer = gray[oy : int(y1 + cell_px - 1.5), ox : int(x1 + cell_px - 1.5)].copy()
        outer[int(y0) - oy - 2 : int(y1) - oy + 3, int(x0) - ox - 2 : int(x1) - ox + 3] = 255
        assert outer.min() > 235
        # a cut tick: along the top edge of the cut square, 1..5 mm left of its top-left corner
        cx, cy = x0 - cell_px, y0 - cell_px
        mm = DPI / 25.4
        tick = gray[int(cy - 2) : int(cy + 3), int(cx - 4.5 * mm) : int(cx - 1.5 * mm)]
        assert tick.min() < 160


def test_page_text_says_print_at_actual_size(sheet):
    doc = pdfium.PdfDocument(str(sheet["dir"] / "sheet.pdf"))
    try:
        text = doc[0].get_textpage().get_text_range()
    finally:
        doc.close()
    flat = " ".join(text.split())
    for needle in [
        "Tank test sheet",
        "print at 100 %",
        "actual size",
        "do not fit to page",
        "this bar is 100 mm",
        "DICT_4X4_50 id 28 50 mm",
    ]:
        assert needle in flat


def test_scale_bar_measures_100_mm(sheet):
    gray = sheet["pages"][0]
    # the bar is the longest horizontal dark run in the bottom 25 mm of the page
    mm = DPI / 25.4
    band = gray[int(gray.shape[0] - 25 * mm) :] < 128
    best = 0
    for row in band:
        padded = np.concatenate(([0], row.astype(np.int8), [0]))
        edges = np.flatnonzero(np.diff(padded))
        if edges.size:
            best = max(best, int((edges[1::2] - edges[::2]).max()))
    assert best / mm == pytest.approx(100.0, abs=0.3)  # bar + line-width, within ~2 px


@pytest.mark.parametrize("paper", ["A4", "A3", "letter", "a4"])
def test_pdf_page_size_is_the_paper(tmp_path, paper):
    path = tmp_path / "s.pdf"
    write_sheet([aruco_entry(13, 40.0)], 40.0, path, None, paper=paper)
    w_mm, h_mm = PAPER_SIZES_MM["A4" if paper == "a4" else paper]
    doc = pdfium.PdfDocument(str(path))
    try:
        w_pt, h_pt = doc[0].get_size()
    finally:
        doc.close()
    assert w_pt == pytest.approx(w_mm / MM_PER_PT, abs=0.01)
    assert h_pt == pytest.approx(h_mm / MM_PER_PT, abs=0.01)


def _svg_black_patch_extents(root: ET.Element) -> list[tuple[float, float]]:
    """(width, height) in viewBox units of every black filled patch path."""
    sizes = []
    for g in root.iter(f"{SVG_NS}g"):
        if not g.get("id", "").startswith("patch_"):
            continue
        for p in g.findall(f"{SVG_NS}path"):
            fill = re.search(r"fill:\s*([^;]+)", p.get("style") or "")
            if fill is not None and fill[1].strip() not in ("#000000", "black"):
                continue  # the SVG default fill is black
            xy = np.array([float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", p.get("d"))])
            xy = xy.reshape(-1, 2)
            sizes.append(tuple(np.ptp(xy, axis=0)))
    return sizes


def test_svg_is_true_scale_and_self_contained(sheet):
    root = ET.parse(sheet["dir"] / "sheet.svg").getroot()
    assert root.get("width") == "210mm" and root.get("height") == "297mm"
    vb = [float(v) for v in root.get("viewBox").split()]
    assert vb[:2] == [0.0, 0.0]
    mm_per_unit_x, mm_per_unit_y = 210.0 / vb[2], 297.0 / vb[3]
    assert mm_per_unit_x == pytest.approx(mm_per_unit_y, rel=1e-7)
    # every marker's black square measures 50 mm through the viewBox scale
    sizes = _svg_black_patch_extents(root)
    assert len(sizes) == len(IDS)
    for w, h in sizes:
        assert w * mm_per_unit_x == pytest.approx(50.0, rel=1e-6)
        assert h * mm_per_unit_y == pytest.approx(50.0, rel=1e-6)
    # text as glyph paths, no external references: renders without fonts or other files
    assert not list(root.iter(f"{SVG_NS}text"))
    hrefs = [v for el in root.iter() for k, v in el.attrib.items() if k.endswith("href")]
    assert hrefs and all(h.startswith("#") for h in hrefs)


def test_black_cells_are_merged_into_few_disjoint_rectangles():
    rng = np.random.default_rng(3)
    for _ in range(20):
        cells = rng.random((7, 7)) < 0.6
        cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = True
        cover = np.zeros(cells.shape, dtype=int)
        rects = black_rectangles(cells)
        for r, c, h, w in rects:
            cover[r : r + h, c : c + w] += 1
        np.testing.assert_array_equal(cover, cells.astype(int))  # exact and disjoint
        row_runs = sum(int(np.count_nonzero(np.diff(np.r_[0, row, 0]) == 1)) for row in cells)
        assert len(rects) <= row_runs
    # the full border alone: top and bottom rows plus two side columns
    ring = np.ones((6, 6), dtype=bool)
    ring[1:-1, 1:-1] = False
    assert len(black_rectangles(ring)) == 4


def test_many_markers_spill_onto_several_pages(tmp_path):
    ids = [13, 14, 15, 28, 30, 34, 35, 41, 42, 43, 49]
    dpi = 100.0
    written = write_sheet(
        [aruco_entry(i, 100.0) for i in ids], 100.0, tmp_path / "m.pdf", tmp_path / "m.svg"
    )
    pages = render_pdf(tmp_path / "m.pdf", dpi)
    assert len(pages) > 1
    svgs = [tmp_path / "m.svg"] + [tmp_path / f"m_p{k}.svg" for k in range(2, len(pages) + 1)]
    assert written == [tmp_path / "m.pdf", *svgs]
    assert all(p.is_file() for p in svgs)
    found: dict[int, float] = {}
    for gray in pages:
        for marker_id, corners in detect(gray).items():
            assert marker_id not in found  # each marker drawn once
            found[marker_id] = side_mm(corners, dpi)
    assert sorted(found) == ids
    for s in found.values():
        assert s == pytest.approx(100.0, rel=SIDE_TOL)


def test_marker_too_big_for_the_paper_raises(tmp_path):
    with pytest.raises(DockError, match="--paper") as info:
        write_sheet([aruco_entry(13, 180.0)], 180.0, tmp_path / "a.pdf", tmp_path / "a.svg")
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []
    # the same marker fits on A3
    write_sheet([aruco_entry(13, 180.0)], 180.0, tmp_path / "a.pdf", None, paper="A3")
    assert (tmp_path / "a.pdf").is_file()


def test_bad_arguments_raise(tmp_path):
    with pytest.raises(DockError, match="paper"):
        write_sheet([aruco_entry(13, 50.0)], 50.0, tmp_path / "a.pdf", None, paper="B5")
    with pytest.raises(DockError):
        write_sheet([], 50.0, tmp_path / "a.pdf", None)
    with pytest.raises(DockError):
        write_sheet([aruco_entry(13, 50.0)], 0.0, tmp_path / "a.pdf", None)
    with pytest.raises(ValueError, match="square"):
        write_sheet([SheetEntry(1, np.ones((4, 6), bool), "x")], 50.0, tmp_path / "a.pdf", None)
    assert list(tmp_path.iterdir()) == []


def test_failure_while_rendering_leaves_nothing_behind(tmp_path, monkeypatch):
    (tmp_path / "old.pdf").write_bytes(b"previous sheet")

    def boom(self, *args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", boom)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_sheet([aruco_entry(13, 50.0)], 50.0, tmp_path / "old.pdf", tmp_path / "new.svg")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.pdf"]  # no new file, no temp
    assert (tmp_path / "old.pdf").read_bytes() == b"previous sheet"  # old file untouched


def test_unwritable_target_leaves_nothing_behind(tmp_path):
    (tmp_path / "not_a_dir").write_text("a file")
    with pytest.raises(OSError):
        write_sheet([aruco_entry(13, 50.0)], 50.0, tmp_path / "not_a_dir" / "s.pdf", None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not_a_dir"]
