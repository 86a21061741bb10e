"""Blink share: how much of a signal's recent change is periodic at a blink's period.

The resonators of :mod:`model.lamp_evidence` read how strongly a lamp's per-frame P(lit)
swings at each blink period; that amplitude depends on how sure the per-frame judge is,
which differs between cameras and renderers (a faint lamp swings P(lit) between 0.1 and
0.3 where a clear one swings it between 0 and 1). The share of the signal's power over the
last :data:`WINDOW` frames that lies at blink periods does not: a flash is periodic
however faint, a steady lamp, box jitter or passing light is not.

Per track the window of the last frames is state (:func:`push`, a new track's window holds
its first value, so its onset is no flash), and the share is one small matrix product
and a mask over its frequency bins (:func:`basis`, :func:`share`): the window's
straight-line trend removed, a Hann taper and the Fourier sums at every frequency, all
folded into one fixed matrix, so ONNX exports it as it is.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np
import torch
from torch import Tensor

from signal_light_node.model.lamp_evidence import PERIODS

#: Frames in the window (about 1.6-4.8 s at 10-30 frames/s: at least one whole blink).
WINDOW = 48
#: Added to the window's power before the share is taken: a steady signal's share is 0
#: rather than that of its rounding noise.
SHARE_FLOOR = 1e-3


def basis(window: int = WINDOW, periods: Tuple[float, float] = (PERIODS[0], PERIODS[-1])
          ) -> Tuple[Tensor, Tensor]:
    """The map ``[W, 2T]`` from a window (oldest frame first) to the real, then the
    imaginary Fourier sums at its ``T`` non-zero bins after the trend and the taper, and
    the mask ``[T]`` (1.0 or 0.0) of the bins whose period in frames lies in ``periods``."""
    t = np.arange(window, dtype=np.float64)
    trend = np.stack((np.ones(window), t), 1)
    detrend = np.eye(window) - trend @ np.linalg.pinv(trend)
    bins = np.arange(1, window // 2 + 1)  # cycles per window
    phase = 2.0 * math.pi * np.outer(t, bins) / window  # [W, T]
    waves = np.concatenate((np.cos(phase), np.sin(phase)), 1) * np.hanning(window)[:, None]
    low, high = periods
    band = (window / bins >= low) & (window / bins <= high)
    return (torch.from_numpy((detrend.T @ waves).astype(np.float32)),
            torch.from_numpy(band.astype(np.float32)))


def push(window: Tensor, signals: Tensor, seen: Tensor) -> Tensor:
    """Windows ``[N, S, W]`` with this frame's ``[N, S]`` signals shifted in; where ``seen``
    ``[N, 1]`` is 0 (a new track) the whole window is this frame's signal."""
    seen = seen.unsqueeze(-1)
    shifted = torch.cat((window[..., 1:], signals.unsqueeze(-1)), -1)
    return shifted * seen + signals.unsqueeze(-1).expand_as(window) * (1.0 - seen)


def share(window: Tensor, fourier: Tensor, band: Tensor, floor: float = SHARE_FLOOR) -> Tensor:
    """``[N, S]`` share in [0, 1) of each window's power (after trend and taper) at blink
    periods, from :func:`basis`'s map and mask."""
    real, imaginary = (window @ fourier).chunk(2, -1)
    power = real.pow(2) + imaginary.pow(2)  # per bin
    return (power @ band) / (power.sum(-1) + floor)
