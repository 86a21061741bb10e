"""Per-frame classification metrics of the light-state heads (pure numpy).

Definitions (labels as in :mod:`signal_light_node.labels`; rows of every confusion
matrix are the ground truth, columns the prediction):

* **accuracy**: fraction of frames whose prediction equals the ground truth.
* **macro recall**: mean of the per-class recalls over the classes that occur in the
  ground truth (recall of a class that never occurs is 0/0, so it is left out).
* **macro F1**: mean of the per-class F1 scores over the classes that occur in the
  ground truth *or* in the predictions. A class that is predicted but never true has
  F1 = 0, so spurious predictions of an absent class lower the score instead of being
  ignored; classes that appear in neither are left out because they say nothing.
* **FP rate** (research definition): of the frames whose ground truth is a "negative"
  state, the fraction classified as any other state. For the light heads (brake, left,
  right) the negative states are OFF and UNKNOWN; for intent they are OFF and UNKNOWN
  too (no blinker active, or not judgeable).
* **FN rate**: of the frames whose ground truth is a "positive" state, the fraction
  classified as any other state. For the light heads the positive state is ON; for
  intent the natural analogue is LEFT, RIGHT and HAZARD (a blinker active), so a LEFT
  predicted as HAZARD counts as a false negative as well.
* The view head has no OFF/ON notion, so its FP and FN rates are ``None``.

A rate whose denominator is empty is ``None`` (JSON ``null``), never 0 or NaN, so a
report never claims a perfect score for something it did not see.

:class:`MetricAccumulator` collects predictions task by task with per-frame group
values (lighting, view, box-size band, occlusion band, ...) and reports the metrics
overall and per group value.

**Switches** (flicker): along each track, the number of frames whose class differs from
the previous scored frame's, for the prediction and for the ground truth;
:class:`SwitchCounter` sums them over tracks and reports their ratio (predicted / true
changes: 1 is an output that changes as often as the truth, more is flicker).
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.labels import CLASS_NAMES, LIGHT_TASKS, TASKS, Intent, LightStatus

#: Ground-truth classes whose misclassification is a false positive, per task.
NEGATIVE_CLASSES: Dict[str, Tuple[int, ...]] = {
    "intent": (int(Intent.OFF), int(Intent.UNKNOWN)),
    **{t: (int(LightStatus.OFF), int(LightStatus.UNKNOWN)) for t in LIGHT_TASKS},
}

#: Ground-truth classes whose misclassification is a false negative, per task.
POSITIVE_CLASSES: Dict[str, Tuple[int, ...]] = {
    "intent": (int(Intent.LEFT), int(Intent.RIGHT), int(Intent.HAZARD)),
    **{t: (int(LightStatus.ON),) for t in LIGHT_TASKS},
}

#: Upper edges (exclusive) of the box-size bands in pixels (``sqrt(width * height)`` of
#: the tracked box, as the data stream records it).
BOX_SIZE_EDGES: Tuple[float, ...] = (32.0, 64.0, 128.0)
BOX_SIZE_BANDS: Tuple[str, ...] = ("<32px", "32-64px", "64-128px", ">=128px")

#: Edges of the occlusion bands (visible fraction hidden, 0..1).
OCCLUSION_EDGES: Tuple[float, ...] = (0.1, 0.5)
OCCLUSION_BANDS: Tuple[str, ...] = ("none", "partial", "heavy")

#: Value used for a group whose value is not known (e.g. occlusion in a user's bag).
UNKNOWN_GROUP = "unknown"

ArrayLike = Union[np.ndarray, Sequence[int]]


def _labels(values: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ConfigError(f"{name} must be one-dimensional, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.equal(np.mod(arr, 1), 0)):
            raise ConfigError(f"{name} must hold integer class indices, got dtype {arr.dtype}")
    return arr.astype(np.int64, copy=False)


def _pair(y_true: ArrayLike, y_pred: ArrayLike) -> Tuple[np.ndarray, np.ndarray]:
    t, p = _labels(y_true, "y_true"), _labels(y_pred, "y_pred")
    if t.shape != p.shape:
        raise ConfigError(f"y_true and y_pred differ in length: {t.shape[0]} vs {p.shape[0]}")
    return t, p


def n_classes(task: str) -> int:
    """Number of classes of a head; raises ConfigError for an unknown task name."""
    if task not in CLASS_NAMES:
        raise ConfigError(f"unknown task {task!r}; expected one of {', '.join(TASKS)}")
    return len(CLASS_NAMES[task])


def confusion_matrix(y_true: ArrayLike, y_pred: ArrayLike, num_classes: int) -> np.ndarray:
    """Count matrix with rows = ground truth and columns = prediction.

    Args:
        y_true: Ground-truth class indices, shape [N].
        y_pred: Predicted class indices, shape [N].
        num_classes: K; every index must lie in 0..K-1.

    Returns:
        int64 array [K, K]; entry (i, j) counts frames of true class i predicted as j.

    Raises:
        ConfigError: Shapes differ or an index is outside 0..K-1.
    """
    t, p = _pair(y_true, y_pred)
    for name, arr in (("y_true", t), ("y_pred", p)):
        if arr.size and (arr.min() < 0 or arr.max() >= num_classes):
            raise ConfigError(f"{name} holds class indices outside 0..{num_classes - 1}: "
                              f"{sorted(set(arr[(arr < 0) | (arr >= num_classes)].tolist()))}")
    flat = np.bincount(t * num_classes + p, minlength=num_classes * num_classes)
    return flat.reshape(num_classes, num_classes).astype(np.int64)


def normalise_rows(matrix: np.ndarray) -> np.ndarray:
    """Row-normalised confusion matrix: each row sums to 1, an empty row stays all 0."""
    m = np.asarray(matrix, dtype=np.float64)
    totals = m.sum(axis=1, keepdims=True)
    return np.divide(m, totals, out=np.zeros_like(m), where=totals > 0)


def _ratio(num: float, den: float) -> Optional[float]:
    return float(num) / float(den) if den > 0 else None


def accuracy(y_true: ArrayLike, y_pred: ArrayLike) -> Optional[float]:
    """Fraction of equal entries; ``None`` for empty input."""
    t, p = _pair(y_true, y_pred)
    return _ratio(np.count_nonzero(t == p), t.size)


def per_class_scores(matrix: np.ndarray) -> Dict[str, List[Optional[float]]]:
    """Precision, recall and F1 of every class of a confusion matrix.

    A score whose denominator is zero is ``None``; F1 is 0 when precision and recall
    are both defined and both 0, or when only one of them is defined (a class that is
    predicted but never true, or true but never predicted).

    Returns:
        ``{"precision": [...], "recall": [...], "f1": [...], "support": [...]}``, one
        entry per class.
    """
    m = np.asarray(matrix, dtype=np.float64)
    tp = np.diag(m)
    true_n = m.sum(axis=1)
    pred_n = m.sum(axis=0)
    precision = [_ratio(tp[k], pred_n[k]) for k in range(m.shape[0])]
    recall = [_ratio(tp[k], true_n[k]) for k in range(m.shape[0])]
    f1: List[Optional[float]] = []
    for k in range(m.shape[0]):
        if true_n[k] == 0 and pred_n[k] == 0:
            f1.append(None)
        else:
            # 2TP / (2TP + FP + FN) equals the harmonic mean where both are defined and
            # gives 0 for a class that is only predicted or only true.
            f1.append(float(2 * tp[k] / (true_n[k] + pred_n[k])))
    return {"precision": precision, "recall": recall, "f1": f1,
            "support": [int(v) for v in true_n]}


def _mean(values: Iterable[Optional[float]]) -> Optional[float]:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def macro_recall(matrix: np.ndarray) -> Optional[float]:
    """Mean recall over the classes present in the ground truth."""
    return _mean(per_class_scores(matrix)["recall"])


def macro_f1(matrix: np.ndarray) -> Optional[float]:
    """Mean F1 over the classes present in the ground truth or the predictions."""
    return _mean(per_class_scores(matrix)["f1"])


def _rate_off_diagonal(matrix: np.ndarray, rows: Sequence[int]) -> Optional[float]:
    m = np.asarray(matrix)
    rows = [r for r in rows if r < m.shape[0]]
    total = sum(int(m[r].sum()) for r in rows)
    wrong = sum(int(m[r].sum() - m[r, r]) for r in rows)
    return _ratio(wrong, total)


def fp_rate(task: str, matrix: np.ndarray) -> Optional[float]:
    """False-positive rate of a task (see the module docstring); ``None`` for view."""
    rows = NEGATIVE_CLASSES.get(task)
    return None if rows is None else _rate_off_diagonal(matrix, rows)


def fn_rate(task: str, matrix: np.ndarray) -> Optional[float]:
    """False-negative rate of a task (see the module docstring); ``None`` for view."""
    rows = POSITIVE_CLASSES.get(task)
    return None if rows is None else _rate_off_diagonal(matrix, rows)


def task_metrics(task: str, y_true: ArrayLike, y_pred: ArrayLike) -> Dict[str, object]:
    """All metrics of one head.

    Args:
        task: A name of ``labels.TASKS``.
        y_true: Ground-truth class indices [N].
        y_pred: Predicted class indices [N].

    Returns:
        A JSON-ready dict: ``n``, ``accuracy``, ``macro_recall``, ``macro_f1``,
        ``fp_rate``, ``fn_rate``, ``class_names``, ``per_class`` (precision / recall /
        F1 / support lists), ``confusion`` (counts, rows = ground truth) and
        ``confusion_normalised`` (rows sum to 1).
    """
    k = n_classes(task)
    matrix = confusion_matrix(y_true, y_pred, k)
    return metrics_from_confusion(task, matrix)


def metrics_from_confusion(task: str, matrix: np.ndarray) -> Dict[str, object]:
    """The metrics of :func:`task_metrics` computed from a count matrix."""
    m = np.asarray(matrix, dtype=np.int64)
    n = int(m.sum())
    return {
        "n": n,
        "accuracy": _ratio(np.trace(m), n),
        "macro_recall": macro_recall(m),
        "macro_f1": macro_f1(m),
        "fp_rate": fp_rate(task, m),
        "fn_rate": fn_rate(task, m),
        "class_names": list(CLASS_NAMES[task]),
        "per_class": per_class_scores(m),
        "confusion": m.tolist(),
        "confusion_normalised": normalise_rows(m).round(6).tolist(),
    }


def _band(values: ArrayLike, edges: Sequence[float], names: Sequence[str]) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    idx = np.searchsorted(np.asarray(edges), v, side="right")
    out = np.asarray(names, dtype=object)[np.minimum(idx, len(names) - 1)]
    out[~np.isfinite(v)] = UNKNOWN_GROUP
    return out


def box_size_band(size_px: ArrayLike) -> np.ndarray:
    """Band name of each box size in pixels (<32, 32-64, 64-128, >=128); NaN gives ``"unknown"``."""
    return _band(size_px, BOX_SIZE_EDGES, BOX_SIZE_BANDS)


def occlusion_band(occlusion: ArrayLike) -> np.ndarray:
    """Band name of each occlusion fraction: none < 0.1 <= partial < 0.5 <= heavy."""
    return _band(occlusion, OCCLUSION_EDGES, OCCLUSION_BANDS)


GroupValues = Union[str, Sequence[str], np.ndarray]


class MetricAccumulator:
    """Collects per-frame predictions and reports metrics overall and per group.

    Example::

        acc = MetricAccumulator()
        acc.add("intent", y_true, y_pred, {"lighting": "night", "view": view_names})
        report = acc.report()

    Frames whose ground truth is negative (e.g. -1 for "not labelled") are skipped.
    """

    def __init__(self) -> None:
        # task -> K x K counts overall; task -> group -> value -> counts.
        self._overall: Dict[str, np.ndarray] = {}
        self._groups: Dict[str, Dict[str, Dict[str, np.ndarray]]] = defaultdict(
            lambda: defaultdict(dict))

    def add(self, task: str, y_true: ArrayLike, y_pred: ArrayLike,
            groups: Optional[Mapping[str, GroupValues]] = None) -> None:
        """Add frames of one task.

        Args:
            task: A name of ``labels.TASKS``.
            y_true: Ground-truth class indices [N]; negative entries are skipped.
            y_pred: Predicted class indices [N].
            groups: Group name -> one value for all N frames, or N values.

        Raises:
            ConfigError: Unknown task, mismatched lengths or out-of-range classes.
        """
        k = n_classes(task)
        t, p = _pair(y_true, y_pred)
        keep = t >= 0
        t, p = t[keep], p[keep]
        matrix = confusion_matrix(t, p, k)
        self._overall[task] = self._overall.get(task, np.zeros((k, k), np.int64)) + matrix
        for name, values in (groups or {}).items():
            if isinstance(values, str):
                col = np.full(keep.shape[0], values, dtype=object)
            else:
                col = np.asarray(values, dtype=object).reshape(-1)
                if col.shape[0] != keep.shape[0]:
                    raise ConfigError(f"group {name!r} has {col.shape[0]} values for "
                                      f"{keep.shape[0]} frames")
            col = col[keep].astype(str)
            for value in np.unique(col):
                sel = col == value
                bucket = self._groups[name][str(value)]
                bucket[task] = bucket.get(task, np.zeros((k, k), np.int64)) + \
                    confusion_matrix(t[sel], p[sel], k)

    def add_frames(self, y_true: np.ndarray, y_pred: np.ndarray,
                   groups: Optional[Mapping[str, GroupValues]] = None,
                   tasks: Sequence[str] = TASKS) -> None:
        """Add frames of every task at once: ``y_true``/``y_pred`` are [N, len(tasks)]."""
        t, p = np.asarray(y_true), np.asarray(y_pred)
        if t.ndim != 2 or t.shape != p.shape or t.shape[1] != len(tasks):
            raise ConfigError(f"expected y_true and y_pred of shape [N, {len(tasks)}], got "
                              f"{t.shape} and {p.shape}")
        for i, task in enumerate(tasks):
            self.add(task, t[:, i], p[:, i], groups)

    def confusion(self, task: str) -> np.ndarray:
        """Overall count matrix of a task (zeros if nothing was added)."""
        k = n_classes(task)
        return self._overall.get(task, np.zeros((k, k), np.int64)).copy()

    def report(self) -> Dict[str, object]:
        """Metrics overall, per group value, and a summary of the headline figures.

        Returns:
            ``{"overall": {task: metrics}, "groups": {group: {value: {task: metrics}}},
            "summary": {...}}`` where metrics are :func:`task_metrics` dicts and the
            summary holds intent macro-F1, brake accuracy, intent FP/FN rates and the
            FP/FN rates pooled over the three light heads.
        """
        overall = {t: metrics_from_confusion(t, m) for t, m in self._ordered(self._overall)}
        groups = {
            name: {value: {t: metrics_from_confusion(t, m) for t, m in self._ordered(by_task)}
                   for value, by_task in sorted(values.items())}
            for name, values in self._groups.items()
        }
        return {"overall": overall, "groups": groups, "summary": self._summary(overall)}

    @staticmethod
    def _ordered(by_task: Mapping[str, np.ndarray]) -> List[Tuple[str, np.ndarray]]:
        return [(t, by_task[t]) for t in TASKS if t in by_task]

    def _summary(self, overall: Mapping[str, Mapping[str, object]]) -> Dict[str, object]:
        def get(task: str, key: str) -> Optional[float]:
            return overall.get(task, {}).get(key)  # type: ignore[return-value]

        pooled_fp = [0, 0]
        pooled_fn = [0, 0]
        for t in LIGHT_TASKS:
            if t not in self._overall:
                continue
            m = self._overall[t]
            for rows, acc in ((NEGATIVE_CLASSES[t], pooled_fp), (POSITIVE_CLASSES[t], pooled_fn)):
                acc[0] += sum(int(m[r].sum() - m[r, r]) for r in rows)
                acc[1] += sum(int(m[r].sum()) for r in rows)
        return {
            "intent_macro_f1": get("intent", "macro_f1"),
            "brake_accuracy": get("brake", "accuracy"),
            "intent_fp_rate": get("intent", "fp_rate"),
            "intent_fn_rate": get("intent", "fn_rate"),
            "lights_fp_rate": _ratio(*pooled_fp),
            "lights_fn_rate": _ratio(*pooled_fn),
        }


def count_changes(labels: ArrayLike) -> int:
    """How often a sequence of classes changes from one element to the next."""
    arr = _labels(labels, "labels")
    return int(np.count_nonzero(arr[1:] != arr[:-1]))


class SwitchCounter:
    """Changes of the predicted and of the true class along tracks (see the module docstring).

    The one place where switches are counted: the evaluation and the replay summary both
    feed it through ``evaluation.scoring.TrackScorer``.
    """

    def __init__(self) -> None:
        self._per_track: Dict[str, Tuple[int, int]] = {}

    def add(self, track_id: str, y_true: ArrayLike, y_pred: ArrayLike) -> None:
        """Count one track's changes.

        Args:
            track_id: The track's name (a repeated name adds to its counts).
            y_true: Ground-truth classes of its scored frames, in time order; frames
                with a negative (unlabelled) truth are left out of both sequences.
            y_pred: Predicted classes of the same frames.

        Raises:
            ConfigError: The two differ in length or are not 1-D class indices.
        """
        t, p = _pair(y_true, y_pred)
        keep = t >= 0
        pred, true = self._per_track.get(track_id, (0, 0))
        self._per_track[track_id] = (pred + count_changes(p[keep]),
                                     true + count_changes(t[keep]))

    def report(self) -> Dict[str, object]:
        """``{"predicted", "true", "ratio", "per_track": {id: {"predicted", "true"}}}``.

        ``ratio`` is predicted / true changes, ``None`` when the truth never changed.
        """
        pred = sum(p for p, _ in self._per_track.values())
        true = sum(t for _, t in self._per_track.values())
        return {"predicted": pred, "true": true, "ratio": _ratio(pred, true),
                "per_track": {k: {"predicted": p, "true": t}
                              for k, (p, t) in self._per_track.items()}}


def unknown_where_visible(overall: Mapping[str, Mapping[str, object]],
                          tasks: Sequence[str] = ("brake", "left", "right")) -> Optional[float]:
    """The share of frames published UNKNOWN among those whose truth is OFF or ON.

    A lamp whose truth is OFF or ON is there to be judged, so an UNKNOWN on it is a miss
    of sight, not a state; the lights' frames are pooled.

    Args:
        overall: A report's ``overall`` section (task name -> :func:`metrics_from_confusion`).
        tasks: The light heads pooled; a task missing from ``overall`` is left out.

    Returns:
        The share, or ``None`` where no such frame was scored.
    """
    unknown = visible = 0
    for task in tasks:
        confusion = overall.get(task, {}).get("confusion") or []
        for row in list(confusion)[:2]:  # true OFF, true ON
            visible += sum(row)
            unknown += row[2] if len(row) > 2 else 0
    return unknown / visible if visible else None


def roc_auc(positive: ArrayLike, negative: ArrayLike) -> Optional[float]:
    """Area under the ROC curve of scores of positives against negatives (the chance that a
    random positive scores above a random negative; ties count as the rank order gives);
    ``None`` when either side is empty."""
    pos, neg = np.asarray(positive, np.float64), np.asarray(negative, np.float64)
    if not len(pos) or not len(neg):
        return None
    ranks = np.concatenate([pos, neg]).argsort().argsort() + 1
    return float((ranks[:len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def _confidence_bins(probs: np.ndarray, labels: np.ndarray, bins: int
                     ) -> Tuple[np.ndarray, List[Tuple[int, float, float]]]:
    """The bin edges and, per equal-width bin of the top-class confidence, ``(count, mean
    confidence, accuracy)`` (NaN means in an empty bin)."""
    p, y = np.asarray(probs, np.float64), np.asarray(labels)
    confidence = p.max(1) if len(y) else np.zeros(0)
    correct = (p.argmax(1) == y).astype(np.float64) if len(y) else np.zeros(0)
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(confidence, edges[1:-1]), 0, bins - 1)
    rows = []
    for b in range(bins):
        sel = which == b
        rows.append((int(sel.sum()), float(confidence[sel].mean()) if sel.any() else np.nan,
                     float(correct[sel].mean()) if sel.any() else np.nan))
    return edges, rows


def expected_calibration_error(probs: np.ndarray, labels: np.ndarray, bins: int = 15) -> float:
    """ECE of ``[M, K]`` probabilities against ``[M]`` labels (top-class confidence bins)."""
    if len(labels) == 0:
        return 0.0
    return _ece(_confidence_bins(probs, labels, bins)[1])


def _ece(rows: Sequence[Tuple[int, float, float]]) -> float:
    """The count-weighted mean gap between accuracy and confidence of the bins."""
    total = sum(n for n, _, _ in rows)
    return float(sum(n / total * abs(acc - conf) for n, conf, acc in rows if n)) if total else 0.0


def reliability_report(probs: np.ndarray, labels: np.ndarray, bins: int = 15) -> Dict[str, object]:
    """Reliability of a light head's published probabilities on frames whose truth is OFF or ON.

    Args:
        probs: ``[M, K]`` published probabilities.
        labels: ``[M]`` true classes.
        bins: Equal-width bins of the top-class confidence (as :func:`expected_calibration_error`).

    Returns:
        ``{"frames", "ece", "bins": [{"low", "high", "count", "confidence", "accuracy"}]}``:
        per bin the mean confidence of the predicted class and how often it was right
        (``None`` in an empty bin).
    """
    edges, rows = _confidence_bins(probs, labels, bins)
    return {"frames": int(len(labels)), "ece": _ece(rows),
            "bins": [{"low": float(edges[b]), "high": float(edges[b + 1]), "count": n,
                      "confidence": conf if n else None, "accuracy": acc if n else None}
                     for b, (n, conf, acc) in enumerate(rows)]}


class LightOutcomes:
    """What the light heads published where the truth is OFF or ON: the share of UNKNOWN
    and (with probabilities) the reliability of the published probabilities.

    The UNKNOWN share of a head is the fraction of its scored frames with a true OFF or
    ON whose published state is UNKNOWN; ``overall`` pools the three heads. Given the
    frames' true and published views, the same counts are also kept per pair of views
    (:meth:`unknown_by_view`): a lamp is published UNKNOWN because the view head took a
    rear for a front, or because the light head could not judge a view it named right.
    """

    def __init__(self) -> None:
        self._unknown = {t: [0, 0] for t in LIGHT_TASKS}  # [UNKNOWN published, frames]
        self._by_view: Dict[Tuple[str, str], List[int]] = {}  # same, per (true, published)
        self._probs: Dict[str, List[np.ndarray]] = {t: [] for t in LIGHT_TASKS}
        self._labels: Dict[str, List[np.ndarray]] = {t: [] for t in LIGHT_TASKS}

    def add(self, task: str, y_true: ArrayLike, y_pred: ArrayLike,
            probs: Optional[np.ndarray] = None,
            views: Optional[Tuple[ArrayLike, ArrayLike]] = None) -> None:
        """Add a light head's scored frames (``probs``: their ``[N, K]`` published
        probabilities, if known; ``views``: their true and published view names, if
        known)."""
        t, p = _pair(y_true, y_pred)
        keep = (t == int(LightStatus.OFF)) | (t == int(LightStatus.ON))
        unknown = p == int(LightStatus.UNKNOWN)
        self._unknown[task][0] += int(np.count_nonzero(unknown[keep]))
        self._unknown[task][1] += int(keep.sum())
        if views is not None:
            self._add_views(keep, unknown, *views)
        if probs is not None:
            q = np.asarray(probs, np.float64)[keep]
            finite = np.isfinite(q).all(axis=1)
            self._probs[task].append(q[finite])
            self._labels[task].append(t[keep][finite])

    def unknown_share(self) -> Dict[str, Dict[str, object]]:
        """``{light: {"unknown", "frames", "share"}, "overall": {...}}`` (share None when no
        frame had a true OFF or ON)."""
        out: Dict[str, Dict[str, object]] = {}
        for task, (u, n) in self._unknown.items():
            out[task] = {"unknown": u, "frames": n, "share": _ratio(u, n)}
        u = sum(v[0] for v in self._unknown.values())
        n = sum(v[1] for v in self._unknown.values())
        out["overall"] = {"unknown": u, "frames": n, "share": _ratio(u, n)}
        return out

    def _add_views(self, keep: np.ndarray, unknown: np.ndarray, true_views: ArrayLike,
                   published_views: ArrayLike) -> None:
        true_views, published_views = np.asarray(true_views), np.asarray(published_views)
        if true_views.shape != keep.shape or published_views.shape != keep.shape:
            raise ConfigError(f"views of {true_views.shape} and {published_views.shape} "
                              f"frames for {keep.shape} labels")
        for pair in set(zip(true_views[keep].tolist(), published_views[keep].tolist())):
            rows = keep & (true_views == pair[0]) & (published_views == pair[1])
            cell = self._by_view.setdefault(pair, [0, 0])
            cell[0] += int(np.count_nonzero(unknown[rows]))
            cell[1] += int(rows.sum())

    def unknown_by_view(self) -> List[Dict[str, object]]:
        """The three heads' frames with a true OFF or ON per (true view, published view),
        most UNKNOWNs first: ``{"true_view", "published_view", "frames", "unknown",
        "share", "share_of_unknown"}`` (empty when no views were given)."""
        total = sum(u for u, _ in self._by_view.values())
        rows = [{"true_view": tv, "published_view": pv, "frames": n, "unknown": u,
                 "share": _ratio(u, n), "share_of_unknown": _ratio(u, total)}
                for (tv, pv), (u, n) in self._by_view.items()]
        return sorted(rows, key=lambda r: (-r["unknown"], -r["frames"], r["true_view"],
                                           r["published_view"]))

    def calibration(self) -> Dict[str, Dict[str, object]]:
        """Light -> :func:`reliability_report`, for the heads whose probabilities were given."""
        return {t: reliability_report(np.concatenate(self._probs[t]),
                                      np.concatenate(self._labels[t]))
                for t in LIGHT_TASKS if self._probs[t]}


def flicker_table(switches: Mapping[str, Mapping[str, object]]) -> List[Dict[str, object]]:
    """Per track, the predicted and true changes of every head, worst tracks first.

    Args:
        switches: Task -> :meth:`SwitchCounter.report`.

    Returns:
        One row per track: ``{"track", "excess", task: {"predicted", "true"}, ...}`` where
        ``excess`` sums, over the heads, the predicted changes beyond the true ones; sorted
        by excess, then predicted changes, then name.
    """
    tasks = [t for t in ("brake", "left", "right", "intent") if t in switches]
    per_track: Dict[str, Mapping[str, Mapping[str, int]]] = {
        t: switches[t].get("per_track", {}) for t in tasks}  # type: ignore[misc]
    names = sorted({k for t in tasks for k in per_track[t]})
    rows = []
    for name in names:
        row: Dict[str, object] = {"track": name}
        excess = 0
        for t in tasks:
            c = per_track[t].get(name, {"predicted": 0, "true": 0})
            row[t] = {"predicted": int(c["predicted"]), "true": int(c["true"])}
            excess += max(0, int(c["predicted"]) - int(c["true"]))
        row["excess"] = excess
        rows.append(row)
    tasks_sum = lambda r: sum(r[t]["predicted"] for t in tasks)  # noqa: E731
    return sorted(rows, key=lambda r: (-r["excess"], -tasks_sum(r), r["track"]))


def selection_score(summary: Mapping[str, Optional[float]],
                    trained: Optional[Iterable[str]] = None) -> float:
    """Scalar used to pick the best checkpoint: mean of intent macro-F1 and brake accuracy.

    Args:
        summary: The ``summary`` of a metrics report.
        trained: Heads that are in the loss; a head left out (an ablation trained on
            intent alone) does not vote, since its figure only moves by chance.
            None means all heads.

    Missing figures count as 0 so that a model that was never scored never wins.
    """
    voters = None if trained is None else set(trained)
    terms = [key for task, key in (("intent", "intent_macro_f1"), ("brake", "brake_accuracy"))
             if voters is None or task in voters]
    if not terms:
        terms = ["intent_macro_f1", "brake_accuracy"]
    return sum(float(summary.get(key) or 0.0) for key in terms) / len(terms)


# ---------------------------------------------------------------------------- rendering


def percent_cell(value: Optional[float]) -> str:
    """A rate as a Markdown table cell ("12.3 %"), "–" when missing or NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{100.0 * value:.1f} %"


