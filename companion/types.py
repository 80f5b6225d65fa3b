"""The small typed values that flow one way through the pipeline.

    Frame -> [Detection] -> PoseMeasurement -> Estimate -> MAVLink message
                         ^ AttitudeSample (the flight controller's roll and pitch at the frame)

Conventions stated once, here, for every stage:

* Pixel coordinates: x right, y down, in pixels, with the centre of the
  top-left pixel at (0, 0) (OpenCV's convention).
* Marker corners: the four corners of the marker's *inner black square*
  (the ArUco border's outer edge), in the marker's upright order
  top-left, top-right, bottom-right, bottom-left, as an array of shape (4, 2).
* Times: integer nanoseconds on the monotonic clock (``time.monotonic_ns()``)
  of the frame's capture, in fields named ``t_ns``.
* Frames of reference and axes (camera, body, map, NED) are defined in
  ``companion.geometry.frames``; rigid transforms are 4x4 homogeneous matrices named
  ``T_to_from`` (``T_map_body`` maps body coordinates into the map frame).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

DetectionPath = Literal["square", "circles"]


@dataclass(frozen=True)
class Frame:
    """One grayscale camera image and when it was captured.

    image: (H, W) uint8 grayscale.
    t_ns: capture time on the monotonic clock, nanoseconds (a replay shifts the recorded times onto it:
        as fast as possible, they run ahead of the clock).
    index: sequence number from the source (0, 1, 2, ...).
    """

    image: np.ndarray
    t_ns: int
    index: int


@dataclass(frozen=True)
class Detection:
    """One RS marker found and decoded in one frame.

    symbol: printable name from the dictionary ("A", "7", "ARROW_UP", ...).
    id: the symbol's stable integer id in the dictionary.
    corners_px: (4, 2) float64, inner black square corners TL, TR, BR, BL
        in the marker's upright orientation, sub-pixel image coordinates.
    path: "square" (found by its black border) or "circles" (found by its
        corner circles when the border is broken).
    corrected: number of RS symbols that were corrected or recovered from
        erasures to decode this marker (0 for a clean read).
    quality: in [0, 1]; the fraction of the marker's cells that were read
        and agree with the decoded marker.
    circles_px: (K, 2) float64 image centres of the corner circles that
        were used (empty for the square path).
    circle_ids: (K,) int, the index of each of those circles in the
        marker layout's circle table (``companion.markers.layout.MarkerLayout.circles``).
    corner_sigma_px: standard deviation of each reported point's x and y
        (corners and circle centres), estimated by the detector from how
        well the marker fitted the image; None when the detector does not
        say (the pose stage then assumes ``PoseParams.corner_sigma_px``).
    corner_cov_px2: (8, 8) float64 joint covariance of ``corners_px``
        flattened row by row (x_TL, y_TL, x_TR, y_TR, x_BR, y_BR, x_BL, y_BL),
        pixels^2, or None. The square path's four corners come from one
        whole-pattern alignment (one homography), so their errors are
        correlated; its diagonal's mean is ``corner_sigma_px``^2. When given,
        the pose stage uses it for the corners instead of
        ``corner_sigma_px`` (which still applies to circle centres).
    """

    symbol: str
    id: int
    corners_px: np.ndarray
    path: DetectionPath
    corrected: int
    quality: float
    circles_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    circle_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=int))
    corner_sigma_px: float | None = None
    corner_cov_px2: np.ndarray | None = None


@dataclass(frozen=True)
class AttitudeSample:
    """The vehicle's roll and pitch from the flight controller at one instant.

    Body FRD relative to the local level frame (NED), Z-Y-X (3-2-1) Euler
    angles as MAVLink's ATTITUDE (``companion.geometry.frames``); yaw is not
    used. t_ns: when the autopilot measured it, on our monotonic clock (or on
    the time base of the recording it was read from).
    """

    t_ns: int
    roll_rad: float
    pitch_rad: float


@dataclass(frozen=True)
class PoseMeasurement:
    """The vehicle pose computed from the markers of one frame (no filtering).

    t_ns: capture time of the frame it was computed from.
    T_map_body: (4, 4) body FRD -> map frame.
    T_ned_body: (4, 4) body FRD -> local NED frame (the flight controller's).
    covariance_ned: (6, 6) over [north_m, east_m, down_m, roll_rad,
        pitch_rad, yaw_rad] (rotation errors as small angles about the NED
        axes), derived from the reprojection residuals and geometry.
    marker_ids: ids of the map markers used.
    reprojection_rms_px: RMS reprojection error of the accepted fit.
    unambiguous: the pose stage ruled out every other pose on its own (by
        the image or the flight controller's attitude), without a prior: a
        fix that needs no confirmation by further frames.
    map_covariance_ned: (6, 6) the share of ``covariance_ned`` that comes
        from the map's stated error of the markers used: the same error in
        every frame that sees them, so averaging frames does not shrink it
        (None: none, an exact map).
    """

    t_ns: int
    T_map_body: np.ndarray
    T_ned_body: np.ndarray
    covariance_ned: np.ndarray
    marker_ids: tuple[int, ...]
    reprojection_rms_px: float
    unambiguous: bool = False
    map_covariance_ned: np.ndarray | None = None


@dataclass(frozen=True)
class Estimate:
    """The fused vehicle state sent to the flight controller.

    t_ns: capture time of the newest frame that went into it.
    position_ned_m: (3,) north, east, down from the map's NED origin.
    velocity_ned_m_s: (3,).
    roll_rad, pitch_rad, yaw_rad: body FRD -> NED attitude, Z-Y-X (3-2-1) Euler.
    covariance_ned: (6, 6) over [north, east, down, roll, pitch, yaw].
    reset_counter: incremented when the estimate jumps (re-acquisition).
    tracking: True while recent markers support the estimate.
    velocity_covariance_ned: (3, 3) over [v_north, v_east, v_down], or None
        if unknown.
    """

    t_ns: int
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    covariance_ned: np.ndarray
    reset_counter: int
    tracking: bool
    velocity_covariance_ned: np.ndarray | None = None
