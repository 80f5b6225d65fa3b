"""`companion markers`: real PNG/SVG/PDF files, read back by OpenCV, an XML parser and a PDF parser."""
from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion import cli
from companion.markers import printing
from companion.markers.codec import GridDecoder
from companion.markers.dictionary import load_dictionary
from companion.markers.layout import MarkerLayout

SYMBOLS = ["A", "B", "7", "HOME"]


def run_markers(tmp_path: Path, *options: str) -> int:
    return cli.main(["markers", "--out", str(tmp_path), *options])


def aruco_detect(image: np.ndarray, dictionary: str) -> dict[int, np.ndarray]:
    params = cv2.aruco.DetectorParameters()
    params.minDistanceToBorder = 0
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(load_dictionary(dictionary).aruco(), params)
    corners, ids, _ = detector.detectMarkers(image)
    return {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners)}


def sample_grid(image: np.ndarray, layout: MarkerLayout, inner_corners_px: np.ndarray) -> np.ndarray:
    """(N, N) int8 cells read at the cell centres, located through the inner corners' homography."""
    H = cv2.getPerspectiveTransform(layout.inner_corners_cells.astype(np.float32),
                                    inner_corners_px.astype(np.float32))
    n = layout.n_cells
    v, u = np.mgrid[0:n, 0:n] + 0.5
    centres = cv2.perspectiveTransform(np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float32), H)
    x, y = np.round(centres.reshape(-1, 2)).astype(int).T
    return (image[y, x] < 128).astype(np.int8).reshape(n, n)


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, body) of every chunk; asserts each CRC."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    chunks, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        assert crc == zlib.crc32(kind + body), kind
        chunks.append((kind, body))
        pos += 12 + length
    return chunks


# --------------------------------------------------------------------- PNG

@pytest.mark.parametrize("parity, dictionary, which", [(2, "6x6", "--all"), (4, "6x6", "--all"),
                                                       (2, "5x5", SYMBOLS), (4, "8x8", SYMBOLS)])
def test_png_markers_are_detected_by_aruco_at_the_sidecar_corners_and_decode(tmp_path, parity, dictionary, which):
    symbols = ["--all"] if which == "--all" else ["--symbols", ",".join(which)]
    assert run_markers(tmp_path, *symbols, "--parity", str(parity), "--dictionary", dictionary) == 0
    pngs = sorted(tmp_path.glob("*.png"))
    assert len(pngs) == (50 if which == "--all" else len(which))
    for png in pngs:
        sidecar = json.loads(png.with_suffix(".json").read_text())
        image = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        assert sidecar["parity"] == parity and sidecar["dictionary"] == dictionary
        assert sidecar["id"] == load_dictionary(dictionary).id_of(sidecar["symbol"])
        corners = np.array(sidecar["inner_corners_px"])

        found = aruco_detect(image, dictionary)
        assert list(found) == [sidecar["id"]], png.name
        assert np.linalg.norm(found[sidecar["id"]] - corners, axis=1).max() < 0.5

        layout = MarkerLayout(sidecar["parity"], sidecar["dictionary"])
        assert sidecar["cells"] == layout.n_cells
        result = GridDecoder(layout).decode_algebraic(sample_grid(image, layout, corners))
        assert result is not None, png.name
        assert (result.id, result.symbol, result.rotation) == (sidecar["id"], sidecar["symbol"], 0)
        assert result.mismatched_cells == 0 and result.erased_cells == 0


def inner_square_run_px(image: np.ndarray, sidecar: dict) -> int:
    """The inner square's width in pixels, measured on the image: the black run of its top border row."""
    corners = np.array(sidecar["inner_corners_px"])
    row = int(round(corners[0, 1] + sidecar["px_per_cell"] / 2))  # the middle of the top border row
    black = image[row] < 128
    x = int(round(corners[0, 0] + 1))
    left, right = x, x
    while left > 0 and black[left - 1]:
        left -= 1
    while right + 1 < len(black) and black[right + 1]:
        right += 1
    return right - left + 1


def png_resolution_px_per_m(png: Path) -> int:
    phys = [body for kind, body in png_chunks(png.read_bytes()) if kind == b"pHYs"]
    assert len(phys) == 1
    ppm_x, ppm_y, unit = struct.unpack(">IIB", phys[0])
    assert ppm_x == ppm_y and unit == 1
    return ppm_x


