"""The detector's per-detection corner sigma against the renderer's ground truth.

``Detection.corner_sigma_px`` is what the pose stage weighs each marker's
points by. The detector computes it from what it measured
(``companion.detect.detector``):

* square path: ``corner_cov_px2 = k_square^2`` times the whole-pattern
  alignment's own (8, 8) corner covariance (``MarkerFit.corner_cov_px2``:
  per marker, the misfit's noise measured along its edges plus the
  template's mismatch (``refine.TEMPLATE_MISMATCH``, ``refine.SMEAR_MISMATCH``
  per unit of the image gradient's anisotropy), through the image's own
  gradient, so it follows the marker's noise, blur and smear),
  ``sigma_px`` the root of its mean variance (where the alignment did not
  hold: ``0.043 residual cell_px^(1/3)``, its misfit); times
  ``CUT_SIGMA_FACTOR`` when the frame's border cuts the marker's grid. The
  four corners' errors together are also scored against sigma^2 I and
  against the covariance (d^2 with 8 degrees of freedom);
* circles path: ``sigma_px = k_circles rms_cells cell_px``, the RMS misfit
  of the edge-refined homography.

Scenes come from ``companion.sim.scenes.random_marker_scene`` (640x480, 70
degree field of view, three markers per scene over clutter, tilts up to 60
degrees, inner squares 12-150 px; occluded ones for the circles path), under
``companion simulate``'s camera (``camera``: its blur, noise and vignetting)
and the detector benchmark's harsher conditions. For every detection
matched to a marker of the scene, the corner error against the truth; per
condition, the constant ``k`` that makes the normalised errors' RMS 1
(``k_rms``), the share of corner coordinates inside 2 sigma with the
detector's constants (95.4 % if honest), and the constants in use.
The square path's constants (``SQUARE_COV_SCALE``, ``refine.TEMPLATE_MISMATCH``,
``refine.SMEAR_MISMATCH``) were fitted together so that ``k/used`` is about 1
in every condition and size band at once; the circles path's
``CIRCLES_SIGMA_PER_MISFIT`` is one constant on its misfit (its rows say how
well it holds). A real camera's images call for running this on its own
conditions.

    PYTHONPATH=. python benchmarks/bench_corner_sigma.py [--quick] [--scenes 12] [--seed 5]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

import common  # noqa: F401  (puts the working tree's companion first)
from companion.detect import detector as detector_module
from companion.detect import refine
from companion.detect.detector import Detector
from companion.sim import raster
from companion.sim.scenes import BASE_DEGRADATIONS, CONDITIONS, SceneCondition, random_marker_scene
from companion.sim.simulate import DEFAULT_DEGRADATIONS

IMAGE_SIZE = (640, 480)
BANDS_PX = ((12, 20), (20, 35), (35, 60), (60, 100), (100, 150))
# companion simulate's camera (its motion blur needs a flight: none here)
CAMERA_CONDITION = SceneCondition("camera", degradations=DEFAULT_DEGRADATIONS.with_(motion_blur=False))
SQUARE_CONDITIONS = (CAMERA_CONDITION, CONDITIONS["clean"], CONDITIONS["gaussian_blur"], CONDITIONS["motion_blur"],
                     CONDITIONS["noise"], CONDITIONS["low_light"], CONDITIONS["jpeg"])
CIRCLES_CONDITIONS = (SceneCondition("camera strip 1/4", "strip", 0.25, CAMERA_CONDITION.degradations),
                      CONDITIONS["strip_1_8"], CONDITIONS["strip_1_4"], CONDITIONS["corner"])


@dataclass
class Sample:
    """One detection: the feature its sigma is made of (before the constant), its sigma, its corner errors (4, 2)."""

    feature: float
    sigma_px: float
    errors_px: np.ndarray
    cov_px2: np.ndarray | None = None


def samples(condition: SceneCondition, path: str, scenes_per_band: int, seed: int, index: int) -> list[Sample]:
    detector = Detector()
    layout = detector.layout
    textures = [raster.rs_marker_texture(layout, i, 16) for i in range(len(layout.all_cells))]
    rng = np.random.default_rng([seed, index])
    found = []
    for band in BANDS_PX:
        for _ in range(scenes_per_band):
            ids = rng.choice(len(textures), 3, replace=False)
            scene = random_marker_scene(rng, IMAGE_SIZE, [textures[i] for i in ids], band, condition, max_tilt_deg=60)
            truth = {int(ids[t.key]): t for t in scene.truths}
            for d in detector.detect(scene.image):
                t = truth.get(d.id)
                # square path: every corner in view; circles path: occluded corners are the point
                if t is None or d.path != path or d.corner_sigma_px is None or \
                        (path == "square" and not t.corners_visible.all()):
                    continue
                constant = square_constant(d) if path == "square" else detector_module.CIRCLES_SIGMA_PER_MISFIT
                found.append(Sample(d.corner_sigma_px / constant, d.corner_sigma_px, d.corners_px - t.corners_px,
                                    d.corner_cov_px2))
    return found


def square_constant(detection) -> float:
    """The square path's constant behind this detection's sigma: the alignment covariance's scale, or
    (an alignment that did not hold) the misfit's."""
    return (detector_module.SQUARE_COV_SCALE if detection.corner_cov_px2 is not None
            else detector_module.SQUARE_SIGMA_PER_RESIDUAL)