_COLUMNS = (("accuracy", "accuracy"), ("macro_recall", "macro recall"),
            ("macro_f1", "macro F1"), ("fp_rate", "FP rate"), ("fn_rate", "FN rate"))


def _task_table(by_task: Mapping[str, Mapping[str, object]]) -> List[str]:
    lines = ["| task | frames | " + " | ".join(h for _, h in _COLUMNS) + " |",
             "|---|---:|" + "---:|" * len(_COLUMNS)]
    for task, m in by_task.items():
        cells = [percent_cell(m.get(key)) for key, _ in _COLUMNS]  # type: ignore[arg-type]
        lines.append(f"| {task} | {m['n']} | " + " | ".join(cells) + " |")
    return lines


def _confusion_table(metrics: Mapping[str, object]) -> List[str]:
    names = list(metrics["class_names"])  # type: ignore[arg-type]
    counts = np.asarray(metrics["confusion"])
    norm = normalise_rows(counts)
    lines = ["| ground truth \\ prediction | " + " | ".join(names) + " | frames |",
             "|---|" + "---:|" * (len(names) + 1)]
    for i, name in enumerate(names):
        cells = [f"{100.0 * norm[i, j]:.1f} %" for j in range(len(names))]
        lines.append(f"| **{name}** | " + " | ".join(cells) + f" | {int(counts[i].sum())} |")
    return lines


