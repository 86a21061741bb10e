"""Side-by-side table of ablation runs (``scripts/ablations.sh``).

Each run directory is one ``scripts/train_default.sh`` run: ``frames/`` and ``lanes/``
training summaries and ``test_eval/metrics.json`` from ``signal-light evaluate``.

Usage::

    python -m signal_light_node.training.ablation_report --out docs/ablations.md \\
        full=runs/ablations/full no_attention=runs/ablations/no_attention
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

from signal_light_node.errors import SignalLightError
from signal_light_node.evaluation.metrics import percent_cell

# (summary key, column title) of the headline figures, in table order.
_COLUMNS = (("intent_macro_f1", "intent macro-F1"), ("brake_accuracy", "brake accuracy"),
            ("intent_fp_rate", "intent FP"), ("intent_fn_rate", "intent FN"),
            ("lights_fp_rate", "lights FP"), ("lights_fn_rate", "lights FN"))
_STAGES = ("frames", "lanes")


def _read_json(path: Path) -> Dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SignalLightError(f"cannot read {path}: {exc}") from exc


def load_run(name: str, run_dir: Path) -> Dict[str, Any]:
    """The figures of one ablation run.

    Args:
        name: The variant's name.
        run_dir: Its ``train_default.sh`` RUN directory.

    Returns:
        ``{"name", "run", "summary", "grace_summary", "steps", "train_seconds", "data"}``.

    Raises:
        SignalLightError: If the evaluation or a training summary is missing or unreadable.
    """
    metrics = _read_json(run_dir / "test_eval" / "metrics.json")
    steps: Dict[str, int] = {}
    seconds = 0.0
    for stage in _STAGES:
        summary = _read_json(run_dir / stage / "summary.json")
        steps[stage] = int(summary["steps"])
        seconds += float(summary.get("wall_seconds", 0.0))
    return {"name": name, "run": str(run_dir), "summary": metrics["no_grace"]["summary"],
            "grace_summary": metrics["grace"]["summary"], "steps": steps,
            "train_seconds": seconds, "data": metrics.get("data_brief", {})}


def render_markdown(runs: Sequence[Mapping[str, Any]], command: str = "") -> str:
    """A Markdown report: one row per run, the first run being the reference."""
    lines: List[str] = ["## Ablations", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    if runs:
        data = runs[0]["data"]
        lines += [f"Test split: `{data.get('split')}` (seed {data.get('seed')}, "
                  f"{data.get('n_sequences')} tracks, {data.get('n_observations')} frames), "
                  "scored frame by frame after the warm-up, no grace window.", ""]
    header = "| variant | steps (frames + lanes) | train min | " + \
        " | ".join(title for _, title in _COLUMNS) + " |"
    lines += [header, "|---|---:|---:|" + "---:|" * len(_COLUMNS)]
    for run in runs:
        steps = " + ".join(str(run["steps"][s]) for s in _STAGES)
        cells = " | ".join(percent_cell(run["summary"].get(key)) for key, _ in _COLUMNS)
        lines.append(f"| {run['name']} | {steps} | {run['train_seconds'] / 60:.0f} | {cells} |")
    lines.append("")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    """Write the ablation table as Markdown (``--out``) and JSON (same name, ``.json``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", metavar="NAME=RUN_DIR")
    parser.add_argument("--out", type=Path, required=True, help="Markdown file to write")
    parser.add_argument("--command", default="", help="command that produced the runs")
    args = parser.parse_args(argv)
    runs = []
    for spec in args.runs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            parser.error(f"expected NAME=RUN_DIR, got {spec!r}")
        runs.append(load_run(name, Path(path)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(render_markdown(runs, args.command))
    args.out.with_suffix(".json").write_text(json.dumps(runs, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
