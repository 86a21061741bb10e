#!/usr/bin/env python3
"""In-domain and transfer scores of one checkpoint, side by side.

Runs ``signal-light evaluate`` on each data set and gathers the figures the model issue
asks for into one table (Markdown and JSON):

* ``own``: the training renderer's held-out test split (style families 0 and 1);
* ``family``: the same renderer's held-out style family 2 (lamp colours and camera tone
  curves never rendered for training);
* ``independent``: the committed bags of the second, independent generator
  (``signal_light_node.evalgen``: its own geometry, lamps and sensor model);
* ``day_street`` and ``night_street``: the committed bags of the training renderer
  (``scripts/make_bags.sh``, truth by the ``lamp`` rule), which ``test/test_replay.py``
  holds the shipped file to (``COMMITTED_BAG_BOUNDS``).

Every set is scored after the warm-up, without a grace window, as the node publishes it
(intent filter on unless ``--no-intent-filter``). Brake, left and right F1 are the F1 of
the ON class; "switches" are predicted intent (brake) changes over the ground truth's.

Each set's full ``signal-light evaluate`` report lands in ``OUT/own``, ``OUT/family`` and
``OUT/independent``. Usage::

    python scripts/transfer_report.py --checkpoint signal_light_node/weights/default.pt \\
        --data runs/v10 --out runs/v10/transfer
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

REPO = Path(__file__).resolve().parents[1]
INDEPENDENT_BAGS = ("bags/independent_day", "bags/independent_night")
#: The training renderer's committed bags and the replay test's bounds on them (brake
#: accuracy, intent macro-F1; test/test_replay.py): a candidate must hold them to ship.
COMMITTED_BAGS = ("bags/day_street", "bags/night_street")
COMMITTED_BAG_BOUNDS = {"brake_acc": 0.93, "intent_f1": 0.60}
COLUMNS = (("intent macro-F1", "intent_f1"), ("intent FP", "intent_fp"),
           ("intent FN", "intent_fn"), ("brake acc.", "brake_acc"), ("brake F1", "brake_f1"),
           ("brake recall", "brake_recall"), ("left F1", "left_f1"), ("right F1", "right_f1"),
           ("intent switches / truth", "switches"), ("brake switches / truth", "brake_switches"),
           ("UNKNOWN where a lamp is visible", "unknown_visible"))
#: The hard-negative bags are signal_light_node.tools.hard_negatives.HARD_NEGATIVE_BAGS: from
#: the independent generator with no signal at all. night_tail_lamps: steady lit tail lamps
#: from behind; night_no_signals: every view at night (head lamps, glare, wet-road
#: reflections); day_running_lamps: every view by day (daytime running lamps, sun glints).
#: The last two: `python -m signal_light_node.evalgen -o bags/NAME --seed 41|42
#: --lighting day|night --events none --width 640 --height 360 --frames 60 --jpeg-quality 80`.


def _on_class(overall: Dict[str, Any], task: str, key: str) -> Optional[float]:
    per_class = overall.get(task, {}).get("per_class", {})
    values = per_class.get(key) or []
    return values[1] if len(values) > 1 else None  # class 1 = ON


def figures(metrics: Dict[str, Any]) -> Dict[str, Optional[float]]:
    """The table's figures from an ``evaluate`` metrics.json."""
    from signal_light_node.evaluation.metrics import unknown_where_visible

    report = metrics["no_grace"]
    summary, overall = report["summary"], report["overall"]
    switches = metrics.get("switches", {}).get("intent", {})
    brake_switches = metrics.get("switches", {}).get("brake", {})
    return {"intent_f1": summary["intent_macro_f1"], "intent_fp": summary["intent_fp_rate"],
            "intent_fn": summary["intent_fn_rate"], "brake_acc": summary["brake_accuracy"],
            "brake_f1": _on_class(overall, "brake", "f1"),
            "brake_recall": _on_class(overall, "brake", "recall"),
            "left_f1": _on_class(overall, "left", "f1"),
            "right_f1": _on_class(overall, "right", "f1"),
            "switches": switches.get("ratio"), "brake_switches": brake_switches.get("ratio"),
            "unknown_visible": unknown_where_visible(overall),
            "scored_frames": metrics.get("counts", {}).get("scored")}


def evaluate(name: str, data: List[str], checkpoint: Path, out: Path,
             extra: Sequence[str]) -> Dict[str, Any]:
    """Run ``signal-light evaluate`` on one set (a split or bags); its metrics.json."""
    target = out / name
    cmd = ["signal-light", "evaluate", "--checkpoint", str(checkpoint), "--out", str(target),
           "--no-progress", *extra, *data]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return json.loads((target / "metrics.json").read_text())


def hard_negatives(checkpoint: Path, out: Path, visibility_confirm_s: float,
                   brake_sight: str = "model") -> Dict[str, Dict[str, float]]:
    """Shares of judged vehicle-frames reporting a light ON in each hard-negative bag.

    Args:
        checkpoint: The model file.
        out: Where each bag's replay lands.
        visibility_confirm_s: The intent filter's hold on a light turning UNKNOWN or back,
            as the evaluated sets get it (``--filter-visibility-confirm``).
        brake_sight: The filter's ``brake_sight``, as the evaluated sets get it.
    """
    from signal_light_node.runtime.engine import engine_from_checkpoint
    from signal_light_node.runtime.intent_filter import IntentFilterConfig
    from signal_light_node.tools.hard_negatives import HARD_NEGATIVE_BAGS, false_lights

    held = IntentFilterConfig(visibility_confirm_s=visibility_confirm_s, brake_sight=brake_sight)
    return {bag: vars(false_lights(REPO / bag, engine_from_checkpoint(checkpoint,
                                                                      intent_filter=held),
                                   out / Path(bag).name))
            for bag in HARD_NEGATIVE_BAGS}


