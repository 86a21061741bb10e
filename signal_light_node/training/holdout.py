"""Adapting with labels: hold out a part of the user's tracks, and the before/after report.

``signal-light train --init-from MODEL --bags LABELLED... --holdout-fraction F`` sets aside
a share ``F`` of the labelled tracks, chosen by track ID (each bag's ``bag:ID``) with the
run's seed, so the same options always hold out the same tracks. The run never sees them
(neither for training nor for validation); afterwards :func:`before_after` evaluates the
``--init-from`` model and the fine-tuned one on them, as ``signal-light evaluate`` scores
(through the node's intent filter, its warm-up rules), and :func:`write_report` writes
``adapt_report.json`` and ``adapt_report.md`` into the run's folder: intent macro-F1,
brake F1 (of ON) and the share of UNKNOWN published where a light's truth is OFF or ON.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Mapping, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import percent_cell
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LightStatus

#: The files :func:`write_report` writes into the run's folder.
REPORT_JSON, REPORT_MD = "adapt_report.json", "adapt_report.md"


def split_by_track_id(tracks: Sequence[TrackSequence], fraction: float, seed: int
                      ) -> Tuple[List[TrackSequence], List[TrackSequence]]:
    """``(kept, held_out)``: round(fraction x track IDs) IDs held out (at least one when
    fraction > 0), drawn with ``seed``; every track of a held-out ID goes with it.

    Raises:
        ConfigError: A fraction > 0 would hold out every track, or there are under 2 IDs.
    """
    if fraction <= 0:
        return list(tracks), []
    ids = sorted({t.track_id for t in tracks})
    n = max(1, int(round(fraction * len(ids))))
    if len(ids) < 2 or n >= len(ids):
        raise ConfigError(f"--holdout-fraction {fraction:g}: {len(ids)} labelled track(s), "
                          "nothing would be left to fine-tune on or to hold out")
    order = np.random.default_rng(seed).permutation(len(ids))
    held = {ids[i] for i in order[:n]}
    return ([t for t in tracks if t.track_id not in held],
            [t for t in tracks if t.track_id in held])


def headline(result: Mapping[str, Any]) -> Dict[str, Any]:
    """Intent macro-F1, brake F1 (of ON) and the UNKNOWN share of an evaluation's result."""
    brake = result["no_grace"]["overall"].get("brake")
    return {"intent_macro_f1": result["no_grace"]["summary"]["intent_macro_f1"],
            "brake_f1": None if brake is None
            else brake["per_class"]["f1"][int(LightStatus.ON)],
            "unknown_share": result["unknown_share"]["overall"]["share"],
            "scored_frames": result["counts"]["scored"]}


def before_after(before: Any, after: Any, held_out: Sequence[TrackSequence],
                 before_name: str, after_name: str, after_filter: Any = None
                 ) -> Dict[str, Any]:
    """Evaluate both models on the held-out tracks (the node's intent filter, default rules).

    Args:
        before: The ``--init-from`` model (a model or backend).
        after: The fine-tuned model.
        held_out: The tracks held out of the run.
        before_name: What ``before`` is (its checkpoint).
        after_name: What ``after`` is.
        after_filter: The ``IntentFilterConfig`` that ``after`` is published with (None:
            the defaults, as ``before``).
    """
    from signal_light_node.evaluation.streaming import evaluate_tracks

    rows = {}
    for key, model, light_filter in (("before", before, None), ("after", after, after_filter)):
        rows[key] = headline(evaluate_tracks(model, held_out, progress=False,
                                             intent_filter=light_filter))
    report = {"held_out_tracks": sorted({t.track_id for t in held_out}),
              "before": {"model": before_name, **rows["before"]},
              "after": {"model": after_name, **rows["after"]}}
    if after_filter is not None:
        report["after"]["filter"] = after_filter.describe()
    return report


def report_markdown(report: Mapping[str, Any], what: str = "Fine-tuning") -> str:
    """The before/after report as Markdown, titled by ``what`` was done between them."""
    lines = [f"## {what}: before / after on {len(report['held_out_tracks'])} held-out "
             "tracks", "",
             f"Held-out tracks: {', '.join(report['held_out_tracks'])}", "",
             "| model | intent macro-F1 | brake F1 | UNKNOWN share | frames scored |",
             "|---|---:|---:|---:|---:|"]
    for key in ("before", "after"):
        r = report[key]
        lines.append(f"| {key}: `{r['model']}` | {percent_cell(r['intent_macro_f1'])} | "
                     f"{percent_cell(r['brake_f1'])} | {percent_cell(r['unknown_share'])} | "
                     f"{r['scored_frames']} |")
    if report["after"].get("filter"):
        lines += ["", f"After is published with the fitted filter: {report['after']['filter']}."]
    return "\n".join(lines) + "\n"


def report_after_run(opts: Any, summary: Mapping[str, Any],
                     held_out: Sequence[TrackSequence]) -> Path:
    """After a run: evaluate its ``--init-from`` model and its best (else last) checkpoint
    on the tracks it held out, write the report into its folder; returns the Markdown's path.

    Args:
        opts: The run's ``TrainOptions``.
        summary: The run's summary (``best_step``).
        held_out: The tracks :func:`split_by_track_id` held out of it.
    """
    from signal_light_node.model import load_checkpoint
    from signal_light_node.training.run_model import resolve_init

    init = resolve_init(opts.init_from)
    best = summary.get("best_step", -1) >= 0 and (opts.out / "best.pt").is_file()
    after = opts.out / ("best.pt" if best else "last.pt")
    before_model = load_checkpoint(init, map_location="cpu").model.eval()
    after_model = load_checkpoint(after, map_location="cpu").model.eval()
    write_report(opts.out, before_after(before_model, after_model, held_out, str(init),
                                        str(after)))
    return Path(opts.out) / REPORT_MD


def write_report(out: Path, report: Mapping[str, Any]) -> str:
    """Write ``adapt_report.json`` and ``adapt_report.md`` into ``out``; returns the Markdown."""
    markdown = report_markdown(report)
    (Path(out) / REPORT_JSON).write_text(json.dumps(report, indent=2) + "\n")
    (Path(out) / REPORT_MD).write_text(markdown)
    return markdown
