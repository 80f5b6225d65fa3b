"""``companion simulate``: render a camera sequence flying through a facility map.

The world is built from the map: every marker as its printed texture on a
small backing sheet, shelving faces or walls behind groups of markers that
share a plane, a floor, a ceiling and enclosing walls. A trajectory (a CSV of
body poses or a built-in pattern) moves the vehicle; the configured camera
(intrinsics, distortion, mounting) looks out of it; the rasteriser
(``companion.sim.raster``) draws each frame, people and boxes
(``companion.sim.occluders``) may cross the view, and the image-realism knobs
(``companion.sim.degrade.Degradations``) make it look like a real camera's.
Output: a sequence folder as ``docs/simulator.md`` (and the project
conventions) describe::

    SEQ/sequence.yaml, map.yaml (a copy of the map: the folder can be copied
    and still localized), frames/NNNNNN.png (or video.avi), timestamps.csv,
    groundtruth.csv, markers.csv (per-frame marker corners in pixels),
    attitude.csv (the flight controller's roll and pitch: the truth with
    ``AttitudeNoise``; ``companion.capture.attitude_csv``)

Simulating again into the same folder replaces all of that (no stale frame
of a longer earlier run is left) once the new sequence is complete: until
then it is written in a hidden folder beside it, removed if the run fails or
is interrupted. A folder holding anything else is refused.
"""
from __future__ import annotations

import csv
import math
import os
import secrets
import shutil
import stat
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from companion.capture.attitude_csv import ATTITUDE_FILE, write_attitude_csv
from companion.capture.replay import sequence_map_path
from companion.files import write_whole
from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap
from companion.markers.layout import MarkerLayout
from companion.progress import progress_bar
from companion.sim import occluders
from companion.sim import raster
from companion.sim import trajectory as trajectories
from companion.sim.degrade import Degradations
from companion.types import AttitudeSample
from companion.yaml_input import read_yaml

DEFAULT_CAMERA = {"width": 640, "height": 480, "hfov_deg": 70.0,
                  "mount": {"lever_arm_m": [0.1, 0.0, 0.05], "facing": "forward", "tilt_down_deg": 20.0}}
# a realistic small camera: motion blur over the exposure, a little optics blur, vignetting, sensor noise
DEFAULT_DEGRADATIONS = Degradations(motion_blur=True, optics_blur_sigma_px=0.6, vignette_strength=0.15,
                                    read_noise_dn=1.5, shot_noise_gain=0.03)
