"""Adapting with labels, cheaply: fit how readily the model says UNKNOWN and ON on your
camera.

A light or an intent is UNKNOWN when the model cannot see the lamps. On crops unlike its
training renders the model says so far too often: on the independent generator's renders
the shipped weights publish UNKNOWN on 58 % of the frames where a lamp is visible, and
lowering the UNKNOWN logit by 2 would halve the intent errors there, while on the training
renderer's held-out colour family the best margin is 0 (measured: docs/model.md). How far
to lower it is a property of the camera, so it is fitted on the user's labelled tracks.
The same holds for how readily a lamp is called ON: the intent filter turns a blinker on
from a fixed P(ON), and a fine-tune on a few tracks moves the blinkers' probabilities
against it (after one, a blinker ON offset of -0.5 gave back what the filter lost;
docs/model.md).

``signal-light calibrate LABELLED... --out MODEL`` (``commands/calibrate.py``):

* reads labelled bags (``annotate import`` writes them) or materialised splits, and holds
  out ``--holdout-fraction`` of the track IDs (:func:`.holdout.split_by_track_id`, the
  fine-tune's rule);
* runs the model once over the fit tracks; for every margin ``b`` of the grid and ON
  offset ``o`` of the ON grid it moves those outputs as subtracting ``b`` from the
  UNKNOWN logit of the brake, left, right and intent heads and shifting both blinkers'
  ON against their OFF by ``o`` in log-odds would
  (:func:`with_offsets`), and scores them as ``evaluate`` does (the node's intent
  filter): the mean of intent macro-F1 and brake F1. The best setting wins; ties go to
  the smaller margin and the offset nearest 0;
* writes the margin into the heads' biases (:func:`apply_offsets`) and the ON offset into
  the config's ``on_offsets`` (:func:`add_on_offsets`; it leaves P(UNKNOWN) as it is,
  where a bias on ON alone would make UNKNOWNs: docs/model.md, "The last step of each
  member"): the checkpoint, its ONNX export and its int8 export all carry both; and the
  checkpoint's
  ``meta["unknown_margin"]`` (margin, ON offset, the grid's scores, the data) and, with
  held-out tracks, the before/after report beside it (``MODEL.report.json`` / ``.md``,
  as the fine-tune's).

Nothing else changes: two numbers per checkpoint, fitted on labels, so a handful of
labelled tracks is enough and they cannot overfit the way a fine-tune can.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import (TYPE_CHECKING, Any, Callable, Dict, Iterator, List, Mapping, Optional,
                    Sequence, Tuple)

import numpy as np
import torch
from torch import nn

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LightStatus
from signal_light_node.model.checkpoint import FILE_META
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.training.fit_guard import DEFAULT_CONFIDENCE, GainGuard, Verdict
from signal_light_node.training.filter_fit import (FilterFit, cli_options, fit_filter,
                                                   parameter_file)

if TYPE_CHECKING:
    from signal_light_node.evaluation.scoring import TrackScorer
    from signal_light_node.runtime.intent_filter import IntentFilterConfig

logger = logging.getLogger(__name__)

#: Heads whose UNKNOWN class the margin lowers (the view head has none).
MARGIN_HEADS = ("brake", "left", "right", "intent")
#: The grid tried by default: 0 (the model as it is) to 3 nats.
DEFAULT_GRID: Tuple[float, ...] = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
#: Heads whose ON logit the blinker offset moves (one offset for both): the intent filter's
#: on-threshold acts on them. The brake has none: on the held-out family a brake offset
#: fitted on one half lowered brake F1 on the other every time (docs/model.md).
ON_HEADS = ("left", "right")
#: The blinker ON offsets tried by default (logit units; 0 = the model as it is). It reaches
#: further down than up: nine of ten two-member models chose -1, then the grid's end.
DEFAULT_ON_GRID: Tuple[float, ...] = (-2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0)
#: Checkpoint metadata key of the fit.
META_KEY = "unknown_margin"
#: ... and of the filter fitted with it (``--fit-filter``).
FILTER_META_KEY = "filter_fit"


@dataclass
class MarginFit:
    """What :func:`fit_unknown_margin` found.

    Attributes:
        margin: The margin chosen.
        on_offset: The ON offset of the blinkers chosen (:data:`ON_HEADS`).
        scores: Per margin tried, the fit tracks' ``(intent macro-F1 + brake F1) / 2`` with
            that margin's best blinker ON offset.
        fit_tracks: Tracks it was fitted on.
        fit_frames: Their frames scored.
        edges: What was chosen at the end of its grid (:func:`grid_edges`): a wider grid
            might score better still.
        filter: The node's filter fitted with it (``--fit-filter``), or None.
        declined: The best margin and ON offset where the gain guard kept 0 and 0 instead
            (:mod:`training.fit_guard`), else None.
        verdict: The guard's verdict on the best setting, where one was asked.
    """

    margin: float
    on_offset: float = 0.0
    scores: Dict[float, float] = field(default_factory=dict)
    fit_tracks: int = 0
    fit_frames: int = 0
    edges: List[str] = field(default_factory=list)
    filter: Optional[FilterFit] = None
    declined: Optional[Tuple[float, float]] = None
    verdict: Optional[Verdict] = None


def grid_edges(margin: float, on_offset: float, grid: Sequence[float],
               on_grid: Sequence[float]) -> List[str]:
    """The chosen values that lie at the end of a grid of several values, named with the
    option that widens it. A margin of 0 is the end of its range, not of the grid."""
    edges = []
    if len(set(grid)) > 1 and margin == max(grid) and margin > 0:
        edges.append(f"UNKNOWN margin {margin:g} is the largest of --grid")
    if len(set(on_grid)) > 1 and on_offset in (min(on_grid), max(on_grid)):
        end = "smallest" if on_offset == min(on_grid) else "largest"
        edges.append(f"blinker ON offset {on_offset:+g} is the {end} of --on-grid")
    return edges


def unknown_index(model: nn.Module, task: str) -> int:
    """Index of UNKNOWN among ``task``'s classes (:func:`class_index`)."""
    return class_index(model, task, "UNKNOWN")


