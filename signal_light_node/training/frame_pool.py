"""Single frames of rendered splits in memory, sampled and augmented for per-frame training.

The per-frame stage of the trunk recipe (``training.trunk_finetune``) needs many
independent frames, each with its per-frame targets: whether each lamp is lit in that very
frame (``lit_labels``: a blink's dark half is OFF) and the viewed face. A
:class:`FramePool` holds every frame of one or more splits (``data.split`` shards, read
directly, not item by item) with the slice each track occupies, so a batch can take a few
frames from each of many tracks and augment each track's frames together: one mirror, one
perspective warp and one camera response per track, as a camera would treat them.

With a ``pair_gap`` every frame comes with the same track's frame that many frames earlier
(:func:`partner_index`; the track's first frame where there is none), augmented with it,
so a head can read a lamp's change as well as its look.

With a ``grey`` share, that share of the tracks is shown without colour (each frame's luma
in all three channels, after the camera): a lamp lit in such a frame can be told only by
its brightness against the vehicle. Luma still depends on the hue (an orange lamp has
less than a yellow one of the same power); ``grey_mode="value"`` shows each pixel's
largest channel instead, which a saturated lit lamp keeps near full whatever its hue.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Sequence, Tuple

import numpy as np
import torch

from signal_light_node.data.camera_response import LUMA_BGR, randomise_camera
from signal_light_node.data.shape_warp import warp_sequence
from signal_light_node.data.stream import mirror_sequence
from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS

#: The per-frame targets, in the column order of :meth:`FramePool.targets`: each lamp's
#: lit state (ON / OFF / UNKNOWN) and the view (4 faces).
FRAME_TARGETS: Tuple[str, ...] = ("brake", "left", "right", "view")
_LIT_COLUMNS = [TASKS.index(t) for t in ("brake", "left", "right")]
_VIEW_COLUMN = TASKS.index("view")


def frame_targets(lit_labels: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per-frame targets ``[n, 4]`` (:data:`FRAME_TARGETS`) of label rows ``[n, 5]``."""
    return np.concatenate([lit_labels[:, _LIT_COLUMNS], labels[:, [_VIEW_COLUMN]]],
                          1).astype(np.int64)


def join_releasing(parts: List[np.ndarray]) -> np.ndarray:
    """``np.concatenate(parts)`` that empties ``parts`` as it copies: the joined array's
    pages are only touched as each part lands, so the peak is the pool plus one part, not
    twice the pool (nine pools of crops are about 6 GB)."""
    total = sum(len(part) for part in parts)
    out = np.empty((total, *parts[0].shape[1:]), parts[0].dtype) if parts else np.empty(0)
    start = 0
    while parts:
        part = parts.pop(0)
        out[start:start + len(part)] = part
        start += len(part)
    return out


