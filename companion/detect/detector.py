"""The RS marker detector: grayscale frame in, decoded markers with sub-pixel corners out.

    detector = Detector(DetectorParams(parity=2), camera=camera)   # camera: optional CameraModel
    detections = detector.detect(gray)        # list[companion.types.Detection]
    detector.last_stage_ms                    # {"square": 1.9, "square_decode": 0.4, ...} of the last frame

Stages (one module each in ``companion.detect``, run in this order):

1. ``square``: OpenCV ArUco finds inner black squares (identified or not)
   -> candidate quads.
2. ``edges``: every candidate gets sub-pixel corners from its inner square's
   edges.
3. ``sampling``: every candidate's N x N grid is read through its
   homography (``homography``), cells classified black / white / unknown
   against the marker's own border (black) and gap ring (white) levels.
4. ``companion.markers.codec``: bounded-distance decoding of the whole
   codeword, then algebraic RS; anything that does not decode is dropped.
5. ``refine``: each decoded square-path marker's whole pattern is aligned
   to the image for its final corners (through the camera's lens model when
   the detector has the camera).
   ``smear``: where a found marker's edges are wide, the frame's motion
   smear is measured on its known pattern, the frame deconvolved with it and
   the square path (1-5) run again there for the markers the smear hid.
   ``small_window``: a frame that is round blurred (wide edges, no line
   smear fits), dim or noisy (or every frame, for the survey) is read again
   by the square path (1-5) with a small threshold window, for the small
   markers whose quads the usual window loses.
6. ``circles`` (the occluded path): in every frame (``circles.run``), where
   the markers found by the square path do not explain them, corner circles
   (found at a pyramid level; while ArUco runs on a second thread when
   OpenCV may use two) are grouped into grids, read again in the frame, fitted,
   refined on the visible edges, sampled with occluded and out-of-image
   cells as erasures, and decoded the same way.

Nothing is reported unless it decodes to a dictionary marker. Every setting
is a field of one of the stage parameter dataclasses that ``DetectorParams``
is made of (``DetectorParams.from_mapping`` reads the config's ``detector:``
section).
"""
from __future__ import annotations

import itertools
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from companion.detect import homography, sampling
from companion.detect.circles import (Blobs, CircleCandidate, CircleParams, assemble_candidates, corner_triples,
                                      find_frame_blobs, find_window_blobs, missing_corner_cells, refine_centres)
from companion.detect.edges import EdgeParams, EdgeRefiner
from companion.detect.refine import MarkerRefiner, RefineParams
from companion.detect.sampling import SamplingParams
from companion.detect.smear import SmearEstimator, SmearParams, deconvolve
from companion.detect.square import SquareFinder, SquareParams
from companion.markers.codec import DecoderParams, GridDecoder
from companion.markers.dictionary import SIZES, DictionaryError, load_dictionary
from companion.markers.layout import UNKNOWN, MarkerLayout
from companion.params import from_mapping, require
from companion.types import Detection

DICTIONARIES = tuple(f"{n}x{n}" for n in SIZES)


# the survey's detector measures the smear in every frame with a found marker (a sharp frame's edges are 1.9-3.1 px
# wide) and undoes it from 3 px on (the daemon's: only from 3.3 px wide edges and 7 px smears); a sharp frame's lens
# blur reads as a 2 px smear, and undone it made a sharp walk's map worse (docs/detector.md)
FOOTAGE_SMEAR = {"min_edge_width_px": 1.0, "min_length_px": 2.0, "min_recover_length_px": 3.0}


class DetectorError(ValueError):
    """Bad input to the detector (the message says what is wrong)."""


