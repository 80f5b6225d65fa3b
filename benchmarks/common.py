"""What the benchmarks share: the OpenCV ArUco baseline as they configure it, and timing.

Run a benchmark as ``python benchmarks/NAME.py`` (its folder is then on the
import path, so ``import common`` finds this module); ``REPO`` is put on the
path too, so the working tree's ``companion`` is the one measured.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def work_folder(path: str) -> Path:
    """An argparse ``type`` for a ``--work DIR`` option: the folder, made if missing; a clear usage error (not a
    traceback) when it cannot be made or written."""
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise argparse.ArgumentTypeError(f"cannot make {path}: {error.strerror}") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write to {path}")
    return folder


def aruco_detector(dictionary: cv2.aruco.Dictionary, corner_refinement: int | None = cv2.aruco.CORNER_REFINE_SUBPIX,
                   error_correction_rate: float | None = None,
                   min_distance_to_border_px: int | None = 0) -> cv2.aruco.ArucoDetector:
    """OpenCV's ArucoDetector as the baselines run it: sub-pixel corners and no border margin (OpenCV 5
    drops visible markers near the image edge otherwise, see shared/notes). None keeps OpenCV's default."""
    params = cv2.aruco.DetectorParameters()
    if corner_refinement is not None:
        params.cornerRefinementMethod = corner_refinement
    if min_distance_to_border_px is not None:
        params.minDistanceToBorder = min_distance_to_border_px
    if error_correction_rate is not None:
        params.errorCorrectionRate = error_correction_rate
    return cv2.aruco.ArucoDetector(dictionary, params)


def aruco_found(detector: cv2.aruco.ArucoDetector, image: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """[(id, corners (4, 2) float64)] of the markers ArUco identified."""
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return []
    return [(int(i), np.asarray(c, float).reshape(4, 2)) for i, c in zip(ids.ravel(), corners)]


def best_of(function, *args, repeats: int = 3, warmup: int = 0):
    """(result of the last call, best wall time in ms over ``repeats`` calls after ``warmup`` untimed ones)."""
    for _ in range(warmup):
        function(*args)
    best_ms, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter_ns()
        result = function(*args)
        best_ms = min(best_ms, (time.perf_counter_ns() - start) / 1e6)
    return result, best_ms


def timed_together(functions, image: np.ndarray, repeats: int):
    """Run the functions in turn, ``repeats`` rounds; (results, best wall ms, best CPU ms of each).

    Alternating keeps a burst of load from other processes from landing on
    one detector only; the best of several runs drops the rest of it. CPU
    time is the process's (all threads): ArUco's thresholding runs on two
    threads, our Python stages on one, so the CPU ratio is lower than the wall one.
    """
    wall = [np.inf] * len(functions)
    cpu = [np.inf] * len(functions)
    results = [None] * len(functions)
    for _ in range(repeats):
        for k, function in enumerate(functions):
            start, start_cpu = time.perf_counter_ns(), time.process_time_ns()
            results[k] = function(image)
            wall[k] = min(wall[k], (time.perf_counter_ns() - start) / 1e6)
            cpu[k] = min(cpu[k], (time.process_time_ns() - start_cpu) / 1e6)
    return results, wall, cpu
