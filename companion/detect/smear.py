"""Detector stage: markers lost to motion blur, found again on the frame with its smear undone.

A linear smear of 9 px over cells of 4-6 px closes the one-cell white gap
between the inner square and the parity bands: ArUco finds no quad for the
marker at all (no threshold window or offset brings it back; a Wiener
deconvolution with the true smear does). Camera motion smears the whole
frame alike, so a marker found in the same frame shows the smear: its decoded
pattern, drawn into the frame through its homography and smeared by line
kernels of several lengths and directions, is compared with the image
(``SmearEstimator``); the kernel that matches best is the frame's smear.
Where it is at least ``min_length_px`` long, the frame is Wiener-deconvolved
with it (``deconvolve``) and the square path runs again on the result.

On a sharp frame this costs one small pattern drawing and five filters of
its patch (the no-smear kernel wins the first comparison); a frame without
any found marker is left as it is.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from companion.detect import homography
from companion.markers.layout import MarkerLayout, marker_image
from companion.params import require

TEMPLATE_PX_PER_CELL = 8
QUIET_ZONE_CELLS = 1


@dataclass(frozen=True)
class SmearParams:
    """Motion-smear recovery (``detect.smear``).

    recover: estimate the frame's smear on a found marker and, where it is
        long enough, look for markers again on the deconvolved frame.
    min_edge_width_px: the smear is looked for only where both edges of a
        pair of the found marker's inner square are at least this wide
        (``EdgeRefiner.step_widths_px``; sharp frames of the benchmark:
        1.9-3.1 px, 9 px smears 3.3-8.4 px, a Gaussian blur of 1.6 px 2.7-5.5 px).
    min_length_px, max_length_px: the shortest and longest smear looked for.
    min_recover_length_px: shorter smears are left alone (the square path
        reads them; a Gaussian lens blur of 1.6 px reads as a 4-6 px line).
    length_step_px, angle_steps: the kernels compared (lengths from
        ``min_length_px`` in this step; directions over 180 degrees, refined
        to half this step around the best).
    noise_to_signal: the Wiener filter's noise-to-signal power ratio.
    marker_side_px: the found marker's patch is compared at a scale where
        its inner side is about this (5 px cells: the smear still shows, the
        kernels stay small).
    """

    recover: bool = True
    min_edge_width_px: float = 3.3
    min_length_px: float = 4.0
    min_recover_length_px: float = 7.0
    max_length_px: float = 16.0
    length_step_px: float = 2.0
    angle_steps: int = 16
    noise_to_signal: float = 0.005
    marker_side_px: float = 40.0

    def __post_init__(self):
        require(self.min_edge_width_px > 0, "min_edge_width_px", "> 0", self.min_edge_width_px)
        require(self.min_length_px >= 1.0, "min_length_px", ">= 1", self.min_length_px)
        require(self.min_recover_length_px >= self.min_length_px, "min_recover_length_px", ">= min_length_px",
                self.min_recover_length_px)
        require(self.max_length_px >= self.min_length_px, "max_length_px", ">= min_length_px", self.max_length_px)
        require(self.length_step_px > 0, "length_step_px", "> 0", self.length_step_px)
        require(self.angle_steps >= 4, "angle_steps", ">= 4", self.angle_steps)
        require(self.noise_to_signal > 0, "noise_to_signal", "> 0", self.noise_to_signal)
        require(self.marker_side_px > 0, "marker_side_px", "> 0", self.marker_side_px)


@dataclass(frozen=True)
class Smear:
    """A linear smear: length_px along angle_rad (image x right, y down; 0..pi), and how well it matched
    (correlation of the smeared pattern with the image, 0..1)."""

    length_px: float
    angle_rad: float
    correlation: float


def line_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """(k, k) float32 kernel of a line segment of ``length_px`` along ``angle_rad``, centred, sum 1.

    Evenly spaced points of the segment spread over the pixel grid with bilinear weights.
    """
    half = int(math.ceil(length_px / 2)) + 1
    size = 2 * half + 1
    steps = np.linspace(-length_px / 2, length_px / 2, max(int(length_px * 8), 1) + 1)
    x, y = half + steps * math.cos(angle_rad), half + steps * math.sin(angle_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((size + 1, size + 1), np.float64)
    for dx, dy, weight in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), weight)
    return (kernel[:size, :size] / kernel.sum()).astype(np.float32)


class SmearEstimator:
    """The frame's smear, measured on one decoded marker (its pattern is known exactly).

    The marker's patch is read at a scale where its inner side is about
    ``marker_side_px`` (never enlarged): the kernels stay small and the
    search cheap: eight directions at three lengths, then the best one's
    neighbours (a length step and half a direction step, then a quarter
    direction step, then half a length step). No smear wins
    against all of them on a sharp patch. The detector asks only where the
    marker's edges are wide (``SmearParams.min_edge_width_px``).
    """

    def __init__(self, layout: MarkerLayout, params: SmearParams):
        self.layout = layout
        self.params = params
        self._templates: dict[int, np.ndarray] = {}
        self._kernels: dict[tuple[float, int], np.ndarray] = {}
        ppc, q = TEMPLATE_PX_PER_CELL, QUIET_ZONE_CELLS
        # template pixel (x, y) -> grid (u, v): u = (x + 0.5) / ppc - q
        self._template_to_grid = np.array([[1 / ppc, 0, 0.5 / ppc - q], [0, 1 / ppc, 0.5 / ppc - q], [0, 0, 1]])
        n = layout.n_cells
        self._outline_cells = np.array([[-q, -q], [n + q, -q], [n + q, n + q], [-q, n + q]], float)

    def pick(self, sides_px) -> int:
        """Index of the marker (mean inner sides (M,), pixels) to measure the smear on: the smallest at least
        ``marker_side_px`` (read without scaling), else the largest."""
        sides = np.asarray(sides_px, float)
        big = sides >= self.params.marker_side_px
        return int(np.flatnonzero(big)[np.argmin(sides[big])]) if big.any() else int(np.argmax(sides))

    def estimate(self, gray: np.ndarray, marker_id: int, corners_px: np.ndarray) -> Smear | None:
        """The smear that best turns the marker's pattern into the image, or None for a sharp (or unreadable) one.

        corners_px: (4, 2) the marker's inner corners TL, TR, BR, BL (upright, as detected).
        """
        p = self.params
        patch = self._patch(gray, marker_id, np.asarray(corners_px, float))
        if patch is None:
            return None
        observed, drawn, inside, scale = patch
        seen = observed[inside] - observed[inside].mean()
        seen_power = float(seen @ seen)

        def explained(model: np.ndarray) -> float:
            # squared correlation of the model with the image: the share an affine fit explains
            m = model[inside]
            m = m - m.mean()
            power = float(m @ m) * seen_power
            return float((seen @ m) ** 2 / power) if power > 0 else 0.0

        def score(length_px: float, angle_step: int) -> tuple[float, float, int]:
            kernel = self._kernel(length_px * scale, angle_step % steps)
            return explained(cv2.filter2D(drawn, -1, kernel)), float(length_px), angle_step % steps

        steps = 2 * p.angle_steps  # directions of the kernel table over 180 degrees (fine steps)
        sharp = explained(drawn)
        lengths = np.arange(p.min_length_px, p.max_length_px + 1e-9, p.length_step_px)
        coarse = lengths[len(lengths) // 6::max(len(lengths) // 3, 1)]
        best = max(score(length, a) for length in coarse for a in range(0, steps, 4))
        near = lengths[np.abs(lengths - best[1]) <= p.length_step_px]
        best = max([best] + [score(length, a) for length in near for a in range(best[2] - 2, best[2] + 3, 2)])
        best = max([best] + [score(best[1], best[2] + a) for a in (-1, 1)])
        # and half a length step either way
        best = max([best] + [score(length, best[2])
                             for length in (best[1] - p.length_step_px / 2, best[1] + p.length_step_px / 2)
                             if p.min_length_px <= length <= p.max_length_px])
        if best[0] <= sharp:
            return None
        return Smear(best[1], best[2] * math.pi / steps, best[0])

    def _kernel(self, length_px: float, angle_step: int) -> np.ndarray:
        key = (round(length_px * 4) / 4, angle_step)
        kernel = self._kernels.get(key)
        if kernel is None:
            kernel = self._kernels[key] = line_kernel(max(key[0], 0.5), angle_step * math.pi / (2 * self.params.angle_steps))
        return kernel

    def _patch(self, gray: np.ndarray, marker_id: int, corners_px: np.ndarray):
        """(observed, drawn, inside, scale) around the marker at ``scale`` (<= 1), or None if it leaves the frame.

        observed, drawn: float32 patches, the image and the marker's pattern (with its white quiet zone)
        through its homography, lightly blurred for the lens; inside: bool, the pixels at least the
        longest half smear inside the drawn pattern.
        """
        H = homography.from_quad(self.layout.inner_corners_cells, corners_px)
        outline = homography.project(H, self._outline_cells)
        side_px = float(homography.mean_side_px(corners_px))
        scale = min(1.0, self.params.marker_side_px / side_px)
        reach = int(math.ceil(self.params.max_length_px / 2)) + 2
        if not np.isfinite(outline).all():
            return None
        x0, y0 = np.floor(outline.min(axis=0)).astype(int) - reach
        x1, y1 = np.ceil(outline.max(axis=0)).astype(int) + reach
        height, width = gray.shape
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        if x1 - x0 < 8 or y1 - y0 < 8:
            return None
        crop = gray[y0:y1 + 1, x0:x1 + 1]
        size = (max(int(round(crop.shape[1] * scale)), 1), max(int(round(crop.shape[0] * scale)), 1))
        observed = (cv2.resize(crop, size, interpolation=cv2.INTER_AREA) if scale < 1 else crop).astype(np.float32)
        # frame pixel x -> patch pixel p = s (x - x0 + 0.5) - 0.5
        to_patch = np.array([[scale, 0, scale * (0.5 - x0) - 0.5], [0, scale, scale * (0.5 - y0) - 0.5], [0, 0, 1]])
        to_patch = to_patch @ H @ self._template_to_grid
        template = self._template(marker_id)
        drawn = cv2.GaussianBlur(cv2.warpPerspective(template, to_patch, size, flags=cv2.INTER_AREA,
                                                     borderMode=cv2.BORDER_REPLICATE), (0, 0), 0.7)
        covered = cv2.warpPerspective(np.full(template.shape, 255, np.uint8), to_patch, size, flags=cv2.INTER_NEAREST)
        margin = 2 * int(math.ceil(reach * scale)) - 1
        inside = cv2.erode(covered, np.ones((margin, margin), np.uint8)) > 0
        if inside.sum() < 64:
            return None
        return observed, drawn, inside, scale

    def _template(self, marker_id: int) -> np.ndarray:
        template = self._templates.get(marker_id)
        if template is None:
            image = marker_image(self.layout, marker_id, TEMPLATE_PX_PER_CELL, quiet_zone_cells=QUIET_ZONE_CELLS)
            template = self._templates[marker_id] = image.astype(np.float32)
        return template


def deconvolve(gray: np.ndarray, smear: Smear, noise_to_signal: float) -> np.ndarray:
    """(H, W) uint8: the frame Wiener-deconvolved with the smear's line kernel.

    X = K Y / (K^2 + nsr), on the frame mirrored at its border (no wrap-around seam). The centred
    line kernel's spectrum is real: K(f) = sinc(L f . d) sinc^2(fx) sinc^2(fy), the segment along
    the unit direction d times the bilinear spread of its points (``line_kernel``), f in cycles per pixel.
    """
    pad = int(math.ceil(smear.length_px)) + 2
    height, width = gray.shape
    rows = scipy.fft.next_fast_len(height + 2 * pad, real=True)
    cols = scipy.fft.next_fast_len(width + 2 * pad, real=True)
    padded = cv2.copyMakeBorder(gray, pad, rows - height - pad, pad, cols - width - pad, cv2.BORDER_REFLECT)
    fy = scipy.fft.fftfreq(rows).astype(np.float32)[:, None]
    fx = scipy.fft.rfftfreq(cols).astype(np.float32)[None, :]
    along = fx * np.float32(math.cos(smear.angle_rad)) + fy * np.float32(math.sin(smear.angle_rad))
    K = np.sinc(np.float32(smear.length_px) * along) * np.sinc(fx) ** 2 * np.sinc(fy) ** 2
    spectrum = scipy.fft.rfft2(padded.astype(np.float32))
    spectrum *= K / (K * K + np.float32(noise_to_signal))
    restored = scipy.fft.irfft2(spectrum, s=(rows, cols))
    return np.clip(restored[pad:pad + height, pad:pad + width], 0, 255).astype(np.uint8)
