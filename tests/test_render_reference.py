"""The simulated camera draws what it drew before the renderer was made faster.

tests/data/render_reference/ holds the warehouse frames of config/sitl-camera.yaml
rendered at a few poses of its 2 m square: the plain rendering and the degraded frame
(noise seeded). First drawn before the speed-up (commit 20aea9d); drawn again when the
texture filtering was made sharper on purpose (issue 9: anisotropic mip levels, box mip
levels, bicubic lens remap; 0.4-0.9 DN mean change, the same markers within 0.055 px, one
more marker found in pose 2's plain frame); and when the lens remap became Lanczos (bicubic
shifted corners near the image centre: tests/test_render.py; 0.07-0.25 DN mean change, the same
markers within 0.029 px). A speed-up must draw the same images to within
rounding (tile seams apart, see below) and the detector must find the same markers at the
same corners in them.

Regenerate (only when a drawing change is intended): python tests/test_render_reference.py
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.capture.simulated import SimState, SimulatedCamera
from companion.daemon.config import load_config
from companion.daemon.service import make_detector
from companion.geometry import frames

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "sitl-camera.yaml"
REFERENCE = Path(__file__).resolve().parent / "data" / "render_reference"
# (x, y) offsets from the config's start on its 2 m square, at 1.2 m, facing the start heading
OFFSETS_M = [(-1.0, -1.0), (0.3, -1.0), (1.0, 0.4), (-0.2, 1.0)]


def vehicle_state(config, offset_m, index: int) -> SimState:
    """The vehicle at ``offset_m`` from the start, 1.2 m up, at the start heading, moving at 0.5 m/s."""
    x, y, z = config.source.start_m
    T_ned_map = config.facility_map.T_ned_map
    position_map = np.array([x + offset_m[0], y + offset_m[1], z + 1.2, 1.0])
    heading = math.radians(config.source.start_heading_deg)
    forward_ned = T_ned_map[:3, :3] @ [math.cos(heading), math.sin(heading), 0.0]
    R_ned_body = frames.rotation_from_euler_321(0.0, 0.0, math.atan2(forward_ned[1], forward_ned[0]))
    return SimState(index * 33_000_000, (T_ned_map @ position_map)[:3], R_ned_body, np.array([0.5, 0.2, 0.0]))


def frames_now(config) -> list[tuple[np.ndarray, np.ndarray]]:
    """(plain rendering, degraded frame) per pose, both (480, 640) uint8."""
    camera = SimulatedCamera(config.facility_map, config.camera, config.source.params)
    out = []
    for index, offset in enumerate(OFFSETS_M):
        state = vehicle_state(config, offset, index)
        T_camera_map = camera._T_camera_map(state.T_ned_body())
        plain = camera._renderer.render(camera._quads_in_view(T_camera_map), T_camera_map, background=40.0).image
        out.append((plain, camera._render(state, index)))
    return out


def reference_path(index: int, kind: str) -> Path:
    return REFERENCE / f"pose{index}_{kind}.png"


@pytest.fixture(scope="module")
def config():
    return load_config(CONFIG)


@pytest.fixture(scope="module")
def rendered(config):
    return frames_now(config)


@pytest.mark.parametrize("index", range(len(OFFSETS_M)))
def test_renderings_match_the_reference(rendered, index):
    plain, degraded = rendered[index]
    old_plain = cv2.imread(str(reference_path(index, "plain")), cv2.IMREAD_GRAYSCALE)
    old_degraded = cv2.imread(str(reference_path(index, "degraded")), cv2.IMREAD_GRAYSCALE)
    # rounding apart, the same pixels; but for the seams between the tiles of an opaque surface (a rack face
    # in 1.5 m tiles): their anti-aliased edges let up to a quarter of what lies behind show through, and
    # what lies wholly behind such a surface is no longer drawn (a few hundred pixels of a frame)
    # The degraded frame: the same noise draws; exposure, vignette and noise are now rounded once, not after
    # each step (1 DN in about a quarter of the pixels).
    for new, old, mean_dn in ((plain, old_plain, 0.05), (degraded, old_degraded, 0.3)):
        diff = np.abs(new.astype(int) - old)
        assert diff.mean() < mean_dn
        assert np.mean(diff > 2) < 0.005


@pytest.mark.parametrize("index", range(len(OFFSETS_M)))
def test_detections_match_the_reference(config, rendered, index):
    detector = make_detector(config)
    for kind, image in zip(("plain", "degraded"), rendered[index]):
        old = {d.id: d for d in detector.detect(cv2.imread(str(reference_path(index, kind)),
                                                                  cv2.IMREAD_GRAYSCALE))}
        new = {d.id: d for d in detector.detect(image)}
        assert old, f"pose {index}: the reference shows no marker"
        assert set(new) == set(old)
        for marker_id, detection in new.items():
            shift_px = np.abs(np.asarray(detection.corners_px) - np.asarray(old[marker_id].corners_px)).max()
            assert shift_px < 0.05, f"pose {index} {kind} marker {marker_id}: corners moved {shift_px:.3f} px"


if __name__ == "__main__":
    REFERENCE.mkdir(parents=True, exist_ok=True)
    for i, (plain, degraded) in enumerate(frames_now(load_config(CONFIG))):
        cv2.imwrite(str(reference_path(i, "plain")), plain)
        cv2.imwrite(str(reference_path(i, "degraded")), degraded)
        print(reference_path(i, "plain"), reference_path(i, "degraded"))
