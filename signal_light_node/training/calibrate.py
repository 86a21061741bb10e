"""Per-head temperatures fitted on a held-out style family, and the calibration error.

``python -m signal_light_node.training.calibrate --checkpoint best.pt --split CAL --out OUT.pt``

The split must be rendered for calibration alone (a style family the model was not
trained on, with seeds no test split uses): fitting on a test set would flatter it.
Each head's logits are divided by one temperature ``T`` that minimises the negative
log-likelihood of its labels over the split's frames after the warm-up (a 1-D search
over ``log T``), kept only where it also lowers the calibration error there (else 1); a
temperature changes no argmax, only how sure the outputs are, so
the node's ON/OFF/UNKNOWN decisions move only where a threshold acts on a probability
(the intent filter's). The expected calibration error (ECE, 15 bins of top-class
confidence) before and after is printed and stored in the checkpoint's meta.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import expected_calibration_error
from signal_light_node.model.checkpoint import load_checkpoint, save_checkpoint
from signal_light_node.labels import TASKS
from signal_light_node.training.feature_cache import (FeatureCache, collect_scored, split_tracks,
                                                      track_logits, trunk_fingerprint, write_cache)

LOG = logging.getLogger(__name__)


@torch.no_grad()
def crop_track_logits(model: torch.nn.Module, split: Path, batch: int = 16
                      ) -> Dict[str, Tuple[np.ndarray, np.ndarray]]:
    """:func:`~signal_light_node.training.feature_cache.track_logits` for any model: every
    track of ``split`` run from its crops, from its first frame."""
    model.eval()
    out: Dict[str, List[Tuple[np.ndarray, np.ndarray]]] = {t: [] for t in TASKS}
    tracks = list(split_tracks(split))
    for start in range(0, len(tracks), batch):
        chunk = tracks[start:start + batch]
        length = max(len(t["crops"]) for t in chunk)
        crops = np.zeros((len(chunk), length) + chunk[0]["crops"].shape[1:], np.uint8)
        labels = np.full((len(chunk), length, len(TASKS)), -1, np.int64)
        mask = np.zeros((len(chunk), length), bool)
        for i, t in enumerate(chunk):
            n = len(t["crops"])
            crops[i, :n], labels[i, :n], mask[i, :n] = t["crops"], t["labels"], True
        x = torch.from_numpy(crops).permute(0, 1, 4, 2, 3).float().div_(255.0)
        logits, _ = model.forward_sequence(x)
        collect_scored(out, {k: v for k, v in logits.items() if k in TASKS},
                       {"labels": torch.from_numpy(labels), "mask": torch.from_numpy(mask),
                        "fps": torch.tensor([t["fps"] for t in chunk], dtype=torch.float64)})
    return {t: (np.concatenate([a for a, _ in v]), np.concatenate([y for _, y in v]))
            for t, v in out.items()}


def _nll(logits: np.ndarray, labels: np.ndarray, temperature: float) -> float:
    z = torch.from_numpy(logits).double() / temperature
    return float(torch.nn.functional.cross_entropy(z, torch.from_numpy(labels).long()))


def fit_temperature(logits: np.ndarray, labels: np.ndarray) -> float:
    """The temperature in [0.25, 8] minimising the NLL (grid, then a finer grid)."""
    grid = np.exp(np.linspace(np.log(0.25), np.log(8.0), 41))
    best = min(grid, key=lambda t: _nll(logits, labels, t))
    fine = best * np.exp(np.linspace(-0.1, 0.1, 21))
    return float(min(fine, key=lambda t: _nll(logits, labels, t)))


def _softmax(logits: np.ndarray, temperature: float) -> np.ndarray:
    return torch.softmax(torch.from_numpy(logits).double() / temperature, 1).numpy()


def calibrate(checkpoint: Path, split: Path, out: Path, cache_root: Path) -> Dict[str, Dict[str, float]]:
    """Fit the temperatures of ``checkpoint`` on ``split``; write the calibrated ``out``."""
    loaded = load_checkpoint(checkpoint)
    if loaded.config.on_offsets:  # they act after the temperatures: fitted first, on raw logits
        raise ConfigError(f"{checkpoint} has ON offsets {dict(loaded.config.on_offsets)}: fit "
                          f"the temperatures of the file before them")
    model = loaded.model.eval()
    if hasattr(model, "frame_features"):  # a frozen trunk: its features cached once
        fingerprint = trunk_fingerprint(model)
        cache = FeatureCache.load(write_cache(split, model, cache_root / fingerprint / split.name),
                                  fingerprint)
        per_task = track_logits(model, cache)
    else:
        per_task = crop_track_logits(model, split)
    report: Dict[str, Dict[str, float]] = {}
    temps: Dict[str, float] = {}
    for task, (logits, labels) in per_task.items():
        old = float(loaded.config.temperatures.get(task, 1.0))
        raw = logits * old  # the logits before any earlier temperature
        t = fit_temperature(raw, labels)
        before = expected_calibration_error(_softmax(raw, 1.0), labels)
        after = expected_calibration_error(_softmax(raw, t), labels)
        if after > before:  # the likelihood's optimum can cost calibration error: keep 1
            t, after = 1.0, before
        temps[task] = round(t, 4)
        report[task] = {"temperature": temps[task], "frames": int(len(labels)),
                        "ece_before": before, "ece_after": after}
        LOG.info("%s: T=%.3f ECE %.4f -> %.4f (%d frames)", task, t, report[task]["ece_before"],
                 report[task]["ece_after"], len(labels))
    config = loaded.config.replace(temperatures=temps)
    model.config = config  # the heads read their temperatures from it
    meta = dict(loaded.meta, calibration={"split": str(split), "heads": report})
    save_checkpoint(out, model, config, meta)
    return report


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--split", type=Path, required=True,
                        help="a split of a held-out style family rendered for calibration")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=None,
                        help="feature cache root (default: next to the split)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = calibrate(args.checkpoint, args.split, args.out, args.cache or args.split.parent / "cache")
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
