"""The data a run trains and validates on: tracks, held-out tracks, validation items.

Tracks come from labelled bags, UC Merced roots and materialised synthetic pools
(:mod:`.sources`); the live synthetic stream takes ``synthetic_fraction`` of the
sequences (by default all of them without tracks, none with). Validation is on, in this
order of preference: ``--val-split``; every k-th track held out (``val_fraction``); a
split of the synthetic stream materialised once under ``OUT/val_split``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Dict, List, Tuple

from signal_light_node.evaluation.tracks import TrackSequence, item_labels
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.training import FRAME_TARGETS
from signal_light_node.training.options import TrainOptions
from signal_light_node.training.sources import (
    WindowDataset,
    load_bag_tracks,
    load_ucm_tracks,
    split_tracks,
)

logger = logging.getLogger(__name__)

#: Offset of the seed of a materialised validation split from the run's seed.
VAL_SPLIT_SEED_OFFSET = 1_000_003


def load_tracks(opts: TrainOptions, crop: CropConfig) -> List[TrackSequence]:
    """Every track of ``opts.bags``, ``opts.ucm`` and ``opts.pools``, in that order."""
    tracks: List[TrackSequence] = []
    for bag in opts.bags:
        tracks += load_bag_tracks(Path(bag), crop)
    for root in opts.ucm:
        tracks += load_ucm_tracks(Path(root), crop)
    for pool in opts.pools:
        tracks += split_tracks(Path(pool), crop, role="pool",
                               label_key=FRAME_TARGETS[opts.frame_targets])
    return tracks


def load_rehearsal(opts: TrainOptions, crop: CropConfig) -> List[TrackSequence]:
    """Every track of ``opts.rehearse``: training data only, never held out or validated."""
    tracks: List[TrackSequence] = []
    for pool in opts.rehearse:
        tracks += split_tracks(Path(pool), crop, role="rehearse",
                               label_key=FRAME_TARGETS[opts.frame_targets])
    return tracks


def hold_out_tracks(tracks: List[TrackSequence], fraction: float
                    ) -> Tuple[List[TrackSequence], List[TrackSequence]]:
    """``(train, validation)``: every k-th track (k = 1/fraction) is held out; deterministic."""
    if fraction <= 0 or len(tracks) < 2:
        return tracks, []
    k = max(2, int(round(1.0 / fraction)))
    val = [t for i, t in enumerate(tracks) if i % k == k - 1]
    train = [t for i, t in enumerate(tracks) if i % k != k - 1]
    return train, val


def synthetic_share(opts: TrainOptions, tracks: List[TrackSequence]) -> float:
    """Share of sequences from the synthetic stream (``opts.synthetic_fraction`` or its default)."""
    if opts.synthetic_fraction is not None:
        return float(opts.synthetic_fraction)
    return 0.0 if tracks else 1.0


def validation_items(opts: TrainOptions, crop: CropConfig, held_out: List[TrackSequence],
                     synthetic: float) -> List[Dict[str, Any]]:
    """The fixed sequences a run validates on (see the module doc; empty: no validation).

    Args:
        opts: The run's options.
        crop: The model's crop (a split must have been cropped alike).
        held_out: Tracks held out for validation.
        synthetic: :func:`synthetic_share` of the run.

    Raises:
        ConfigError: The validation split was cropped for another model, or lacks the
            labels ``opts.frame_targets`` asks for.
    """
    if opts.val_split is not None:
        return _split_items(opts, crop)
    if held_out:
        win = WindowDataset(held_out, max(opts.seq_len, opts.val_seq_len), seed=opts.seed)
        return [win.window(i) for i in range(len(win.windows))]
    if synthetic > 0:
        return _synthetic_items(opts, crop)
    return []


def _split_items(opts: TrainOptions, crop: CropConfig) -> List[Dict[str, Any]]:
    """The items of ``--val-split``, labelled as ``--frame-targets`` asks."""
    from signal_light_node.data.split import SequenceSplit

    split = SequenceSplit(opts.val_split)
    split.require_crop(crop, "validation split")
    key = FRAME_TARGETS[opts.frame_targets]
    items = [split[i] for i in range(len(split))]
    if key == "labels":
        return items
    return [dict(item, labels=item_labels(item, key, f"validation split {opts.val_split}"))
            for item in items]


def _synthetic_items(opts: TrainOptions, crop: CropConfig) -> List[Dict[str, Any]]:
    """The items of ``OUT/val_split``, rendered the first time a run needs them."""
    from signal_light_node.data.split import SequenceSplit, write_split

    val_dir = Path(opts.out) / "val_split"
    if not (val_dir / "manifest.json").is_file():
        logger.info("materialising a validation split of %d sequences in %s",
                    opts.val_sequences, val_dir)
        write_split(val_dir, seed=(opts.seed + VAL_SPLIT_SEED_OFFSET) % (2**31),
                    n_sequences=opts.val_sequences,
                    seq_len=max(opts.seq_len, opts.val_seq_len),
                    crop=crop, progress=opts.progress, **opts.stream)
    split = SequenceSplit(val_dir)
    return [split[i] for i in range(len(split))]
