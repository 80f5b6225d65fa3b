"""`companion calibrate`: camera intrinsics and distortion from views of a ChArUco board or a chessboard.

A **ChArUco** board (``companion.markers.charuco``) gives numbered corners,
so a view showing part of the board counts: the edges and corners of the
image, where the lens distorts most, get covered. A plain **chessboard** must
be seen whole. Each view is checked and either used or rejected with its
reason (too few corners, corners on one line, a different image size, a
reprojection error far above the others); the fit is OpenCV's
``calibrateCameraExtended`` with the 5-coefficient lens model (k1 k2 p1 p2
k3), which also gives each coefficient's standard deviation.

Writes an OpenCV ``cv2.FileStorage`` YAML (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height``, as OpenCV's
own calibration tools do), which a config's ``camera.calibration_file`` reads.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from companion.files import write_whole
from companion.markers.charuco import CharucoSpec

MIN_VIEWS = 5
MIN_CHARUCO_CORNERS = 8
# a view whose RMS reprojection error exceeds both of these is left out (blur, a moved board, a bad detection)
OUTLIER_FACTOR = 3.0
OUTLIER_MIN_PX = 1.0
# a corner this far from the fit (x the median corner's error, and at least MISLOCATED_MIN_PX) is mislocated
MISLOCATED_FACTOR = 8.0
MISLOCATED_MIN_PX = 2.0
MISLOCATED_ROUNDS = 10
# the image is split into COVERAGE_GRID cells to say how much of it the corners covered
COVERAGE_GRID = (8, 6)
PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


class CalibrationError(ValueError):
    """The images or the board description cannot give a calibration."""


class CalibrationBoard(Protocol):
    def find(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | str:
        """(image points (K, 2) float32, board points (K, 3) float32), or why the view cannot be used."""

    def describe(self) -> str: ...


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

    def find(self, gray: np.ndarray):
        corners = find_corners(gray, self)
        if corners is None:
            return f"the {self.columns}x{self.rows} chessboard is not seen whole"
        return corners.astype(np.float32), self.object_points()

    def describe(self) -> str:
        return f"{self.columns}x{self.rows} chessboard"


class CharucoBoard:
    """A ChArUco board as a calibration target: any view with ``MIN_CHARUCO_CORNERS`` corners not on one line."""

    def __init__(self, spec: CharucoSpec):
        self.spec = spec
        self.board = spec.board()
        self.detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(corner ids (K,), image points (K, 2) float32); empty when no corner was found."""
        corners, ids, _, _ = self.detector.detectBoard(gray)
        if ids is None or corners is None:
            return np.zeros(0, dtype=int), np.zeros((0, 2), dtype=np.float32)
        return ids.ravel().astype(int), corners.reshape(-1, 2).astype(np.float32)

    def find(self, gray: np.ndarray):
        ids, corners = self.detect(gray)
        if len(ids) < MIN_CHARUCO_CORNERS:
            return f"{len(ids)} ChArUco corners found (at least {MIN_CHARUCO_CORNERS} needed)"
        if self.board.checkCharucoCornersCollinear(ids.reshape(-1, 1)):
            return f"the {len(ids)} corners found lie on one line"
        object_points, image_points = self.board.matchImagePoints(corners.reshape(-1, 1, 2), ids.reshape(-1, 1))
        return image_points.reshape(-1, 2).astype(np.float32), object_points.reshape(-1, 3).astype(np.float32)

    def describe(self) -> str:
        return self.spec.describe()


@dataclass(frozen=True)
class Calibration:
    """K: (3, 3); dist: (5,) k1 k2 p1 p2 k3; rms_px: RMS reprojection error over every corner used.

    views: the names of the views used; rejected: (name, reason) of the others;
    std: standard deviation of each of ``PARAMETERS`` (OpenCV's estimate from the fit);
    view_rms_px: RMS error of each view used; coverage: share of the image's
    ``COVERAGE_GRID`` cells holding a corner of a view used; points: corners used;
    dropped_corners: corners dropped as mislocated.
    """

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float
    views: tuple[str, ...]
    rejected: tuple[tuple[str, str], ...] = ()
    std: dict[str, float] | None = None
    view_rms_px: tuple[float, ...] = ()
    coverage: float = 0.0
    points: int = 0
    dropped_corners: int = 0

    def parameters(self) -> dict[str, float]:
        K, d = self.K, self.dist
        return dict(zip(PARAMETERS, (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d[:5])))


