"""The rasteriser: what a pinhole camera sees of textured planes, with ground truth.

Shared by the camera simulator (``companion.sim.simulate``) and the detector
benchmark's scenes (``companion.sim.scenes``), so both draw markers and compute
ground truth with one piece of code. Image degradations are in
``companion.sim.degrade``, occluder quads in ``companion.sim.occluders``.

* ``Renderer`` draws ``TexturedQuad`` s (flat textured parallelograms in the
  world) as the camera with intrinsics ``K``, distortion ``dist`` and an image
  size sees them: one OpenCV perspective warp per quad into an ideal
  (undistorted) canvas with a per-pixel inverse-depth buffer, polygons clipped
  at a near plane so a plane behind or partly behind the camera is never drawn
  wrong, then one remap through the lens distortion.
* Markers are ``MarkerTexture`` s placed at their inner-square size
  (``marker_quad``); their ground truth (``marker_truth``) is the projection
  of the same 3-D points through the same camera model (``cv2.projectPoints``),
  with flags for points that are behind the camera, outside the image or
  hidden (read from the renderer's label buffer).

Pixel coordinates follow OpenCV: x right, y down, the centre of the top-left
pixel at (0, 0). Texture coordinates likewise, so a texture of width W spans
x in [-0.5, W - 0.5].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from companion.geometry import frames
from companion.markers.layout import cell_point_to_px, marker_image

NEAR_M = 0.02  # near clipping plane: nothing closer to the camera is drawn
MIN_MIP_SIZE_PX = 4
MIP_BIAS = 0.0  # > 0 picks coarser levels: less aliasing, more blur
MAX_MIP_TAPS = 2  # anisotropic filtering: samples along each axis of a pixel's texture footprint, at most
# canvas -> distorted image. Bilinear blurs edges by up to 0.5 px; bicubic shifted the detector's corners
# 0.015-0.025 px towards the centre where the lens moves the image by a slowly changing fraction of a pixel
# (tests/test_render.py); Lanczos (8x8) 0.003 px, 4 ms a 640x480 frame against 1
LENS_INTERPOLATION = cv2.INTER_LANCZOS4
MARKER_LIFT_M = 0.001  # a marker sits this far in front of its backing board
OCCLUSION_DEPTH_M = 1e-5  # a quad this far behind an opaque surface, in its image, is hidden by it
OCCLUSION_MARGIN_PX = 2.0  # a hidden quad stays this far inside its occluder's edges (anti-aliasing: 1 px)
MAX_SUPERSAMPLE = 8  # beyond, the canvas samples a marker cell (16 texels) finer than its texture holds
# Memory, so that no camera file or option can ask for more than fits (measured on 640x480 at supersample
# 1-16 and a 6000x6000 lens): drawing takes about 30 bytes a canvas pixel (the frame supersampled, with the
# lens's margin: colour, depth, labels, a quad's shade, coverage and depth), the lens map about 70 bytes a
# frame pixel while it is made. 40 million canvas pixels is about 1.2 GB (640x480 at supersample 8 is 20
# million, 1920x1080 at 4 is 33 million); 12 million frame pixels (4000x3000) about 0.9 GB.
MAX_CANVAS_PIXELS = 40_000_000
MAX_FRAME_PIXELS = 12_000_000
CANVAS_BYTES_PER_PIXEL = 30


class RenderError(ValueError):
    """Bad input to the renderer (shapes, sizes, non-planar quads)."""


# ------------------------------------------------------------------ textures

@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Texture:
    """A grayscale texture with its mip levels (each half the previous size).

    levels: tuple of (H_i, W_i) uint8, level 0 first.
    alpha_levels: same shapes, uint8 coverage (255 opaque), or None if opaque.
    """

    levels: tuple
    alpha_levels: tuple | None = None

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height) of level 0."""
        h, w = self.levels[0].shape
        return w, h


def make_texture(image: np.ndarray, alpha: np.ndarray | None = None) -> Texture:
    """Texture with mip levels from an (H, W) uint8 image and optional (H, W) uint8 alpha.

    Levels are 2 x 2 box averages (``cv2.INTER_AREA`` to half size) while both sides are even, so texel
    x_i of level i is centred on level-0 texel 2^i x_i + (2^i - 1)/2. A box adds a third of the blur
    ``cv2.pyrDown``'s Gaussian does (variance 1/3 against 1 input texel^2 per level): the renderer's
    anisotropic taps do the anti-aliasing, and a blurred marker reads shorter.
    """
    image = np.ascontiguousarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise RenderError(f"texture must be (H, W) uint8, got {image.shape} {image.dtype}")
    if alpha is not None and (alpha.shape != image.shape or alpha.dtype != np.uint8):
        raise RenderError(f"alpha must match the texture {image.shape} uint8, got {alpha.shape} {alpha.dtype}")
    levels = [image]
    alphas = None if alpha is None else [np.ascontiguousarray(alpha)]
    while (levels[-1].shape[0] % 2 == 0 and levels[-1].shape[1] % 2 == 0
           and min(levels[-1].shape) >= 2 * MIN_MIP_SIZE_PX):
        levels.append(_half(levels[-1]))
        if alphas is not None:
            alphas.append(_half(alphas[-1]))
    return Texture(tuple(levels), None if alphas is None else tuple(alphas))


