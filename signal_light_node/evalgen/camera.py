"""Camera of the evaluation generator: a pitched, rolled pinhole with radial distortion,
and a sensor model that develops a linear HDR radiance buffer into an 8-bit BGR image.

World frame: X to the right of the ego lane, Y up, Z forward along the road; the camera
sits at ``(0, mount_height, ego_z)``. Radiance is linear, in arbitrary units where a white
surface under the day sun is about 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Tuple

import cv2
import numpy as np

from signal_light_node.errors import ConfigError

#: Closest camera depth (m) a projected point may have; nearer geometry is not drawn.
NEAR_M = 0.5


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics and mounting of the camera.

    Attributes:
        width: Image width in pixels.
        height: Image height in pixels.
        hfov_deg: Horizontal field of view.
        mount_height: Height of the optical centre above the road (m).
        pitch: Downward tilt (rad).
        roll: Roll about the optical axis (rad).
        k1: Radial distortion coefficient (negative: barrel).
    """

    width: int
    height: int
    hfov_deg: float
    mount_height: float
    pitch: float
    roll: float
    k1: float

    def __post_init__(self) -> None:
        if self.width < 32 or self.height < 32:
            raise ConfigError(f"image must be at least 32x32, got {self.width}x{self.height}")
        if not 20.0 <= self.hfov_deg <= 120.0:
            raise ConfigError(f"hfov_deg must be in 20..120, got {self.hfov_deg}")

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2.0)

    def to_camera(self, pts: np.ndarray, ego_z: float, sway: float = 0.0) -> np.ndarray:
        """World points ``[N, 3]`` to camera coordinates ``[N, 3]`` (x right, y up, z depth).

        Args:
            pts: World points.
            ego_z: Camera position along the road.
            sway: Extra pitch (rad) from the ride (bumps, braking).
        """
        rel = np.asarray(pts, dtype=np.float64) - np.array([0.0, self.mount_height, ego_z])
        p = self.pitch + sway
        fwd = np.array([0.0, -math.sin(p), math.cos(p)])
        up = np.array([0.0, math.cos(p), math.sin(p)])
        xc, yc, zc = rel[:, 0], rel @ up, rel @ fwd
        c, s = math.cos(self.roll), math.sin(self.roll)
        return np.stack([c * xc - s * yc, s * xc + c * yc, zc], axis=1)

    def project(self, pts: np.ndarray, ego_z: float, sway: float = 0.0
                ) -> Tuple[np.ndarray, np.ndarray]:
        """Project world points to distorted pixel coordinates.

        Args:
            pts: World points ``[N, 3]``.
            ego_z: Camera position along the road.
            sway: Extra pitch (rad).

        Returns:
            ``(uv [N, 2] float, depth [N])``; points nearer than ``NEAR_M`` get depth < NEAR_M
            and meaningless pixels, so callers drop them.
        """
        cam = self.to_camera(pts, ego_z, sway)
        z = np.maximum(cam[:, 2], 1e-3)
        xn, yn = cam[:, 0] / z, cam[:, 1] / z
        # the polynomial only holds inside the field of view; beyond it the mapping goes linear
        r2_max = (1.3 * (1.0 + (self.height / self.width) ** 2)
                  * (self.width / 2.0 / self.focal) ** 2)
        d = 1.0 + self.k1 * np.minimum(xn * xn + yn * yn, r2_max)
        f = self.focal
        uv = np.stack([self.width / 2.0 + f * xn * d, self.height / 2.0 - f * yn * d], axis=1)
        return uv, cam[:, 2]