@dataclass(frozen=True)
class DetectorParams:
    """Detector settings: the marker layout and each stage's parameters (the config's ``detector:`` section).

    parity, dictionary: the marker layout (must match the facility map's).
    duplicate_offset_fraction: two detections of one id whose centres are
        closer than this share of the side are one marker (the best is kept).
    sampling, square, edges, circles, decoder, refine: the stages' own
        parameters (``SamplingParams``, ``SquareParams``, ``EdgeParams``,
        ``CircleParams``, ``DecoderParams``, ``RefineParams``), every default
        written once there.
    """

    parity: int = 2
    dictionary: str = "6x6"
    duplicate_offset_fraction: float = 0.25
    sampling: SamplingParams = field(default_factory=SamplingParams)
    square: SquareParams = field(default_factory=SquareParams)
    edges: EdgeParams = field(default_factory=EdgeParams)
    circles: CircleParams = field(default_factory=CircleParams)
    decoder: DecoderParams = field(default_factory=DecoderParams)
    refine: RefineParams = field(default_factory=RefineParams)
    smear: SmearParams = field(default_factory=SmearParams)

    def __post_init__(self):
        require(self.parity in (2, 4), "parity", "2 or 4", self.parity)
        try:
            load_dictionary(self.dictionary)
        except DictionaryError:
            require(False, "dictionary", f"one of {', '.join(DICTIONARIES)}", self.dictionary)
        require(0.0 < self.duplicate_offset_fraction <= 1.0, "duplicate_offset_fraction", "in (0, 1]",
                self.duplicate_offset_fraction)

    @classmethod
    def for_footage(cls, **fields) -> DetectorParams:
        """``fields`` for footage processed offline (survey, map check, localize), recall before speed:
        occluded markers beside found ones are looked for down to ``circles.min_side_px`` on one thread
        too (on two the search beside ArUco does so by default); for the small markers a walk's motion
        smears by a few pixels, every frame is read again with the small threshold window
        (``square.small_window_every_frame``) and its smear measured and, from 3 px on, undone
        (``FOOTAGE_SMEAR``)."""
        params = cls(**fields)
        return replace(params, circles=replace(params.circles, min_side_beside_found_px=params.circles.min_side_px),
                       square=replace(params.square, small_window_every_frame=True),
                       smear=replace(params.smear, **FOOTAGE_SMEAR))

    @classmethod
    def from_mapping(cls, mapping) -> DetectorParams:
        """From a (YAML) mapping, stages as nested mappings; ``ParamsError`` names the dotted key that is wrong::

            {"parity": 4, "circles": {"run": "always"}, "decoder": {"min_gap_cells": 8}}
        """
        return from_mapping(cls, mapping)


