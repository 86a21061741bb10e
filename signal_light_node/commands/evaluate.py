"""``signal-light evaluate``: score a checkpoint, frame by frame, as the engine runs it.

Data (one of): a materialised split (``--split DIR``), labelled bags (``--bags``), the
UC Merced layout (``--ucm``), or synthetic tracks rendered on the fly
(``--synthetic-seed N --tracks N``; the same seed always gives the same tracks).

Every track is stepped through ``model.step`` from a fresh state and its outputs through
the node's intent filter (``--no-intent-filter`` scores the raw model); frames in the
warm-up (the first ``max(--warmup-frames, --warmup-seconds)`` of each track) are not
scored, and a second report also leaves out ``--grace`` seconds after each ground-truth
change (see :mod:`signal_light_node.evaluation.scoring`). The reports also count the
switches (class changes along the tracks, predicted against true), per track as well
(the flicker table, worst tracks first), the share of UNKNOWN published per light where
the truth is OFF or ON, and the calibration of each light's published probabilities
(ECE). Writes ``metrics.json``, ``metrics.md``,
``confusion_intent.png`` (no grace window), ``confusion_intent_grace.png`` and one
reliability diagram per light head, ``reliability_<light>.png``, into ``--out`` and
prints the Markdown.

``--ideal-observer`` scores, instead of a checkpoint, the best any online model could do
on a split or synthetic tracks (:mod:`signal_light_node.evaluation.ideal_observer`): the
ceiling of each metric under these scoring rules.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from itertools import islice
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, Optional, Tuple

from signal_light_node.commands.options import (add_intent_filter_options,
                                                add_labelled_data_options, add_model_options,
                                                add_torch_options, intent_filter_from_args)
from signal_light_node.errors import ConfigError

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light evaluate``."""
    # The scoring rules' defaults live in EvalSettings only (replay scores with them too).
    from signal_light_node.evaluation.scoring import EvalSettings

    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    add_model_options(parser)
    parser.add_argument("--out", type=Path, required=True, help="directory for the reports")
    data = parser.add_argument_group("data (choose one)")
    data.add_argument("--split", type=Path, default=None, help="materialised split directory")
    add_labelled_data_options(data)
    data.add_argument("--synthetic-seed", type=int, default=None,
                      help="render synthetic test tracks from this stream seed")
    data.add_argument("--tracks", type=int, default=200,
                      help="number of synthetic tracks (with --synthetic-seed)")
    data.add_argument("--track-frames", type=int, default=120,
                      help="frames per synthetic scene (with --synthetic-seed)")
    data.add_argument("--lighting", default="unknown",
                      help="lighting recorded for bag tracks (bags do not carry it)")
    rules = parser.add_argument_group("scoring")
    rules.add_argument("--warmup-frames", type=int, default=EvalSettings.warmup_frames,
                       help="frames at the start of each track not scored")
    rules.add_argument("--warmup-seconds", type=float,
                       default=EvalSettings.warmup_seconds,
                       help="seconds at the start of each track not scored")
    rules.add_argument("--grace", type=float, default=EvalSettings.grace_seconds,
                       help="seconds after each label change left out of the grace report")
    rules.add_argument("--ideal-observer", action="store_true",
                       help="score the ideal causal observer (perfect per-frame sight, known "
                            "flasher timing) instead of a checkpoint: the ceiling of every "
                            "metric (--split or --synthetic-seed)")
    add_intent_filter_options(parser.add_argument_group("intent filter (as the node's)"))
    parser.add_argument("--batch-tracks", type=int, default=EvalSettings.batch_tracks,
                        help="tracks stepped together")
    add_torch_options(parser)


def _tracks(args: argparse.Namespace, crop: Any) -> Tuple[Iterable[Any], Optional[int], Dict]:
    """The chosen data as an iterable of tracks, its length if known, and a description."""
    from signal_light_node.evaluation.tracks import track_from_item
    from signal_light_node.training import sources

    _check_one_source(args)
    if args.bags:
        tracks = []
        for bag in args.bags:
            tracks += sources.load_bag_tracks(bag, crop, lighting=args.lighting)
        return tracks, len(tracks), {"bags": [str(b) for b in args.bags]}
    if args.ucm:
        tracks = []
        for root in args.ucm:
            tracks += sources.load_ucm_tracks(root, crop)
        return tracks, len(tracks), {"ucm": [str(u) for u in args.ucm]}
    items, total, data = _items(args, crop)
    source = args.split.name if args.split is not None else f"synthetic:{args.synthetic_seed}"
    gen = (track_from_item(item, f"{source}:{i}") for i, item in enumerate(items))
    return gen, total, data


