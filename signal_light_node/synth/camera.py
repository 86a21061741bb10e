"""Camera effects applied to the finished scene: exposure, haze, vignetting, clipped light
turned white, a round bloom and a horizontal glare streak of over-exposed light, blur,
motion blur, sensor noise and JPEG artefacts.

All per-frame work is on ``uint8`` images with OpenCV calls (saturating adds, LUTs, small
kernels); the expensive parts (noise fields, haze/vignette images) are made once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np


@dataclass
class CameraParams:
    """Random camera behaviour for one renderer (all in image units).

    Attributes:
        noise: Sensor noise sigma (grey levels).
        blur: Gaussian blur sigma (0 = sharp).
        motion_blur: Maximum motion-blur length in pixels (0 = none).
        motion_prob: Fraction of frames with motion blur.
        jpeg_quality: JPEG quality, or 0 for no compression.
        exposure: Base exposure gain.
        exposure_drift: Amplitude of slow exposure changes.
        exposure_jump: Probability per second of an auto-exposure jump.
        gamma: Tone curve exponent.
        vignette: Darkening at the corners (0..1).
        haze: Strength of haze near the horizon (0..1).
        haze_colour: BGR colour of the haze.
        shake: Camera shake amplitude in pixels.
        bloom: Gain of the round bloom that over-exposed light spreads around itself (a
            lens's and a sensor's veiling glare; 0 = none): the more of a lamp is clipped,
            the wider and brighter its halo.
        bloom_sigma: Width (Gaussian sigma) of that bloom as a share of the image width.
        streak: Gain of the horizontal glare streak that over-exposed light smears along
            its row (a windscreen's or a lens's; 0 = none).
        streak_len: Length of that streak as a share of the image width.
        white_clip: How far light over ``_WHITE_FLOOR`` (after the tone curve) turns white,
            0..1 (0 = not at all): a saturated lamp clips in every channel at once, so its
            core shows white and only its fringe keeps the lamp's colour.
    """

    noise: float = 2.0
    blur: float = 0.0
    motion_blur: float = 0.0
    motion_prob: float = 0.0
    jpeg_quality: int = 0
    exposure: float = 1.0
    exposure_drift: float = 0.0
    exposure_jump: float = 0.0
    gamma: float = 1.0
    vignette: float = 0.0
    haze: float = 0.0
    haze_colour: tuple = (200, 200, 200)
    shake: float = 0.0
    bloom: float = 0.0
    bloom_sigma: float = 0.0
    streak: float = 0.0
    streak_len: float = 0.0
    white_clip: float = 0.0


#: Range of :attr:`CameraParams.streak`, and of ``streak_len`` (share of the width).
STREAK_GAIN = (2.0, 8.0)
STREAK_LEN = (1 / 30, 1 / 8)
#: Level (after the tone curve) above which a pixel counts as over-exposed for the streak
#: and the bloom.
_STREAK_FLOOR = 200
#: Range of :attr:`CameraParams.bloom`, and of ``bloom_sigma`` (share of the width).
BLOOM_GAIN = (10.0, 60.0)
BLOOM_SIGMA = (1 / 100, 1 / 30)
#: Range of the exposure factor of a night camera that exposes for a lit street (its lamps
#: saturate), and of its :attr:`CameraParams.white_clip`.
NIGHT_GAIN = (1.8, 3.2)
WHITE_CLIP = (0.4, 0.9)
#: Brightest channel (after the tone curve) from which light starts to turn white; at 255
#: it has moved ``white_clip`` of the way.
_WHITE_FLOOR = 230


def sample_streak(rng: np.random.Generator) -> "tuple[float, float]":
    """A glare streak's gain and length (share of the width)."""
    return float(rng.uniform(*STREAK_GAIN)), float(rng.uniform(*STREAK_LEN))


def sample_bloom(rng: np.random.Generator) -> "tuple[float, float]":
    """A bloom's gain and width (Gaussian sigma, share of the width)."""
    return float(rng.uniform(*BLOOM_GAIN)), float(rng.uniform(*BLOOM_SIGMA))


def sample_night_clip(rng: np.random.Generator) -> "tuple[float, float]":
    """A bright night camera's exposure factor and :attr:`CameraParams.white_clip`."""
    return float(rng.uniform(*NIGHT_GAIN)), float(rng.uniform(*WHITE_CLIP))


#: Tone-curve exponent and exposure ranges per style family (``synth.lamps.STYLE_FAMILIES``).
_GAMMA = {0: (0.8, 1.0), 1: (1.0, 1.2), 2: (1.25, 1.5)}
_EXPOSURE = {0: (0.85, 1.05), 1: (1.0, 1.2), 2: (1.2, 1.45)}