_GROUP_COLUMNS = (("intent", "macro_f1", "intent F1"), ("intent", "fp_rate", "intent FP"),
                  ("intent", "fn_rate", "intent FN"), ("brake", "accuracy", "brake acc"),
                  ("left", "accuracy", "left acc"), ("right", "accuracy", "right acc"),
                  ("view", "accuracy", "view acc"))


def _group_table(name: str, values: Mapping[str, Mapping[str, Mapping[str, object]]]) -> List[str]:
    lines = [f"| {name} | frames | " + " | ".join(h for _, _, h in _GROUP_COLUMNS) + " |",
             "|---|---:|" + "---:|" * len(_GROUP_COLUMNS)]
    for value, by_task in values.items():
        # Heads can differ (grace windows are per head); show the most frames scored.
        n = max((m["n"] for m in by_task.values()), default=0)
        cells = [percent_cell(by_task.get(t, {}).get(key)) for t, key, _ in _GROUP_COLUMNS]
        lines.append(f"| {value} | {n} | " + " | ".join(cells) + " |")
    return lines


def markdown_report(report: Mapping[str, object], title: Optional[str] = None) -> str:
    """Render a :meth:`MetricAccumulator.report` as Markdown.

    Args:
        report: The report dict.
        title: Optional heading (level 3) put first.

    Returns:
        Markdown with the per-task table, the row-normalised intent confusion matrix
        (rows = ground truth) and one table per group.
    """
    lines: List[str] = []
    if title:
        lines += [f"### {title}", ""]
    overall = report.get("overall", {})  # type: ignore[union-attr]
    lines += _task_table(overall)  # type: ignore[arg-type]
    if "intent" in overall:  # type: ignore[operator]
        lines += ["", "Intent confusion matrix (rows = ground truth, row-normalised):", ""]
        lines += _confusion_table(overall["intent"])  # type: ignore[index]
    for name, values in report.get("groups", {}).items():  # type: ignore[union-attr]
        lines += ["", f"By {name}:", ""]
        lines += _group_table(name, values)
    return "\n".join(lines) + "\n"


