"""The ideal causal observer: the best score any online model can reach on a split.

The ground truth of a blinker is its logical state: ON from the moment it is switched on
to the moment it is switched off, through the dark halves of the blink. A model that
sees frames one after another cannot know, during a dark phase, whether the blinker
was just switched off or is about to light again; it learns the truth only when the
next lit phase should have come. Some error after every switch-off is therefore
unavoidable, and the evaluation's no-grace report counts it.

This observer sees what every frame shows perfectly (the split's ``lit_labels``: each
lamp lit, dark or not visible) and knows each blinker's flasher timing (its longest dark
run while switched on, taken from the ground truth). Per frame and blinker it says:

* UNKNOWN when the lamp is not visible in this frame (as the ground truth does);
* ON when the lamp was lit at most one dark run plus one frame ago;
* OFF otherwise.

Brake and view are steady and copied from the ground truth; the intent follows from the
two blinkers by :func:`signal_light_node.labels.intent_from_lights`, as the labels do.
Scored with the evaluation's rules (:class:`.scoring.TrackScorer`), its report is the
ceiling of every metric; ``signal-light evaluate --ideal-observer`` writes it.
"""

from __future__ import annotations

from typing import Any, Dict, Iterable, Mapping

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, LightStatus, intent_from_lights
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.tracks import item_labels, track_from_item

_BLINKERS = (TASKS.index("left"), TASKS.index("right"))
_INTENT = TASKS.index("intent")
_ON, _OFF, _UNKNOWN = int(LightStatus.ON), int(LightStatus.OFF), int(LightStatus.UNKNOWN)


def longest_dark_run(lit: np.ndarray, state: np.ndarray) -> int:
    """Longest run of frames between two lit frames while the blinker stays switched on.

    Args:
        lit: int ``[T]`` what each frame shows (ON lit, OFF dark, UNKNOWN hidden).
        state: int ``[T]`` the logical state of the same blinker.

    Returns:
        The number of frames in the longest such run (0 when no blink was seen twice).
    """
    best = run = 0
    seen_lit = False
    for shown, switched_on in zip(lit, state == _ON):
        if not switched_on:
            seen_lit, run = False, 0
        elif shown == _ON:
            if seen_lit:
                best = max(best, run)
            seen_lit, run = True, 0
        else:
            run += 1
    return best


def ideal_observer(labels: np.ndarray, lit_labels: np.ndarray, fps: float) -> np.ndarray:
    """The ideal causal observer's predictions for one track.

    Args:
        labels: int ``[T, len(TASKS)]`` logical ground truth (negative: not labelled).
        lit_labels: int ``[T, len(TASKS)]`` what each frame shows.
        fps: Frame rate, for blinkers never seen to blink twice (half a second of patience).

    Returns:
        int64 ``[T, len(TASKS)]`` predicted classes (negative where the frame is not
        labelled).

    Raises:
        ConfigError: The two label arrays do not have the same ``[T, len(TASKS)]`` shape.
    """
    labels = np.asarray(labels, np.int64)
    lit_labels = np.asarray(lit_labels, np.int64)
    if labels.shape != lit_labels.shape or labels.ndim != 2 or labels.shape[1] != len(TASKS):
        raise ConfigError(f"labels and lit labels must both be [T, {len(TASKS)}], got "
                          f"{labels.shape} and {lit_labels.shape}")
    pred = labels.copy()
    for j in _BLINKERS:
        patience = longest_dark_run(lit_labels[:, j], labels[:, j]) or max(1, round(fps / 2))
        last_lit = None
        for f in range(len(pred)):
            shown = lit_labels[f, j]
            if shown < 0:
                continue
            if shown == _ON:
                last_lit = f
            if shown == _UNKNOWN:
                pred[f, j] = _UNKNOWN
            elif last_lit is not None and f - last_lit <= patience + 1:
                pred[f, j] = _ON
            else:
                pred[f, j] = _OFF
    for f in np.flatnonzero(labels[:, _INTENT] >= 0):
        pred[f, _INTENT] = int(intent_from_lights(int(pred[f, _BLINKERS[0]]),
                                                  int(pred[f, _BLINKERS[1]])))
    return pred


def score_ideal_observer(items: Iterable[Mapping[str, Any]],
                         settings: EvalSettings = EvalSettings()) -> Dict[str, Any]:
    """Score the ideal observer on split or stream items with the evaluation's rules.

    Args:
        items: Items with ``labels``, ``lit_labels``, ``mask`` and ``meta``.
        settings: Scoring rules (warm-up, grace window).

    Returns:
        :meth:`.evaluation.TrackScorer.result` of the observer.

    Raises:
        ConfigError: An item has no lit labels, or there were no items.
    """
    scorer = TrackScorer(settings)
    for i, item in enumerate(items):
        track = track_from_item(item, f"item {i}")
        lit = item_labels(item, "lit_labels", f"item {i}")
        pred = ideal_observer(track.labels, lit, track.fps)
        pred[~np.asarray(track.mask, bool)] = -1
        scorer.add(track, pred)
    if scorer.counts["tracks"] == 0:
        raise ConfigError("nothing to score: no tracks")
    return scorer.result()