def find_corners(gray: np.ndarray, board: Board) -> np.ndarray | None:
    """(rows * columns, 2) float32 sub-pixel inner corners, or None if the board is not seen whole."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, (board.columns, board.rows), flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    return cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria).reshape(-1, 2)


def coverage(points_px: list[np.ndarray], width: int, height: int) -> float:
    """Share of the ``COVERAGE_GRID`` cells of a width x height image that hold at least one point."""
    columns, rows = COVERAGE_GRID
    covered = set()
    for points in points_px:
        for x, y in np.asarray(points).reshape(-1, 2):
            covered.add((min(int(x * columns / width), columns - 1), min(int(y * rows / height), rows - 1)))
    return len(covered) / (columns * rows)


def calibrate(images: dict[str, np.ndarray], board: CalibrationBoard) -> Calibration:
    """Calibrate from named (H, W) uint8 grayscale images of one camera."""
    if not images:
        raise CalibrationError("no images")
    # one camera's views share one size: the size most of them have (an odd file is named, not the rest)
    (height, width), _ = collections.Counter(image.shape[:2] for image in images.values()).most_common(1)[0]
    found, rejected = {}, []
    for name, image in images.items():
        if image.shape[:2] != (height, width):
            rejected.append((name, f"{image.shape[1]}x{image.shape[0]}, not {width}x{height} like most views"))
            continue
        result = board.find(image)
        if isinstance(result, str):
            rejected.append((name, result))
        else:
            found[name] = result
    return calibrate_points(found, (width, height), board, rejected)


def calibrate_points(found: dict[str, tuple[np.ndarray, np.ndarray]], size: tuple[int, int],
                     board: CalibrationBoard, rejected: list[tuple[str, str]] | None = None) -> Calibration:
    """Calibrate from each view's (image points (K, 2), board points (K, 3)).

    Two clean-ups, each followed by a new fit: corners far from where the
    fit puts them (a detector that snapped to the wrong corner, typically at
    the edge of a wide lens) are dropped, then views whose error is far above
    the others' are left out and named in ``rejected``.
    """
    rejected = list(rejected or [])
    found = dict(found)
    width, height = size
    _require_views(found, rejected, board)
    fit = _fit(found, size)
    dropped = 0
    for _ in range(MISLOCATED_ROUNDS):
        found, dropped_now = _drop_mislocated_corners(found, fit)
        if not dropped_now:
            break
        dropped += dropped_now
        for name in [n for n, (points, _) in found.items() if len(points) < MIN_CHARUCO_CORNERS]:
            rejected.append((name, f"{len(found[name][0])} corners left after dropping mislocated ones"))
            del found[name]
        _require_views(found, rejected, board)
        fit = _fit(found, size)
    view_rms = fit[4]
    limit_px = max(OUTLIER_FACTOR * float(np.median(view_rms)), OUTLIER_MIN_PX)
    outliers = [name for name, rms in zip(found, view_rms) if rms > limit_px]
    if outliers and len(found) - len(outliers) >= MIN_VIEWS:
        for name, rms in zip(list(found), view_rms):
            if rms > limit_px:
                rejected.append((name, f"reprojection error {rms:.2f} px, above {limit_px:.2f} px "
                                       f"({OUTLIER_FACTOR:g} x the median view's)"))
                del found[name]
        fit = _fit(found, size)
    rms_px, K, dist, std, view_rms, _, _ = fit
    return Calibration(K=K, dist=dist, width=width, height=height, rms_px=rms_px, views=tuple(found),
                       rejected=tuple(rejected), std=dict(zip(PARAMETERS, std)), view_rms_px=tuple(view_rms),
                       coverage=coverage([image for image, _ in found.values()], width, height),
                       points=sum(len(image) for image, _ in found.values()), dropped_corners=dropped)


def _require_views(found: dict, rejected: list, board: CalibrationBoard) -> None:
    if len(found) < MIN_VIEWS:
        reasons = "; ".join(f"{name}: {why}" for name, why in rejected[:5])
        raise CalibrationError(f"the {board.describe()} was found in {len(found)} of {len(found) + len(rejected)} "
                               f"images; at least {MIN_VIEWS} views are needed" + (f" ({reasons})" if reasons else ""))


def _drop_mislocated_corners(found: dict, fit) -> tuple[dict, int]:
    """The views without their worst corner where it is mislocated: farther from the fit than
    ``MISLOCATED_FACTOR`` x the median corner's error (and ``MISLOCATED_MIN_PX``); how many were dropped.
    One a view at a time: a far-off corner pulls its neighbours in the fit too."""
    _, K, dist, _, _, rvecs, tvecs = fit
    errors = []
    for (image, board), rvec, tvec in zip(found.values(), rvecs, tvecs):
        projected, _ = cv2.projectPoints(board.reshape(-1, 3), rvec, tvec, K, dist)
        errors.append(np.linalg.norm(projected.reshape(-1, 2) - image.reshape(-1, 2), axis=1))
    limit_px = max(MISLOCATED_FACTOR * float(np.median(np.concatenate(errors))), MISLOCATED_MIN_PX)
    kept, dropped = {}, 0
    for (name, (image, board)), error in zip(found.items(), errors):
        worst = int(np.argmax(error))
        if error[worst] > limit_px:
            image, board = np.delete(image, worst, axis=0), np.delete(board, worst, axis=0)
            dropped += 1
        kept[name] = (image, board)
    return kept, dropped


def _fit(found: dict, size: tuple[int, int]):
    """(rms px, K (3, 3), dist (5,), std of PARAMETERS (9,), RMS px of each view, rvecs, tvecs)."""
    image_points = [image.reshape(-1, 1, 2) for image, _ in found.values()]
    object_points = [board.reshape(-1, 1, 3) for _, board in found.values()]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms_px, K, dist, rvecs, tvecs, std_intrinsics, _, view_errors = cv2.calibrateCameraExtended(
        object_points, image_points, size, None, None, flags=0, criteria=criteria)
    return (float(rms_px), K, dist.ravel()[:5].astype(float), std_intrinsics.ravel()[:9].astype(float),
            view_errors.ravel().astype(float), rvecs, tvecs)


def write_calibration(path: Path, calibration: Calibration) -> None:
    """OpenCV's calibration YAML, written whole or not at all."""
    storage = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    try:
        storage.write("image_width", calibration.width)
        storage.write("image_height", calibration.height)
        storage.write("camera_matrix", calibration.K)
        storage.write("distortion_coefficients", calibration.dist.reshape(1, -1))
        storage.write("avg_reprojection_error", calibration.rms_px)
        storage.write("views", len(calibration.views))
        if calibration.std is not None:
            # one standard deviation of fx fy cx cy k1 k2 p1 p2 k3, from the fit
            storage.write("std_fx_fy_cx_cy_k1_k2_p1_p2_k3",
                          np.array([calibration.std[p] for p in PARAMETERS]).reshape(1, -1))
        storage.write("image_coverage", calibration.coverage)
    finally:
        text = storage.releaseAndGetString()
    write_whole(path, text)


