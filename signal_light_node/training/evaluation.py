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

Scoring rules (documented in the report's ``settings``):

* **Warm-up**: the first frames of every track are not scored: a frame is scored only
  when at least ``warmup_frames`` frames of the track came before it *and* at least
  ``warmup_seconds`` have passed since the track's first frame (a blink needs about one
  cycle, 0.5–1 s, before it can be told from a lamp that is off).
* **Grace window** (second report): for each head separately, frames within
  ``grace_seconds`` after a change of that head's ground-truth label (the frame of the
  change included) are not scored either, since the model needs a moment to notice that
  a blinker was switched on or off.

Breakdowns: lighting (the track's), view (the ground-truth view of the frame), box-size
band and occlusion band (:mod:`signal_light_node.tools.metrics`).

Switches (flicker): per head and track, how often the predicted and the true class
change from one scored frame to the next (after the warm-up, no grace window);
reported per track and summed, with their ratio (``metrics.SwitchCounter``).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence

import numpy as np
import torch
from tqdm import tqdm

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig
from signal_light_node.labels import CLASS_NAMES, TASKS
from signal_light_node.tools.metrics import (MetricAccumulator, SwitchCounter, box_size_band,
                                       occlusion_band)
from signal_light_node.model.backends.registry import as_backend
from signal_light_node.training.sources import TrackSequence

logger = logging.getLogger(__name__)

_VIEW = TASKS.index("view")


@dataclass(frozen=True)
class EvalSettings:
    """Scoring rules (see the module docstring).

    Attributes:
        warmup_frames: Frames at the start of each track that are never scored.
        warmup_seconds: Time from a track's first frame during which nothing is scored.
        grace_seconds: Time after each ground-truth change not scored in the grace report.
        batch_tracks: Tracks stepped together.
    """

    warmup_frames: int = 10
    warmup_seconds: float = 1.0
    grace_seconds: float = 0.5
    batch_tracks: int = 32

    def __post_init__(self) -> None:
        if self.warmup_frames < 0 or self.warmup_seconds < 0 or self.grace_seconds < 0:
            raise ConfigError("warm-up and grace window must be >= 0")
        if self.batch_tracks < 1:
            raise ConfigError(f"batch_tracks must be >= 1, got {self.batch_tracks}")


def warmup_mask(track: TrackSequence, settings: EvalSettings) -> np.ndarray:
    """bool ``[T]``: True for frames scored after the warm-up (valid frames only).

    A frame is past the warm-up when ``warmup_frames`` valid frames of the track precede
    it and its stamp is at least ``warmup_seconds`` after the first valid frame's.
    """
    valid = np.asarray(track.mask, bool)
    out = np.zeros(len(track), bool)
    if not valid.any():
        return out
    order = np.cumsum(valid) - 1  # number of valid frames before each frame
    t0 = track.stamps_ns[np.flatnonzero(valid)[0]]
    late = (track.stamps_ns - t0) >= int(round(settings.warmup_seconds * 1e9))
    return valid & (order >= settings.warmup_frames) & late


def grace_mask(track: TrackSequence, task_index: int, settings: EvalSettings) -> np.ndarray:
    """bool ``[T]``: False for frames within the grace window after a label change.

    A change is a valid frame whose label differs from the previous valid frame's; the
    window covers stamps in ``[change, change + grace_seconds)``.
    """
    valid = np.flatnonzero(np.asarray(track.mask, bool) & (track.labels[:, task_index] >= 0))
    keep = np.ones(len(track), bool)
    if valid.size < 2 or settings.grace_seconds <= 0:
        return keep
    lab = track.labels[valid, task_index]
    changes = valid[1:][lab[1:] != lab[:-1]]
    grace = int(round(settings.grace_seconds * 1e9))
    for c in changes:
        start = track.stamps_ns[c]
        keep &= ~((track.stamps_ns >= start) & (track.stamps_ns < start + grace))
    return keep


def predict_track_batch(model: Any, tracks: Sequence[TrackSequence],
                        device: "str | torch.device" = "cpu",
                        intent_filter: Optional[IntentFilterConfig] = None) -> List[np.ndarray]:
    """Step a batch of tracks frame by frame; returns int64 ``[T_i, len(TASKS)]`` each.

    Args:
        model: A model backend (``runtime.backend.ModelBackend``: torch, onnxruntime), or
            a bare ``LightStateModel``, run through the torch backend on ``device``.
        tracks: The tracks (crops, mask, stamps).
        device: Where a bare model runs (a backend keeps its own).
        intent_filter: The filter over the model's outputs, as in the engine (default:
            its defaults; ``enabled=False`` gives the raw model's argmax).

    Returns:
        Published classes per frame; rows of frames that are not stepped (mask False)
        are -1.
    """
    backend = as_backend(model, str(device))
    n = len(tracks)
    length = max(len(t) for t in tracks)
    preds = [np.full((len(t), len(TASKS)), -1, np.int64) for t in tracks]
    # Each track's state is a row of the backend's row store, as in the state bank.
    states = backend.new_rows(n)
    light_filter = IntentFilter(intent_filter)
    rows = light_filter.initial_rows(n)
    for i in range(length):
        active = np.array([k for k, t in enumerate(tracks) if i < len(t) and bool(t.mask[i])],
                          np.int64)
        if not len(active):
            continue
        crops = np.stack([tracks[k].crop_window(i, i + 1)[0] for k in active])
        out = backend.step(crops, backend.gather_rows(states, active))
        backend.store_rows(states, active, out.state)
        filtered = light_filter.step(out.probs,
                                     np.array([tracks[k].stamps_ns[i] for k in active], np.int64),
                                     rows[active])
        rows[active] = filtered.rows
        labels = np.stack([filtered.states[t] for t in TASKS], axis=1)
        for row, k in enumerate(active):
            preds[k][i] = labels[row]
    return preds


def _groups(track: TrackSequence, rows: np.ndarray) -> Dict[str, Any]:
    view = track.labels[rows, _VIEW]
    names = np.array(CLASS_NAMES["view"] + ("unknown",), dtype=object)
    view_names = names[np.where((view >= 0) & (view < len(CLASS_NAMES["view"])), view, -1)]
    return {"lighting": track.lighting or "unknown",
            "view": view_names,
            "box_size": box_size_band(track.box_size[rows]),
            "occlusion": occlusion_band(track.occlusion[rows])}


def _chunks(tracks: Iterable[TrackSequence], size: int) -> Iterator[List[TrackSequence]]:
    chunk: List[TrackSequence] = []
    for track in tracks:
        chunk.append(track)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class TrackScorer:
    """Scores predicted classes of whole tracks with the warm-up and grace-window rules.

    The one scoring loop: :func:`evaluate_tracks` feeds it the model's predictions and
    ``replay.score_summary`` the engine's.

    Args:
        settings: Scoring rules.

    Attributes:
        settings: The rules.
        strict: Metrics after the warm-up.
        graced: Metrics after the warm-up, without the grace windows.
        switches: Per head, the changes of the predicted and true classes along the
            tracks' scored frames.
        counts: Tracks and frames seen, frames stepped, excluded by the warm-up, scored,
            and per head excluded by the grace window.
    """

    def __init__(self, settings: EvalSettings = EvalSettings()) -> None:
        self.settings = settings
        self.strict, self.graced = MetricAccumulator(), MetricAccumulator()
        self.switches = {task: SwitchCounter() for task in TASKS}
        self.counts: Dict[str, Any] = {"tracks": 0, "frames": 0, "stepped": 0,
                                       "warmup_excluded": 0, "scored": 0,
                                       "grace_excluded": {t: 0 for t in TASKS}}

    def add(self, track: TrackSequence, pred: np.ndarray, breakdowns: bool = True) -> None:
        """Score one track.

        Args:
            track: The track with its ground truth; frames with ``mask`` False count as
                not stepped and are never scored.
            pred: int64 ``[len(track), len(TASKS)]`` predicted classes.
            breakdowns: Also group the metrics by lighting, view, box size and occlusion.
        """
        stepped = np.asarray(track.mask, bool)
        scored = warmup_mask(track, self.settings)
        counts = self.counts
        counts["tracks"] += 1
        counts["frames"] += len(track)
        counts["stepped"] += int(stepped.sum())
        counts["warmup_excluded"] += int((stepped & ~scored).sum())
        counts["scored"] += int(scored.sum())
        rows = np.flatnonzero(scored)
        groups = _groups(track, rows) if breakdowns else {}
        for i, task in enumerate(TASKS):
            y, p = track.labels[rows, i], pred[rows, i]
            self.strict.add(task, y, p, groups)
            self.switches[task].add(track.track_id, y, p)
            keep = grace_mask(track, i, self.settings)[rows]
            counts["grace_excluded"][task] += int((~keep).sum())
            self.graced.add(task, y[keep], p[keep],
                            {k: (v if isinstance(v, str) else v[keep])
                             for k, v in groups.items()})

    def result(self) -> Dict[str, Any]:
        """``{"settings", "counts", "no_grace": report, "grace": report, "switches"}``.

        The reports come from :meth:`MetricAccumulator.report`, the switches (task ->
        report) from :meth:`SwitchCounter.report`.
        """
        return {"settings": asdict(self.settings), "counts": self.counts,
                "no_grace": self.strict.report(), "grace": self.graced.report(),
                "switches": {t: c.report() for t, c in self.switches.items()}}


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
    for batch in _chunks(tracks, settings.batch_tracks):
        preds = predict_track_batch(backend, batch, intent_filter=intent_filter)
        for track, pred in zip(batch, preds):
            scorer.add(track, pred)
        bar.update(len(batch))
    bar.close()
    if scorer.counts["tracks"] == 0:
        raise ConfigError("nothing to evaluate: no tracks")
    return {**scorer.result(), "intent_filter": asdict(intent_filter)}
