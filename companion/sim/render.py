"""The rendering core: what a pinhole camera sees of textured planes, with ground truth.

Shared by the camera simulator (``companion simulate``) and the detector
benchmark's scene renderer, so both draw markers, degrade images and compute
ground truth with one piece of code.

* ``Renderer`` draws ``TexturedQuad`` s (flat textured parallelograms in the
  world) as the camera with intrinsics ``K``, distortion ``dist`` and an image
  size sees them: one OpenCV perspective warp per quad into an ideal
  (undistorted) canvas with a per-pixel inverse-depth buffer, polygons clipped
  at a near plane so a plane behind or partly behind the camera is never drawn
  wrong, then one remap through the lens distortion.
* Markers are ``MarkerTexture`` s placed at their inner-square size
  (``marker_quads``); their ground truth (``marker_truth``) is the projection
  of the same 3-D points through the same camera model (``cv2.projectPoints``),
  with flags for points that are behind the camera, outside the image or
  hidden (read from the renderer's label buffer).
* Degradations are small functions (blur, motion blur, sensor noise,
  exposure, low light, JPEG) and occluder quads (side strip, corner patch,
  blob, box, person). Everything random takes a ``numpy.random.Generator``.
* ``random_marker_scene`` renders a detector-benchmark scene.

Pixel coordinates follow OpenCV: x right, y down, the centre of the top-left
pixel at (0, 0). Texture coordinates likewise, so a texture of width W spans
x in [-0.5, W - 0.5].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import cv2
import numpy as np

from companion.geometry import frames

NEAR_M = 0.02  # near clipping plane: nothing closer to the camera is drawn
MIN_MIP_SIZE_PX = 4
MIP_BIAS = 0.0  # > 0 picks coarser levels: less aliasing, more blur
MARKER_LIFT_M = 0.001  # a marker sits this far in front of its backing board
OCCLUDER_LIFT_M = 0.003  # a stuck-on occluder sits this far in front of its marker


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

    Levels are made with ``cv2.pyrDown`` while both sides are even; texel x_i
    of level i is centred on texel 2^i x_i of level 0 (pyrDown's sampling).
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
        levels.append(cv2.pyrDown(levels[-1]))
        if alphas is not None:
            alphas.append(cv2.pyrDown(alphas[-1]))
    return Texture(tuple(levels), None if alphas is None else tuple(alphas))


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
        given to ``Renderer.render`` (-1: background).
    """

    image: np.ndarray
    label: np.ndarray


