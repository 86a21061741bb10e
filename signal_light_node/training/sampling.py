"""Countering class imbalance: sequence strata, stratified sampling, class weights.

On real roads most frames show no light at all, and HAZARD or a brake light together
with a blinker are rare. Two mechanisms counter this, both documented in the trainer:

* **Stratified sequence sampling.** Each training window gets the rarest *stratum* it
  contains (:func:`sequence_stratum`); finite sources (bags, UCM) draw windows so that
  every stratum present is drawn equally often (:func:`stratum_weights`), and the
  infinite synthetic stream is thinned by :class:`StratumBalancer`, which drops windows
  of over-represented strata with a bounded probability (it never drops more than
  ``max_drop`` of any stratum, so rendering time is not wasted without limit).
* **Class-weighted cross-entropy.** :class:`ClassFrequency` counts the labels the
  trainer has seen and gives per-class loss weights ``(share)^-power``, normalised so
  that the expected weight of a frame is 1 and clipped to ``[min_weight, max_weight]``.
"""

from __future__ import annotations

from typing import Dict, Iterable, Iterator, List, Mapping, Optional, Sequence

import numpy as np
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, Intent, LightStatus, View

#: Strata from rarest to most common; a window belongs to the first one it matches.
STRATA = ("hazard", "brake_blink", "blink", "brake", "plain")

_INTENT = TASKS.index("intent")
_BRAKE = TASKS.index("brake")


def sequence_stratum(labels: np.ndarray, mask: Optional[np.ndarray] = None) -> str:
    """The rarest stratum that a window's labels contain.

    Args:
        labels: int64 ``[T, len(TASKS)]`` labels in ``TASKS`` order.
        mask: bool ``[T]``; frames with False are ignored (all used when None).

    Returns:
        One of :data:`STRATA`: ``hazard`` (some frame has intent HAZARD),
        ``brake_blink`` (a frame with brake ON and intent LEFT/RIGHT), ``blink``
        (intent LEFT/RIGHT), ``brake`` (brake ON), else ``plain``.
    """
    lab = np.asarray(labels)
    if lab.ndim != 2 or lab.shape[1] != len(TASKS):
        raise ConfigError(f"labels must be [T, {len(TASKS)}], got shape {lab.shape}")
    if mask is not None:
        lab = lab[np.asarray(mask, dtype=bool)]
    intent, brake = lab[:, _INTENT], lab[:, _BRAKE]
    turning = (intent == Intent.LEFT) | (intent == Intent.RIGHT)
    braking = brake == LightStatus.ON
    if np.any(intent == Intent.HAZARD):
        return "hazard"
    if np.any(turning & braking):
        return "brake_blink"
    if np.any(turning):
        return "blink"
    if np.any(braking):
        return "brake"
    return "plain"


def side_blink_tracks(labels: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Per track (frames ``offsets[i]:offsets[i+1]`` of ``labels [N, len(TASKS)]``): does it
    show a blinker ON from the blinker's own side (a LEFT view with the left blinker ON, a
    RIGHT view with the right one)? The model misses those most (docs/model.md)."""
    view = labels[:, TASKS.index("view")]
    on = LightStatus.ON
    side = (((view == View.LEFT) & (labels[:, TASKS.index("left")] == on))
            | ((view == View.RIGHT) & (labels[:, TASKS.index("right")] == on)))
    return _any_per_track(side, offsets)


def hazard_tracks(labels: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Per track (as :func:`side_blink_tracks`): does any of its frames show a HAZARD? Both
    sides flash in phase there, which a model that learnt one blinker at a time misses."""
    return _any_per_track(labels[:, _INTENT] == Intent.HAZARD, offsets)


