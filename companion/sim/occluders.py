"""Occluder quads: things in front of a marker or crossing the view (strip, side, corner patch, blob, box, person).

Stuck on a marker (``strip_occluder``, ``side_occluder``, ``corner_occluder``, ``blob_occluder``:
the benchmark scenes' conditions) or standing in the scene (``person_occluder``,
``box_occluder``; ``PassingOccluder`` walks one across the simulator's view).
Everything random takes a ``numpy.random.Generator``.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.geometry import frames
from companion.sim.raster import (RenderError, MarkerTexture, TexturedQuad, lift, make_texture, rectangle_corners,
                                  solid_texture, texture_to_marker)

OCCLUDER_LIFT_M = 0.003  # a stuck-on occluder sits this far in front of its marker


def strip_occluder(marker: MarkerTexture, size_m: float, T_world_marker: np.ndarray, fraction: float,
                   side: str, rng: np.random.Generator, level: float | None = None) -> TexturedQuad:
    """A strip over ``fraction`` of the inner square's width from one side, border and margin included.

    side: "left", "right", "top" or "bottom" of the upright marker. The strip
    reaches a fifth of the inner side past the marker's texture in the other
    three directions (over the corner circles at both ends of that side).
    """
    reach = _outer_reach_m(marker, size_m) + 0.2 * size_m
    return _side_band(rng, T_world_marker, size_m, fraction, side, reach, reach, level)


def side_occluder(marker: MarkerTexture, size_m: float, T_world_marker: np.ndarray, fraction: float,
                  side: str, rng: np.random.Generator, level: float | None = None) -> TexturedQuad:
    """A long occluder in front of one whole side: a rack upright, a pipe, a cable along the sheet.

    It hides ``fraction`` of the inner square's width from ``side`` (as ``strip_occluder``) and runs on
    1 to 4 inner sides past both corners of that side, so the corner circles at both ends are gone
    too; outward it reaches 0.05 to 1 inner side past the marker's texture (a pipe of any width).
    """
    texture_reach = _outer_reach_m(marker, size_m)
    outward = texture_reach + rng.uniform(0.05, 1.0) * size_m
    along = texture_reach + rng.uniform(1.0, 4.0) * size_m
    return _side_band(rng, T_world_marker, size_m, fraction, side, outward, along, level)


def _side_band(rng, T_world_marker, size_m: float, fraction: float, side: str, outward_m: float, along_m: float,
               level: float | None) -> TexturedQuad:
    """A rectangle from ``fraction`` of the inner width in from ``side`` out to ``outward_m`` from the
    marker centre, ``along_m`` from the centre both ways along that side (marker frame: x right, y up)."""
    inner_edge = -size_m / 2 + fraction * size_m  # measured from the chosen side
    across = inner_edge + outward_m
    centre_across = (inner_edge - outward_m) / 2
    if side == "left":
        width_m, height_m, centre = across, 2 * along_m, (centre_across, 0.0)
    elif side == "right":
        width_m, height_m, centre = across, 2 * along_m, (-centre_across, 0.0)
    elif side == "bottom":
        width_m, height_m, centre = 2 * along_m, across, (0.0, centre_across)
    elif side == "top":
        width_m, height_m, centre = 2 * along_m, across, (0.0, -centre_across)
    else:
        raise RenderError(f"strip side must be left, right, top or bottom, got {side!r}")
    return _flat_occluder(rng, T_world_marker, width_m, height_m, centre, level)


def corner_occluder(marker: MarkerTexture, size_m: float, T_world_marker: np.ndarray, fraction: float,
                    corner: int, rng: np.random.Generator, level: float | None = None) -> TexturedQuad:
    """A patch hiding one inner corner (0 TL, 1 TR, 2 BR, 3 BL) and ``fraction`` of the side along both edges."""
    s = size_m
    reach = _outer_reach_m(marker, size_m) + 0.2 * s
    corner_xy = frames.marker_inner_corners_m(s)[corner, :2]
    inward = -np.sign(corner_xy)  # toward the marker centre
    inner = corner_xy + inward * fraction * s
    outer = corner_xy - inward * (reach - s / 2)
    centre = (inner + outer) / 2
    size = np.abs(outer - inner)
    return _flat_occluder(rng, T_world_marker, float(size[0]), float(size[1]), tuple(centre), level)


def blob_occluder(size_m: float, T_world_marker: np.ndarray, rng: np.random.Generator,
                  radius_fraction: float = 0.2, level: float | None = None) -> TexturedQuad:
    """An irregular blob (a smudge, a sticker, a glare spot) inside the data area.

    Its radius is about ``radius_fraction`` of the inner side; its centre lies
    within the inner 6x6 data cells so it never reaches the border.
    """
    s = size_m
    max_offset = max(3.0 / 8.0 * s - radius_fraction * s, 0.0)
    centre = rng.uniform(-max_offset, max_offset, 2)
    side_px = 64
    alpha = np.zeros((side_px, side_px), np.uint8)
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    radii = (side_px / 2 - 2) * (1.0 - 0.25 * rng.uniform(0, 1, len(angles)))
    radii = np.convolve(np.r_[radii[-2:], radii, radii[:2]], np.ones(5) / 5, mode="valid")
    pts = np.column_stack([side_px / 2 + radii * np.cos(angles), side_px / 2 + radii * np.sin(angles)])
    cv2.fillPoly(alpha, [np.round(pts * 16).astype(np.int32)], 255, lineType=cv2.LINE_AA, shift=4)
    level = rng.choice([rng.uniform(20, 90), rng.uniform(160, 250)]) if level is None else level
    texture = make_texture(solid_texture(rng, (side_px, side_px), level, 8.0), alpha)
    diameter = 2 * radius_fraction * s * side_px / (side_px - 4)
    corners = rectangle_corners(lift(T_world_marker, OCCLUDER_LIFT_M), diameter, diameter, tuple(centre))
    return TexturedQuad(corners, texture)


def _outer_reach_m(marker: MarkerTexture, size_m: float) -> float:
    """Distance from the marker centre to the texture's outer edge, metres (max over sides)."""
    A = texture_to_marker(marker, size_m)
    h, w = marker.image.shape
    outer = np.array([[-0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0]]) @ A.T
    return float(np.abs(outer[:, :2]).max())


