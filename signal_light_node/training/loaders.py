"""The training DataLoader of a run, per batch mode (``TrainOptions.mode``).

* "frames" / "lanes": in-memory tracks cut by :mod:`.track_batches`, in-process (the
  lanes must stay in the order of the state the trainer carries).
* "windows": ``batch`` sequences per step, each drawn from the synthetic stream (replayed
  and optionally thinned, :mod:`.streams`) or as a stratum-balanced window of a track
  (:class:`.sources.WindowDataset`), mixed with fixed shares; the synthetic stream renders
  in ``workers`` DataLoader processes.

Augmentation (:class:`.augment.Augment`) comes last, so that every served copy of a
sequence is augmented on its own.
"""

from __future__ import annotations

from typing import List, Sequence

import torch
from torch.utils.data import DataLoader, IterableDataset

from signal_light_node.data.stream import SyntheticSequenceStream, collate_sequences
from signal_light_node.errors import ConfigError
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.training.augment import Augment
from signal_light_node.training.options import TrainOptions
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.training.sources import WindowDataset
from signal_light_node.training.streams import BalancedStream, MixedStream, ReplayStream
from signal_light_node.training.track_batches import FrameBatches, LaneBatches

#: Windows cut from each track of a rendered training scene (scene length / seq_len).
SCENE_WINDOWS = 4


def worker_init(worker_id: int) -> None:
    """Data workers render on one core each; OpenCV's own pool would fight the trainer."""
    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)


def training_loader(opts: TrainOptions, crop: CropConfig, tracks: List[TrackSequence],
                    synthetic: float, seed: int, rank: int,
                    rehearse: Sequence[TrackSequence] = ()) -> DataLoader:
    """The DataLoader of a run's training batches.

    Args:
        opts: The run's options.
        crop: The model's crop.
        tracks: The training tracks (held-out ones excluded).
        synthetic: Share of sequences from the synthetic stream (``run_data.synthetic_share``).
        seed: The data seed (``seeding.data_seed``).
        rank: Process rank.
        rehearse: Tracks rehearsed beside ``tracks`` (``opts.rehearse``); they take
            ``opts.rehearse_share`` of the sequences that come from tracks.

    Raises:
        ConfigError: Some sequences must come from tracks, and there are none.
    """
    augment = Augment(opts.mirror_prob, opts.jitter, opts.camera_response, opts.shape_warp)
    if opts.mode != "windows":
        return _track_batch_loader(opts, tracks, augment, seed, rank, rehearse)
    parts: List[IterableDataset] = []
    probs: List[float] = []
    if synthetic > 0:
        parts.append(_synthetic_part(opts, crop, augment, seed, rank))
        probs.append(synthetic)
    if synthetic < 1:
        if not tracks:
            raise ConfigError("no training tracks: --bags / --ucm gave nothing to train on")
        # WindowDataset draws stratum-balanced windows itself.
        parts.append(WindowDataset(tracks, opts.seq_len, seed=seed, augment=augment, rank=rank))
        share = opts.rehearse_share if rehearse else 0.0
        probs.append((1.0 - synthetic) * (1.0 - share))
        if rehearse:
            parts.append(WindowDataset(rehearse, opts.seq_len, seed=seed + 1, augment=augment,
                                       rank=rank))
            probs.append((1.0 - synthetic) * share)
    return _window_loader(MixedStream(parts, probs, seed, rank), opts.batch, int(opts.workers))


def _track_batch_loader(opts: TrainOptions, tracks: List[TrackSequence], augment: Augment,
                        seed: int, rank: int, rehearse: Sequence[TrackSequence] = ()
                        ) -> DataLoader:
    """Single frames or lanes of in-memory tracks, batched by the dataset itself."""
    if opts.mode == "frames":
        batches: IterableDataset = FrameBatches(tracks, opts.batch, seed, augment, rank)
    else:
        batches = LaneBatches(tracks, opts.batch, opts.seq_len, seed, augment, rank,
                              rehearse=rehearse, rehearse_share=opts.rehearse_share)
    return DataLoader(batches, batch_size=None, num_workers=0)


def _synthetic_part(opts: TrainOptions, crop: CropConfig, augment: Augment, seed: int,
                    rank: int) -> IterableDataset:
    """The synthetic stream, thinned if asked, behind its replay buffer."""
    stream_opts = dict(opts.stream)
    # Setting up a scene costs about as much as rendering 10 frames: render
    # longer scenes and cut several windows from each track.
    stream_opts.setdefault("scene_frames", SCENE_WINDOWS * opts.seq_len)
    stream: IterableDataset = SyntheticSequenceStream(
        seed % (2**31), opts.seq_len, crop, mirror_prob=0.0, jitter=False, rank=rank,
        **stream_opts)
    if opts.balance and opts.balance_max_drop > 0:
        stream = BalancedStream(stream, seed, rank, opts.balance_max_drop)
    # Augmentation comes after the balancer and the replay buffer, so that every
    # served copy of a sequence is augmented on its own.
    return ReplayStream(stream, opts.reuse, opts.replay_capacity, augment, seed, rank,
                        stratified=opts.balance)


def _window_loader(mixed: IterableDataset, batch: int, workers: int) -> DataLoader:
    """Batches of ``batch`` windows, collated, from ``workers`` processes (0: in-process)."""
    # "spawn", not fork: a child forked after OpenCV or OpenMP ran their thread pools
    # in this process can deadlock on a lock copied in the held state.
    return DataLoader(
        mixed, batch_size=batch, collate_fn=collate_sequences, num_workers=workers,
        persistent_workers=workers > 0, prefetch_factor=4 if workers > 0 else None,
        multiprocessing_context="spawn" if workers > 0 else None,
        worker_init_fn=worker_init if workers > 0 else None)
