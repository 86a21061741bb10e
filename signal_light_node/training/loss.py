"""The multi-task loss: weighted per-head cross-entropies over the valid frames.

Each head's cross-entropy is averaged over the frames of the batch that count (``mask``
True and a label >= 0) and weighted by ``TrainOptions.task_weights``; class weights
(``share^-power``, :class:`.sampling.ClassFrequency`) counter the imbalance of the
classes. The blinker-driven heads (:data:`TEMPORAL_TASKS`) skip the first ``max(frames,
ceil(seconds * fps))`` frames of every window: a window starts from a blank state, and a
blink cannot be told from a dark lamp before part of a cycle has been seen.
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, LightStatus

#: Tasks whose label needs time to be seen (no loss during a window's warm-up).
TEMPORAL_TASKS = ("intent", "left", "right")


def share_weights(counts: np.ndarray, power: float = 0.5) -> torch.Tensor:
    """Class weights ``(share * K) ** -power`` from per-class frame counts (one added to
    each, so an unseen class is not infinite), clipped to [0.25, 5]: the fixed weights of
    the trunk recipe's stages, which count their whole cache or pool once."""
    counts = np.asarray(counts, np.float64) + 1.0
    share = counts / counts.sum()
    return torch.tensor(np.clip((share * len(counts)) ** -power, 0.25, 5.0),
                        dtype=torch.float32)


def multitask_loss(logits: Mapping[str, torch.Tensor], labels: torch.Tensor, mask: torch.Tensor,
                   task_weights: Mapping[str, float],
                   class_weights: Optional[Mapping[str, torch.Tensor]] = None,
                   loss_warmup: "int | torch.Tensor" = 0) -> Tuple[torch.Tensor, Dict[str, float]]:
    """Weighted sum of per-head cross-entropies over the valid frames.

    Args:
        logits: Task -> ``[B, T, K]``.
        labels: int64 ``[B, T, len(TASKS)]``; negative entries are ignored.
        mask: bool ``[B, T]``; False frames are ignored.
        task_weights: Task -> weight (missing or 0: not in the loss).
        class_weights: Task -> ``[K]`` class weights, or None.
        loss_warmup: Leading frames without loss for :data:`TEMPORAL_TASKS`: one number
            for all sequences, or an int64 ``[B]`` tensor per sequence.

    Returns:
        ``(total loss, {task: its mean cross-entropy})``.
    """
    total = logits[TASKS[0]].new_zeros(())
    parts: Dict[str, float] = {}
    for i, task in enumerate(TASKS):
        w = float(task_weights.get(task, 0.0))
        if w <= 0 or task not in logits:
            continue
        valid = _valid_frames(labels[..., i], mask, loss_warmup if task in TEMPORAL_TASKS
                              else None)
        loss = _masked_cross_entropy(logits[task], labels[..., i], valid,
                                     None if class_weights is None else class_weights.get(task))
        parts[task] = float(loss.detach())
        total = total + w * loss
    return total, parts


def brake_judge_loss(logit: torch.Tensor, labels: torch.Tensor, mask: torch.Tensor
                     ) -> torch.Tensor:
    """Binary cross-entropy of the brake judge's ``[B, T, 1]`` logit against the brake
    truth, over the frames whose truth is ON or OFF."""
    y = labels[..., TASKS.index("brake")]
    on, off = y == int(LightStatus.ON), y == int(LightStatus.OFF)
    valid = (mask & (on | off)).to(logit.dtype)
    bce = F.binary_cross_entropy_with_logits(logit[..., 0], on.to(logit.dtype), reduction="none")
    return (bce * valid).sum() / valid.sum().clamp(min=1.0)


def pair_rank_loss(logits: torch.Tensor, y: torch.Tensor, valid: torch.Tensor
                   ) -> Tuple[torch.Tensor, int]:
    """Summed logistic ranking loss over the pairs of one track's frames where a lamp is ON
    in one and OFF in the other: the ON frame's ON-over-OFF log-odds must exceed the OFF
    frame's. Rows are tracks (``logits`` ``[B, T, K]``, ``y`` and ``valid`` ``[B, T]``);
    frames of two tracks and frames not ``valid`` are never paired.

    Returns:
        ``(sum of the pairs' losses, number of pairs)``, so that callers may pool lamps.
    """
    on, off = int(LightStatus.ON), int(LightStatus.OFF)
    score = logits[..., on].float() - logits[..., off].float()  # [B, T]
    pair = ((y == on) & valid)[:, :, None] & ((y == off) & valid)[:, None, :]
    if not bool(pair.any()):
        return score.new_zeros(()), 0
    # softplus(unlit - lit) = log(1 + e^-(lit - unlit))
    return F.softplus(score[:, None, :] - score[:, :, None])[pair].sum(), int(pair.sum())


