"""Detector-benchmark scenes: markers at random poses over clutter, under one condition.

``random_marker_scene`` renders a scene (rasteriser, occluders and degradations
from the sibling modules) with each marker's ground truth; ``CONDITIONS`` are
the named benchmark conditions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import cv2
import numpy as np

from companion.geometry import frames
from companion.geometry.camera import intrinsics_from_hfov
from companion.sim.degrade import Degradations, gaussian_blur
from companion.sim.occluders import blob_occluder, corner_occluder, side_occluder, strip_occluder
from companion.sim.raster import (MARKER_LIFT_M, MarkerTexture, MarkerTruth, RenderError, Renderer, TexturedQuad,
                                  make_texture, marker_quad, marker_truth, solid_texture)


def clutter_image(rng: np.random.Generator, size_px: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8 cluttered background: shading, boxes, edges, blobs, lines and fine texture.

    Made with a few dozen OpenCV drawing calls; nothing in it is a marker,
    but it has many quadrilaterals and strong edges for a detector to reject.
    """
    w, h = size_px
    coarse = rng.normal(0, 1, (6, 8)).astype(np.float32)
    base = 120 + 45 * cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    img = np.clip(base, 0, 255).astype(np.uint8)
    for _ in range(int(rng.integers(15, 35))):
        kind = rng.integers(0, 4)
        level = int(rng.integers(0, 256))
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        size = rng.uniform(0.03, 0.3) * min(w, h)
        if kind == 0:  # rotated box
            rect = ((cx, cy), (size, size * rng.uniform(0.3, 1.5)), rng.uniform(0, 180))
            cv2.fillConvexPoly(img, cv2.boxPoints(rect).astype(np.int32), level, cv2.LINE_AA)
        elif kind == 1:  # ellipse
            cv2.ellipse(img, ((cx, cy), (size, size * rng.uniform(0.3, 1.0)), rng.uniform(0, 180)),
                        level, -1, cv2.LINE_AA)
        elif kind == 2:  # line
            angle = rng.uniform(0, np.pi)
            d = np.array([np.cos(angle), np.sin(angle)]) * size * 2
            p0 = (int(cx - d[0]), int(cy - d[1]))
            p1 = (int(cx + d[0]), int(cy + d[1]))
            cv2.line(img, p0, p1, level, int(rng.integers(1, 6)), cv2.LINE_AA)
        else:  # outlined box (shelf edge, label)
            rect = ((cx, cy), (size, size * rng.uniform(0.3, 1.5)), rng.uniform(0, 180))
            cv2.polylines(img, [cv2.boxPoints(rect).astype(np.int32)], True, level,
                          int(rng.integers(1, 4)), cv2.LINE_AA)
    fine = rng.normal(0, 1, (h // 2, w // 2)).astype(np.float32)
    fine = cv2.resize(cv2.GaussianBlur(fine, (0, 0), 1.0), (w, h), interpolation=cv2.INTER_LINEAR)
    out = img.astype(np.float32) + rng.uniform(3, 12) * fine
    return np.clip(gaussian_blur(out, 0.7), 0, 255).astype(np.uint8)


# every condition's camera: a little optics blur and sensor noise
BASE_DEGRADATIONS = Degradations(optics_blur_sigma_px=0.5, read_noise_dn=1.0, shot_noise_gain=0.02)


@dataclass(frozen=True)
class SceneCondition:
    """One benchmark condition: occluders stuck on each marker and image degradations.

    occlusion: "none", "strip", "side" (a long strip past both corners of
        one side: a rack upright, a pipe), "corner" or "blob".
    occlusion_fraction: strip width (of the inner side hidden) or corner
        depth as a fraction of the inner side; blob radius as a fraction of
        the inner side.
    degradations: applied to the whole image after rendering; a motion blur
        with ``motion_length_px`` gets a random direction per scene.
    """

    name: str
    occlusion: str = "none"
    occlusion_fraction: float = 0.0
    degradations: Degradations = BASE_DEGRADATIONS


CONDITIONS: dict[str, SceneCondition] = {
    c.name: c for c in (
        SceneCondition("clean"),
        SceneCondition("strip_1_8", "strip", 1.0 / 8.0),
        SceneCondition("strip_1_4", "strip", 1.0 / 4.0),
        SceneCondition("side_1_8", "side", 1.0 / 8.0),
        SceneCondition("side_1_4", "side", 1.0 / 4.0),
        SceneCondition("corner", "corner", 0.25),
        SceneCondition("blob", "blob", 0.18),
        SceneCondition("gaussian_blur", degradations=BASE_DEGRADATIONS.with_(optics_blur_sigma_px=1.6)),
        SceneCondition("motion_blur", degradations=BASE_DEGRADATIONS.with_(motion_length_px=9.0)),
        SceneCondition("noise", degradations=BASE_DEGRADATIONS.with_(read_noise_dn=12.0, shot_noise_gain=0.5)),
        SceneCondition("low_light", degradations=BASE_DEGRADATIONS.with_(exposure_gain=0.15, read_noise_dn=2.5,
                                                             shot_noise_gain=0.3)),
        SceneCondition("jpeg", degradations=BASE_DEGRADATIONS.with_(jpeg_quality=15)),
    )
}


@dataclass
class Scene:
    """A rendered benchmark scene: the image, each marker's ground truth, the condition."""

    image: np.ndarray
    truths: list[MarkerTruth]
    condition: SceneCondition
    K: np.ndarray


def random_marker_scene(rng: np.random.Generator, image_size: tuple[int, int],
                        markers: Sequence[MarkerTexture], inner_px_range=(40.0, 150.0),
                        condition: SceneCondition | str = "clean", max_tilt_deg: float = 50.0,
                        hfov_deg: float = 70.0, background: np.ndarray | None = None,
                        supersample: int = 1) -> Scene:
    """Render the given markers at random poses over clutter, under one condition.

    image_size: (width, height). Each marker gets an inner-square side drawn
    uniformly from ``inner_px_range`` (pixels, face-on), a random in-plane
    rotation (all four upright orientations and between), a tilt up to
    ``max_tilt_deg`` about a random in-plane axis, and a spot where its whole
    texture is inside the image and overlaps no other marker (markers that
    find no spot after a few tries are left out: check ``len(truths)``). It
    sits on a shaded board a little larger than its texture. The physical
    size is 0.15 m; only pixels matter. ``truths[i].key`` is the index of
    the marker in ``markers``.
    """
    if isinstance(condition, str):
        if condition not in CONDITIONS:
            raise RenderError(f"unknown condition {condition!r}; known: {', '.join(CONDITIONS)}")
        condition = CONDITIONS[condition]
    width, height = image_size
    K = intrinsics_from_hfov(width, height, hfov_deg)
    renderer = Renderer(K, np.zeros(5), width, height, supersample)
    if background is None:
        background = clutter_image(rng, (width, height))
    size_m = 0.15
    f = K[0, 0]
    R_face = frames.R_camera_marker_face_on()
    T_camera_world = np.eye(4)  # the world is the camera frame here

    quads: list[TexturedQuad] = []
    placed: list[tuple[int, MarkerTexture, np.ndarray, int]] = []  # (key, marker, T, quad index)
    boxes: list[np.ndarray] = []
    for key, marker in enumerate(markers):
        for _ in range(30):
            inner_px = rng.uniform(*inner_px_range)
            # face-on side in pixels = f s / z
            z = f * size_m / inner_px
            tilt_axis = rng.uniform(0, 2 * np.pi)
            tilt = math.radians(rng.uniform(0, max_tilt_deg))
            R_tilt = frames.rotation_from_rotvec([math.cos(tilt_axis) * tilt, math.sin(tilt_axis) * tilt, 0.0])
            R_spin = frames.rot_z(rng.uniform(0, 2 * np.pi))
            R = R_tilt @ R_spin @ R_face
            u, v = rng.uniform(0, width), rng.uniform(0, height)
            centre = z * np.linalg.solve(K, [u, v, 1.0])
            T = frames.make_transform(R, centre)
            quad = marker_quad(marker, size_m, T)
            outline, in_front = renderer.project(quad.corners_world, T_camera_world)
            if not in_front.all() or not renderer.inside_image(outline, margin_px=2).all():
                continue
            board = _board_behind(rng, quad, rng.uniform(1.15, 1.6), rng.uniform(60, 200))
            board_outline, board_in_front = renderer.project(board.corners_world, T_camera_world)
            if not board_in_front.all():
                continue
            # boards must not overlap either, or one would hide part of another marker
            box = np.r_[board_outline.min(axis=0), board_outline.max(axis=0)]
            if any(_boxes_overlap(box, other) for other in boxes):
                continue
            boxes.append(box)
            paper_gain = rng.uniform(0.7, 0.95)
            quads.append(board)
            quads.append(replace(quad, gain=paper_gain, offset=rng.uniform(5, 30)))
            placed.append((key, marker, T, len(quads) - 1))
            quads.extend(_condition_occluders(condition, marker, size_m, T, rng))
            break

    rendering = renderer.render(quads, T_camera_world, background)
    truths = [marker_truth(renderer, rendering, marker, size_m, T, T_camera_world, index, key)
              for key, marker, T, index in placed]
    degradations = condition.degradations
    if degradations.motion_length_px > 0:
        degradations = degradations.with_(motion_angle_rad=rng.uniform(0, np.pi))
    image = degradations.apply(rendering.image, rng)
    return Scene(image, truths, condition, K)


def _boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    return not (a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1])


def _board_behind(rng, quad: TexturedQuad, scale: float, level: float) -> TexturedQuad:
    """A shaded board behind a marker quad: the quad scaled about its centre, pushed back."""
    c = quad.corners_world
    centre = c.mean(axis=0)
    normal = np.cross(c[3] - c[0], c[1] - c[0])  # front normal (b x a)
    normal /= np.linalg.norm(normal)
    corners = centre + scale * (c - centre) - MARKER_LIFT_M * normal
    return TexturedQuad(corners, make_texture(solid_texture(rng, (64, 64), level, 20.0)))


def _condition_occluders(condition: SceneCondition, marker: MarkerTexture, size_m: float,
                         T_world_marker: np.ndarray, rng: np.random.Generator) -> list[TexturedQuad]:
    if condition.occlusion == "none":
        return []
    if condition.occlusion in ("strip", "side"):
        side = ("left", "right", "top", "bottom")[int(rng.integers(0, 4))]
        occluder = strip_occluder if condition.occlusion == "strip" else side_occluder
        return [occluder(marker, size_m, T_world_marker, condition.occlusion_fraction, side, rng)]
    if condition.occlusion == "corner":
        return [corner_occluder(marker, size_m, T_world_marker, condition.occlusion_fraction,
                                int(rng.integers(0, 4)), rng)]
    if condition.occlusion == "blob":
        return [blob_occluder(size_m, T_world_marker, rng, condition.occlusion_fraction)]
    raise RenderError(f"unknown occlusion {condition.occlusion!r}")
