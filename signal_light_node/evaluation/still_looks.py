"""Looks held still: is a light read from how a vehicle looks, or from how its look changes?

A track's crop at one frame, repeated for the track's whole length, gives the model a
vehicle that never changes. If the model still publishes a light ON there, it reads that
light from the look alone (an absolute read: a steady tail lamp bright enough to pass for
a brake); if it publishes the light ON on the recorded track but not on its looks held
still, it reads it from the changes between frames (a step over the vehicle's own lamps).
docs/model.md ("Which of the truck's looks read braking") measured both on the night bags.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, List

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.streaming import predict_track_probs
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LIGHT_TASKS, TASKS, LightStatus

_ON, _OFF = int(LightStatus.ON), int(LightStatus.OFF)


def held_still(track: TrackSequence, index: int) -> TrackSequence:
    """The track with every crop replaced by its crop at ``index`` (stamps, mask and
    labels kept, so the filter and the scorer see the same timing). The crops are a
    read-only view of that one crop: all looks of a long track held still at once cost
    one crop each, not the track's length.

    Raises:
        ConfigError: ``index`` is outside the track.
        CropError: A lazily read frame cannot be read.
    """
    look = track.crop_window(index, index + 1)[0]
    return replace(track, crops=np.broadcast_to(look, (len(track), *look.shape)))


def on_share(published: np.ndarray) -> float:
    """Share of the judged (OFF or ON) entries of a published class column that are ON
    (0 when none is judged)."""
    judged = int(((published == _OFF) | (published == _ON)).sum())
    return float((published == _ON).sum()) / judged if judged else 0.0


def still_look_reads(model: Any, track: TrackSequence, task: str = "brake",
                     every: int = 3) -> List[bool]:
    """For the looks at frames 0, ``every``, 2 ``every``...: whether, held still for the
    track's length, ``task`` is published ON on more than half of its judged frames.

    Args:
        model: A checkpoint's model or a backend (as :func:`predict_track_probs` takes).
        track: A track (its crops in memory or read from its frame files).
        task: A light task (``labels.LIGHT_TASKS``: ``brake``, ``left``, ``right``).
        every: Take every ``every``-th look (all looks cost the track's length squared).

    Returns:
        One bool per look taken, in frame order.

    Raises:
        ConfigError: ``task`` is not a light or ``every`` is below 1.
        CropError: A lazily read frame cannot be read.
    """
    if task not in LIGHT_TASKS:
        raise ConfigError(f"task must be one of {', '.join(LIGHT_TASKS)}, got {task!r}")
    if every < 1:
        raise ConfigError(f"every must be >= 1, got {every}")
    column = TASKS.index(task)
    stills = [held_still(track, i) for i in range(0, len(track), every)]
    published = predict_track_probs(model, stills)[0]
    return [on_share(p[:, column]) > 0.5 for p in published]