def task_heads(model: nn.Module, task: str) -> List[nn.Module]:
    """The output layers whose logits make ``task``'s (the network's ``output_layers``:
    one per member of a model averaging members).

    Raises:
        ConfigError: The network does not name its output layers.
    """
    if not hasattr(model, "output_layers"):
        raise ConfigError(f"{type(model).__name__} does not name its output layers: its "
                          "biases cannot be moved")
    return model.output_layers(task)


def class_index(model: nn.Module, task: str, name: str) -> int:
    """Index of class ``name`` among ``task``'s classes.

    Raises:
        ConfigError: The head has no such class, or is not a layer with a bias.
    """
    names = tuple(model.config.class_names[task])
    heads = task_heads(model, task)
    if name not in names or any(getattr(h, "bias", None) is None for h in heads):
        raise ConfigError(f"the {task} head has no {name} class with a bias to move")
    return names.index(name)


def head_offsets(model: nn.Module, margin: float) -> Dict[str, np.ndarray]:
    """Per head, what to add to each class's logit: ``-margin`` on UNKNOWN of
    :data:`MARGIN_HEADS`."""
    out = {t: np.zeros(len(model.config.class_names[t])) for t in MARGIN_HEADS}
    for task in MARGIN_HEADS:
        out[task][unknown_index(model, task)] -= float(margin)
    return out


def on_offsets(tasks: Sequence[str], offset: float) -> Dict[str, float]:
    """Per head of ``tasks``, its shift of ON against OFF (``ModelConfig.on_offsets``)."""
    return {task: float(offset) for task in tasks}


