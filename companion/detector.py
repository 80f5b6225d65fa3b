"""The RS marker detector: grayscale frame in, decoded markers with sub-pixel corners out.

    detector = Detector(DetectorParams(parity=2))
    detections = detector.detect(gray)        # list[companion.types.Detection]
    detector.last_stage_ms                    # {"square": 2.4, "sample": 0.1, ...}

Stages (one module each, run in this order):

1. ``detect_square``: OpenCV ArUco finds inner black squares (identified or
   not) -> candidate quads.
2. ``grid_sampling``: every candidate's N x N grid is read through its
   homography, cells classified black / white / unknown against the
   marker's own border (black) and gap ring (white) levels.
3. ``grid_decode``: bounded-distance decoding of the whole codeword, then
   algebraic RS; anything that does not decode is dropped.
4. ``detect_circles`` (the occluded path): where the square path found
   nothing, corner circles are grouped into grids, sampled with occluded and
   out-of-image cells as erasures, and decoded the same way.

Nothing is reported unless it decodes to a dictionary marker.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields

import numpy as np

from companion import grid_sampling
from companion.detect_square import SquareFinder, SquareParams, refine_corners
from companion.grid_decode import DEFAULT_FALSE_ACCEPT_BOUND, GridDecoder
from companion.marker import MarkerLayout
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
    circles: str = "when_square_empty"
    ambiguity: float = 0.15
    min_contrast: float = 20.0
    false_accept_bound: float = DEFAULT_FALSE_ACCEPT_BOUND
    min_gap: int = 6

    def __post_init__(self):
        if self.parity not in (2, 4):
            raise DetectorParamsError(f"parity must be 2 or 4, got {self.parity!r}")
        if not 0.0 <= self.aruco_error_correction_rate <= 1.0:
            raise DetectorParamsError(f"aruco_error_correction_rate must be in [0, 1], got "
                                      f"{self.aruco_error_correction_rate!r}")
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

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


class Detector:
    """Finds and decodes RS markers in grayscale frames. Not thread-safe: one per thread."""

    def __init__(self, params: DetectorParams | None = None):
        self.params = params = params or DetectorParams()
        self.layout = MarkerLayout(parity=params.parity, dictionary=params.dictionary)
        self.decoder = GridDecoder(self.layout, params.false_accept_bound, params.min_gap)
        self.square = SquareFinder(self.layout, SquareParams(
            error_correction_rate=params.aruco_error_correction_rate,
            decode_rejected=params.decode_rejected, min_contrast=params.min_contrast))
        self._border = self.layout.border_mask
        self._gap = grid_sampling.gap_ring_mask(self.layout)
        self.last_stage_ms: dict[str, float] = {}

    def detect(self, gray: np.ndarray) -> list[Detection]:
        """All RS markers in an (H, W) uint8 frame, each once."""
        gray = _as_gray(gray)
        clock = _StageClock()
        candidates = self.square.find(gray)
        clock.lap("square")
        detections = self._decode_quads(gray, candidates.corners_px, candidates.from_aruco)
        clock.lap("square_decode")
        self.last_stage_ms = clock.stages_ms
        return detections

    def _decode_quads(self, gray: np.ndarray, quads: np.ndarray, refined: np.ndarray) -> list[Detection]:
        """Sample, classify and decode M candidate inner squares (M, 4, 2) (clockwise corners)."""
        if len(quads) == 0:
            return []
        H = grid_sampling.homographies_from_quads(self.layout.inner_corners_cells, quads)
        cells = grid_sampling.sample_cells(gray, H, self.layout.n_cells)
        levels = grid_sampling.grid_levels(cells, self._border, self._gap)
        grids = grid_sampling.classify_cells(cells, levels, self.params.ambiguity)
        usable = levels.contrast >= self.params.min_contrast
        results = self.decoder.decode(grids[usable])
        detections = []
        for index, result in zip(np.flatnonzero(usable), results):
            if result is None:
                continue
            corners = quads[index]
            if not refined[index]:
                cell_px = np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1).mean() / 8
                corners = refine_corners(gray, corners, cell_px)
            detections.append(Detection(
                symbol=result.symbol, id=result.id, corners_px=np.roll(corners, -result.rotation, axis=0),
                path="square", corrected=result.corrected, quality=result.quality))
        return _unique(detections)


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
