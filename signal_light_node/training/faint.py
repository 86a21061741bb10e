"""Faint flashes: training windows whose changes over time are shrunk towards their mean.

On the held-out style family the per-frame stage's P(lit) still swings with a blink, but
less far than on the training renderer's own styles (docs/model.md, "Where the family's
day blinkers are lost"): a temporal part that learnt "a blink is a large swing" misses
them. This augmentation draws, for a share of the windows of a batch, a factor ``a`` in
``[low, 1]`` and replaces every cached per-frame input ``x_t`` (trunk features and lamp
maps) by ``mean + a * (x_t - mean)``, the mean taken per channel and cell over the
window's real frames. A steady lamp stays steady, a flash keeps its rhythm and loses
its size; the labels are kept, so a faint flash must still be called a blink.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import numpy as np
import torch

from signal_light_node.errors import ConfigError

#: The per-frame inputs of a cached window that are shrunk.
SHRUNK_KEYS = ("features", "maps")


@dataclass(frozen=True)
class FaintFlashes:
    """How often and how far windows are made faint.

    Attributes:
        share: Probability that a window is shrunk (0: never).
        low: Smallest factor drawn; factors are uniform in ``[low, 1]``.
    """

    share: float = 0.0
    low: float = 0.3

    def __post_init__(self) -> None:
        if not 0.0 <= self.share <= 1.0:
            raise ConfigError(f"faint share must be in [0, 1], got {self.share}")
        if not 0.0 <= self.low <= 1.0:
            raise ConfigError(f"faint low must be in [0, 1], got {self.low}")

    @property
    def active(self) -> bool:
        """Whether any window can be shrunk."""
        return self.share > 0.0 and self.low < 1.0


def window_factors(n: int, faint: FaintFlashes, rng: np.random.Generator) -> np.ndarray:
    """One factor per window: 1 for windows left alone, uniform in ``[low, 1]`` for the
    ``share`` that are shrunk."""
    shrunk = rng.random(n) < faint.share
    drawn = rng.uniform(faint.low, 1.0, n)
    return np.where(shrunk, drawn, 1.0).astype(np.float32)


def shrink_window_changes(batch: Dict[str, torch.Tensor], factors: np.ndarray
                          ) -> Dict[str, torch.Tensor]:
    """A copy of ``batch`` (``collate_windows``'s layout) whose per-frame inputs are moved
    towards each window's mean over its real frames by ``factors`` (``[B]``, 1 = as
    drawn); the padding stays zero and every other entry is shared."""
    mask = batch["mask"].float()  # [B, T]
    count = mask.sum(1).clamp(min=1.0)
    out = dict(batch)
    for key in SHRUNK_KEYS:
        x = batch[key]
        per_window = (x.shape[0], 1) + (1,) * (x.dim() - 2)  # broadcast over time and cells
        m = mask.view((x.shape[0], x.shape[1]) + per_window[2:])
        mean = (x * m).sum(1, keepdim=True) / count.view(per_window)
        a = torch.from_numpy(factors).to(x).view(per_window)
        out[key] = (mean + a * (x - mean)) * m
    return out


def faint_batch(batch: Dict[str, torch.Tensor], faint: FaintFlashes,
                rng: np.random.Generator) -> Dict[str, torch.Tensor]:
    """``batch`` with :func:`window_factors` applied (unchanged, and ``rng`` untouched, when
    ``faint`` is inactive, so that a run without it draws as before)."""
    if not faint.active:
        return batch
    return shrink_window_changes(batch, window_factors(batch["mask"].shape[0], faint, rng))