def add_on_offsets(model: nn.Module, shifts: Mapping[str, float]) -> None:
    """Add ``shifts`` to the model's ``config.on_offsets`` (in place; the heads read them
    from it after the temperatures); a sum of 0 is dropped."""
    total = dict(model.config.on_offsets)
    for task, shift in shifts.items():
        total[task] = total.get(task, 0.0) + float(shift)
    model.config = model.config.replace(on_offsets={t: v for t, v in total.items() if v != 0.0})


def apply_offsets(model: nn.Module, offsets: Dict[str, np.ndarray]) -> None:
    """Add :func:`head_offsets` to the heads' biases (in place; temperatures apply after,
    as to every logit)."""
    with torch.no_grad():
        for task, delta in offsets.items():
            for head in task_heads(model, task):
                head.bias += torch.as_tensor(delta, dtype=head.bias.dtype)


def apply_unknown_margin(model: nn.Module, margin: float) -> None:
    """Lower the UNKNOWN logit of every head of :data:`MARGIN_HEADS` by ``margin``."""
    apply_offsets(model, head_offsets(model, margin))


def score(result: Dict[str, Any]) -> float:
    """The fit's objective: the mean of intent macro-F1 and brake F1 (of ON), 0 where a
    figure is missing."""
    from signal_light_node.training.holdout import headline

    h = headline(result)
    return 0.5 * (float(h["intent_macro_f1"] or 0.0) + float(h["brake_f1"] or 0.0))


def with_offsets(raw: Dict[str, np.ndarray], offsets: Dict[str, np.ndarray],
                 temperatures: Dict[str, float], shifts: Optional[Mapping[str, float]] = None
                 ) -> Dict[str, np.ndarray]:
    """What a model would output after :func:`apply_offsets` and :func:`add_on_offsets`,
    from what it output before (exact, no second model pass): the heads' probabilities are
    a softmax of (logit + bias) / temperature, so adding ``d`` to a class's bias multiplies
    its probability by ``exp(d / T)`` before renormalising; a shift ``s`` of ON against OFF
    then multiplies the odds of ON to OFF by ``exp(s)``, their sum kept.

    Args:
        raw: Task -> probabilities ``[..., K]`` (``evaluation.streaming.model_track_probs``).
        offsets: :func:`head_offsets`.
        temperatures: The model config's temperatures (missing tasks 1.0).
        shifts: :func:`on_offsets` (none by default); every light head's classes are
            :class:`~signal_light_node.labels.LightStatus`'s (a checkpoint is refused otherwise).
    """
    out = dict(raw)
    for task, delta in offsets.items():
        scale = np.exp(np.asarray(delta, np.float64) / float(temperatures.get(task, 1.0)))
        moved = out[task].astype(np.float64) * scale
        out[task] = (moved / moved.sum(axis=-1, keepdims=True)).astype(raw[task].dtype)
    for task, shift in (shifts or {}).items():
        on, off = int(LightStatus.ON), int(LightStatus.OFF)
        p = out[task].astype(np.float64)
        lit, dark = p[..., on] * math.exp(shift), p[..., off]
        total = p[..., on] + dark
        share = np.divide(lit, lit + dark, out=np.zeros_like(lit), where=lit + dark > 0)
        p[..., on], p[..., off] = total * share, total * (1.0 - share)
        out[task] = p.astype(raw[task].dtype)
    return out


def _best(values: Dict[float, float]) -> float:
    """The key of the largest value; ties go to the key nearest 0, then the smaller."""
    top = max(values.values())
    return min((k for k, v in values.items() if v == top), key=lambda k: (abs(k), k))


