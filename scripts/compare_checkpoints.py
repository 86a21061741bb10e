#!/usr/bin/env python3
"""Is one checkpoint better than another, or did the scenes decide? A scene bootstrap.

Every checkpoint is run once over the same labelled tracks (materialised splits or labelled
bags, as ``signal-light calibrate`` reads them) through the node's intent filter, and scored
as step 3 of the recipe scores (the mean of intent macro-F1 and brake F1 of ON). Then the
scenes are resampled with replacement: each file's score gets a 90 % interval and, against
the first file, the paired difference gets one (``evaluation.bootstrap``; docs/model.md,
"How many scenes decide step 3"). Usage::

    python scripts/compare_checkpoints.py --data runs/streak/family_cal_split \\
        --checkpoint signal_light_node/weights/default.pt --checkpoint RUN/joined/calibrated.pt \\
        --json OUT.json

Checkpoints that crop differently (``crop_fill``) read the same tracks from twin splits:
give both (``--data runs/bright/family_test_split --data runs/fill/family_test_split``);
each file reads the bags and the splits cut as it crops, and the tracks must pair with
the first file's frame for frame.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from typing import List, Optional

import torch

from signal_light_node.evaluation.bootstrap import (require_same_tracks, scene_bootstrap,
                                                    scene_groups, track_confusions)
from signal_light_node.evaluation.streaming import chunks, predict_track_probs
from signal_light_node.model.checkpoint import load_checkpoint
from signal_light_node.training.sources import paths_cut_with
from signal_light_node.training.unknown_bias import load_labelled


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, action="append", required=True,
                        help="a split directory or labelled bag (repeatable)")
    parser.add_argument("--checkpoint", type=Path, action="append", required=True,
                        help=".pt checkpoint (repeatable; the first is the reference)")
    parser.add_argument("--resamples", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch-tracks", type=int, default=32)
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    reference, files, by_crop = None, [], {}
    for path in args.checkpoint:
        model = load_checkpoint(path, map_location="cpu").model.eval()
        crop = model.config.crop_config()
        if crop not in by_crop:  # files that crop alike read the same tracks once
            by_crop[crop] = load_labelled(paths_cut_with(args.data, crop), crop)
        tracks = by_crop[crop]
        if reference is None:
            reference = tracks
        require_same_tracks(reference, tracks, f"the data {path} reads")
        preds = []
        with torch.no_grad():
            for batch in chunks(tracks, args.batch_tracks):
                preds += predict_track_probs(model, batch)[0]
        files.append(track_confusions(tracks, preds))
    tracks = reference
    groups = scene_groups(tracks)
    rows = scene_bootstrap(files, groups, args.resamples, args.seed)

    print(f"{len(tracks)} tracks in {len(groups)} scenes, {args.resamples} resamples of the scenes")
    print("| checkpoint | score | 90 % interval | minus the first | 90 % interval | resamples above the first |")
    print("|---|---:|---:|---:|---:|---:|")
    for path, row in zip(args.checkpoint, rows):
        print(f"| {path} | {100 * row.score:.1f} % | {100 * row.interval[0]:.1f}-"
              f"{100 * row.interval[1]:.1f} % | {100 * row.difference:+.1f} | "
              f"{100 * row.difference_interval[0]:+.1f} to {100 * row.difference_interval[1]:+.1f} | "
              f"{100 * row.share_above:.0f} % |")
    if args.json:
        args.json.write_text(json.dumps(
            {"data": [str(d) for d in args.data], "tracks": len(tracks), "scenes": len(groups),
             "resamples": args.resamples, "seed": args.seed,
             "files": {str(p): asdict(r) for p, r in zip(args.checkpoint, rows)}}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