def _any_per_track(flags: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Per track, whether any of its frames ``offsets[i]:offsets[i+1]`` is flagged."""
    running = np.concatenate(([0], np.cumsum(flags, dtype=np.int64)))
    return running[offsets[1:]] > running[offsets[:-1]]


def stratum_weights(strata: Sequence[str]) -> np.ndarray:
    """Sampling probabilities that give every present stratum the same total share.

    Args:
        strata: The stratum of each item.

    Returns:
        float64 probabilities, one per item, summing to 1.
    """
    if not len(strata):
        raise ConfigError("cannot weight an empty set of sequences")
    names, inverse, counts = np.unique(np.asarray(strata), return_inverse=True,
                                       return_counts=True)
    weights = 1.0 / counts[inverse].astype(np.float64)
    return weights / weights.sum()


class StratumBalancer:
    """Thins an infinite stream of windows towards equal stratum shares.

    A window of stratum ``s`` is kept with probability
    ``max(1 - max_drop, min(1, rarest_share / share(s)))`` where the shares are running
    counts of the windows *offered* so far, so the rarest stratum is always kept and
    the most common one is dropped at most ``max_drop`` of the time.

    Args:
        seed: Seed of the keep/drop decisions.
        max_drop: Highest drop probability of any stratum, in [0, 1).
        min_count: Offers seen before anything is dropped (the shares need data first).
    """

    def __init__(self, seed: int, max_drop: float = 0.75, min_count: int = 50) -> None:
        if not 0.0 <= max_drop < 1.0:
            raise ConfigError(f"max_drop must be in [0, 1), got {max_drop}")
        self._rng = np.random.default_rng(seed)
        self.max_drop = float(max_drop)
        self.min_count = int(min_count)
        self.offered: Dict[str, int] = {s: 0 for s in STRATA}
        self.kept: Dict[str, int] = {s: 0 for s in STRATA}

    def keep_probability(self, stratum: str) -> float:
        """Probability with which a window of ``stratum`` is kept now."""
        total = sum(self.offered.values())
        if total < self.min_count or self.offered.get(stratum, 0) == 0:
            return 1.0
        present = [c for c in self.offered.values() if c > 0]
        ratio = min(present) / self.offered[stratum]
        return max(1.0 - self.max_drop, min(1.0, ratio))

    def offer(self, stratum: str) -> bool:
        """Record a window of ``stratum`` and decide whether the trainer gets it."""
        if stratum not in self.offered:
            raise ConfigError(f"unknown stratum {stratum!r}; expected one of {STRATA}")
        self.offered[stratum] += 1
        keep = bool(self._rng.random() < self.keep_probability(stratum))
        if keep:
            self.kept[stratum] += 1
        return keep

    def filter(self, items: Iterable[Mapping]) -> Iterator[Mapping]:
        """Yield the kept items of a stream of ``{"labels", "mask", ...}`` dicts."""
        for item in items:
            labels = np.asarray(item["labels"])
            mask = item.get("mask")
            if self.offer(sequence_stratum(labels, None if mask is None else np.asarray(mask))):
                yield item


class ClassFrequency:
    """Running label counts per task and the class weights derived from them.

    Args:
        num_classes: Classes per task.
        power: Exponent of the inverse share (0 disables weighting, 1 is full inverse
            frequency; 0.5 is a compromise that does not blow up rare classes).
        min_weight: Lower clip of a class weight.
        max_weight: Upper clip of a class weight.
    """

    def __init__(self, num_classes: Mapping[str, int], power: float = 0.5,
                 min_weight: float = 0.25, max_weight: float = 5.0) -> None:
        if power < 0:
            raise ConfigError(f"class weight power must be >= 0, got {power}")
        self.power = float(power)
        self.min_weight = float(min_weight)
        self.max_weight = float(max_weight)
        # A prior of one frame per class keeps unseen classes finite.
        self.counts: Dict[str, np.ndarray] = {t: np.ones(int(k), np.float64)
                                              for t, k in num_classes.items()}

    def update(self, labels: np.ndarray, mask: np.ndarray,
               tasks: Sequence[str] = TASKS) -> None:
        """Count the labels of valid frames: ``labels [..., len(tasks)]``, ``mask [...]``."""
        lab = np.asarray(labels).reshape(-1, len(tasks))
        valid = np.asarray(mask, dtype=bool).reshape(-1)
        for i, task in enumerate(tasks):
            if task not in self.counts:
                continue
            col = lab[valid, i]
            col = col[(col >= 0) & (col < len(self.counts[task]))]
            self.counts[task] += np.bincount(col, minlength=len(self.counts[task]))

    def weights(self, task: str) -> np.ndarray:
        """Loss weight of each class of ``task`` (mean weight per frame is 1 before clipping)."""
        counts = self.counts[task]
        if self.power == 0:
            return np.ones_like(counts)
        share = counts / counts.sum()
        w = share ** (-self.power)
        w = w / float((share * w).sum())
        return np.clip(w, self.min_weight, self.max_weight)

    def tensors(self, device: torch.device) -> Dict[str, torch.Tensor]:
        """:meth:`weights` of every task as float32 tensors on ``device``."""
        return {t: torch.as_tensor(self.weights(t), dtype=torch.float32, device=device)
                for t in self.counts}

    def state_dict(self) -> Dict[str, List[float]]:
        """Counts as plain lists (for the training-state file)."""
        return {t: c.tolist() for t, c in self.counts.items()}

    def load_state_dict(self, state: Mapping[str, Sequence[float]]) -> None:
        """Restore counts saved by :meth:`state_dict`."""
        for t, c in state.items():
            if t in self.counts and len(c) == len(self.counts[t]):
                self.counts[t] = np.asarray(c, dtype=np.float64)
