"""Sub-pixel marker corners: candidate refinements against the renderer's exact ground truth.

Scenes come from ``companion.sim.scenes.random_marker_scene`` (640x480, 70 degree
field of view, three RS markers per scene, tilts up to 60 degrees) per size
band of the inner square and per image condition. The initial corners are
what the detector's square path gets today: OpenCV ``ArucoDetector`` with
the 6x6 dictionary, ``minDistanceToBorder = 0`` and ``CORNER_REFINE_SUBPIX``.
Each detection matched (by id) to a fully visible marker is then refined by

* ``aruco_subpix``: the initial corners themselves;
* ``cornersubpix``: ``cv2.cornerSubPix`` again on the 4 corners, window half
  a cell (what the detector does for quads ArUco did not identify): the
  time baseline;
* ``aruco_contour``, ``aruco_apriltag``: ArUco run again with
  ``CORNER_REFINE_CONTOUR`` / ``CORNER_REFINE_APRILTAG`` (their time is the
  extra ``detectMarkers`` time over ``CORNER_REFINE_NONE``, per marker);
* ``border_lines``: sub-pixel edge points across the four outer edges of the
  inner square (profiles through the homography, one remap), a line fitted
  to each side, corners where the lines meet; two rounds;
* ``ecc``: ``cv2.findTransformECC`` (``MOTION_HOMOGRAPHY``) between the marker
  drawn at the image's scale and the frame, from the initial corners;
* ``lk``: ``companion.detect.refine.MarkerRefiner`` (the package's choice:
  inverse-compositional Lucas-Kanade on the decoded marker's edge template).

Errors are Euclidean distances of each corner from the truth, in pixels;
times are the median per marker of the second call (template caches warm),
and ``x_subpix`` is that time over ``cornersubpix``'s in the same row.
Smaller tables follow: ``lk`` started from the corners ``Detector`` gives
today (square path), lens distortion (``lk`` and the whole ``Detector``,
each without and with the camera model; an undistorted row for reference),
and the detector's occluded (circles-path) detections.

    PYTHONPATH=. python benchmarks/bench_refine.py [--quick] [--scenes 10] [--seed 1]
"""
from __future__ import annotations

import argparse
import math
import sys
from collections import Counter, defaultdict
from dataclasses import dataclass

import cv2
import numpy as np

from common import aruco_detector, aruco_found, best_of
from companion.geometry import frames
from companion.sim import degrade
from companion.sim import raster
from companion.sim.scenes import random_marker_scene
from companion.geometry.camera import CameraModel, intrinsics_from_hfov
from companion.markers.dictionary import load_dictionary
from companion.markers.layout import MarkerLayout, marker_image
from companion.detect.refine import MarkerRefiner

IMAGE_SIZE = (640, 480)
BANDS_PX = ((20, 45), (45, 70), (70, 100), (100, 150))
CONDITIONS = ("clean", "gaussian_blur", "motion_blur", "noise", "low_light", "jpeg")
MAX_TILT_DEG = 60.0
MARKERS_PER_SCENE = 3
METHODS = ("aruco_subpix", "cornersubpix", "aruco_contour", "aruco_apriltag", "border_lines", "ecc", "lk")
ARUCO_METHODS = {"aruco_subpix": cv2.aruco.CORNER_REFINE_SUBPIX, "aruco_contour": cv2.aruco.CORNER_REFINE_CONTOUR,
                 "aruco_apriltag": cv2.aruco.CORNER_REFINE_APRILTAG}


@dataclass
class Sample:
    """One detected marker: the frame, its id, its initial (ArUco SUBPIX) corners and the truth."""

    image: np.ndarray
    marker_id: int
    initial_px: np.ndarray
    truth_px: np.ndarray


# ------------------------------------------------------------ candidate methods