class Detector:
    """Finds and decodes RS markers in grayscale frames. Not thread-safe: one per thread.

    camera: optional ``companion.geometry.camera.CameraModel``; with it the
    square-path corners are aligned through its lens model (``refine``).
    With OpenCV on more than one thread, the square path's ArUco call runs on
    a thread of its own while the circles path's blob search runs on the
    caller's (the thread is started at the first frame, stopped by ``close``
    or when the detector is dropped).
    """

    def __init__(self, params: DetectorParams | None = None, camera=None):
        self.params = params = params or DetectorParams()
        self.layout = MarkerLayout(parity=params.parity, dictionary=params.dictionary)
        self.decoder = GridDecoder(self.layout, params.decoder)
        min_contrast_gray = params.sampling.min_contrast_gray
        self.square = SquareFinder(self.layout, params.square, min_contrast_gray, screen=self.decoder.plausible)
        self.edges = EdgeRefiner(self.layout, params.edges, min_contrast_gray)
        self.refiner = MarkerRefiner(self.layout, params.refine, camera)
        self.smear = SmearEstimator(self.layout, params.smear)
        self.probe = sampling.CellProbe(self.layout)
        self._border = self.layout.border_mask
        self._gap = sampling.gap_ring_mask(self.layout)
        self._codeword = self.layout.codeword_mask
        # (N, N) cells likely hidden for each set of corners whose circles were found
        self._hidden_by_corners = {corners: missing_corner_cells(self.layout, np.array(corners, int))
                                   for k in range(5) for corners in itertools.combinations(range(4), k)}
        self.last_stage_ms: dict[str, float] = {}
        self._aruco_worker: ThreadPoolExecutor | None = None

    def detect(self, gray: np.ndarray, expected_px: np.ndarray | None = None) -> list[Detection]:
        """All RS markers in an (H, W) uint8 frame, each once.

        expected_px: optional (K, 4, 2) inner-square corners (TL, TR, BR, BL of the upright marker) where
        markers are expected, e.g. the mapped markers seen from the daemon's current pose. With them, in a
        frame where the square path found a marker, the circles path looks only around the expected
        markers it did not find that face the camera and are large enough for it
        (``circles.expected_margin_fraction``, ``circles.min_side_px``), and not at all when there are
        none; without them, or when the square path found nothing, it searches the whole frame. With
        them the ``small_window`` pass, too, runs only where fewer than ``square.small_window_enough_markers``
        markers were found and an expected marker the square path could read (``square.min_side_px``) is not.
        """
        gray = _as_gray(gray)
        if min(gray.shape) < min(self.params.square.min_side_px, self.params.circles.min_side_px):
            # smaller than the smallest inner square either path reads: no marker fits (and OpenCV's filters
            # refuse the empty rows a reduced copy of it would have)
            self.last_stage_ms = {}
            return []
        clock = _StageClock()
        run = self.params.circles.run
        dim = self.square.is_dim(gray)
        aruco_pending = self._aruco_beside(gray, dim) if run == "always" and expected_px is None else None
        blobs_beside = None
        if aruco_pending is not None:
            # the frame-wide blob search needs nothing from the square path: this thread does it while ArUco runs
            blobs_beside = find_frame_blobs(gray, self.params.circles)
            clock.lap("circles_blobs")
            # on a loaded machine the thread may not have started ArUco yet: then it runs here
            quads = self.square.aruco_quads(gray, None, dim) if aruco_pending.cancel() else aruco_pending.result()
            candidates = self.square.candidates(gray, *quads)
        else:
            candidates = self.square.find(gray, dim=dim)
        clock.lap("square")
        detections = self._decode_quads(gray, candidates.corners_px, candidates.from_aruco)
        clock.lap("square_decode")
        detections = [self._aligned(gray, d) for d in detections]
        clock.lap("square_align")
        round_blur = False
        if self.params.smear.recover and detections:
            smeared, round_blur = self._smeared_markers(gray, detections)
            detections += smeared
            clock.lap("smear")
        read_again = self.params.square.small_window_every_frame or round_blur or dim or self.square.is_noisy(gray)
        if read_again and self._may_miss(expected_px, detections, gray.shape):
            detections += self._found_again(gray, detections, self.params.square.small_window_px, dim)
            clock.lap("small_window")
        if run == "always" or (run == "when_square_empty" and not detections):
            # (M, 3, 3) grid -> frame of the markers found so far: the circles path looks only outside them
            found_H = self._grids_of(detections) if detections else None
            circles = self.params.circles
            if blobs_beside is not None:
                blobs = blobs_beside
            elif expected_px is not None and detections:
                windows = self._windows_of_missing(expected_px, found_H, gray.shape, circles.min_side_px)
                blobs = find_window_blobs(gray, windows, circles) if len(windows) else None
            else:
                blobs = find_frame_blobs(gray, circles, circles.min_side_beside_found_px if detections else None)
            if blobs is not None:
                detections += self._circles_path(gray, blobs, found_H, clock)
        self.last_stage_ms = clock.stages_ms
        return detections

    def close(self) -> None:
        """Stop the ArUco thread, if one was started (it also stops when the detector is dropped)."""
        if self._aruco_worker is not None:
            self._aruco_worker.shutdown()
            self._aruco_worker = None

    def _aruco_beside(self, gray: np.ndarray, dim: bool) -> Future | None:
        """The square path's ArUco call started on a second thread, for the circles path's blob search to run
        on this one meanwhile, when OpenCV may use more than one thread (``cv2.setNumThreads``) and
        ``circles.search_beside_aruco``; None otherwise. ArUco is one OpenCV call, which leaves the
        interpreter: the blob search's Python steps do not wait for it, as they would for the square path's."""
        if cv2.getNumThreads() < 2 or not self.params.circles.search_beside_aruco:
            return None
        if self._aruco_worker is None:
            self._aruco_worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="detector-aruco")
        return self._aruco_worker.submit(self.square.aruco_quads, gray, None, dim)

    def _grids_of(self, found: list[Detection]) -> np.ndarray:
        """(M, 3, 3) homographies grid cells -> frame of M found markers (M >= 1)."""
        return homography.from_quads(self.layout.inner_corners_cells, np.stack([d.corners_px for d in found]))

    def _may_miss(self, expected_px: np.ndarray | None, found: list[Detection], gray_shape: tuple[int, int]) -> bool:
        """Whether the frame is worth reading again for a marker not yet found: no expected places were
        given; or fewer than ``square.small_window_enough_markers`` were found and an expected marker
        (facing the camera, ``square.min_side_px`` or larger, in the frame) lies outside every found grid."""
        if expected_px is None or not found:
            return True
        if len(found) >= self.params.square.small_window_enough_markers:
            return False
        found_H = self._grids_of(found)
        return len(self._windows_of_missing(expected_px, found_H, gray_shape, self.params.square.min_side_px)) > 0

    def _windows_of_missing(self, expected_px: np.ndarray, found_H: np.ndarray, gray_shape: tuple[int, int],
                            min_side_px: float) -> np.ndarray:
        """(B, 4) int windows (x0, y0, x1, y1) inside the frame around the expected markers (K, 4, 2) that
        face the camera (clockwise in the image), have a mean side of ``min_side_px`` or more, and
        whose centres no found marker's whole grid (``found_H`` (M, 3, 3)) covers: each one's square grown about its centre to
        the whole grid, its bounding box grown by ``circles.expected_margin_fraction`` of its larger side."""
        expected = np.asarray(expected_px, dtype=np.float64).reshape(-1, 4, 2)
        with np.errstate(invalid="ignore"):
            x, y = expected[..., 0], expected[..., 1]
            # shoelace: twice the signed area, > 0 for TL, TR, BR, BL clockwise on the screen (y down)
            facing = (x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1) > 0
            usable = facing & (homography.mean_side_px(expected) >= min_side_px)
        expected = expected[usable]
        if len(expected) == 0:
            return np.zeros((0, 4), np.int64)
        expected = expected[~sampling.inside_grids(expected.mean(axis=1), found_H, self.layout.n_cells)]
        if len(expected) == 0:
            return np.zeros((0, 4), np.int64)
        # the corners' order does not matter for the outline's bounding box: the grid shares the inner
        # square's centre, (n / inner) times its size
        centre = expected.mean(axis=1, keepdims=True)
        outline = centre + (expected - centre) * (self.layout.n_cells / self.layout.inner_cells)
        low, high = outline.min(axis=1), outline.max(axis=1)
        margin = self.params.circles.expected_margin_fraction * (high - low).max(axis=1, keepdims=True)
        height, width = gray_shape
        boxes = np.concatenate([np.floor(low - margin), np.ceil(high + margin) + 1], axis=1)
        boxes = boxes[(boxes[:, 0] < width) & (boxes[:, 1] < height) & (boxes[:, 2] > 0) & (boxes[:, 3] > 0)]
        return np.clip(boxes, 0, [width, height, width, height]).astype(np.int64)

    def _aligned(self, gray: np.ndarray, detection: Detection) -> Detection:
        """Square-path corners aligned on the decoded marker's whole pattern (see ``refine``), with their noise;
        where the alignment does not hold, the corners of the inner square's edge lines."""
        fit = self.refiner.refine(gray, detection.id, detection.corners_px)
        corners_px = fit.corners_px if fit.refined else self._edge_corners(gray, detection.corners_px[None])[0]
        cov_px2 = square_corner_cov_px2(fit.corner_cov_px2) if fit.refined else None
        if cov_px2 is not None:
            # sigma_px^2 = the mean variance of the 8 corner coordinates
            sigma_px = float(np.sqrt(np.trace(cov_px2) / 8))
        else:
            sigma_px = square_corner_sigma_px(fit.residual, _cell_px(corners_px, self.layout.inner_cells))
        if sigma_px is not None and not self._pattern_inside(corners_px, gray.shape):
            sigma_px *= CUT_SIGMA_FACTOR
            cov_px2 = None if cov_px2 is None else cov_px2 * CUT_SIGMA_FACTOR ** 2
        return replace(detection, corners_px=corners_px, corner_sigma_px=sigma_px, corner_cov_px2=cov_px2)

    def _smeared_markers(self, gray: np.ndarray, found: list[Detection]) -> tuple[list[Detection], bool]:
        """Markers the square path missed in a smeared frame (``smear``): the edges of one found marker
        measured (a sharp frame stops there), its pattern compared with the image under line smears, the
        frame deconvolved with the best one and the square path run again there (with the small window too
        where every frame is, ``square.small_window_every_frame``). Also whether the frame is
        round blurred instead (wide edges, no line smear fits), for the ``small_window`` stage."""
        params = self.params.smear
        corners_px = np.stack([d.corners_px for d in found])  # (M, 4, 2)
        sides_px = homography.mean_side_px(corners_px)
        pick = self.smear.pick(sides_px)
        marker = found[pick]
        H = homography.from_quad(self.layout.inner_corners_cells, marker.corners_px)
        widths_px = self.edges.step_widths_px(gray, H, sides_px[pick] / self.layout.inner_cells)
        # the smear widens both edges of a pair alike; one widened edge is more likely an occluder or a shadow
        if not max(min(widths_px[0], widths_px[2]), min(widths_px[1], widths_px[3])) >= params.min_edge_width_px:
            return [], False
        smear = self.smear.estimate(gray, marker.id, marker.corners_px)
        if smear is None or smear.length_px < params.min_recover_length_px:
            return [], True
        deconvolved = deconvolve(gray, smear, params.noise_to_signal)
        again = self._found_again(deconvolved, found)
        if self.params.square.small_window_every_frame:
            again += self._found_again(deconvolved, found + again, self.params.square.small_window_px)
        return again, False

    def _found_again(self, image: np.ndarray, found: list[Detection], window_px: int | None = None,
                     dim: bool | None = None) -> list[Detection]:
        """Markers the square path (1-5) finds in ``image`` (the frame deconvolved, or read with another
        threshold window ``window_px``) whose quads lie outside the grids of the markers already found."""
        candidates = self.square.find(image, window_px, dim)
        corners_px, from_aruco = candidates.corners_px, candidates.from_aruco
        if len(corners_px) and found:
            new = ~sampling.inside_grids(corners_px.mean(axis=1), self._grids_of(found), self.layout.n_cells)
            corners_px, from_aruco = corners_px[new], from_aruco[new]
        if len(corners_px) == 0:
            return []
        return [self._aligned(image, d) for d in self._decode_quads(image, corners_px, from_aruco)]

    def _pattern_inside(self, corners_px: np.ndarray, shape: tuple[int, int]) -> bool:
        """Whether the marker's whole printed grid lies inside the frame (the alignment saw all of it)."""
        n = self.layout.n_cells
        H = homography.from_quad(self.layout.inner_corners_cells, corners_px)
        outline = homography.project(H, np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]]))
        height, width = shape
        return bool(np.all((outline >= -0.5) & (outline <= [width - 0.5, height - 0.5])))

    def _read_grids(self, gray: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, sampling.GridLevels]:
        """(M, N, N) int8 classified grids of M homographies, and their levels."""
        cells = sampling.sample_cells(gray, H, self.layout.n_cells)
        levels = sampling.grid_levels(cells, self._border, self._gap)
        return sampling.classify_cells(cells, levels, self.params.sampling.ambiguity_fraction), levels

    def _edge_corners(self, gray: np.ndarray, quads: np.ndarray, rough: bool = False) -> np.ndarray:
        """(M, 4, 2) inner-square corners where the edge lines of M quads (M, 4, 2) meet (see ``edges``)."""
        H = homography.from_quads(self.layout.inner_corners_cells, quads)
        return self.edges.refine_square_corners(gray, H, quads, rough=rough)

    def _decode_quads(self, gray: np.ndarray, quads: np.ndarray, from_aruco: np.ndarray) -> list[Detection]:
        """Sample, classify and decode M candidate inner squares (M, 4, 2) (clockwise corners).

        Rejected quads come with whole-pixel corners, off by up to a few pixels on small markers:
        their corners are taken from the edges first (a wide pass, then a fine one). ArUco's
        sub-pixel corners read almost every identified grid as they are; a thin, oblique marker
        that does not decode is read again from its edges' corners (a fine pass; where ArUco's
        corners are off by a few pixels along its long sides, a wide pass then a fine one).
        """
        if len(quads) == 0:
            return []
        aruco_quads, quads = quads, quads.copy()  # ArUco's corners, kept for the passes below
        rough = ~from_aruco
        if rough.any():
            quads[rough] = self._edge_corners(gray, self._edge_corners(gray, quads[rough], rough=True))
        results = self._decode_grids(gray, quads)
        for wide_first in (False, True):
            again = np.flatnonzero(from_aruco & np.array([r is None for r in results]))
            if len(again) == 0:
                break
            start = self._edge_corners(gray, aruco_quads[again], rough=True) if wide_first else aruco_quads[again]
            quads[again] = self._edge_corners(gray, start)
            for i, result in zip(again, self._decode_grids(gray, quads[again])):
                results[i] = result
        detections = [Detection(symbol=r.symbol, id=r.id, corners_px=q[homography.CORNERS_FROM[r.rotation]], path="square",
                                corrected=r.corrected, quality=r.quality)
                      for r, q in zip(results, quads) if r is not None]
        return _unique(detections, self.params.duplicate_offset_fraction)

    def _decode_grids(self, gray: np.ndarray, quads: np.ndarray) -> list:
        """The decoder's result (or None) for the grid of each of M quads (M, 4, 2); None below the contrast floor."""
        grids, levels = self._read_grids(gray, homography.from_quads(self.layout.inner_corners_cells, quads))
        usable = levels.contrast >= self.params.sampling.min_contrast_gray
        results: list = [None] * len(quads)
        for i, result in zip(np.flatnonzero(usable), self.decoder.decode(grids[usable])):
            results[i] = result
        return results

    # ------------------------------------------------------------------ circles path

    def _circles_path(self, gray: np.ndarray, blobs: Blobs, found_H: np.ndarray | None,
                      clock: "_StageClock") -> list[Detection]:
        """Markers found by their corner circles among the frame's blobs, where no marker found already
        explains them (blobs inside the whole grid of a found marker, ``found_H`` (M, 3, 3) or None, are left out)."""
        params = self.params.circles
        if found_H is not None and len(blobs):
            blobs = blobs.subset(~sampling.inside_grids(blobs.centres_px, found_H, self.layout.n_cells))
        clock.lap("circles_blobs")
        candidates = assemble_candidates(blobs, corner_triples(blobs, self.layout, params), self.layout, params)
        clock.lap("circles_group")
        detections = self._decode_circle_candidates(gray, candidates)
        clock.lap("circles_decode")
        return _unique(detections, self.params.duplicate_offset_fraction)

    def _decode_circle_candidates(self, gray: np.ndarray, candidates: list[CircleCandidate]) -> list[Detection]:
        """Fit, refine on the edges, sample and decode circle candidates, all batched.

        The circle centres are read again in the frame first (the blobs were found at a pyramid
        level; even at full resolution a thresholded blob's centroid is 4x further off).
        """
        params, min_contrast_gray = self.params.circles, self.params.sampling.min_contrast_gray
        fitted = []
        for candidate in candidates:
            circles = self.layout.circles[candidate.circle_ids]
            grid_points = circles[:, :2]
            # the grouping fitted this homography to these very circles already (an affine map below)
            H = (candidate.H if len(grid_points) >= params.min_circles_for_homography
                 else homography.fit(grid_points, candidate.circles_px))
            if np.isfinite(H[2, 2]):
                centres = refine_centres(gray, H, circles)
                if np.isfinite(centres).all():
                    H = homography.fit(grid_points, centres)
                    candidate = CircleCandidate(candidate.circle_ids, centres, candidate.blob_index, H)
            if homography.fit_error_cells(H, grid_points, candidate.circles_px) <= params.max_fit_error_cells:
                fitted.append((candidate, H, (grid_points, candidate.circles_px)))
        if fitted:  # a first look at one sample per cell: a wrong pairing of corners reads as no marker
            # (the cells of corners whose circles are missing are likely hidden: left out)
            hidden = np.stack([self._hidden_by_corners[tuple(c.corners.tolist())] for c, _, _ in fitted])
            reading = self.probe.read(gray, np.stack([h for _, h, _ in fitted]), hidden)
            agreement = params.min_fixed_agreement_fraction
            plausible = ((reading.contrast >= min_contrast_gray) & (reading.border_black >= agreement)
                         & (reading.gap_white >= agreement) & self.decoder.plausible(reading.grid))
            fitted = [f for f, ok in zip(fitted, plausible) if ok]
        if not fitted:
            return []
        fits = self.edges.refine_homographies(gray, np.stack([h for _, h, _ in fitted]), [a for _, _, a in fitted])
        good = [i for i, fit in enumerate(fits) if fit.rms_cells <= params.max_edge_fit_rms_cells]
        if not good:
            return []
        candidates = [fitted[i][0] for i in good]
        H = np.stack([fits[i].H for i in good])
        grids, levels = self._read_grids(gray, H)
        probed = sampling.erase_near_bad_fixed_cells(grids, self._border, self._gap, self._codeword,
                                                     self.params.sampling.occlusion_reach_cells)
        # reading 1: occlusion probes; reading 2: also the region of the corners whose circles are missing
        readings, owners = [], []
        for i, candidate in enumerate(candidates):
            if levels.contrast[i] < min_contrast_gray:
                continue
            readings.append(probed[i])
            owners.append(i)
            region = self._hidden_by_corners[tuple(candidate.corners.tolist())] & self._codeword
            if region.any():
                readings.append(np.where(region, UNKNOWN, probed[i]).astype(np.int8))
                owners.append(i)
        if not readings:
            return []
        decoded = self.decoder.decode_groups(np.stack(readings), np.array(owners))
        detections = []
        for i, result in decoded.items():
            k, candidate = result.rotation, candidates[i]
            inner = homography.project(H[i], self.layout.inner_corners_cells)
            corner, slot = divmod(candidate.circle_ids, 3)
            sigma_px = circles_corner_sigma_px(fits[good[i]].rms_cells, _cell_px(inner, self.layout.inner_cells))
            detections.append(Detection(
                symbol=result.symbol, id=result.id, corners_px=inner[homography.CORNERS_FROM[k]], path="circles",
                corrected=result.corrected, quality=result.quality, circles_px=candidate.circles_px.copy(),
                circle_ids=3 * ((corner - k) % 4) + slot, corner_sigma_px=sigma_px))
        return detections


