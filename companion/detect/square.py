"""Detector stage: the square path. OpenCV ArUco finds the inner black squares.

``cv2.aruco.ArucoDetector`` with the RS marker dictionary (as a custom ArUco
dictionary) does the adaptive thresholding, contour and quad search, and
sub-pixel corner refinement inside OpenCV. We keep two kinds of quads:

* *accepted*: ArUco identified the inner marker (it may have mis-corrected
  bits silently; the RS decode that follows checks every one);
* *rejected*: quads ArUco could not identify. An intact border around a
  damaged data area (a blob, glare) lands here, and the RS parity ring can
  still decode it. A cheap batched pre-filter on the fixed cells (border
  black, gap ring white, enough contrast) keeps only marker-like quads.

Both come back as candidate quads with the inner-square corners in the
order ArUco gives them (clockwise in the image, starting anywhere for a
rejected quad); the decode finds the rotation.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from companion.detect import homography, sampling
from companion.markers.layout import MarkerLayout
from companion.params import require


# one image size's four: normal or dim offset, usual or small window (two sizes, as the benchmark mixes, fit)
ARUCO_DETECTORS_KEPT = 8
# the noise test reads every ROW_STRIDE-th row through a second difference along it
ROW_STRIDE = 24
SECOND_DIFFERENCE = np.array([[1.0, -2.0, 1.0]])
# pixel noise of sd s gives second differences of sd s * sqrt(6); 20 % of them exceed 1.2816 of that
NOISE_TAIL_SD, NOISE_TAIL_FRACTION = 1.2816, 0.2


@dataclass(frozen=True)
class SquareParams:
    """ArUco and pre-filter settings of the square path.

    aruco_error_correction_rate: ArUco's own bit correction (0..1 of the
        dictionary's correctable bits); everything it cannot identify is
        still RS-decoded from the rejected quads.
    decode_rejected: RS-decode marker-like quads ArUco rejected (blobs on data).
    aruco_threshold_windows_px: ArUco's adaptive-threshold windows (min, max,
        step), odd sizes. OpenCV's default (3, 23, 10) thresholds three times;
        (15, 15, 10) once: 40 % of OpenCV's time on one thread, with the same
        recall here (docs/detector.md has the measurement).
    aruco_threshold_constant_gray: ArUco's adaptive-threshold offset (OpenCV's
        7), in a frame of normal brightness. Lower values find more small
        markers in dim frames but cost ArUco time on every frame (5: 25 % more).
    dim_frame_mean_gray, dim_threshold_constant_gray: a frame whose mean gray
        level is below ``dim_frame_mean_gray`` is thresholded with the offset
        ``dim_threshold_constant_gray`` instead: the offset is in gray levels,
        and a marker in a frame a sixth as bright has a sixth of the contrast
        (the benchmark's low light, mean 16-21: 266 -> 268 of 270 markers
        with 4, for 50 % more time in those frames; 3 and 2 found no more).
    small_window_px: the threshold window of the square path's second pass
        (the detector's ``small_window`` stage) over a frame that is round
        blurred (found markers' edges wide, no line smear to undo), dim, or
        noisy: at 15 px the local mean of a small blurred marker closes its
        white gap ring, and a grainy or dim small marker's quad breaks up
        (benchmark: Gaussian blur 290 -> 291 of 294 markers; noise 276 -> 277
        of 277, low light 268 -> 269 of 270).
    noisy_frame_sd_gray: pixel noise (standard deviation, gray levels) from
        which a frame is called noisy and read again with ``small_window_px``
        (the benchmark's noise is sd 12; a sharp clean frame measures ~2).
    small_window_every_frame: read every frame again with ``small_window_px``,
        not only round blurred, dim or noisy ones (``DetectorParams.for_footage``:
        footage processed offline, recall before speed). A walk's small
        markers (20-30 px) smeared by 1.5-3 px are lost to the usual window
        without the frame looking blurred, dim or noisy; on bench_survey's
        640x480 walk the pass found 43 of 120 such markers missed and the
        one-anchor survey's median error fell from 11.2 to 8.6 mm.
    small_window_enough_markers: in a frame with expected places (the
        daemon's), as many markers found as this and the ``small_window`` pass
        is skipped: two markers fix the pose well, and on a noisy rendered
        aisle the pass on every frame found 17-22 % more markers for a third
        of the daemon's frame rate, with no frame more posed and no pose
        better (``benchmarks/bench_noisy_frames.py``).
    min_side_px: the smallest inner square the path reads, mean side in
        pixels, whatever the image size (ArUco's smallest quad perimeter is
        4 x this). 12, as ArUco's relative default (0.08 of the long side)
        was at 640 px: 19-20 px markers of the simulated hover flights are
        read (at 20 they were not); 1.5 px per cell is about the least that
        decodes.
    min_fixed_agreement_fraction: of the border cells that must read black
        and of the gap-ring cells that must read white (rejected quads).
    min_dark_codeword_fraction, max_dark_codeword_fraction: the share of a
        rejected quad's codeword cells that read black (every marker has
        35-65 %; a blob over the data moves that by ~10 %; a plain dark or
        light square is no marker).
    """

    aruco_error_correction_rate: float = 0.6
    decode_rejected: bool = True
    aruco_threshold_windows_px: tuple[int, int, int] = (15, 15, 10)
    aruco_threshold_constant_gray: float = 7.0
    dim_frame_mean_gray: float = 50.0
    dim_threshold_constant_gray: float = 4.0
    small_window_px: int = 7
    noisy_frame_sd_gray: float = 8.0
    small_window_every_frame: bool = False
    small_window_enough_markers: int = 2
    min_side_px: float = 12.0
    min_fixed_agreement_fraction: float = 0.75
    min_dark_codeword_fraction: float = 0.15
    max_dark_codeword_fraction: float = 0.85

    def __post_init__(self):
        require(0.0 <= self.aruco_error_correction_rate <= 1.0, "aruco_error_correction_rate", "in [0, 1]",
                self.aruco_error_correction_rate)
        windows = tuple(self.aruco_threshold_windows_px)
        require(len(windows) == 3 and all(isinstance(w, int) for w in windows) and windows[0] >= 3
                and windows[0] % 2 == 1 and windows[1] >= windows[0] and windows[2] >= 1,
                "aruco_threshold_windows_px", "[min, max, step] integers with an odd min >= 3, max >= min and "
                "step >= 1", self.aruco_threshold_windows_px)
        object.__setattr__(self, "aruco_threshold_windows_px", windows)
        require(self.min_side_px > 0, "min_side_px", "> 0", self.min_side_px)
        require(isinstance(self.small_window_px, int) and self.small_window_px >= 3 and self.small_window_px % 2,
                "small_window_px", "an odd integer >= 3", self.small_window_px)
        require(self.noisy_frame_sd_gray > 0, "noisy_frame_sd_gray", "> 0", self.noisy_frame_sd_gray)
        require(isinstance(self.small_window_enough_markers, int) and self.small_window_enough_markers >= 1,
                "small_window_enough_markers", "an integer >= 1", self.small_window_enough_markers)
        require(0 <= self.dim_frame_mean_gray <= 255, "dim_frame_mean_gray", "in [0, 255]", self.dim_frame_mean_gray)
        for key in ("min_fixed_agreement_fraction", "min_dark_codeword_fraction", "max_dark_codeword_fraction"):
            require(0.0 <= getattr(self, key) <= 1.0, key, "in [0, 1]", getattr(self, key))


@dataclass(frozen=True)
class SquareCandidates:
    """Quads from the square path.

    corners_px: (M, 4, 2) float64 inner-square corners, clockwise in the image.
    from_aruco: (M,) bool, True where ArUco identified the quad (its corners
        are sub-pixel refined; the others are refined after decoding).
    """

    corners_px: np.ndarray
    from_aruco: np.ndarray


def make_aruco_detector(layout: MarkerLayout, params: SquareParams, image_side_px: int) -> cv2.aruco.ArucoDetector:
    """ArucoDetector for the layout's inner marker, sub-pixel corners, no border margin, for images
    whose larger side is ``image_side_px`` (OpenCV sets the smallest quad as a share of it)."""
    aruco_params = cv2.aruco.DetectorParameters()
    aruco_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    aruco_params.minDistanceToBorder = 0
    aruco_params.errorCorrectionRate = params.aruco_error_correction_rate
    aruco_params.adaptiveThreshWinSizeMin, aruco_params.adaptiveThreshWinSizeMax, \
        aruco_params.adaptiveThreshWinSizeStep = params.aruco_threshold_windows_px
    aruco_params.minMarkerPerimeterRate = 4.0 * params.min_side_px / image_side_px
    aruco_params.adaptiveThreshConstant = params.aruco_threshold_constant_gray
    return cv2.aruco.ArucoDetector(layout.dictionary.aruco(), aruco_params)


class SquareFinder:
    """Finds candidate inner squares in a grayscale frame."""

    def __init__(self, layout: MarkerLayout, params: SquareParams, min_contrast_gray: float, screen=None):
        """min_contrast_gray: white - black gray levels of a marker-like rejected quad.
        screen: optional (M, N, N) int8 grids -> (M,) bool, a quick test of a rejected quad's
        codeword read at one sample per cell (the detector passes its decoder's ``plausible``)."""
        self.layout = layout
        self.params = params
        self.min_contrast_gray = min_contrast_gray
        self._screen = screen
        self._aruco_detectors: dict[tuple, cv2.aruco.ArucoDetector] = {}
        self._inner_corners = layout.inner_corners_cells
        self._probe = sampling.CellProbe(layout)

    def is_dim(self, gray: np.ndarray) -> bool:
        """Whether the frame's mean gray level (of every 8th row) is below ``dim_frame_mean_gray``."""
        return cv2.mean(gray[::8])[0] < self.params.dim_frame_mean_gray

    def is_noisy(self, gray: np.ndarray) -> bool:
        """Whether the frame's pixel noise is about ``noisy_frame_sd_gray`` or more, judged on every
        ``ROW_STRIDE``-th row: edges and texture give large second differences along a row in a few
        places, pixel noise everywhere, so the test is the share of them beyond the noise's 80th percentile."""
        rows = np.ascontiguousarray(gray[ROW_STRIDE // 3::ROW_STRIDE], dtype=np.float32)
        second = cv2.filter2D(rows, -1, SECOND_DIFFERENCE, borderType=cv2.BORDER_REPLICATE)
        limit = NOISE_TAIL_SD * np.sqrt(6.0) * self.params.noisy_frame_sd_gray
        return bool(np.count_nonzero(np.abs(second) > limit) > NOISE_TAIL_FRACTION * second.size)

    def find(self, gray: np.ndarray, window_px: int | None = None, dim: bool | None = None) -> SquareCandidates:
        """Candidate inner squares; window_px: one ArUco threshold window of this size instead of
        ``aruco_threshold_windows_px`` (``small_window_px``: the detector's second pass); dim: whether the
        frame is dim (``is_dim``), when already known."""
        return self.candidates(gray, *self.aruco_quads(gray, window_px, dim))

    def aruco_quads(self, gray: np.ndarray, window_px: int | None = None,
                    dim: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """ArUco's own step of ``find`` (one OpenCV call, which leaves the interpreter to other threads):
        (A, 4, 2) identified and (R, 4, 2) rejected quads, float64."""
        dim = self.is_dim(gray) if dim is None else dim
        constant = self.params.dim_threshold_constant_gray if dim else self.params.aruco_threshold_constant_gray
        windows = self.params.aruco_threshold_windows_px if window_px is None else (window_px, window_px, 10)
        corners, _, rejected = self._aruco(max(gray.shape), constant, windows).detectMarkers(gray)
        return (np.array(corners, dtype=np.float64).reshape(-1, 4, 2),
                np.array(rejected, dtype=np.float64).reshape(-1, 4, 2))

    def candidates(self, gray: np.ndarray, accepted: np.ndarray, rejected: np.ndarray) -> SquareCandidates:
        """The rest of ``find``: ArUco's identified quads, and its rejected ones that read like a marker."""
        others = rejected
        if self.params.decode_rejected and len(others):
            others = others[(homography.mean_side_px(others) >= self.params.min_side_px) & ~self._within(others, accepted)]
            others = others[self.marker_like(gray, others)] if len(others) else others
        else:
            others = others[:0]
        return SquareCandidates(np.concatenate([accepted, others]),
                                np.r_[np.ones(len(accepted), bool), np.zeros(len(others), bool)])

    def _aruco(self, image_side_px: int, threshold_constant_gray: float,
               windows_px: tuple[int, int, int]) -> cv2.aruco.ArucoDetector:
        """The ArUco detector for images of this larger side, threshold offset and windows (a few kept:
        frames rarely change size)."""
        key = (image_side_px, threshold_constant_gray, windows_px)
        detector = self._aruco_detectors.get(key)
        if detector is None:
            if len(self._aruco_detectors) >= ARUCO_DETECTORS_KEPT:
                self._aruco_detectors.pop(next(iter(self._aruco_detectors)))
            params = replace(self.params, aruco_threshold_windows_px=windows_px,
                             aruco_threshold_constant_gray=threshold_constant_gray)
            detector = self._aruco_detectors[key] = make_aruco_detector(self.layout, params, image_side_px)
        return detector

    def _within(self, quads: np.ndarray, markers: np.ndarray) -> np.ndarray:
        """(M,) bool: quad centres inside the whole grid of an identified marker (its own cells)."""
        if len(markers) == 0:
            return np.zeros(len(quads), bool)
        H = homography.from_quads(self._inner_corners, markers)
        return sampling.inside_grids(quads.mean(axis=1), H, self.layout.n_cells)

    def marker_like(self, gray: np.ndarray, quads: np.ndarray) -> np.ndarray:
        """(M,) bool: quads that read like an RS marker at one sample per cell.

        The border must read black and the gap ring white (``min_fixed_agreement_fraction``
        of their cells), with ``min_contrast_gray``; the codeword cells must be
        mixed (``min_dark_codeword_fraction`` to ``max_dark_codeword_fraction``
        of them black); and, with a screen, the codeword read this roughly must
        be near a marker's.
        """
        H = homography.from_quads(self._inner_corners, quads)
        r = self._probe.read(gray, H)
        p = self.params
        ok = ((r.contrast >= self.min_contrast_gray) & (r.border_black >= p.min_fixed_agreement_fraction)
              & (r.gap_white >= p.min_fixed_agreement_fraction) & (r.dark_codeword >= p.min_dark_codeword_fraction)
              & (r.dark_codeword <= p.max_dark_codeword_fraction))
        if self._screen is not None and ok.any():
            ok[ok] = self._screen(r.grid[ok])
        return ok