def test_png_is_written_at_the_asked_dpi_and_prints_the_inner_square_at_size(tmp_path):
    """Printed at the --dpi it says, the inner square is --size-mm to within half a pixel (the
    landed code wrote 301.9 dpi and whole pixels per cell: 0.6 % large when printed at 300 dpi)."""
    for dpi in (300, 600, 97):
        out = tmp_path / str(dpi)
        assert run_markers(out, "--symbols", "C", "--size-mm", "35", "--dpi", str(dpi)) == 0
        png = out / "marker-C-p2.png"
        sidecar = json.loads((out / "marker-C-p2.json").read_text())
        ppm = png_resolution_px_per_m(png)
        assert ppm == round(dpi / 0.0254)          # the PNG's unit: whole pixels per metre
        assert ppm * 0.0254 == pytest.approx(dpi, abs=0.5 * 0.0254)  # half a px/m: the format's own step
        image = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        inner_px = inner_square_run_px(image, sidecar)
        printed_mm = inner_px / dpi * 25.4       # printed at the DPI the file states
        assert abs(printed_mm - 35.0) <= 0.5 * 25.4 / dpi + 1e-9, (dpi, inner_px, printed_mm)
        assert inner_px == sidecar["inner_px"] and sidecar["size_mm"] == pytest.approx(inner_px / ppm * 1000)
        assert list(image.shape[::-1]) == sidecar["image_px"]


def test_png_of_a_larger_marker_and_quiet_zone_keeps_the_size(tmp_path):
    assert run_markers(tmp_path, "--symbols", "C", "--size-mm", "42.5", "--dpi", "300", "--quiet-zone-cells", "2") == 0
    sidecar = json.loads((tmp_path / "marker-C-p2.json").read_text())
    image = cv2.imread(str(tmp_path / "marker-C-p2.png"), cv2.IMREAD_GRAYSCALE)
    assert inner_square_run_px(image, sidecar) == round(42.5 / 25.4 * 300)  # 502 px
    # the quiet zone, 2 cells of 502 / 8 px each side, is white up to the grid
    assert abs(image.shape[0] - (14 + 4) * 502 / 8) <= 1 and image[:125, :].min() == 255


def test_a_png_too_large_to_make_is_refused_before_any_work(tmp_path, capsys):
    for size, lower_dpi in (("1000", "--dpi 152 or less"), ("3000", ""), ("1e6", "")):
        assert run_markers(tmp_path, "--symbols", "A", "--size-mm", size) == 2
        err = capsys.readouterr().err
        assert "--format svg or --format pdf" in err and lower_dpi in err, err
    assert not list(tmp_path.iterdir())


def test_png_sidecar_circles_match_the_drawn_circles(tmp_path):
    for parity in ("2", "4"):
        assert run_markers(tmp_path, "--symbols", "Z", "--parity", parity) == 0
        sidecar = json.loads((tmp_path / f"marker-Z-p{parity}.json").read_text())
        image = cv2.imread(str(tmp_path / f"marker-Z-p{parity}.png"), cv2.IMREAD_GRAYSCALE)
        circles = np.array(sidecar["circles_px"])
        assert circles.shape == (12, 3)
        angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        ring = np.stack([np.cos(angles), np.sin(angles)], 1)
        for x, y, r in circles:
            inside = np.round([x, y] + 0.85 * r * ring).astype(int)
            outside = np.round([x, y] + 1.2 * r * ring).astype(int)
            assert image[inside[:, 1], inside[:, 0]].max() < 60
            assert image[outside[:, 1], outside[:, 0]].min() > 195


def test_png_with_phys_replaces_an_existing_chunk():
    ok, encoded = cv2.imencode(".png", np.zeros((3, 5), np.uint8))
    twice = printing.png_with_phys(printing.png_with_phys(encoded.tobytes(), 1000), 11811)
    chunks = png_chunks(twice)
    assert [k for k, _ in chunks].count(b"pHYs") == 1
    assert struct.unpack(">IIB", dict(chunks)[b"pHYs"]) == (11811, 11811, 1)
    assert cv2.imdecode(np.frombuffer(twice, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (3, 5)


# --------------------------------------------------------------------- SVG

def test_svg_has_mm_size_and_draws_the_layout_cells_and_circles(tmp_path):
    assert run_markers(tmp_path, "--symbols", "7,STAR", "--format", "svg", "--parity", "4",
                       "--size-mm", "50") == 0
    layout = MarkerLayout(4)
    for symbol in ("7", "STAR"):
        root = ET.parse(tmp_path / f"marker-{symbol}-p4.svg").getroot()
        side_cells = layout.n_cells + 2
        # inner square 50 mm = 8 cells -> side = 20 cells = 125 mm
        assert root.get("width") == root.get("height") == f"{side_cells * 50 / 8:g}mm"
        assert root.get("viewBox") == f"0 0 {side_cells} {side_cells}"
        ns = "{http://www.w3.org/2000/svg}"
        group = root.find(f"{ns}g")
        grid = np.zeros((side_cells, side_cells), np.uint8)
        for rect in group.findall(f"{ns}rect"):
            x, y, w, h = (float(rect.get(k)) for k in ("x", "y", "width", "height"))
            assert h == 1 and x == int(x) and y == int(y) and w == int(w)
            assert not grid[int(y), int(x):int(x + w)].any()  # runs never overlap
            grid[int(y), int(x):int(x + w)] = 1
        marker_id = load_dictionary("6x6").id_of(symbol)
        np.testing.assert_array_equal(grid, np.pad(layout.cells(marker_id), 1))
        drawn = np.array([[float(c.get(k)) for k in ("cx", "cy", "r")] for c in group.findall(f"{ns}circle")])
        np.testing.assert_allclose(drawn, layout.circles + [1, 1, 0], atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.integers(0, 1), min_size=7, max_size=7), min_size=1, max_size=7))