def _half(image: np.ndarray) -> np.ndarray:
    """(H/2, W/2) uint8: the mean of each 2 x 2 block of an (H, W) uint8 image with even sides."""
    h, w = image.shape
    return cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)


def solid_texture(rng: np.random.Generator, size_px: tuple[int, int], level: float,
                  texture_amplitude: float = 12.0) -> np.ndarray:
    """(H, W) uint8 surface of mean ``level`` with a soft random mottle and a gradient; size_px: (W, H)."""
    w, h = size_px
    coarse = rng.normal(0.0, 1.0, (max(h // 16, 2), max(w // 16, 2))).astype(np.float32)
    mottle = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    gradient = np.linspace(-1.0, 1.0, w, dtype=np.float32)[None, :] * rng.uniform(-1, 1)
    surface = level + texture_amplitude * (0.6 * mottle + 0.4 * gradient)
    return np.clip(surface, 0, 255).astype(np.uint8)


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class TexturedQuad:
    """A flat textured parallelogram in the world.

    corners_world: (4, 3) world positions of the texture's outer corners
        TL, TR, BR, BL (texture x runs TL -> TR, texture y runs TL -> BL);
        BR must equal TR + BL - TL.
    texture: the image on it.
    gain, offset: drawn intensity = texture * gain + offset (lighting, paper
        and ink reflectance).
    two_sided: False culls the quad when seen from behind (the front is the
        side from which TL -> TR -> BR runs clockwise in the image).
    """

    corners_world: np.ndarray
    texture: Texture
    gain: float = 1.0
    offset: float = 0.0
    two_sided: bool = True

    def __post_init__(self):
        c = np.asarray(self.corners_world, dtype=float)
        if c.shape != (4, 3):
            raise RenderError(f"quad corners must be (4, 3), got {c.shape}")
        # parallelogram: BR = TR + BL - TL
        misfit = np.linalg.norm(c[2] - (c[1] + c[3] - c[0]))
        scale = max(np.linalg.norm(c[1] - c[0]), np.linalg.norm(c[3] - c[0]), 1e-9)
        if misfit > 1e-6 * max(scale, 1.0):
            raise RenderError(f"quad corners are not a parallelogram (misfit {misfit:.3g} m)")
        object.__setattr__(self, "corners_world", c)


def rectangle_corners(T_world_plane: np.ndarray, width_m: float, height_m: float,
                      center_xy_m=(0.0, 0.0)) -> np.ndarray:
    """(4, 3) world corners TL, TR, BR, BL of a width x height rectangle in a plane.

    The rectangle lies in the z = 0 plane of the frame ``T_world_plane`` with
    its texture's x along the plane's +x and its texture's y along the
    plane's -y (the plane's y is "up" on the face, as for a marker frame),
    centred at ``center_xy_m`` in that plane.
    """
    cx, cy = center_xy_m
    hw, hh = width_m / 2.0, height_m / 2.0
    # up = +y in the plane, so the top edge is at y = cy + hh
    local = np.array([[cx - hw, cy + hh, 0.0], [cx + hw, cy + hh, 0.0],
                      [cx + hw, cy - hh, 0.0], [cx - hw, cy - hh, 0.0]])
    return frames.transform_points(T_world_plane, local)


# ------------------------------------------------------------------- camera

@dataclass
class Rendering:
    """One rendered image and which quad is seen at each pixel.

    image: (H, W) uint8.
    label: (H, W) int32, index of the quad covering each pixel in the list
        given to ``Renderer.render`` (-1: background); None if not asked for.
    """

    image: np.ndarray
    label: np.ndarray | None


def check_render_size(width: int, height: int, supersample: int, lens_canvas: tuple[int, int] | None = None) -> None:
    """RenderError unless a ``width`` x ``height`` frame is at most ``MAX_FRAME_PIXELS`` and, at
    ``supersample``, is drawn on at most ``MAX_CANVAS_PIXELS``; ``lens_canvas``: the (unsupersampled)
    canvas a distorting lens needs, drawn instead of the frame."""
    if width * height > MAX_FRAME_PIXELS:
        raise RenderError(f"a {width}x{height} frame is {width * height / 1e6:.0f} million pixels: more than the "
                          f"{MAX_FRAME_PIXELS // 1_000_000} million the renderer allows")
    canvas_w, canvas_h = lens_canvas or (width, height)
    pixels = canvas_w * canvas_h * supersample**2
    if pixels <= MAX_CANVAS_PIXELS:
        return
    lens = f" (the lens distortion's canvas is {canvas_w}x{canvas_h})" if lens_canvas else ""
    raise RenderError(f"a {width}x{height} frame at supersample {supersample} is drawn on "
                      f"{canvas_w * supersample}x{canvas_h * supersample} pixels{lens}, {pixels / 1e6:.0f} million: "
                      f"more than the {MAX_CANVAS_PIXELS // 1_000_000} million (about "
                      f"{MAX_CANVAS_PIXELS * CANVAS_BYTES_PER_PIXEL / 1e9:.1f} GB of memory) the renderer allows")


class Renderer:
    """Renders textured quads as one camera sees them.

    K: (3, 3) intrinsics; dist: OpenCV distortion coefficients (k,) (4, 5, 8,
    12 or 14 values, or empty); width, height: image size in pixels.
    supersample: render at this integer factor and average down
    (anti-aliasing; 1 is usually enough with a little optics blur), 1 to
    ``MAX_SUPERSAMPLE``. The frame is at most ``MAX_FRAME_PIXELS``, the
    supersampled canvas at most ``MAX_CANVAS_PIXELS`` (``check_render_size``).

    The canvas is an ideal pinhole image large enough to hold every ray the
    distorted image sees; distortion is applied by one ``cv2.remap`` whose
    map is computed once here.
    """

    def __init__(self, K: np.ndarray, dist, width: int, height: int, supersample: int = 1):
        self.K = np.asarray(K, dtype=float).reshape(3, 3)
        self.dist = np.asarray(dist if dist is not None else [], dtype=float).ravel()
        self.width, self.height = int(width), int(height)
        self.supersample = int(supersample)
        if self.width <= 0 or self.height <= 0 or not 1 <= self.supersample <= MAX_SUPERSAMPLE:
            raise RenderError(f"bad image size {width}x{height} or supersample {supersample} (1..{MAX_SUPERSAMPLE})")
        check_render_size(self.width, self.height, self.supersample)  # before the lens map, as large as the image
        self.distorted = bool(np.any(self.dist != 0.0))
        if self.distorted:
            self._undistort_map, canvas_K, canvas_size = self._distortion_map()
        else:
            self._undistort_map, canvas_K, canvas_size = None, self.K.copy(), (self.width, self.height)
        # the canvas at the supersampled resolution: u_ss = s (u + 0.5) - 0.5
        s = self.supersample
        S = np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])
        self.canvas_K = S @ canvas_K
        self.canvas_size = (canvas_size[0] * s, canvas_size[1] * s)
        self._canvas_K_inv = np.linalg.inv(self.canvas_K)
        if self.distorted:
            check_render_size(self.width, self.height, s, canvas_size)

    @classmethod
    def from_camera(cls, camera, supersample: int = 1) -> "Renderer":
        """Renderer for a ``companion.geometry.camera.CameraModel`` (K, dist, width, height)."""
        return cls(camera.K, camera.dist, camera.width, camera.height, supersample)

    def _distortion_map(self):
        """Map from each distorted output pixel to the ideal canvas, and the canvas."""
        xs, ys = np.meshgrid(np.arange(self.width, dtype=np.float64),
                             np.arange(self.height, dtype=np.float64))
        pixels = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        ideal = cv2.undistortPoints(pixels, self.K, self.dist, None, None, self.K, criteria).reshape(-1, 2)
        # the canvas spans the ideal positions, with a 2-pixel margin for interpolation
        x_min, y_min = np.floor(ideal.min(axis=0)) - 2
        x_max, y_max = np.ceil(ideal.max(axis=0)) + 2
        limit = 2.0  # never more than twice the image on each side (fisheye-like maps)
        x_min = max(x_min, -limit * self.width)
        y_min = max(y_min, -limit * self.height)
        x_max = min(x_max, (1 + limit) * self.width)
        y_max = min(y_max, (1 + limit) * self.height)
        canvas_K = self.K.copy()
        canvas_K[0, 2] -= x_min
        canvas_K[1, 2] -= y_min
        map_xy = (ideal - [x_min, y_min]).astype(np.float32).reshape(self.height, self.width, 2)
        canvas_size = (int(x_max - x_min) + 1, int(y_max - y_min) + 1)
        return map_xy, canvas_K, canvas_size

    # ------------------------------------------------------------ projection

    def project(self, points_world: np.ndarray, T_camera_world: np.ndarray):
        """Image positions of world points through the full camera model.

        points_world: (N, 3). Returns (uv (N, 2) float64, NaN for points not in
        front of the camera; in_front (N,) bool).
        """
        p_cam = frames.transform_points(T_camera_world, np.asarray(points_world, dtype=float).reshape(-1, 3))
        in_front = p_cam[:, 2] > NEAR_M
        uv = np.full((len(p_cam), 2), np.nan)
        if np.any(in_front):
            projected, _ = cv2.projectPoints(p_cam[in_front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                             self.K, self.dist)
            uv[in_front] = projected.reshape(-1, 2)
        return uv, in_front

    def inside_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: which of the (N, 2) pixel positions lie inside the image."""
        x, y = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            return ((x >= -0.5 + margin_px) & (x <= self.width - 0.5 - margin_px)
                    & (y >= -0.5 + margin_px) & (y <= self.height - 0.5 - margin_px))

    # ------------------------------------------------------------- drawing

    def render(self, quads: Sequence[TexturedQuad], T_camera_world: np.ndarray,
               background: np.ndarray | float = 0.0, labels: bool = True) -> Rendering:
        """Draw the quads (nearest wins, per pixel) over a background.

        T_camera_world: (4, 4) world -> OpenCV camera.
        background: a gray level, or an (H, W) uint8 image (the output size;
        it is laid into the canvas, stretched if the lens distorts).
        labels: False leaves out the label image (ground truth), which costs a pass per quad and a remap.
        """
        cw, ch = self.canvas_size
        if np.isscalar(background):
            color = np.full((ch, cw), float(background), np.float32)
        else:
            bg = np.asarray(background)
            if bg.shape != (self.height, self.width):
                raise RenderError(f"background must be {(self.height, self.width)}, got {bg.shape}")
            color = cv2.resize(bg, (cw, ch), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        inv_depth = np.zeros((ch, cw), np.float32)
        label = np.full((ch, cw), -1, np.int32) if labels else None
        if len(quads) > 0:
            # every quad's corners in the camera frame at once: (Q, 4, 3)
            corners_cam = (np.stack([quad.corners_world for quad in quads]) @ T_camera_world[:3, :3].T
                           + T_camera_world[:3, 3])
            tl, tr, bl = corners_cam[:, 0], corners_cam[:, 1], corners_cam[:, 3]
            # the plane n . X = c of each quad, n = a x b (a = TL->TR, b = TL->BL); c > 0: its front
            # (TL -> TR -> BR clockwise in the image, front normal b x a) faces the camera
            normals = np.cross(tr - tl, bl - tl)
            plane_c = np.einsum("qi,qi->q", normals, tl)
            all_in_front = (corners_cam[:, :, 2] >= NEAR_M).all(axis=1)
            prepared = []
            for index, quad in enumerate(quads):
                if not quad.two_sided and not plane_c[index] > 0.0:
                    continue
                polygon = corners_cam[index] if all_in_front[index] else clip_polygon_near(corners_cam[index])
                if len(polygon) < 3:
                    continue
                prepared.append((float(polygon[:, 2].mean()), index, polygon))
            hidden = self._hidden_behind_occluders(quads, corners_cam, normals, plane_c,
                                                   [index for _, index, _ in prepared if all_in_front[index]])
            # back to front, so anti-aliased edges blend over what lies behind them
            prepared.sort(key=lambda item: -item[0])
            for _, index, polygon in prepared:
                if index in hidden:
                    continue
                self._draw_quad(color, inv_depth, label, index, quads[index], corners_cam[index], polygon,
                                normals[index], plane_c[index])
        return self._finish(color, label)

    def _hidden_behind_occluders(self, quads, corners_cam, normals, plane_c, candidates: list[int]) -> set[int]:
        """Indices of quads that cannot show, so need not be drawn: each lies wholly behind an opaque plane
        surface, and its image wholly inside that surface's image, away from its anti-aliased edge. That surface
        paints over every pixel they would reach (or they would fail the depth test there): skipping them
        changes nothing. A surface is the coplanar opaque quads of the list that tile a convex polygon (a
        wall, a rack face in tiles).

        candidates: quads in front of the near plane (4 corners each), not culled.
        """
        if len(candidates) < 2:
            return set()
        index = np.asarray(candidates)
        corners = corners_cam[index]                                     # (Q, 4, 3)
        projected = corners @ self.canvas_K.T
        uv = projected[..., :2] / projected[..., 2:3]                    # (Q, 4, 2) canvas pixels
        unit_n = normals[index] / np.linalg.norm(normals[index], axis=1, keepdims=True)
        distance_m = plane_c[index] / np.linalg.norm(normals[index], axis=1)  # unit_n . X = distance_m
        plane_keys = np.column_stack([np.round(unit_n, 6), np.round(distance_m, 5)]).tolist()
        surfaces: dict[tuple, list[int]] = {}
        for row, i in enumerate(index):
            if quads[i].texture.alpha_levels is None and abs(distance_m[row]) > NEAR_M:
                surfaces.setdefault(tuple(plane_keys[row]), []).append(row)
        uv_min, uv_max = uv.min(axis=1), uv.max(axis=1)                  # (Q, 2) image bounding boxes
        # shoelace: area = 1/2 |sum x_i y_i+1 - x_i+1 y_i|, (Q,)
        uv_next = uv[:, [1, 2, 3, 0]]
        area = 0.5 * np.abs(np.sum(uv[..., 0] * uv_next[..., 1] - uv_next[..., 0] * uv[..., 1], axis=1))
        hidden = np.zeros(len(index), bool)
        for rows in surfaces.values():
            # a quad can only hide inside the surface's bounding box: most surfaces (a marker) hide none
            if not np.any((uv_min >= uv_min[rows].min(axis=0)).all(axis=1)
                          & (uv_max <= uv_max[rows].max(axis=0)).all(axis=1) & ~np.isin(np.arange(len(index)), rows)):
                continue
            hull = cv2.convexHull(uv[rows].reshape(-1, 2).astype(np.float32)).reshape(-1, 2).astype(float)
            hull_area = _polygon_area(hull)
            if hull_area < 1.0 or area[rows].sum() < hull_area * (1.0 - 1e-4):
                continue  # the quads leave gaps in their hull (a missing tile: far more than 1e-4 of it)
            # signed distance of every corner p of every quad to every hull edge e from v:
            # d = (e x (p - v)) / |e|, (Q, 4 corners, E edges); one sign all round = inside
            e = np.roll(hull, -1, axis=0) - hull
            rel = uv[:, :, None, :] - hull[None, None]
            d = (e[..., 0] * rel[..., 1] - e[..., 1] * rel[..., 0]) / np.maximum(np.linalg.norm(e, axis=1), 1e-12)
            inside = (d >= OCCLUSION_MARGIN_PX).all(axis=(1, 2)) | (d <= -OCCLUSION_MARGIN_PX).all(axis=(1, 2))
            # behind: every corner beyond the plane n . X = c, on the side away from the camera (the origin)
            row = rows[0]
            beyond_m = (corners @ unit_n[row] - distance_m[row]) * np.sign(distance_m[row])  # (Q, 4)
            hidden |= inside & (beyond_m > OCCLUSION_DEPTH_M).all(axis=1)
        return set(index[hidden].tolist())

    def _draw_quad(self, color, inv_depth, label, index, quad, corners_cam, polygon, normal, plane_c) -> None:
        """Blend one quad into the canvas where it is nearer than what is there; each step one pass over its ROI."""
        cw, ch = self.canvas_size
        # ideal projection of the clipped polygon: u = K p / z
        projected = polygon @ self.canvas_K.T
        uv = projected[:, :2] / projected[:, 2:3]
        x0 = max(int(math.floor(uv[:, 0].min())) - 1, 0)
        y0 = max(int(math.floor(uv[:, 1].min())) - 1, 0)
        x1 = min(int(math.ceil(uv[:, 0].max())) + 2, cw)
        y1 = min(int(math.ceil(uv[:, 1].max())) + 2, ch)
        if x1 <= x0 or y1 <= y0:
            return
        if abs(plane_c) < 1e-12 * float(np.linalg.norm(normal)):
            return  # seen exactly edge-on
        roi_size = (x1 - x0, y1 - y0)

        tex_w, tex_h = quad.texture.size_px
        tl, tr, _, bl = corners_cam
        a, b = tr - tl, bl - tl
        # texture pixel (x, y) lies at tl + (x + 0.5)/W a + (y + 0.5)/H b, so
        # H_canvas_tex = K [a/W, b/H, tl + a/(2W) + b/(2H)]
        H0 = self.canvas_K @ np.column_stack([a / tex_w, b / tex_h, tl + a / (2 * tex_w) + b / (2 * tex_h)])
        level, blend, taps_px = _mip_levels(H0, uv, len(quad.texture.levels))
        # shade = texture * gain + offset, trilinear between two mip levels, averaged over the taps
        shade = _warp_level(quad.texture.levels, level, blend, taps_px, H0, (x0, y0), roi_size, cv2.BORDER_REPLICATE,
                            quad.gain, quad.offset)

        coverage = np.zeros(roi_size[::-1], np.uint8)
        shift = 4
        points = np.round((uv - [x0, y0]) * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(coverage, points, 255, lineType=cv2.LINE_AA, shift=shift)
        alpha = np.multiply(coverage, np.float32(1.0 / 255.0), dtype=np.float32)
        if quad.texture.alpha_levels is not None:
            alpha *= _warp_level(quad.texture.alpha_levels, level, blend, taps_px, H0, (x0, y0), roi_size,
                                 cv2.BORDER_CONSTANT, 1.0 / 255.0, 0.0)

        # along the ray X = z K^-1 [u, v, 1] the plane n.X = c gives
        # 1/z = n . K^-1 [u, v, 1] / c, affine in (u, v)
        A, B, C = (normal @ self._canvas_K_inv) / plane_c
        xs = np.arange(x0, x1, dtype=np.float32)
        ys = np.arange(y0, y1, dtype=np.float32)
        quad_inv_depth = np.float32(A) * xs[None, :] + np.float32(B) * ys[:, None]
        quad_inv_depth += np.float32(C)

        roi = (slice(y0, y1), slice(x0, x1))
        color_roi, inv_depth_roi = color[roi], inv_depth[roi]
        # alpha: the coverage where the quad is nearer than what is drawn, 0 elsewhere
        alpha *= quad_inv_depth > inv_depth_roi
        # color += alpha (shade - color), in place
        shade -= color_roi
        shade *= alpha
        color_roi += shade
        solid = alpha >= 0.5
        np.copyto(inv_depth_roi, quad_inv_depth, where=solid)
        if label is not None:
            np.copyto(label[roi], index, where=solid)

    def _finish(self, color: np.ndarray, label: np.ndarray | None) -> Rendering:
        s = self.supersample
        if s > 1:
            h, w = color.shape
            color = cv2.resize(color, (w // s, h // s), interpolation=cv2.INTER_AREA)
            if label is not None:
                label = np.ascontiguousarray(label[s // 2::s, s // 2::s][: h // s, : w // s])
        if self._undistort_map is not None:
            color = cv2.remap(color, self._undistort_map, None, LENS_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE)
            if label is not None:
                label = cv2.remap(label.astype(np.float32), self._undistort_map, None, cv2.INTER_NEAREST,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=-1).astype(np.int32)
        np.rint(color, out=color)
        np.clip(color, 0, 255, out=color)
        return Rendering(image=color.astype(np.uint8), label=label)


def _warp_level(levels, level: int, blend: float, taps_px: np.ndarray, H0: np.ndarray, roi_origin, size,
                border: int, gain: float, offset: float) -> np.ndarray:
    """(h, w) float32: gain * (mip ``level`` mixed with the next level by ``blend``) + offset, warped into the
    ROI whose top-left canvas pixel is ``roi_origin``, averaged over canvas offsets ``taps_px`` (T, 2)."""
    x0, y0 = roi_origin
    weights = [(level, 1.0 - blend)] + ([(level + 1, blend)] if blend > 0.0 else [])
    total = None
    for dx, dy in taps_px:
        # output pixel p shows the texture at canvas p + (x0 + dx, y0 + dy)
        shift = np.array([[1.0, 0.0, -x0 - dx], [0.0, 1.0, -y0 - dy], [0.0, 0.0, 1.0]])
        for k, weight in weights:
            s = 2.0 ** k
            # a 2^k box average centres level-k texel x_k on level-0 texel x_0 = 2^k x_k + (2^k - 1)/2
            H = shift @ H0 @ np.array([[s, 0.0, 0.5 * (s - 1.0)], [0.0, s, 0.5 * (s - 1.0)], [0.0, 0.0, 1.0]])
            warped = cv2.warpPerspective(levels[k], H, size, flags=cv2.INTER_LINEAR, borderMode=border, borderValue=0)
            # total = sum over taps and levels of gain weight / T * warped, + offset
            scale = gain * weight / len(taps_px)
            if total is None:
                total = cv2.addWeighted(warped, scale, warped, 0.0, offset, dtype=cv2.CV_32F)
            else:
                total = cv2.addWeighted(total, 1.0, warped, scale, 0.0, dtype=cv2.CV_32F)
    return total


def _polygon_area(points: np.ndarray) -> float:
    """Area of a simple polygon (K, 2) by the shoelace formula: 1/2 |sum x_i y_i+1 - x_i+1 y_i|."""
    x, y = points[:, 0], points[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - np.roll(x, -1) @ y))


def _mip_levels(H_canvas_tex: np.ndarray, uv_polygon: np.ndarray, n_levels: int) -> tuple[int, float, np.ndarray]:
    """Mip level, blend toward the next one and anisotropic taps for the texel footprint at the polygon's centre.

    The texture -> canvas Jacobian J = U diag(p1, p2) V^T (p1 >= p2 canvas pixels per level-0 texel) maps a
    canvas pixel onto an ellipse of 1/p1 by 1/p2 texels. The level comes from the ellipse's short axis:
    floor(log2(1/p1) + MIP_BIAS), the blend its fraction (trilinear), so a foreshortened marker is not blurred
    along its long image axis by the coarser level its short one would need (that blur read as a squashed
    marker, 0.01 px). Along the long axis the pixel is sampled by T taps spaced 1/T pixel apart along U's
    second column (T = ceil(1/(p2 2^level)); at most MAX_MIP_TAPS, with a coarser level when more would be
    needed), so each tap covers about one texel of the level and a shrunken texture is not aliased either (a
    marker's edges would move by up to 0.2 px with the sub-pixel phase). Returns (level, blend, taps (T, 2)
    canvas pixel offsets).
    """
    no_taps = np.zeros((1, 2))
    centre = np.append(uv_polygon.mean(axis=0), 1.0)
    tex = np.linalg.solve(H_canvas_tex, centre)
    if abs(tex[2]) < 1e-12:
        return 0, 0.0, no_taps
    tex = tex / tex[2]
    probe = np.array([tex, tex + [1.0, 0.0, 0.0], tex + [0.0, 1.0, 0.0]]) @ H_canvas_tex.T
    img = probe[:, :2] / probe[:, 2:3]
    (a, c), (b, d) = img[1] - img[0], img[2] - img[0]          # J = [[a, b], [c, d]]
    # singular values of a 2 x 2 matrix: p^2 = (|J|_F^2 +- sqrt(|J|_F^2^2 - 4 det^2)) / 2
    frobenius2, det = a * a + b * b + c * c + d * d, a * d - b * c
    root = math.sqrt(max(frobenius2 * frobenius2 - 4.0 * det * det, 0.0))
    px_long, px_short = math.sqrt((frobenius2 + root) / 2.0), math.sqrt(max(frobenius2 - root, 0.0) / 2.0)
    if not px_short > 1e-12:
        return 0, 0.0, no_taps
    # the image direction of the short axis: the eigenvector of J J^T = [[P, Q], [Q, R]] for p_short^2
    P, Q, R = a * a + b * b, a * c + b * d, c * c + d * d
    if abs(Q) > 1e-12 * frobenius2:
        short_dir = np.array([Q, px_short ** 2 - P])
    else:
        short_dir = np.array([0.0, 1.0] if R < P else [1.0, 0.0])
    short_dir /= np.linalg.norm(short_dir)
    long_dir = np.array([-short_dir[1], short_dir[0]])
    # the level whose texels span the short footprint 1/p1, unless MAX_MIP_TAPS taps cannot cover 1/p2 with it
    log_scale = max(math.log2(1.0 / px_long), math.log2(1.0 / (px_short * MAX_MIP_TAPS))) + MIP_BIAS
    log_scale = min(log_scale, n_levels - 1)
    level = int(math.floor(max(log_scale, 0.0)))
    blend = max(log_scale, 0.0) - level
    blend = blend if blend > 0.02 and level + 1 < n_levels else 0.0
    # taps along each footprint axis i: each covers 1/(T_i p_i) level-0 texels <= 2^log_scale
    texel = 2.0 ** max(log_scale, 0.0)
    n_long, n_short = (min(max(1, math.ceil(1.0 / (px * texel) - 1e-6)), MAX_MIP_TAPS) for px in (px_long, px_short))
    if n_long * n_short == 1:
        return level, blend, no_taps
    along_long = ((np.arange(n_long) + 0.5) / n_long - 0.5)[:, None] * long_dir     # (n_long, 2)
    along_short = ((np.arange(n_short) + 0.5) / n_short - 0.5)[:, None] * short_dir  # (n_short, 2)
    return level, blend, (along_long[:, None, :] + along_short[None, :, :]).reshape(-1, 2)


def clip_polygon_near(points_cam: np.ndarray, near_m: float = NEAR_M) -> np.ndarray:
    """Clip a convex polygon (K, 3), in camera coordinates, to z >= near_m.

    Sutherland-Hodgman against one plane; returns (M, 3), M = 0 when the
    polygon lies wholly behind the plane.
    """
    out = []
    n = len(points_cam)
    for i in range(n):
        p, q = points_cam[i], points_cam[(i + 1) % n]
        p_in, q_in = p[2] >= near_m, q[2] >= near_m
        if p_in:
            out.append(p)
        if p_in != q_in:
            # the edge crosses z = near at p + t (q - p), t = (near - p_z) / (q_z - p_z)
            t = (near_m - p[2]) / (q[2] - p[2])
            out.append(p + t * (q - p))
    return np.array(out).reshape(-1, 3)


# ------------------------------------------------------------------ markers

@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class MarkerTexture:
    """A printable square marker as an image, and where its reference points are on it.

    image: (H, W) uint8, white 255 / black 0.
    inner_corners_px: (4, 2) texture coordinates of the inner black square's
        corners TL, TR, BR, BL.
    circles_px: (K, 2) texture coordinates of the corner circles' centres
        (K = 12 for an RS marker, 0 for ArUco or AprilTag).
    marker_id: the id the detector should report.
    family: "rs", "aruco", "apriltag" ... (free text for reports).
    """

    image: np.ndarray
    inner_corners_px: np.ndarray
    circles_px: np.ndarray
    marker_id: int
    family: str = "rs"
    texture: Texture = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.texture is None:
            object.__setattr__(self, "texture", make_texture(self.image))


def rs_marker_texture(layout, marker_id: int, px_per_cell: int = 16, quiet_zone_cells: int = 1) -> MarkerTexture:
    """MarkerTexture of an RS marker (``layout``: a ``companion.markers.layout.MarkerLayout``),
    drawn by ``companion.markers.layout.marker_image``.

    Its reference points come from the layout (inner corners, circle centres in
    grid cells) through ``companion.markers.layout.cell_point_to_px``, the same mapping
    the image was drawn with.
    """
    image = marker_image(layout, marker_id, px_per_cell, quiet_zone_cells=quiet_zone_cells)
    corners = cell_point_to_px(layout.inner_corners_cells, px_per_cell, quiet_zone_cells)
    circles = cell_point_to_px(np.asarray(layout.circles, dtype=float)[:, :2].reshape(-1, 2), px_per_cell,
                               quiet_zone_cells)
    return MarkerTexture(image, corners, circles, int(marker_id), "rs")


def aruco_marker_texture(dictionary, marker_id: int, px_per_cell: int = 16, quiet_zone_cells: int = 2,
                         family: str = "aruco") -> MarkerTexture:
    """MarkerTexture of an OpenCV ArUco/AprilTag dictionary marker (``cv2.aruco.Dictionary``).

    The inner square is the marker's black border square; a white quiet zone
    of ``quiet_zone_cells`` surrounds it.
    """
    cells = dictionary.markerSize + 2
    side = cells * px_per_cell
    marker = cv2.aruco.generateImageMarker(dictionary, int(marker_id), side, borderBits=1)
    q = quiet_zone_cells * px_per_cell
    image = cv2.copyMakeBorder(marker, q, q, q, q, cv2.BORDER_CONSTANT, value=255)
    lo, hi = q - 0.5, q + side - 0.5
    corners = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
    return MarkerTexture(image, corners, np.zeros((0, 2)), int(marker_id), family)


def texture_to_marker(marker: MarkerTexture, size_m: float) -> np.ndarray:
    """(3, 3) affine map from texture pixel (x, y, 1) to marker-frame (x_m, y_m, 1).

    Fitted to the four inner corners, so the texture's orientation on the
    marker frame comes from the data, not from an axis convention here.
    """
    src = marker.inner_corners_px
    dst = frames.marker_inner_corners_m(size_m)[:, :2]
    # least squares for [x_m, y_m] = M [x, y, 1]; exact for a square
    design = np.column_stack([src, np.ones(4)])
    M, *_ = np.linalg.lstsq(design, dst, rcond=None)
    return np.vstack([M.T, [0.0, 0.0, 1.0]])


def marker_points_marker(marker: MarkerTexture, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Marker-frame 3-D positions (inner corners (4, 3), circle centres (K, 3)), metres."""
    A = texture_to_marker(marker, size_m)
    circles = np.column_stack([marker.circles_px, np.ones(len(marker.circles_px))]) @ A.T
    circles[:, 2] = 0.0
    return frames.marker_inner_corners_m(size_m), circles


def marker_quad(marker: MarkerTexture, size_m: float, T_world_marker: np.ndarray,
                gain: float = 1.0, offset: float = 0.0) -> TexturedQuad:
    """The marker's whole texture (grid and quiet zone) as a one-sided quad in the world."""
    A = texture_to_marker(marker, size_m)
    h, w = marker.image.shape
    outer = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0], [-0.5, h - 0.5, 1.0]])
    local = outer @ A.T
    local[:, 2] = 0.0
    return TexturedQuad(frames.transform_points(T_world_marker, local), marker.texture,
                        gain=gain, offset=offset, two_sided=False)


