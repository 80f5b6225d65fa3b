"""Regenerate the marker figures of docs/marker-spec.md (all from the generator and the layout).

* ``marker-A-p2.png``, ``marker-A-p4.png`` (+ JSON sidecars): ``companion markers`` output.
* ``marker-layout.png``: marker A (p = 2) with its cell roles tinted and labelled
  (data, black border, white gap, row- and column-code parity bands with their
  symbol index k, corner circles in layout order, grid axes), drawn with OpenCV
  from ``MarkerLayout``.
* ``gap-comparison.png``: marker A with and without the white gap, with the
  outer contour of the border's black blob and its polygon (as ArUco
  approximates it, 3 % of the perimeter): a square with the gap, many
  corners without it.
* ``sheet-a4-p2.png``: page 1 of the A4 PDF sheet, rasterised by pdftoppm
  (skipped with a note if poppler-utils is not installed).

    PYTHONPATH=. python docs/img/make_figures.py
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np

from companion import cli
from companion.markers.layout import MarkerLayout, cell_point_to_px, marker_image

HERE = Path(__file__).resolve().parent
FONT = cv2.FONT_HERSHEY_SIMPLEX
# BGR tints of the cell roles
COLOURS = {
    "data": (60, 60, 220),
    "border": (90, 90, 90),
    "gap": (80, 200, 80),
    "row parity": (220, 120, 40),
    "column parity": (40, 160, 240),
    "circles": (200, 60, 200),
    "quiet zone": (200, 200, 200),
}


def cell_roles(layout: MarkerLayout) -> dict[str, np.ndarray]:
    """(N, N) bool masks of each cell role, from the layout's own masks and origin."""
    n, o, side = layout.n_cells, layout.inner_origin, layout.inner_cells
    rows, columns = np.mgrid[0:n, 0:n]
    inside = (rows >= o) & (rows < o + side) & (columns >= o) & (columns < o + side)
    ring = (rows >= o - layout.gap_cells) & (rows < o + side + layout.gap_cells) & \
           (columns >= o - layout.gap_cells) & (columns < o + side + layout.gap_cells) & ~inside
    parity = layout.codeword_mask & ~inside
    return {
        "data": layout.codeword_mask & inside,
        "border": layout.border_mask,
        "gap": ring & layout.white_mask,
        "row parity": parity & ((rows < o) | (rows >= o + side)),
        "column parity": parity & ((columns < o) | (columns >= o + side)),
    }


def tint(image_bgr: np.ndarray, mask_px: np.ndarray, colour, alpha: float) -> None:
    image_bgr[mask_px] = ((1 - alpha) * image_bgr[mask_px] + alpha * np.array(colour)).astype(np.uint8)


def put_text(image, text, origin, scale=0.5, colour=(0, 0, 0), thickness=1) -> None:
    cv2.putText(image, text, (int(origin[0]), int(origin[1])), FONT, scale, colour, thickness, cv2.LINE_AA)


def layout_figure(path: Path, marker_id: int = 0, ppc: int = 40) -> None:
    layout = MarkerLayout(2)
    q = 1
    n, o, side = layout.n_cells, layout.inner_origin, layout.inner_cells
    margin = 60
    marker = cv2.cvtColor(marker_image(layout, marker_id, ppc, q), cv2.COLOR_GRAY2BGR)
    cells_px = lambda mask: np.kron(np.pad(mask, q), np.ones((ppc, ppc), bool))  # noqa: E731
    for role, mask in cell_roles(layout).items():
        tint(marker, cells_px(mask), COLOURS[role], 0.55 if role != "border" else 0.3)
    quiet = cells_px(np.zeros((n, n), bool))
    quiet[:] = True
    quiet[q * ppc:(q + n) * ppc, q * ppc:(q + n) * ppc] = False
    tint(marker, quiet, COLOURS["quiet zone"], 0.5)

    legend_w = 330
    canvas = np.full((marker.shape[0] + 2 * margin, marker.shape[1] + 2 * margin + legend_w, 3), 255, np.uint8)
    canvas[margin:margin + marker.shape[0], margin:margin + marker.shape[1]] = marker
    to_canvas = lambda uv: cell_point_to_px(uv, ppc, q) + margin  # noqa: E731
    # grid lines and cell indices
    for k in range(n + 1):
        a, b = to_canvas([k, 0]) + 0.5, to_canvas([k, n]) + 0.5
        cv2.line(canvas, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), (170, 170, 170), 1)
        a, b = to_canvas([0, k]) + 0.5, to_canvas([n, k]) + 0.5
        cv2.line(canvas, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), (170, 170, 170), 1)
    origin = to_canvas([0, 0]) + 0.5  # the grid's outer top-left corner, (u, v) = (0, 0)
    for k in range(n):  # cell indices inside the quiet zone
        x, _ = to_canvas([k + 0.5, 0])
        put_text(canvas, str(k), (x - 5 * len(str(k)), origin[1] - 12), 0.45, (60, 60, 60))
        _, y = to_canvas([0, k + 0.5])
        put_text(canvas, str(k), (origin[0] - 8 - 9 * len(str(k)), y + 5), 0.45, (60, 60, 60))
    corner = (int(origin[0]) - ppc * q, int(origin[1]) - ppc * q - 12)
    cv2.arrowedLine(canvas, corner, (corner[0] + 80, corner[1]), (0, 0, 0), 1, cv2.LINE_AA, tipLength=0.15)
    put_text(canvas, "u", (corner[0] + 86, corner[1] + 5), 0.55)
    corner = (int(origin[0]) - ppc * q - 12, int(origin[1]) - ppc * q)
    cv2.arrowedLine(canvas, corner, (corner[0], corner[1] + 80), (0, 0, 0), 1, cv2.LINE_AA, tipLength=0.15)
    put_text(canvas, "v", (corner[0] - 5, corner[1] + 100), 0.55)
    # parity symbol index k on each band cell row/column
    for k in range(layout.parity):
        for index in (layout.parity - 1 - k, n - layout.parity + k):
            x, y = to_canvas([o - 0.5, index + 0.5])
            put_text(canvas, f"k{k}", (x - 9, y + 5), 0.4, (0, 0, 0))
            x, y = to_canvas([index + 0.5, o - 0.5])
            put_text(canvas, f"k{k}", (x - 9, y + 5), 0.4, (0, 0, 0))
    # circles in layout order
    for i, (u, v, radius) in enumerate(layout.circles):
        x, y = to_canvas([u, v])
        cv2.circle(canvas, (int(round(x)), int(round(y))), int(round(radius * ppc)) + 2, COLOURS["circles"], 2,
                   cv2.LINE_AA)
        put_text(canvas, str(i), (x - 5 * len(str(i)), y + 5), 0.45, (255, 255, 255), 1)

    x0 = margin + marker.shape[1] + 30
    y = margin + 10
    put_text(canvas, f"RS marker A, p = {layout.parity}: {n} x {n} cells", (x0, y), 0.55, thickness=1)
    y += 22
    put_text(canvas, f"+ {q}-cell quiet zone = {n + 2 * q} x {n + 2 * q}", (x0, y), 0.5)
    y += 32
    legend = [
        ("data", "6 x 6 data (ArUco bits)"),
        ("border", "black border (inner square:"),
        (None, f"  cells {o}..{o + side}, size_m = 8 cells)"),
        ("gap", "white gap (1 cell)"),
        ("row parity", "row-code parity rows,"),
        (None, "  k = symbol index, top + bottom"),
        ("column parity", "column-code parity columns,"),
        (None, "  left + right copies"),
        ("circles", "corner circles 0-11 (layout order:"),
        (None, "  TL large, top, left; TR; BR; BL)"),
        ("quiet zone", "white quiet zone"),
    ]
    for role, text in legend:
        if role is not None:
            cv2.rectangle(canvas, (x0, y - 14), (x0 + 18, y + 4), COLOURS[role], -1)
            cv2.rectangle(canvas, (x0, y - 14), (x0 + 18, y + 4), (0, 0, 0), 1)
        put_text(canvas, text, (x0 + 28, y), 0.48)
        y += 26
    cv2.imwrite(str(path), canvas)