def switches_markdown(switches: Mapping[str, Mapping[str, object]],
                      max_tracks: int = 20) -> str:
    """Render switch reports (task -> :meth:`SwitchCounter.report`) as Markdown.

    Args:
        switches: One report per task.
        max_tracks: Per-track intent counts are listed for at most this many tracks,
            the most flickering first.

    Returns:
        A table of the changes per task and one of the intent's changes per track.
    """
    def ratio(value: object) -> str:
        return "–" if value is None else f"{value:.2f}"

    lines = ["| task | predicted changes | true changes | ratio |", "|---|---:|---:|---:|"]
    for task, rep in switches.items():
        lines.append(f"| {task} | {rep['predicted']} | {rep['true']} | {ratio(rep['ratio'])} |")
    tracks = dict(switches.get("intent", {}).get("per_track", {}))  # type: ignore[union-attr]
    if tracks:
        shown = sorted(tracks.items(), key=lambda kv: (-kv[1]["predicted"], kv[0]))[:max_tracks]
        more = f" ({len(shown)} of {len(tracks)}, most changes first)" \
            if len(shown) < len(tracks) else ""
        lines += ["", f"Intent changes per track{more}:", "",
                  "| track | predicted | true |", "|---|---:|---:|"]
        lines += [f"| {k} | {v['predicted']} | {v['true']} |" for k, v in shown]
    return "\n".join(lines) + "\n"