def test_cell_runs_rebuild_the_grid_with_maximal_runs(rows):
    cells = np.array(rows, np.uint8)
    rebuilt = np.zeros_like(cells)
    for row, column, length in printing.cell_runs(cells):
        assert length > 0 and not rebuilt[row, column:column + length].any()
        rebuilt[row, column:column + length] = 1
        assert column == 0 or cells[row, column - 1] == 0  # maximal: white before and after
        assert column + length == cells.shape[1] or cells[row, column + length] == 0
    np.testing.assert_array_equal(rebuilt, cells)


# --------------------------------------------------------------------- PDF

PT_PER_MM = 72 / 25.4  # PDF user space unit: 1/72 inch
CONTENT_TOKEN = re.compile(r"\((?:\\.|[^\\)])*\)|\[|\]|[^\s\[\]()]+")


def pdf_objects(data: bytes) -> dict[int, bytes]:
    """Objects found through the xref table; asserts every offset lands on ``N 0 obj``."""
    assert data.startswith(b"%PDF-1.") and data.rstrip().endswith(b"%%EOF")
    startxref = int(re.search(rb"startxref\s+(\d+)\s+%%EOF\s*$", data).group(1))
    assert data[startxref:startxref + 4] == b"xref"
    header = re.match(rb"xref\n0 (\d+)\n", data[startxref:])
    size = int(header.group(1))
    table = data[startxref + header.end():startxref + header.end() + 20 * size]
    entries = [table[20 * i:20 * i + 20] for i in range(size)]
    assert entries[0] == b"0000000000 65535 f \n"
    assert int(re.search(rb"/Size (\d+)", data[startxref:]).group(1)) == size
    objects = {}
    for number, entry in enumerate(entries[1:], start=1):
        assert re.fullmatch(rb"\d{10} 00000 n \n", entry), entry
        offset = int(entry[:10])
        assert data[offset:].startswith(b"%d 0 obj\n" % number)
        end = data.index(b"\nendobj\n", offset)
        objects[number] = data[offset + len(b"%d 0 obj\n" % number):end]
    return objects


def pdf_pages(objects: dict[int, bytes]) -> list[tuple[tuple[float, float], str]]:
    """(MediaBox width, height in pt) and the content stream text of every page, in page order."""
    catalog = next(o for o in objects.values() if b"/Type /Catalog" in o)
    pages_ref = int(re.search(rb"/Pages (\d+) 0 R", catalog).group(1))
    kids = [int(k) for k in re.findall(rb"(\d+) 0 R", re.search(rb"/Kids \[(.*?)\]", objects[pages_ref], re.S).group(1))]
    assert int(re.search(rb"/Count (\d+)", objects[pages_ref]).group(1)) == len(kids)
    pages = []
    for kid in kids:
        page = objects[kid]
        box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", page).group(1).split()]
        content = objects[int(re.search(rb"/Contents (\d+) 0 R", page).group(1))]
        assert b"/Filter" not in content  # uncompressed: readable here
        length = int(re.search(rb"/Length (\d+)", content).group(1))
        stream = content[content.index(b"stream\n") + 7:]
        assert stream[length:].strip() == b"endstream"
        pages.append(((box[2], box[3]), stream[:length].decode("latin-1")))
    return pages


def pdf_string(token: str) -> str:
    """The text of a PDF literal string token ``(...)`` (backslash escapes of ( ) and \\)."""
    return re.sub(r"\\(.)", r"\1", token[1:-1])


@dataclass
class PageDrawing:
    """What a page's content stream paints, in pt, PDF y up.

    groups: per top-level q ... Q block, the filled rectangles (x, y, w, h) and circles
    ((4 arcs, start + 2 controls + end, 2) Bezier points) inside it; rects: filled rectangles
    outside any block; segments: stroked lines (x0, y0, x1, y1); texts: (x, y, size, text).
    """

    groups: list[tuple[list, list]] = field(default_factory=list)
    rects: list[tuple[float, ...]] = field(default_factory=list)
    segments: list[tuple[float, ...]] = field(default_factory=list)
    texts: list[tuple[float, float, float, str]] = field(default_factory=list)


