"""Training batches cut from whole tracks held in memory: single frames, or stateful lanes.

Windows of consecutive frames from a handful of vehicles make poor mini-batches on a
small CPU: the frames of one window are nearly the same picture, so a step of 8 windows
x 24 frames teaches about as much as 8 frames do. Two batchers fix that for tracks
already in memory (materialised splits, labelled bags, UCM):

* :class:`FrameBatches` draws ``batch`` single frames from anywhere in the tracks
  (``T = 1``, zero state): the per-frame pre-training of attention, backbone and heads
  on many different vehicles per step.
* :class:`LaneBatches` runs ``lanes`` tracks side by side, ``seq_len`` frames per step,
  the way the node runs: each lane's recurrent state is carried from one step to the
  next (truncated back-propagation through time), and when its track ends the lane
  takes a new track and flags ``reset`` so the trainer zeroes that lane's state. A step
  thus costs ``lanes x seq_len`` frames but sees ``lanes`` different vehicles, each
  with its whole history in the state.

Both yield already collated batches (``DataLoader(..., batch_size=None)``) in the layout
of :func:`signal_light_node.data.stream.collate_sequences`; lanes add::

    reset   bool  [B]  the lane starts a new track with this batch (zero its state)
    start   int64 [B]  index in its track of the lane's first frame in this batch (the
                       trainer's warm-up counts from the track's start, not the batch's)

Augmentation (mirroring, colour jitter) is drawn once per track visit, so a lane's
frames stay consistent across its batches.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence

import numpy as np
import torch

from signal_light_node.data.stream import PAD_LABEL
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.tracks import TrackSequence

#: ``f(item, rng) -> item`` on a sequence item (see :mod:`.sources`).
Augment = Callable[[Dict[str, Any], np.random.Generator], Dict[str, Any]]


def _usable(tracks: Sequence[TrackSequence]) -> List[TrackSequence]:
    """Tracks held in memory, cut down to the frames that have a crop."""
    out = []
    for track in tracks:
        if track.crops is None:
            raise ConfigError(f"track {track.track_id} is not held in memory; frame and lane "
                              "batches need in-memory crops")
        keep = np.asarray(track.mask, dtype=bool)
        if not keep.any():
            continue
        if keep.all():
            out.append(track)
            continue
        out.append(TrackSequence(
            track_id=track.track_id, labels=track.labels[keep], mask=np.ones(int(keep.sum()), bool),
            stamps_ns=track.stamps_ns[keep], box_size=track.box_size[keep],
            occlusion=track.occlusion[keep], lighting=track.lighting, source=track.source,
            crops=track.crops[keep], crop_config=track.crop_config,
            lit_maps=None if track.lit_maps is None else track.lit_maps[keep]))
    if not out:
        raise ConfigError("no track has a usable frame")
    return out


def _rng(seed: int, rank: int, salt: int) -> np.random.Generator:
    info = torch.utils.data.get_worker_info()
    worker = info.id if info is not None else 0
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(rank), worker, salt]))


def _item(track: TrackSequence, start: int, stop: int) -> Dict[str, Any]:
    n = stop - start
    item = {"crops": np.ascontiguousarray(track.crops[start:stop]),
            "labels": track.labels[start:stop].astype(np.int64),
            "mask": np.ones(n, bool), "meta": {"fps": track.fps}}
    if track.lit_maps is not None:
        item["lit_maps"] = track.lit_maps[start:stop]
    return item


class FrameBatches(torch.utils.data.IterableDataset):
    """Endless batches of ``batch`` single frames drawn uniformly from all frames.

    Args:
        tracks: In-memory tracks.
        batch: Frames per batch.
        seed: Seed of the draws (with rank and worker).
        augment: Mirroring / jitter of each frame, or None.
        rank: Process rank under DDP.
    """

    def __init__(self, tracks: Sequence[TrackSequence], batch: int, seed: int = 0,
                 augment: Optional[Augment] = None, rank: int = 0) -> None:
        super().__init__()
        if batch < 1:
            raise ConfigError(f"batch must be >= 1, got {batch}")
        self.tracks = _usable(tracks)
        self.batch, self.seed, self.rank, self.augment = int(batch), int(seed), int(rank), augment
        self._offsets = np.cumsum([0] + [len(t) for t in self.tracks])

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        rng = _rng(self.seed, self.rank, 41)
        total = int(self._offsets[-1])
        while True:
            flat = rng.integers(total, size=self.batch)
            which = np.searchsorted(self._offsets, flat, side="right") - 1
            items = []
            for ti, f in zip(which, flat - self._offsets[which]):
                item = _item(self.tracks[int(ti)], int(f), int(f) + 1)
                items.append(self.augment(item, rng) if self.augment else item)
            batch = {"crops": torch.from_numpy(np.stack([i["crops"] for i in items])),
                     "labels": torch.from_numpy(np.stack([i["labels"] for i in items])),
                     "mask": torch.ones((self.batch, 1), dtype=torch.bool),
                     "meta": {"fps": [i["meta"]["fps"] for i in items]}}
            if all("lit_maps" in i for i in items):
                batch["lit_maps"] = torch.from_numpy(np.stack([i["lit_maps"] for i in items]))
            yield batch


@dataclass
class _Lane:
    """One track being played in a lane: its (augmented) frames and the next position."""

    crops: np.ndarray
    labels: np.ndarray
    fps: float
    position: int = 0


class LaneBatches(torch.utils.data.IterableDataset):
    """Endless stateful batches: ``lanes`` tracks played side by side, ``seq_len`` frames at a time.

    Use with ``num_workers=0``: the lanes' order must match the recurrent state the
    trainer keeps for them.

    Args:
        tracks: In-memory tracks.
        lanes: Tracks played at once (the batch size B).
        seq_len: Frames per lane per batch (the truncation length of back-propagation).
        seed: Seed of the track draws and the augmentation.
        augment: Mirroring / jitter applied to a whole track when a lane takes it.
        rank: Process rank under DDP.
        rehearse: Tracks rehearsed beside ``tracks`` (the training renders beside a
            user's labelled tracks, so a fine-tune cannot learn those by heart).
        rehearse_share: Chance that a lane's next track is a rehearsed one.
    """

    def __init__(self, tracks: Sequence[TrackSequence], lanes: int, seq_len: int, seed: int = 0,
                 augment: Optional[Augment] = None, rank: int = 0,
                 rehearse: Sequence[TrackSequence] = (), rehearse_share: float = 0.0) -> None:
        super().__init__()
        if lanes < 1 or seq_len < 1:
            raise ConfigError(f"lanes and seq_len must be >= 1, got {lanes}, {seq_len}")
        self.tracks = _usable(tracks)
        self.rehearse = _usable(rehearse) if rehearse else []
        self.rehearse_share = float(rehearse_share) if self.rehearse else 0.0
        self.lanes, self.seq_len = int(lanes), int(seq_len)
        self.seed, self.rank, self.augment = int(seed), int(rank), augment

    def _take(self, rng: np.random.Generator) -> _Lane:
        source = self.tracks
        # No draw without rehearsal: runs without it keep their exact track order.
        if self.rehearse_share > 0 and rng.random() < self.rehearse_share:
            source = self.rehearse
        track = source[int(rng.integers(len(source)))]
        item = _item(track, 0, len(track))
        if self.augment is not None:
            item = self.augment(item, rng)
        return _Lane(crops=item["crops"], labels=item["labels"], fps=track.fps)

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        rng = _rng(self.seed, self.rank, 43)
        lanes = [self._take(rng) for _ in range(self.lanes)]
        b, t = self.lanes, self.seq_len
        size = self.tracks[0].crops.shape[1:]
        while True:
            reset = np.zeros(b, bool)
            for i, lane in enumerate(lanes):
                if lane.position >= len(lane.labels):
                    lanes[i] = self._take(rng)
                if lanes[i].position == 0:
                    reset[i] = True
            crops = np.zeros((b, t) + tuple(size), np.uint8)
            labels = np.full((b, t, lanes[0].labels.shape[1]), PAD_LABEL, np.int64)
            mask = np.zeros((b, t), bool)
            starts = np.zeros(b, np.int64)
            for i, lane in enumerate(lanes):
                start = lane.position
                stop = min(start + t, len(lane.labels))
                crops[i, :stop - start] = lane.crops[start:stop]
                labels[i, :stop - start] = lane.labels[start:stop]
                mask[i, :stop - start] = True
                starts[i] = start
                lane.position = stop
            yield {"crops": torch.from_numpy(crops), "labels": torch.from_numpy(labels),
                   "mask": torch.from_numpy(mask), "reset": torch.from_numpy(reset),
                   "start": torch.from_numpy(starts),
                   "meta": {"fps": [lane.fps for lane in lanes]}}