def sample_camera(rng: np.random.Generator, lighting_noise: float, lighting: str, weather: str,
                  family: int = 0) -> CameraParams:
    """Random camera parameters; noise grows in the dark, haze appears with haze or rain;
    ``family`` picks the ranges of the tone curve and the exposure."""
    haze = 0.0
    if weather == "haze":
        haze = rng.uniform(0.25, 0.55)
    elif weather == "rain":
        haze = rng.uniform(0.1, 0.3)
    elif rng.random() < 0.3:
        haze = rng.uniform(0.03, 0.15)
    g = {"day": rng.uniform(185, 230), "dusk": rng.uniform(90, 150), "night": rng.uniform(25, 55)}[lighting]
    return CameraParams(
        noise=lighting_noise * rng.uniform(0.6, 1.3),
        blur=float(rng.choice([0.0, 0.0, rng.uniform(0.4, 1.2)])),
        motion_blur=float(rng.uniform(2, 7)) if rng.random() < 0.45 else 0.0,
        motion_prob=float(rng.uniform(0.1, 0.5)),
        jpeg_quality=int(rng.integers(35, 92)) if rng.random() < 0.7 else 0,
        exposure=float(rng.uniform(*_EXPOSURE[family])),
        exposure_drift=float(rng.uniform(0.0, 0.15)),
        exposure_jump=float(rng.uniform(0.0, 0.15)),
        gamma=float(rng.uniform(*_GAMMA[family])),
        vignette=float(rng.uniform(0.0, 0.35)),
        haze=float(haze),
        haze_colour=(g * rng.uniform(0.95, 1.08), g, g * rng.uniform(0.92, 1.04)),
        shake=float(rng.choice([0.0, rng.uniform(0.5, 4.0)])),
    )