@dataclass(frozen=True)
class FrameView:
    """The camera in one frame: where the ego car is along the road and how its ride
    pitches the camera.

    Attributes:
        camera: The camera.
        ego_z: Camera position along the road (m).
        sway: Extra pitch from the ride (rad).
    """

    camera: PinholeCamera
    ego_z: float
    sway: float

    def project(self, pts: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """``PinholeCamera.project`` in this frame: ``(uv [N, 2], depth [N])``."""
        return self.camera.project(pts, self.ego_z, self.sway)

    @property
    def position(self) -> np.ndarray:
        """The optical centre in world coordinates."""
        return np.array([0.0, self.camera.mount_height, self.ego_z])

def sample_camera(rng: np.random.Generator, width: int, height: int) -> PinholeCamera:
    """A random dash-cam-like camera."""
    return PinholeCamera(width=int(width), height=int(height),
                         hfov_deg=float(rng.uniform(52.0, 72.0)),
                         mount_height=float(rng.uniform(1.15, 1.65)),
                         pitch=float(rng.uniform(0.01, 0.05)),
                         roll=float(rng.uniform(-0.012, 0.012)),
                         k1=float(rng.uniform(-0.09, -0.02)))


@dataclass(frozen=True)
class Sensor:
    """Exposure, optics and noise of the sensor.

    Attributes:
        exposure: Multiplier from radiance to sensor signal before the tone curve.
        bloom_gain: Weight of the multi-scale bloom of over-exposed light.
        streak_gain: Weight of the horizontal (anamorphic) glare streak.
        crosstalk: Share of each colour channel that leaks into the others.
        shot_noise: Shot-noise scale (std = sqrt(shot_noise * signal)).
        read_noise: Signal-independent noise std.
        vignette: Strength of the radial fall-off at the corners (0..1).
        aberration: Relative scale of the red channel against blue (lateral CA).
        exposure_s: Shutter time (s), over which lamp levels are integrated.
        denoise: Sigma (pixels) of the ISP's spatial noise reduction.
    """

    exposure: float
    bloom_gain: float
    streak_gain: float
    crosstalk: float
    shot_noise: float
    read_noise: float
    vignette: float
    aberration: float
    exposure_s: float
    denoise: float = 0.6


def sample_sensor(rng: np.random.Generator, night: bool) -> Sensor:
    """Sensor settings for day or night."""
    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    if night:
        return Sensor(exposure=u(5.0, 8.0), bloom_gain=u(0.35, 0.6), streak_gain=u(0.04, 0.12),
                      crosstalk=u(0.05, 0.09), shot_noise=u(0.0015, 0.003),
                      read_noise=u(0.0012, 0.002), vignette=u(0.25, 0.45),
                      aberration=u(0.001, 0.003), exposure_s=u(1 / 40, 1 / 20), denoise=0.9)
    return Sensor(exposure=u(1.3, 1.8), bloom_gain=u(0.08, 0.16), streak_gain=0.0,
                  crosstalk=u(0.03, 0.06), shot_noise=u(0.0004, 0.001), read_noise=u(0.001, 0.002),
                  vignette=u(0.15, 0.3), aberration=u(0.0005, 0.0015),
                  exposure_s=u(1 / 500, 1 / 120))


def _bloom(signal: np.ndarray, levels: int = 5) -> np.ndarray:
    """Sum of Gaussian-pyramid blurs of the over-exposed part of ``signal``."""
    bright = np.maximum(signal - 0.9, 0.0)
    h, w = bright.shape[:2]
    acc = np.zeros_like(bright)
    level = bright
    for i in range(levels):
        level = cv2.pyrDown(level)
        up = level
        for _ in range(i + 1):
            up = cv2.pyrUp(up)
        acc += cv2.resize(up, (w, h), interpolation=cv2.INTER_LINEAR) * (0.6 ** i)
    return acc


def _vignette_map(width: int, height: int, strength: float) -> np.ndarray:
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = ((xs - width / 2) / (width / 2)) ** 2 + ((ys - height / 2) / (width / 2)) ** 2
    return (1.0 - strength * np.clip(r2, 0.0, 1.5) / 1.5).astype(np.float32)[..., None]


def develop(radiance: np.ndarray, sensor: Sensor, rng: np.random.Generator) -> np.ndarray:
    """Turn a linear radiance buffer into an 8-bit BGR image.

    Steps: exposure, colour crosstalk, bloom and glare streak of over-exposed light,
    vignetting, lateral chromatic aberration, shot and read noise, an exponential
    (film-like) tone curve and a 2.2 display gamma.

    Args:
        radiance: ``float32 [H, W, 3]`` BGR radiance.
        sensor: The sensor settings.
        rng: Noise source.

    Returns:
        ``uint8 [H, W, 3]`` BGR.
    """
    h, w = radiance.shape[:2]
    sig = radiance * np.float32(sensor.exposure)
    k = sensor.crosstalk
    mix = np.full((3, 3), k, dtype=np.float32) + np.eye(3, dtype=np.float32) * (1.0 - 3 * k)
    sig = cv2.transform(sig, mix)
    sig += _bloom(sig) * np.float32(sensor.bloom_gain)
    if sensor.streak_gain > 0:
        hot = np.maximum(sig - 2.0, 0.0)
        sig += cv2.blur(hot, (max(3, w // 12) | 1, 1)) * np.float32(sensor.streak_gain * 4.0)
    sig *= _vignette_map(w, h, sensor.vignette)
    s = 1.0 + sensor.aberration
    red = np.float32([[s, 0, (1 - s) * w / 2], [0, s, (1 - s) * h / 2]])
    sig[..., 2] = cv2.warpAffine(sig[..., 2], red, (w, h), borderMode=cv2.BORDER_REPLICATE)
    std = np.sqrt(np.clip(sig, 0.0, 4.0) * np.float32(sensor.shot_noise)
                  + np.float32(sensor.read_noise ** 2))
    sig += rng.standard_normal(sig.shape, dtype=np.float32) * std
    sig = cv2.GaussianBlur(sig, (3, 3), sensor.denoise)  # the ISP's spatial noise reduction
    toned = 1.0 - np.exp(-np.maximum(sig, 0.0))
    out = np.power(toned, np.float32(1.0 / 2.2)) * 255.0 + 0.5
    return np.clip(out, 0, 255).astype(np.uint8)