def flicker_markdown(table: Sequence[Mapping[str, object]], max_tracks: int = 20) -> str:
    """Render :func:`flicker_table` (per track, predicted / true changes per head)."""
    if not table:
        return "No track was scored.\n"
    tasks = [t for t in ("brake", "left", "right", "intent") if t in table[0]]
    shown = list(table[:max_tracks])
    more = f" ({len(shown)} of {len(table)})" if len(shown) < len(table) else ""
    lines = [f"Changes per track, predicted / true, worst first{more}:", "",
             "| track | " + " | ".join(tasks) + " | excess |",
             "|---|" + "---:|" * (len(tasks) + 1)]
    for row in shown:
        cells = [f"{row[t]['predicted']} / {row[t]['true']}" for t in tasks]  # type: ignore[index]
        lines.append(f"| {row['track']} | " + " | ".join(cells) + f" | {row['excess']} |")
    return "\n".join(lines) + "\n"


def light_outcomes_markdown(unknown: Mapping[str, Mapping[str, object]],
                            calibration: Optional[Mapping[str, Mapping[str, object]]] = None
                            ) -> str:
    """The UNKNOWN share per light (and overall) and, when given, each light's ECE."""
    lines = ["| light | frames with true OFF/ON | published UNKNOWN | share |"
             + (" ECE |" if calibration else ""),
             "|---|---:|---:|---:|" + ("---:|" if calibration else "")]
    for name, u in unknown.items():
        ece = ""
        if calibration:
            c = calibration.get(name)
            ece = " " + ("–" if c is None else f"{c['ece']:.3f}") + " |"
        lines.append(f"| {name} | {u['frames']} | {u['unknown']} | "
                     f"{percent_cell(u['share'])} |{ece}")  # type: ignore[arg-type]
    return "\n".join(lines) + "\n"