def _flat_occluder(rng, T_world_marker, width_m, height_m, centre_xy, level) -> TexturedQuad:
    level = rng.uniform(30, 230) if level is None else level
    texture = make_texture(solid_texture(rng, (64, 64), level))
    corners = rectangle_corners(lift(T_world_marker, OCCLUDER_LIFT_M), width_m, height_m, centre_xy)
    return TexturedQuad(corners, texture)


def person_alpha(height_px: int = 256) -> np.ndarray:
    """(H, W) uint8 coverage of a standing person seen from the front (W = H / 2)."""
    h = height_px
    w = h // 2
    alpha = np.zeros((h, w), np.uint8)
    cx = w / 2
    aa = cv2.LINE_AA
    cv2.ellipse(alpha, (int(cx), int(0.09 * h)), (int(0.085 * h), int(0.09 * h)), 0, 0, 360, 255, -1, aa)
    torso = np.array([[cx - 0.16 * h, 0.2 * h], [cx + 0.16 * h, 0.2 * h], [cx + 0.13 * h, 0.56 * h],
                      [cx - 0.13 * h, 0.56 * h]], np.int32)
    cv2.fillConvexPoly(alpha, torso, 255, aa)
    for sign in (-1, 1):
        arm = np.array([[cx + sign * 0.16 * h, 0.21 * h], [cx + sign * 0.23 * h, 0.22 * h],
                        [cx + sign * 0.21 * h, 0.52 * h], [cx + sign * 0.15 * h, 0.5 * h]], np.int32)
        cv2.fillConvexPoly(alpha, arm, 255, aa)
        leg = np.array([[cx + sign * 0.01 * h, 0.55 * h], [cx + sign * 0.13 * h, 0.55 * h],
                        [cx + sign * 0.11 * h, 0.99 * h], [cx + sign * 0.03 * h, 0.99 * h]], np.int32)
        cv2.fillConvexPoly(alpha, leg, 255, aa)
    return alpha


def person_occluder(rng: np.random.Generator, T_world_plane: np.ndarray, height_m: float = 1.75) -> TexturedQuad:
    """A person-shaped upright silhouette in the plane's z = 0 plane, feet at the plane origin.

    The plane's +y is up; the silhouette is two-sided.
    """
    alpha = person_alpha(256)
    shade = solid_texture(rng, (alpha.shape[1], alpha.shape[0]), rng.uniform(40, 140), 25.0)
    corners = rectangle_corners(T_world_plane, height_m / 2, height_m, (0.0, height_m / 2))
    return TexturedQuad(corners, make_texture(shade, alpha))


def box_occluder(rng: np.random.Generator, T_world_plane: np.ndarray, width_m: float,
                 height_m: float) -> TexturedQuad:
    """A cardboard box face (with a tape line) in the plane's z = 0 plane, bottom edge at the origin."""
    w_px, h_px = 128, max(int(128 * height_m / width_m) // 2 * 2, 8)
    face = solid_texture(rng, (w_px, h_px), rng.uniform(110, 190), 15.0)
    tape = slice(max(h_px // 2 - h_px // 16, 0), h_px // 2 + h_px // 16)
    face[tape, :] = np.clip(face[tape, :].astype(int) + 35, 0, 255).astype(np.uint8)
    corners = rectangle_corners(T_world_plane, width_m, height_m, (0.0, height_m / 2))
    return TexturedQuad(corners, make_texture(face))


@dataclass(frozen=True)
class PassingOccluder:
    """A person or a box crossing in front of the camera along a straight floor path.

    start_m, velocity_m_s: (3,) feet position at t_start_s and its velocity;
    facing: (3,) horizontal unit normal of its face; kind: "person" or "box".
    """

    kind: str
    t_start_s: float
    t_end_s: float
    start_m: np.ndarray
    velocity_m_s: np.ndarray
    facing: np.ndarray
    quad_texture_seed: int

    def quad_at(self, t_s: float) -> TexturedQuad | None:
        """Its quad at ``t_s``, or None outside [t_start_s, t_end_s]."""
        if not (self.t_start_s <= t_s <= self.t_end_s):
            return None
        feet = self.start_m + (t_s - self.t_start_s) * self.velocity_m_s
        # plane frame: z = facing, y = up, x = y cross z
        up = np.array([0.0, 0.0, 1.0])
        T = frames.make_transform(np.column_stack([np.cross(up, self.facing), up, self.facing]), feet)
        rng = np.random.default_rng(self.quad_texture_seed)
        if self.kind == "person":
            return person_occluder(rng, T)
        return box_occluder(rng, T, 1.1, 1.3)