def corner_subpix(gray: np.ndarray, corners_px: np.ndarray) -> np.ndarray:
    """cv2.cornerSubPix on the four corners, window half a cell (2-6 px)."""
    cell_px = np.linalg.norm(corners_px - np.roll(corners_px, -1, axis=0), axis=1).mean() / 8
    half = int(np.clip(round(cell_px * 0.5), 2, 6))
    points = corners_px.astype(np.float32).reshape(-1, 1, 2).copy()
    criteria = (cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    cv2.cornerSubPix(gray, points, (half, half), (-1, -1), criteria)
    return points.reshape(4, 2).astype(np.float64)


class BorderLines:
    """Lines fitted to sub-pixel edge points across the inner square's four outer edges."""

    def __init__(self, layout: MarkerLayout, step_cells: float = 0.25, half_cells: float = 0.7, samples: int = 15):
        lo, hi = layout.inner_origin, layout.inner_origin + layout.inner_cells
        along = lo + np.arange(0.5, layout.inner_cells - 0.5 + 1e-9, step_cells)
        k = len(along)
        self.grid_corners = layout.inner_corners_cells.astype(np.float32)
        # sides top, right, bottom, left; each point on the edge with its outward normal (grid cells)
        self.on_edge = np.stack([np.column_stack([along, np.full(k, lo)]), np.column_stack([np.full(k, hi), along]),
                                 np.column_stack([along, np.full(k, hi)]), np.column_stack([np.full(k, lo), along])])
        self.normals = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
        self.offsets = np.linspace(-half_cells, half_cells, samples)
        # (4, k, S, 2) profile points, inside (black border) to outside (white gap)
        self.profiles = self.on_edge[:, :, None, :] + self.offsets[None, None, :, None] * self.normals[:, None, None, :]

    def refine(self, gray: np.ndarray, corners_px: np.ndarray, rounds: int = 2) -> np.ndarray:
        for _ in range(rounds):
            H = cv2.getPerspectiveTransform(self.grid_corners, corners_px.astype(np.float32))
            xy = cv2.perspectiveTransform(self.profiles.reshape(1, -1, 2), H).astype(np.float32)
            values = cv2.remap(gray.astype(np.float32), xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=np.nan).reshape(self.profiles.shape[:3])
            black, white = values[..., :2].mean(axis=-1), values[..., -2:].mean(axis=-1)
            mid = (black + white) / 2
            above = values >= mid[..., None]
            index = np.clip(np.argmax(above, axis=-1), 1, len(self.offsets) - 1)
            v0 = np.take_along_axis(values, index[..., None] - 1, axis=-1)[..., 0]
            v1 = np.take_along_axis(values, index[..., None], axis=-1)[..., 0]
            with np.errstate(invalid="ignore", divide="ignore"):
                fraction = np.clip((mid - v0) / (v1 - v0), 0.0, 1.0)
                good = np.isfinite(values).all(axis=-1) & (white - black > 10) & np.isfinite(fraction)
            offset = self.offsets[0] + (index - 1 + np.nan_to_num(fraction)) * (self.offsets[1] - self.offsets[0])
            edge_grid = self.on_edge + offset[..., None] * self.normals[:, None, :]
            edge_px = cv2.perspectiveTransform(edge_grid.reshape(1, -1, 2), H).reshape(edge_grid.shape)
            if (good.sum(axis=1) < 3).any():
                return corners_px
            w = good.astype(float)[..., None]
            centre = (edge_px * w).sum(axis=1) / w.sum(axis=1)
            d = (edge_px - centre[:, None, :]) * w
            _, vectors = np.linalg.eigh(np.einsum("ski,skj->sij", d, d))
            normal = vectors[:, :, 0]  # the smallest eigenvector is the line's normal
            lines = np.column_stack([normal, -(normal * centre).sum(axis=1)])
            # corner i is where side i - 1 meets side i (TL = left x top)
            points = np.cross(np.roll(lines, 1, axis=0), lines)
            corners_px = points[:, :2] / points[:, 2:3]
        return corners_px


class Ecc:
    """cv2.findTransformECC (homography) between the marker drawn at the image's scale and the frame."""

    def __init__(self, layout: MarkerLayout, iterations: int = 3, gauss_size: int = 1):
        self.layout = layout
        self.iterations = iterations
        self.gauss_size = gauss_size
        self.templates: dict = {}

    def refine(self, gray: np.ndarray, marker_id: int, corners_px: np.ndarray) -> np.ndarray:
        layout, n = self.layout, self.layout.n_cells
        (x0, y0), (x1, y1), (x2, y2), (x3, y3) = corners_px.tolist()
        area = 0.5 * abs((x2 - x0) * (y3 - y1) - (y2 - y0) * (x3 - x1))
        ppc = int(np.clip(round(math.sqrt(area) / 8), 3, 6))
        template = self.templates.get((marker_id, ppc))
        if template is None:
            template = self.templates[(marker_id, ppc)] = marker_image(layout, marker_id, ppc, 1)
        H = cv2.getPerspectiveTransform(layout.inner_corners_cells.astype(np.float32), corners_px.astype(np.float32))
        # template pixel (x, y) is grid u = (x + 0.5) / ppc - 1
        A = np.array([[1 / ppc, 0, 0.5 / ppc - 1], [0, 1 / ppc, 0.5 / ppc - 1], [0, 0, 1.0]])
        outline = cv2.perspectiveTransform(np.array([[[-1.0, -1.0], [n + 1, -1], [n + 1, n + 1], [-1, n + 1]]]), H)[0]
        x0, y0 = np.maximum(np.floor(outline.min(axis=0)).astype(int) - 3, 0)
        x1, y1 = np.ceil(outline.max(axis=0)).astype(int) + 3
        crop = gray[y0:y1 + 1, x0:x1 + 1]
        S = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]])
        warp = S @ H @ A
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.iterations, 1e-5)
        try:
            _, warp = cv2.findTransformECC(template, crop, (warp / warp[2, 2]).astype(np.float32),
                                           cv2.MOTION_HOMOGRAPHY, criteria, None, self.gauss_size)
        except cv2.error:
            return corners_px
        H = np.linalg.inv(S) @ warp.astype(np.float64) @ np.linalg.inv(A)
        return cv2.perspectiveTransform(layout.inner_corners_cells[None], H)[0]


