"""A tiny PDF writer for vector marker sheets: filled rectangles and circles, lines, Helvetica text.

Pages are drawn in millimetres from the page's top-left corner, y down (like
the marker grid); the writer converts to PDF points (1 mm = 72 / 25.4 pt)
with y up from the bottom-left corner. Content streams are uncompressed so the
output stays readable and checkable. Helvetica is one of the 14 standard
fonts: no embedding. Only ASCII text is supported.
"""
from __future__ import annotations

from dataclasses import dataclass, field

PT_PER_MM = 72.0 / 25.4
# Control-point distance of a cubic Bezier quarter circle, as a fraction of the radius:
# kappa = 4 (sqrt(2) - 1) / 3
BEZIER_KAPPA = 4.0 * (2.0 ** 0.5 - 1.0) / 3.0


class PdfError(ValueError):
    """Something the tiny writer cannot draw (non-ASCII text, empty document)."""


def fmt(value: float) -> str:
    """A PDF number: up to 4 decimals (1e-4 pt = 35 nm), no trailing zeros, no '-0'."""
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def pdf_string(text: str) -> str:
    """A PDF literal string: ( ) and \\ escaped."""
    if not text.isascii():
        raise PdfError(f"only ASCII text is supported, got {text!r}")
    return "(" + text.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)") + ")"


@dataclass
class PdfPage:
    """One page's drawing commands; coordinates in mm from the top-left corner, y down."""

    width_mm: float
    height_mm: float
    ops: list[str] = field(default_factory=list)

    def _x(self, x_mm: float) -> str:
        return fmt(x_mm * PT_PER_MM)

    def _y(self, y_mm: float) -> str:
        return fmt((self.height_mm - y_mm) * PT_PER_MM)

    def begin_group(self) -> None:
        """Save the graphics state (PDF ``q``); ``end_group`` restores it."""
        self.ops.append("q")

    def end_group(self) -> None:
        self.ops.append("Q")

    def rect(self, x_mm: float, y_mm: float, width_mm: float, height_mm: float) -> None:
        """Add a rectangle (top-left corner x, y) to the current path; ``fill`` paints it."""
        # PDF "re" takes the lower-left corner and a positive height upward.
        self.ops.append(f"{self._x(x_mm)} {self._y(y_mm + height_mm)} "
                        f"{fmt(width_mm * PT_PER_MM)} {fmt(height_mm * PT_PER_MM)} re")

    def circle(self, cx_mm: float, cy_mm: float, radius_mm: float) -> None:
        """Add a circle to the current path as four cubic Bezier quarter arcs."""
        r, k = radius_mm, BEZIER_KAPPA * radius_mm
        # start at the rightmost point, go round through bottom, left, top (y down)
        self.ops.append(f"{self._x(cx_mm + r)} {self._y(cy_mm)} m")
        arcs = (((r, k), (k, r), (0, r)), ((-k, r), (-r, k), (-r, 0)),
                ((-r, -k), (-k, -r), (0, -r)), ((k, -r), (r, -k), (r, 0)))
        for arc in arcs:
            points = " ".join(f"{self._x(cx_mm + dx)} {self._y(cy_mm + dy)}" for dx, dy in arc)
            self.ops.append(f"{points} c")
        self.ops.append("h")

    def fill(self, gray: float = 0.0) -> None:
        """Fill the current path (nonzero winding) with a gray level (0 black, 1 white)."""
        self.ops.append(f"{fmt(gray)} g f")

    def line(self, x0_mm: float, y0_mm: float, x1_mm: float, y1_mm: float, width_mm: float = 0.1) -> None:
        """Stroke a black line segment."""
        self.ops.append(f"0 G {fmt(width_mm * PT_PER_MM)} w {self._x(x0_mm)} {self._y(y0_mm)} m "
                        f"{self._x(x1_mm)} {self._y(y1_mm)} l S")

    def text(self, x_mm: float, baseline_mm: float, text: str, size_pt: float = 7.0) -> None:
        """Black Helvetica text starting at x with its baseline at ``baseline_mm``."""
        self.ops.append(f"BT 0 g /F1 {fmt(size_pt)} Tf {self._x(x_mm)} {self._y(baseline_mm)} Td "
                        f"{pdf_string(text)} Tj ET")

    def content(self) -> bytes:
        return ("\n".join(self.ops) + "\n").encode("ascii")


def text_width_mm(text: str, size_pt: float) -> float:
    """Upper bound of Helvetica text width: 0.6 em per character (its widest common glyphs)."""
    return len(text) * 0.6 * size_pt / PT_PER_MM


def write_pdf(pages: list[PdfPage], title: str = "") -> bytes:
    """A complete PDF 1.4 file of ``pages`` with a correct cross-reference table."""
    if not pages:
        raise PdfError("a PDF needs at least one page")
    n_pages = len(pages)
    # object numbers: 1 catalog, 2 page tree, 3 font, 4 info, then (page, content) pairs
    page_ids = [5 + 2 * i for i in range(n_pages)]
    objects: dict[int, bytes] = {
        1: b"<< /Type /Catalog /Pages 2 0 R >>",
        2: (f"<< /Type /Pages /Count {n_pages} /Kids [" + " ".join(f"{i} 0 R" for i in page_ids) + "] >>").encode(),
        3: b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        4: f"<< /Title {pdf_string(title)} /Producer (companion markers) >>".encode(),
    }
    for page_id, page in zip(page_ids, pages):
        box = f"[0 0 {fmt(page.width_mm * PT_PER_MM)} {fmt(page.height_mm * PT_PER_MM)}]"
        objects[page_id] = (f"<< /Type /Page /Parent 2 0 R /MediaBox {box} "
                            f"/Resources << /Font << /F1 3 0 R >> >> /Contents {page_id + 1} 0 R >>").encode()
        stream = page.content()
        objects[page_id + 1] = b"<< /Length %d >>\nstream\n" % len(stream) + stream + b"endstream"

    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = {}
    for number in sorted(objects):
        offsets[number] = len(out)
        out += b"%d 0 obj\n" % number + objects[number] + b"\nendobj\n"
    xref_offset = len(out)
    size = max(objects) + 1
    out += b"xref\n0 %d\n0000000000 65535 f \n" % size
    for number in range(1, size):
        out += b"%010d 00000 n \n" % offsets[number]  # every entry is exactly 20 bytes
    out += b"trailer\n<< /Size %d /Root 1 0 R /Info 4 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (size, xref_offset)
    return bytes(out)
