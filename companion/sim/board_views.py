"""Rendered views of a ChArUco board through a known 640x480 camera: the ground truth of calibration.

A lens is ``(K (3, 3), dist (5,))``; views are rendered by ``companion.sim.raster``
through it, with OpenCV's own image of the board on a white sheet. Used by the
calibration tests and ``benchmarks/bench_calibration.py``.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from companion.geometry import frames
from companion.markers.charuco import CharucoSpec
from companion.sim.raster import Renderer, TexturedQuad, make_texture, rectangle_corners

PX_PER_SQUARE = 64   # texture resolution of the board


def board_quad(spec: CharucoSpec) -> TexturedQuad:
    """The board (OpenCV's own image of it) on a white sheet half a square wider on each side, at z = 0."""
    image = spec.board().generateImage((spec.columns * PX_PER_SQUARE, spec.rows * PX_PER_SQUARE), marginSize=0)
    image = np.pad(image, PX_PER_SQUARE // 2, constant_values=255)
    width_m, height_m = ((n + 1) * spec.square_mm / 1000.0 for n in (spec.columns, spec.rows))
    return TexturedQuad(rectangle_corners(np.eye(4), width_m, height_m), make_texture(image), gain=0.8, offset=20)


def look_at(eye_m, target_m, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """T_camera_world of an OpenCV camera at ``eye_m`` looking at ``target_m``."""
    z = np.subtract(target_m, eye_m)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R_world_camera = np.column_stack([x, np.cross(z, x), z])
    return frames.invert_transform(frames.make_transform(R_world_camera, eye_m))


def view_poses(lens: tuple[np.ndarray, np.ndarray], count: int, seed: int) -> list[np.ndarray]:
    """Camera poses around the board: tilted up to 45 degrees, rolled, aimed so the board lands all over
    the image (some views show it only in part)."""
    half_hfov = math.radians(hfov_deg(lens)) / 2
    distance = (0.3, 0.6) if half_hfov < math.radians(45) else (0.15, 0.35)
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(count):
        d = rng.uniform(*distance)
        tilt, azimuth = rng.uniform(0, math.radians(45)), rng.uniform(0, 2 * math.pi)
        eye = d * np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])
        target = [rng.uniform(-0.09, 0.09), rng.uniform(-0.12, 0.12), 0.0]
        T = look_at(eye, target, frames.rot_z(rng.uniform(-0.6, 0.6)) @ [0.0, 1.0, 0.0])
        aim = frames.rot_y(rng.uniform(-0.25, 0.25) * half_hfov) @ frames.rot_x(rng.uniform(-0.2, 0.2) * half_hfov)
        poses.append(frames.make_transform(aim, np.zeros(3)) @ T)
    return poses


def hfov_deg(lens: tuple[np.ndarray, np.ndarray]) -> float:
    """Horizontal field of view: the angle between the rays of the left and right image edges."""
    K, dist = lens
    edges = cv2.undistortPoints(np.array([[[-0.5, K[1, 2]]], [[639.5, K[1, 2]]]]), K, dist).reshape(-1, 2)
    return math.degrees(math.atan(-edges[0, 0]) + math.atan(edges[1, 0]))


class BoardCamera:
    """A 640x480 camera with lens ``(K, dist)`` looking at a ChArUco board lying at z = 0 of the world."""

    def __init__(self, spec: CharucoSpec, lens: tuple[np.ndarray, np.ndarray]):
        K, dist = lens
        self.renderer = Renderer(K, dist, 640, 480)
        self.quad = board_quad(spec)

    def render(self, T_camera_world: np.ndarray, noise_seed: int | None = None) -> np.ndarray:
        """(480, 640) uint8: the view, slightly blurred (optics), with unit sensor noise when seeded."""
        image = self.renderer.render([self.quad], T_camera_world, background=90.0).image
        image = cv2.GaussianBlur(image, (0, 0), 0.6)
        if noise_seed is not None:
            noise = np.random.default_rng(noise_seed).normal(0.0, 1.0, image.shape)
            image = np.clip(image + noise, 0, 255).astype(np.uint8)
        return image