@dataclass
class FramePool:
    """Frames of whole tracks: crops ``[F, S, S, 3]`` uint8, ``labels`` and ``lit_labels``
    ``[F, 5]`` int8 (-1 unlabelled), and ``offsets`` ``[tracks + 1]`` into them."""

    crops: np.ndarray
    labels: np.ndarray
    lit_labels: np.ndarray
    offsets: np.ndarray

    @classmethod
    def load(cls, splits: Sequence["str | os.PathLike[str]"]) -> "FramePool":
        """Read every shard of the split directories ``splits``.

        Raises:
            ConfigError: A directory is not a split, or a shard has no per-frame lit labels.
        """
        crops: List[np.ndarray] = []
        labels: List[np.ndarray] = []
        lit: List[np.ndarray] = []
        lengths: List[np.ndarray] = []
        for split in map(Path, splits):
            manifest = split / "manifest.json"
            if not manifest.is_file():
                raise ConfigError(f"{split} is not a rendered split (no manifest.json)")
            for shard in json.loads(manifest.read_text())["shards"]:
                with np.load(split / shard["file"], allow_pickle=False) as data:
                    if "lit_labels" not in data.files:
                        raise ConfigError(f"{split / shard['file']} has no lit_labels "
                                          f"(rendered before 2026-11-21): render it again")
                    crops.append(data["crops"])
                    labels.append(data["labels"].astype(np.int8))
                    lit.append(data["lit_labels"].astype(np.int8))
                    lengths.append(data["lengths"])
        offsets = np.concatenate(([0], np.cumsum(np.concatenate(lengths)))).astype(np.int64)
        return cls(join_releasing(crops), np.concatenate(labels), np.concatenate(lit), offsets)

    def __len__(self) -> int:
        return len(self.crops)

    @property
    def n_tracks(self) -> int:
        """Number of tracks."""
        return len(self.offsets) - 1

    def targets(self, index: np.ndarray) -> np.ndarray:
        """Per-frame targets ``[n, 4]`` (:data:`FRAME_TARGETS`) of frames ``index``."""
        return frame_targets(self.lit_labels[index], self.labels[index])

    def class_counts(self, num_classes: Sequence[int]) -> List[np.ndarray]:
        """Per target, how many frames hold each class (unlabelled frames left out)."""
        all_targets = self.targets(np.arange(len(self)))
        return [np.bincount(col[col >= 0], minlength=k)[:k]
                for col, k in zip(all_targets.T, num_classes)]


#: What a greyed frame shows in all three channels (:func:`grey_frames`).
GREY_MODES = ("luma", "value")


def grey_frames(crops: np.ndarray, mode: str = "luma") -> np.ndarray:
    """BGR uint8 frames ``[..., 3]`` with one grey level per pixel in all three channels:
    its luma (:data:`LUMA_BGR`) or, with ``mode="value"``, its largest channel.

    Raises:
        ConfigError: ``mode`` is not one of :data:`GREY_MODES`.
    """
    if mode == "value":
        level = crops.max(axis=-1)
    elif mode == "luma":
        level = np.clip(np.rint(crops.astype(np.float32) @ LUMA_BGR), 0, 255).astype(np.uint8)
    else:
        raise ConfigError(f"grey mode must be one of {GREY_MODES}, got {mode!r}")
    return np.repeat(level[..., None], 3, axis=-1)