def read_content(content: str) -> PageDrawing:
    """Interpret the operators the sheets use; anything that is not a vector shape or text fails."""
    page, depth, path, operands = PageDrawing(), 0, [], []
    font_pt = text_x = text_y = None
    for token in CONTENT_TOKEN.findall(content):
        if token.startswith(("(", "/")) or token in "[]":
            operands.append(pdf_string(token) if token.startswith("(") else token)
            continue
        try:
            operands.append(float(token))
            continue
        except ValueError:
            op, args, operands = token, operands, []
        if op == "cm":
            assert args == [1, 0, 0, 1, 0, 0], args  # page coordinates stay page coordinates
        elif op == "q":
            depth += 1
            if depth == 1:
                page.groups.append(([], []))
        elif op == "Q":
            depth -= 1
        elif op == "re":
            path.append(("re", tuple(args)))
        elif op == "m":
            path.append(("m", [tuple(args)]))
        elif op in ("l", "c"):
            path[-1][1].append(tuple(args))
        elif op in ("f", "f*"):
            assert op == "f", "filled with the nonzero winding rule"
            rects, circles = page.groups[-1] if depth else (page.rects, [])
            for kind, points in path:
                if kind == "re":
                    rects.append(points)
                else:
                    start, arcs = points[0], np.array(points[1:], float).reshape(-1, 3, 2)
                    assert len(arcs) == 4 and np.array_equal(arcs[-1, 2], start)  # a closed 4-arc outline
                    starts = np.vstack([start, arcs[:-1, 2]])
                    circles.append(np.concatenate([starts[:, None], arcs], axis=1))
            path = []
        elif op == "S":
            page.segments += [a + b for kind, (a, b) in path]
            path = []
        elif op == "Tf":
            font_pt = args[1]
        elif op == "Tm":
            text_x, text_y = args[4:6]
        elif op == "Td":  # right after BT: from the origin
            text_x, text_y = args
        elif op == "Tj":
            page.texts.append((text_x, text_y, font_pt, args[0]))
        elif op in ("Do", "BI", "sh"):
            raise AssertionError(f"{op}: an image or shading where vector shapes belong")
        else:
            assert op in ("n", "h", "w", "BT", "ET", "TL", "T*", "g", "G", "rg", "RG"), op
    assert depth == 0 and not path
    return page