class Renderer:
    """Renders textured quads as one camera sees them.

    K: (3, 3) intrinsics; dist: OpenCV distortion coefficients (k,) (4, 5, 8,
    12 or 14 values, or empty); width, height: image size in pixels.
    supersample: render at this integer factor and average down
    (anti-aliasing; 1 is usually enough with a little optics blur).

    The canvas is an ideal pinhole image large enough to hold every ray the
    distorted image sees; distortion is applied by one ``cv2.remap`` whose
    map is computed once here.
    """

    def __init__(self, K: np.ndarray, dist, width: int, height: int, supersample: int = 1):
        self.K = np.asarray(K, dtype=float).reshape(3, 3)
        self.dist = np.asarray(dist if dist is not None else [], dtype=float).ravel()
        self.width, self.height = int(width), int(height)
        self.supersample = int(supersample)
        if self.width <= 0 or self.height <= 0 or self.supersample < 1:
            raise RenderError(f"bad image size {width}x{height} or supersample {supersample}")
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
               background: np.ndarray | float = 0.0) -> Rendering:
        """Draw the quads (nearest wins, per pixel) over a background.

        T_camera_world: (4, 4) world -> OpenCV camera.
        background: a gray level, or an (H, W) uint8 image (the output size;
        it is laid into the canvas, stretched if the lens distorts).
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
        label = np.full((ch, cw), -1, np.int32)

        prepared = []
        for index, quad in enumerate(quads):
            corners_cam = frames.transform_points(T_camera_world, quad.corners_world)
            if not quad.two_sided and not _faces_camera(corners_cam):
                continue
            polygon = clip_polygon_near(corners_cam, NEAR_M)
            if len(polygon) < 3:
                continue
            depth = float(np.mean(polygon[:, 2]))
            prepared.append((depth, index, quad, corners_cam, polygon))
        # back to front, so anti-aliased edges blend over what lies behind them
        prepared.sort(key=lambda item: -item[0])
        for _, index, quad, corners_cam, polygon in prepared:
            self._draw_quad(color, inv_depth, label, index, quad, corners_cam, polygon)
        return self._finish(color, label)

    def _draw_quad(self, color, inv_depth, label, index, quad, corners_cam, polygon) -> None:
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
        roi_w, roi_h = x1 - x0, y1 - y0

        tex_w, tex_h = quad.texture.size_px
        tl, tr, _, bl = corners_cam
        a, b = tr - tl, bl - tl
        # texture pixel (x, y) lies at tl + (x + 0.5)/W a + (y + 0.5)/H b, so
        # H_canvas_tex = K [a/W, b/H, tl + a/(2W) + b/(2H)]
        H0 = self.canvas_K @ np.column_stack([a / tex_w, b / tex_h, tl + a / (2 * tex_w) + b / (2 * tex_h)])
        level, blend = _mip_levels(H0, uv, len(quad.texture.levels))
        shift_roi = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        warped = self._warp_level(quad.texture.levels, level, blend, H0, shift_roi, (roi_w, roi_h),
                                  cv2.BORDER_REPLICATE)

        coverage = np.zeros((roi_h, roi_w), np.uint8)
        shift = 4
        points = np.round((uv - [x0, y0]) * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(coverage, points, 255, lineType=cv2.LINE_AA, shift=shift)
        alpha = coverage.astype(np.float32) * (1.0 / 255.0)
        if quad.texture.alpha_levels is not None:
            warped_alpha = self._warp_level(quad.texture.alpha_levels, level, blend, H0, shift_roi,
                                            (roi_w, roi_h), cv2.BORDER_CONSTANT)
            alpha *= warped_alpha * np.float32(1.0 / 255.0)

        # plane n.X = c in the camera frame; along the ray X = z K^-1 [u, v, 1]:
        # 1/z = n . K^-1 [u, v, 1] / c, affine in (u, v)
        normal = np.cross(a, b)
        c = float(normal @ tl)
        if abs(c) < 1e-12 * float(np.linalg.norm(normal)):
            return  # seen exactly edge-on
        A, B, C = (normal @ self._canvas_K_inv) / c
        xs = np.arange(x0, x1, dtype=np.float32)
        ys = np.arange(y0, y1, dtype=np.float32)
        quad_inv_depth = (np.float32(A) * xs[None, :] + np.float32(B) * ys[:, None]
                          + np.float32(C))

        roi = (slice(y0, y1), slice(x0, x1))
        in_front = (alpha > 0.0) & (quad_inv_depth > inv_depth[roi])
        alpha = np.where(in_front, alpha, 0.0)
        shade = warped * np.float32(quad.gain) + np.float32(quad.offset)
        color[roi] += alpha * (shade - color[roi])
        solid = in_front & (alpha >= 0.5)
        inv_depth[roi][solid] = quad_inv_depth[solid]
        label[roi][solid] = index

    @staticmethod
    def _warp_level(levels, level: int, blend: float, H0: np.ndarray, shift_roi: np.ndarray, size,
                    border: int) -> np.ndarray:
        """(h, w) float32: mip ``level`` warped into the ROI, mixed with the next level by ``blend``."""
        def warp(k: int) -> np.ndarray:
            s = 2.0 ** k
            # cv2.pyrDown centres level-k texel x_k on level-0 texel x_0 = 2^k x_k
            H = shift_roi @ H0 @ np.diag([s, s, 1.0])
            return cv2.warpPerspective(levels[k], H, size, flags=cv2.INTER_LINEAR, borderMode=border,
                                       borderValue=0).astype(np.float32)

        warped = warp(level)
        if blend > 0.0:
            # trilinear: (1 - b) level + b (level + 1)
            warped += np.float32(blend) * (warp(level + 1) - warped)
        return warped

    def _finish(self, color: np.ndarray, label: np.ndarray) -> Rendering:
        s = self.supersample
        if s > 1:
            h, w = color.shape
            color = cv2.resize(color, (w // s, h // s), interpolation=cv2.INTER_AREA)
            label = np.ascontiguousarray(label[s // 2::s, s // 2::s][: h // s, : w // s])
        if self._undistort_map is not None:
            color = cv2.remap(color, self._undistort_map, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            label = cv2.remap(label.astype(np.float32), self._undistort_map, None, cv2.INTER_NEAREST,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=-1).astype(np.int32)
        image = np.clip(np.rint(color), 0, 255).astype(np.uint8)
        return Rendering(image=image, label=label)


def _faces_camera(corners_cam: np.ndarray) -> bool:
    """True if the quad's front (TL -> TR -> BR clockwise in the image) faces the camera."""
    tl, tr, _, bl = corners_cam
    # the front normal is b x a (a = TL->TR, b = TL->BL); it points at the camera
    # (origin) when n . (0 - tl) > 0
    front = np.cross(bl - tl, tr - tl)
    return float(front @ -tl) > 0.0


