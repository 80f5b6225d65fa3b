"""Image degradations, applied in the order a camera produces them: motion blur, optics blur,
exposure, vignetting, sensor noise, JPEG.

Small functions on (H, W) uint8 images and ``Degradations``, the one set of
image-realism knobs that chains them (the simulator and the benchmark scenes
both use it). Everything random takes a ``numpy.random.Generator``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np


class DegradationError(ValueError):
    """A degradation knob out of its range, or an image step that failed; the message names it."""


# The largest value of each knob (``Degradations``; every knob but the motion's angle is 0 or more): beyond,
# the image is nothing but blur, glare or noise, and a blur's kernel outgrows the memory.
KNOB_LIMITS = {"exposure_ms": 1000.0, "motion_length_px": 1000.0, "optics_blur_sigma_px": 50.0,
               "exposure_gain": 100.0, "exposure_wander": 5.0, "vignette_strength": 1.0, "read_noise_dn": 255.0,
               "shot_noise_gain": 255.0, "jpeg_quality": 100}


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
    """Linear motion blur: the image smeared over ``length_px`` along ``angle_rad`` (at most its diagonal:
    a longer smear looks the same, and its kernel would outgrow the memory)."""
    if length_px < 0.5:
        return image.copy()
    length_px = min(length_px, math.hypot(*image.shape[:2]))
    return cv2.filter2D(image, -1, motion_blur_kernel(length_px, angle_rad), borderType=cv2.BORDER_REPLICATE)


def sensor_noise(image: np.ndarray, rng: np.random.Generator, read_noise_dn: float = 2.0,
                 shot_noise_gain: float = 0.05) -> np.ndarray:
    """Shot plus read noise, in 8-bit digital numbers (DN).

    variance(I) = read_noise_dn^2 + shot_noise_gain * I (the gaussian
    approximation of Poisson photon noise with gain DN per electron, plus the
    read-out noise), then rounded and clipped to 0..255.
    """
    signal = image.astype(np.float32)
    _add_noise(signal, rng, read_noise_dn, shot_noise_gain)
    return _to_uint8(signal)


def _add_noise(signal: np.ndarray, rng: np.random.Generator, read_noise_dn: float, shot_noise_gain: float) -> None:
    """sensor_noise on an (H, W) float32 signal, in place (before rounding)."""
    # sigma = sqrt(read^2 + gain I)
    sigma = signal * np.float32(shot_noise_gain)
    sigma += np.float32(read_noise_dn) ** 2
    np.sqrt(sigma, out=sigma)
    sigma *= rng.standard_normal(signal.shape, dtype=np.float32)
    signal += sigma


def _to_uint8(signal: np.ndarray) -> np.ndarray:
    """(H, W) uint8: the float32 signal rounded and clipped to 0..255 (in place, then converted)."""
    np.rint(signal, out=signal)
    np.clip(signal, 0, 255, out=signal)
    return signal.astype(np.uint8)


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
        raise DegradationError(f"JPEG encoding failed at quality {quality}")
    return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)


def vignette(image: np.ndarray, strength: float) -> np.ndarray:
    """Darker corners: I * (1 - strength r^2), r = distance from the centre over the half diagonal."""
    return np.clip(np.rint(image * vignette_gain(image.shape, strength)), 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def vignette_gain(shape: tuple[int, int], strength: float) -> np.ndarray:
    """(H, W) float32 read-only: 1 - strength r^2 (see ``vignette``), made once per image size."""
    h, w = shape
    ys, xs = np.ogrid[:h, :w]
    r2 = ((xs - (w - 1) / 2) ** 2 + (ys - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    gain = (1.0 - strength * r2).astype(np.float32)
    gain.flags.writeable = False
    return gain


def exposure_wander_gain(t_s: float, amplitude: float, seed: int) -> float:
    """Slow auto-exposure drift at ``t_s``: exp(amplitude * smooth noise in [-1, 1]), fixed by ``seed``.

    The smooth noise is the mean of three sines with periods of 2-7 s.
    """
    if amplitude <= 0:
        return 1.0
    rng = np.random.default_rng(seed + 7919)
    periods = rng.uniform(2.0, 7.0, 3)
    phases = rng.uniform(0, 2 * np.pi, 3)
    wave = float(np.mean(np.sin(2 * np.pi * t_s / periods + phases)))
    return math.exp(amplitude * wave)


@dataclass(frozen=True)
class Degradations:
    """The image-realism knobs, in the order a camera produces their effects.

    Every default leaves the image as it is (``Degradations()`` changes
    nothing; ``exposure_ms`` matters only with ``motion_blur``). Presets:
    ``companion.sim.simulate.DEFAULT_DEGRADATIONS`` (a realistic camera for
    ``companion simulate``), ``companion.sim.scenes.CONDITIONS`` (the
    detector benchmark's conditions).

    motion_blur: smear by the image motion during the exposure; the caller
        measures it over ``exposure_ms`` and passes it as ``motion_px``.
    exposure_ms: exposure time, milliseconds.
    motion_length_px, motion_angle_rad: a fixed smear instead (length > 0
        forces it, whatever ``motion_blur`` says).
    optics_blur_sigma_px: lens/focus blur, gaussian sigma (0 = off).
    exposure_gain: multiplies the light (1 = unchanged).
    exposure_wander: amplitude of slow auto-exposure changes over time
        (0 = off; 0.3 = the light level varies by about x/÷ 1.35); ``at``
        turns it into the gain of one frame.
    vignette_strength: corner darkening, 0..1 (0 = off).
    read_noise_dn, shot_noise_gain: sensor noise (both 0 = off).
    jpeg_quality: JPEG round trip at this quality, 1..100 (0 = off).
    Each knob is a finite number from 0 to its ``KNOB_LIMITS`` (the angle any finite number).
    """

    motion_blur: bool = False
    exposure_ms: float = 8.0
    motion_length_px: float = 0.0
    motion_angle_rad: float = 0.0
    optics_blur_sigma_px: float = 0.0
    exposure_gain: float = 1.0
    exposure_wander: float = 0.0
    vignette_strength: float = 0.0
    read_noise_dn: float = 0.0
    shot_noise_gain: float = 0.0
    jpeg_quality: int = 0

    def __post_init__(self):
        for name, limit in KNOB_LIMITS.items():
            value = getattr(self, name)
            if not 0 <= value <= limit:  # NaN too
                rule = "0 (off) or 1..100" if name == "jpeg_quality" else f"0..{limit:g}"
                raise DegradationError(f"degradations: {name} must be {rule}, got {value}")
        if not math.isfinite(self.motion_angle_rad):
            raise DegradationError(f"degradations: motion_angle_rad must be a finite number, got {self.motion_angle_rad}")

    def at(self, t_s: float, seed: int) -> "Degradations":
        """The degradations of the frame captured at ``t_s``: the exposure wander (fixed by ``seed``)
        folded into ``exposure_gain``."""
        if self.exposure_wander <= 0:
            return self
        gain = self.exposure_gain * exposure_wander_gain(t_s, self.exposure_wander, seed)
        return replace(self, exposure_gain=gain, exposure_wander=0.0)

    def apply(self, image: np.ndarray, rng: np.random.Generator,
              motion_px: tuple[float, float] | None = None) -> np.ndarray:
        """Degrade an (H, W) uint8 image; ``motion_px``: image motion (dx, dy) over the exposure."""
        if self.exposure_wander > 0:
            raise DegradationError("degradations: exposure_wander changes over time: apply the frame's "
                                   "degradations, at(t_s, seed)")
        out = image
        if self.motion_length_px > 0:
            out = motion_blur(out, self.motion_length_px, self.motion_angle_rad)
        elif self.motion_blur and motion_px is not None:
            out = motion_blur(out, math.hypot(*motion_px), math.atan2(motion_px[1], motion_px[0]))
        if self.optics_blur_sigma_px > 0:
            out = gaussian_blur(out, self.optics_blur_sigma_px)
        noisy = self.read_noise_dn > 0 or self.shot_noise_gain > 0
        if self.exposure_gain != 1.0 or self.vignette_strength > 0 or noisy:
            out = self._expose_and_sense(out, rng, noisy)
        if self.jpeg_quality > 0:
            out = jpeg(out, self.jpeg_quality)
        return out if out is not image else image.copy()

    def _expose_and_sense(self, image: np.ndarray, rng: np.random.Generator, noisy: bool) -> np.ndarray:
        """exposure, vignette and sensor_noise as one float32 signal, rounded once at the end."""
        signal = image.astype(np.float32)
        if self.exposure_gain != 1.0:
            signal *= np.float32(self.exposure_gain)
            np.minimum(signal, 255.0, out=signal)  # bright areas saturate before the lens darkens the corners
        if self.vignette_strength > 0:
            signal *= vignette_gain(image.shape, self.vignette_strength)
        if noisy:
            _add_noise(signal, rng, self.read_noise_dn, self.shot_noise_gain)
        return _to_uint8(signal)

    def with_(self, **changes) -> "Degradations":
        return replace(self, **changes)