def check_marker_geometry(rects, circles, layout: MarkerLayout, marker_id: int, size_mm: float) -> None:
    """The drawn rectangles are exactly the marker's black cells at ``size_mm`` / 8 per cell."""
    rects = np.array(rects) / PT_PER_MM  # mm, PDF y up
    widest = rects[np.argsort(rects[:, 2])[-2:]]  # the top and bottom border rows: 8 cells wide
    np.testing.assert_allclose(widest[:, 2], size_mm, atol=1e-3)
    np.testing.assert_allclose(widest[:, 3], size_mm / 8, atol=1e-3)
    # inner square height: top of the top border row to the bottom of the bottom border row
    assert (widest[:, 1] + widest[:, 3]).max() - widest[:, 1].min() == pytest.approx(size_mm, abs=1e-3)
    cell = size_mm / layout.inner_cells
    o = layout.inner_origin
    x0 = widest[0, 0] - o * cell
    y_top = (widest[:, 1] + widest[:, 3]).max() + o * cell  # grid top edge, PDF y up
    grid = np.zeros((layout.n_cells, layout.n_cells), np.uint8)
    for x, y, w, h in rects:
        c, r, length = (x - x0) / cell, (y_top - (y + h)) / cell, w / cell
        assert np.allclose([c, r, length, h / cell], np.round([c, r, length, 1]), atol=1e-3)
        grid[round(r), round(c):round(c + length)] = 1
    np.testing.assert_array_equal(grid, layout.cells(marker_id))
    t = np.linspace(0, 1, 9)[:, None]
    drawn = []
    for arcs in np.array(circles) / PT_PER_MM:
        ends = arcs[:, 3]
        centre, radius = ends.mean(axis=0), np.ptp(ends[:, 0]) / 2
        for p0, p1, p2, p3 in arcs:
            # cubic Bezier B(t) = (1-t)^3 p0 + 3 (1-t)^2 t p1 + 3 (1-t) t^2 p2 + t^3 p3
            curve = (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t ** 2 * p2 + t ** 3 * p3
            # the standard 4-arc approximation stays within 0.03 % of the radius
            np.testing.assert_allclose(np.linalg.norm(curve - centre, axis=1), radius, rtol=3e-4)
        drawn.append([centre[0] - x0, y_top - centre[1], radius])
    np.testing.assert_allclose(np.array(drawn) / cell, layout.circles, atol=1e-3)


def pdf_drawings(pdf_path: Path) -> list[tuple[tuple[float, float], PageDrawing]]:
    return [(box, read_content(content)) for box, content in pdf_pages(pdf_objects(pdf_path.read_bytes()))]


def poppler(tool: str) -> str:
    path = shutil.which(tool)
    assert path, f"{tool} is needed for this test (apt-get install poppler-utils)"
    return path


def render_page(pdf_path: Path, page: int, dpi: int) -> np.ndarray:
    """Page ``page`` (1-based) rasterised by poppler as an 8-bit gray image."""
    out = pdf_path.with_name(f"page{page}")
    subprocess.run([poppler("pdftoppm"), "-r", str(dpi), "-gray", "-f", str(page), "-l", str(page), "-singlefile",
                    str(pdf_path), str(out)], check=True, timeout=120)
    return cv2.imread(str(out.with_suffix(".pgm")), cv2.IMREAD_GRAYSCALE)


def text_boxes_mm(pdf_path: Path, page: int) -> list[tuple[str, float, float, float, float]]:
    """Words of page ``page`` with poppler's boxes (x0, y0, x1, y1 in mm from the top-left corner),
    measured with poppler's own metrics of the standard fonts."""
    xhtml = subprocess.run([poppler("pdftotext"), "-bbox", "-f", str(page), "-l", str(page), str(pdf_path), "-"],
                           check=True, capture_output=True, text=True, timeout=60).stdout
    words = re.findall(r'<word xMin="(\S+)" yMin="(\S+)" xMax="(\S+)" yMax="(\S+)">(.*?)</word>', xhtml)
    return [(text, *(float(v) / PT_PER_MM for v in box)) for *box, text in words]


def test_pdf_sheet_is_valid_and_draws_markers_at_exact_scale(tmp_path):
    assert run_markers(tmp_path, "--symbols", "A,B,7", "--format", "pdf", "--size-mm", "30") == 0
    (pdf_path,) = tmp_path.glob("*.pdf")
    assert b"/BaseFont /Helvetica" in pdf_path.read_bytes()
    ((width_pt, height_pt), page), = pdf_drawings(pdf_path)
    assert (width_pt, height_pt) == pytest.approx((210 * PT_PER_MM, 297 * PT_PER_MM), abs=1e-3)
    layout = MarkerLayout(2)
    assert len(page.groups) == 3
    texts = [text for *_, text in page.texts]
    for symbol, (rects, circles) in zip(("A", "B", "7"), page.groups):
        marker_id = layout.dictionary.id_of(symbol)
        check_marker_geometry(rects, circles, layout, marker_id, 30.0)
        assert f"{symbol}   id {marker_id}" in texts
    assert texts.count("parity 2, 6x6, inner square 30 mm") == 3
    assert len(page.segments) == 3 * 8  # crop marks: 2 per corner
    # the scale bar: 50 x 1 mm, 8 mm from the left and 8.5 mm from the bottom edge
    np.testing.assert_allclose(np.array(page.rects) / PT_PER_MM, [[8, 8.5, 50, 1]], atol=1e-3)


def test_pdf_all_markers_fill_letter_pages_inside_the_margins(tmp_path):
    assert run_markers(tmp_path, "--all", "--format", "pdf", "--parity", "4", "--page", "letter") == 0
    (pdf_path,) = tmp_path.glob("*.pdf")
    pages = pdf_drawings(pdf_path)
    layout = MarkerLayout(4)
    labels = []
    for (width_pt, height_pt), page in pages:
        assert (width_pt, height_pt) == pytest.approx((215.9 * PT_PER_MM, 279.4 * PT_PER_MM), abs=1e-3)
        for rects, circles in page.groups:
            assert len(circles) == 12
            xs = np.array([(x, x + w) for x, _, w, _ in rects]) / PT_PER_MM
            assert xs.min() >= printing.PAGE_MARGIN_MM and xs.max() <= 215.9 - printing.PAGE_MARGIN_MM
        labels += [re.fullmatch(r"(\S+)   id (\d+)", text).groups() for *_, text in page.texts if " id " in text]
    assert [(s, int(i)) for s, i in labels] == [(s, i) for i, s in enumerate(layout.dictionary.symbols)]
    # 35 mm inner square, parity 4: a 20-cell, 87.5 mm cut square; slot 87.5 + 2 x 4 mm crop marks wide
    # and 8 mm more (two label lines) high: 2 columns and 2 rows in 199.9 x 255.4 mm inside the margins
    assert len(pages) == 13 and [len(page.groups) for _, page in pages] == [4] * 12 + [2]
    rects, circles = pages[-1][1].groups[-1]
    check_marker_geometry(rects, circles, layout, 49, 35.0)


def test_pdf_rendered_by_poppler_has_35_mm_inner_squares_where_the_layout_puts_them(tmp_path):
    assert run_markers(tmp_path, "--all", "--format", "pdf") == 0
    (pdf_path,) = tmp_path.glob("*.pdf")
    dpi = 600
    image = render_page(pdf_path, 1, dpi)
    assert image.shape == (round(297 / 25.4 * dpi), round(210 / 25.4 * dpi))
    mm_per_px = 25.4 / dpi
    found = aruco_detect(image, "6x6")
    # By hand for 35 mm, parity 2, A4: a 16-cell, 70 mm cut square in a 78 x 86 mm slot (4 mm of crop
    # marks each side, 8 mm of labels below); 2 columns centred, (210 - 2 x 78 - 1) / 2 = 26.5 mm from
    # the left, 3 rows from the 8 mm margin, 1 mm apart; the inner square is 4 cells (17.5 mm) inside.
    expected_top_left_mm = {k: (26.5 + 4 + 17.5 + 79 * (k % 2), 8 + 4 + 17.5 + 87 * (k // 2)) for k in range(6)}
    assert sorted(found) == list(expected_top_left_mm)
    layout = MarkerLayout(2)
    for marker_id, corners_px in found.items():
        # corners are pixel-centre coordinates: the edge of pixel 0 is at -0.5
        corners_mm = (corners_px + 0.5) * mm_per_px
        sides_mm = np.linalg.norm(corners_mm - np.roll(corners_mm, 1, axis=0), axis=1)
        assert sides_mm.min() > 34.967 and sides_mm.max() < 35.019, sides_mm
        np.testing.assert_allclose(corners_mm.min(axis=0), expected_top_left_mm[marker_id], atol=0.03)
        result = GridDecoder(layout).decode_algebraic(sample_grid(image, layout, corners_px))
        assert (result.id, result.mismatched_cells, result.erased_cells) == (marker_id, 0, 0)
    # the scale bar: 1 mm high, its top 297 - 8 - 1.5 mm from the top edge, 50 mm long
    bar_row = image[round((297 - 8 - 1.0) / mm_per_px)]
    black = np.flatnonzero(bar_row < 128)
    bar = np.split(black, np.flatnonzero(np.diff(black) > 1) + 1)[0]  # the footer text follows the bar
    assert bar[0] * mm_per_px == pytest.approx(8.0, abs=0.05)
    assert len(bar) * mm_per_px == pytest.approx(50.0, abs=0.05)


def test_a_long_label_fits_its_slot_by_the_font_metrics(tmp_path):
    # tiny markers, so the longest details line sets the slot width: 4.123456 mm in 6 decimals
    assert run_markers(tmp_path, "--all", "--format", "pdf", "--dictionary", "8x8", "--parity", "4",
                       "--size-mm", "4.123456") == 0
    (pdf_path,) = tmp_path.glob("*.pdf")
    words = text_boxes_mm(pdf_path, 1)
    label = "parity 4, 8x8, inner square 4.123456 mm".split()
    starts = [i for i, (text, *_) in enumerate(words) if text == "parity"]
    assert len(starts) > 4
    rows = {}
    for i in starts:
        line = words[i:i + len(label)]
        assert [text for text, *_ in line] == label
        rows.setdefault(round(line[0][2], 2), []).append((line[0][1], line[-1][3]))  # x0, x1 (mm) per row
    # the black square spans the grid's columns, centred in it
    column_centres_mm = sorted({round((min(x for x, *_ in rects) + max(x + w for x, _, w, _ in rects)) / 2 / PT_PER_MM, 4)
                                for rects, _ in pdf_drawings(pdf_path)[0][1].groups})
    for spans in rows.values():
        spans.sort()
        assert spans[0][0] >= printing.PAGE_MARGIN_MM and spans[-1][1] <= 210 - printing.PAGE_MARGIN_MM
        gaps = [next_x0 - x1 for (_, x1), (next_x0, _) in zip(spans, spans[1:])]
        # labels in neighbouring slots keep the 1 mm slot spacing between them: each fits its
        # slot, and the slot is no wider than the label (measured, not estimated per character)
        np.testing.assert_allclose(gaps, 1.0, atol=0.01)
        # each label is centred under its marker
        np.testing.assert_allclose([(x0 + x1) / 2 for x0, x1 in spans], column_centres_mm, atol=0.01)


# ------------------------------------------------------------------ errors

def test_unknown_symbol_lists_the_known_symbols_and_exits_2(tmp_path, capsys):
    assert run_markers(tmp_path, "--symbols", "A,QQ") == 2
    err = capsys.readouterr().err
    assert "'QQ'" in err and "A, B, C" in err and "HOME" in err and "STAR" in err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("size", ["0", "-5", "nan"])
def test_non_positive_size_is_a_clear_error(tmp_path, capsys, size):
    assert run_markers(tmp_path, "--symbols", "A", f"--size-mm={size}") == 2
    assert "--size-mm must be a positive number" in capsys.readouterr().err


def test_the_readme_example_tiles_150_mm_markers_over_a4_pages_that_join_into_the_marker(tmp_path, capsys):
    """`companion markers --symbols A,B,7,HOME --parity 4 --size-mm 150 --format pdf --page a4` (the README's
    example, refused by the landed code): every marker on several pages; rendered by poppler, the tiles
    of each marker put side by side are that marker, 150 mm across its inner square."""
    assert cli.main(["markers", "--symbols", "A,B,7,HOME", "--parity", "4", "--size-mm", "150", "--format", "pdf",
                     "--page", "a4", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    # one page: the 20-cell cut square plus 2 x 4 mm of crop marks in 210 - 2 x 8 mm: 186 mm = 20 cells of
    # 9.3 mm, an inner square of 8 x 9.3 = 74.4 mm
    assert "each tiled on 2 x 3 A4 pages (24 pages)" in out and "the largest that fits one A4 page is 74.4 mm" in out
    (pdf_path,) = tmp_path.glob("*.pdf")
    layout = MarkerLayout(4)
    marker = printing.MarkerPrint(layout, 0, 150.0, 1)
    tiles = printing.tile_geometry(marker, "a4")
    dpi = 40
    px_per_mm = dpi / 25.4
    origin_mm = printing.PAGE_MARGIN_MM + printing.CROP_MARK_GAP_MM + printing.CROP_MARK_LENGTH_MM
    for index, symbol in enumerate(["A", "B", "7", "HOME"]):
        rows = []
        for row in range(tiles.rows):
            pieces = []
            for column in range(tiles.columns):
                page = render_page(pdf_path, 1 + index * tiles.per_marker + row * tiles.columns + column, dpi)
                width_mm = (tiles.column_cells[column + 1] - tiles.column_cells[column]) * marker.cell_mm
                height_mm = (tiles.row_cells[row + 1] - tiles.row_cells[row]) * marker.cell_mm
                x0, y0 = round(origin_mm * px_per_mm), round(origin_mm * px_per_mm)
                pieces.append(page[y0:y0 + round(height_mm * px_per_mm), x0:x0 + round(width_mm * px_per_mm)])
            rows.append(np.hstack([p[:min(q.shape[0] for q in pieces)] for p in pieces]))
        joined = np.vstack([r[:, :min(q.shape[1] for q in rows)] for r in rows])
        found = aruco_detect(joined, "6x6")
        marker_id = layout.dictionary.id_of(symbol)
        assert list(found) == [marker_id], symbol
        corners = found[marker_id]
        side_mm = np.mean(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)) / px_per_mm
        assert side_mm == pytest.approx(150.0, abs=1.5)  # within about two pixels at 40 dpi
        result = GridDecoder(layout).decode_algebraic(sample_grid(joined, layout, corners))
        assert result is not None and result.symbol == symbol and result.mismatched_cells == 0


def test_a_marker_too_large_for_one_page_says_the_largest_that_fits(tmp_path):
    marker = printing.MarkerPrint(MarkerLayout(2), 0, 150.0, 1)
    with pytest.raises(printing.PrintingError, match=r"the largest that fits is \d+\.\d mm"):
        printing.sheet_geometry([marker], "a4")
    largest = printing.largest_on_one_page_mm(marker, "a4")
    assert printing.fits_one_page([printing.MarkerPrint(MarkerLayout(2), 0, largest, 1)], "a4")
    assert not printing.fits_one_page([printing.MarkerPrint(MarkerLayout(2), 0, largest + 0.1, 1)], "a4")


@pytest.mark.parametrize("out", ["/proc/companion-markers", "a-file", "a-file/below"])
def test_an_output_folder_that_cannot_be_written_is_one_line(tmp_path, capsys, out):
    (tmp_path / "a-file").write_text("")
    path = out if out.startswith("/") else str(tmp_path / out)
    assert cli.main(["markers", "--symbols", "A", "--out", path]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"companion markers: --out {path}: ") and err.count("\n") == 1, err


def test_quiet_zone_narrower_than_the_border_is_refused(tmp_path, capsys):
    assert run_markers(tmp_path, "--symbols", "A", "--quiet-zone-cells", "0") == 2
    assert "--quiet-zone-cells" in capsys.readouterr().err


@pytest.mark.parametrize("options, message", [
    (["--dpi", "inf"], "--dpi must be 72 to 4800 (what printers print at), not inf"),
    (["--dpi", "nan", "--format", "svg"], "--dpi must be 72 to 4800 (what printers print at), not nan"),
    (["--dpi", "1e-9"], "--dpi must be 72 to 4800 (what printers print at), not 1e-09"),
    (["--dpi", "20000"], "--dpi must be 72 to 4800 (what printers print at), not 20000"),
    (["--size-mm", "inf", "--format", "svg"], "--size-mm must be a positive number of millimetres (the inner black "
                                              "square's side), not inf"),
    (["--size-mm", "0.01"], "--size-mm 0.01 is too small to print: its cells would be 0.00125 mm, at least 0.25 mm "
                            "(--size-mm 2 or more for 8 cells across the inner square)"),
    (["--size-mm", "0.01", "--format", "pdf"], "--size-mm 0.01 is too small to print: its cells would be 0.00125 mm, "
                                               "at least 0.25 mm (--size-mm 2 or more for 8 cells across the inner square)"),
    (["--size-mm", "3", "--dpi", "300"], "a 3 mm marker at 300 dpi has 4.38 px per cell (at least 5): use --size-mm "
                                         "3.4 or more, or --dpi 339"),
    (["--size-mm", "10", "--dpi", "72"], "a 10 mm marker at 72 dpi has 3.5 px per cell (at least 5): use --size-mm "
                                         "14.2 or more, or --dpi 102"),
    (["--size-mm", "1e6", "--format", "svg"], "a 1000000 mm marker with 1 quiet-zone cell(s) is a 2000000 mm square SVG "
                                              "(at most 10000 mm): use a smaller --size-mm or --quiet-zone-cells"),
    (["--quiet-zone-cells", "100000", "--format", "svg"], "a 35 mm marker with 100000 quiet-zone cell(s) is a "
                                                          "875061.25 mm square SVG (at most 10000 mm): use a smaller "
                                                          "--size-mm or --quiet-zone-cells"),
])
def test_a_marker_that_cannot_be_printed_is_refused_with_the_limits(tmp_path, capsys, options, message):
    """A --dpi printers do not print at, or a marker too small for its cells to print (a 0.677 mm PNG, an 8 m
    one at 1e-9 dpi: both written before) or too large for a print, is one line naming the limit, exit 2."""
    out = tmp_path / "m"
    assert run_markers(out, "--symbols", "A", *options) == 2
    assert capsys.readouterr().err == f"companion markers: error: {message}\n"
    assert not out.exists()


def test_the_smallest_marker_and_the_dpi_limits_print(tmp_path):
    """The limits the errors name are accepted: 5 px per cell at 300 dpi, and 72 and 4800 dpi."""
    for size, dpi, inner_px in (("3.4", "300", 40), ("35", "72", 99), ("20", "4800", 3780)):
        out = tmp_path / dpi
        assert run_markers(out, "--symbols", "A", "--size-mm", size, "--dpi", dpi) == 0
        assert json.loads((out / "marker-A-p2.json").read_text())["inner_px"] == inner_px
    assert run_markers(tmp_path / "svg", "--symbols", "A", "--size-mm", "2", "--format", "svg") == 0


def test_a_charuco_board_too_small_to_print_is_refused(tmp_path, capsys):
    out = tmp_path / "board"
    assert cli.main(["markers", "--charuco", "--square-mm", "1", "--marker-mm", "0.5", "--out", str(out)]) == 2
    assert capsys.readouterr().err == ("companion markers: error: --marker-mm 0.5 is too small to print: its cells "
                                       "would be 0.0714 mm, at least 0.25 mm (--marker-mm 1.75 or more for the 7 "
                                       "cells of a DICT_5X5_100 marker)\n")
    assert not out.exists()


@pytest.mark.parametrize("options, message", [
    (["--symbols", "A", "--size-mm", "1e6"], "one 125000 mm cell does not fit one A4 page; use a smaller --size-mm"),
    (["--all", "--size-mm", "300"], "50 marker(s) of 300 mm would take 600 A4 pages (at most 500); use --format svg, "
                                    "or fewer or smaller markers"),
])
def test_a_refused_pdf_leaves_no_output_folder(tmp_path, capsys, options, message):
    """The PDF's refusals (a cell larger than the page, too many tiled pages) come before --out is made (it was
    left behind empty)."""
    out = tmp_path / "m"
    assert run_markers(out, *options, "--format", "pdf") == 2
    assert capsys.readouterr().err == f"companion markers: error: {message}\n"
    assert not out.exists()


def test_an_interrupted_run_removes_the_output_folder_it_made_and_left_empty(tmp_path, monkeypatch, capsys):
    from companion.cli import markers as markers_cli

    def interrupted(*_):
        raise KeyboardInterrupt
    monkeypatch.setattr(markers_cli, "markers_pdf", interrupted)
    assert run_markers(tmp_path / "new", "--symbols", "A", "--format", "pdf") == 130
    assert capsys.readouterr().err == "companion markers: interrupted\n"
    assert not (tmp_path / "new").exists()
    (tmp_path / "old").mkdir()
    assert run_markers(tmp_path / "old", "--symbols", "A", "--format", "pdf") == 130
    assert (tmp_path / "old").is_dir()  # a folder that was there stays


@pytest.mark.parametrize("format", ["png", "svg"])
def test_a_charuco_board_in_another_format_than_pdf_is_refused(tmp_path, capsys, format):
    """--charuco --format png wrote a PDF without saying so."""
    out = tmp_path / "board"
    assert cli.main(["markers", "--charuco", "--format", format, "--out", str(out)]) == 2
    assert capsys.readouterr().err == (f"companion markers: error: --format {format}: a --charuco board is written "
                                       "as a PDF only (leave out --format)\n")
    assert not out.exists()
    assert cli.main(["markers", "--charuco", "--format", "pdf", "--out", str(out)]) == 0
    assert [path.name for path in out.iterdir()] == ["charuco-8x11-22mm-16mm-a4.pdf"]


@pytest.mark.parametrize("parity", ["2", "4"])
def test_the_marker_figures_of_the_docs_are_what_the_generator_writes_now(tmp_path, parity):
    """docs/img/make_figures.py writes docs/img/marker-A-p*.png and .json with `companion markers`: the committed
    ones went stale once (832 px at 301.9 dpi, while docs/marker-spec.md described 826 px at 299.9994 dpi)."""
    docs = Path(__file__).resolve().parents[1] / "docs" / "img"
    assert cli.main(["markers", "--symbols", "A", "--parity", parity, "--out", str(tmp_path)]) == 0
    name = f"marker-A-p{parity}"
    assert json.loads((tmp_path / f"{name}.json").read_text()) == json.loads((docs / f"{name}.json").read_text())
    assert np.array_equal(cv2.imread(str(tmp_path / f"{name}.png")), cv2.imread(str(docs / f"{name}.png")))