def border_contour(image: np.ndarray, layout: MarkerLayout, ppc: int, q: int) -> tuple[np.ndarray, np.ndarray]:
    """Outer contour of the black blob holding the inner square's border, and its ArUco-style polygon."""
    _, black = cv2.threshold(image, 127, 255, cv2.THRESH_BINARY_INV)
    contours, _ = cv2.findContours(black, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    probe = cell_point_to_px([layout.inner_origin + 0.5, layout.inner_origin + 0.5], ppc, q)
    contour = next(c for c in contours if cv2.pointPolygonTest(c, tuple(map(float, probe)), False) >= 0)
    # ArUco's DetectorParameters.polygonalApproxAccuracyRate default: 0.03 of the perimeter
    polygon = cv2.approxPolyDP(contour, 0.03 * cv2.arcLength(contour, True), True)
    return contour, polygon


def gap_figure(path: Path, marker_id: int = 0, ppc: int = 24) -> None:
    panels = []
    for gap_cells, title in ((1, "with the white gap"), (0, "without the gap")):
        layout = MarkerLayout(2, gap_cells=gap_cells)
        image = marker_image(layout, marker_id, ppc, 1)
        contour, polygon = border_contour(image, layout, ppc, 1)
        panel = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        colour = (40, 170, 40) if len(polygon) == 4 else (40, 40, 220)
        cv2.drawContours(panel, [contour], -1, colour, 3, cv2.LINE_AA)
        for x, y in polygon.reshape(-1, 2):
            cv2.circle(panel, (int(x), int(y)), 6, (220, 80, 0), -1, cv2.LINE_AA)
        header = np.full((70, panel.shape[1], 3), 255, np.uint8)
        put_text(header, f"{title} ({layout.n_cells} x {layout.n_cells})", (10, 28), 0.6)
        put_text(header, f"border blob polygon: {len(polygon)} corners", (10, 56), 0.55, colour)
        panels.append(np.vstack([header, panel]))
    height = max(p.shape[0] for p in panels)
    padded = [cv2.copyMakeBorder(p, 0, height - p.shape[0], 10, 10, cv2.BORDER_CONSTANT, value=(255, 255, 255))
              for p in panels]
    cv2.imwrite(str(path), np.hstack(padded))


def sheet_figure(path: Path) -> None:
    if shutil.which("pdftoppm") is None:
        print(f"pdftoppm not found (apt-get install poppler-utils): {path.name} not regenerated")
        return
    with tempfile.TemporaryDirectory() as tmp:
        cli.main(["markers", "--all", "--format", "pdf", "--out", tmp])
        (pdf,) = Path(tmp).glob("*.pdf")
        subprocess.run(["pdftoppm", "-r", "60", "-gray", "-png", "-f", "1", "-l", "1", "-singlefile",
                        str(pdf), str(path.with_suffix(""))], check=True)


def main() -> None:
    for parity in ("2", "4"):
        cli.main(["markers", "--symbols", "A", "--parity", parity, "--out", str(HERE)])
    layout_figure(HERE / "marker-layout.png")
    gap_figure(HERE / "gap-comparison.png")
    sheet_figure(HERE / "sheet-a4-p2.png")


if __name__ == "__main__":
    main()
