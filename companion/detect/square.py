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

from dataclasses import dataclass

import cv2
import numpy as np

from companion.detect import homography, sampling
from companion.markers.layout import MarkerLayout


@dataclass(frozen=True)
class SquareParams:
    """ArUco and pre-filter settings of the square path.

    error_correction_rate: ArUco's own bit correction (0..1 of the
        dictionary's 6 correctable bits); everything it cannot identify is
        still RS-decoded from the rejected quads.
    decode_rejected: RS-decode marker-like rejected quads too.
    min_contrast: white - black levels (gray levels) for a marker-like quad.
    min_fixed_agreement: fraction of border cells that must read black and of
        gap-ring cells that must read white.
    min_side_px: mean side of a rejected quad worth decoding (2.5 px per
        cell; smaller quads are mostly single cells of markers already found).
    threshold_windows_px: ArUco's adaptive-threshold windows (min, max, step).
        OpenCV's default (3, 23, 10) thresholds three times; (7, 27, 20)
        twice, about 25 % faster with the same or better recall here
        (docs/detector.md has the measurement).
    min_perimeter_rate: ArUco's smallest quad perimeter over the image's
        larger side (OpenCV: 0.03). 0.08 is a 13 px inner side at 640 px,
        26 px at 1280 px (under 3 px per cell: too small to read the grid
        anyway); skipping the many small contours saves 5-15 %.
    threshold_constant: ArUco's adaptive-threshold offset (OpenCV's 7). 5
        finds more small markers in dim frames (low light 97.8 -> 99.3 % in
        the benchmark) but costs 25 % more ArUco time on every frame (0.55 ms
        at 640x480 and 1280x720): not the default.
    """

    error_correction_rate: float = 0.6
    decode_rejected: bool = True
    min_contrast: float = 20.0
    min_fixed_agreement: float = 0.75
    min_side_px: float = 20.0
    threshold_windows_px: tuple[int, int, int] = (7, 27, 20)
    min_perimeter_rate: float = 0.08
    threshold_constant: float = 7.0


@dataclass(frozen=True)
class SquareCandidates:
    """Quads from the square path.

    corners_px: (M, 4, 2) float64 inner-square corners, clockwise in the image.
    from_aruco: (M,) bool, True where ArUco identified the quad (its corners
        are sub-pixel refined; the others are refined after decoding).
    """

    corners_px: np.ndarray
    from_aruco: np.ndarray


def make_aruco_detector(layout: MarkerLayout, params: SquareParams) -> cv2.aruco.ArucoDetector:
    """ArucoDetector for the layout's inner marker, sub-pixel corners, no border margin."""
    aruco_params = cv2.aruco.DetectorParameters()
    aruco_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    aruco_params.minDistanceToBorder = 0
    aruco_params.errorCorrectionRate = params.error_correction_rate
    aruco_params.adaptiveThreshWinSizeMin, aruco_params.adaptiveThreshWinSizeMax, \
        aruco_params.adaptiveThreshWinSizeStep = params.threshold_windows_px
    aruco_params.minMarkerPerimeterRate = params.min_perimeter_rate
    aruco_params.adaptiveThreshConstant = params.threshold_constant
    return cv2.aruco.ArucoDetector(layout.dictionary.aruco(), aruco_params)


class SquareFinder:
    """Finds candidate inner squares in a grayscale frame."""

    def __init__(self, layout: MarkerLayout, params: SquareParams, screen=None):
        """screen: optional (M, N, N) int8 grids -> (M,) bool, a quick test of a rejected quad's
        codeword read at one sample per cell (the detector passes its decoder's ``plausible``)."""
        self.layout = layout
        self.params = params
        self._screen = screen
        self._aruco = make_aruco_detector(layout, params)
        self._inner_corners = layout.inner_corners_cells
        self._probe = sampling.CellProbe(layout)

    def find(self, gray: np.ndarray) -> SquareCandidates:
        corners, _, rejected = self._aruco.detectMarkers(gray)
        accepted = np.array(corners, dtype=np.float64).reshape(-1, 4, 2)
        others = np.array(rejected, dtype=np.float64).reshape(-1, 4, 2)
        if self.params.decode_rejected and len(others):
            others = others[(_mean_side(others) >= self.params.min_side_px) & ~self._within(others, accepted)]
            others = others[self.marker_like(gray, others)] if len(others) else others
        else:
            others = others[:0]
        return SquareCandidates(np.concatenate([accepted, others]),
                                np.r_[np.ones(len(accepted), bool), np.zeros(len(others), bool)])

    def _within(self, quads: np.ndarray, markers: np.ndarray) -> np.ndarray:
        """(M,) bool: quad centres inside the whole grid of an identified marker (its own cells)."""
        if len(markers) == 0:
            return np.zeros(len(quads), bool)
        H = homography.from_quads(self._inner_corners, markers)
        return sampling.inside_grids(quads.mean(axis=1), H, self.layout.n_cells)

    def marker_like(self, gray: np.ndarray, quads: np.ndarray) -> np.ndarray:
        """(M,) bool: quads that read like an RS marker at one sample per cell.

        The border must read black and the gap ring white (``min_fixed_agreement``
        of their cells), with ``min_contrast``; and the codeword cells must be
        mixed (every marker has 35-65 % black codeword cells; a blob over the
        data moves that by ~10 %): a plain dark or light square is no marker;
        and, with a screen, the codeword read this roughly must be near a marker's.
        """
        H = homography.from_quads(self._inner_corners, quads)
        r = self._probe.read(gray, H)
        p = self.params
        ok = ((r.contrast >= p.min_contrast) & (r.border_black >= p.min_fixed_agreement)
              & (r.gap_white >= p.min_fixed_agreement) & (r.dark_codeword >= 0.15) & (r.dark_codeword <= 0.85))
        if self._screen is not None and ok.any():
            ok[ok] = self._screen(r.grid[ok])
        return ok


def _mean_side(quads: np.ndarray) -> np.ndarray:
    """(M,) mean side of M quads (M, 4, 2)."""
    return np.linalg.norm(quads - np.roll(quads, -1, axis=1), axis=2).mean(axis=1)