# ------------------------------------------------------------------ the scenes

def render_band(rng, layout: MarkerLayout, textures: dict, band, condition: str, scenes: int):
    """Scenes of one band and condition, detected with each ArUco refinement.

    Returns (samples, {aruco method: corners by sample (None if not found)}, {aruco method: ms per marker}):
    an ArUco refinement's time is its detectMarkers time over CORNER_REFINE_NONE's, summed over the
    scenes, divided by the markers it refined.
    """
    dictionary = load_dictionary("6x6").aruco()
    detectors = {name: aruco_detector(dictionary, method) for name, method in ARUCO_METHODS.items()}
    plain = aruco_detector(dictionary, cv2.aruco.CORNER_REFINE_NONE)
    samples: list[Sample] = []
    aruco_corners: dict[str, list] = defaultdict(list)
    extra_ms: dict[str, float] = defaultdict(float)
    refined: dict[str, int] = defaultdict(int)
    for _ in range(scenes):
        ids = rng.choice(len(layout.dictionary.bits), MARKERS_PER_SCENE, replace=False)
        markers = [textures.setdefault(int(i), raster.rs_marker_texture(layout, int(i))) for i in ids]
        scene = random_marker_scene(rng, IMAGE_SIZE, markers, band, condition, max_tilt_deg=MAX_TILT_DEG)
        truths = {int(ids[t.key]): t for t in scene.truths if t.fully_visible}
        base_ms, _ = timed_detect(plain, scene.image)
        found = {}
        for name, detector in detectors.items():
            ms, found[name] = timed_detect(detector, scene.image)
            extra_ms[name] += ms - base_ms
            refined[name] += len(found[name])
        for marker_id, initial in found["aruco_subpix"].items():
            truth = truths.get(marker_id)
            if truth is None or np.linalg.norm(initial - truth.corners_px, axis=1).mean() > 0.25 * truth.inner_px:
                continue
            samples.append(Sample(scene.image, marker_id, initial, truth.corners_px))
            for name in ARUCO_METHODS:
                aruco_corners[name].append(found[name].get(marker_id))
    aruco_ms = {name: extra_ms[name] / refined[name] if refined[name] else math.nan for name in ARUCO_METHODS}
    return samples, aruco_corners, aruco_ms


def timed_detect(detector, image) -> tuple[float, dict[int, np.ndarray]]:
    """(best of three detectMarkers times in ms, {id: corners (4, 2)})."""
    found, best_ms = best_of(aruco_found, detector, image, repeats=3)
    return best_ms, dict(found)


def timed(function, *args) -> tuple[np.ndarray, float]:
    """(result, ms) of the second call (caches warm)."""
    return best_of(function, *args, repeats=1, warmup=1)