def row(name: str, found: list[Sample], constant: float) -> str:
    if not found:
        return f"{name:<18} {0:>5}"
    errors = np.stack([s.errors_px for s in found])                   # (N, 4, 2)
    sigma = np.array([s.sigma_px for s in found])[:, None, None]
    ratio = float(np.sqrt(np.mean((errors / sigma) ** 2)))          # the honest k over the one in use
    # k_rms: sqrt(mean((error / (sigma / k))^2)) over every corner coordinate
    k_rms = ratio * constant
    inside = float(np.mean(np.abs(errors / sigma) <= 2.0))
    error_rms = float(np.sqrt(np.mean(errors ** 2)))
    return (f"{name:<18} {len(found):>5} {error_rms:9.4f} {float(np.median(sigma)):9.4f} {k_rms:8.4f} "
            f"{ratio:6.2f} {inside:8.1%}{joint(found)}")


def joint(found: list[Sample]) -> str:
    """The four corners' errors together (8 coordinates) against sigma^2 I and against the detection's
    (8, 8) ``corner_cov_px2``: median d^2 (honest 7.34) and the share inside the 95 % ellipsoid."""
    with_cov = [s for s in found if s.cov_px2 is not None]
    if not with_cov:
        return ""
    errors = np.stack([s.errors_px.reshape(8) for s in with_cov])
    # d^2 = e^T Sigma^-1 e
    d2_diagonal = np.sum(errors ** 2, axis=1) / np.array([s.sigma_px for s in with_cov]) ** 2
    d2_joint = np.array([e @ np.linalg.solve(s.cov_px2, e) for e, s in zip(errors, with_cov)])
    limit = chi2.ppf(0.95, 8)
    return (f" {len(with_cov):>5} {np.median(d2_diagonal):7.2f} {np.mean(d2_diagonal <= limit):6.1%}"
            f" {np.median(d2_joint):7.2f} {np.mean(d2_joint <= limit):6.1%}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: 2 scenes per size band, two conditions")
    parser.add_argument("--scenes", type=int, default=12, help="scenes per size band and condition")
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args(argv)
    scenes = 2 if args.quick else args.scenes
    square_conditions = SQUARE_CONDITIONS[:2] if args.quick else SQUARE_CONDITIONS
    circles_conditions = CIRCLES_CONDITIONS[:1] if args.quick else CIRCLES_CONDITIONS
    head = f"{'condition':<18} {'marks':>5} {'err_rms':>9} {'sigma_med':>9} {'k_rms':>8} {'k/used':>6} {'in 2 sig':>8}"
    joint_head = f" {'cov':>5} {'d2_diag':>7} {'in95':>6} {'d2_cov':>7} {'in95':>6}"
    for path, conditions, constant in (("square", square_conditions, detector_module.SQUARE_COV_SCALE),
                                       ("circles", circles_conditions, detector_module.CIRCLES_SIGMA_PER_MISFIT)):
        what = ("k^2 x the alignment's (8, 8) corner covariance (sigma: its mean variance's root; "
                f"k {detector_module.SQUARE_SIGMA_PER_RESIDUAL} x the misfit where the alignment did not hold)"
                if path == "square" else "sigma = k x feature")
        mismatch = (f" (template mismatch {refine.TEMPLATE_MISMATCH}, smear {refine.SMEAR_MISMATCH})"
                    if path == "square" else "")
        print(f"\n{path} path: {what}, k in use {constant}{mismatch} "
              f"(err_rms, sigma_med: px per corner coordinate; k_rms: the honest k for the condition)")
        if path == "square":
            print("  4 corners together: cov detections with corner_cov_px2; d2 = e^T Sigma^-1 e (8 coordinates; "
                  "honest median 7.34, 95 % inside) with Sigma = sigma^2 I (diag) and = corner_cov_px2 (cov)")
        print(head + (joint_head if path == "square" else ""))
        for index, condition in enumerate(conditions):
            print(row(condition.name, samples(condition, path, scenes, args.seed, index), constant))
    print(f"\nbase degradations of the benchmark conditions: {BASE_DEGRADATIONS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