def _mip_levels(H_canvas_tex: np.ndarray, uv_polygon: np.ndarray, n_levels: int) -> tuple[int, float]:
    """Mip level and blend toward the next one for the texel size at the polygon's centre.

    Trilinear filtering: with p canvas pixels per level-0 texel, the level is
    floor(log2(1/p) + MIP_BIAS) and the blend its fraction, so a shrunken texture is
    neither aliased (a marker's edges would move by up to 0.2 px with the
    sub-pixel phase) nor blurred more than needed.
    """
    centre = np.append(uv_polygon.mean(axis=0), 1.0)
    tex = np.linalg.solve(H_canvas_tex, centre)
    if abs(tex[2]) < 1e-12:
        return 0, 0.0
    tex = tex / tex[2]
    probe = np.array([tex, tex + [1.0, 0.0, 0.0], tex + [0.0, 1.0, 0.0]]) @ H_canvas_tex.T
    img = probe[:, :2] / probe[:, 2:3]
    # canvas pixels per texel: sqrt(|det J|) of the texture -> canvas map
    jac = np.column_stack([img[1] - img[0], img[2] - img[0]])
    px_per_texel = math.sqrt(abs(float(np.linalg.det(jac))))
    if px_per_texel <= 0.0:
        return 0, 0.0
    log_scale = min(math.log2(1.0 / px_per_texel) + MIP_BIAS, n_levels - 1)
    if log_scale <= 0.0:
        return 0, 0.0
    level = int(math.floor(log_scale))
    blend = log_scale - level
    return level, (blend if blend > 0.02 and level + 1 < n_levels else 0.0)


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
    """MarkerTexture of an RS marker, drawn by ``companion.markers.layout.marker_image``.

    Its reference points come from the layout (inner corners, circle centres in
    grid cells) through ``companion.markers.layout.cell_point_to_px``, the same mapping
    the image was drawn with.
    """
    from companion.markers import layout as marker_module

    image = marker_module.marker_image(layout, marker_id, px_per_cell, quiet_zone_cells=quiet_zone_cells)
    corners = marker_module.cell_point_to_px(layout.inner_corners_cells, px_per_cell, quiet_zone_cells)
    circles = marker_module.cell_point_to_px(np.asarray(layout.circles, dtype=float)[:, :2].reshape(-1, 2),
                                             px_per_cell, quiet_zone_cells)
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


# ---------------------------------------------------------------- occluders