# ------------------------------------------------------------------- the tables

def main_table(layout: MarkerLayout, scenes: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    textures: dict = {}
    lines, ecc, lk = BorderLines(layout), Ecc(layout), MarkerRefiner(layout)
    header = f"{'band px':<9} {'condition':<14} {'method':<15} {'n':>4} {'median px':>10} {'p90 px':>8} " \
             f"{'ms/marker':>10} {'x_subpix':>9}"
    print(header)
    print("-" * len(header))
    overall: dict = defaultdict(list)
    statuses: Counter = Counter()
    for band in BANDS_PX:
        for condition in CONDITIONS:
            samples, aruco_corners, aruco_ms = render_band(rng, layout, textures, band, condition, scenes)
            errors: dict[str, list] = defaultdict(list)
            ms: dict[str, list] = defaultdict(list)
            for i, s in enumerate(samples):
                for name in ARUCO_METHODS:
                    corners = aruco_corners[name][i]
                    if corners is not None:
                        errors[name].append(np.linalg.norm(corners - s.truth_px, axis=1))
                for name, call in (("cornersubpix", lambda: corner_subpix(s.image, s.initial_px)),
                                   ("border_lines", lambda: lines.refine(s.image, s.initial_px)),
                                   ("ecc", lambda: ecc.refine(s.image, s.marker_id, s.initial_px)),
                                   ("lk", lambda: lk.refine(s.image, s.marker_id, s.initial_px))):
                    result, elapsed = timed(call)
                    if name == "lk":
                        statuses[result.status] += 1
                        result = result.corners_px
                    errors[name].append(np.linalg.norm(result - s.truth_px, axis=1))
                    ms[name].append(elapsed)
            for name in ARUCO_METHODS:
                ms[name] = [aruco_ms[name]]
            baseline_ms = np.median(ms["cornersubpix"]) if ms["cornersubpix"] else math.nan
            for name in METHODS:
                e = np.concatenate(errors[name]) if errors[name] else np.full(1, np.nan)
                t = float(np.median(ms[name])) if ms[name] else math.nan
                overall[(band, name)].append(e)
                label = f"{band[0]}-{band[1]}" if name == METHODS[0] and condition == CONDITIONS[0] else ""
                cond = condition if name == METHODS[0] else ""
                print(f"{label:<9} {cond:<14} {name:<15} {len(errors[name]):>4} {np.median(e):>10.3f} "
                      f"{np.percentile(e, 90):>8.3f} {t:>10.3f} {t / baseline_ms:>9.1f}")
        print()
    print("all conditions together (corner error px, median / p90):")
    print(f"{'method':<15} " + " ".join(f"{f'{lo}-{hi} px':>15}" for lo, hi in BANDS_PX))
    for name in METHODS:
        cells = []
        for band in BANDS_PX:
            e = np.concatenate(overall[(band, name)])
            cells.append(f"{np.nanmedian(e):6.3f} / {np.nanpercentile(e, 90):5.3f}")
        print(f"{name:<15} " + " ".join(f"{c:>15}" for c in cells))
    print(f"lk status: {dict(statuses)}")
    return overall


def lens_table(layout: MarkerLayout, markers: int, seed: int) -> None:
    """Markers of 40-150 px anywhere in a distorted image: lk, and the whole detector, without and with the camera."""
    from companion.detect.detector import Detector

    width, height = IMAGE_SIZE
    K = intrinsics_from_hfov(width, height, 70.0)
    detector = aruco_detector(load_dictionary("6x6").aruco())
    print("\nlens distortion (40-150 px, tilt <= 40 deg, anywhere in the frame; mean corner error px, median / p90; "
          "'edge' = markers > 90 px centred > 200 px off the image centre; det = companion.detect.detector.Detector):")
    print(f"{'k1, k2':<13} {'n':>3} {'aruco_subpix':>15} {'lk':>15} {'lk + camera':>15} {'lk edge':>9} "
          f"{'lk+cam edge':>12} {'ms lk':>6} {'ms lk+cam':>10} {'det':>15} {'det + camera':>15}")
    for dist in ((0.0, 0.0), (-0.05, 0.02), (-0.3, 0.0), (-0.3, 0.1)):
        coefficients = np.array([dist[0], dist[1], 0.0, 0.0, 0.0])
        camera = CameraModel(K, coefficients, width, height, np.eye(4))
        renderer = raster.Renderer(K, coefficients, width, height)
        plain = MarkerRefiner(layout)
        with_camera = MarkerRefiner(layout, camera=camera)
        detectors = Detector(), Detector(camera=camera)
        rng = np.random.default_rng(seed)
        rows = []
        for _ in range(markers):
            marker_id = int(rng.integers(len(layout.dictionary.bits)))
            texture = raster.rs_marker_texture(layout, marker_id)
            z = K[0, 0] * 0.15 / rng.uniform(40, 150)
            centre = z * np.linalg.solve(K, [rng.uniform(60, width - 60), rng.uniform(60, height - 60), 1.0])
            tilt = frames.rotation_from_rotvec([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.0])
            R = tilt @ frames.rot_z(rng.uniform(0, 2 * np.pi)) @ frames.R_camera_marker_face_on()
            T = frames.make_transform(R, centre)
            quad = raster.marker_quad(texture, 0.15, T, gain=0.85, offset=15.0)
            rendering = renderer.render([quad], np.eye(4), 120.0)
            image = degrade.sensor_noise(degrade.gaussian_blur(rendering.image, 0.5), rng, 1.0, 0.02)
            truth = raster.marker_truth(renderer, rendering, texture, 0.15, T, np.eye(4), 0)
            _, found = timed_detect(detector, image)
            if not truth.fully_visible or marker_id not in found:
                continue
            initial = found[marker_id]
            a, ms_a = timed(plain.refine, image, marker_id, initial)
            b, ms_b = timed(with_camera.refine, image, marker_id, initial)
            edge = truth.inner_px > 90 and np.linalg.norm(truth.corners_px.mean(axis=0) - [width / 2, height / 2]) > 200
            by_detector = [{d.id: d.corners_px for d in d_.detect(image)}.get(marker_id) for d_ in detectors]
            rows.append([np.linalg.norm(c - truth.corners_px, axis=1).mean() for c in (initial, a.corners_px,
                                                                                       b.corners_px)]
                        + [edge, ms_a, ms_b]
                        + [np.nan if c is None else np.linalg.norm(c - truth.corners_px, axis=1).mean()
                           for c in by_detector])
        r = np.array(rows, dtype=float)
        edge = r[:, 3] > 0

        def stat(column, mask=None):
            v = r[:, column] if mask is None else r[mask, column]
            v = v[np.isfinite(v)]
            return f"{np.median(v):6.3f} / {np.percentile(v, 90):5.3f}" if len(v) else "-"
        print(f"{f'{dist[0]}, {dist[1]}':<13} {len(r):>3} {stat(0):>15} {stat(1):>15} {stat(2):>15} "
              f"{np.median(r[edge, 1]) if edge.any() else math.nan:>9.3f} "
              f"{np.median(r[edge, 2]) if edge.any() else math.nan:>12.3f} {np.median(r[:, 4]):>6.3f} "
              f"{np.median(r[:, 5]):>10.3f} {stat(6):>15} {stat(7):>15}")


def detector_table(layout: MarkerLayout, scenes: int, seed: int) -> None:
    """The detector's own square-path corners (whatever ``Detector`` does today) and lk started from them."""
    from companion.detect.detector import Detector

    detector = Detector()
    refiner = MarkerRefiner(layout)
    textures: dict = {}
    rng = np.random.default_rng(seed)
    print("\nthe detector's square-path corners -> lk from them (companion.detect.detector.Detector as it is today; "
          "corner error px, median -> median, n):")
    print(f"{'condition':<14} " + " ".join(f"{f'{lo}-{hi} px':>22}" for lo, hi in BANDS_PX))
    totals = defaultdict(list)
    for condition in CONDITIONS:
        cells = []
        for band in BANDS_PX:
            before, after = [], []
            for _ in range(scenes):
                ids = rng.choice(len(layout.dictionary.bits), MARKERS_PER_SCENE, replace=False)
                markers = [textures.setdefault(int(i), raster.rs_marker_texture(layout, int(i))) for i in ids]
                scene = random_marker_scene(rng, IMAGE_SIZE, markers, band, condition,
                                                   max_tilt_deg=MAX_TILT_DEG)
                truths = {int(ids[t.key]): t for t in scene.truths if t.fully_visible}
                for detection in detector.detect(scene.image):
                    truth = truths.get(detection.id)
                    if detection.path != "square" or truth is None:
                        continue
                    fit = refiner.refine(scene.image, detection.id, detection.corners_px)
                    before.append(np.linalg.norm(detection.corners_px - truth.corners_px, axis=1))
                    after.append(np.linalg.norm(fit.corners_px - truth.corners_px, axis=1))
            if before:
                b, a = np.concatenate(before), np.concatenate(after)
                totals[("detector", band)].append(b)
                totals[("lk", band)].append(a)
                cells.append(f"{np.median(b):.3f} -> {np.median(a):.3f} ({len(before):>2})")
            else:
                cells.append("-")
        print(f"{condition:<14} " + " ".join(f"{c:>22}" for c in cells))
    for name in ("detector", "lk"):
        cells = []
        for band in BANDS_PX:
            e = np.concatenate(totals[(name, band)]) if totals[(name, band)] else np.full(1, np.nan)
            cells.append(f"{np.median(e):.3f} / p90 {np.percentile(e, 90):.3f}")
        print(f"{'all: ' + name:<14} " + " ".join(f"{c:>22}" for c in cells))


def occluded_table(layout: MarkerLayout, scenes: int, seed: int) -> None:
    """Detections of partly occluded markers (the detector's circles path): lk against what the detector gives."""
    from companion.detect.detector import Detector

    detector = Detector()
    refiner = MarkerRefiner(layout)
    textures: dict = {}
    print("\noccluded markers, the detector's own detections (30-150 px; largest corner error px, median / p90):")
    print(f"{'condition':<11} {'path':<8} {'n':>3} {'detector':>15} {'lk':>15} {'lk worse by > 0.1 px':>21} "
          f"{'lk fell back':>13}")
    rng = np.random.default_rng(seed)
    for condition in ("strip_1_8", "strip_1_4", "corner", "blob"):
        rows = defaultdict(list)
        for _ in range(scenes):
            ids = rng.choice(len(layout.dictionary.bits), MARKERS_PER_SCENE, replace=False)
            markers = [textures.setdefault(int(i), raster.rs_marker_texture(layout, int(i))) for i in ids]
            scene = random_marker_scene(rng, IMAGE_SIZE, markers, (30, 150), condition,
                                               max_tilt_deg=MAX_TILT_DEG)
            truths = {int(ids[t.key]): t for t in scene.truths}
            for detection in detector.detect(scene.image):
                truth = truths.get(detection.id)
                if truth is None or not np.all(np.isfinite(truth.corners_px)):
                    continue
                fit = refiner.refine(scene.image, detection.id, detection.corners_px)
                rows[detection.path].append((np.linalg.norm(detection.corners_px - truth.corners_px, axis=1).max(),
                                             np.linalg.norm(fit.corners_px - truth.corners_px, axis=1).max(),
                                             not fit.refined))
        for path, values in sorted(rows.items()):
            r = np.array(values, dtype=float)
            print(f"{condition:<11} {path:<8} {len(r):>3} "
                  f"{np.median(r[:, 0]):6.3f} / {np.percentile(r[:, 0], 90):5.3f} "
                  f"{np.median(r[:, 1]):6.3f} / {np.percentile(r[:, 1], 90):5.3f} "
                  f"{int(np.sum(r[:, 1] > r[:, 0] + 0.1)):>21} {int(r[:, 2].sum()):>13}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: 2 scenes per band and condition")
    parser.add_argument("--scenes", type=int, default=10, help="scenes per band and condition (3 markers each)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    scenes = 2 if args.quick else args.scenes
    layout = MarkerLayout(parity=2)
    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, "
          f"{scenes} scenes x {MARKERS_PER_SCENE} markers per band and condition, tilt <= {MAX_TILT_DEG:.0f} deg\n")
    main_table(layout, scenes, args.seed)
    detector_table(layout, 1 if args.quick else 4, args.seed)
    lens_table(layout, 12 if args.quick else 80, args.seed)
    occluded_table(layout, 3 if args.quick else 25, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
