"""Streaming evaluation: every track stepped frame by frame, as the engine steps it.

Each track starts from the model backend's initial state and is advanced one ``step`` per
observed frame (frames with ``mask`` False, e.g. a box that could not be cropped, are
neither stepped nor scored, as the engine never judges them). Tracks are batched only
for speed: at frame index ``t`` every track of the batch that has a frame ``t`` is
stepped together, which gives the same outputs as stepping each track alone. The
model's outputs go through the same :class:`~signal_light_node.runtime.intent_filter.IntentFilter`
as in the engine, driven by each track's own stamps, so what is scored is what the node
publishes; with the filter disabled, the predicted class of a head is the argmax of its
probabilities (the raw model).

The predictions are scored by :class:`~signal_light_node.evaluation.scoring.TrackScorer`
(warm-up, grace window, breakdowns and switches: see :mod:`.scoring`).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, TypeVar

import numpy as np
import torch
from tqdm import tqdm

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import CLASS_NAMES, LIGHT_TASKS, TASKS
from signal_light_node.model.backends.registry import as_backend
from signal_light_node.runtime import flash_gate
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig


#: Key of :func:`model_track_probs`'s lamp levels (beside the tasks' probabilities).
LAMP_LEVELS = "lamp_levels"


def predict_track_batch(model: Any, tracks: Sequence[TrackSequence],
                        device: "str | torch.device" = "cpu",
                        intent_filter: Optional[IntentFilterConfig] = None) -> List[np.ndarray]:
    """Step a batch of tracks frame by frame; returns int64 ``[T_i, len(TASKS)]`` each
    (:func:`predict_track_probs` without the probabilities)."""
    return predict_track_probs(model, tracks, device, intent_filter)[0]


def predict_track_probs(model: Any, tracks: Sequence[TrackSequence],
                        device: "str | torch.device" = "cpu",
                        intent_filter: Optional[IntentFilterConfig] = None
                        ) -> Tuple[List[np.ndarray], List[Dict[str, np.ndarray]]]:
    """Step a batch of tracks frame by frame: the published classes and light probabilities.

    Args:
        model: A model backend (``runtime.backend.ModelBackend``: torch, onnxruntime), or
            a bare ``LightStateModel``, run through the torch backend on ``device``.
        tracks: The tracks (crops, mask, stamps).
        device: Where a bare model runs (a backend keeps its own).
        intent_filter: The filter over the model's outputs, as in the engine (default:
            its defaults; ``enabled=False`` gives the raw model's argmax).

    Returns:
        Per track: the published classes per frame, int64 ``[T_i, len(TASKS)]`` (rows of
        frames that are not stepped, mask False, are -1), and per light head the
        published probabilities ``[T_i, K]`` (NaN where not stepped).
    """
    return filter_track_probs(model_track_probs(model, tracks, device), tracks, intent_filter)


def _active(tracks: Sequence[TrackSequence], i: int) -> np.ndarray:
    """Indices of the tracks stepped at frame index ``i`` (they have it, its mask is set)."""
    return np.array([k for k, t in enumerate(tracks) if i < len(t) and bool(t.mask[i])],
                    np.int64)


def model_track_probs(model: Any, tracks: Sequence[TrackSequence],
                      device: "str | torch.device" = "cpu") -> Dict[str, np.ndarray]:
    """Step a batch of tracks frame by frame: every head's probabilities as the model
    gives them, before any filter.

    Each track's state is a row of the backend's row store, as in the state bank.

    Returns:
        Task -> float32 ``[len(tracks), longest track, K]``, NaN where a track has no
        stepped frame, and :data:`LAMP_LEVELS` -> ``[..., 2]`` the crops' lamp levels (the
        flash gate's input, as the engine computes them);
        :func:`filter_track_probs` turns it into what the node publishes.
    """
    backend = as_backend(model, str(device))
    n, length = len(tracks), max(len(t) for t in tracks)
    raw = {task: np.full((n, length, len(CLASS_NAMES[task])), np.nan, np.float32)
           for task in TASKS}
    raw[LAMP_LEVELS] = np.full((n, length, 2), np.nan, np.float32)
    states = backend.new_rows(n)
    for i in range(length):
        active = _active(tracks, i)
        if not len(active):
            continue
        crops = np.stack([tracks[k].crop_window(i, i + 1)[0] for k in active])
        out = backend.step(crops, backend.gather_rows(states, active))
        backend.store_rows(states, active, out.state)
        for task in TASKS:
            raw[task][active, i] = out.probs[task]
        raw[LAMP_LEVELS][active, i] = flash_gate.lamp_levels(crops)
    return raw


def filter_track_probs(raw: Dict[str, np.ndarray], tracks: Sequence[TrackSequence],
                       intent_filter: Optional[IntentFilterConfig] = None
                       ) -> Tuple[List[np.ndarray], List[Dict[str, np.ndarray]]]:
    """The intent filter over :func:`model_track_probs`'s outputs, driven by each track's
    stamps as in the engine: :func:`predict_track_probs`'s two lists. Cheap next to the
    model, so one model pass can be filtered and scored under many settings."""
    preds = [np.full((len(t), len(TASKS)), -1, np.int64) for t in tracks]
    probs: List[Dict[str, np.ndarray]] = [
        {task: np.full((len(t), len(CLASS_NAMES[task])), np.nan) for task in LIGHT_TASKS}
        for t in tracks]
    light_filter = IntentFilter(intent_filter)
    rows = light_filter.initial_rows(len(tracks))
    for i in range(max(len(t) for t in tracks)):
        active = _active(tracks, i)
        if not len(active):
            continue
        levels = raw[LAMP_LEVELS][active, i] if LAMP_LEVELS in raw else None
        cover = np.array([np.nan if tracks[k].cover is None else tracks[k].cover[i]
                          for k in active])
        filtered = light_filter.step({task: raw[task][active, i] for task in TASKS},
                                     np.array([tracks[k].stamps_ns[i] for k in active], np.int64),
                                     rows[active], levels, cover)
        rows[active] = filtered.rows
        labels = np.stack([filtered.states[t] for t in TASKS], axis=1)
        for row, k in enumerate(active):
            preds[k][i] = labels[row]
            for task in LIGHT_TASKS:
                probs[k][task][i] = filtered.probs[task][row]
    return preds, probs


T = TypeVar("T")


def chunks(items: Iterable[T], size: int) -> Iterator[List[T]]:
    """``items`` in lists of ``size`` (the last one shorter), consumed lazily."""
    chunk: List[T] = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def evaluate_tracks(model: Any, tracks: Iterable[TrackSequence],
                    settings: EvalSettings = EvalSettings(),
                    device: "str | torch.device" = "cpu", progress: bool = True,
                    total: Optional[int] = None,
                    intent_filter: Optional[IntentFilterConfig] = None) -> Dict[str, Any]:
    """Score a model on tracks with and without the grace window.

    Tracks are consumed lazily, ``settings.batch_tracks`` at a time, so a long test set
    never has to sit in memory at once.

    Args:
        model: A model backend, or a bare ``LightStateModel`` (run through the torch
            backend on ``device``, in eval mode).
        tracks: Tracks with ground truth (any iterable).
        settings: Scoring rules.
        device: Where a bare model runs.
        progress: Show a progress bar.
        total: Number of tracks, for the progress bar.
        intent_filter: The filter over the model's outputs (default: its defaults, as
            the node runs; ``enabled=False`` scores the raw model).

    Returns:
        :meth:`TrackScorer.result`: ``{"settings", "counts", "no_grace": report, "grace":
        report, "switches"}`` where ``counts`` says how many frames were stepped,
        excluded by the warm-up and (per head) by the grace window, plus
        ``"intent_filter"``: the filter's settings.

    Raises:
        ConfigError: There were no tracks.
    """
    backend = as_backend(model, str(device))
    intent_filter = intent_filter or IntentFilterConfig()
    scorer = TrackScorer(settings)
    bar = tqdm(total=total, desc="evaluate", unit="track", disable=not progress)
    for batch in chunks(tracks, settings.batch_tracks):
        score_batch(scorer, batch, model_track_probs(backend, batch), intent_filter)
        bar.update(len(batch))
    bar.close()
    return scorer_result(scorer, intent_filter)


def score_batch(scorer: TrackScorer, tracks: Sequence[TrackSequence], raw: Dict[str, np.ndarray],
                intent_filter: IntentFilterConfig) -> List[np.ndarray]:
    """Add a batch of tracks to ``scorer``: their :func:`model_track_probs` outputs ``raw``
    through the intent filter, as published. Returns the published states per track
    (``[T, len(TASKS)]``, -1 where none), for callers that count more than the scorer."""
    preds, probs = filter_track_probs(raw, tracks, intent_filter)
    for track, pred, prob in zip(tracks, preds, probs):
        scorer.add(track, pred, probs=prob)
    return list(preds)


def scorer_result(scorer: TrackScorer, intent_filter: IntentFilterConfig) -> Dict[str, Any]:
    """:func:`evaluate_tracks`'s result of a filled scorer.

    Raises:
        ConfigError: No track was added.
    """
    if scorer.counts["tracks"] == 0:
        raise ConfigError("nothing to evaluate: no tracks")
    return {**scorer.result(), "intent_filter": asdict(intent_filter)}
