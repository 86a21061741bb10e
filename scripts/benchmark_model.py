#!/usr/bin/env python3
"""Measure the CPU cost of one batched model ``step`` (the engine's per-frame work).

Prints, for each batch size (tracks per frame), the mean and p95 time of ``step`` in
eval mode under ``torch.inference_mode`` with a fixed number of threads, plus the
FLOPs per track-step, the parameter count and the checkpoint size. The machine may be
shared, so the timing is repeated in several rounds and the round with the lowest
mean is reported next to the load average.

Usage::

    python scripts/benchmark_model.py                      # the shipped config, fresh weights
    python scripts/benchmark_model.py --weights signal_light_node/weights/default.pt
    python scripts/benchmark_model.py --set input_size=48 --set lstm_hidden=32,32
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Sequence

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from signal_light_node.runtime.engine import require_device
from signal_light_node.model import (
    DEFAULT_WEIGHTS,
    ModelConfig,
    build_model,
    load_checkpoint,
    save_checkpoint,
    to_input,
)

logger = logging.getLogger("benchmark_model")


def parse_override(text: str) -> tuple:
    """``key=value`` with comma-separated lists, e.g. ``lstm_hidden=32,32``."""
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--set needs key=value, got {text!r}")
    if "," in value:
        return key, [float(v) if "." in v else int(v) for v in value.split(",") if v]
    for cast in (int, float):
        try:
            return key, cast(value)
        except ValueError:
            pass
    if value.lower() in ("true", "false"):
        return key, value.lower() == "true"
    return key, value


def time_steps(model: torch.nn.Module, n: int, reps: int, warmup: int, rounds: int,
               seed: int = 0, device: str = "cpu") -> Dict[str, Any]:
    """Time ``model.step`` on ``n`` tracks; returns the best round's statistics in ms.

    On CUDA each step is followed by a synchronisation, as the engine's copy of the
    probabilities to the host would force.
    """
    size = model.config.input_size
    rng = np.random.default_rng(seed)
    crops = to_input(rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8)).to(device)
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    results: List[Dict[str, float]] = []
    with torch.inference_mode():
        state = model.initial_state(n)
        for _ in range(warmup):
            _, state = model.step(crops, state)
        for _ in range(rounds):
            times = []
            for _ in range(reps):
                start = time.perf_counter()
                _, state = model.step(crops, state)  # carry the state as the engine does
                sync()
                times.append((time.perf_counter() - start) * 1e3)
            times.sort()
            results.append({"mean_ms": statistics.fmean(times),
                            "p95_ms": times[min(len(times) - 1, int(round(0.95 * (len(times) - 1))))],
                            "min_ms": times[0]})
    best = min(results, key=lambda r: r["mean_ms"])
    return {"tracks": n, **best, "round_means_ms": [r["mean_ms"] for r in results]}


def count_flops(model: torch.nn.Module, n: int = 32) -> float:
    """FLOPs (multiply-add = 2) of one step per track, counted by torch's FlopCounterMode.

    Counts convolutions and matrix products; element-wise work (normalisation, gates,
    activations) is a few percent on top.
    """
    size = model.config.input_size
    crops = torch.rand(n, 3, size, size)
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        model.step(crops, model.initial_state(n))
    return counter.get_total_flops() / n


def checkpoint_size(model: torch.nn.Module) -> int:
    """Bytes of the model saved in the checkpoint format."""
    with tempfile.TemporaryDirectory() as tmp:
        path = save_checkpoint(Path(tmp) / "bench.pt", model, model.config, {"notes": "benchmark"})
        return path.stat().st_size


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, help="checkpoint to time (default: fresh model "
                        "of the shipped weights' config, or of ModelConfig() without them; "
                        "timing does not depend on the weights)")
    parser.add_argument("--set", dest="overrides", action="append", type=parse_override,
                        default=[], metavar="KEY=VALUE", help="override a ModelConfig field")
    parser.add_argument("--tracks", type=int, nargs="+", default=[1, 8, 32, 64])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--reps", type=int, default=30, help="timed steps per round (>= 30)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--budget-ms", type=float, default=50.0,
                        help="time budget of a 32-track step (exit 1 if exceeded)")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")

    torch.set_num_threads(args.threads)
    device = str(require_device(args.device))
    if args.weights is not None:
        loaded = load_checkpoint(args.weights)
        model, config = loaded.model, loaded.config
        if args.overrides:
            parser.error("--set cannot be combined with --weights")
    else:
        base = load_checkpoint(DEFAULT_WEIGHTS).config if DEFAULT_WEIGHTS.exists() \
            else ModelConfig()
        config = base.replace(**dict(args.overrides))
        torch.manual_seed(0)
        model = build_model(config)
    model.eval()
    gpu = f", GPU {torch.cuda.get_device_name(device)}" if device.startswith("cuda") else ""

    params = sum(p.numel() for p in model.parameters())
    flops = count_flops(model)
    size_bytes = checkpoint_size(model)
    load = os.getloadavg()
    print(f"config: input {config.input_size}x{config.input_size}, attention "
          f"{'on' if config.use_attention else 'off'} {config.attention_channels}, backbone "
          f"{config.backbone_channels}, ConvLSTM {config.lstm_hidden} at "
          f"{config.feature_size}x{config.feature_size}, norm {config.norm}, temporal input "
          f"{'on' if config.temporal_input else 'off'}")
    print(f"torch {torch.__version__}, device {device}{gpu}, threads {torch.get_num_threads()}, "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs")
    print(f"parameters: {params:,}  FLOPs per track-step: {flops / 1e6:.1f} M  "
          f"checkpoint: {size_bytes / 1e6:.2f} MB")
    print(f"{'tracks':>6} {'mean ms':>9} {'p95 ms':>9} {'min ms':>9} {'ms/track':>9}  round means")
    rows = []
    for n in args.tracks:
        row = time_steps(model.to(device), n, max(args.reps, 1), args.warmup,
                         max(args.rounds, 1), device=device)
        rows.append(row)
        rounds = " ".join(f"{m:.1f}" for m in row["round_means_ms"])
        print(f"{n:>6} {row['mean_ms']:>9.2f} {row['p95_ms']:>9.2f} {row['min_ms']:>9.2f} "
              f"{row['mean_ms'] / n:>9.3f}  {rounds}")
    load_after = os.getloadavg()[0]
    print(f"load average after: {load_after:.2f}")

    verdict = 0
    for row in rows:
        if row["tracks"] == 32:
            ok = row["mean_ms"] <= args.budget_ms
            print(f"32 tracks: {row['mean_ms']:.1f} ms mean, {row['p95_ms']:.1f} ms p95 -> "
                  f"{'within' if ok else 'OVER'} the {args.budget_ms:g} ms budget")
            verdict = 0 if ok else 1
    if args.json:
        args.json.write_text(json.dumps({
            "config": config.to_dict(), "threads": args.threads, "device": device + gpu,
            "parameters": params,
            "flops_per_track_step": flops, "checkpoint_bytes": size_bytes,
            "load_average": list(load), "steps": rows}, indent=2))
    return verdict


if __name__ == "__main__":
    sys.exit(main())