class ModelPass:
    """One pass of a model over labelled tracks, scored under any offsets of its heads'
    logits without running it again (:func:`with_offsets`), filtered and counted as
    ``evaluate`` does.

    Args:
        model: The model (set to eval mode).
        tracks: The labelled tracks.
    """

    def __init__(self, model: nn.Module, tracks: Sequence[TrackSequence]) -> None:
        from signal_light_node.evaluation.scoring import EvalSettings
        from signal_light_node.evaluation.streaming import chunks, model_track_probs
        from signal_light_node.runtime.intent_filter import IntentFilterConfig

        self.settings, self.light_filter = EvalSettings(), IntentFilterConfig()
        model = model.eval()
        self.temperatures = dict(model.config.temperatures)
        self.outputs = [(batch, model_track_probs(model, batch))
                        for batch in chunks(tracks, self.settings.batch_tracks)]

    def scorer(self, offsets: Dict[str, np.ndarray],
               shifts: Optional[Mapping[str, float]] = None,
               light_filter: Optional["IntentFilterConfig"] = None) -> "TrackScorer":
        """Every track scored as the model moved by bias ``offsets`` and ON ``shifts``
        (:func:`with_offsets`) would publish it, through ``light_filter`` (default: the
        node's defaults)."""
        from signal_light_node.evaluation.scoring import TrackScorer
        from signal_light_node.evaluation.streaming import score_batch

        scorer = TrackScorer(self.settings)
        for batch, moved in self._moved(offsets, shifts):
            score_batch(scorer, batch, moved, light_filter or self.light_filter)
        return scorer

    def _moved(self, offsets: Dict[str, np.ndarray], shifts: Optional[Mapping[str, float]]
               ) -> Iterator[Tuple[list, Dict[str, np.ndarray]]]:
        """Per batch its tracks and the outputs moved by ``offsets`` and ``shifts``."""
        for batch, raw in self.outputs:
            yield batch, with_offsets(raw, offsets, self.temperatures, shifts)

    @property
    def tracks(self) -> List[TrackSequence]:
        """The tracks, in the order :meth:`published` gives their states."""
        return [track for batch, _ in self.outputs for track in batch]

    def published(self, offsets: Dict[str, np.ndarray],
                  shifts: Optional[Mapping[str, float]] = None,
                  light_filter: Optional["IntentFilterConfig"] = None) -> List[np.ndarray]:
        """Per track what the node would publish (``[T, len(TASKS)]``), as :meth:`scorer`
        scores it."""
        from signal_light_node.evaluation.streaming import filter_track_probs

        preds: List[np.ndarray] = []
        for batch, moved in self._moved(offsets, shifts):
            preds += filter_track_probs(moved, batch, light_filter or self.light_filter)[0]
        return preds


def fit_unknown_margin(model: nn.Module, tracks: Sequence[TrackSequence],
                       grid: Sequence[float] = DEFAULT_GRID,
                       on_grid: Sequence[float] = (0.0,),
                       passed: Optional[ModelPass] = None,
                       confidence: float = 0.0) -> MarginFit:
    """Score ``tracks`` at every margin of ``grid`` and ON offset of ``on_grid``; keep the
    best. ``model`` itself is not changed.

    The model runs once (or ``passed``, its pass over ``tracks``, is used); each setting
    is applied to its outputs (:func:`with_offsets`) and filtered and scored as
    ``evaluate`` does. With ``confidence`` above 0 the best is kept only if it beats margin
    0 and offset 0 on that share of scene resamples (:class:`~.fit_guard.GainGuard`).

    Raises:
        ConfigError: An empty grid, a negative margin, or no track to fit on.
    """
    from signal_light_node.evaluation.streaming import scorer_result

    if not grid or min(grid) < 0:
        raise ConfigError(f"the margins to try must be >= 0, got {list(grid)}")
    if not on_grid:
        raise ConfigError("no ON offset to try (give 0 to keep the ON logits)")
    if not tracks:
        raise ConfigError("no labelled track to fit the UNKNOWN margin on")
    head_offsets(model, 0.0)  # every head has the classes moved
    passed = passed or ModelPass(model, tracks)
    fit = MarginFit(margin=0.0, fit_tracks=len(tracks))
    chosen: Dict[float, float] = {}
    for margin in sorted({float(m) for m in grid}):
        by_offset: Dict[float, float] = {}
        for on in sorted({float(o) for o in on_grid}):
            result = scorer_result(passed.scorer(head_offsets(model, margin),
                                                 on_offsets(ON_HEADS, on)),
                                   passed.light_filter)
            by_offset[on] = score(result)
            fit.fit_frames = int(result["counts"]["scored"])
        chosen[margin] = _best(by_offset)
        fit.scores[margin] = by_offset[chosen[margin]]
        logger.info("UNKNOWN margin %.2f: score %.4f with blinker ON offset %+g", margin,
                    fit.scores[margin], chosen[margin])
    best = max(fit.scores.values())
    fit.margin = min(m for m, s in fit.scores.items() if s == best)
    fit.on_offset = chosen[fit.margin]
    fit.edges = grid_edges(fit.margin, fit.on_offset, [float(m) for m in grid],
                           [float(o) for o in on_grid])
    if confidence > 0.0 and (fit.margin, fit.on_offset) != (0.0, 0.0):
        _guard_margin(model, passed, fit, GainGuard(passed.tracks, confidence))
    return fit