def lift(T_world_marker: np.ndarray, distance_m: float) -> np.ndarray:
    """(4, 4) the same frame moved ``distance_m`` along its own +z (out of the face)."""
    return T_world_marker @ frames.make_transform(np.eye(3), [0.0, 0.0, distance_m])


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class MarkerTruth:
    """Ground truth of one rendered marker in one image.

    marker_id: the marker's id; key: the caller's key (map id, scene index).
    corners_px: (4, 2) inner corners TL, TR, BR, BL through the camera model
        (NaN where behind the camera).
    circles_px: (K, 2) circle centres (NaN where behind).
    corners_visible, circles_visible: (4,), (K,) bool: in front, inside the
        image and not hidden by anything drawn over them.
    inner_visible_fraction: fraction of the inner square's image area that
        shows the marker (0 when not seen).
    inner_px: mean side of the inner square in the image, pixels.
    """

    marker_id: int
    key: int
    corners_px: np.ndarray
    circles_px: np.ndarray
    corners_visible: np.ndarray
    circles_visible: np.ndarray
    inner_visible_fraction: float
    inner_px: float

    @property
    def fully_visible(self) -> bool:
        return bool(self.corners_visible.all()) and self.inner_visible_fraction > 0.999


def marker_truth(renderer: Renderer, rendering: Rendering, marker: MarkerTexture, size_m: float,
                 T_world_marker: np.ndarray, T_camera_world: np.ndarray, quad_index: int,
                 key: int | None = None) -> MarkerTruth:
    """Ground truth of a marker drawn as quad ``quad_index`` of the rendered list."""
    corners_m, circles_m = marker_points_marker(marker, size_m)
    points = frames.transform_points(T_world_marker, np.vstack([corners_m, circles_m]))
    uv, in_front = renderer.project(points, T_camera_world)
    seen = in_front & renderer.inside_image(uv) & _label_at(rendering.label, uv, quad_index)
    corners_px = uv[:4]
    if in_front[:4].all():
        sides = np.linalg.norm(corners_px - np.roll(corners_px, -1, axis=0), axis=1)
        inner_px = float(sides.mean())
        fraction = _visible_fraction(rendering.label, corners_px, quad_index)
    else:
        inner_px, fraction = 0.0, 0.0
    return MarkerTruth(marker.marker_id, marker.marker_id if key is None else key, corners_px, uv[4:],
                       seen[:4], seen[4:], fraction, inner_px)


