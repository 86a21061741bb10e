"""Temporal evidence: what changed in a track's crop, as extra input channels.

A blinker is a lamp that flashes; a tail lamp, a head lamp or a reflection is bright but
steady. One crop cannot tell them apart, the track's recent crops can. Per track the
model keeps the previous crop and a running mean of its crops (an exponential moving
average), both in the coordinates of the last frame. Each step

1. estimates the integer shift between the previous and the current crop (tracker
   boxes jitter by a few pixels) by trying every shift within ``radius`` pixels on the
   grey images and keeping the one with the smallest mean absolute difference (no
   shift on a tie),
2. shifts the previous crop and the running mean by it,
3. returns two difference images: current minus previous (a lamp switching on or off
   right now) and current minus the running mean (a region that departs from how the
   track usually looks: positive in a blink's lit half, negative in its dark half, near
   zero for a steady lamp whatever its brightness),
4. updates the running mean with the current crop.

A track's first frame has no history: its differences are zero. Everything is batched
tensor work (slices, a gather), so training unrolls it over sequences on any device.
"""

from __future__ import annotations

from typing import Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

#: Channels the evidence adds to the model input: 3 for the frame difference, 3 for
#: the difference from the running mean.
EVIDENCE_CHANNELS = 6


def best_shifts(reference: Tensor, current: Tensor, radius: int) -> Tensor:
    """Per-row integer shift that best aligns ``reference`` to ``current``.

    Args:
        reference: ``[N, C, S, S]`` earlier crops.
        current: ``[N, C, S, S]`` current crops.
        radius: Largest shift tried in each direction, in pixels.

    Returns:
        int64 ``[N, 2]`` offsets ``(oy, ox)`` in ``0..2*radius`` into the reference padded
        by ``radius`` (``radius, radius`` is no shift).
    """
    n, _, size, _ = current.shape
    r = int(radius)
    if r == 0:
        return current.new_zeros((n, 2), dtype=torch.long)
    # No shift first: argmin returns the first of equal scores, so ties (flat crops)
    # keep the crop where it is.
    candidates = [(0, 0)] + [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)
                             if (dy, dx) != (0, 0)]
    inner = size - 2 * r
    # Scores are sums of whole numbers of at most 765: exact in float32 (fast) while they
    # stay below 2**24, else in float64.
    dtype = torch.float32 if ((inner + 1) // 2) ** 2 * 765 < 2 ** 24 else torch.float64
    with torch.no_grad():
        # Every other row and column of the grey images: a quarter of the work, the same
        # one-pixel precision of the shift.
        cur = _grey_levels(current, dtype)[..., r:size - r:2, r:size - r:2]
        pad = F.pad(_grey_levels(reference, dtype), (r, r, r, r), mode="replicate")
        # Current row y (inner: y >= r) against reference row y + dy = padded row y + r + dy.
        scores = torch.stack([(pad[..., r + dy + r:r + dy + r + inner:2,
                                   r + dx + r:r + dx + r + inner:2] - cur)
                              .abs().sum(dim=(1, 2, 3))
                              for dy, dx in candidates], 1)
        best = scores.argmin(1)
    offsets = torch.tensor([(dy + r, dx + r) for dy, dx in candidates], dtype=torch.long,
                           device=current.device)
    return offsets.index_select(0, best)


def _grey_levels(images: Tensor, dtype: torch.dtype) -> Tensor:
    """``[N, 1, H, W]``: the sum of the three channels in steps of 1/255, rounded.

    Whole numbers, so the alignment scores are exact sums: the shift chosen cannot
    depend on the order a framework adds them in (torch and onnxruntime, CPU and CUDA
    pick the same one). Crops cut from uint8 images lose nothing by the rounding.
    """
    return torch.round(images.float().sum(1, keepdim=True) * 255.0).to(dtype)


def shift_images(images: Tensor, offsets: Tensor, radius: int) -> Tensor:
    """Shift each row of ``images`` by its offsets (edges repeat), one gather for all.

    Args:
        images: ``[N, C, S, S]``.
        offsets: int64 ``[N, 2]`` from :func:`best_shifts`.
        radius: The radius the offsets were found with.

    Returns:
        ``[N, C, S, S]`` shifted images.
    """
    r = int(radius)
    if r == 0:
        return images
    n, c, size, _ = images.shape
    padded = F.pad(images, (r, r, r, r), mode="replicate")
    width = size + 2 * r
    rows = torch.arange(size, device=images.device)
    base = (rows[:, None] * width + rows[None, :]).reshape(1, -1)
    index = base + (offsets[:, 0] * width + offsets[:, 1]).reshape(-1, 1)
    flat = padded.reshape(n, c, width * width)
    out = flat.gather(2, index.unsqueeze(1).expand(n, c, size * size))
    return out.reshape(n, c, size, size)


def evidence_step(current: Tensor, history: Tensor, seen: Tensor, radius: int,
                  rate: float) -> Tuple[Tensor, Tensor]:
    """One frame of temporal evidence for ``N`` tracks.

    Args:
        current: ``[N, 3, S, S]`` crops in [0, 1].
        history: ``[N, 6, S, S]``: the previous crop (channels 0-2) and the running mean
            (3-5), in the previous frame's coordinates.
        seen: ``[N, 1, 1, 1]`` 1 where the track has a previous frame, else 0.
        radius: Alignment search radius in pixels.
        rate: Weight of the current crop in the running mean.

    Returns:
        ``([N, 6, S, S]`` differences (current - previous, current - mean), zero for
        unseen tracks; the new ``[N, 6, S, S]`` history).
    """
    # NCHW: the gathers and concatenations below are several times slower channels-last.
    current = current.float().contiguous()
    offsets = best_shifts(history[:, :3], current, radius)
    aligned = shift_images(history, offsets, radius)
    seen = seen.to(current.dtype)
    evidence = (current.repeat(1, 2, 1, 1) - aligned) * seen
    mean = aligned[:, 3:]
    # An unseen track's mean starts at its first crop.
    new_mean = mean + (current - mean) * (seen * rate + (1.0 - seen))
    return evidence, torch.cat((current, new_mean), 1)
