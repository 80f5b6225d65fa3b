"""The daemon's pipeline tells the detector where the mapped markers in view should be (projected from its
fused pose): checked against where the detector finds them in the bundled recorded flight's images."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from companion.capture.replay import open_recording
from companion.daemon.pipeline import Pipeline
from companion.detect.detector import Detector
from companion.fusion import PoseFilter
from companion.geometry import frames
from companion.geometry.pose import PoseSolver
from companion.localize import resources
from companion.types import Frame

SEQUENCE = Path(__file__).resolve().parents[1] / "tests" / "data" / "sequences" / "warehouse_hover"


class RecordingDetector(Detector):
    """The real detector, keeping what the pipeline told it for each frame."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.expected = []

    def detect(self, gray, expected_px=None):
        self.expected.append(None if expected_px is None else np.array(expected_px))
        return super().detect(gray, expected_px=expected_px)


def test_expected_places_from_the_fused_pose_match_the_markers_found():
    facility_map, camera = resources(SEQUENCE, None, None)
    detector = RecordingDetector(camera=camera)
    pipeline = Pipeline(detector, PoseSolver(facility_map, camera), PoseFilter(), None,
                        frames.invert_transform(facility_map.T_ned_map))
    recording = open_recording(SEQUENCE)
    video = cv2.VideoCapture(str(recording.video))
    records = []
    for index, t_ns in enumerate(recording.t_ns[:30]):
        ok, image = video.read()
        assert ok
        records.append(pipeline.process(Frame(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), int(t_ns), index)))
    video.release()
    assert detector.expected[0] is None  # no fused pose yet: the whole frame is searched
    matched = 0
    for record, expected in zip(records[1:], detector.expected[1:]):
        if expected is None or not record.detections:
            continue
        assert expected.shape[1:] == (4, 2)
        for detection in record.detections:
            # the detection's corners (TL, TR, BR, BL) against the nearest expected marker's, same order
            errors = np.linalg.norm(expected - detection.corners_px[None], axis=2).max(axis=1)
            assert errors.min() < 0.1 * np.linalg.norm(detection.corners_px[1] - detection.corners_px[0]) + 2.0
            matched += 1
    assert matched >= 20


def test_no_mapped_marker_in_view_expects_none():
    # far from every mapped marker: an empty (0, 4, 2) set, not an error; no prior or another frame size: None
    facility_map, camera = resources(SEQUENCE, None, None)
    pipeline = Pipeline(Detector(camera=camera), PoseSolver(facility_map, camera), PoseFilter(), None,
                        frames.invert_transform(facility_map.T_ned_map))
    far_away = frames.make_transform(np.eye(3), np.array([1.0e4, 1.0e4, 0.0]))
    assert pipeline._expected_markers_px(far_away, (camera.height, camera.width)).shape == (0, 4, 2)
    assert pipeline._expected_markers_px(None, (camera.height, camera.width)) is None
    assert pipeline._expected_markers_px(far_away, (camera.height + 2, camera.width)) is None