def evaluate_options(args: argparse.Namespace) -> List[str]:
    """The options every ``signal-light evaluate`` run of the report gets."""
    extra = ["--threads", str(args.threads)]
    if args.no_intent_filter:
        return extra + ["--no-intent-filter"]
    return extra + ["--filter-visibility-confirm", f"{args.filter_visibility_confirm:g}",
                    "--filter-brake-sight", args.filter_brake_sight]


def _cell(key: str, value: Optional[float]) -> str:
    if value is None:
        return "-"
    return f"{value:.2f}x" if key.endswith("switches") else f"{100 * value:.1f} %"


def markdown(rows: Dict[str, Dict[str, Optional[float]]]) -> str:
    """One row per data set."""
    head = "| data | " + " | ".join(c for c, _ in COLUMNS) + " | scored frames |"
    lines = [head, "|---|" + "---:|" * (len(COLUMNS) + 1)]
    for name, f in rows.items():
        cells = " | ".join(_cell(k, f.get(k)) for _, k in COLUMNS)
        lines.append(f"| {name} | {cells} | {f.get('scored_frames') or '-'} |")
    return "\n".join(lines) + "\n"


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """The report's command line."""
    from signal_light_node.runtime.intent_filter import BRAKE_SIGHTS, IntentFilterConfig

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", type=Path, default=REPO / "signal_light_node/weights/default.pt")
    p.add_argument("--data", type=Path, default=REPO / "runs/default",
                   help="scripts/train_default.sh DATA directory (test_split, family_test_split)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--no-intent-filter", action="store_true", help="score the raw model")
    p.add_argument("--threads", default="2")
    p.add_argument("--filter-visibility-confirm", type=float,
                   default=IntentFilterConfig.visibility_confirm_s, metavar="S",
                   help="the intent filter's visibility hold for every set, hard negatives "
                        "included (the node's filter_visibility_confirm_s; 0: none)")
    p.add_argument("--filter-brake-sight", choices=BRAKE_SIGHTS,
                   default=IntentFilterConfig.brake_sight,
                   help="the intent filter's brake sight for every set, hard negatives "
                        "included (the node's filter_brake_sight)")
    p.add_argument("--independent-renders", nargs="*", type=Path, default=[], metavar="BAG",
                   help="more bags of the independent generator (scripts/render_independent.sh),"
                        " scored as one more row")
    return p.parse_args(argv)


def main(argv: Optional[Sequence[str]] = None) -> int:
    from signal_light_node.evaluation.metrics import unknown_by_view_markdown

    args = parse_args(argv)
    extra = evaluate_options(args)
    # (report directory, row name, data)
    sets = (("own", "own test split (families 0-1)", ["--split", str(args.data / "test_split")]),
            ("family", "held-out style family 2",
             ["--split", str(args.data / "family_test_split")]),
            ("independent", "independent generator (2 bags)", ["--bags", *INDEPENDENT_BAGS]))
    if args.independent_renders:
        bags = [str(b) for b in args.independent_renders]
        sets += (("independent_renders", f"independent renders ({len(bags)} scenes)",
                  ["--bags", *bags]),)
    sets += tuple((Path(bag).name, f"committed bag {Path(bag).name} (lamp rule)", ["--bags", bag])
                  for bag in COMMITTED_BAGS)
    metrics = {name: evaluate(folder, data, args.checkpoint, args.out, extra)
               for folder, name, data in sets}
    rows = {name: figures(m) for name, m in metrics.items()}
    by_view = {name: m.get("unknown_by_view", []) for name, m in metrics.items()}
    args.out.mkdir(parents=True, exist_ok=True)
    table = markdown(rows)
    for name in [n for n in by_view if n.startswith("independent")]:
        table += (f"\nWhere the UNKNOWNs come from, {name} (brake, left and right where the "
                  f"truth is OFF or ON):\n\n{unknown_by_view_markdown(by_view[name])}")
    held = [f"{name}: brake {100 * rows[name]['brake_acc']:.1f} %, intent "
            f"{100 * rows[name]['intent_f1']:.1f} %" for name in rows if name.startswith("committed")]
    table += ("\nCommitted bags of the training renderer, as the replay test bounds them (brake "
              f"accuracy >= {100 * COMMITTED_BAG_BOUNDS['brake_acc']:.0f} %, intent macro-F1 >= "
              f"{100 * COMMITTED_BAG_BOUNDS['intent_f1']:.0f} %): " + "; ".join(held) + "\n")
    negatives = hard_negatives(args.checkpoint, args.out, args.filter_visibility_confirm,
                               "model" if args.no_intent_filter else args.filter_brake_sight)
    table += ("\nHard negatives (no signal at all; share of judged vehicle-frames reporting "
              "a light ON; target for blinkers < 5 %):\n\n| bag | blinker ON | brake ON | "
              "judged |\n|---|---:|---:|---:|\n")
    for bag, f in negatives.items():
        table += (f"| {Path(bag).name} | {100 * f['blinker_on']:.1f} % | "
                  f"{100 * f['brake_on']:.1f} % | {f['judged']} |\n")
    (args.out / "transfer.md").write_text(table)
    (args.out / "transfer.json").write_text(json.dumps(
        {"checkpoint": str(args.checkpoint), "intent_filter": not args.no_intent_filter,
         "visibility_confirm_s": args.filter_visibility_confirm,
         "brake_sight": args.filter_brake_sight,
         "sets": rows, "unknown_by_view": by_view, "hard_negatives": negatives},
        indent=2) + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