# Point noise of a detection from what the detector measured, calibrated on rendered scenes against
# their ground truth (benchmarks/bench_corner_sigma.py prints both constants again from new scenes):
# square path: the whole-pattern alignment's own corner covariance (MarkerFit.corner_cov_px2: the misfit's
# noise measured along the marker's edges plus the template's mismatch, through the normal equations with
# the image's own gradient; the scale: the noise of neighbouring template points is not independent), and
# where the alignment did not hold, its misfit (MarkerFit.residual, a share of the contrast);
# circles path: the RMS misfit of the edge-refined homography (EdgeFit.rms_cells).
SQUARE_COV_SCALE = 1.08
SQUARE_SIGMA_PER_RESIDUAL = 0.043
CIRCLES_SIGMA_PER_MISFIT = 2.5
# A square-path marker whose printed grid the frame's border cuts is aligned on what is visible:
# its corners are 2-3 times worse than its misfit says (rendered flights and cropped scenes).
CUT_SIGMA_FACTOR = 2.5


def square_corner_sigma_px(residual: float, cell_px: float) -> float | None:
    """Square path: sigma_px = k residual cell_px^(1/3) (None when the misfit was not measured)."""
    if not (np.isfinite(residual) and residual > 0):
        return None
    return float(SQUARE_SIGMA_PER_RESIDUAL * residual * np.cbrt(cell_px))


