"""`companion calibrate`: camera intrinsics and distortion from chessboard images.

Writes an OpenCV ``cv2.FileStorage`` YAML (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height``, as OpenCV's own
calibration tools do), which a config's ``camera.calibration`` key reads.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

MIN_VIEWS = 5


class CalibrationError(ValueError):
    """The images or the board description cannot give a calibration."""


@dataclass(frozen=True)
class Board:
    """A chessboard: inner corners per row and column, square side in metres."""

    columns: int
    rows: int
    square_m: float

    def object_points(self) -> np.ndarray:
        """(rows * columns, 3) float32 corners on the board plane z = 0, row by row."""
        grid = np.mgrid[0:self.columns, 0:self.rows].T.reshape(-1, 2)
        return np.hstack([grid * self.square_m, np.zeros((len(grid), 1))]).astype(np.float32)


@dataclass(frozen=True)
class Calibration:
    """K: (3, 3); dist: (5,) k1 k2 p1 p2 k3; rms_px: RMS reprojection error; views used."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float
    views: tuple[str, ...]


def find_corners(gray: np.ndarray, board: Board) -> np.ndarray | None:
    """(rows * columns, 2) float32 sub-pixel inner corners, or None if the board is not seen whole."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, (board.columns, board.rows), flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    return cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria).reshape(-1, 2)


def calibrate(images: dict[str, np.ndarray], board: Board) -> Calibration:
    """Calibrate from named (H, W) uint8 grayscale images of one camera."""
    sizes = {image.shape for image in images.values()}
    if len(sizes) != 1:
        raise CalibrationError(f"images differ in size: {sorted(sizes)}")
    height, width = sizes.pop()
    found = {name: c for name, image in images.items() if (c := find_corners(image, board)) is not None}
    if len(found) < MIN_VIEWS:
        raise CalibrationError(f"the {board.columns}x{board.rows} board was found in {len(found)} of "
                               f"{len(images)} images; at least {MIN_VIEWS} views are needed")
    object_points = [board.object_points()] * len(found)
    rms_px, K, dist, _, _ = cv2.calibrateCamera(object_points, list(found.values()), (width, height), None, None)
    return Calibration(K, dist.ravel()[:5], width, height, float(rms_px), tuple(found))


def write_calibration(path: Path, calibration: Calibration) -> None:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        storage.write("image_width", calibration.width)
        storage.write("image_height", calibration.height)
        storage.write("camera_matrix", calibration.K)
        storage.write("distortion_coefficients", calibration.dist.reshape(1, -1))
        storage.write("avg_reprojection_error", calibration.rms_px)
        storage.write("views", len(calibration.views))
    finally:
        storage.release()
