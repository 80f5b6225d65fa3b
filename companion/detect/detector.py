"""The RS marker detector: grayscale frame in, decoded markers with sub-pixel corners out.

    detector = Detector(DetectorParams(parity=2))
    detections = detector.detect(gray)        # list[companion.types.Detection]
    detector.last_stage_ms                    # {"square": 1.9, "square_decode": 0.4, ...} of the last frame

Stages (one module each, run in this order):

1. ``detect_square``: OpenCV ArUco finds inner black squares (identified or
   not) -> candidate quads.
2. ``grid_sampling``: every candidate's N x N grid is read through its
   homography, cells classified black / white / unknown against the
   marker's own border (black) and gap ring (white) levels.
3. ``grid_decode``: bounded-distance decoding of the whole codeword, then
   algebraic RS; anything that does not decode is dropped.
   (``edge_refine`` gives every candidate sub-pixel corners from its edges
   before sampling; ``marker_refine`` then aligns each decoded square-path
   marker's whole pattern to the image for its final corners.)
4. ``detect_circles`` (the occluded path): where the square path found
   nothing, corner circles are grouped into grids, sampled with occluded and
   out-of-image cells as erasures, and decoded the same way.

Nothing is reported unless it decodes to a dictionary marker.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from companion.detect import homography, sampling
from companion.detect.circles import (CircleCandidate, CircleParams, assemble_candidates, corner_triples,
                                      find_blobs, missing_corner_cells)
from companion.detect.square import SquareFinder, SquareParams
from companion.detect.edges import EdgeRefiner
from companion.markers.codec import DecoderParams, GridDecoder
from companion.markers.layout import MarkerLayout
from companion.detect.refine import MarkerRefiner
from companion.types import Detection

CIRCLES_MODES = ("when_square_empty", "always", "never")


class DetectorError(ValueError):
    """Bad input to the detector (the message says what is wrong)."""


class DetectorParamsError(DetectorError):
    """A detector parameter is out of range (the message names it)."""


@dataclass(frozen=True)
class DetectorParams:
    """Detector settings (the ``detector:`` section of the config; every key optional).

    parity, dictionary: the marker layout (must match the facility map's).
    aruco_error_correction_rate: bits ArUco may correct itself (fraction of
        the dictionary's 6); the rest is left to the RS decode of rejected quads.
    decode_rejected: RS-decode marker-like quads ArUco rejected (blobs on data).
    aruco_threshold_windows_px: ArUco's adaptive threshold windows (min, max,
        step), odd sizes; two thresholds instead of OpenCV's three (3, 23, 10).
    circles: when the occluded (circles) path runs: "when_square_empty"
        (only in frames where the square path found nothing), "always", or "never".
    ambiguity: cells whose mean is within this fraction of the marker's
        contrast from its black/white midpoint are unknown (erasures).
    min_contrast: white - black gray levels below which a candidate is dropped.
    false_accept_bound: probability that random cells decode (per candidate).
    min_gap: the runner-up marker must be this many cells further than the winner.
    """

    parity: int = 2
    dictionary: str = "6x6"
    aruco_error_correction_rate: float = 0.6
    decode_rejected: bool = True
    aruco_threshold_windows_px: tuple[int, int, int] = (7, 27, 20)
    circles: str = "when_square_empty"
    ambiguity: float = 0.15
    min_contrast: float = 20.0
    false_accept_bound: float = 1e-12
    min_gap: int = 6

    def __post_init__(self):
        if self.parity not in (2, 4):
            raise DetectorParamsError(f"parity must be 2 or 4, got {self.parity!r}")
        if not 0.0 <= self.aruco_error_correction_rate <= 1.0:
            raise DetectorParamsError(f"aruco_error_correction_rate must be in [0, 1], got "
                                      f"{self.aruco_error_correction_rate!r}")
        windows = tuple(self.aruco_threshold_windows_px)
        if (len(windows) != 3 or not all(isinstance(w, int) for w in windows) or windows[0] < 3
                or windows[0] % 2 == 0 or windows[1] < windows[0] or windows[2] < 1):
            raise DetectorParamsError("aruco_threshold_windows_px must be [min, max, step] integers with an odd "
                                      f"min >= 3, max >= min and step >= 1, got {self.aruco_threshold_windows_px!r}")
        object.__setattr__(self, "aruco_threshold_windows_px", windows)
        if self.circles not in CIRCLES_MODES:
            raise DetectorParamsError(f"circles must be one of {', '.join(CIRCLES_MODES)}, got {self.circles!r}")
        if not 0.0 <= self.ambiguity < 0.5:
            raise DetectorParamsError(f"ambiguity must be in [0, 0.5), got {self.ambiguity!r}")
        if not self.min_contrast > 0:
            raise DetectorParamsError(f"min_contrast must be > 0, got {self.min_contrast!r}")
        if not 0.0 < self.false_accept_bound < 1e-3:
            raise DetectorParamsError(f"false_accept_bound must be in (0, 1e-3), got {self.false_accept_bound!r}")
        if self.min_gap < 1:
            raise DetectorParamsError(f"min_gap must be >= 1, got {self.min_gap!r}")


class Detector:
    """Finds and decodes RS markers in grayscale frames. Not thread-safe: one per thread."""

    def __init__(self, params: DetectorParams | None = None):
        self.params = params = params or DetectorParams()
        self.layout = MarkerLayout(parity=params.parity, dictionary=params.dictionary)
        self.decoder = GridDecoder(self.layout, DecoderParams(false_accept_probability=params.false_accept_bound,
                                                             min_gap_cells=params.min_gap))
        self.square = SquareFinder(self.layout, SquareParams(
            error_correction_rate=params.aruco_error_correction_rate,
            decode_rejected=params.decode_rejected, min_contrast=params.min_contrast,
            threshold_windows_px=params.aruco_threshold_windows_px), screen=self.decoder.plausible)
        self.circle_params = CircleParams()
        self.edges = EdgeRefiner(self.layout, min_contrast=params.min_contrast)
        self.refiner = MarkerRefiner(self.layout)
        self.probe = sampling.CellProbe(self.layout)
        self._border = self.layout.border_mask
        self._gap = sampling.gap_ring_mask(self.layout)
        self._codeword = self.layout.codeword_mask
        self.last_stage_ms: dict[str, float] = {}

    def detect(self, gray: np.ndarray) -> list[Detection]:
        """All RS markers in an (H, W) uint8 frame, each once."""
        gray = _as_gray(gray)
        clock = _StageClock()
        candidates = self.square.find(gray)
        clock.lap("square")
        detections = self._decode_quads(gray, candidates.corners_px, candidates.from_aruco)
        clock.lap("square_decode")
        detections = [self._aligned(gray, d) for d in detections]
        clock.lap("square_align")
        mode = self.params.circles
        if mode == "always" or (mode == "when_square_empty" and not detections):
            detections += self._circles_path(gray, detections, clock)
        self.last_stage_ms = clock.stages_ms
        return detections

    def _aligned(self, gray: np.ndarray, detection: Detection) -> Detection:
        """Square-path corners aligned on the decoded marker's whole pattern (see marker_refine)."""
        fit = self.refiner.refine(gray, detection.id, detection.corners_px)
        return replace(detection, corners_px=fit.corners_px) if fit.refined else detection

    def _decode_quads(self, gray: np.ndarray, quads: np.ndarray, from_aruco: np.ndarray) -> list[Detection]:
        """Sample, classify and decode M candidate inner squares (M, 4, 2) (clockwise corners)."""
        if len(quads) == 0:
            return []
        inner = self.layout.inner_corners_cells
        # sub-pixel corners first: a thin, oblique marker needs good ones to be sampled right.
        # Rejected quads come with whole-pixel corners, off by up to a few pixels on small
        # markers: look wider across their edges first.
        rough = ~from_aruco
        if rough.any():
            quads = quads.copy()
            quads[rough] = self.edges.refine_square_corners(
                gray, homography.from_quads(inner, quads[rough]), quads[rough],
                half_width_cells=0.7, samples=21)
        quads = self.edges.refine_square_corners(gray, homography.from_quads(inner, quads), quads)
        H = homography.from_quads(inner, quads)
        cells = sampling.sample_cells(gray, H, self.layout.n_cells)
        levels = sampling.grid_levels(cells, self._border, self._gap)
        grids = sampling.classify_cells(cells, levels, self.params.ambiguity)
        usable = levels.contrast >= self.params.min_contrast
        index = np.flatnonzero(usable)
        results = self.decoder.decode(grids[usable])
        found = np.array([r is not None for r in results], bool)
        if not found.any():
            return []
        index, results = index[found], [r for r in results if r is not None]
        corners = quads[index]
        detections = [Detection(symbol=r.symbol, id=r.id, corners_px=np.roll(c, -r.rotation, axis=0), path="square",
                                corrected=r.corrected, quality=r.quality) for r, c in zip(results, corners)]
        return _unique(detections)

    # ------------------------------------------------------------------ circles path

    def _circles_path(self, gray: np.ndarray, found: list[Detection], clock: "_StageClock") -> list[Detection]:
        """Markers found by their corner circles, away from markers already found."""
        blobs = find_blobs(gray, self.circle_params)
        if found and len(blobs):
            blobs = blobs.subset(~self._inside_found(blobs.centres_px, found))
        clock.lap("circles_blobs")
        candidates = assemble_candidates(blobs, corner_triples(blobs, self.layout), self.layout)
        clock.lap("circles_group")
        detections = self._decode_circle_candidates(gray, candidates)
        clock.lap("circles_decode")
        return _unique(detections)

    def _inside_found(self, points_px: np.ndarray, found: list[Detection]) -> np.ndarray:
        """(K,) bool: points inside the full grid outline of an already found marker."""
        corners = np.stack([d.corners_px for d in found])
        H = homography.from_quads(self.layout.inner_corners_cells, corners)
        return sampling.inside_grids(points_px, H, self.layout.n_cells)

    def _decode_circle_candidates(self, gray: np.ndarray, candidates: list[CircleCandidate]) -> list[Detection]:
        """Fit, refine on the edges, sample and decode circle candidates, all batched."""
        fitted = []
        for candidate in candidates:
            grid_points = self.layout.circles[candidate.circle_ids, :2]
            H = homography.fit(grid_points, candidate.circles_px)
            if homography.fit_error_cells(H, grid_points, candidate.circles_px) <= 0.3:
                fitted.append((candidate, H, (grid_points, candidate.circles_px)))
        if fitted:  # a first look at one sample per cell: a wrong pairing of corners reads as no marker
            reading = self.probe.read(gray, np.stack([h for _, h, _ in fitted]))
            plausible = ((reading.contrast >= self.params.min_contrast) & (reading.border_black >= 0.6)
                         & (reading.gap_white >= 0.6) & self.decoder.plausible(reading.grid))
            fitted = [f for f, ok in zip(fitted, plausible) if ok]
        if not fitted:
            return []
        fits = self.edges.refine_homographies(gray, np.stack([h for _, h, _ in fitted]), [a for _, _, a in fitted])
        good = [i for i, fit in enumerate(fits) if fit.rms_cells <= 0.15]
        if not good:
            return []
        candidates = [fitted[i][0] for i in good]
        H = np.stack([fits[i].H for i in good])
        cells = sampling.sample_cells(gray, H, self.layout.n_cells)
        levels = sampling.grid_levels(cells, self._border, self._gap)
        grids = sampling.classify_cells(cells, levels, self.params.ambiguity)
        probed = sampling.erase_near_bad_fixed_cells(grids, self._border, self._gap, self._codeword)
        # reading 1: occlusion probes; reading 2: also the region of the corners whose circles are missing
        readings, owners = [], []
        for i, candidate in enumerate(candidates):
            if levels.contrast[i] < self.params.min_contrast:
                continue
            readings.append(probed[i])
            owners.append(i)
            region = missing_corner_cells(self.layout, candidate.corners) & self._codeword
            if region.any():
                readings.append(np.where(region, -1, probed[i]).astype(np.int8))
                owners.append(i)
        if not readings:
            return []
        decoded = self.decoder.decode_groups(np.stack(readings), np.array(owners))
        detections = []
        for i, result in decoded.items():
            k, candidate = result.rotation, candidates[i]
            inner = homography.project(H[i], self.layout.inner_corners_cells)
            corner, slot = divmod(candidate.circle_ids, 3)
            detections.append(Detection(
                symbol=result.symbol, id=result.id, corners_px=np.roll(inner, -k, axis=0), path="circles",
                corrected=result.corrected, quality=result.quality, circles_px=candidate.circles_px.copy(),
                circle_ids=3 * ((corner - k) % 4) + slot))
        return detections


def _unique(detections: list[Detection]) -> list[Detection]:
    """Drop repeats of one marker (same id, centres closer than a quarter side), keeping the best."""
    kept: list[Detection] = []
    for d in sorted(detections, key=lambda d: -d.quality):
        centre = d.corners_px.mean(axis=0)
        side = np.linalg.norm(d.corners_px[1] - d.corners_px[0])
        if not any(k.id == d.id and np.linalg.norm(k.corners_px.mean(axis=0) - centre) < side / 4 for k in kept):
            kept.append(d)
    return kept


def _as_gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise DetectorError(f"detect() needs an (H, W) uint8 grayscale image, got {image.shape} {image.dtype}")
    return np.ascontiguousarray(image)


class _StageClock:
    """Milliseconds per stage on the monotonic performance counter."""

    def __init__(self):
        self.stages_ms: dict[str, float] = {}
        self._last = time.perf_counter_ns()

    def lap(self, stage: str) -> None:
        now = time.perf_counter_ns()
        self.stages_ms[stage] = (now - self._last) / 1e6
        self._last = now
