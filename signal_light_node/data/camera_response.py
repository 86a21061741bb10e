"""Randomised camera response for training crops (domain randomisation on the crop).

The renderer draws with one camera model; a real camera, or another renderer, differs in
tone curve, colour saturation, clipping of bright lamps, noise, sharpness, resolution and
compression. :func:`randomise_camera` draws one such response per sequence (a camera's
settings change slowly) and applies it to every frame, with fresh noise per frame, so the
model cannot learn one look of lamps. It acts on uint8 crops with a LUT, one colour
transform and small OpenCV calls: a few milliseconds for a 150-frame track.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import cv2
import numpy as np


@dataclass(frozen=True)
class CameraResponse:
    """One camera's response, drawn by :meth:`draw`.

    Attributes:
        gain: Exposure gain before clipping (> 1 saturates bright lamps).
        gamma: Tone-curve exponent.
        saturation: Colour saturation factor (0 grey .. >1 vivid).
        noise: Sensor noise sigma in grey levels.
        blur: Gaussian blur sigma in crop pixels (0: sharp).
        scale: Resolution factor (< 1: the crop is seen through fewer pixels).
        jpeg_quality: JPEG quality of each frame, 0 for none.
        white_balance: Gains on the B, G and R channels before the colour transform (a
            camera's white balance and tint; (1, 1, 1) leaves the colours as rendered).
    """

    gain: float
    gamma: float
    saturation: float
    noise: float
    blur: float
    scale: float
    jpeg_quality: int
    white_balance: Tuple[float, float, float] = (1.0, 1.0, 1.0)

    @classmethod
    def draw(cls, rng: np.random.Generator, white_balance: float = 0.0) -> "CameraResponse":
        """A random response; about a third of the draws keep each effect off.

        Args:
            rng: Source of the draws.
            white_balance: Each channel's gain is drawn log-uniform in
                ``[exp(-white_balance), exp(white_balance)]``; 0 keeps (1, 1, 1) and draws
                nothing for it, so the other fields come out as without it.
        """
        gains = (1.0, 1.0, 1.0)
        if white_balance > 0:
            gains = tuple(float(g) for g in np.exp(rng.uniform(-white_balance, white_balance, 3)))
        return cls(white_balance=gains, gain=float(np.exp(rng.uniform(np.log(0.7), np.log(1.8)))),
                   gamma=float(np.exp(rng.uniform(np.log(0.7), np.log(1.4)))),
                   saturation=float(rng.uniform(0.5, 1.5)),
                   noise=float(rng.uniform(0.0, 8.0) if rng.random() < 0.7 else 0.0),
                   blur=float(rng.uniform(0.3, 1.2) if rng.random() < 0.35 else 0.0),
                   scale=float(rng.uniform(0.35, 1.0) if rng.random() < 0.4 else 1.0),
                   jpeg_quality=int(rng.integers(25, 90) if rng.random() < 0.5 else 0))


def _tone_lut(gain: float, gamma: float) -> np.ndarray:
    x = np.arange(256, dtype=np.float32) / 255.0
    return np.clip(255.0 * np.clip(x * gain, 0.0, 1.0) ** gamma, 0, 255).astype(np.uint8)


#: Luma weights of the B, G, R channels (ITU-R BT.601).
LUMA_BGR = np.array([0.114, 0.587, 0.299], np.float32)


def _colour_matrix(saturation: float, white_balance: Tuple[float, float, float]) -> np.ndarray:
    # Channel gains first (the sensor's white balance), then each channel mixed with the
    # luma (BGR weights): saturation 1 keeps, 0 greys out.
    mix = saturation * np.eye(3, dtype=np.float32) + (1.0 - saturation) * np.tile(LUMA_BGR, (3, 1))
    return (mix @ np.diag(np.asarray(white_balance, np.float32))).astype(np.float32)


def apply_camera(crops: np.ndarray, response: CameraResponse,
                 rng: np.random.Generator) -> np.ndarray:
    """Apply ``response`` to uint8 ``[T, S, S, 3]`` BGR crops (new array, same shape)."""
    if crops.size == 0:
        return crops.copy()
    t, size = crops.shape[0], crops.shape[1]
    flat = crops.reshape(t * size, size, 3)
    out = cv2.transform(flat, _colour_matrix(response.saturation, response.white_balance))
    out = cv2.LUT(out, _tone_lut(response.gain, response.gamma))
    if response.noise > 0:
        noise = rng.normal(0.0, response.noise, out.shape).astype(np.float32)
        out = np.clip(out.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    out = out.reshape(t, size, size, 3)
    small = max(8, int(round(size * response.scale)))
    frames = []
    for frame in out:
        if response.blur > 0:
            frame = cv2.GaussianBlur(frame, (0, 0), response.blur)
        if small < size:
            frame = cv2.resize(cv2.resize(frame, (small, small), interpolation=cv2.INTER_AREA),
                               (size, size), interpolation=cv2.INTER_LINEAR)
        if response.jpeg_quality:
            ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY,
                                                   response.jpeg_quality])
            if ok:
                frame = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        frames.append(frame)
    return np.stack(frames)


def randomise_camera(crops: np.ndarray, rng: np.random.Generator,
                     white_balance: float = 0.0) -> np.ndarray:
    """One random :class:`CameraResponse` (:meth:`CameraResponse.draw`'s ``white_balance``)
    applied to a whole sequence of crops."""
    return apply_camera(crops, CameraResponse.draw(rng, white_balance), rng)
