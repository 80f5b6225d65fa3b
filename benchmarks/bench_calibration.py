"""ChArUco calibration accuracy on rendered views of known cameras (70 and 120 degree lenses).

    python benchmarks/bench_calibration.py [--quick]

For each lens and several random sets of 30 views (``companion.sim.board_views``:
the board tilted up to 45 degrees, rolled, anywhere in the image, often in
part), ``companion.geometry.calibration.calibrate`` runs as ``companion
calibrate`` does; the table gives the errors against the rendered camera.
Targets: fx, fy, cx, cy within 0.5 %, k1 within 0.01. Baseline in the same
run: the same views through OpenCV's plain ``calibrateCamera`` on the
detector's corners, with no clean-up of mislocated corners or outlier views.
"""
from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np

from common import REPO  # noqa: F401,E402  (puts the working tree's companion first)

from companion.geometry.calibration import CharucoBoard, calibrate  # noqa: E402
from companion.markers.charuco import CharucoSpec  # noqa: E402
from companion.sim.board_views import BoardCamera, hfov_deg, view_poses  # noqa: E402

LENSES = {  # the lenses of tests/test_charuco.py
    "70 deg": (np.array([[478.0, 0.0, 322.5], [0.0, 478.0, 236.0], [0.0, 0.0, 1.0]]), np.array([-0.10, 0.02, 0, 0, 0])),
    "120 deg": (np.array([[248.0, 0.0, 318.0], [0.0, 248.6, 243.0], [0.0, 0.0, 1.0]]),
                np.array([-0.22, 0.045, 0.0, 0.0, 0.0])),
}
PINHOLE = ("fx", "fy", "cx", "cy")


def errors(values: dict, lens) -> tuple[float, float]:
    """(worst relative error of fx, fy, cx, cy in %, k1 error)."""
    K, dist = lens
    truth = dict(zip(PINHOLE, (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
    worst = max(abs(values[k] - truth[k]) / truth[k] for k in PINHOLE)
    return 100 * worst, values["k1"] - dist[0]


def plain_opencv(board: CharucoBoard, views: dict) -> dict:
    found = [r for r in (board.find(v) for v in views.values()) if not isinstance(r, str)]
    _, K, dist, _, _ = cv2.calibrateCamera([o.reshape(-1, 1, 3) for _, o in found],
                                           [i.reshape(-1, 1, 2) for i, _ in found], (640, 480), None, None)
    return dict(zip((*PINHOLE, "k1"), (K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist.ravel()[0])))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: one set of views per lens")
    args = parser.parse_args()
    spec = CharucoSpec()
    board = CharucoBoard(spec)
    seeds = range(1, 2) if args.quick else range(1, 7)
    print(f"\n{spec.describe()}; 30 rendered views per set; errors against the rendered camera")
    print(f"{'lens':<8} {'hfov':>5} {'set':>3} {'views':>5} {'RMS px':>7} {'cover':>5} {'pinhole %':>9} "
          f"{'k1 err':>8} {'OpenCV plain: pinhole %':>23} {'k1 err':>8}")
    worst = {}
    for name, lens in LENSES.items():
        camera = BoardCamera(spec, lens)
        for seed in seeds:
            views = {f"view{i:02d}": camera.render(T) for i, T in enumerate(view_poses(lens, 30, seed))}
            result = calibrate(views, board)
            pinhole, k1 = errors(result.parameters(), lens)
            plain_pinhole, plain_k1 = errors(plain_opencv(board, views), lens)
            previous = worst.get(name, (0.0, 0.0))
            worst[name] = (max(previous[0], pinhole), max(previous[1], abs(k1)))
            print(f"{name:<8} {hfov_deg(lens):5.1f} {seed:3d} {len(result.views):5d} {result.rms_px:7.3f} "
                  f"{100 * result.coverage:4.0f}% {pinhole:9.3f} {k1:+8.4f} {plain_pinhole:23.3f} {plain_k1:+8.4f}")
    for name, (pinhole, k1) in worst.items():
        print(f"{name}: worst pinhole error {pinhole:.3f} % (target 0.5: {'met' if pinhole < 0.5 else 'NOT met'}), "
              f"worst |k1 error| {k1:.4f} (target 0.01: {'met' if k1 < 0.01 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