def _check_one_source(args: argparse.Namespace) -> None:
    chosen = [name for name, given in (("--split", args.split is not None),
                                       ("--bags", bool(args.bags)), ("--ucm", bool(args.ucm)),
                                       ("--synthetic-seed", args.synthetic_seed is not None))
              if given]
    if len(chosen) != 1:
        raise ConfigError("choose exactly one of --split, --bags, --ucm, --synthetic-seed"
                          + (f" (got {', '.join(chosen)})" if chosen else ""))


def _items(args: argparse.Namespace, crop: Any) -> Tuple[Iterator[Any], int, Dict]:
    """Split or synthetic-stream items (crops, both label arrays, meta), count, description."""
    if args.split is not None:
        from signal_light_node.data.split import SequenceSplit

        split = SequenceSplit(args.split)
        split.require_crop(crop)
        items = (split[i] for i in range(len(split)))
        return items, len(split), {"split": str(args.split), **split.summary()}
    if args.synthetic_seed is None:
        raise ConfigError("--ideal-observer needs --split or --synthetic-seed: bags and UCM "
                          "sequences carry no per-frame lamp labels")
    if args.tracks < 1 or args.track_frames < 2:
        raise ConfigError("--tracks must be >= 1 and --track-frames >= 2")
    from signal_light_node.data.stream import SyntheticSequenceStream

    stream = SyntheticSequenceStream(int(args.synthetic_seed), int(args.track_frames), crop,
                                     mirror_prob=0.0, jitter=False, full_tracks=True, rank=0)
    items = islice(stream.sequences(worker_id=0), int(args.tracks))
    return items, int(args.tracks), {"synthetic_seed": int(args.synthetic_seed),
                                   "tracks": int(args.tracks),
                                   "track_frames": int(args.track_frames)}


def _headline(result: Dict[str, Any]) -> str:
    lines = ["| report | intent macro-F1 | brake accuracy | intent FP | intent FN | "
             "lights FP | lights FN |", "|---|---:|---:|---:|---:|---:|---:|"]
    for key, name in (("no_grace", "after warm-up"), ("grace", "after warm-up, with grace")):
        s = result[key]["summary"]

        def pct(v: Optional[float]) -> str:
            return "–" if v is None else f"{100 * v:.1f} %"

        lines.append(f"| {name} | {pct(s['intent_macro_f1'])} | {pct(s['brake_accuracy'])} | "
                     f"{pct(s['intent_fp_rate'])} | {pct(s['intent_fn_rate'])} | "
                     f"{pct(s['lights_fp_rate'])} | {pct(s['lights_fn_rate'])} |")
    return "\n".join(lines)


def render_markdown(result: Dict[str, Any]) -> str:
    """The whole evaluation as Markdown (headline, then both full reports)."""
    from signal_light_node.evaluation.metrics import (flicker_markdown, light_outcomes_markdown,
                                                      markdown_report, switches_markdown,
                                                      unknown_by_view_markdown)

    st, counts = result["settings"], result["counts"]
    intent = result["switches"]["intent"]
    ratio = "–" if intent["ratio"] is None else f"{intent['ratio']:.2f}"
    parts = [
        f"## Evaluation of `{result['checkpoint']}`", "",
        *([result["model"]["text"], ""] if result.get("model") else []),
        f"Data: `{json.dumps(result['data_brief'])}`", "",
        f"{counts['tracks']} tracks, {counts['stepped']} frames "
        f"{'judged' if result.get('ideal_observer') else 'stepped through `model.step`'}, "
        f"{counts['scored']} scored after the warm-up (first max({st['warmup_frames']} frames, "
        f"{st['warmup_seconds']:g} s) of each track, {counts['warmup_excluded']} frames). "
        f"Grace window: {st['grace_seconds']:g} s after each ground-truth change of a head."
        + (f" Intent filter: {result['intent_filter_text']}."
           if result.get("intent_filter_text") else ""), "",
        _headline(result), "",
        f"Intent switches after the warm-up: {intent['predicted']} predicted, "
        f"{intent['true']} true (ratio {ratio}).", "",
        markdown_report(result["no_grace"], "After warm-up (no grace window)"),
        markdown_report(result["grace"],
                        f"After warm-up, {st['grace_seconds']:g} s grace window after label changes"),
        "### Switches (after warm-up: class changes along the tracks)", "",
        switches_markdown(result["switches"]),
        "### Flicker per track (after warm-up)", "",
        flicker_markdown(result.get("flicker", [])),
        "### UNKNOWN published where the truth is OFF or ON"
        + (" and calibration (ECE, 15 bins of the predicted class's confidence)"
           if result.get("calibration") else ""), "",
        light_outcomes_markdown(result["unknown_share"], result.get("calibration")),
    ]
    by_view = unknown_by_view_markdown(result.get("unknown_by_view", []))
    if by_view:
        parts += ["### Where the UNKNOWNs come from: true view -> view published", "", by_view]
    return "\n".join(parts)


