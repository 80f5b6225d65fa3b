"""The camera: pinhole intrinsics, OpenCV distortion, and its mounting on the vehicle.

A ``CameraModel`` comes from the config's ``camera`` section
(``CameraModel.from_config``), whose intrinsics are either inline or in an
OpenCV calibration file (``cv2.FileStorage`` YAML as OpenCV's calibration
tools write it: ``camera_matrix``, ``distortion_coefficients``,
``image_width``, ``image_height``). The section (see
``config/camera-example.yaml``)::

    camera:
      calibration_file: calib.yaml        # or inline: width, height and
      width: 640                          #   fx_px, fy_px, cx_px, cy_px
      height: 480                         #   (or hfov_deg for an ideal
      hfov_deg: 70.0                      #   centred pinhole), distortion
      distortion: [k1, k2, p1, p2, k3]
      mount:
        lever_arm_m: [0.10, 0.0, 0.05]    # optical centre in body FRD
        facing: forward                   # forward/backward/left/right/down/up
        tilt_down_deg: 20                 # or roll_deg, pitch_deg, yaw_deg

Axis conventions come from ``companion.geometry.frames``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.geometry import frames
from companion.yaml_input import Where, read_yaml

SECTION_KEYS = {"calibration_file", "width", "height", "fx_px", "fy_px", "cx_px", "cy_px", "hfov_deg", "distortion", "mount"}
INTRINSIC_KEYS = ("width", "height", "fx_px", "fy_px", "cx_px", "cy_px", "hfov_deg", "distortion")
MOUNT_KEYS = {"lever_arm_m", "facing", "tilt_down_deg", "roll_deg", "pitch_deg", "yaw_deg"}
# (yaw_deg, pitch_deg) of the camera FRD frame in the body for each facing word.
FACINGS = {
    "forward": (0.0, 0.0),
    "right": (90.0, 0.0),
    "backward": (180.0, 0.0),
    "left": (-90.0, 0.0),
    "down": (0.0, -90.0),
    "up": (0.0, 90.0),
}
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


class CameraError(ValueError):
    """A camera section or calibration file is invalid; the message says where."""


@dataclass(frozen=True)
class CameraModel:
    """A calibrated camera on the vehicle.

    K: (3, 3) intrinsic matrix, pixels (OpenCV convention, pixel centres at integers).
    dist: (k,) OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]).
    width, height: image size in pixels.
    T_body_camera: (4, 4) camera (OpenCV axes) -> body FRD.
    """

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    T_body_camera: np.ndarray

    # ----------------------------------------------------------- geometry

    @property
    def T_camera_body(self) -> np.ndarray:
        """(4, 4) body FRD -> camera."""
        return frames.invert_transform(self.T_body_camera)

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view of the undistorted pinhole, degrees."""
        return math.degrees(2.0 * math.atan2(self.width / 2.0, self.K[0, 0]))

    def project(self, points_camera) -> np.ndarray:
        """(N, 2) pixel positions of (N, 3) camera-frame points, with distortion.

        Points at or behind the optical centre (z <= 0) give NaN.
        """
        p = np.asarray(points_camera, dtype=float).reshape(-1, 3)
        px, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.dist)
        px = px.reshape(-1, 2)
        px[p[:, 2] <= 0.0] = np.nan
        return px

    def projection_jacobian(self, points_camera) -> np.ndarray:
        """(N, 2, 3) derivative of each point's pixel position by its camera-frame position, with distortion.

        OpenCV's d(pixels)/d(tvec): with the pose at zero, a point's camera
        coordinates are X + tvec, so d(pixels)/d(tvec) = d(pixels)/dX.
        """
        p = np.asarray(points_camera, dtype=float).reshape(-1, 3)
        _, jacobian = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.dist)
        # columns: rvec (3), tvec (3), focal lengths (2), principal point (2), distortion
        return jacobian[:, 3:6].reshape(-1, 2, 3)

    def project_with_jacobian(self, points_camera) -> tuple[np.ndarray, np.ndarray]:
        """((N, 2) pixels, (N, 2, 3) their derivatives by the camera-frame points) in one OpenCV call.

        ``project`` and ``projection_jacobian`` together, for the pose
        stage's iterations (points behind the camera give NaN pixels).
        """
        p = np.asarray(points_camera, dtype=float).reshape(-1, 3)
        px, jacobian = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.dist)
        px = px.reshape(-1, 2)
        px[p[:, 2] <= 0.0] = np.nan
        return px, jacobian[:, 3:6].reshape(-1, 2, 3)

    def project_from(self, T_camera_x: np.ndarray, points_x) -> np.ndarray:
        """(N, 2) pixel positions of (N, 3) points given in frame x."""
        return self.project(frames.transform_points(T_camera_x, points_x))

    def normalized(self, points_px) -> np.ndarray:
        """(N, 2) undistorted normalised image coordinates (x/z, y/z) of (N, 2) pixels."""
        px = np.asarray(points_px, dtype=float).reshape(-1, 1, 2)
        return cv2.undistortPoints(px, self.K, self.dist).reshape(-1, 2)

    def undistort_px(self, points_px) -> np.ndarray:
        """(N, 2) pixel positions the ideal pinhole (same K, no distortion) would see."""
        px = np.asarray(points_px, dtype=float).reshape(-1, 1, 2)
        return cv2.undistortPoints(px, self.K, self.dist, P=self.K).reshape(-1, 2)

    def in_image(self, points_px, margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: the pixels lie inside the image, ``margin_px`` from its edges."""
        p = np.asarray(points_px, dtype=float).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            inside_x = (p[:, 0] >= -0.5 + margin_px) & (p[:, 0] <= self.width - 0.5 - margin_px)
            inside_y = (p[:, 1] >= -0.5 + margin_px) & (p[:, 1] <= self.height - 0.5 - margin_px)
        return inside_x & inside_y

    def same_intrinsics(self, other: "CameraModel") -> bool:
        """Whether ``other`` delivers the same images: frame size, K and distortion equal (the mount may differ)."""
        return ((self.width, self.height) == (other.width, other.height) and np.array_equal(self.K, other.K)
                and np.array_equal(self.dist, other.dist))

    def frame_size_problem(self, image: np.ndarray) -> str | None:
        """Why this camera cannot describe ``image`` (another size), or None; for tools that take the camera
        as calibrated (the daemon scales a camera to frames of the same aspect, ``scaled_to``)."""
        height, width = image.shape[:2]
        if (width, height) == (self.width, self.height):
            return None
        return (f"the frames are {width}x{height} but the camera file describes a {self.width}x{self.height} "
                "camera; calibrate this camera at this resolution")

    def differences(self, other: "CameraModel") -> list[str]:
        """What ``other`` has otherwise, as "what: ours -> other's" (a tenth of a pixel, of a degree, a
        millimetre, a distortion coefficient's thousandth: below that they are the same camera); [] if nothing."""
        found = []
        if (self.width, self.height) != (other.width, other.height):
            found.append(f"frame size {self.width}x{self.height} -> {other.width}x{other.height}")
        for name, (row, col) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            if abs(self.K[row, col] - other.K[row, col]) >= 0.1:
                found.append(f"{name} {self.K[row, col]:.1f} -> {other.K[row, col]:.1f} px")
        ours, theirs = (np.pad(np.ravel(d), (0, 14 - np.size(d))) for d in (self.dist, other.dist))
        if np.abs(ours - theirs).max() >= 1e-3:
            found.append(f"distortion {np.trim_zeros(ours, 'b').round(4).tolist()} -> "
                         f"{np.trim_zeros(theirs, 'b').round(4).tolist()}")
        turn_deg = math.degrees(frames.rotation_angle_rad(self.T_body_camera[:3, :3], other.T_body_camera[:3, :3]))
        if turn_deg >= 0.1:
            found.append(f"mount turned by {turn_deg:.1f} deg")
        lever_m = float(np.linalg.norm(self.T_body_camera[:3, 3] - other.T_body_camera[:3, 3]))
        if lever_m >= 0.001:
            found.append(f"lever arm {1000 * lever_m:.0f} mm apart")
        return found

    def scaled_to(self, width: int, height: int) -> "CameraModel":
        """The same camera delivering ``width`` x ``height`` frames of the same field of view (a
        sensor mode that scales the whole image): the intrinsics scaled, the distortion (in
        normalised coordinates) kept. CameraError when the aspect ratio differs (a crop, another
        mode: the calibration does not describe those frames)."""
        sx, sy = width / self.width, height / self.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise CameraError(f"the camera is calibrated for {self.width}x{self.height} frames but gets "
                              f"{width}x{height} (aspect ratio {self.width / self.height:.3f}, not "
                              f"{width / height:.3f}): calibrate at the resolution you use (companion calibrate), "
                              f"or set the source to {self.width}x{self.height}")
        K = np.array(self.K, dtype=float)
        K[0, :] *= sx
        K[1, :] *= sy
        # pixel centres at integers: x' + 0.5 = s (x + 0.5)
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return dataclasses.replace(self, K=K, width=int(width), height=int(height))

    # ------------------------------------------------------------ loading

    @classmethod
    def from_config(cls, section: dict, origin: str) -> "CameraModel":
        """Build from a config ``camera`` section; ``origin`` (file name) prefixes errors.

        A relative ``calibration_file`` is resolved against the directory of
        ``origin``.
        """
        where = Where(str(origin), CameraError, "camera", style="quoted")
        section = where.mapping(section, "calibration_file or width/height/..., mount")
        where.reject_unknown(section, SECTION_KEYS)
        if "calibration_file" in section:
            K, dist, width, height = _from_calibration_section(section, where)
        else:
            K, dist, width, height = _inline_intrinsics(section, where)
        T_body_camera = mount_transform(section.get("mount"), where.sub("mount"))
        return cls(K=K, dist=dist, width=width, height=height, T_body_camera=T_body_camera)

    @classmethod
    def from_calibration_file(cls, path, T_body_camera: np.ndarray | None = None) -> "CameraModel":
        """Read an OpenCV calibration YAML; the mount defaults to a forward camera at the body origin."""
        K, dist, width, height = read_opencv_calibration(path)
        if T_body_camera is None:
            T_body_camera = mount_transform({}, Where(str(path), CameraError, "mount", style="quoted"))
        return cls(K=K, dist=dist, width=width, height=height, T_body_camera=T_body_camera)

    def to_config(self) -> dict:
        """A plain-YAML ``camera`` section that ``from_config`` reads back to this model."""
        roll, pitch, yaw = frames.euler_321_from_rotation(self.T_body_camera[:3, :3] @ frames.R_CAMFRD_CAMERA.T)
        return {
            "width": int(self.width),
            "height": int(self.height),
            "fx_px": float(self.K[0, 0]),
            "fy_px": float(self.K[1, 1]),
            "cx_px": float(self.K[0, 2]),
            "cy_px": float(self.K[1, 2]),
            "distortion": [float(d) for d in self.dist],
            "mount": {
                "lever_arm_m": [float(v) for v in self.T_body_camera[:3, 3]],
                "roll_deg": math.degrees(roll),
                "pitch_deg": math.degrees(pitch),
                "yaw_deg": math.degrees(yaw),
            },
        }


def load_camera(path) -> CameraModel:
    """Read a camera from a file: an OpenCV calibration YAML (forward mount),
    a config file with a ``camera`` section, or a bare camera section."""
    if _is_file_storage(path):
        return CameraModel.from_calibration_file(path)
    document = read_yaml(path, CameraError, "camera file")
    return CameraModel.from_config(document.get("camera", document), str(path))


def intrinsics_from_hfov(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) K of an ideal pinhole with ``hfov_deg`` horizontal field of view, principal point at the image centre."""
    # fx = fy = (W / 2) / tan(hfov / 2); the centre of a W-pixel row is at (W - 1) / 2
    f_px = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f_px, 0.0, (width - 1) / 2.0], [0.0, f_px, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------ pieces

def _is_file_storage(path) -> bool:
    """OpenCV 4 writes "%YAML:1.0", OpenCV 5 "%YAML 1.2"; both tag matrices."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError):
        return False  # read_yaml says why
    return text.lstrip().startswith(("%YAML:", "<?xml")) or "!!opencv-matrix" in text


def _inline_intrinsics(section: dict, where: Where):
    """(K, dist, width, height) from inline keys: fx/fy/cx/cy or hfov_deg."""
    width = where.positive(section, "width", integer=True)
    height = where.positive(section, "height", integer=True)
    pinhole = [k for k in ("fx_px", "fy_px", "cx_px", "cy_px") if k in section]
    if "hfov_deg" in section and pinhole:
        raise where.error("give either hfov_deg or fx_px/fy_px/cx_px/cy_px, not both", "hfov_deg")
    if "hfov_deg" in section:
        hfov_deg = where.positive(section, "hfov_deg")
        if hfov_deg >= 180.0:
            raise where.error(f"must be below 180 for a pinhole camera, got {hfov_deg:g}", "hfov_deg")
        K = intrinsics_from_hfov(width, height, hfov_deg)
    else:
        fx, fy = where.positive(section, "fx_px"), where.positive(section, "fy_px")
        cx, cy = where.number(section, "cx_px"), where.number(section, "cy_px")
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    dist = where.numbers(section, "distortion", DISTORTION_LENGTHS, [0.0] * 5)
    _check_intrinsics(K, width, height, where, "cx_px")
    return K, dist, width, height


def _check_intrinsics(K: np.ndarray, width: int, height: int, where: Where, key: str) -> None:
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise where.error(f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}", key)
    if not (0.0 <= K[0, 2] <= width and 0.0 <= K[1, 2] <= height):
        raise where.error(f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {width}x{height} image", key)


def _from_calibration_section(section: dict, where: Where):
    inline = [k for k in INTRINSIC_KEYS if k in section]
    if inline:
        raise where.error("intrinsics come from calibration_file; remove the inline value", inline[0])
    path = where.path(section, "calibration_file")
    if not path.is_file():  # named by the config's key, not only by the path it gave
        raise where.error(f"{path}: {'not a file' if path.exists() else 'no such file'}", "calibration_file")
    return read_opencv_calibration(path)


def read_opencv_calibration(path):
    """(K (3, 3), dist (k,), width, height) from an OpenCV ``cv2.FileStorage`` YAML/XML.

    Needs the nodes ``camera_matrix``, ``distortion_coefficients``,
    ``image_width`` and ``image_height`` (as OpenCV's calibration samples write).
    """
    path = str(path)
    where = Where(path, CameraError, style="quoted")
    if not Path(path).is_file():
        raise where.error("cannot read calibration file: no such file")
    try:
        storage = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as error:  # an empty or binary file: OpenCV's parser raises SystemError
        raise where.error(f"not an OpenCV FileStorage file: {getattr(error, 'err', None) or 'empty or not YAML/XML'}"
                          ) from None
    try:
        K = _matrix_node(storage, "camera_matrix", where)
        dist = _matrix_node(storage, "distortion_coefficients", where).reshape(-1)
        width = _int_node(storage, "image_width", where)
        height = _int_node(storage, "image_height", where)
    finally:
        storage.release()
    if K.shape != (3, 3):
        raise where.error(f"must be 3x3, got {K.shape[0]}x{K.shape[1]}", "camera_matrix")
    if dist.size not in DISTORTION_LENGTHS:
        raise where.error(f"must have {', '.join(map(str, DISTORTION_LENGTHS))} values, got {dist.size}", "distortion_coefficients")
    if not (np.isfinite(K).all() and np.isfinite(dist).all()):
        raise where.error("holds non-finite values", "camera_matrix")
    _check_intrinsics(K, width, height, where, "camera_matrix")
    return K, dist, width, height


def _matrix_node(storage, key: str, where: Where) -> np.ndarray:
    node = storage.getNode(key)
    if node.empty():
        raise where.error("missing", key)
    try:
        matrix = node.mat()
    except cv2.error:  # rows x cols not the number of values, or values that are not numbers
        matrix = None
    if matrix is None:
        raise where.error("must be an !!opencv-matrix (rows x cols numbers in data)", key)
    return np.asarray(matrix, dtype=float)


def _int_node(storage, key: str, where: Where) -> int:
    node = storage.getNode(key)
    if node.empty() or not (node.isInt() or node.isReal()):
        raise where.error("missing or not a number", key)
    value = node.real()
    if value <= 0 or value != int(value):
        raise where.error(f"must be a positive integer, got {value:g}", key)
    return int(value)


def mount_transform(mount, where: Where) -> np.ndarray:
    """(4, 4) T_body_camera from a ``mount`` section (lever arm + simple rotation)."""
    mount = where.mapping(mount, "lever_arm_m, facing, tilt_down_deg or roll/pitch/yaw_deg")
    where.reject_unknown(mount, MOUNT_KEYS)
    lever_arm_m = where.numbers(mount, "lever_arm_m", (3,), [0.0, 0.0, 0.0], " [forward, right, down] in metres")
    roll_deg, pitch_deg, yaw_deg = _mount_angles(mount, where)
    R_body_camera = frames.R_body_camera_from_mount(roll_deg, pitch_deg, yaw_deg)
    return frames.make_transform(R_body_camera, lever_arm_m)


def _mount_angles(mount: dict, where: Where) -> tuple[float, float, float]:
    """(roll, pitch, yaw) degrees of the camera FRD frame in the body."""
    explicit = [k for k in ("roll_deg", "pitch_deg", "yaw_deg") if k in mount]
    simple = [k for k in ("facing", "tilt_down_deg") if k in mount]
    if explicit and simple:
        raise where.error("give either facing/tilt_down_deg or roll/pitch/yaw_deg, not both", explicit[0])
    if explicit:
        return tuple(where.number(mount, k, 0.0) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
    facing = mount.get("facing", "forward")
    if not isinstance(facing, str) or facing.lower() not in FACINGS:
        raise where.error(f"must be one of {', '.join(FACINGS)}, got {facing!r}", "facing")
    yaw_deg, pitch_deg = FACINGS[facing.lower()]
    tilt_down_deg = where.number(mount, "tilt_down_deg", 0.0)
    if tilt_down_deg and facing.lower() in ("down", "up"):
        raise where.error(f"only for horizontal facings, not {facing!r}", "tilt_down_deg")
    if not -90.0 <= tilt_down_deg <= 90.0:
        raise where.error(f"must be within [-90, 90], got {tilt_down_deg:g}", "tilt_down_deg")
    return 0.0, pitch_deg - tilt_down_deg, yaw_deg