def _guard_margin(model: nn.Module, passed: ModelPass, fit: MarginFit, guard: GainGuard) -> None:
    """Put ``fit`` back to margin 0 and offset 0 unless ``guard`` keeps its choice."""
    def published(margin: float, on: float) -> List[np.ndarray]:
        return passed.published(head_offsets(model, margin), on_offsets(ON_HEADS, on))

    fit.verdict = guard.judge(published(0.0, 0.0), published(fit.margin, fit.on_offset))
    logger.info("margin %g, ON offset %+g: above 0 / 0 on %.1f %% of scene resamples",
                fit.margin, fit.on_offset, 100 * fit.verdict.share_above)
    if not fit.verdict.kept:
        fit.declined = (fit.margin, fit.on_offset)
        fit.margin, fit.on_offset, fit.edges = 0.0, 0.0, []


def load_labelled(paths: Sequence[Path], crop: CropConfig) -> List[TrackSequence]:
    """Every track of labelled bags and split directories, in the order given.

    Raises:
        BagIOError: A path is missing, or a bag unreadable or without ground truth.
        ConfigError: A split cropped with other settings than ``crop``.
    """
    from signal_light_node.training.adapt_norms import check_inputs
    from signal_light_node.training.sources import load_bag_tracks, tracks_from

    check_inputs(paths)
    return tracks_from(paths, crop, "calibration data", lambda path: load_bag_tracks(path, crop))


def report_paths(out: Path) -> Tuple[Path, Path]:
    """Where the before/after report of ``out`` goes: ``OUT.report.json`` and ``.md``."""
    return out.with_suffix(".report.json"), out.with_suffix(".report.md")


