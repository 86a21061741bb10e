#!/usr/bin/env python3
"""Sight or time? Per day blink episode, what the per-frame lit head saw against what the
model called.

A day blink episode is a light (left or right) whose truth is ON for at least
``--min-frames`` frames of a daylight track after the warm-up. For each, the model's
per-frame lit head (``ModelConfig.lit_head``; with members, their mean P(lit)) is read on
the episode's lit and dark frames (the split's ``lit_labels``) and beside it the share of
the episode's frames the model's argmax calls ON (the members' mean logits, before any
calibration or filter). An episode the model misses while its lit head saw the flashes is
a failure of time; one whose flashes the lit head did not see is a failure of sight.
Usage::

    python scripts/probe_sight.py --split runs/fillf/family_cal_split \\
        [--model signal_light_node/weights/default.pt] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch

from signal_light_node.data.split import SequenceSplit
from signal_light_node.evaluation.scoring import EvalSettings, warmup_mask
from signal_light_node.evaluation.tracks import track_from_item
from signal_light_node.labels import TASKS
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint

LIGHTS = ("left", "right")
#: An episode is missed below this share of its frames called ON, called above the other.
MISSED, CALLED = 0.1, 0.7


@torch.no_grad()
def track_outputs(model: torch.nn.Module, crops: np.ndarray) -> Dict[str, np.ndarray]:
    """Per light of one track's uint8 crops ``[T, S, S, 3]``: ``P(lit)`` ``[T]`` of the lit
    head and ``ON`` ``[T]`` (bool) of the argmax, each over the members' mean."""
    x = torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 255.0
    features, maps = model.frame_features(x)
    members = getattr(model, "members", [model])
    outs = [m.sequence_features(features.unsqueeze(0), maps.unsqueeze(0))[0] for m in members]
    result = {}
    for light in LIGHTS:
        lit = torch.stack([torch.softmax(o[f"lit_{light}"][0], -1)[:, 1] for o in outs]).mean(0)
        logits = torch.stack([o[light][0] for o in outs]).mean(0)
        result[f"plit_{light}"] = lit.numpy()
        result[f"on_{light}"] = (logits.argmax(-1) == 1).numpy()
    return result


def _mean(values: np.ndarray) -> float:
    return float(values.mean()) if len(values) else float("nan")


def episodes(model: torch.nn.Module, split: SequenceSplit, min_frames: int) -> List[Dict]:
    """One row per day blink episode of ``split`` (module doc)."""
    rows = []
    for i in range(len(split)):
        item = split[i]
        if item["meta"]["lighting"] != "day":
            continue
        n = int(item["mask"].sum())
        valid = warmup_mask(track_from_item(item, str(i)), EvalSettings())[:n]
        out = track_outputs(model, item["crops"][:n])
        for light in LIGHTS:
            j = TASKS.index(light)
            on = (item["labels"][:n, j] == 1) & valid
            if on.sum() < min_frames:
                continue
            lit = item["lit_labels"][:n, j]
            plit = out[f"plit_{light}"]
            rows.append({"track": i, "light": light, "design": item["meta"]["lamp_design"],
                         "frames": int(on.sum()),
                         "on_share": float(out[f"on_{light}"][on].mean()),
                         "lit_recall": _mean(plit[on & (lit == 1)] > 0.5),
                         "dark_called_lit": _mean(plit[on & (lit == 0)] > 0.5)})
    return rows


def summary(rows: List[Dict]) -> Dict[str, Dict[str, float]]:
    """Per lamp design and for missed / called episodes: count, mean ON share, missed share,
    mean lit-head recall on lit frames and share of dark frames called lit."""
    groups: Dict[str, List[Dict]] = defaultdict(list)
    for row in rows:
        groups[row["design"]].append(row)
        if row["on_share"] < MISSED:
            groups["missed episodes"].append(row)
        elif row["on_share"] > CALLED:
            groups["called episodes"].append(row)
    groups["all"] = rows
    table = {}
    for name, group in groups.items():
        table[name] = {"episodes": len(group),
                       "on_share": float(np.mean([r["on_share"] for r in group])),
                       "missed": float(np.mean([r["on_share"] < MISSED for r in group])),
                       "lit_recall": float(np.nanmean([r["lit_recall"] for r in group])),
                       "dark_called_lit": float(np.nanmean([r["dark_called_lit"]
                                                            for r in group]))}
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", type=Path, required=True)
    parser.add_argument("--model", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--min-frames", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_checkpoint(args.model).model
    if not getattr(model.config, "lit_periods", False):
        parser.error(f"{args.model} has no per-frame lit head in its steps (lit_periods)")
    rows = episodes(model, SequenceSplit(args.split), args.min_frames)
    table = summary(rows)
    print(f"{'day blink episodes':18s} {'n':>4s} {'ON share':>9s} {'missed':>7s} "
          f"{'lit-head recall':>16s} {'dark called lit':>16s}")
    for name, r in table.items():
        print(f"{name:18s} {r['episodes']:4d} {r['on_share']:9.2f} {r['missed']:7.2f} "
              f"{r['lit_recall']:16.2f} {r['dark_called_lit']:16.2f}")
    if args.json:
        args.json.write_text(json.dumps({"split": str(args.split), "model": str(args.model),
                                         "summary": table, "episodes": rows}, indent=1))


if __name__ == "__main__":
    main()