def solid_texture(rng: np.random.Generator, size_px: tuple[int, int], level: float,
                  texture_amplitude: float = 12.0) -> np.ndarray:
    """(H, W) uint8 surface of mean ``level`` with a soft random mottle and a gradient."""
    w, h = size_px
    coarse = rng.normal(0.0, 1.0, (max(h // 16, 2), max(w // 16, 2))).astype(np.float32)
    mottle = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    gradient = np.linspace(-1.0, 1.0, w, dtype=np.float32)[None, :] * rng.uniform(-1, 1)
    surface = level + texture_amplitude * (0.6 * mottle + 0.4 * gradient)
    return np.clip(surface, 0, 255).astype(np.uint8)


def strip_occluder(marker: MarkerTexture, size_m: float, T_world_marker: np.ndarray, fraction: float,
                   side: str, rng: np.random.Generator, level: float | None = None) -> TexturedQuad:
    """A strip over ``fraction`` of the inner square's width from one side, border and margin included.

    side: "left", "right", "top" or "bottom" of the upright marker. The strip
    reaches well past the marker on the other three directions.
    """
    s = size_m
    reach = _outer_reach_m(marker, size_m) + 0.2 * s
    inner_edge = -s / 2 + fraction * s  # measured from the chosen side
    # in the marker frame (x right, y up): the strip covers [-reach, inner_edge] along the side axis
    length = inner_edge + reach
    centre_along = (-reach + inner_edge) / 2
    if side == "left":
        width_m, height_m, centre = length, 2 * reach, (centre_along, 0.0)
    elif side == "right":
        width_m, height_m, centre = length, 2 * reach, (-centre_along, 0.0)
    elif side == "bottom":
        width_m, height_m, centre = 2 * reach, length, (0.0, centre_along)
    elif side == "top":
        width_m, height_m, centre = 2 * reach, length, (0.0, -centre_along)
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


# ------------------------------------------------------------- degradations

def gaussian_blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """Defocus or optics blur: a gaussian of ``sigma_px`` pixels."""
    if sigma_px <= 0:
        return image.copy()
    return cv2.GaussianBlur(image, (0, 0), sigmaX=sigma_px, sigmaY=sigma_px, borderType=cv2.BORDER_REPLICATE)


def motion_blur_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """(k, k) float32 line kernel of ``length_px`` along ``angle_rad`` (image x right, y down), sum 1.

    Built by spreading many evenly spaced samples of the segment over the
    pixel grid with bilinear weights, so a horizontal kernel stays one row.
    """
    length = max(float(length_px), 1.0)
    half = int(math.ceil(length / 2)) + 1
    k = 2 * half + 1
    steps = np.linspace(-length / 2, length / 2, int(length * 16) + 1)
    xs = half + steps * math.cos(angle_rad)
    ys = half + steps * math.sin(angle_rad)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    kernel = np.zeros((k + 1, k + 1), np.float64)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), w)
    kernel = kernel[:k, :k]
    return (kernel / kernel.sum()).astype(np.float32)


def motion_blur(image: np.ndarray, length_px: float, angle_rad: float) -> np.ndarray:
    """Linear motion blur: the image smeared over ``length_px`` along ``angle_rad``."""
    if length_px < 0.5:
        return image.copy()
    return cv2.filter2D(image, -1, motion_blur_kernel(length_px, angle_rad), borderType=cv2.BORDER_REPLICATE)


def sensor_noise(image: np.ndarray, rng: np.random.Generator, read_noise_dn: float = 2.0,
                 shot_noise_gain: float = 0.05) -> np.ndarray:
    """Shot plus read noise, in 8-bit digital numbers (DN).

    variance(I) = read_noise_dn^2 + shot_noise_gain * I (the gaussian
    approximation of Poisson photon noise with gain DN per electron, plus the
    read-out noise), then rounded and clipped to 0..255.
    """
    signal = image.astype(np.float32)
    sigma = np.sqrt(np.float32(read_noise_dn) ** 2 + np.float32(shot_noise_gain) * signal)
    noisy = signal + sigma * rng.standard_normal(image.shape, dtype=np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def exposure(image: np.ndarray, gain: float, black_level_dn: float = 0.0) -> np.ndarray:
    """Exposure or gain change: (I - black) * gain + black, clipped (bright areas saturate)."""
    out = (image.astype(np.float32) - black_level_dn) * np.float32(gain) + black_level_dn
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def low_light(image: np.ndarray, rng: np.random.Generator, light_fraction: float = 0.15,
              read_noise_dn: float = 2.5, shot_noise_gain: float = 0.3) -> np.ndarray:
    """A dim scene: ``light_fraction`` of the light, then the sensor's noise on the weak signal.

    The result stays dark (no digital gain), with low contrast and a noise
    floor that is large relative to it.
    """
    return sensor_noise(exposure(image, light_fraction), rng, read_noise_dn, shot_noise_gain)


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """The image after a JPEG encode/decode round trip at ``quality`` (1..100)."""
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RenderError(f"JPEG encoding failed at quality {quality}")
    return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)


def vignette(image: np.ndarray, strength: float) -> np.ndarray:
    """Darker corners: I * (1 - strength r^2), r = distance from the centre over the half diagonal."""
    h, w = image.shape
    ys, xs = np.ogrid[:h, :w]
    r2 = ((xs - (w - 1) / 2) ** 2 + (ys - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return np.clip(np.rint(image * (1.0 - strength * r2)), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Degradations:
    """The image-side realism knobs, applied in the order a camera produces them.

    optics_blur_sigma_px: lens/focus blur (0 = off).
    motion_blur: smear by the image motion during the exposure (the caller
        passes it as ``motion_px``; ``motion_length_px`` > 0 forces a fixed kernel).
    exposure_gain: multiplies the light (1 = unchanged).
    vignette_strength: corner darkening (0 = off).
    read_noise_dn, shot_noise_gain: sensor noise (both 0 = off).
    jpeg_quality: JPEG round trip (0 = off).
    """

    optics_blur_sigma_px: float = 0.0
    motion_blur: bool = False
    motion_length_px: float = 0.0
    motion_angle_rad: float = 0.0
    exposure_gain: float = 1.0
    vignette_strength: float = 0.0
    read_noise_dn: float = 0.0
    shot_noise_gain: float = 0.0
    jpeg_quality: int = 0

    def apply(self, image: np.ndarray, rng: np.random.Generator,
              motion_px: tuple[float, float] | None = None) -> np.ndarray:
        """Degrade an (H, W) uint8 image; ``motion_px``: image motion (dx, dy) over the exposure."""
        out = image
        if self.motion_length_px > 0:
            out = motion_blur(out, self.motion_length_px, self.motion_angle_rad)
        elif self.motion_blur and motion_px is not None:
            out = motion_blur(out, math.hypot(*motion_px), math.atan2(motion_px[1], motion_px[0]))
        if self.optics_blur_sigma_px > 0:
            out = gaussian_blur(out, self.optics_blur_sigma_px)
        if self.exposure_gain != 1.0:
            out = exposure(out, self.exposure_gain)
        if self.vignette_strength > 0:
            out = vignette(out, self.vignette_strength)
        if self.read_noise_dn > 0 or self.shot_noise_gain > 0:
            out = sensor_noise(out, rng, self.read_noise_dn, self.shot_noise_gain)
        if self.jpeg_quality > 0:
            out = jpeg(out, self.jpeg_quality)
        return out if out is not image else image.copy()

    def with_(self, **changes) -> "Degradations":
        return replace(self, **changes)


# ------------------------------------------------------------ backgrounds

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


# --------------------------------------------------------- benchmark scenes

@dataclass(frozen=True)
class SceneCondition:
    """One benchmark condition: occluders stuck on each marker and image degradations.

    occlusion: "none", "strip", "corner" or "blob".
    occlusion_fraction: strip width or corner depth as a fraction of the
        inner side; blob radius as a fraction of the inner side.
    degradations: applied to the whole image after rendering; a motion blur
        with ``motion_length_px`` gets a random direction per scene.
    """

    name: str
    occlusion: str = "none"
    occlusion_fraction: float = 0.0
    degradations: Degradations = Degradations(optics_blur_sigma_px=0.5, read_noise_dn=1.0, shot_noise_gain=0.02)


_BASE = Degradations(optics_blur_sigma_px=0.5, read_noise_dn=1.0, shot_noise_gain=0.02)

CONDITIONS: dict[str, SceneCondition] = {
    c.name: c for c in (
        SceneCondition("clean"),
        SceneCondition("strip_1_8", "strip", 1.0 / 8.0),
        SceneCondition("strip_1_4", "strip", 1.0 / 4.0),
        SceneCondition("corner", "corner", 0.25),
        SceneCondition("blob", "blob", 0.18),
        SceneCondition("gaussian_blur", degradations=_BASE.with_(optics_blur_sigma_px=1.6)),
        SceneCondition("motion_blur", degradations=_BASE.with_(motion_length_px=9.0)),
        SceneCondition("noise", degradations=_BASE.with_(read_noise_dn=12.0, shot_noise_gain=0.5)),
        SceneCondition("low_light", degradations=_BASE.with_(exposure_gain=0.15, read_noise_dn=2.5,
                                                             shot_noise_gain=0.3)),
        SceneCondition("jpeg", degradations=_BASE.with_(jpeg_quality=15)),
    )
}


def default_camera_matrix(width: int, height: int, hfov_deg: float = 70.0) -> np.ndarray:
    """(3, 3) K of an ideal pinhole with ``hfov_deg`` horizontal field of view, centred."""
    # f = (W / 2) / tan(hfov / 2)
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _R_camera_marker_facing() -> np.ndarray:
    """(3, 3) marker -> OpenCV camera for an upright marker seen face-on.

    Composed from frames.py: a level body looking along map +x (yaw 0 in a
    map whose x points north), a forward camera, a wall marker facing -x.
    """
    R_map_body = frames.R_ned_map(0.0).T
    R_map_camera = R_map_body @ frames.R_body_camera_from_mount()
    return R_map_camera.T @ frames.R_map_marker_on_wall(180.0)


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
    K = default_camera_matrix(width, height, hfov_deg)
    renderer = Renderer(K, np.zeros(5), width, height, supersample)
    if background is None:
        background = clutter_image(rng, (width, height))
    size_m = 0.15
    f = K[0, 0]
    R_face = _R_camera_marker_facing()
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
    if condition.occlusion == "strip":
        side = ("left", "right", "top", "bottom")[int(rng.integers(0, 4))]
        return [strip_occluder(marker, size_m, T_world_marker, condition.occlusion_fraction, side, rng)]
    if condition.occlusion == "corner":
        return [corner_occluder(marker, size_m, T_world_marker, condition.occlusion_fraction,
                                int(rng.integers(0, 4)), rng)]
    if condition.occlusion == "blob":
        return [blob_occluder(size_m, T_world_marker, rng, condition.occlusion_fraction)]
    raise RenderError(f"unknown occlusion {condition.occlusion!r}")
