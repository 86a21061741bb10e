#!/usr/bin/env python3
"""Measure the CPU cost of one batched model ``step`` (the engine's per-frame work).

Prints, for each batch size (tracks per frame) and each backend (``--backend``, torch
and onnxruntime side by side by default), the mean and p95 time of the backend's
``step`` (uint8 crops in, as the engine calls it) with a fixed number of threads, plus
the FLOPs per track-step, the parameter count, the checkpoint size and the instruction
set each framework uses. The machine may be shared, so the timing is repeated in
several rounds, the backends alternating, and the round with the lowest mean is
reported next to the load average. For onnxruntime the model timed is exported on the
fly (``--onnx`` to time a given export instead).

Usage::

    python scripts/benchmark_model.py                      # the shipped config, fresh weights
    python scripts/benchmark_model.py --weights signal_light_node/weights/default.pt
    python scripts/benchmark_model.py --backend onnxruntime --threads 1 --tracks 32
    python scripts/benchmark_model.py --set input_size=48 --set lstm_hidden=32,32
"""

from __future__ import annotations

import os

# As the node: idle OpenMP threads sleep (set before torch loads libgomp; see
# signal_light_node/__init__.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Dict, List, Sequence  # noqa: E402

import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

from signal_light_node.errors import SignalLightError  # noqa: E402
from signal_light_node.model import (  # noqa: E402
    DEFAULT_WEIGHTS,
    ModelConfig,
    build_model,
    load_checkpoint,
    save_checkpoint,
)
from signal_light_node.model.backends.torch_backend import TorchBackend, require_device  # noqa: E402
from signal_light_node.runtime.backend import check_device  # noqa: E402
from signal_light_node.tools import benchmarking as bench  # noqa: E402

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


def time_steps(backends: Dict[str, Any], n: int, reps: int, warmup: int, rounds: int,
               seed: int = 0, sync: Any = None) -> Dict[str, Dict[str, Any]]:
    """Time ``backend.step`` on ``n`` tracks per backend; each one's best round, in ms.

    The backends alternate round by round, so a load change on a shared machine hits
    them alike. The state is carried from step to step, as the engine does; the crops
    are the uint8 arrays the engine passes (their conversion is part of the step).
    """
    sync = sync or (lambda: None)
    results: Dict[str, List[Dict[str, float]]] = {name: [] for name in backends}
    for name, backend in backends.items():
        bench.time_backend_steps(backend, n, 0, warmup, seed)
    for _ in range(rounds):
        for name, backend in backends.items():
            times = sorted(t * 1e3 for t in bench.time_backend_steps(backend, n, reps, 1, seed))
            results[name].append({
                "mean_ms": statistics.fmean(times),
                "p95_ms": times[min(len(times) - 1, int(round(0.95 * (len(times) - 1))))],
                "min_ms": times[0], "median_ms": statistics.median(times)})
            sync()
    out = {}
    for name, rows in results.items():
        best = min(rows, key=lambda r: r["mean_ms"])
        out[name] = {"tracks": n, **best, "round_means_ms": [r["mean_ms"] for r in rows]}
    return out


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
    parser.add_argument("--backend", nargs="+", default=["torch", "onnxruntime"],
                        help="backends timed side by side (default: torch onnxruntime)")
    parser.add_argument("--weights", type=Path, help="checkpoint to time (default: fresh model "
                        "of the shipped weights' config, or of ModelConfig() without them; "
                        "timing does not depend on the weights)")
    parser.add_argument("--onnx", type=Path, help="ONNX export for onnxruntime (default: the "
                        "model timed, exported on the fly)")
    parser.add_argument("--set", dest="overrides", action="append", type=parse_override,
                        default=[], metavar="KEY=VALUE", help="override a ModelConfig field")
    parser.add_argument("--tracks", type=int, nargs="+", default=[1, 8, 32, 64])
    parser.add_argument("--threads", type=int, default=2, help="intra-op threads of every "
                        "backend (0: its default)")
    parser.add_argument("--reps", type=int, default=30, help="timed steps per round (>= 30)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--budget-ms", type=float, default=50.0,
                        help="time budget of a 32-track step of the first backend (exit 1 if "
                             "exceeded)")
    parser.add_argument("--device", default="cpu", help="device (cpu, cuda, cuda:1)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    try:
        names = bench.require_known(args.backend)
        device = str(require_device(check_device(args.device)))
    except SignalLightError as exc:
        parser.error(str(exc))

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.weights is not None:
        if args.overrides:
            parser.error("--set cannot be combined with --weights")
        loaded = load_checkpoint(args.weights)
        model, config = loaded.model, loaded.config
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
    print(f"device {device}{gpu}, threads {args.threads or 'default'}, load average "
          f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs")
    for line in bench.isa_lines(names):
        print(line)
    print(f"parameters: {params:,}  FLOPs per track-step: {flops / 1e6:.1f} M  "
          f"checkpoint: {size_bytes / 1e6:.2f} MB")
    sync = torch.cuda.synchronize if device.startswith("cuda") else None
    with tempfile.TemporaryDirectory() as tmp:
        weights = args.weights
        if weights is None and "onnxruntime" in names and args.onnx is None:
            weights = save_checkpoint(Path(tmp) / "bench.pt", model, config,
                                      {"notes": "benchmark"})
        backends = {}
        for name in names:
            if name == "torch":
                backends[name] = TorchBackend(model, device=device, threads=args.threads or None)
            else:
                backends[name] = bench.bench_backend(name, weights, args.onnx, args.threads,
                                                     device, Path(tmp))
        cols = "".join(f"{name + ' mean':>18} {'p95':>7} {'min':>7} {'ms/track':>8}"
                       for name in names)
        print(f"{'tracks':>6}{cols}  round means (ms)")
        rows: Dict[str, List[Dict[str, Any]]] = {name: [] for name in names}
        for n in args.tracks:
            timed = time_steps(backends, n, max(args.reps, 1), args.warmup,
                               max(args.rounds, 1), sync=sync)
            line = f"{n:>6}"
            rounds = []
            for name in names:
                row = timed[name]
                rows[name].append(row)
                line += (f"{row['mean_ms']:>18.2f} {row['p95_ms']:>7.2f} {row['min_ms']:>7.2f} "
                         f"{row['mean_ms'] / n:>8.3f}")
                rounds.append(f"{name}: " + " ".join(f"{m:.1f}" for m in row["round_means_ms"]))
            print(line + "  " + "; ".join(rounds))
    print(f"load average after: {os.getloadavg()[0]:.2f}")

    verdict = 0
    for k, name in enumerate(names):
        for row in rows[name]:
            if row["tracks"] == 32:
                ok = row["mean_ms"] <= args.budget_ms
                print(f"{name}, 32 tracks: {row['mean_ms']:.1f} ms mean, {row['p95_ms']:.1f} ms "
                      f"p95 -> {'within' if ok else 'OVER'} the {args.budget_ms:g} ms budget")
                if k == 0 and not ok:
                    verdict = 1
    if args.json:
        args.json.write_text(json.dumps({
            "config": config.to_dict(), "threads": args.threads, "device": device + gpu,
            "isa": bench.isa_lines(names), "parameters": params,
            "flops_per_track_step": flops, "checkpoint_bytes": size_bytes,
            "load_average": list(load), "steps": rows}, indent=2))
    return verdict


if __name__ == "__main__":
    sys.exit(main())