def calibrate_checkpoint(out: Path, inputs: Sequence[Path],
                         checkpoint: Optional[Path] = None, holdout_fraction: float = 0.0,
                         seed: int = 0, grid: Sequence[float] = DEFAULT_GRID,
                         on_grid: Sequence[float] = DEFAULT_ON_GRID,
                         after_fit: Optional[Callable[[nn.Module], Dict[str, Any]]] = None,
                         filter_grid: Optional[Sequence[Dict[str, float]]] = None,
                         confidence: float = DEFAULT_CONFIDENCE
                         ) -> Tuple[MarginFit, Optional[Dict[str, Any]]]:
    """Fit the UNKNOWN margin and ON offsets of ``checkpoint`` on ``inputs``, write ``out``
    (and, with held-out tracks, its before/after report); returns the fit and the report.

    With ``filter_grid`` the node's filter settings are fitted too, on the same tracks and
    model pass, once the margin and offsets are chosen and before ``after_fit`` moves the
    model further (:mod:`training.filter_fit`): they
    go into the metadata (``filter_fit``) and into ``OUT.filter.yaml`` (node parameters),
    and the held-out tracks are scored after with them.

    ``confidence``: the gain guard's level (:mod:`training.fit_guard`; 0: the best on the
    fit tracks wins whatever its margin over the model as it is and the default filter).

    ``after_fit`` is called with the model once its margin and offsets are applied; it may
    move the model further (``training.night_bound.NightBounds``), and what it returns joins
    the checkpoint's metadata.

    Raises:
        ConfigError: Bad grid or fraction, no track, or a head without UNKNOWN.
        BagIOError: An input is missing or unreadable.
        CheckpointError: The checkpoint cannot be loaded or ``out`` written.
    """
    from signal_light_node.model.checkpoint import (DEFAULT_WEIGHTS, load_checkpoint,
                                                    save_checkpoint)
    from signal_light_node.training.holdout import before_after, report_markdown
    from signal_light_node.training.holdout import split_by_track_id

    source = Path(DEFAULT_WEIGHTS if checkpoint is None else checkpoint)
    loaded = load_checkpoint(source, map_location="cpu")
    head_offsets(loaded.model, 0.0)  # the heads have the classes moved
    tracks = load_labelled(inputs, loaded.config.crop_config())
    kept, held = split_by_track_id(tracks, holdout_fraction, seed)
    passed = ModelPass(loaded.model, kept) if kept else None
    fit = fit_unknown_margin(loaded.model, kept, grid, on_grid, passed, confidence)
    fit.filter = filtered = (None if filter_grid is None
                             else _fit_filter(loaded.model, passed, fit, filter_grid, confidence))
    apply_offsets(loaded.model, head_offsets(loaded.model, fit.margin))
    add_on_offsets(loaded.model, on_offsets(ON_HEADS, fit.on_offset))
    extra = after_fit(loaded.model) if after_fit is not None else {}
    meta = {k: v for k, v in loaded.meta.items() if k not in FILE_META}
    meta[META_KEY] = {"margin": fit.margin, "on_offset": fit.on_offset,
                      "on_heads": list(ON_HEADS),
                      "from": str(source),
                      "previous": loaded.meta.get(META_KEY),
                      "heads": list(MARGIN_HEADS), "data": [str(p) for p in inputs],
                      "fit_tracks": fit.fit_tracks, "fit_frames": fit.fit_frames,
                      "held_out_tracks": len(held), "seed": seed,
                      "scores": {f"{m:g}": s for m, s in fit.scores.items()},
                      "gain_confidence": confidence,
                      "declined": list(fit.declined) if fit.declined else None,
                      "verdict": fit.verdict.as_dict() if fit.verdict else None}
    meta.update(extra)
    if filtered is not None:
        meta[FILTER_META_KEY] = {"changes": filtered.changes, "score": filtered.score,
                                 "default_score": filtered.default_score,
                                 "tried": filtered.tried, "allowed": filtered.allowed,
                                 "declined": filtered.declined,
                                 "verdict": (filtered.verdict.as_dict()
                                             if filtered.verdict else None)}
    report = None
    if held:
        original = load_checkpoint(source, map_location="cpu").model.eval()
        report = before_after(original, loaded.model.eval(), held, str(source), str(out),
                              None if filtered is None else filtered.config)
    save_checkpoint(out, loaded.model, loaded.model.config, meta)
    if filtered is not None:
        filter_paths(Path(out)).write_text(parameter_file(filtered.changes))
    if report is not None:
        path_json, path_md = report_paths(Path(out))
        path_json.write_text(json.dumps(report, indent=2) + "\n")
        path_md.write_text(report_markdown(report, what="UNKNOWN margin and ON offsets"
                                           + (" and the filter" if filtered else "")))
    return fit, report


def filter_paths(out: Path) -> Path:
    """Where ``calibrate --fit-filter`` writes the node parameters: ``OUT.filter.yaml``."""
    return out.with_suffix(".filter.yaml")