# T_map_body as groundtruth.csv gives it: position, then the unit quaternion w, x, y, z
POSE_COLUMNS = ("x_m", "y_m", "z_m", "qw", "qx", "qy", "qz")
GROUNDTRUTH_COLUMNS = ("frame", "t_ns", *POSE_COLUMNS, "north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "yaw_rad")
MARKERS_COLUMNS = ("frame", "t_ns", "marker_id", "tl_x", "tl_y", "tr_x", "tr_y", "br_x", "br_y", "bl_x", "bl_y",
                   "corners_visible", "visible_fraction", "inner_px")
PX_PER_CELL = 16
TILE_M = 1.5
PROGRESS_MIN_FRAMES = 60  # longer renders show a progress bar unless told otherwise
MAX_FRAMES = 1_000_000   # 9 hours at 30 fps: more is a typo (a duration in ms, say)
MAP_COPY = "map.yaml"
# What a simulation writes into its folder (frames/ holds NNNNNN.png besides).
GENERATED_FILES = ("sequence.yaml", MAP_COPY, "timestamps.csv", "groundtruth.csv", "markers.csv", "video.avi",
                   ATTITUDE_FILE)
GENERATOR = "companion simulate"


class SimulationError(ValueError):
    """Bad simulator input (options, files); the message names what is wrong."""


# -------------------------------------------------------------------- world

@dataclass
class WorldMarker:
    """A map marker in the rendered world: its texture and its quad's index."""

    marker_id: int
    size_m: float
    T_map_marker: np.ndarray
    texture: raster.MarkerTexture
    quad_index: int


@dataclass
class World:
    """Everything static that the camera can see, in the map frame."""

    quads: list[raster.TexturedQuad]
    markers: list[WorldMarker]
    floor_z_m: float
    bounds_m: np.ndarray  # (2, 3) min and max corner of the hall
    T_ned_map: np.ndarray  # (4, 4) map -> NED, for the ground truth


def build_world(facility_map: FacilityMap, seed: int = 0) -> World:
    """Markers on sheets, shelf faces or walls behind marker groups, floor, ceiling and walls."""
    rng = np.random.default_rng(seed)
    layout = MarkerLayout(parity=facility_map.parity, dictionary=facility_map.dictionary)
    markers = sorted(facility_map.markers.values(), key=lambda m: m.id)
    if not markers:
        raise SimulationError(f"{facility_map.path}: the map has no markers to render")
    positions = np.array([m.T_map_marker[:3, 3] for m in markers])
    low, high = positions.min(axis=0), positions.max(axis=0)
    floor_z = min(0.0, float(low[2]))
    ceiling_z = max(float(high[2]) + 0.02, floor_z + 3.5)
    margin = 0.5
    bounds = np.array([[low[0] - margin, low[1] - margin, floor_z], [high[0] + margin, high[1] + margin, ceiling_z]])
    textures = _SurfaceTextures(rng)

    quads: list[raster.TexturedQuad] = []
    quads += _floor_and_ceiling(bounds, textures)
    quads += _enclosing_walls(bounds, textures)
    grouped = _vertical_groups(markers)
    for group in grouped:
        quads += _panel_behind(group, bounds, textures)

    world_markers = []
    in_groups = {m.id for group in grouped for m in group}
    for m in markers:
        texture = raster.rs_marker_texture(layout, m.id, PX_PER_CELL)
        quad = raster.marker_quad(texture, m.size_m, m.T_map_marker, gain=0.84, offset=18.0)
        sheet_scale = 1.25 if m.id in in_groups else 2.2
        quads.append(_sheet_behind(quad, sheet_scale, textures, rng))
        quads.append(quad)
        world_markers.append(WorldMarker(m.id, m.size_m, m.T_map_marker, texture, len(quads) - 1))
    return World(quads, world_markers, floor_z, bounds, facility_map.T_ned_map)


class _SurfaceTextures:
    """A few procedural surface textures, made once and shared by many tiles."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.floor = [raster.make_texture(self._concrete(256)) for _ in range(3)]
        self.wall = [raster.make_texture(self._blocks(256)) for _ in range(2)]
        self.ceiling = raster.make_texture(raster.solid_texture(rng, (64, 64), 200.0, 10.0))
        self.sheet = raster.make_texture(raster.solid_texture(rng, (64, 64), 235.0, 6.0))

    def _concrete(self, n: int) -> np.ndarray:
        rng = self.rng
        base = raster.solid_texture(rng, (n, n), 150.0, 18.0).astype(np.float32)
        base += 2.0 * cv2.GaussianBlur(rng.normal(0, 1, (n, n)).astype(np.float32), (0, 0), 1.5)
        for _ in range(3):  # scuffs and cracks
            p0 = rng.integers(0, n, 2)
            p1 = p0 + rng.integers(-n // 3, n // 3, 2)
            cv2.line(base, tuple(int(v) for v in p0), tuple(int(v) for v in p1), float(rng.uniform(90, 130)), 1,
                     cv2.LINE_AA)
        base[:2, :] = base[:, :2].T * 0.8  # expansion joint along the tile edge
        return np.clip(base, 0, 255).astype(np.uint8)

    def _blocks(self, n: int) -> np.ndarray:
        rng = self.rng
        wall = raster.solid_texture(rng, (n, n), 175.0, 8.0)
        course = n // 8
        for row in range(8):
            y = row * course
            wall[y:y + 2, :] = 140
            offset = (row % 2) * (n // 4)
            for x in range(offset, n, n // 2):
                wall[y:y + course, x:x + 2] = 140
        return wall

    def shelving(self, width_px: int, height_px: int, height_m: float) -> raster.Texture:
        """Rack face: dark interior, boxes on beams every ~0.8 m, uprights at the edges."""
        rng = self.rng
        face = raster.solid_texture(rng, (width_px, height_px), 55.0, 10.0)
        px_per_m = height_px / height_m
        beams = np.arange(0.05, height_m, 0.8)
        for z in beams:
            y = int(height_px - z * px_per_m)
            x = 0
            while x < width_px:  # boxes standing on this beam
                w = int(rng.uniform(0.25, 0.6) * px_per_m)
                h = int(rng.uniform(0.25, 0.6) * px_per_m)
                if rng.uniform() < 0.8:
                    cv2.rectangle(face, (x + 2, max(y - h, 0)), (x + w - 2, y), float(rng.uniform(110, 190)), -1)
                x += w
            cv2.rectangle(face, (0, max(y - int(0.06 * px_per_m), 0)), (width_px, y), 120, -1)
        upright = max(int(0.05 * px_per_m), 2)
        face[:, :upright] = 90
        face[:, -upright:] = 90
        return raster.make_texture(face)


def _tiles(origin: np.ndarray, along: np.ndarray, up: np.ndarray, length_m: float, height_m: float,
           tile_m: float = TILE_M):
    """Split a rectangle (origin = bottom-left, unit axes along/up) into tile corner sets (4, 3)."""
    n_along = max(int(math.ceil(length_m / tile_m - 1e-9)), 1)
    n_up = max(int(math.ceil(height_m / tile_m - 1e-9)), 1)
    da, du = length_m / n_along, height_m / n_up
    for i in range(n_along):
        for j in range(n_up):
            bl = origin + i * da * along + j * du * up
            yield np.array([bl + du * up, bl + du * up + da * along, bl + da * along, bl]), (i, j)


def _floor_and_ceiling(bounds: np.ndarray, textures: _SurfaceTextures) -> list[raster.TexturedQuad]:
    (x0, y0, z0), (x1, y1, z1) = bounds
    quads = []
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    floor_origin = np.array([x0, y0, z0 - raster.MARKER_LIFT_M])
    for corners, (i, j) in _tiles(floor_origin, ex, ey, x1 - x0, y1 - y0):
        quads.append(raster.TexturedQuad(corners, textures.floor[(i * 7 + j * 3) % len(textures.floor)], gain=0.95))
    ceiling_origin = np.array([x0, y0, z1 + raster.MARKER_LIFT_M])
    for corners, _ in _tiles(ceiling_origin, ex, ey, x1 - x0, y1 - y0, tile_m=4 * TILE_M):
        quads.append(raster.TexturedQuad(corners, textures.ceiling, gain=0.8))
    return quads


def _enclosing_walls(bounds: np.ndarray, textures: _SurfaceTextures) -> list[raster.TexturedQuad]:
    (x0, y0, z0), (x1, y1, z1) = bounds
    corners_xy = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    quads = []
    for k in range(4):
        a = np.array([*corners_xy[k], z0])
        b = np.array([*corners_xy[(k + 1) % 4], z0])
        length = float(np.linalg.norm(b - a))
        along = (b - a) / length
        for corners, (i, j) in _tiles(a, along, np.array([0.0, 0.0, 1.0]), length, z1 - z0):
            quads.append(raster.TexturedQuad(corners, textures.wall[(i + j) % 2], gain=0.85))
    return quads


def _vertical_groups(markers, max_gap_m: float = 3.5) -> list[list]:
    """Runs of two or more wall markers on one vertical plane (same facing within 2 deg,
    offset within 5 cm), neighbours at most ``max_gap_m`` apart along the plane."""
    planes: dict[tuple[int, int], list] = {}
    for m in markers:
        n = m.T_map_marker[:3, 2]
        if abs(n[2]) > 0.05:
            continue
        heading = int(round(math.degrees(math.atan2(n[1], n[0])) / 2.0))
        offset = int(round(float(n @ m.T_map_marker[:3, 3]) / 0.05))
        planes.setdefault((heading, offset), []).append(m)
    groups = []
    for plane in planes.values():
        n = plane[0].T_map_marker[:3, 2]
        along = np.array([-n[1], n[0], 0.0])
        plane.sort(key=lambda m: float(m.T_map_marker[:3, 3] @ along))
        run = [plane[0]]
        for m in plane[1:]:
            gap = float((m.T_map_marker[:3, 3] - run[-1].T_map_marker[:3, 3]) @ along)
            if gap > max_gap_m:
                groups.append(run)
                run = []
            run.append(m)
        groups.append(run)
    return [g for g in groups if len(g) >= 2]


def _panel_behind(group, bounds: np.ndarray, textures: _SurfaceTextures) -> list[raster.TexturedQuad]:
    """A shelving face behind a marker group (none on the hall's boundary: the wall is there)."""
    up = np.array([0.0, 0.0, 1.0])
    n = group[0].T_map_marker[:3, 2] * [1.0, 1.0, 0.0]
    n /= np.linalg.norm(n)
    # a viewer facing the panel looks along -n; their right is (-n) x up = up x n
    right = np.cross(up, n)
    positions = np.array([m.T_map_marker[:3, 3] for m in group])
    (x0, y0, z0), (x1, y1, _) = bounds
    centre = positions.mean(axis=0)
    if any(abs(centre[k] - edge) < 0.6 for k, edge in ((0, x0), (0, x1), (1, y0), (1, y1))):
        return []
    along = positions @ right
    start, end = float(along.min()) - 1.2, float(along.max()) + 1.2
    height = float(max(positions[:, 2].max() + 0.6, 2.4))
    offset = float(np.mean(positions @ n)) - 2 * raster.MARKER_LIFT_M
    bottom_left = offset * n + start * right + z0 * up
    n_tiles = max(int(math.ceil((end - start) / TILE_M)), 1)
    tile = (end - start) / n_tiles
    texture_height_px = int(256 * height / tile) // 2 * 2
    quads = []
    for i in range(n_tiles):
        bl = bottom_left + i * tile * right
        corners = np.array([bl + height * up, bl + height * up + tile * right, bl + tile * right, bl])
        quads.append(raster.TexturedQuad(corners, textures.shelving(256, texture_height_px, height)))
    return quads


def _sheet_behind(quad: raster.TexturedQuad, scale: float, textures: _SurfaceTextures, rng) -> raster.TexturedQuad:
    """A light sheet (laminated sign, painted board) a little larger than the marker, just behind it."""
    c = quad.corners_world
    centre = c.mean(axis=0)
    front = np.cross(c[3] - c[0], c[1] - c[0])
    front /= np.linalg.norm(front)
    corners = centre + scale * (c - centre) - raster.MARKER_LIFT_M * front
    return raster.TexturedQuad(corners, textures.sheet, gain=float(rng.uniform(0.75, 0.9)))


# ---------------------------------------------------------------- occluders

def plan_occluders(traj: trajectories.Trajectory, camera: CameraModel, count: int, world: World,
                   rng: np.random.Generator) -> list[occluders.PassingOccluder]:
    """``count`` crossings spread over the flight, each well in front of what the camera sees.

    Each walks straight across the view the camera has at the crossing's
    middle time ``t_mid``, perpendicular to its optical axis, at 0.45 times
    the range of the nearest marker in view (0.7-2 m), so it passes between
    the camera and the markers, and is in the middle of the image at t_mid.
    """
    crossings = []
    for k in range(count):
        t_mid = (k + rng.uniform(0.3, 0.7)) * traj.duration_s / max(count, 1)
        T_map_camera = traj.pose_at(t_mid) @ camera.T_body_camera
        optical_axis = T_map_camera[:3, 2]
        forward = np.array([optical_axis[0], optical_axis[1], 0.0])
        forward /= max(np.linalg.norm(forward), 1e-9)
        right = np.array([forward[1], -forward[0], 0.0])
        distance = float(np.clip(0.45 * _nearest_marker_range(world, camera, T_map_camera), 0.7, 2.0))
        speed = rng.uniform(0.9, 1.4)
        direction = 1.0 if rng.uniform() < 0.5 else -1.0
        half_width = distance * math.tan(math.radians(40.0)) + 0.6
        centre = T_map_camera[:3, 3] + distance * forward
        start = centre - direction * half_width * right
        start[2] = world.floor_z_m
        half_time = half_width / speed
        kind = "person" if rng.uniform() < 0.6 else "box"
        # in the middle of the view at t_mid
        crossings.append(occluders.PassingOccluder(kind, t_mid - half_time, t_mid + half_time, start,
                                                   direction * speed * right, -forward,
                                                   int(rng.integers(0, 2**31))))
    return crossings


def _nearest_marker_range(world: World, camera: CameraModel, T_map_camera: np.ndarray) -> float:
    """Range (m) to the nearest marker centre inside the image, or 3.3 m with none in view."""
    centres = np.array([m.T_map_marker[:3, 3] for m in world.markers])
    T_camera_map = frames.invert_transform(T_map_camera)
    in_camera = frames.transform_points(T_camera_map, centres)
    in_view = (in_camera[:, 2] > 0.1) & camera.in_image(camera.project(in_camera))
    if not in_view.any():
        return 3.3
    return float(np.linalg.norm(in_camera[in_view], axis=1).min())


# ---------------------------------------------------------------- rendering

@dataclass
class RenderedFrame:
    image: np.ndarray
    t_ns: int
    T_map_body: np.ndarray
    truths: list[raster.MarkerTruth]


class Simulator:
    """Renders frames of a trajectory through a world with a camera and image-realism knobs.

    occluder_count: people or boxes crossing the view during the flight
    (``plan_occluders``); ``occluders`` lists them.
    """

    def __init__(self, world: World, camera: CameraModel, traj: trajectories.Trajectory,
                 degradations: Degradations = DEFAULT_DEGRADATIONS, seed: int = 0, supersample: int = 1,
                 occluder_count: int = 0):
        self.world, self.camera, self.trajectory, self.seed = world, camera, traj, seed
        self.degradations = degradations
        self.renderer = raster.Renderer.from_camera(camera, supersample)
        self.occluders = plan_occluders(traj, camera, occluder_count, world, np.random.default_rng(seed + 104729))

    def T_camera_map(self, t_s: float) -> np.ndarray:
        return frames.invert_transform(self.trajectory.pose_at(t_s) @ self.camera.T_body_camera)

    def render_frame(self, index: int, t_ns: int) -> RenderedFrame:
        t_s = t_ns * 1e-9
        T_map_body = self.trajectory.pose_at(t_s)
        T_camera_map = frames.invert_transform(T_map_body @ self.camera.T_body_camera)
        quads = list(self.world.quads)
        for occluder in self.occluders:
            quad = occluder.quad_at(t_s)
            if quad is not None:
                quads.append(quad)
        rendering = self.renderer.render(quads, T_camera_map, background=40.0)
        truths = [raster.marker_truth(self.renderer, rendering, m.texture, m.size_m, m.T_map_marker,
                                      T_camera_map, m.quad_index, m.marker_id)
                  for m in self.world.markers]
        truths = [t for t in truths if t.corners_visible.any() or t.inner_visible_fraction > 0]
        motion = self.image_motion_px(t_s, truths) if self.degradations.motion_blur else None
        rng = np.random.default_rng([self.seed, index])
        image = self.degradations.at(t_s, self.seed).apply(rendering.image, rng, motion)
        return RenderedFrame(image, t_ns, T_map_body, truths)

    def image_motion_px(self, t_s: float, truths: list[raster.MarkerTruth]) -> tuple[float, float]:
        """Image displacement (dx, dy) during the exposure of the scene points that matter.

        The median over the visible markers' centres, or, with none in view,
        of the point 3 m ahead on the optical axis.
        """
        half = self.degradations.exposure_ms * 1e-3 / 2
        seen = {t.key for t in truths if t.corners_visible.any()}
        points = np.array([m.T_map_marker[:3, 3] for m in self.world.markers if m.marker_id in seen])
        if len(points) == 0:
            T_map_camera = frames.invert_transform(self.T_camera_map(t_s))
            points = frames.transform_points(T_map_camera, [[0.0, 0.0, 3.0]])
        before, ok0 = self.renderer.project(points, self.T_camera_map(t_s - half))
        after, ok1 = self.renderer.project(points, self.T_camera_map(t_s + half))
        ok = ok0 & ok1
        if not ok.any():
            return (0.0, 0.0)
        d = np.median(after[ok] - before[ok], axis=0)
        return (float(d[0]), float(d[1]))


# ------------------------------------------------------------------ output

def frames_progress_bar(total: int, progress: bool | None):
    """A progress bar of ``total`` frames on stderr; ``progress`` None: only for more than
    ``PROGRESS_MIN_FRAMES`` frames."""
    return progress_bar(total, "frame", total > PROGRESS_MIN_FRAMES if progress is None else progress)


def frame_times_ns(duration_s: float, fps: float) -> list[int]:
    """Capture times from 0 at ``fps`` up to ``duration_s`` inclusive, integer ns."""
    if not (math.isfinite(duration_s) and duration_s >= 0 and math.isfinite(fps) and fps > 0):
        raise SimulationError(f"a trajectory of {duration_s} s at {fps} fps has no frames: both must be positive")
    n = int(math.floor(duration_s * fps + 1e-9)) + 1
    if n > MAX_FRAMES:
        raise SimulationError(f"{duration_s:g} s at {fps:g} fps is {n} frames, more than {MAX_FRAMES}")
    return [int(round(i * 1e9 / fps)) for i in range(n)]


@dataclass(frozen=True)
class AttitudeNoise:
    """How the simulated flight controller's attitude (attitude.csv) departs from the truth.

    rate_hz: samples per second (on their own clock, not the frames'), at most 1000.
    noise_deg: standard deviation of independent Gaussian noise on each roll
        and each pitch sample, 0..45; bias_deg: added to every roll and every
        pitch, -45..45.
    """

    rate_hz: float = 50.0
    noise_deg: float = 0.2
    bias_deg: float = 0.0

    def __post_init__(self):
        if not 0 < self.rate_hz <= 1000:
            raise SimulationError(f"attitude rate must be positive and at most 1000 Hz, got {self.rate_hz}")
        if not 0 <= self.noise_deg <= 45:
            raise SimulationError(f"attitude noise must be 0..45 degrees, got {self.noise_deg}")
        if not (math.isfinite(self.bias_deg) and abs(self.bias_deg) <= 45):
            raise SimulationError(f"attitude bias must be within +-45 degrees, got {self.bias_deg}")


def attitude_samples(traj: trajectories.Trajectory, T_ned_map: np.ndarray, noise: AttitudeNoise,
                     seed: int = 0) -> list[AttitudeSample]:
    """The body's roll and pitch (Z-Y-X, relative to NED) over the flight, as the flight controller reports them."""
    rng = np.random.default_rng([seed, 2718])
    sd, bias = math.radians(noise.noise_deg), math.radians(noise.bias_deg)
    samples = []
    for t_ns in frame_times_ns(traj.duration_s, noise.rate_hz):
        # R_ned_body = R_ned_map R_map_body
        roll, pitch = frames.roll_pitch_321(T_ned_map[:3, :3] @ traj.pose_at(t_ns * 1e-9)[:3, :3])
        roll_error, pitch_error = rng.normal(0.0, sd, 2) + bias
        samples.append(AttitudeSample(t_ns, roll + roll_error, pitch + pitch_error))
    return samples


def check_folder(out: Path) -> None:
    """SimulationError unless ``out`` is new, an empty folder, or an earlier simulation's sequence holding
    nothing else (all of it is replaced: nothing of the user's may be lost with it)."""
    if out.exists() and not out.is_dir():
        raise SimulationError(f"{out}: exists and is not a folder")
    if not out.is_dir() or not any(out.iterdir()):
        return
    info = out / "sequence.yaml"
    earlier = info.is_file() and read_yaml(info, SimulationError, "sequence info").get("generator") == GENERATOR
    if not earlier:
        raise SimulationError(f"{out}: not empty and not a sequence written by {GENERATOR}: give a new or "
                              "empty folder")
    foreign = _foreign_files(out)
    if foreign:
        shown = ", ".join(str(path.relative_to(out)) for path in foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise SimulationError(f"{out}: holds {shown} besides the sequence {GENERATOR} wrote, which a new one "
                              "replaces: move them away, or give a new or empty folder")


def _foreign_files(out: Path) -> list[Path]:
    """What is in the sequence folder ``out`` that ``write_sequence`` does not write, sorted."""
    foreign = [path for path in out.iterdir() if path.name not in GENERATED_FILES and path.name != "frames"]
    frames_dir = out / "frames"
    if frames_dir.is_dir() and not frames_dir.is_symlink():
        foreign += [path for path in frames_dir.iterdir() if not _is_frame(path)]
    elif frames_dir.exists() or frames_dir.is_symlink():
        foreign.append(frames_dir)
    return sorted(foreign)


def _is_frame(path: Path) -> bool:
    return path.suffix == ".png" and path.stem.isdigit() and path.is_file() and not path.is_symlink()


def _new_folder_beside(target: Path) -> Path:
    """A new hidden folder beside ``target`` (the same file system, so renamed onto it at once), with the
    permissions ``mkdir`` gives it (``target``'s when it exists)."""
    folder = target.with_name(f".{target.name}.{secrets.token_hex(4)}")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        folder.mkdir()
    except OSError as error:
        raise SimulationError(f"{target}: cannot make the new sequence's folder beside it in {target.parent}: "
                              f"{error.strerror}") from None
    if target.is_dir():
        os.chmod(folder, stat.S_IMODE(target.stat().st_mode))
    return folder


def _replace_folder(target: Path, new: Path) -> None:
    """Put the folder ``new`` where ``target`` is; the earlier ``target`` stays until ``new`` is in its place."""
    if not target.exists():
        os.rename(new, target)
        return
    earlier = target.with_name(f".{target.name}.{secrets.token_hex(4)}")
    os.rename(target, earlier)
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(earlier, target)
        raise
    shutil.rmtree(earlier)


VIDEO_CODECS = {"mp4v": "small, lossy (MPEG-4 part 2)", "ffv1": "lossless, large"}


def write_sequence(out_dir, simulator: Simulator, fps: float, map_path: str, video: bool = False,
                   progress: bool | None = None, extra_info: dict | None = None, codec: str = "mp4v",
                   attitude: AttitudeNoise | None = AttitudeNoise()) -> Path:
    """Render every frame and write the sequence folder; returns its path.

    video: one ``video.avi`` in ``codec`` ("mp4v" or "ffv1") instead of PNG frames.
    progress: a progress bar on stderr (None: for more than ``PROGRESS_MIN_FRAMES`` frames).
    attitude: how attitude.csv departs from the truth; None writes no attitude.csv.
    The sequence is written into a new hidden folder beside ``out_dir`` (``.NAME.XXXXXXXX``), which
    replaces ``out_dir`` (an earlier sequence, ``check_folder``) once complete. A sequence that cannot be
    finished (a full disk, Ctrl-C) is removed and leaves ``out_dir`` as it was: an OSError then names the
    file (or the folder) that could not be written, as it would be in ``out_dir``.
    """
    out = Path(out_dir)
    check_folder(out)
    target = out.resolve()  # a link's folder, not the link; "." by its name
    new = _new_folder_beside(target)
    try:
        _write_sequence(new, simulator, fps, map_path, video, progress, extra_info, codec, attitude)
        _replace_folder(target, new)
    except BaseException as error:
        shutil.rmtree(new, ignore_errors=True)
        if isinstance(error, OSError):  # a full disk's write error names no file; a copy's names both
            where = str(error.filename2 or error.filename or new).replace(str(new), str(out), 1)
            raise OSError(error.errno, error.strerror, where) from error
        raise
    return out


def _write_sequence(out: Path, simulator: Simulator, fps: float, map_path: str, video: bool,
                    progress: bool | None, extra_info: dict | None, codec: str, attitude: AttitudeNoise | None) -> None:
    times = frame_times_ns(simulator.trajectory.duration_s, fps)
    shutil.copyfile(map_path, out / MAP_COPY)
    cam = simulator.camera
    writer = None
    if video:
        if codec not in VIDEO_CODECS:
            raise SimulationError(f"unknown video codec {codec!r}; known: {', '.join(VIDEO_CODECS)}")
        fourcc = cv2.VideoWriter_fourcc(*codec.upper()) if codec == "ffv1" else cv2.VideoWriter_fourcc(*codec)
        writer = cv2.VideoWriter(str(out / "video.avi"), fourcc, fps, (cam.width, cam.height), isColor=False)
        if not writer.isOpened():
            raise SimulationError(f"{out / 'video.avi'}: OpenCV cannot write a {codec} video here")
    else:
        (out / "frames").mkdir(exist_ok=True)
    T_ned_map = simulator.world.T_ned_map
    with open(out / "timestamps.csv", "w", newline="") as ft, open(out / "groundtruth.csv", "w", newline="") as fg, \
            open(out / "markers.csv", "w", newline="") as fm, frames_progress_bar(len(times), progress) as bar:
        ts, gt, mk = csv.writer(ft), csv.writer(fg), csv.writer(fm)
        ts.writerow(("frame", "t_ns", "file"))
        gt.writerow(GROUNDTRUTH_COLUMNS)
        mk.writerow(MARKERS_COLUMNS)
        for index, t_ns in enumerate(times):
            frame = simulator.render_frame(index, t_ns)
            if writer is not None:
                writer.write(frame.image)
                file = ""
            else:
                file = f"frames/{index:06d}.png"
                _write_png(out / file, frame.image)
            ts.writerow((index, t_ns, file))
            gt.writerow((index, t_ns, *groundtruth_values(frame.T_map_body, T_ned_map)))
            for truth in frame.truths:
                mk.writerow((index, t_ns, truth.key, *(f"{v:.4f}" for v in truth.corners_px.ravel()),
                             "".join("1" if v else "0" for v in truth.corners_visible),
                             f"{truth.inner_visible_fraction:.3f}", f"{truth.inner_px:.2f}"))
            bar.update(1)
    if writer is not None:
        writer.release()
    if attitude is not None:
        write_attitude_csv(out / ATTITUDE_FILE, attitude_samples(simulator.trajectory, T_ned_map, attitude, simulator.seed))
    info = {
        "generator": GENERATOR,
        "map": MAP_COPY,
        "map_source": str(Path(map_path).resolve()),
        # the world is rendered from map.yaml: its markers are exactly where it says (PoseParams.map_sd_m)
        "map_sd_m": 0.0,
        "map_sd_deg": 0.0,
        "camera": cam.to_config(),
        "fps": fps,
        "frames": len(times),
        "duration_s": simulator.trajectory.duration_s,
        "trajectory": simulator.trajectory.describe(),
        "seed": simulator.seed,
        "degradations": asdict(simulator.degradations),
        "occluders": len(simulator.occluders),
        "attitude": asdict(attitude) if attitude is not None else None,
        "video": "video.avi" if video else None,
        "video_codec": codec if video else None,
    }
    info.update(extra_info or {})
    (out / "sequence.yaml").write_text(yaml.safe_dump(_plain(info), sort_keys=False))


def _write_png(path: Path, image: np.ndarray) -> None:
    """One frame as PNG; an OSError (a full disk) names the file. (Encoded, then written by ``write_whole``:
    ``cv2.imwrite`` only returns False, after libpng prints its own line on stderr.)"""
    ok, png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise SimulationError(f"{path}: OpenCV could not encode the frame as PNG")
    write_whole(path, png.tobytes())


def groundtruth_values(T_map_body: np.ndarray, T_ned_map: np.ndarray) -> list[str]:
    """The groundtruth.csv columns after frame,t_ns for one body pose."""
    q = frames.quaternion_from_rotation(T_map_body[:3, :3])
    T_ned_body = T_ned_map @ T_map_body
    roll, pitch, yaw = frames.euler_321_from_rotation(T_ned_body[:3, :3])
    return [*(f"{v:.6f}" for v in T_map_body[:3, 3]), *(f"{v:.9f}" for v in q),
            *(f"{v:.6f}" for v in T_ned_body[:3, 3]), *(f"{v:.9f}" for v in (roll, pitch, yaw))]


def _plain(value):
    """YAML-safe copy: numpy scalars and arrays become Python numbers and lists."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


# ----------------------------------------------------------------- reading

@dataclass
class RecordedSequence:
    """A sequence folder read back: what made it, the frames, the truth.

    info: sequence.yaml as a dict; t_ns: (N,) int64; files: N relative paths
    (empty strings for a video); T_map_body: (N, 4, 4); T_ned_body: (N, 4, 4).
    """

    path: Path
    info: dict
    t_ns: np.ndarray
    files: list[str]
    T_map_body: np.ndarray
    T_ned_body: np.ndarray
    markers: list[dict] = field(default_factory=list)

    def images(self):
        """Yield (index, (H, W) uint8) for every frame, from PNGs or the video."""
        if self.info.get("video"):
            capture = cv2.VideoCapture(str(self.path / self.info["video"]))
            index = 0
            while True:
                ok, image = capture.read()
                if not ok:
                    break
                yield index, (cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image)
                index += 1
            capture.release()
            return
        for index, file in enumerate(self.files):
            image = cv2.imread(str(self.path / file), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise SimulationError(f"{self.path / file}: unreadable frame")
            yield index, image

    def map_path(self) -> Path:
        """The map file (``companion.capture.replay.sequence_map_path``)."""
        try:
            path = sequence_map_path(self.path, self.info)
        except ValueError as error:
            raise SimulationError(str(error)) from None
        if path is None:
            raise SimulationError(f"{self.path / 'sequence.yaml'}: names no map")
        return path


def read_sequence(path) -> RecordedSequence:
    """Read a sequence folder written by ``write_sequence``; errors name the file and column."""
    folder = Path(path)
    info_file = folder / "sequence.yaml"
    info = read_yaml(info_file, SimulationError, "sequence info")
    stamps = _read_csv(folder / "timestamps.csv", ("frame", "t_ns", "file"))
    truth = _read_csv(folder / "groundtruth.csv", GROUNDTRUTH_COLUMNS)
    if len(stamps) != len(truth):
        raise SimulationError(f"{folder}: timestamps.csv has {len(stamps)} rows, groundtruth.csv {len(truth)}")
    t_ns = np.array([int(r["t_ns"]) for r in stamps], dtype=np.int64)
    T_map, T_ned = [], []
    for row in truth:
        v = {k: float(row[k]) for k in GROUNDTRUTH_COLUMNS[2:]}
        R = frames.rotation_from_quaternion([v["qw"], v["qx"], v["qy"], v["qz"]])
        T_map.append(frames.make_transform(R, [v["x_m"], v["y_m"], v["z_m"]]))
        R_ned = frames.rotation_from_euler_321(v["roll_rad"], v["pitch_rad"], v["yaw_rad"])
        T_ned.append(frames.make_transform(R_ned, [v["north_m"], v["east_m"], v["down_m"]]))
    markers = _read_csv(folder / "markers.csv", MARKERS_COLUMNS) if (folder / "markers.csv").exists() else []
    return RecordedSequence(folder, info, t_ns, [r["file"] for r in stamps], np.array(T_map), np.array(T_ned),
                            markers)


def _read_csv(path: Path, columns) -> list[dict]:
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
            header = rows[0].keys() if rows else []
    except OSError as error:
        raise SimulationError(f"{path}: cannot read: {error.strerror}") from None
    missing = [c for c in columns if c not in header]
    if rows and missing:
        raise SimulationError(f"{path}: missing column(s) {', '.join(missing)}")
    return rows


# --------------------------------------------------------------------- CLI