def unknown_by_view_markdown(rows: Sequence[Mapping[str, object]]) -> str:
    """:meth:`LightOutcomes.unknown_by_view` as a table (empty string without rows)."""
    if not rows:
        return ""
    lines = ["| true view -> published view | lamp-frames with true OFF/ON | published UNKNOWN "
             "| share | share of all UNKNOWNs |", "|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['true_view']} -> {r['published_view']} | {r['frames']} | "
                     f"{r['unknown']} | {percent_cell(r['share'])} | "  # type: ignore[arg-type]
                     f"{percent_cell(r['share_of_unknown'])} |")  # type: ignore[arg-type]
    return "\n".join(lines) + "\n"


def render_reliability_png(report: Mapping[str, object], path: str, title: str = "") -> None:
    """Draw a :func:`reliability_report` as a reliability diagram PNG with OpenCV.

    One bar per confidence bin at the observed accuracy of the predicted class, the
    diagonal (perfect calibration), and the frame count of each bin under it.

    Raises:
        ConfigError: The file cannot be written.
    """
    import cv2  # local: keep the metric functions importable without OpenCV

    size, left, top = 400, 60, 50
    width, height = left + size + 30, top + size + 70
    img = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    x0, y0 = left, top + size  # origin (confidence 0, accuracy 0)
    if title:
        cv2.putText(img, title, (10, 24), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    for b in report["bins"]:  # type: ignore[union-attr]
        if b["accuracy"] is None:
            continue
        xa, xb = x0 + int(b["low"] * size), x0 + int(b["high"] * size)
        ya = y0 - int(round(b["accuracy"] * size))
        cv2.rectangle(img, (xa + 1, ya), (xb - 1, y0), (200, 120, 40), -1)
        yc = y0 - int(round(b["confidence"] * size))
        cv2.line(img, (xa + 1, yc), (xb - 1, yc), (0, 0, 200), 2)
        cv2.putText(img, str(b["count"]), (xa + 2, y0 + 14), font, 0.3, (80, 80, 80), 1,
                    cv2.LINE_AA)
    cv2.rectangle(img, (x0, top), (x0 + size, y0), (0, 0, 0), 1)
    cv2.line(img, (x0, y0), (x0 + size, top), (128, 128, 128), 1, cv2.LINE_AA)
    for v in (0.0, 0.5, 1.0):
        cv2.putText(img, f"{v:.1f}", (x0 + int(v * size) - 10, y0 + 30), font, 0.4, (0, 0, 0), 1,
                    cv2.LINE_AA)
        cv2.putText(img, f"{v:.1f}", (left - 35, y0 - int(v * size) + 4), font, 0.4, (0, 0, 0), 1,
                    cv2.LINE_AA)
    cv2.putText(img, "confidence of the predicted class (bars: observed accuracy, red: mean "
                "confidence; counts under the bins)", (10, height - 14), font, 0.3, (0, 0, 0), 1,
                cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise ConfigError(f"cannot write reliability diagram to {path}")


def render_confusion_png(matrix: np.ndarray, class_names: Sequence[str], path: str,
                         title: str = "") -> None:
    """Draw a confusion matrix (rows = ground truth) as a PNG with OpenCV.

    Cells are shaded by the row-normalised value and show the percentage and the count.

    Args:
        matrix: Count matrix [K, K].
        class_names: K names.
        path: Output file (``.png``).
        title: Optional line drawn on top.

    Raises:
        ConfigError: The matrix is not K x K for the K names, or the file cannot be written.
    """
    import cv2  # local: keep the metric functions importable without OpenCV

    m = np.asarray(matrix, dtype=np.int64)
    k = len(class_names)
    if m.shape != (k, k):
        raise ConfigError(f"confusion matrix of shape {m.shape} does not match {k} class names")
    norm = normalise_rows(m)
    cell, left, top = 96, 130, 80
    width, height = left + k * cell + 20, top + k * cell + 60
    img = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    if title:
        cv2.putText(img, title, (10, 24), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "prediction", (left + k * cell // 2 - 45, 48), font, 0.5, (0, 0, 0), 1,
                cv2.LINE_AA)
    for j, name in enumerate(class_names):
        cv2.putText(img, str(name)[:9], (left + j * cell + 6, top - 8), font, 0.45, (0, 0, 0),
                    1, cv2.LINE_AA)
    for i, name in enumerate(class_names):
        y = top + i * cell
        cv2.putText(img, str(name)[:11], (8, y + cell // 2 + 5), font, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
        for j in range(k):
            x = left + j * cell
            v = float(norm[i, j])
            # White -> dark blue as the share of the row grows (BGR).
            colour = (255, int(255 * (1 - 0.75 * v)), int(255 * (1 - v)))
            cv2.rectangle(img, (x, y), (x + cell - 1, y + cell - 1), colour, -1)
            cv2.rectangle(img, (x, y), (x + cell - 1, y + cell - 1), (160, 160, 160), 1)
            ink = (255, 255, 255) if v > 0.55 else (0, 0, 0)
            cv2.putText(img, f"{100 * v:.1f}%", (x + 14, y + cell // 2 - 2), font, 0.5, ink, 1,
                        cv2.LINE_AA)
            cv2.putText(img, str(int(m[i, j])), (x + 14, y + cell // 2 + 20), font, 0.4, ink,
                        1, cv2.LINE_AA)
    cv2.putText(img, "rows: ground truth", (8, height - 20), font, 0.5, (0, 0, 0), 1,
                cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise ConfigError(f"cannot write confusion matrix image to {path}")