def _label_at(label: np.ndarray, uv: np.ndarray, quad_index: int, radius_px: int = 1) -> np.ndarray:
    """(N,) bool: every pixel within ``radius_px`` of each point shows quad ``quad_index``."""
    h, w = label.shape
    ok = np.isfinite(uv).all(axis=1)
    result = np.zeros(len(uv), bool)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return result
    xi = np.rint(uv[idx, 0]).astype(int)
    yi = np.rint(uv[idx, 1]).astype(int)
    good = np.ones(len(idx), bool)
    for dy in range(-radius_px, radius_px + 1):
        for dx in range(-radius_px, radius_px + 1):
            x, y = xi + dx, yi + dy
            inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            hit = np.zeros(len(idx), bool)
            hit[inside] = label[y[inside], x[inside]] == quad_index
            good &= hit
    result[idx] = good
    return result


def _visible_fraction(label: np.ndarray, corners_px: np.ndarray, quad_index: int) -> float:
    """Fraction of the (unclipped) inner-square polygon's area whose pixels show the quad."""
    polygon_area = abs(cv2.contourArea(corners_px.astype(np.float32)))
    if polygon_area < 1.0:
        return 0.0
    h, w = label.shape
    x0 = int(max(math.floor(corners_px[:, 0].min()), 0))
    y0 = int(max(math.floor(corners_px[:, 1].min()), 0))
    x1 = int(min(math.ceil(corners_px[:, 0].max()) + 1, w))
    y1 = int(min(math.ceil(corners_px[:, 1].max()) + 1, h))
    if x1 <= x0 or y1 <= y0:
        return 0.0
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    shift = 4
    pts = np.round((corners_px - [x0, y0]) * (1 << shift)).astype(np.int32)
    cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=shift)
    seen = np.count_nonzero((mask > 0) & (label[y0:y1, x0:x1] == quad_index))
    return float(min(seen / polygon_area, 1.0))
