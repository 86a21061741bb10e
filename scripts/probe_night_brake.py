#!/usr/bin/env python3
"""Does anything tell a night brake from a tail lamp? The model against plain pixel statistics.

On the night tracks of each data set (bags of the second generator, or a rendered split's
night scenes), every rear-view frame whose brake truth is OFF or ON is scored by

* the model's brake P(ON) as a logit (``model``), and the same less its running minimum
  over the track so far (``model - track min``): the raw model, before any filter;
* per crop pixel statistics: the share of clipped pixels (any channel >= 245), of bright
  ones (>= 200), of red ones (R >= 150 and R - max(G, B) >= 40), the mean redness
  ``R - max(G, B)``, the mean of the 32 reddest pixels' redness, and each of these less its
  running minimum over the track (the lamp grown above the vehicle's own lowest level);

and the ROC AUC of each score for ON against OFF is printed. A statistic is not a model: it
says where the evidence lies (docs/model.md, "Night brakes: the model at chance where pixel
statistics are not"). Usage::

    python scripts/probe_night_brake.py --checkpoint signal_light_node/weights/default.pt \\
        --data "runs/indep/night_*/*.mcap" --data runs/ship/family_cal_split \\
        --json docs/results/night_brake_probe.json
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import torch

from signal_light_node.evaluation.metrics import roc_auc
from signal_light_node.evaluation.streaming import model_track_probs
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import TASKS, LightStatus, View
from signal_light_node.model.checkpoint import load_checkpoint
from signal_light_node.model.config import CropConfig
from signal_light_node.training.sources import load_bag_tracks, tracks_from

_BRAKE, _VIEW = TASKS.index("brake"), TASKS.index("view")
_ON, _OFF = int(LightStatus.ON), int(LightStatus.OFF)
STATS = ("clipped share", "bright share", "red share", "mean redness", "top redness")


def night_tracks(spec: str, crop: CropConfig) -> List[TrackSequence]:
    """The night tracks of a split directory or of a glob of bags (bags do not say their
    lighting: the second generator's night bags are taken as night)."""
    paths = [Path(p) for p in sorted(glob.glob(spec))]
    if not paths:
        raise SystemExit(f"error: {spec} names no split or bag")
    tracks = tracks_from(paths, crop, "probed split",
                         lambda bag: load_bag_tracks(bag, crop, lighting="night"))
    return [t for t in tracks if t.lighting == "night"]


def crop_stats(crop: np.ndarray) -> np.ndarray:
    """float64 ``[len(STATS)]`` of one uint8 BGR crop."""
    c = crop.astype(np.float32)
    redness = c[..., 2] - np.maximum(c[..., 0], c[..., 1])
    brightest = c.max(-1)
    return np.array([(brightest >= 245).mean(), (brightest >= 200).mean(),
                     ((c[..., 2] >= 150) & (redness >= 40)).mean(),
                     np.clip(redness, 0, None).mean(), np.sort(redness.ravel())[-32:].mean()])


def less_running_min(values: np.ndarray) -> np.ndarray:
    """Each row less the column-wise minimum of the rows up to it (NaN rows skipped)."""
    return values - np.fmin.accumulate(np.where(np.isnan(values), np.inf, values), axis=0)


def track_scores(track: TrackSequence, p_on: np.ndarray) -> Dict[str, np.ndarray]:
    """Every score of every frame of one track (NaN where the frame is not stepped)."""
    p = np.where(track.mask, p_on.astype(np.float64), np.nan)
    logit = np.log(np.clip(p, 1e-4, 1 - 1e-4) / np.clip(1 - p, 1e-4, 1))
    stats = np.full((len(track), len(STATS)), np.nan)
    for i in np.flatnonzero(track.mask):
        stats[i] = crop_stats(track.crop_window(i, i + 1)[0])
    grown = less_running_min(stats)
    scores = {"model": logit, "model - track min": less_running_min(logit[:, None])[:, 0]}
    for k, name in enumerate(STATS):
        scores[name] = stats[:, k]
        scores[f"{name} - track min"] = grown[:, k]
    return scores


def probe(model: torch.nn.Module, tracks: List[TrackSequence], batch: int = 32
          ) -> Dict[str, Dict[str, float]]:
    """AUC of every score on the rear-view frames with brake truth OFF or ON."""
    pooled: Dict[str, Tuple[List[float], List[float]]] = {}
    for start in range(0, len(tracks), batch):
        part = tracks[start:start + batch]
        raw = model_track_probs(model, part)
        for k, track in enumerate(part):
            truth, view = track.labels[:, _BRAKE], track.labels[:, _VIEW]
            rear = track.mask & (view == int(View.BEHIND))
            for name, score in track_scores(track, raw["brake"][k, :len(track), _ON]).items():
                on, off = pooled.setdefault(name, ([], []))
                on += list(score[rear & (truth == _ON)])
                off += list(score[rear & (truth == _OFF)])
    return {name: {"auc": roc_auc(np.array(on), np.array(off)), "on": len(on), "off": len(off)}
            for name, (on, off) in pooled.items()}


def main() -> None:
    """Print (and optionally write) the AUCs per data set."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--data", action="append", required=True,
                        help="a split directory or a quoted glob of bags; repeatable")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    loaded = load_checkpoint(args.checkpoint)
    result = {"checkpoint": str(args.checkpoint), "sets": {}}
    for spec in args.data:
        tracks = night_tracks(spec, loaded.config.crop_config())
        aucs = probe(loaded.model, tracks)
        result["sets"][spec] = {"night_tracks": len(tracks), "auc": aucs}
        print(f"{spec}: {len(tracks)} night tracks")
        for name, row in aucs.items():
            print(f"  {name:28s} AUC {row['auc']:.3f}  (ON {row['on']}, OFF {row['off']})")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
