"""Scoring whole tracks: the warm-up and grace-window rules, breakdowns and switches.

:class:`TrackScorer` is the one scoring loop: the streaming evaluation
(:func:`signal_light_node.evaluation.streaming.evaluate_tracks`) feeds it the model's
predictions, ``signal-light replay`` (``tools.replay.score_summary``) the engine's and the
ideal observer (:mod:`.ideal_observer`) its own.

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
band and occlusion band (:mod:`signal_light_node.evaluation.metrics`).

Switches (flicker): per head and track, how often the predicted and the true class
change from one scored frame to the next (after the warm-up, no grace window);
reported per track and summed, with their ratio (``metrics.SwitchCounter``), and as
a per-track table over the heads, worst first (``metrics.flicker_table``).

Light outcomes (``metrics.LightOutcomes``, after the warm-up, no grace window): per light
head the share of frames with a true OFF or ON published as UNKNOWN (with the breakdowns,
also per pair of true and published view), and, where the published probabilities are
given, their reliability (bins and ECE).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Dict, Mapping, Optional

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import (LightOutcomes, MetricAccumulator,
                                                  SwitchCounter, box_size_band, flicker_table,
                                                  occlusion_band)
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import CLASS_NAMES, LIGHT_TASKS, TASKS

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


def view_names(view: np.ndarray) -> np.ndarray:
    """View class indices as names (``"unknown"`` for the UNKNOWN label or none)."""
    names = np.array(CLASS_NAMES["view"] + ("unknown",), dtype=object)
    return names[np.where((view >= 0) & (view < len(CLASS_NAMES["view"])), view, -1)]


def _groups(track: TrackSequence, rows: np.ndarray) -> Dict[str, Any]:
    return {"lighting": track.lighting or "unknown",
            "view": view_names(track.labels[rows, _VIEW]),
            "box_size": box_size_band(track.box_size[rows]),
            "occlusion": occlusion_band(track.occlusion[rows])}


class TrackScorer:
    """Scores predicted classes of whole tracks with the warm-up and grace-window rules.

    The one scoring loop: :func:`.streaming.evaluate_tracks` feeds it the model's
    predictions and ``replay.score_summary`` the engine's.

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
        self.lights = LightOutcomes()
        self.counts: Dict[str, Any] = {"tracks": 0, "frames": 0, "stepped": 0,
                                       "warmup_excluded": 0, "scored": 0,
                                       "grace_excluded": {t: 0 for t in TASKS}}

    def add(self, track: TrackSequence, pred: np.ndarray, breakdowns: bool = True,
            probs: Optional[Mapping[str, np.ndarray]] = None) -> None:
        """Score one track.

        Args:
            track: The track with its ground truth; frames with ``mask`` False count as
                not stepped and are never scored.
            pred: int64 ``[len(track), len(TASKS)]`` predicted classes.
            breakdowns: Also group the metrics by lighting, view, box size and occlusion.
            probs: Light head -> ``[len(track), K]`` published probabilities, for the
                calibration report (optional).
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
        views = (groups["view"], view_names(pred[rows, _VIEW])) if breakdowns else None
        for i, task in enumerate(TASKS):
            y, p = track.labels[rows, i], pred[rows, i]
            self.strict.add(task, y, p, groups)
            self.switches[task].add(track.track_id, y, p)
            if task in LIGHT_TASKS:
                self.lights.add(task, y, p, None if probs is None or task not in probs
                                else np.asarray(probs[task])[rows], views)
            keep = grace_mask(track, i, self.settings)[rows]
            counts["grace_excluded"][task] += int((~keep).sum())
            self.graced.add(task, y[keep], p[keep],
                            {k: (v if isinstance(v, str) else v[keep])
                             for k, v in groups.items()})

    def result(self) -> Dict[str, Any]:
        """``{"settings", "counts", "no_grace": report, "grace": report, "switches",
        "flicker", "unknown_share", "unknown_by_view", "calibration"}``.

        The reports come from :meth:`MetricAccumulator.report`, the switches (task ->
        report) from :meth:`SwitchCounter.report`, ``flicker`` from
        :func:`~.metrics.flicker_table`, ``unknown_share``, ``unknown_by_view`` and
        ``calibration`` (light -> reliability report, the heads given probabilities only)
        from :class:`~.metrics.LightOutcomes`.
        """
        switches = {t: c.report() for t, c in self.switches.items()}
        return {"settings": asdict(self.settings), "counts": self.counts,
                "no_grace": self.strict.report(), "grace": self.graced.report(),
                "switches": switches, "flicker": flicker_table(switches),
                "unknown_share": self.lights.unknown_share(),
                "unknown_by_view": self.lights.unknown_by_view(),
                "calibration": self.lights.calibration()}
