"""The shipped aisle flight and tape-measured maps of its site, for the tests of maps that are off."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from companion.capture.replay import sequence_camera
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap
from companion.geometry.frames import make_transform
from companion.sim.simulate import RecordedSequence, read_sequence

FOLDER = Path(__file__).resolve().parent.parent / "companion" / "data" / "sequences" / "warehouse_aisle"


def aisle_flight() -> tuple[CameraModel, RecordedSequence]:
    """(its camera, the sequence read back with its ground truth and frames: ``images()``)."""
    return sequence_camera(FOLDER), read_sequence(FOLDER)


def tape_map(facility_map: FacilityMap, seed: int) -> FacilityMap:
    """The map as a tape measure gives it: every entry moved by 2 cm sd along each of its own axes and turned
    by 2 degrees sd about each."""
    rng = np.random.default_rng(seed)
    return replace(facility_map, markers={i: replace(m, T_map_marker=m.T_map_marker @ make_transform(
        cv2.Rodrigues(np.radians(rng.normal(0, 2.0, 3)))[0], rng.normal(0, 0.02, 3)))
        for i, m in facility_map.markers.items()})