def square_corner_cov_px2(alignment_cov_px2: np.ndarray | None) -> np.ndarray | None:
    """Square path: the (8, 8) corner covariance, k^2 times the alignment's own (None if it has none or it is
    not finite and positive)."""
    if alignment_cov_px2 is None or not np.all(np.isfinite(alignment_cov_px2)):
        return None
    if not np.trace(alignment_cov_px2) > 0:
        return None
    return SQUARE_COV_SCALE ** 2 * alignment_cov_px2


def circles_corner_sigma_px(rms_cells: float, cell_px: float) -> float | None:
    """Circles path: sigma_px = k rms_cells cell_px, the edge fit's misfit in pixels (None if unknown)."""
    if not (np.isfinite(rms_cells) and rms_cells > 0):
        return None
    return float(CIRCLES_SIGMA_PER_MISFIT * rms_cells * cell_px)


def _cell_px(corners_px: np.ndarray, inner_cells: int) -> float:
    """Mean side of the inner square in the image over its cells."""
    return float(homography.mean_side_px(corners_px)) / inner_cells


def _unique(detections: list[Detection], offset_fraction: float) -> list[Detection]:
    """Drop repeats of one marker (same id, centres closer than ``offset_fraction`` of a side), keeping the best."""
    if len(detections) < 2:
        return list(detections)
    kept: list[Detection] = []
    for d in sorted(detections, key=lambda d: -d.quality):
        centre = d.corners_px.mean(axis=0)
        side = np.linalg.norm(d.corners_px[1] - d.corners_px[0])
        if not any(k.id == d.id and np.linalg.norm(k.corners_px.mean(axis=0) - centre) < offset_fraction * side for k in kept):
            kept.append(d)
    return kept


def _as_gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise DetectorError(f"detect() needs an (H, W) uint8 grayscale image, got {image.shape} {image.dtype}")
    return np.ascontiguousarray(image)


class _StageClock:
    """Milliseconds per stage on the monotonic performance counter; a stage timed twice in a frame (the blob
    search beside ArUco, then the choice among its blobs) is the sum."""

    def __init__(self):
        self.stages_ms: dict[str, float] = {}
        self._last = time.perf_counter_ns()

    def lap(self, stage: str) -> None:
        now = time.perf_counter_ns()
        self.stages_ms[stage] = self.stages_ms.get(stage, 0.0) + (now - self._last) / 1e6
        self._last = now