# ------------------------------------------------------------ live capture

@dataclass(frozen=True)
class CaptureGoal:
    """When live capture takes a view and when it stops.

    A view is taken when the board has been still for ``still_frames`` frames
    (its corners moved less than ``still_px``) and is somewhere new: it covers a
    ``COVERAGE_GRID`` cell no view covered yet, or its corners are at least
    ``new_view_px`` from where every taken view had them (a new tilt or distance).
    Capture stops when at least ``min_views`` views give a calibration with the
    image ``coverage``, an RMS error of at most ``max_rms_px`` and fx, fy known to
    ``max_relative_std``; or at ``max_views``.
    """

    min_views: int = 15
    coverage: float = 0.7
    max_rms_px: float = 1.0
    max_relative_std: float = 0.005
    max_views: int = 50
    still_frames: int = 4
    still_px: float = 0.7
    new_view_px: float = 25.0


@dataclass(frozen=True)
class CaptureEvent:
    """What live capture tells the operator: a view taken, a calibration tried, or the end."""

    kind: str                 # "view", "calibration", "done"
    message: str
    calibration: Calibration | None = None


class ViewPicker:
    """Decides frame by frame which live frames become calibration views (see ``CaptureGoal``)."""

    def __init__(self, board: CharucoBoard, goal: CaptureGoal = CaptureGoal()):
        self.board = board
        self.goal = goal
        self.found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.images: dict[str, np.ndarray] = {}
        self.taken: list[dict[int, np.ndarray]] = []     # corner id -> image point, per view taken
        self.size: tuple[int, int] | None = None
        self._previous: dict[int, np.ndarray] = {}
        self._still = 0

    def offer(self, gray: np.ndarray) -> str | None:
        """Look at one frame; the name of the view if it was taken."""
        height, width = gray.shape[:2]
        if self.size is None:
            self.size = (width, height)
        elif self.size != (width, height):
            return None
        ids, points = self.board.detect(gray)
        current = dict(zip(ids.tolist(), points))
        moved_px = _median_shift(self._previous, current)
        self._still = self._still + 1 if moved_px is not None and moved_px < self.goal.still_px else 0
        self._previous = current
        if self._still < self.goal.still_frames or not self._is_new(current):
            return None
        result = self.board.find(gray)
        if isinstance(result, str):
            return None
        name = f"view{len(self.found) + 1:02d}"
        self.found[name] = result
        self.images[name] = gray
        self.taken.append(current)
        self._still = 0
        return name

    def coverage(self) -> float:
        return coverage([image for image, _ in self.found.values()], *self.size) if self.found else 0.0

    def _is_new(self, current: dict[int, np.ndarray]) -> bool:
        if len(current) < MIN_CHARUCO_CORNERS:
            return False
        covered = {cell for view in self.taken for cell in _cells(list(view.values()), *self.size)}
        if set(_cells(list(current.values()), *self.size)) - covered:
            return True
        for view in self.taken:
            shift_px = _median_shift(view, current)
            if shift_px is None or shift_px < self.goal.new_view_px:
                return False
        return True

    def verdict(self) -> tuple[bool, Calibration | None, str]:
        """(goal met, the calibration of the views so far or None, what is still missing)."""
        goal = self.goal
        if len(self.found) < max(goal.min_views, MIN_VIEWS):
            return False, None, f"{len(self.found)} of {goal.min_views} views"
        calibration = calibrate_points(dict(self.found), self.size, self.board)
        missing = []
        if calibration.coverage < goal.coverage:
            missing.append(f"coverage {100 * calibration.coverage:.0f} % < {100 * goal.coverage:.0f} % "
                           "(show the board in the empty parts of the image)")
        if calibration.rms_px > goal.max_rms_px:
            missing.append(f"RMS {calibration.rms_px:.2f} px > {goal.max_rms_px:g} px")
        for name in ("fx", "fy"):
            relative = calibration.std[name] / calibration.parameters()[name]
            if relative > goal.max_relative_std:
                missing.append(f"{name} uncertain to {100 * relative:.2f} % > {100 * goal.max_relative_std:.2f} % "
                               "(tilt the board more)")
        return not missing, calibration, "; ".join(missing) or "goal met"