class Camera:
    """Applies ``CameraParams`` to rendered frames.

    Args:
        params: The camera behaviour.
        width: Image width.
        height: Image height.
        horizon: Horizon row (haze is strongest there).
        seed: Seed for the fixed noise fields and the exposure schedule.
        enabled: False turns every effect off (clean images for tests).
    """

    _POOL = 1
    _PAD = 16

    def __init__(self, params: CameraParams, width: int, height: int, horizon: float, seed: int, enabled: bool = True) -> None:
        self.p = params
        self.enabled = enabled
        self.width, self.height = width, height
        rng = np.random.default_rng(seed)
        self._rng = rng
        # Noise fields: signed noise split into a positive and a negative uint8 part.
        self._noise = []
        if params.noise > 0.2:
            for _ in range(self._POOL):
                n = rng.standard_normal((height + self._PAD, width + self._PAD, 3), dtype=np.float32)
                n += 0.5 * rng.standard_normal((height + self._PAD, width + self._PAD, 1), dtype=np.float32)  # luma part
                n *= params.noise
                self._noise.append((cv2.convertScaleAbs(np.maximum(n, 0)), cv2.convertScaleAbs(np.minimum(n, 0))))
        # Haze and vignette: out = img * mult / 255 + add.
        self._use_mult = params.haze > 0.005 or params.vignette > 0.02
        if self._use_mult:
            ys = np.arange(height, dtype=np.float32)[:, None]
            xs = np.arange(width, dtype=np.float32)[None, :]
            haze = np.clip(params.haze * np.exp(-np.abs(ys - horizon) / (0.35 * height)) + params.haze * 0.3, 0, 0.9)
            r2 = ((xs - width / 2) / (width / 2)) ** 2 + ((ys - height / 2) / (height / 2)) ** 2
            mult = cv2.convertScaleAbs((1.0 - haze) * (1.0 - params.vignette * np.minimum(r2 * 0.5, 1.0)), alpha=255.0)
            self._mult = cv2.merge([mult, mult, mult])
            add = (haze * np.asarray(params.haze_colour, np.float32)[None, :]).astype(np.uint8)  # (H, 3)
            self._add = cv2.resize(add[:, None, :], (width, height), interpolation=cv2.INTER_NEAREST)
        # Exposure: a slow drift plus occasional jumps (auto-exposure reacting to the scene).
        self._drift_f = rng.uniform(0.05, 0.3)
        self._drift_ph = rng.uniform(0, 2 * np.pi)
        self._jumps = np.sort(rng.uniform(0, 600, rng.poisson(params.exposure_jump * 600)))
        self._jump_vals = rng.uniform(-0.2, 0.2, len(self._jumps))
        self._last_lut_key = None
        self._lut = None

    def exposure(self, t: float) -> float:
        """Exposure gain at time ``t``."""
        g = self.p.exposure * (1.0 + self.p.exposure_drift * math.sin(2 * math.pi * self._drift_f * t + self._drift_ph))
        k = int(np.searchsorted(self._jumps, t % 600.0))
        if k > 0:
            g *= 1.0 + self._jump_vals[k - 1]
        return g

    def apply(self, img: np.ndarray, t: float, frame_rng: np.random.Generator) -> np.ndarray:
        """Return the camera's view of the scene ``img`` at time ``t``."""
        if not self.enabled:
            return img
        p = self.p
        if self._use_mult:
            img = cv2.multiply(img, self._mult, scale=1.0 / 255.0)
            img = cv2.add(img, self._add)
        gain = round(self.exposure(t), 2)
        key = (gain, p.gamma)
        if key != self._last_lut_key:
            x = np.arange(256, dtype=np.float32) / 255.0
            self._lut = np.clip(255.0 * (x * gain) ** p.gamma, 0, 255).astype(np.uint8)
            self._last_lut_key = key
        img = cv2.LUT(img, self._lut)
        if p.white_clip > 0:
            img = self._whiten(img)
        if p.bloom > 0 and p.bloom_sigma > 0:
            img = self._bloom(img)
        if p.streak > 0 and p.streak_len > 0:
            img = self._streak(img)
        if p.motion_blur > 0 and frame_rng.random() < p.motion_prob:
            n = int(frame_rng.uniform(2, p.motion_blur + 1))
            if n >= 2:
                k = np.zeros((n, n), np.float32)
                ang = frame_rng.uniform(0, np.pi)
                c = (n - 1) / 2
                cv2.line(k, (int(round(c - c * math.cos(ang))), int(round(c - c * math.sin(ang)))),
                         (int(round(c + c * math.cos(ang))), int(round(c + c * math.sin(ang)))), 1.0, 1)
                img = cv2.filter2D(img, -1, k / max(k.sum(), 1e-6))
        if p.blur > 0.05:
            img = cv2.GaussianBlur(img, (0, 0), p.blur)
        if self._noise:
            pos, neg = self._noise[int(frame_rng.integers(0, self._POOL))]
            ox, oy = int(frame_rng.integers(0, self._PAD)), int(frame_rng.integers(0, self._PAD))
            img = cv2.add(img, pos[oy:oy + self.height, ox:ox + self.width])
            img = cv2.subtract(img, neg[oy:oy + self.height, ox:ox + self.width])
        if p.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(p.jpeg_quality)])
            if ok:
                img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return img

    def _whiten(self, img: np.ndarray) -> np.ndarray:
        """Move each pixel whose brightest channel is over ``_WHITE_FLOOR`` towards white, by
        ``white_clip`` times how far over it is (only those pixels are touched)."""
        top = img.max(axis=2)
        ys, xs = np.nonzero(top > _WHITE_FLOOR)
        if not len(ys):
            return img
        share = (top[ys, xs].astype(np.float32) - _WHITE_FLOOR) * (
            self.p.white_clip / (255.0 - _WHITE_FLOOR))
        px = img[ys, xs].astype(np.float32)
        out = img.copy()
        out[ys, xs] = np.round(px + share[:, None] * (255.0 - px)).astype(np.uint8)
        return out

    @staticmethod
    def _spread_hot(img: np.ndarray, spread: Callable[[np.ndarray], np.ndarray],
                    gain: float) -> np.ndarray:
        """The part of ``img`` above ``_STREAK_FLOOR``, spread by ``spread`` and added back
        with ``gain`` (saturating, in uint8): what over-exposed light does to its surround."""
        hot = cv2.subtract(img, (_STREAK_FLOOR,) * 3 + (0,))
        return cv2.add(img, cv2.convertScaleAbs(spread(hot), alpha=gain))

    def _bloom(self, img: np.ndarray) -> np.ndarray:
        """Spread what is over-exposed around itself, a Gaussian of ``bloom_sigma``."""
        sigma = self.p.bloom_sigma * self.width
        return self._spread_hot(img, lambda hot: cv2.GaussianBlur(
            hot, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT), self.p.bloom)

    def _streak(self, img: np.ndarray) -> np.ndarray:
        """Smear what is over-exposed along its row, a box of ``streak_len``."""
        length = max(3, int(round(self.p.streak_len * self.width)) | 1)
        return self._spread_hot(img, lambda hot: cv2.blur(
            hot, (length, 1), borderType=cv2.BORDER_CONSTANT), self.p.streak)
