"""Detector stage: the occluded path. Corner circles -> marker grids, when the border is broken.

Each corner of an RS marker carries one large circle and two small ones
(``MarkerLayout.circles``): the small ones sit two cells from the large one
along the two grid edges, with half its radius. A marker whose black border
is hidden (a strip over one side, a corner patch) still shows at least two
corners, so at least six circles, which fix the grid homography.

1. ``find_frame_blobs``: at a pyramid level (``blob_level``: half
   resolution by default, ``reduce``), one local-mean threshold inside
   OpenCV, a table of the dark blobs (outer contours reduced with vectorised
   numpy, or OpenCV's connected components on speckled frames) with their
   moment ellipses, vectorised filters on it (area, elongation, fill of the
   ellipse) and a ring of 8 samples on the ellipse around each blob (a circle
   is a dark, compact spot on white paper: the ring is bright all round, and
   the spot is much darker than the ring). No per-blob Python loop.
2. ``corner_triples``: (large, small, small) blobs at the layout's relative
   positions and size ratio, oriented by the handedness of the printed face.
3. ``assemble_candidates``: from each triple (called corner 0; the decoder
   resolves the true rotation), the other corners' circles are predicted and
   matched blob by blob, so a corner that lost a small circle still counts.
4. The detector then reads each candidate's circle centres again in the
   frame (``refine_centres``), fits the homography to them, refines it
   on the inner square's visible edges (``edges``), and samples and
   decodes the grid with erasures where the image shows no marker
   (``missing_corner_cells``, ``sampling.erase_near_bad_fixed_cells``).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from companion.detect import homography, sampling
from companion.markers.layout import MarkerLayout
from companion.params import require

RING_ANGLES = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
RING_DIRECTIONS = np.stack([np.cos(RING_ANGLES), np.sin(RING_ANGLES)], axis=1)
# a blob whose box ellipse is turned less than this (correlation) is tested one way only
MIN_TESTED_TURN = 0.3
PIXEL_VARIANCE_PX2 = 1.0 / 12.0  # of a uniform unit square along each axis
CENTROID_OFFSETS = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), axis=-1).reshape(-1, 2)
MAX_LENGTH_PER_SQRT_AREA = 6.0  # boundary pixels of a compact blob over the root of its area (with a margin)


CIRCLES_RUN_MODES = ("always", "when_square_empty", "never")
BLOB_METHODS = ("auto", "contours", "components")


@dataclass(frozen=True)
class CircleParams:
    """The occluded (corner circles) path: when it runs, blob finding, grouping and fit checks.

    run: "always" (in every frame, over what the markers found by the square
        path do not explain), "when_square_empty" (only in frames where the
        square path found nothing), or "never".

    expected_margin_fraction: with the markers' expected places given
        (``Detector.detect``'s ``expected_px``: the daemon's prediction from its
        pose and the map), the window searched around each expected marker the
        square path did not find: its whole printed grid's bounding box grown
        by this share of its larger side on every side (the prediction's error).

    Blobs (looked for at a pyramid level, see ``blob_level``; sizes are in frame pixels):
    min_side_px: the smallest marker (inner-square side, pixels) the
        path looks for: circles are searched at the coarsest pyramid level at
        which it keeps ``min_level_side_px`` (20 and 20: full resolution; 40
        would search at half resolution, a quarter of the pixels, where the
        small circles of 40-50 px markers start to merge with the large ones).
    min_side_beside_found_px: the same, in a frame-wide search of a frame
        where the square path has found a marker (no expected places given):
        40 searches for the other, occluded markers at half resolution, half
        the cost (a 28 px oblique marker beside a clean one was still found
        there); the daemon, which passes expected places, searches its
        windows at ``min_side_px``.
    search_beside_aruco: with OpenCV on two threads or more, run the
        frame-wide search (at ``min_side_px``) while ArUco runs on a second
        thread, before it is known whether the square path finds a marker.
    threshold_block_px, threshold_offset_gray, threshold_ratio: a pixel is
        dark when below both mean - offset and mean x ratio over the window.
    pre_blur: 3 x 3 box blur before thresholding (fewer noise specks, but
        merges circles with their neighbours on oblique markers; off: the
        ring test removes the specks).
    blob_method: "components" (OpenCV's 16-bit connected components with
        statistics; each blob's ellipse from its bounding box and area, its
        turn's sign tried both ways), "contours" (outer contours, statistics
        vectorised over the concatenated points; each blob's own moment
        ellipse; 4-5x slower on noisy frames, whose thousands of specks each
        become a Python array), or "auto": contours unless more than
        ``max_speck_fraction`` of the pixels are isolated specks (what a
        3 x 3 median removes; under 0.8 % on ordinary frames, over 1.6 % on
        noisy ones). Components by default: the benchmark finds the same
        markers either way, and its one OpenCV call leaves the interpreter
        to the square path on the other thread (docs/detector.md,
        "Decisions").
    max_blobs: keep at most this many blobs (the darkest), a bound on the
        work a speckled texture causes (a marker has 12 circles).
    min_area_px: smallest blob (a small circle of a 40 px marker is ~12 px).
    max_area_fraction: largest blob, as a share of the image.
    max_aspect: elongation allowed, the ratio of the axes of the blob's
        moment ellipse (tilted or smeared circles are ellipses).
    min_fill: blob area over the area of its moment ellipse (about 1 for an
        ellipse, less for a ring, a cross or an L).
    ring_scale, ring_margin_px: the test ring: ring_scale x the blob's
        moment ellipse (to the region's edge), + ring_margin_px (level pixels).
    ring_dark_allowed: ring samples (of 8) allowed to be dark (a neighbour,
        the paper's edge).
    ring_dark_contrast_fraction: a ring sample is dark when less than this
        share of the blob's contrast (ring median - centre) above the centre.
    max_darkness_ratio: blob centre over the ring's median intensity (black
        ink on white paper is far below 1; sensor-noise specks are not).
    min_ring_contrast_gray: ring median - centre, gray levels.

    Corner triples (a large circle and its two small ones):
    max_triples: at most this many per frame (the most corner-like): eight
        markers' worth, and a bound on the work a dotted texture can cause.
    area_ratio_tolerance: a (large, small) pair's area ratio within this
        factor of the layout's.
    min_arm_fraction, max_arm_fraction: their distance within these
        multiples of the layout's (large radius x spacing).
    max_arm_cos: |cos| of the angle between the two arms (90 deg: 0).
    max_arm_ratio, max_small_area_ratio: the two arms' lengths, and the two
        small circles' areas, within these factors of each other.

    Candidates (corners grown from a triple; see ``assemble_candidates``):
    min_circles: circles a candidate needs (on at least ``min_corners`` corners).
    min_corners: corners with at least two circles a candidate needs.
    first_triple_window_cells, triple_window_cells: a whole triple joins if its
        circles lie on average within this of their predictions (the first
        while only the anchor corner is known, then the second).
    first_large_window_cells, large_window_cells, small_window_cells: else
        circle by circle: the large circle within the first (while only the
        anchor corner is known) or the second, the small ones within the third.
    min_radius_ratio, max_radius_ratio: a blob's radius over the predicted circle's.
    min_circles_for_homography: below this many circles the grid map is
        affine (a homography's perspective terms are poorly pinned by 4-5
        circles, three of them in one corner).
    max_fit_error_cells: RMS misfit of the circles to one homography.

    Fit checks (the detector):
    min_fixed_agreement_fraction: a candidate's border cells read black and
        its gap-ring cells white, at one sample per cell, in this share.
    max_edge_fit_rms_cells: RMS misfit of the edge-refined homography.
    """

    run: str = "always"
    expected_margin_fraction: float = 0.5
    min_side_px: float = 20.0
    min_side_beside_found_px: float = 40.0
    search_beside_aruco: bool = True
    min_level_side_px: float = 20.0
    threshold_block_px: int = 31
    threshold_offset_gray: float = 7.0
    threshold_ratio: float = 0.75
    pre_blur: bool = False
    blob_method: str = "components"
    max_speck_fraction: float = 0.01
    max_blobs: int = 300
    min_area_px: int = 5
    max_area_fraction: float = 0.01
    max_aspect: float = 4.0
    min_fill: float = 0.6
    ring_scale: float = 1.4
    ring_margin_px: float = 0.5
    ring_dark_allowed: int = 2
    ring_dark_contrast_fraction: float = 0.5
    max_darkness_ratio: float = 0.7
    min_ring_contrast_gray: float = 10.0
    max_triples: int = 32
    area_ratio_tolerance: float = 2.5
    min_arm_fraction: float = 0.45
    max_arm_fraction: float = 1.8
    max_arm_cos: float = 0.8
    max_arm_ratio: float = 3.0
    max_small_area_ratio: float = 2.5
    min_circles: int = 5
    min_corners: int = 2
    first_triple_window_cells: float = 4.0
    triple_window_cells: float = 1.0
    first_large_window_cells: float = 3.0
    large_window_cells: float = 1.1
    small_window_cells: float = 0.7
    min_radius_ratio: float = 0.4
    max_radius_ratio: float = 2.5
    min_circles_for_homography: int = 6
    max_fit_error_cells: float = 0.3
    min_fixed_agreement_fraction: float = 0.6
    max_edge_fit_rms_cells: float = 0.15

    def __post_init__(self):
        require(self.run in CIRCLES_RUN_MODES, "run", f"one of {', '.join(CIRCLES_RUN_MODES)}", self.run)
        require(self.blob_method in BLOB_METHODS, "blob_method", f"one of {', '.join(BLOB_METHODS)}",
                self.blob_method)
        require(self.threshold_block_px >= 3 and self.threshold_block_px % 2 == 1, "threshold_block_px",
                "an odd integer >= 3", self.threshold_block_px)
        require(0 <= self.ring_dark_allowed <= 7, "ring_dark_allowed", "in [0, 7]", self.ring_dark_allowed)
        require(self.min_corners in (2, 3, 4), "min_corners", "2, 3 or 4", self.min_corners)
        require(4 <= self.min_circles_for_homography <= 12, "min_circles_for_homography", "in [4, 12]",
                self.min_circles_for_homography)
        for key in ("min_side_px", "min_side_beside_found_px"):
            require(getattr(self, key) >= self.min_level_side_px > 0, key,
                    f">= min_level_side_px ({self.min_level_side_px}) > 0", getattr(self, key))
        for key in ("expected_margin_fraction", "threshold_offset_gray", "min_area_px", "ring_margin_px", "min_ring_contrast_gray"):
            require(getattr(self, key) >= 0, key, ">= 0", getattr(self, key))
        for key in ("threshold_ratio", "max_speck_fraction", "max_area_fraction", "min_fill",
                    "ring_dark_contrast_fraction", "max_darkness_ratio", "min_arm_fraction",
                    "max_arm_cos", "min_radius_ratio", "min_fixed_agreement_fraction"):
            require(0.0 <= getattr(self, key) <= 1.0, key, "in [0, 1]", getattr(self, key))
        for key in ("max_aspect", "ring_scale", "area_ratio_tolerance", "max_arm_fraction", "max_arm_ratio",
                    "max_small_area_ratio", "max_radius_ratio"):
            require(getattr(self, key) >= 1.0, key, ">= 1", getattr(self, key))
        for key in ("max_blobs", "max_triples", "min_circles"):
            require(getattr(self, key) >= 1, key, ">= 1", getattr(self, key))
        for key in ("first_triple_window_cells", "triple_window_cells", "first_large_window_cells",
                    "large_window_cells", "small_window_cells",
                    "max_fit_error_cells", "max_edge_fit_rms_cells"):
            require(getattr(self, key) > 0, key, "> 0", getattr(self, key))


@dataclass(frozen=True)
class Blobs:
    """Circle-like dark blobs, in full-resolution pixels.

    centres_px: (M, 2) float64 centroids; areas_px: (M,) float64.
    """

    centres_px: np.ndarray
    areas_px: np.ndarray

    def __len__(self) -> int:
        return len(self.areas_px)

    def subset(self, keep: np.ndarray) -> "Blobs":
        return Blobs(self.centres_px[keep], self.areas_px[keep])


@dataclass(frozen=True)
class _BlobTable:
    """Every dark region of a binary image: centres (K, 2), areas (K,) in pixels, and the second central
    moments (K, 3) = (var x, var y, cov xy) in px^2 of the region's shape."""

    centres: np.ndarray
    areas: np.ndarray
    moments: np.ndarray

    def subset(self, keep: np.ndarray) -> "_BlobTable":
        return _BlobTable(self.centres[keep], self.areas[keep], self.moments[keep])


def blob_level(params: CircleParams, min_side_px: float | None = None) -> int:
    """The pyramid level (0: full resolution, k: 2^k smaller) blobs are looked for at: the coarsest at which
    the smallest marker looked for (``min_side_px``, default ``params.min_side_px``) keeps ``min_level_side_px``."""
    min_side_px = params.min_side_px if min_side_px is None else min_side_px
    return max(int(np.floor(np.log2(min_side_px / params.min_level_side_px))), 0)


def find_frame_blobs(gray: np.ndarray, params: CircleParams, min_side_px: float | None = None) -> Blobs:
    """The blobs of an (H, W) uint8 frame, looked for at the pyramid level ``blob_level`` (in frame pixels)."""
    scale = 2 ** blob_level(params, min_side_px)
    return find_blobs(reduce(gray, scale), params, scale)


def find_window_blobs(gray: np.ndarray, boxes_px: np.ndarray, params: CircleParams) -> Blobs:
    """The blobs of an (H, W) uint8 frame inside the windows ``boxes_px`` (B, 4) int (x0, y0, x1, y1),
    clipped to the frame; overlapping windows are searched as one (their bounding box). Sizes are
    judged against the whole frame, as ``find_frame_blobs`` does."""
    scale = 2 ** blob_level(params)
    height, width = gray.shape
    boxes = [box for box in _merged_boxes(np.clip(np.asarray(boxes_px, np.int64).reshape(-1, 4),
                                                  0, [width, height, width, height]))
             if box[2] - box[0] >= 2 * scale and box[3] - box[1] >= 2 * scale]
    found = []
    for x0, y0, x1, y1 in boxes:
        x0, y0 = x0 // scale * scale, y0 // scale * scale  # the window on the level's pixel grid
        blobs = find_blobs(reduce(gray[y0:y1, x0:x1], scale), params, scale, frame_pixels=gray.size / scale ** 2)
        found.append(Blobs(blobs.centres_px + [x0, y0], blobs.areas_px))
    if not found:
        return Blobs(np.zeros((0, 2)), np.zeros(0))
    return Blobs(np.concatenate([b.centres_px for b in found]), np.concatenate([b.areas_px for b in found]))


def _merged_boxes(boxes: np.ndarray) -> list[np.ndarray]:
    """Boxes (B, 4) (x0, y0, x1, y1) with every group of overlapping ones replaced by its bounding box."""
    merged = [box.copy() for box in boxes if box[2] > box[0] and box[3] > box[1]]
    joined = True
    while joined:
        joined = False
        for a, b in itertools.combinations(range(len(merged)), 2):
            first, second = merged[a], merged[b]
            if first[0] < second[2] and second[0] < first[2] and first[1] < second[3] and second[1] < first[3]:
                merged[a] = np.r_[np.minimum(first[:2], second[:2]), np.maximum(first[2:], second[2:])]
                del merged[b]
                joined = True
                break
    return merged


def find_blobs(level_image: np.ndarray, params: CircleParams, scale: int = 1,
               frame_pixels: float | None = None) -> Blobs:
    """Dark, compact blobs on bright surroundings.

    level_image: (h, w) uint8, the frame (or a window of it) reduced ``scale`` times (``reduce``); the
    parameters are in frame pixels. frame_pixels: the whole frame's pixel count at the level (the
    largest blob is a share of it; default: the image's). Returns the blobs in pixels of the image
    given, at full resolution (centres to a few tenths of a level pixel; ``refine_centres`` reads the frame).
    """
    smooth = cv2.blur(level_image, (3, 3)) if params.pre_blur else level_image
    binary = dark_pixels(smooth, params, scale)
    max_area_px = params.max_area_fraction * (level_image.size if frame_pixels is None else frame_pixels)
    min_area_px = params.min_area_px / scale ** 2
    contours = _use_contours(binary, params)
    if contours:
        # a contour of one or two points is a speck or a straight run of k + 1 pixels; the run passes the
        # elongation test below only while its variance along, k^2 / 4 + 1/12, is at most max_aspect^2 / 12
        # (across: 1/12): so none of them where blobs need more pixels than the longest such run has
        longest_run_px = 1 + np.floor(np.sqrt((params.max_aspect ** 2 - 1) / 3))
        table = _contour_table(binary, max_area_px, min_points=3 if min_area_px > longest_run_px else 1)
    else:
        table = _component_table(binary)
    var_x, var_y, cov = table.moments.T
    # eigenvalues of the shape's covariance: its squared half axes / 4 for a filled ellipse
    half_sum, half_diff = (var_x + var_y) / 2, np.hypot((var_x - var_y) / 2, cov)
    major, minor = half_sum + half_diff, half_sum - half_diff
    with np.errstate(invalid="ignore", divide="ignore"):
        # fill: area over the area of the ellipse of the same moments (pi a b = 4 pi sqrt(major minor))
        shape_ok = ((table.areas >= min_area_px)
                    & (table.areas <= max_area_px)
                    & (minor > 0) & (major <= params.max_aspect ** 2 * minor)
                    & (table.areas >= params.min_fill * 4 * np.pi * np.sqrt(major * minor)))
    table = table.subset(shape_ok)
    # a contour gives the turn of a blob; a component's box only its size (the ring test tries both signs)
    passed, darkness = (_ring_test if contours else _ring_test_either_turn)(smooth, table, params)
    keep = np.flatnonzero(passed)
    if len(keep) > params.max_blobs:
        # a speckled texture: keep the darkest spots (relative to their rings), a bound on later work
        keep = np.sort(keep[np.argsort(darkness[keep], kind="stable")[:params.max_blobs]])
    return Blobs(to_frame_px(table.centres[keep], scale), table.areas[keep] * scale ** 2)


def reduce(gray: np.ndarray, scale: int) -> np.ndarray:
    """The frame averaged over scale x scale blocks (``cv2.INTER_AREA``; a copy a scale^2-th of its size).

    Averaging keeps a small circle's contrast better than a Gaussian pyramid step."""
    if scale == 1:
        return gray
    return cv2.resize(gray, (gray.shape[1] // scale, gray.shape[0] // scale), interpolation=cv2.INTER_AREA)


def to_frame_px(level_px: np.ndarray, scale: int) -> np.ndarray:
    """(..., 2) positions in a ``reduce``d image -> frame pixels (level pixel i averages frame pixels
    scale i .. scale i + scale - 1)."""
    return level_px * scale + (scale - 1) / 2


def dark_pixels(gray: np.ndarray, params: CircleParams, scale: int = 1) -> np.ndarray:
    """(H, W) uint8 255 where a pixel is darker than its neighbourhood.

    Darker than both mean - offset and mean x ratio over a square window
    (``threshold_block_px`` frame pixels, at ``scale``): the offset keeps dim,
    low-contrast frames working, the ratio shrinks blobs on bright paper to
    their dark cores, so circles close to cells stay apart. Two images of
    the frame's size are made (a large frame is not copied more).
    """
    block = max(int(params.threshold_block_px / scale) // 2 * 2 + 1, 3)
    limit = cv2.blur(gray, (block, block))
    scaled = cv2.convertScaleAbs(limit, alpha=params.threshold_ratio)
    cv2.subtract(limit, params.threshold_offset_gray, dst=limit)
    cv2.min(limit, scaled, dst=limit)
    return cv2.compare(gray, limit, cv2.CMP_LT, dst=scaled)


def _use_contours(binary: np.ndarray, params: CircleParams) -> bool:
    if params.blob_method != "auto":
        return params.blob_method == "contours"
    specks = cv2.medianBlur(binary, 3)
    cv2.absdiff(binary, specks, dst=specks)
    return cv2.countNonZero(specks) <= params.max_speck_fraction * binary.size


def _contour_table(binary: np.ndarray, max_area_px: float, min_points: int = 1) -> _BlobTable:
    """The blobs of the binary image from their outer contours, vectorised.

    Contours of fewer than ``min_points`` compressed points are left out (specks). Contours (OpenCV's, straight runs of boundary pixels compressed to their
    ends) longer than a blob of ``max_area_px`` can be (a 1:4 ellipse of that
    area has a perimeter of 5.2 sqrt(area); edges and large regions of
    clutter are most of the points) are dropped first; the others are
    concatenated once and reduced segment-wise (one ``np.add.reduceat``), so
    the cost per contour is one array in a list, not a Python loop of OpenCV
    calls. Area: the pixel count of the region, from the polygon through its
    boundary pixels by Pick's theorem (A + B / 2 + 1, B the boundary pixels:
    the longer coordinate step of each run); centre and second moments: the
    polygon's (Green's theorem), its vertices' for a polygon of no area.
    """
    # two levels: every blob's outer boundary (even a blob inside another's hole), and the holes
    contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return _BlobTable(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)))
    lengths = np.fromiter(map(len, contours), np.intp, len(contours))
    kept = np.flatnonzero((hierarchy[0, :, 3] < 0) & (lengths >= min_points)
                          & (lengths <= MAX_LENGTH_PER_SQRT_AREA * np.sqrt(max_area_px)))
    if len(kept) == 0:
        return _BlobTable(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)))
    contours, lengths = [contours[i] for i in kept], lengths[kept]
    # (2, P): x and y each contiguous (every elementwise step below runs over unit-stride rows)
    x, y = np.concatenate(contours).reshape(-1, 2).T.astype(np.float64)
    ends = np.cumsum(lengths)
    starts = ends - lengths
    following = np.arange(1, len(x) + 1)
    following[ends - 1] = starts  # each contour is closed
    xn, yn = x[following], y[following]
    cross = x * yn - xn * y
    # polygon moments (Green): m00 = sum(c) / 2, m10 = sum((x + x') c) / 6,
    # m20 = sum((x^2 + x x' + x'^2) c) / 12, m11 = sum((2 x y + x y' + x' y + 2 x' y') c) / 24;
    # the boundary pixels of each run, max(|x' - x|, |y' - y|); and the vertices' sums (for flat ones)
    # (12, P), one row per term, summed along the rows (a (P, 12) table cost twice as much to fill)
    terms = np.stack([cross, (x + xn) * cross, (y + yn) * cross, (x * x + x * xn + xn * xn) * cross,
                      (y * y + y * yn + yn * yn) * cross, (2 * x * y + x * yn + xn * y + 2 * xn * yn) * cross,
                      np.maximum(np.abs(xn - x), np.abs(yn - y)), x, y, x * x, y * y, x * y])
    m00, m10, m01, m20, m02, m11, boundary, sx, sy, sxx, syy, sxy = np.add.reduceat(terms, starts, axis=1)
    polygon_area = m00 / 2
    flat = np.abs(polygon_area) < 0.5  # a line or a single pixel: its vertices' mean and spread
    polygon_area[flat] = np.nan
    cx = np.where(flat, sx / lengths, m10 / (6 * polygon_area))
    cy = np.where(flat, sy / lengths, m01 / (6 * polygon_area))
    var_x = np.where(flat, sxx / lengths, m20 / (12 * polygon_area)) - cx * cx
    var_y = np.where(flat, syy / lengths, m02 / (12 * polygon_area)) - cy * cy
    cov = np.where(flat, sxy / lengths, m11 / (24 * polygon_area)) - cx * cy
    polygon_area[flat] = 0.0
    # the polygon runs through the boundary pixels' centres: each pixel's own spread (1/12 px^2) on top
    moments = np.column_stack([var_x + PIXEL_VARIANCE_PX2, var_y + PIXEL_VARIANCE_PX2, cov])
    area = np.abs(polygon_area) + boundary / 2 + 1
    return _BlobTable(np.column_stack([cx, cy]), area, moments)


def _component_table(binary: np.ndarray) -> _BlobTable:
    """The same table from OpenCV's connected components with statistics (16-bit labels, 2-3x faster
    than 32-bit; 32-bit when a frame has more than 65534 components); each blob's moments those of the
    ellipse with its bounding box and its area, turned by a positive angle (the box does not say which
    way: cov xy >= 0)."""
    try:
        _, _, stats, centroids = cv2.connectedComponentsWithStatsWithAlgorithm(binary, 8, cv2.CV_16U, cv2.CCL_DEFAULT)
    except cv2.error:
        _, _, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    w, h = stats[1:, 2].astype(np.float64), stats[1:, 3].astype(np.float64)
    area = stats[1:, 4].astype(np.float64)
    # an ellipse through the boundary pixels' centres, of moments S: its box's half widths 2 sqrt(S_xx),
    # 2 sqrt(S_yy), (w - 1) / 2 and (h - 1) / 2; its area 4 pi sqrt(det S) = the blob's, so that
    # S_xy^2 = S_xx S_yy - (area / 4 pi)^2 (0 for a blob that fills at least an upright ellipse)
    var_x, var_y = (w - 1) ** 2 / 16, (h - 1) ** 2 / 16
    cov = np.sqrt(np.maximum(var_x * var_y - (area / (4 * np.pi)) ** 2, 0.0))
    moments = np.column_stack([var_x + PIXEL_VARIANCE_PX2, var_y + PIXEL_VARIANCE_PX2, cov])
    return _BlobTable(centroids[1:], area, moments)


def _ring_test(smooth: np.ndarray, table: _BlobTable, params: CircleParams) -> tuple[np.ndarray, np.ndarray]:
    """(M,) bool: the blob centre is much darker than a bright ring around it; (M,) centre / ring median.

    The ring follows the blob's shape: ``ring_scale`` times the ellipse of its moments (half a pixel
    out, to the region's edge), plus ``ring_margin_px``; a tilted or smeared circle is an ellipse
    whose ring must not reach the marker cells beside its narrow side.
    """
    if len(table.areas) == 0:
        return np.zeros(0, bool), np.zeros(0)
    var_x, var_y, cov = table.moments.T
    # the ellipse x^T (4 S)^-1 x = 1 of moments S reaches r(d) = 2 / sqrt(d^T S^-1 d) along the unit vector d
    dx, dy = RING_DIRECTIONS[:, 0], RING_DIRECTIONS[:, 1]
    det = var_x * var_y - cov * cov
    quadratic = (var_y[:, None] * dx ** 2 - 2 * cov[:, None] * dx * dy + var_x[:, None] * dy ** 2) / det[:, None]
    reach = params.ring_scale * (2 / np.sqrt(quadratic) + 0.5) + params.ring_margin_px  # (M, 8)
    ring = table.centres[:, None, :] + reach[..., None] * RING_DIRECTIONS[None]
    # a ring point past the image edge reads the edge pixel (circles near the border stay testable)
    h, w = smooth.shape
    ring = np.clip(ring, 0, [w - 1, h - 1])
    points = np.concatenate([table.centres[:, None, :], ring], axis=1)
    values, _ = sampling.sample_image(smooth, points)
    centre, ring_values = values[:, 0], np.sort(values[:, 1:], axis=1)
    ring_median = (ring_values[:, 3] + ring_values[:, 4]) / 2  # of 8 sorted samples (np.median is 10x slower)
    contrast = ring_median - centre
    passed = ((contrast >= params.min_ring_contrast_gray)
              & (centre <= params.max_darkness_ratio * ring_median)
              & (ring_values[:, params.ring_dark_allowed] - centre >= params.ring_dark_contrast_fraction * contrast))
    with np.errstate(invalid="ignore", divide="ignore"):
        darkness = centre / ring_median
    return passed, darkness


def _ring_test_either_turn(smooth: np.ndarray, table: _BlobTable, params: CircleParams) -> tuple[np.ndarray, np.ndarray]:
    """``_ring_test`` of blobs whose turn's sign is not known: each turned one also tested the other way
    (one call for both), passed if either way passes (its darkness then from the way that passed)."""
    var_x, var_y, cov = table.moments.T
    turned = np.flatnonzero(cov > MIN_TESTED_TURN * np.sqrt(var_x * var_y))
    both = _BlobTable(np.concatenate([table.centres, table.centres[turned]]),
                      np.concatenate([table.areas, table.areas[turned]]),
                      np.concatenate([table.moments, table.moments[turned] * [1.0, 1.0, -1.0]]))
    passed, darkness = _ring_test(smooth, both, params)
    count = len(table.areas)
    only_other_way = passed[count:] & ~passed[turned]
    passed[turned[only_other_way]] = True
    darkness[turned[only_other_way]] = darkness[count:][only_other_way]
    return passed[:count], darkness[:count]


def refine_centres(gray: np.ndarray, H: np.ndarray, circles_cells: np.ndarray) -> np.ndarray:
    """(K, 2) circle centres read in the full-resolution frame: the darkness-weighted centroid of
    a window of 1.5 radii around each circle, laid out on the grid through H (3, 3) grid -> frame
    (so it follows the circle's ellipse; one ``cv2.remap`` for all 9 x 9 samples of every window).

    circles_cells: (K, 3) the circles' (u, v, radius) in cells. Blobs found at a pyramid level are
    off by a few tenths of a frame pixel; these are as good as the frame's. Only samples darker than
    the window's median by a fifth of its contrast count, so the paper around a circle adds no pull
    toward the window's centre.
    """
    window_cells = circles_cells[:, None, :2] + 1.5 * circles_cells[:, None, 2:3] * CENTROID_OFFSETS[None]  # (K, S, 2)
    points = homography.project(H, window_cells.reshape(-1, 2)).reshape(window_cells.shape)
    values, inside = sampling.sample_image(gray, points)  # (K, S), NaN outside the frame
    darkness = sampling.nan_median_rows(values)[:, None] - values
    # fmax skips NaN: the largest finite darkness of each row, and a weight of 0 where the sample is NaN
    weight = np.fmax(darkness - 0.2 * np.fmax.reduce(darkness, axis=1, keepdims=True), 0.0)
    total = weight.sum(axis=1)
    centres = (weight[..., None] * np.where(inside[..., None], points, 0.0)).sum(axis=1) / np.maximum(total, 1e-9)[:, None]
    return np.where((total > 0)[:, None], centres, np.nan)


@dataclass(frozen=True)
class Triples:
    """Corner groups: (large, small along the first edge, small along the second edge).

    index: (T, 3) indices into the blobs, in the layout's circle order of a corner.
    points_px: (T, 3, 2) their centres.
    """

    index: np.ndarray
    points_px: np.ndarray

    def __len__(self) -> int:
        return len(self.index)


def corner_triples(blobs: Blobs, layout: MarkerLayout, params: CircleParams) -> Triples:
    """Find (large, small, small) blob triples shaped like one corner of the layout.

    Face-on, the small circles are 2 cells from the large one (``spacing``
    over the large radius: 2.5 for p = 2) at half its radius, at right angles.
    Under perspective and tilt up to ~60 deg the tests below stay loose; the
    homography fit and the decode are the strict checks. At most
    ``max_triples`` (the most corner-like) are kept.
    """
    p = params
    large_r, small_r = layout.circles[0, 2], layout.circles[1, 2]
    spacing = np.linalg.norm(layout.circles[1, :2] - layout.circles[0, :2]) / large_r
    area_ratio = (large_r / small_r) ** 2
    c, a = blobs.centres_px, blobs.areas_px
    if len(a) < 3:
        return Triples(np.zeros((0, 3), int), np.zeros((0, 3, 2)))
    radius = np.sqrt(a / np.pi)
    # candidate (large i, small j) pairs, in a window sorted by x so the work stays near-linear
    reach = spacing * p.max_arm_fraction * radius
    order = np.argsort(c[:, 0], kind="stable")
    xs = c[order, 0]
    lo = np.searchsorted(xs, c[:, 0] - reach, "left")
    hi = np.searchsorted(xs, c[:, 0] + reach, "right")
    counts = hi - lo
    i = np.repeat(np.arange(len(a)), counts)
    j = order[np.repeat(lo - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())]
    d = np.linalg.norm(c[j] - c[i], axis=1)
    ratio = a[i] / a[j]
    keep = ((ratio >= area_ratio / p.area_ratio_tolerance) & (ratio <= area_ratio * p.area_ratio_tolerance)
            & (d >= p.min_arm_fraction * spacing * radius[i]) & (d <= p.max_arm_fraction * spacing * radius[i]))
    i, j = i[keep], j[keep]
    if len(i) < 2:
        return Triples(np.zeros((0, 3), int), np.zeros((0, 3, 2)))
    # all (j1, j2) pairs sharing a large i (pairs are grouped by i already)
    starts = np.flatnonzero(np.concatenate([[True], i[1:] != i[:-1]]))
    sizes = np.diff(np.append(starts, len(i)))
    starts, sizes = starts[sizes >= 2], sizes[sizes >= 2]
    if len(starts) == 0:
        return Triples(np.zeros((0, 3), int), np.zeros((0, 3, 2)))
    # each group's (a, b) pairs, offset to the group's start in i and j
    pairs = [_pairs(size) for size in sizes.tolist()]
    first = np.repeat(starts, [len(pair) for pair in pairs])
    pairs = np.concatenate(pairs) + first[:, None]
    t = np.column_stack([i[first], j[pairs[:, 0]], j[pairs[:, 1]]])
    e1, e2 = c[t[:, 1]] - c[t[:, 0]], c[t[:, 2]] - c[t[:, 0]]
    cross = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    n1, n2 = np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1)
    cos = (e1 * e2).sum(axis=1) / (n1 * n2)
    small_ratio = a[t[:, 1]] / a[t[:, 2]]
    ok = ((np.abs(cos) < p.max_arm_cos) & (n1 / n2 < p.max_arm_ratio) & (n2 / n1 < p.max_arm_ratio)
          & (small_ratio < p.max_small_area_ratio) & (small_ratio > 1 / p.max_small_area_ratio))
    t, cross = t[ok], cross[ok]
    if len(t) > p.max_triples:
        # a dotted texture makes thousands; keep the most corner-like (right angle, equal arms and smalls)
        score = np.abs(cos[ok]) + np.abs(np.log(n1[ok] / n2[ok])) + np.abs(np.log(small_ratio[ok]))
        best = np.argsort(score, kind="stable")[:p.max_triples]
        t, cross = t[best], cross[best]
    # handedness: seen from the front, (first edge) x (second edge) > 0 in image coordinates
    t[cross < 0] = t[cross < 0][:, [0, 2, 1]]
    return Triples(t, c[t])


