#!/usr/bin/env python3
"""Which per-frame representation tells a lit lamp? Linear probes on a rendered split.

For every frame of SPLIT, each representation (the pretrained trunk cut at stride 16 and
8, the lamp maps at 4x4 and 8x8, the same trunk with random weights, and the backbone of
a CNN checkpoint fed no history) is computed once; a logistic regression per lamp
(brake, left, right: lit or not in this very frame, the split's ``lit_labels``, frames
where the lamp is hidden left out) is fitted on the even tracks and scored (ROC AUC) on
the odd ones. With ``--transfer SPLIT2`` each probe is also fitted on all of SPLIT and
scored on SPLIT2 (e.g. the held-out style family): does what tells a lit lamp carry over?
Usage::

    python scripts/probe_per_frame.py --split runs/default/val_split \\
        --transfer runs/default/family_cal_split --cnn CNN_CHECKPOINT \\
        --json docs/results/trunk_probe_per_frame.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict

import numpy as np
import torch

from signal_light_node.evaluation.metrics import roc_auc
from signal_light_node.labels import TASKS
from signal_light_node.model.checkpoint import load_checkpoint
from signal_light_node.model.config import trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.training.feature_cache import split_tracks


@torch.no_grad()
def representations(x: torch.Tensor, cnn: Path) -> Dict[str, torch.Tensor]:
    """Per-frame feature vectors of crops ``x`` [N, 3, 64, 64] in [0, 1]."""
    reps = {}
    for stride in (16, 8):
        model = build_model(trunk_config(trunk_stride=stride), pretrained=True).eval()
        features, maps = model.frame_features(x)
        reps[f"trunk stride {stride}"] = features.flatten(1)
        reps[f"lamp maps {model.grid}x{model.grid}"] = maps.flatten(1)
    torch.manual_seed(0)
    random = build_model(trunk_config(trunk_init="random"), pretrained=True).eval()
    reps["random trunk stride 16"] = random.frame_features(x)[0].flatten(1)
    net = load_checkpoint(cnn).model.eval()
    history = torch.zeros((len(x), 6) + tuple(x.shape[2:])) if net.config.temporal_input else None
    reps[f"CNN backbone of {cnn.name} (no history)"] = net.encode(x, history).flatten(1)
    return reps


def probe(x: torch.Tensor, lit: np.ndarray, train: np.ndarray) -> Dict[str, float]:
    """AUC per lamp on the frames not in ``train`` of a logistic regression fitted on
    the frames in it."""
    x = (x - x[train].mean(0)) / (x[train].std(0) + 1e-4)
    out = {}
    for task in ("brake", "left", "right"):
        y = torch.from_numpy(lit[:, TASKS.index(task)]).long()
        keep = y <= 1
        linear = torch.nn.Linear(x.shape[1], 2)
        optim = torch.optim.LBFGS(linear.parameters(), max_iter=100)
        fit = torch.from_numpy(train) & keep

        def closure() -> torch.Tensor:
            optim.zero_grad()
            loss = torch.nn.functional.cross_entropy(linear(x[fit]), y[fit]) \
                + 1e-3 * linear.weight.pow(2).sum()
            loss.backward()
            return loss

        optim.step(closure)
        test = torch.from_numpy(~train) & keep
        p = torch.softmax(linear(x[test]), 1)[:, 1].detach().numpy()
        truth = y[test].numpy()
        out[task] = round(roc_auc(p[truth == 1], p[truth == 0]), 3)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", type=Path, required=True)
    parser.add_argument("--cnn", type=Path, required=True, help="a CNN-encoder checkpoint")
    parser.add_argument("--transfer", type=Path, default=None,
                        help="a second split to score probes fitted on all of --split")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    tracks = list(split_tracks(args.split))
    n_fit = sum(len(t["crops"]) for t in tracks)
    if args.transfer is not None:
        tracks += list(split_tracks(args.transfer))
    crops = np.concatenate([t["crops"] for t in tracks])
    lit = np.concatenate([t["lit_labels"] for t in tracks])
    track_of = np.concatenate([np.full(len(t["crops"]), i) for i, t in enumerate(tracks)])
    x = torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 255.0
    own = np.arange(len(x)) < n_fit
    results: Dict[str, Dict[str, Dict[str, float]]] = {}
    for name, features in representations(x, args.cnn).items():
        results[name] = {"held-out tracks": probe(features[own], lit[own],
                                                  track_of[own] % 2 == 0)}
        if args.transfer is not None:
            results[name]["transfer split"] = probe(features, lit, own)
        print(f"{name} ({features.shape[1]} values): {results[name]}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
