"""The detection phase of a survey: every frame of every walk, its markers as point correspondences.

``collect(sequences, camera, detector, ...)`` replays each sequence (anything
``companion.capture.replay`` reads), detects markers in every frame and keeps
each marker's inner-square corners and, for the circles path, its corner
circles' centres: ``Sighting``\\s of marker-frame points against pixels.
``keyframes`` then drops frames where the camera barely moved (the same
markers at nearly the same pixels): such frames add the same view again,
so they would cost time and make the uncertainty look smaller than it is.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from companion.capture.replay import ReplaySource, check_recording_path, open_recording, sequence_camera
from companion.capture.source import SourceError
from companion.geometry import frames
from companion.geometry.camera import CameraModel, load_camera
from companion.markers.layout import MarkerLayout
from companion.progress import progress_bar
from companion.types import Detection

# the kinds of point a sighting gives, each with its own noise: the square path's corners (aligned on the whole
# printed pattern), the circles path's corners and its circle centres
POINT_KINDS = ("corner", "circles-path corner", "circle centre")


class SurveyError(ValueError):
    """The survey cannot be made from this input; the message says what is wrong and what to do."""


@dataclass(frozen=True)
class Sighting:
    """One marker seen in one frame.

    points_marker_m: (K, 3) its points in the marker frame (4 corners TL, TR, BR, BL, then circle centres).
    points_px: (K, 2) where they are in the image.
    path: the detector's path that found it ("square" or "circles").
    sigma_px: the detector's standard deviation of each point's x and y (``Detection.corner_sigma_px``), or
        None where it states none.
    """

    marker_id: int
    points_marker_m: np.ndarray
    points_px: np.ndarray
    path: str = "square"
    sigma_px: float | None = None

    def point_kinds(self) -> np.ndarray:
        """(K,) index into POINT_KINDS of each point."""
        kinds = np.full(len(self.points_px), POINT_KINDS.index("circle centre"))
        kinds[:4] = POINT_KINDS.index("corner" if self.path == "square" else "circles-path corner")
        return kinds

    @property
    def corners_px(self) -> np.ndarray:
        """(4, 2) the inner-square corners in the image."""
        return self.points_px[:4]


@dataclass(frozen=True)
class SurveyFrame:
    """A frame of a walk with the markers decoded in it (each marker at most once).

    walk: index of the sequence it came from; index: its frame number there; t_ns: recorded time.
    """

    walk: int
    index: int
    t_ns: int
    sightings: tuple[Sighting, ...]

    @property
    def marker_ids(self) -> tuple[int, ...]:
        return tuple(s.marker_id for s in self.sightings)


@dataclass(frozen=True)
class Footage:
    """Everything the detection phase found.

    frames: every frame with at least one marker, in walk and time order.
    frame_count: frames read (with or without markers).
    skipped: frames that could not be read.
    """

    frames: tuple[SurveyFrame, ...]
    frame_count: int
    skipped: int

    def frames_seen(self) -> dict[int, int]:
        """Number of frames each marker id was decoded in."""
        counts: dict[int, int] = {}
        for frame in self.frames:
            for marker_id in frame.marker_ids:
                counts[marker_id] = counts.get(marker_id, 0) + 1
        return counts


def check_footage(sequences: list[Path], fps: float | None) -> None:
    """SurveyError, before any work, for a walk that is no recording (missing, a map given for a video) or an
    ``--fps`` that is no frame rate."""
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise SurveyError(f"--fps must be positive, not {fps}")
    for sequence in sequences:
        try:
            check_recording_path(sequence)
        except SourceError as error:
            raise SurveyError(str(error)) from None


def footage_camera(sequences: list[Path], camera_path: str | None) -> CameraModel:
    """The camera that filmed the footage: the file ``camera_path`` (``--camera``) when given, else the one
    each sequence folder's sequence.yaml describes (a drone's recording, a simulated walk), which must be
    one camera for all. SurveyError when a sequence carries none (a video, an image folder) or they differ."""
    if camera_path is not None:
        return load_camera(camera_path)
    cameras = []
    for sequence in sequences:
        camera = sequence_camera(sequence) if Path(sequence).is_dir() else None
        if camera is None:
            raise SurveyError(f"{sequence}: which camera filmed it? give --camera (a calibration file, companion "
                              f"calibrate): only a sequence folder's sequence.yaml names its camera")
        cameras.append(camera)
    for sequence, camera in zip(sequences[1:], cameras[1:]):
        if not camera.same_intrinsics(cameras[0]):
            raise SurveyError(f"{sequence} and {sequences[0]} were filmed by different cameras (their "
                              f"sequence.yaml): survey them separately, or give the one --camera that took both")
    return cameras[0]


def collect(sequences: list[Path], camera: CameraModel, detector, size_m: Callable[[int], float | None],
            layout: MarkerLayout, fps: float | None = None, progress: bool = True) -> Footage:
    """Detect markers in every frame of every sequence; raises SurveyError for unusable footage.

    size_m: the inner-square side of a marker id (fixes its points in the marker frame); None leaves it out.
    """
    found: list[SurveyFrame] = []
    frame_count = skipped = 0
    for walk, sequence in enumerate(sequences):
        try:
            recording = open_recording(sequence, fps, "--fps")
        except SourceError as error:
            raise SurveyError(str(error)) from None
        source = ReplaySource(recording, realtime=False)
        source.start()
        bar = progress_bar(len(recording.frames), "frame", progress, f"detecting {Path(sequence).name}")
        first = True
        try:
            for frame in source.frames():
                if first:
                    problem = camera.frame_size_problem(frame.image)
                    if problem is not None:
                        raise SurveyError(f"{sequence}: {problem}")
                    first = False
                frame_count += 1
                bar.update(1)
                sightings = sightings_of(detector.detect(frame.image), size_m, layout)
                if sightings:
                    found.append(SurveyFrame(walk, int(frame.index), source.recorded_t_ns(frame), sightings))
        finally:
            bar.close()
            source.close()
        if source.error is not None:
            raise SurveyError(f"{sequence}: the replay failed: {source.error}")
        skipped += source.counters.corrupt
    return Footage(tuple(found), frame_count, skipped)


def sightings_of(detections: list[Detection], size_m: Callable[[int], float | None],
                 layout: MarkerLayout) -> tuple[Sighting, ...]:
    """Each marker decoded once in the frame as points; a marker decoded twice is left out (it cannot be
    both), and so is one whose size is None."""
    ids = [d.id for d in detections]
    circles_uv = np.asarray(layout.circles, dtype=float)[:, :2]
    sightings = []
    for detection in detections:
        size = size_m(detection.id)
        if ids.count(detection.id) > 1 or size is None:
            continue
        points_marker = [frames.marker_inner_corners_m(size)]
        points_px = [np.asarray(detection.corners_px, dtype=float).reshape(4, 2)]
        circle_ids = np.asarray(detection.circle_ids, dtype=int).reshape(-1)
        if len(circle_ids):
            valid = (circle_ids >= 0) & (circle_ids < len(circles_uv))
            points_marker.append(frames.grid_to_marker_m(circles_uv[circle_ids[valid]], layout.inner_origin,
                                                         layout.inner_cells, size))
            points_px.append(np.asarray(detection.circles_px, dtype=float).reshape(-1, 2)[valid])
        sightings.append(Sighting(detection.id, np.vstack(points_marker), np.vstack(points_px), detection.path,
                                  detection.corner_sigma_px))
    return tuple(sightings)


def keyframes(survey_frames, min_motion_px: float) -> list[SurveyFrame]:
    """The frames that show something new: a different set of markers than the last kept frame of the
    walk, or the shared markers' corners moved by at least ``min_motion_px`` (median) since then."""
    kept: list[SurveyFrame] = []
    last: SurveyFrame | None = None
    for frame in survey_frames:
        if last is None or last.walk != frame.walk or _moved_px(last, frame) >= min_motion_px:
            kept.append(frame)
            last = frame
    return kept


def _moved_px(a: SurveyFrame, b: SurveyFrame) -> float:
    """Median corner displacement (px) of the markers both frames see; inf if they see different markers."""
    if set(a.marker_ids) != set(b.marker_ids):
        return np.inf
    corners_a = {s.marker_id: s.corners_px for s in a.sightings}
    shifts = [np.linalg.norm(s.corners_px - corners_a[s.marker_id], axis=1) for s in b.sightings]
    return float(np.median(np.concatenate(shifts)))