@lru_cache(maxsize=64)
def _pairs(size: int) -> np.ndarray:
    """(P, 2) index pairs (a < b) of ``size`` items (np.triu_indices, cached: it costs ~30 us a call)."""
    pairs = np.array(list(itertools.combinations(range(size), 2)), dtype=np.intp).reshape(-1, 2)
    pairs.flags.writeable = False
    return pairs


@dataclass(frozen=True)
class CircleCandidate:
    """A marker candidate assembled around one corner triple.

    circle_ids: (K,) layout circle indices (corner 3c + slot, with the anchor
        triple called corner 0: the true rotation is left to the decoder).
    circles_px: (K, 2) matched blob centres; blob_index: (K,) their blob indices.
    H: (3, 3) the grid -> image map ``_fit`` made of them while assembling (a homography from
        ``min_circles_for_homography`` circles on, else affine).
    corners: sorted layout corners with at least two matched circles.
    """

    circle_ids: np.ndarray
    circles_px: np.ndarray
    blob_index: np.ndarray
    H: np.ndarray

    @property
    def corners(self) -> np.ndarray:
        """Sorted layout corners with at least two of their circles matched (a lone circle may be the
        part of one that shows past an occluder's edge: its corner is taken as hidden)."""
        return np.flatnonzero(np.bincount(self.circle_ids // 3, minlength=4) >= 2)


def assemble_candidates(blobs: Blobs, triples: Triples, layout: MarkerLayout,
                        params: CircleParams) -> list[CircleCandidate]:
    """Grow marker candidates from corner triples by predicting the other corners.

    Each triple, taken as corner 0, fixes an affine grid -> image map. The
    other corners are visited nearest first (the neighbour that matches
    more circles, the other neighbour, then the diagonal) and each is taken
    from, in order of preference:

    1. a whole triple whose three circles lie, on average, within
       ``first_triple_window_cells`` of their predictions while only the
       anchor is known (one corner extrapolates poorly under perspective),
       ``triple_window_cells`` after that;
    2. the blob nearest the predicted large circle within
       ``first_large_window_cells`` (while only the anchor is known) or
       ``large_window_cells`` (its whole triple if it is the large circle of
       one), then each small circle's nearest blob within
       ``small_window_cells`` (a corner that lost a small circle still counts).

    Sizes must fit the map (a blob's radius within ``min_radius_ratio`` to
    ``max_radius_ratio`` x the circle's). Every match refines the map (a
    homography from ``min_circles_for_homography`` circles on, which must fit
    within ``max_fit_error_cells``). A candidate needs ``min_circles`` circles
    on at least ``min_corners`` corners (of two circles or more). The blobs of a
    candidate with three or four such corners take part in no other; a two-corner candidate may be a wrong
    pairing, so its blobs stay free (the decoder settles it; identical
    candidates are listed once).
    """
    p = params
    grid = layout.circles[:, :2]
    radius_cells = layout.circles[:, 2]
    taken = np.zeros(len(blobs), bool)
    blob_r = np.sqrt(blobs.areas_px / np.pi)
    centres = blobs.centres_px
    triple_index, triple_px = triples.index, triples.points_px
    triple_large_r = blob_r[triple_index[:, 0]]
    # (4, 5, 2) per corner: its three circles, then one cell along u and along v from its large circle
    corner_points = np.concatenate([grid.reshape(4, 3, 2), grid[0::3, None] + homography.UNIT_STEPS], axis=1)
    candidates, seen = [], set()
    in_any = np.zeros(len(blobs), bool)
    for t in range(len(triples)):
        if taken[triple_index[t]].any() or in_any[triple_index[t]].all():
            continue  # part of a settled candidate, or would only rebuild an earlier one
        ids, index = [0, 1, 2], triple_index[t].tolist()
        in_candidate = np.zeros(len(blobs), bool)
        in_candidate[index] = True
        free_triples = (~(taken | in_candidate))[triple_index].all(axis=1)  # again whenever a corner joins
        H = _fit(grid[ids], centres[index], p)

        def tries_at(corner: int) -> list[list[int]]:
            """Ways to match ``corner``'s circles through the current map (blob indices, -1: none), best first."""
            points = homography.project(H, corner_points[corner])
            cell_px = homography.cell_px_at(points[0], points[3], points[4]) if np.isfinite(points).all() else math.nan
            if not math.isfinite(cell_px):
                return []
            predicted = points[:3]
            # 1. a whole triple: the mean distance of its circles from the predictions, in cells
            window = p.first_triple_window_cells if len(ids) == 3 else p.triple_window_cells
            offsets = triple_px - predicted
            error = np.sqrt((offsets * offsets).sum(axis=2)).sum(axis=1) / 3 / cell_px
            r_ratio = triple_large_r / (radius_cells[3 * corner] * cell_px)
            fits = ((error < window) & (r_ratio > p.min_radius_ratio) & (r_ratio < p.max_radius_ratio)
                    & free_triples)
            if fits.any():
                return [triple_index[k].tolist() for k in np.flatnonzero(fits)[np.argsort(error[fits])][:2]]
            # 2. else circle by circle: the large one (with its whole triple if it has one), then the small
            # ones shifted by the large one's offset
            window = p.first_large_window_cells if len(ids) == 3 else p.large_window_cells
            tries = []
            for found in _match_corner(centres, blob_r, predicted, cell_px, radius_cells[3 * corner:3 * corner + 3],
                                       taken, index, window, p):
                own = np.flatnonzero((triple_index[:, 0] == found[0]) & free_triples)
                tries += [triple_index[k].tolist() for k in own[:1]] + [found]
            return tries

        def quality(tries: list[list[int]]) -> int:
            return max((sum(b >= 0 for b in found) for found in tries), default=0)

        # the first neighbour to join is the one that matches best (a neighbour hidden under a strip can
        # still lend a stray blob to a loose first window); then the other neighbour, then the diagonal
        first_tries = {corner: tries_at(corner) for corner in (1, 3)}
        first = max((1, 3), key=lambda corner: quality(first_tries[corner]))
        for corner in (first, 4 - first, 2):
            # until a corner joins, the map and the free blobs are those first_tries was made with
            for found in first_tries[corner] if corner in first_tries and len(ids) == 3 else tries_at(corner):
                added = [3 * corner + slot for slot, b in enumerate(found) if b >= 0]
                blobs_added = [b for b in found if b >= 0]
                H_new = _fit(grid[ids + added], centres[index + blobs_added], p)
                # below min_circles_for_homography points the fit is affine and always "fits"; from there
                # the whole set must fit, and so must the added circles themselves (one stray blob among
                # seven good circles moves the RMS little)
                checkable = len(ids) + len(added) >= p.min_circles_for_homography
                if not checkable or max(homography.fit_errors_cells(H_new, grid[ids + added], centres[index + blobs_added],
                                                                    len(added))) <= p.max_fit_error_cells:
                    ids, index, H = ids + added, index + blobs_added, H_new
                    in_candidate[blobs_added] = True
                    free_triples = (~(taken | in_candidate))[triple_index].all(axis=1)
                    break
        candidate = CircleCandidate(np.array(ids), centres[index], np.array(index), H)
        corners = len(candidate.corners)
        if len(ids) >= p.min_circles and corners >= p.min_corners and frozenset(index) not in seen:
            seen.add(frozenset(index))
            candidates.append(candidate)
            in_any[index] = True
            if corners >= 3:
                taken[index] = True  # three corners agreeing: these circles are this marker's
    return candidates


def _match_corner(centres, blob_r, predicted, cell_px, radii_cells, taken, used, window_cells: float,
                  params: CircleParams) -> list[list[int]]:
    """Up to two ways of matching one corner's circles: blob indices (3,) each (-1: none); [] if its
    large circle is missing.

    The large circle is one of the two nearest blobs of fitting size within
    ``window_cells`` of its prediction; the small ones are searched within
    ``small_window_cells`` of their predictions moved by the large circle's
    offset (most of an extrapolation's error is that shift).
    """
    p = params
    free = ~taken
    free[used] = False
    offsets = centres - predicted[0]
    d = np.sqrt((offsets * offsets).sum(axis=1))
    r_ratio = blob_r / (radii_cells[0] * cell_px)
    ok = free & (d < window_cells * cell_px) & (r_ratio > p.min_radius_ratio) & (r_ratio < p.max_radius_ratio)
    if not ok.any():
        return []
    matches = []
    for large in np.flatnonzero(ok)[np.argsort(d[ok], kind="stable")][:2].tolist():
        left = free.copy()
        left[large] = False
        shift = centres[large] - predicted[0]
        found = [large]
        for k in (1, 2):
            offsets = centres - (predicted[k] + shift)
            d_small = np.sqrt((offsets * offsets).sum(axis=1))
            r_ratio = blob_r / (radii_cells[k] * cell_px)
            ok_small = (left & (d_small < p.small_window_cells * cell_px) & (r_ratio > p.min_radius_ratio)
                        & (r_ratio < p.max_radius_ratio))
            found.append(int(np.flatnonzero(ok_small)[np.argmin(d_small[ok_small])]) if ok_small.any() else -1)
            if found[-1] >= 0:
                left[found[-1]] = False
        matches.append(found)
    return matches


def _fit(grid_points: np.ndarray, image_points: np.ndarray, params: CircleParams) -> np.ndarray:
    """(3, 3) grid -> image: least-squares affine below ``min_circles_for_homography`` points, a homography from there.

    Four or five points, three of them bunched in one corner, pin a
    homography's perspective terms badly; an affine map extrapolates better
    until a second corner is complete.
    """
    if len(grid_points) < params.min_circles_for_homography:
        return homography.fit_affine(grid_points, image_points)
    return homography.fit(grid_points, image_points)


def missing_corner_cells(layout: MarkerLayout, present_corners: np.ndarray) -> np.ndarray:
    """(N, N) bool: cells likely hidden, given which corners' circles were not found.

    An occluder that hides a corner's circles reaches in from outside: each
    missing corner erases its square up to and including the first data row
    and column (parity bands, gap, border and first data cells), and two
    missing corners of one side erase that whole side band. Corners are in
    the candidate's own labels.
    """
    n, depth = layout.n_cells, layout.data_origin + 1
    corner_square = np.zeros((n, n), bool)
    corner_square[:depth, :depth] = True
    top_band = np.zeros((n, n), bool)
    top_band[:depth, :] = True
    missing = [c for c in range(4) if c not in set(np.asarray(present_corners).tolist())]
    region = np.zeros((n, n), bool)
    for c in missing:
        region |= np.rot90(corner_square, -c)  # TL square turned clockwise to corner c
        if (c + 1) % 4 in missing:
            region |= np.rot90(top_band, -c)  # side from corner c to corner c + 1
    return region
