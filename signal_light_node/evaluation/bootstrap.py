"""How far a score can be trusted: resample the scenes, not the frames.

The frames of one track, and the tracks of one scene, share a camera, a light and a
drawing of the lamps; they are not independent draws. A split of 120 tracks may hold 22
scenes, and that is its sample size. :func:`scene_bootstrap` scores several files' published
states on the same resamples of scenes (with replacement), so the difference between two
files comes with an interval that knows how few scenes decided it.

The score is the one ``signal-light calibrate`` and the recipe's step 3 choose by: the mean of
intent macro-F1 and brake F1 (of ON), after the warm-up, without grace
(:func:`score_from_confusions`). Each file is passed once over the tracks; a resample only
sums per-track confusion matrices (:func:`track_confusions`), so a thousand resamples cost
about a second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Mapping, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import metrics_from_confusion
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LightStatus

#: The heads the score reads.
SCORED_TASKS: Tuple[str, ...] = ("intent", "brake")


@dataclass
class FileInterval:
    """One file's score and, against the first file, the paired difference.

    Attributes:
        score: The score on every track.
        interval: The score's 5th and 95th percentile over the resamples.
        difference: ``score`` less the first file's.
        difference_interval: The paired difference's 5th and 95th percentile.
        share_above: Share of resamples where this file scores above the first.
    """

    score: float
    interval: Tuple[float, float]
    difference: float
    difference_interval: Tuple[float, float]
    share_above: float


def track_confusions(tracks: Sequence[TrackSequence], preds: Sequence[np.ndarray],
                     settings: EvalSettings = EvalSettings()) -> Dict[str, np.ndarray]:
    """Per track, the scored frames' confusion matrix of each head of :data:`SCORED_TASKS`.

    Args:
        tracks: The tracks with their ground truth.
        preds: Per track the published classes ``[len(track), len(TASKS)]``.
        settings: Warm-up and grace, as the scorer's.

    Returns:
        Task -> int64 ``[len(tracks), K, K]``.
    """
    if len(tracks) != len(preds):
        raise ConfigError(f"{len(tracks)} tracks but {len(preds)} predictions")
    rows: Dict[str, List[np.ndarray]] = {t: [] for t in SCORED_TASKS}
    for track, pred in zip(tracks, preds):
        scorer = TrackScorer(settings)
        scorer.add(track, pred, breakdowns=False)
        for task in SCORED_TASKS:
            rows[task].append(scorer.strict.confusion(task))
    return {t: np.stack(v) for t, v in rows.items()}


def score_from_confusions(intent: np.ndarray, brake: np.ndarray) -> float:
    """The mean of intent macro-F1 and brake F1 of ON from summed confusion matrices."""
    macro = metrics_from_confusion("intent", intent)["macro_f1"]
    brake_f1 = metrics_from_confusion("brake", brake)["per_class"]["f1"][int(LightStatus.ON)]
    return 0.5 * (float(macro or 0.0) + float(brake_f1 or 0.0))


def _score(confusions: Mapping[str, np.ndarray], rows: np.ndarray) -> float:
    return score_from_confusions(confusions["intent"][rows].sum(0),
                                 confusions["brake"][rows].sum(0))


def scene_groups(tracks: Sequence[TrackSequence]) -> List[np.ndarray]:
    """Track indices per scene; a track without a scene is a scene of its own."""
    keys = [t.scene or f"track:{i}" for i, t in enumerate(tracks)]
    order = sorted(set(keys))
    return [np.flatnonzero(np.asarray(keys) == key) for key in order]


def require_same_tracks(reference: Sequence[TrackSequence], tracks: Sequence[TrackSequence],
                        what: str) -> None:
    """Raise ConfigError unless ``tracks`` are ``reference``'s tracks in the same order (the
    same scenes and labels frame for frame), so that confusions of the two pair track by
    track: twin splits cut with other crops are; two different splits are not.

    Args:
        what: Whose tracks ``tracks`` are, for the message.
    """
    if len(tracks) != len(reference):
        raise ConfigError(f"{what}: {len(tracks)} tracks, the first file's data {len(reference)}")
    for i, (a, b) in enumerate(zip(reference, tracks)):
        if a.scene != b.scene or not np.array_equal(a.labels, b.labels):
            raise ConfigError(f"{what}: track {i} ({b.track_id}) is not the first file's "
                              f"{a.track_id} (other scene or labels)")


def scene_bootstrap(files: Sequence[Mapping[str, np.ndarray]], groups: Sequence[np.ndarray],
                    resamples: int = 1000, seed: int = 0) -> List[FileInterval]:
    """Score every file on the same resamples of scenes; differences against ``files[0]``.

    Args:
        files: Per file :func:`track_confusions` of the same tracks, in the same order.
        groups: :func:`scene_groups` of those tracks.
        resamples: How many resamples of the scenes.
        seed: Seed of the resampling.

    Raises:
        ConfigError: No file, no scene, fewer than one resample, or files of other tracks.
    """
    if not files or not groups or resamples < 1:
        raise ConfigError(f"need files, scenes and resamples (got {len(files)}, "
                          f"{len(groups)}, {resamples})")
    n = len(files[0]["intent"])
    if any(len(f[t]) != n for f in files for t in SCORED_TASKS):
        raise ConfigError("the files' confusions are not of the same tracks")
    rng = np.random.default_rng(seed)
    scores = np.zeros((resamples, len(files)))
    for r in range(resamples):
        rows = np.concatenate([groups[g] for g in rng.integers(0, len(groups), len(groups))])
        scores[r] = [_score(f, rows) for f in files]
    every = np.arange(n)
    points = [_score(f, every) for f in files]
    out = []
    for i, point in enumerate(points):
        diff = scores[:, i] - scores[:, 0]
        out.append(FileInterval(
            score=point, interval=_percentiles(scores[:, i]), difference=point - points[0],
            difference_interval=_percentiles(diff), share_above=float(np.mean(diff > 0))))
    return out


def _percentiles(values: np.ndarray) -> Tuple[float, float]:
    low, high = np.percentile(values, [5, 95])
    return float(low), float(high)