def capture_live(source, board: CharucoBoard, goal: CaptureGoal = CaptureGoal(), stop=None,
                 on_event=lambda event: None, frame_timeout_s: float = 5.0) -> tuple[Calibration, dict]:
    """Take views from a started FrameSource (a V4L2 camera, or a replay) until the goal is met,
    ``max_views`` is reached, ``stop`` (a threading.Event) is set or the source ends; returns
    (the calibration, the images taken by name)."""
    picker, calibration = _take_views(source, ViewPicker(board, goal), stop, on_event, frame_timeout_s, until_goal=True)
    if calibration is None or len(calibration.views) + len(calibration.rejected) != len(picker.found):
        calibration = calibrate_points(dict(picker.found), picker.size or (0, 0), board)
    on_event(CaptureEvent("done", f"{len(picker.found)} views taken", calibration))
    return calibration, picker.images


def recorded_views(source, board: CharucoBoard, goal: CaptureGoal = CaptureGoal(), stop=None,
                   on_event=lambda event: None) -> dict[str, np.ndarray]:
    """The views a started replay of a recording gives as live capture would take them, all of them up to
    ``max_views`` (not stopped at the goal, nor calibrated on the way), by name."""
    picker, _ = _take_views(source, ViewPicker(board, goal), stop, on_event, frame_timeout_s=5.0, until_goal=False)
    return picker.images


def _take_views(source, picker: ViewPicker, stop, on_event, frame_timeout_s: float,
                until_goal: bool) -> tuple[ViewPicker, Calibration | None]:
    """Offer the source's frames to the picker until it ends, ``stop`` is set, ``max_views`` views are taken or
    (until_goal) the goal is met; (the picker, the calibration of the last verdict or None)."""
    goal, calibration = picker.goal, None
    while stop is None or not stop.is_set():
        frame = source.get(timeout_s=frame_timeout_s)
        if frame is None:
            if source.finished:
                break
            raise CalibrationError(f"no frame from the camera for {frame_timeout_s:g} s")
        name = picker.offer(frame.image)
        if name is None:
            continue
        image_points, _ = picker.found[name]
        on_event(CaptureEvent("view", f"{name}: {len(image_points)} corners, image coverage "
                                      f"{100 * picker.coverage():.0f} %"))
        if len(picker.found) >= goal.max_views:
            break
        if until_goal:
            met, calibration, missing = picker.verdict()
            if calibration is not None:
                on_event(CaptureEvent("calibration", f"{len(calibration.views)} views: RMS "
                                                     f"{calibration.rms_px:.3f} px, {missing}", calibration))
            if met:
                break
    return picker, calibration


def _cells(points, width: int, height: int) -> list[tuple[int, int]]:
    columns, rows = COVERAGE_GRID
    return [(min(int(x * columns / width), columns - 1), min(int(y * rows / height), rows - 1))
            for x, y in np.asarray(points).reshape(-1, 2)]


def _median_shift(before: dict[int, np.ndarray], after: dict[int, np.ndarray]) -> float | None:
    """Median distance (px) the corners seen in both moved; None with fewer than MIN_CHARUCO_CORNERS in common."""
    common = before.keys() & after.keys()
    if len(common) < MIN_CHARUCO_CORNERS:
        return None
    return float(np.median([np.linalg.norm(after[i] - before[i]) for i in common]))