def _augment_track(crops: np.ndarray, lit: np.ndarray, labels: np.ndarray,
                   rng: np.random.Generator, augment: float, white_balance: float = 0.0,
                   grey: float = 0.0, grey_mode: str = "luma"
                   ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One track's frames mirrored with probability 0.5, then, with probability
    ``augment``, one perspective warp and one camera response (its channel gains drawn
    within ``white_balance``, :meth:`.CameraResponse.draw`), then with probability
    ``grey`` greyed (:func:`grey_frames` by ``grey_mode``). ``crops`` may hold more frames
    than the label rows (their partners, behind them): all get the same treatment."""
    if rng.random() < 0.5:
        item = mirror_sequence({"crops": crops, "labels": labels, "lit_labels": lit,
                                "mask": np.ones(len(labels), bool), "meta": {}})
        crops, labels, lit = item["crops"], item["labels"], item["lit_labels"]
    if rng.random() < augment:
        crops = randomise_camera(warp_sequence(crops, rng), rng, white_balance)
    # Drawn only when asked, so that runs without it keep their random stream.
    if grey > 0 and rng.random() < grey:
        crops = grey_frames(crops, grey_mode)
    return crops, lit, labels


def partner_index(offsets: np.ndarray, index: np.ndarray, gap: int) -> np.ndarray:
    """For frames ``index`` of a pool with track ``offsets``, the same track's frame
    ``gap`` frames earlier, or the track's first frame where the track is younger."""
    start = offsets[np.searchsorted(offsets, index, side="right") - 1]
    return np.maximum(index - gap, start)


def _with_partner_rows(offsets: np.ndarray, index: np.ndarray, pair_gap: int) -> np.ndarray:
    """Rows ``index`` then, with ``pair_gap`` > 0, their partners (:func:`partner_index`)."""
    if not pair_gap:
        return index
    return np.concatenate([index, partner_index(offsets, index, pair_gap)])


def _with_partners(frames: np.ndarray, pair_gap: int) -> np.ndarray:
    """``[2n, S, S, 3]`` frames then their partners -> ``[n, S, S, 6]`` (channels stacked)."""
    n = len(frames) // 2
    return np.concatenate([frames[:n], frames[n:]], axis=-1) if pair_gap else frames


def sample_batch(pool: FramePool, rng: np.random.Generator, tracks: int, per_track: int,
                 augment: float, white_balance: float = 0.0, pair_gap: int = 0,
                 grey: float = 0.0, grey_mode: str = "luma"
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
    """``tracks x per_track`` random frames (tracks drawn uniformly, frames uniformly in
    each), augmented per track (:func:`_augment_track`, ``grey`` its share of greyed
    tracks, ``grey_mode`` how they are greyed): crops ``[N, 3, S, S]`` uint8 and targets
    ``[N, 4]``. With ``pair_gap`` > 0 each frame's partner (:func:`partner_index`,
    augmented with it) is stacked behind it: crops ``[N, 6, S, S]``."""
    crops, targets = [], []
    for track in rng.integers(0, pool.n_tracks, tracks):
        a, b = int(pool.offsets[track]), int(pool.offsets[track + 1])
        index = np.sort(rng.integers(a, b, per_track))
        frames = _with_partner_rows(pool.offsets, index, pair_gap)
        c, lit, labels = _augment_track(pool.crops[frames], pool.lit_labels[index],
                                        pool.labels[index], rng, augment, white_balance,
                                        grey, grey_mode)
        crops.append(_with_partners(c, pair_gap))
        targets.append(frame_targets(lit, labels))
    x = torch.from_numpy(np.ascontiguousarray(np.concatenate(crops))).permute(0, 3, 1, 2)
    return x, torch.from_numpy(np.concatenate(targets))


class FrameBatches(torch.utils.data.IterableDataset):
    """Endless :func:`sample_batch` batches; each DataLoader worker draws from its own
    stream (``seed``, the worker's id and ``start``, the step a resumed run is at)."""

    def __init__(self, pool: FramePool, seed: int, tracks: int, per_track: int,
                 augment: float, start: int = 0, white_balance: float = 0.0,
                 pair_gap: int = 0, grey: float = 0.0, grey_mode: str = "luma") -> None:
        super().__init__()
        self.pool, self.seed, self.start = pool, seed, start
        self.tracks, self.per_track, self.augment = tracks, per_track, augment
        self.white_balance, self.pair_gap, self.grey = white_balance, pair_gap, grey
        self.grey_mode = grey_mode

    def __iter__(self) -> Iterator[Tuple[torch.Tensor, torch.Tensor]]:
        info = torch.utils.data.get_worker_info()
        worker = 0 if info is None else info.id
        rng = np.random.default_rng([self.seed, worker, self.start])
        while True:
            yield sample_batch(self.pool, rng, self.tracks, self.per_track, self.augment,
                               self.white_balance, self.pair_gap, self.grey, self.grey_mode)


def frame_arrays(pool: FramePool, stride: int = 1, pair_gap: int = 0) -> Dict[str, np.ndarray]:
    """Every ``stride``-th frame of a pool, unaugmented: ``crops`` and ``targets`` (with
    ``pair_gap`` > 0 the crops ``[M, S, S, 6]`` carry each frame's partner behind it)."""
    index = np.arange(0, len(pool), stride)
    crops = _with_partners(pool.crops[_with_partner_rows(pool.offsets, index, pair_gap)],
                           pair_gap)
    return {"crops": crops, "targets": pool.targets(index)}