def _model_meta(backend: Any) -> Dict[str, Any]:
    """Where the scored model came from: a checkpoint's training metadata, an export's
    source and hash."""
    from signal_light_node.model import DEFAULT_WEIGHTS, load_checkpoint

    metadata = getattr(backend, "metadata", None)
    if metadata is not None:  # an ONNX export
        return {k.split(".", 1)[-1]: v for k, v in metadata.items()
                if k.startswith("signal_light.source") or k.endswith("package_version")}
    meta = load_checkpoint(backend.source or DEFAULT_WEIGHTS).meta
    return {k: meta.get(k) for k in ("training_data", "created", "package_version")}


def run(args: argparse.Namespace) -> int:
    """Evaluate and write the reports; prints the Markdown."""
    import numpy as np

    from signal_light_node.labels import CLASS_NAMES
    from signal_light_node.model.backends.registry import create_backend
    from signal_light_node.runtime.backend import ModelRun
    from signal_light_node.evaluation.ideal_observer import score_ideal_observer
    from signal_light_node.evaluation.metrics import render_confusion_png, render_reliability_png
    from signal_light_node.evaluation.scoring import EvalSettings
    from signal_light_node.evaluation.streaming import evaluate_tracks
    from signal_light_node.runtime.intent_filter import IntentFilter

    backend = create_backend(args.backend, None if args.checkpoint is None
                             else str(args.checkpoint), device=args.device,
                             threads=args.threads, precision=args.precision)
    checkpoint = backend.source or "the shipped model"
    settings = EvalSettings(warmup_frames=args.warmup_frames,
                            warmup_seconds=args.warmup_seconds, grace_seconds=args.grace,
                            batch_tracks=args.batch_tracks)
    started = time.monotonic()
    ran: Optional[ModelRun] = None
    if args.ideal_observer:
        _check_one_source(args)
        # The model only gives the crop settings the split must have been made with.
        items, _, data = _items(args, backend.config.crop_config())
        result = score_ideal_observer(items, settings)
        checkpoint = "the ideal observer"
    else:
        intent_filter = intent_filter_from_args(args)
        if IntentFilter(intent_filter).uses_cover and not args.bags:
            logger.warning("a sight of geometry needs every box of a frame: only bags keep "
                           "them, so here every light's UNKNOWN stays the model's")
        tracks, total, data = _tracks(args, backend.config.crop_config())
        result = evaluate_tracks(backend, tracks, settings, progress=not args.no_progress,
                                 total=total, intent_filter=intent_filter)
        result["intent_filter_text"] = intent_filter.describe()
        ran = ModelRun.of(backend)  # after the steps: the threads they ran on
    result = {"checkpoint": str(checkpoint), "ideal_observer": bool(args.ideal_observer),
              "data": data,
              "data_brief": {k: v for k, v in data.items()
                             if k not in ("label_histogram", "lighting")},
              "seconds": round(time.monotonic() - started, 1),
              "backend": backend.name, "checkpoint_meta": _model_meta(backend),
              "model": None if ran is None else ran.as_dict(), **result}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    markdown = render_markdown(result)
    (out / "metrics.md").write_text(markdown)
    for key, name in (("no_grace", "confusion_intent.png"), ("grace", "confusion_intent_grace.png")):
        intent = result[key]["overall"].get("intent")
        matrix = np.asarray(intent["confusion"]) if intent else np.zeros((5, 5), np.int64)
        render_confusion_png(matrix, CLASS_NAMES["intent"], str(out / name),
                             title=f"intent, {'grace window' if key == 'grace' else 'after warm-up'}")
    for light, report in result.get("calibration", {}).items():
        render_reliability_png(report, str(out / f"reliability_{light}.png"),
                               title=f"{light}: reliability, ECE {report['ece']:.3f} "
                                     f"({report['frames']} frames, truth OFF/ON)")
    print(markdown)
    logger.info("wrote %s/metrics.json, metrics.md, confusion_intent.png, reliability_*.png", out)
    return 0