def _fit_filter(model: nn.Module, passed: ModelPass, fit: MarginFit,
                grid: Sequence[Dict[str, float]], confidence: float = 0.0) -> FilterFit:
    """The node's filter fitted on ``passed``'s tracks, the model moved by ``fit``; with
    ``confidence`` above 0 kept only where it beats the defaults on that share of scene
    resamples."""
    from signal_light_node.evaluation.streaming import scorer_result
    from signal_light_node.runtime.intent_filter import IntentFilterConfig

    offsets, shifts = head_offsets(model, fit.margin), on_offsets(ON_HEADS, fit.on_offset)
    judge: Optional[Callable[[IntentFilterConfig], Verdict]] = None
    if confidence > 0.0:
        gain = GainGuard(passed.tracks, confidence)
        defaults = passed.published(offsets, shifts, IntentFilterConfig())

        def judge(config: IntentFilterConfig) -> Verdict:
            return gain.judge(defaults, passed.published(offsets, shifts, config))

    return fit_filter(lambda config: scorer_result(passed.scorer(offsets, shifts, config),
                                                   config), score, grid, judge)


def declined_line(what: str, kept: str, verdict: Optional[Verdict]) -> str:
    """The line saying the gain guard declined ``what`` and kept ``kept``."""
    share = verdict.share_above if verdict is not None else float("nan")
    return (f"declined: {what}, the best on the fit tracks, scored above {kept} on only "
            f"{100 * share:.0f} % of their scene resamples (--gain-confidence); kept {kept}")


def _held(verdict: Optional[Verdict], reference: str) -> str:
    """``, above REFERENCE on N % of scene resamples`` for a choice the gain guard kept (and
    judged), else nothing."""
    if verdict is None or not verdict.kept or np.isnan(verdict.share_above):
        return ""
    return f", above {reference} on {100 * verdict.share_above:.0f} % of scene resamples"


def summary_lines(fit: MarginFit, out: Path, report: Optional[Dict[str, Any]]) -> List[str]:
    """What ``signal-light calibrate`` prints."""
    grid = ", ".join(f"{m:g}: {100 * s:.1f} %" for m, s in sorted(fit.scores.items()))
    lines = [f"fitted on {fit.fit_frames} frames of {fit.fit_tracks} tracks; score (mean of "
             f"intent macro-F1 and brake F1, best blinker ON offset) per UNKNOWN margin: {grid}",
             f"UNKNOWN margin {fit.margin:g} (UNKNOWN logit of {', '.join(MARGIN_HEADS)} "
             f"lowered by it); blinker ON offset {fit.on_offset:+g} (ON against OFF of "
             f"{', '.join(ON_HEADS)}, in log-odds){_held(fit.verdict, '0 / 0')}; wrote {out}"]
    if fit.edges:
        lines.append(f"note: {'; '.join(fit.edges)}: a wider grid may score better")
    if fit.declined is not None:
        lines.append(declined_line(f"margin {fit.declined[0]:g} with ON offset "
                                   f"{fit.declined[1]:+g}", "margin 0 and offset 0", fit.verdict))
    if fit.filter is not None:
        f = fit.filter
        lines.append(f"filter fitted ({f.allowed} of {f.tried} settings within the switch "
                     f"bound): {f.changes or 'the defaults'}, score {100 * f.score:.1f} % "
                     f"(defaults {100 * f.default_score:.1f} %)"
                     f"{_held(f.verdict, 'the defaults')}; node parameters in "
                     f"{filter_paths(Path(out))}; evaluate / replay options: "
                     f"{' '.join(cli_options(f.changes)) or '(none)'}")
        if f.declined is not None:
            lines.append(declined_line(f"filter {f.declined}", "the defaults", f.verdict))
    if report is not None:
        for key in ("before", "after"):
            r = report[key]
            lines.append(f"held-out {key}: intent macro-F1 {100 * r['intent_macro_f1']:.1f} %,"
                         f" brake F1 {100 * (r['brake_f1'] or 0):.1f} %, UNKNOWN share "
                         f"{100 * r['unknown_share']:.1f} % ({r['scored_frames']} frames)")
        lines.append(f"report: {report_paths(Path(out))[1]}")
    return lines