def lamp_rank_loss(logits: Mapping[str, torch.Tensor], labels: torch.Tensor, mask: torch.Tensor,
                   lamps: Sequence[str], loss_warmup: "int | torch.Tensor" = 0) -> torch.Tensor:
    """Mean :func:`pair_rank_loss` of the lamp heads ``lamps`` over each window's valid
    frames (past the warm-up for :data:`TEMPORAL_TASKS`, as :func:`multitask_loss` counts
    them): within one window, a frame whose lamp is ON must score above one where it is
    OFF. 0 when no window holds such a pair."""
    total, pairs = labels.new_zeros((), dtype=torch.float32), 0
    for lamp in lamps:
        y = labels[..., TASKS.index(lamp)]
        valid = _valid_frames(y, mask, loss_warmup if lamp in TEMPORAL_TASKS else None)
        summed, n = pair_rank_loss(logits[lamp], y, valid)
        total, pairs = total + summed, pairs + n
    return total / max(pairs, 1)


def _valid_frames(y: torch.Tensor, mask: torch.Tensor,
                  warmup: "int | torch.Tensor | None") -> torch.Tensor:
    """bool ``[B, T]``: frames with a label, past the warm-up when one is given."""
    valid = mask & (y >= 0)
    if warmup is not None:
        t_idx = torch.arange(y.shape[1], device=y.device)
        warm = torch.as_tensor(warmup, device=y.device).reshape(-1, 1)
        valid = valid & (t_idx[None, :] >= warm)
    return valid


def _masked_cross_entropy(logits: torch.Tensor, y: torch.Tensor, valid: torch.Tensor,
                          weight: Optional[torch.Tensor]) -> torch.Tensor:
    """Mean cross-entropy of ``[B, T, K]`` logits over the ``valid`` frames (0 if none)."""
    k = logits.shape[-1]
    ce = F.cross_entropy(logits.reshape(-1, k), y.clamp(min=0).reshape(-1), weight=weight,
                         reduction="none")
    valid_f = valid.reshape(-1).to(ce.dtype)
    return (ce * valid_f).sum() / valid_f.sum().clamp(min=1.0)


def warmup_frames(fps: Sequence[float], frames: int, seconds: float) -> torch.Tensor:
    """Per-sequence warm-up length: ``max(frames, ceil(seconds * fps))``, int64 ``[B]``."""
    rates = torch.as_tensor([float(f) if f else 10.0 for f in fps], dtype=torch.float64)
    return torch.clamp(torch.ceil(rates * float(seconds)), min=float(frames)).to(torch.int64)


def batch_loss_warmup(batch: Mapping[str, Any], frames: int, seconds: float, per_frame: bool,
                      device: torch.device) -> "int | torch.Tensor":
    """Leading frames per sequence of a training batch without loss on :data:`TEMPORAL_TASKS`.

    Args:
        batch: A collated batch (``labels``, ``meta`` with ``fps``; lanes add ``start``,
            each lane's first frame's index in its track).
        frames: ``TrainOptions.loss_warmup``.
        seconds: ``TrainOptions.loss_warmup_seconds``.
        per_frame: Single-frame batches (``--mode frames``): no warm-up. A lit lamp is a
            per-frame cue; a blinker's dark phase is label noise the recurrent stage
            later resolves.
        device: Where the loss is computed.

    Returns:
        0 for single frames, else an int64 ``[B]`` tensor on ``device``; in lanes only the
        start of each track warms up.
    """
    if per_frame:
        return 0
    fps = batch["meta"].get("fps", [None] * len(batch["labels"]))
    warm = warmup_frames(fps, frames, seconds)
    if "start" in batch:
        warm = (warm - batch["start"]).clamp(min=0)
    return warm.to(device)


#: Weight of a lit cell against a dark one in :func:`lit_map_loss`: lit lamps cover a
#: few cells of the map, and a loss dominated by dark cells would learn "nothing is lit".
LIT_MAP_POS_WEIGHT = 10.0


def lit_map_loss(logits: torch.Tensor, maps: torch.Tensor,
                 pos_weight: float = LIT_MAP_POS_WEIGHT) -> torch.Tensor:
    """Binary cross-entropy of the lit-map head against the rendered lit maps.

    A cell's target is the brightest map value inside it (a lamp covering part of a
    cell makes the cell lit, in proportion to how much of the finer map pixel it fills).

    Args:
        logits: ``[B, T, C F F]`` from the model's lit-map head (C channels, F x F cells).
        maps: uint8 ``[B, T, M, M, C]`` lit maps, M a multiple of F.
        pos_weight: Weight of the lit part of a target.

    Raises:
        ConfigError: The shapes do not fit together.
    """
    b, t, m, c = maps.shape[0], maps.shape[1], maps.shape[2], maps.shape[-1]
    cells = logits.shape[-1] // c
    f = int(round(cells ** 0.5))
    if logits.shape[:2] != maps.shape[:2] or f * f * c != logits.shape[-1] or m % f:
        raise ConfigError(f"lit-map logits {tuple(logits.shape)} do not fit maps "
                          f"{tuple(maps.shape)}")
    target = maps.to(logits.device).reshape(b * t, m, m, c).permute(0, 3, 1, 2).float() / 255.0
    target = F.max_pool2d(target, m // f)
    weight = logits.new_full((c, 1, 1), float(pos_weight))
    return F.binary_cross_entropy_with_logits(logits.reshape(b * t, c, f, f), target,
                                              pos_weight=weight)
