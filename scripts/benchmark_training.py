#!/usr/bin/env python3
"""Measure the CPU cost of one training step of the trunk recipe's temporal part.

A step of ``training.trunk_recipe`` is one batch of ``--batch`` windows of ``--seq-len``
frames of cached trunk features: the forward pass (``sequence_features``), the loss, the
backward pass and the AdamW update. This times exactly that on random features of the
cache's shapes (no data needed), so that the cost of a recipe member (``STEPS`` of them)
can be read before it is trained and a change to the network's training path measured.

Prints the mean and the fastest of ``--steps`` timed steps (after ``--warmup`` untimed
ones) split into forward, backward and update, the thread count and the CPU
(``tools.benchmarking.isa_lines``).

Usage::

    python scripts/benchmark_training.py                       # the recipe's long member
    python scripts/benchmark_training.py --threads 2 --steps 10
    python scripts/benchmark_training.py --model '{"lstm_hidden": [32]}'
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from typing import Dict, List, Optional

import torch

from signal_light_node.errors import SignalLightError
from signal_light_node.labels import TASKS
from signal_light_node.model.config import trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.tools import benchmarking as bench
from signal_light_node.training.trunk_recipe import step_loss

logger = logging.getLogger("benchmark_training")

#: The model of the recipe's members (scripts/train_trunk.sh RECIPE_MODEL plus the lit
#: area, the track floor and the brake judge).
RECIPE_MEMBER = {"frequency_evidence": False, "lamp_detail": 2, "lit_hidden": 128,
                 "blink_levels": False, "lamp_area": True, "track_floor": True,
                 "brake_expert": True}


def random_batch(model: torch.nn.Module, batch: int, seq_len: int, seed: int
                 ) -> Dict[str, torch.Tensor]:
    """A batch shaped like ``feature_cache.collate_windows``'s for ``model``, random."""
    gen = torch.Generator().manual_seed(seed)
    g = model.grid
    shape = (batch, seq_len)
    labels = torch.stack([torch.randint(0, model.config.num_classes[t], shape, generator=gen)
                          for t in TASKS], -1)
    return {"features": torch.rand(shape + (model.trunk_channels, g, g), generator=gen),
            "maps": torch.rand(shape + (model.lamp_channels, g, g), generator=gen),
            "labels": labels, "lit_labels": labels.clone(),
            "mask": torch.ones(shape, dtype=torch.bool),
            "fps": torch.full((batch,), 15.0, dtype=torch.float64)}


def time_steps(model: torch.nn.Module, batch: Dict[str, torch.Tensor], steps: int,
               warmup: int) -> List[Dict[str, float]]:
    """Seconds of forward (with the loss), backward and update per step."""
    params = [p for p in model.parameters() if p.requires_grad]
    optim = torch.optim.AdamW(params, lr=1e-3)
    weights = {t: torch.ones(model.config.num_classes[t]) for t in TASKS}
    model.train()
    out = []
    for i in range(warmup + steps):
        t0 = time.perf_counter()
        loss, _ = step_loss(model, batch, weights)
        t1 = time.perf_counter()
        optim.zero_grad(set_to_none=True)
        loss.backward()
        t2 = time.perf_counter()
        torch.nn.utils.clip_grad_norm_(params, 5.0)
        optim.step()
        t3 = time.perf_counter()
        if i >= warmup:
            out.append({"forward": t1 - t0, "backward": t2 - t1, "update": t3 - t2,
                        "total": t3 - t0})
    return out


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=json.dumps(RECIPE_MEMBER),
                        help="JSON changes on trunk_config() (default: the recipe's member)")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--seq-len", type=int, default=96)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.steps < 1 or args.batch < 1 or args.seq_len < 1 or args.threads < 1:
        parser.error("--steps, --batch, --seq-len and --threads must be >= 1")
    try:
        changes = json.loads(args.model)
        torch.manual_seed(args.seed)
        model = build_model(trunk_config(**changes))
    except (ValueError, SignalLightError) as exc:
        print(f"benchmark_training: bad --model: {exc}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    model.freeze_encoder()
    batch = random_batch(model, args.batch, args.seq_len, args.seed)
    runs = time_steps(model, batch, args.steps, args.warmup)
    print("\n".join(bench.isa_lines(["torch"])) + f"; {args.threads} thread(s)")
    print(f"batch {args.batch} x {args.seq_len} frames, {args.steps} timed steps")
    for part in ("forward", "backward", "update", "total"):
        values = [r[part] for r in runs]
        print(f"  {part:8s} mean {statistics.mean(values):7.3f} s   min {min(values):7.3f} s")
    total = statistics.mean(r["total"] for r in runs)
    print(f"3,000 steps (one recipe member): {3000 * total / 60:.0f} minutes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
