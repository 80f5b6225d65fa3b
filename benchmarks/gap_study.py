"""Gap study: does the white gap between the parity bands and the black border matter to ArUco?

Without the gap (``MarkerLayout(parity, gap_cells=0)``) the nearest parity
band sits right against the inner marker's black border, so black parity
cells join the border's blob and its outer contour is no longer a square.
This renders each of the 50 markers, with and without the gap, under random
perspectives (inner square 40-150 px, tilt up to 50 degrees, any in-plane
rotation) with ``companion.sim.scenes.random_marker_scene``, on a plain and on a
cluttered background, and runs OpenCV's ``ArucoDetector`` with our custom
dictionary (``minDistanceToBorder = 0``). Both variants see the same scenes
(same seeds: poses, boards, background, noise), two markers per 640x480 image.

A marker counts as detected when a detection has its id and all four corners
within 15 % of its inner side of the ground truth. Detections whose id is not
one of the scene's markers are counted as wrong ids. Markers partly hidden by
a neighbour's backing board are not scored.

    PYTHONPATH=. python benchmarks/gap_study.py [--views 8] [--seed 1]
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field

import numpy as np

from common import aruco_detector
from companion.sim import raster
from companion.sim import scenes
from companion.markers.layout import MarkerLayout

IMAGE_SIZE = (640, 480)
MARKERS_PER_SCENE = 2
INNER_PX_RANGE = (40.0, 150.0)
SIZE_BINS_PX = (40.0, 75.0, 110.0, 150.0)
CORNER_TOLERANCE = 0.15  # of the inner side
TEXTURE_PX_PER_CELL = 24
VARIANTS = {"gap": 1, "no gap": 0}  # name -> gap_cells
BACKGROUNDS = ("plain", "clutter")


@dataclass
class Tally:
    """Detection counts of one (parity, background, variant) configuration."""

    placed: int = 0
    detected: int = 0
    wrong: int = 0
    placed_by_size: np.ndarray = field(default_factory=lambda: np.zeros(len(SIZE_BINS_PX) - 1, int))
    detected_by_size: np.ndarray = field(default_factory=lambda: np.zeros(len(SIZE_BINS_PX) - 1, int))

    @property
    def rate(self) -> float:
        return self.detected / max(self.placed, 1)


def touching_markers(layout: MarkerLayout) -> int:
    """Markers with a black parity cell edge-adjacent to the black border (outside its corners)."""
    o, side = layout.inner_origin, layout.inner_cells
    count = 0
    for cells in layout.all_cells:
        ring = np.r_[cells[o - 1, o:o + side], cells[o + side, o:o + side],
                     cells[o:o + side, o - 1], cells[o:o + side, o + side]] if o > 0 else np.zeros(1)
        count += bool(ring.any())
    return count


def background_image(kind: str, rng: np.random.Generator) -> np.ndarray | None:
    """A plain (one gray level) background, or None for the renderer's clutter."""
    if kind == "plain":
        return np.full(IMAGE_SIZE[::-1], rng.uniform(60, 200), np.float32).astype(np.uint8)
    return None


def score_scene(scene: scenes.Scene, corners: tuple, ids, tally: Tally) -> None:
    found = [] if ids is None else [(int(i), c.reshape(4, 2)) for i, c in zip(ids.ravel(), corners)]
    for truth in scene.truths:
        if not truth.fully_visible:  # a neighbour's board can hide part of it: not scored
            continue
        tally.placed += 1
        size_bin = int(np.clip(np.searchsorted(SIZE_BINS_PX, truth.inner_px) - 1, 0, len(SIZE_BINS_PX) - 2))
        tally.placed_by_size[size_bin] += 1
        errors_px = [np.linalg.norm(c - truth.corners_px, axis=1).max()
                     for marker_id, c in found if marker_id == truth.marker_id]
        if errors_px and min(errors_px) < CORNER_TOLERANCE * truth.inner_px:
            tally.detected += 1
            tally.detected_by_size[size_bin] += 1
    in_scene = {truth.marker_id for truth in scene.truths}
    tally.wrong += sum(marker_id not in in_scene for marker_id, _ in found)


def run_configuration(parity: int, gap_cells: int, background: str, views: int, seed: int) -> Tally:
    layout = MarkerLayout(parity, gap_cells=gap_cells)
    textures = [raster.rs_marker_texture(layout, i, TEXTURE_PX_PER_CELL) for i in range(len(layout.all_cells))]
    detector = aruco_detector(layout.dictionary.aruco(), corner_refinement=None)
    tally = Tally()
    n_markers = len(textures)
    n_scenes = views * n_markers // MARKERS_PER_SCENE
    for s in range(n_scenes):
        # same seed for both variants: same poses, boards, background and noise
        rng = np.random.default_rng([seed, parity, BACKGROUNDS.index(background), s])
        first = (s * MARKERS_PER_SCENE) % n_markers
        chosen = [textures[(first + k) % n_markers] for k in range(MARKERS_PER_SCENE)]
        scene = scenes.random_marker_scene(rng, IMAGE_SIZE, chosen, INNER_PX_RANGE, "clean",
                                           background=background_image(background, rng))
        corners, ids, _ = detector.detectMarkers(scene.image)
        score_scene(scene, corners, ids, tally)
    return tally


def print_table(results: dict, views: int, seed: int) -> None:
    print(f"ArUco detection of RS markers with and without the white gap "
          f"({views} views of each of the 50 markers per row, {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, "
          f"inner square {INNER_PX_RANGE[0]:.0f}-{INNER_PX_RANGE[1]:.0f} px, seed {seed})")
    bins = [f"{lo:.0f}-{hi:.0f}px" for lo, hi in zip(SIZE_BINS_PX[:-1], SIZE_BINS_PX[1:])]
    header = f"{'p':>2} {'background':<10} {'variant':<7} {'touching':>8} {'placed':>6} {'detected':>8} " \
             f"{'rate':>6} {'wrong id':>8}  " + " ".join(f"{b:>10}" for b in bins)
    print(header)
    print("-" * len(header))
    for (parity, background, variant), (tally, touching) in results.items():
        by_size = " ".join(f"{d / max(p, 1):>10.1%}" for d, p in zip(tally.detected_by_size, tally.placed_by_size))
        print(f"{parity:>2} {background:<10} {variant:<7} {touching:>5}/50 {tally.placed:>6} {tally.detected:>8} "
              f"{tally.rate:>6.1%} {tally.wrong:>8}  {by_size}")
    print()
    print("rate with the gap / rate without it:")
    for parity in (2, 4):
        for background in BACKGROUNDS:
            gap = results[(parity, background, "gap")][0].rate
            no_gap = results[(parity, background, "no gap")][0].rate
            ratio = f"{gap / no_gap:.1f}x" if no_gap > 0 else "inf (no gap: none detected)"
            print(f"  p={parity} {background:<8} {gap:.1%} vs {no_gap:.1%}: {ratio}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=8, help="random views of each marker per configuration")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    results = {}
    for parity in (2, 4):
        for background in BACKGROUNDS:
            for variant, gap_cells in VARIANTS.items():
                tally = run_configuration(parity, gap_cells, background, args.views, args.seed)
                touching = touching_markers(MarkerLayout(parity, gap_cells=gap_cells))
                results[(parity, background, variant)] = (tally, touching)
    print_table(results, args.views, args.seed)


if __name__ == "__main__":
    main()
