#!/usr/bin/env python3
"""Does periodic energy per crop cell tell a blinking vehicle across renderers? A probe.

For every track of the given data (rendered splits or labelled bags), each frame's crop is
cut into cells and run through the model's cell-period evidence
(``model.lamp_evidence.cell_blink_step``: each cell's peak brightness and peak warm excess
drive blink-period resonators, read raw and over the cell's broadband change; per image
half the largest over its cells). Logistic regressions are fitted on FIT and scored
(ROC AUC) on every SCORE set:

* ``any``: a blinker ON (intent LEFT, RIGHT or HAZARD) against both OFF;
* ``side``: from behind only, the image-left half's blinker (the vehicle's left) ON.

Each feature family (``periodic``: all 56 values; ``pooled``: the 4 of ``cell_pooled``,
each raw amplitude's largest over the periods) is probed alone, and the full one beside
the per-frame lamp maps (8x8, the model's brightness evidence), so the table says what the periodic evidence adds and whether it
carries to a style family or a generator never fitted on. Without any fitting, each set
also gets the ROC AUC of one number, the largest raw amplitude over cells, channels,
halves and periods, for ``any`` (``max amplitude``; ``max amplitude, grace`` leaves out
the frames within ``--grace`` seconds after an intent change, where a detector with a
memory still rings after the last flash). Usage::

    python scripts/probe_blink.py --fit runs/v13/test_split \\
        --score family=runs/v13/family_test_split indep=runs/indep/day_101,... --json OUT
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np
import torch

from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import TASKS, Intent, LightStatus, View
from signal_light_node.model.lamp_evidence import (PERIODS, cell_blink_sizes, cell_blink_step,
                                                    lamp_maps)

WARMUP = 10


def load(path: Path) -> List[TrackSequence]:
    """Tracks of a split directory or a labelled bag."""
    from signal_light_node.training import sources
    from signal_light_node.training.sources import is_split_dir

    if is_split_dir(path):
        return sources.split_tracks(path)
    return sources.load_bag_tracks(path)


def periodic_features(crops: np.ndarray, grid: int) -> np.ndarray:
    """``[T, F]`` per frame: the model's cell-period vector
    (``model.lamp_evidence.cell_blink_step`` on a ``grid x grid`` lamp map)."""
    x = torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 255.0
    maps = lamp_maps(x, grid)
    n_signals = cell_blink_sizes(grid)[0]
    resonators = torch.zeros(1, 2, n_signals, len(PERIODS))
    memory = torch.zeros(1, 3, n_signals)
    out = []
    for t in range(len(x)):
        seen = torch.full((1, 1), float(t > 0))
        vector, _, resonators, memory = cell_blink_step(maps[t:t + 1], resonators, memory, seen)
        out.append(vector[0])
    return torch.stack(out).numpy()


def brightness_features(crops: np.ndarray) -> np.ndarray:
    x = torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 255.0
    return lamp_maps(x, 8).flatten(1).numpy()


def targets(track: TrackSequence, grace: float = 0.0) -> Dict[str, np.ndarray]:
    """Per frame: 1 / 0 / -1 (not scored) for each probe target; ``any_grace`` also
    leaves out ``grace`` seconds after each intent change."""
    lab = track.labels
    intent = lab[:, TASKS.index("intent")]
    view = lab[:, TASKS.index("view")]
    left = lab[:, TASKS.index("left")]
    any_on = np.where(np.isin(intent, [Intent.LEFT, Intent.RIGHT, Intent.HAZARD]), 1,
                      np.where(intent == Intent.OFF, 0, -1))
    side = np.where(view != View.BEHIND, -1,
                    np.where(left == LightStatus.ON, 1, np.where(left == LightStatus.OFF, 0, -1)))
    keep = track.mask & (np.arange(len(track)) >= WARMUP)
    after_change = np.zeros(len(track), bool)
    for change in np.nonzero(np.diff(intent) != 0)[0] + 1:
        after_change[change:change + int(round(grace * track.fps))] = True
    return {"any": np.where(keep, any_on, -1), "side": np.where(keep, side, -1),
            "any_grace": np.where(keep & ~after_change, any_on, -1)}


def featurise(tracks: Sequence[TrackSequence], grid: int, grace: float
              ) -> Tuple[Dict[str, np.ndarray], Dict[str, np.ndarray]]:
    """Features (periodic, brightness, both) and targets of every frame of ``tracks``."""
    feats: Dict[str, List[np.ndarray]] = {"periodic": [], "pooled": [], "brightness": []}
    tg: Dict[str, List[np.ndarray]] = {"any": [], "side": [], "any_grace": []}
    for track in tracks:
        crops = track.crops
        periodic = periodic_features(crops, grid)
        feats["periodic"].append(periodic)
        raw = periodic.reshape(len(periodic), 2, -1, 2, len(PERIODS))[:, 0]
        feats["pooled"].append(raw.max(-1).reshape(len(periodic), -1))
        feats["brightness"].append(brightness_features(crops))
        for k, v in targets(track, grace).items():
            tg[k].append(v)
    f = {k: np.concatenate(v) for k, v in feats.items()}
    f["both"] = np.concatenate((f["periodic"], f["brightness"]), 1)
    return f, {k: np.concatenate(v) for k, v in tg.items()}


def auc(score: np.ndarray, y: np.ndarray) -> float:
    pos, neg = score[y == 1], score[y == 0]
    if not len(pos) or not len(neg):
        return float("nan")
    ranks = np.concatenate([pos, neg]).argsort().argsort() + 1
    return float((ranks[:len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def fit(x: np.ndarray, y: np.ndarray):
    keep = y >= 0
    mu, sd = x[keep].mean(0), x[keep].std(0) + 1e-4
    xt = torch.from_numpy((x[keep] - mu) / sd).float()
    yt = torch.from_numpy(y[keep]).long()
    lin = torch.nn.Linear(x.shape[1], 2)
    opt = torch.optim.LBFGS(lin.parameters(), max_iter=200)

    def closure():
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(lin(xt), yt) + 1e-3 * lin.weight.pow(2).sum()
        loss.backward()
        return loss

    opt.step(closure)

    def predict(z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.softmax(lin(torch.from_numpy((z - mu) / sd).float()), 1)[:, 1].numpy()
    return predict


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fit", type=Path, nargs="+", required=True)
    p.add_argument("--score", nargs="+", default=[], help="NAME=PATH[,PATH...]")
    p.add_argument("--grid", type=int, default=8, help="fine lamp-map grid (even)")
    p.add_argument("--grace", type=float, default=1.0,
                   help="seconds after an intent change left out of 'max amplitude, grace'")
    p.add_argument("--max-tracks", type=int, default=0, help="first N tracks of each set (0: all)")
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    torch.set_num_threads(1)
    cap = (lambda ts: ts[:args.max_tracks]) if args.max_tracks else (lambda ts: ts)
    fit_tracks = cap([t for path in args.fit for t in load(path)])
    n = len(fit_tracks)
    half = [t for i, t in enumerate(fit_tracks) if i % 2 == 0]
    other = [t for i, t in enumerate(fit_tracks) if i % 2 == 1]
    sets = {"fit, held-out tracks": other}
    for spec in args.score:
        name, paths = spec.split("=", 1)
        sets[name] = cap([t for path in paths.split(",") for t in load(Path(path))])
    fx, fy = featurise(half, args.grid, args.grace)
    print(f"fitted on {len(half)} of {n} tracks; positives any {int((fy['any'] == 1).sum())}"
          f" / {int((fy['any'] >= 0).sum())}", flush=True)
    models = {(kind, target): fit(fx[kind], fy[target])
              for kind in fx for target in ("any", "side")}
    amplitude = slice(0, fx["periodic"].shape[1] // 2)  # raw amplitudes come first
    results: Dict[str, Dict[str, float]] = {}
    for name, tracks in sets.items():
        sx, sy = featurise(tracks, args.grid, args.grace)
        row = {f"{kind}/{target}": round(auc(models[kind, target](sx[kind]), sy[target]), 3)
               for kind, target in models}
        row.update({f"{kind}/any, grace": round(auc(models[kind, "any"](sx[kind]),
                                                     sy["any_grace"]), 3) for kind in sx})
        biggest = sx["periodic"][:, amplitude].max(1)
        row["max amplitude"] = round(auc(biggest, sy["any"]), 3)
        row["max amplitude, grace"] = round(auc(biggest, sy["any_grace"]), 3)
        row["frames any"] = int((sy["any"] >= 0).sum())
        judged = max(1, int((sy["any"] >= 0).sum()))
        row["share ON any"] = round(float((sy["any"] == 1).sum()) / judged, 3)
        results[name] = row
        print(name, row, flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
