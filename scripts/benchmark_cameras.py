#!/usr/bin/env python3
"""One shared model step for several cameras against one step per camera.

A tick of ``--cameras`` cameras with ``--tracks`` tracked boxes each is judged two ways,
interleaved tick by tick so both see the same machine load:

* shared: ONE ``engine.process_many`` over every camera's frame (one backend step of
  cameras x tracks crops), as the node with ``cameras`` does;
* separate: ``engine.process`` once per camera (one backend step of ``tracks`` crops
  each), as separate single-camera nodes (or a node per camera) would.

Printed: the wall time per tick of both (median, mean, p95 over ``--ticks`` after
``--warmup``), the same for the backend step alone (the crops cut once, then
``backend.step`` of all crops against one step per camera) and the ratios. Frames are
1280x720 with boxes of 32..160 px. The model is the shipped one when its weights exist,
else a freshly initialised default model (timing does not depend on weight values).

Usage::

    python scripts/benchmark_cameras.py                      # 3 cameras x 16 tracks, torch
    python scripts/benchmark_cameras.py --cameras 4 --tracks 8 --backend onnxruntime
"""

from __future__ import annotations

import os

# Idle OpenMP threads sleep instead of spinning (see benchmark_replay.py); before torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Dict, List, Sequence  # noqa: E402

import numpy as np  # noqa: E402

from signal_light_node.boxes import TrackBox  # noqa: E402
from signal_light_node.runtime.crops import crop_vehicles  # noqa: E402
from signal_light_node.runtime.engine import LightStateEngine, engine_from_checkpoint  # noqa: E402

T0 = 1_700_000_000 * 1_000_000_000
WIDTH, HEIGHT = 1280, 720


def frame(camera: int, t: int, rng: np.random.Generator) -> np.ndarray:
    """A road-like gradient with noise and dark blobs, different per camera."""
    base = np.linspace(60 + 10 * camera, 160, HEIGHT, dtype=np.float32)[:, None, None]
    image = np.clip(base + rng.normal(0, 12, (HEIGHT, WIDTH, 3)), 0, 255).astype(np.uint8)
    for k in range(12):
        x = int((k * 97 + t * 7 + camera * 31) % (WIDTH - 120))
        y = int(HEIGHT * 0.4 + (k * 37) % (HEIGHT // 3))
        image[y:y + 60, x:x + 100] = (40 + 10 * k) % 255
    return image


def boxes(n: int, t: int, camera: int) -> List[TrackBox]:
    """``n`` boxes of 32..160 px over the image, drifting; IDs 0..n-1 on every camera."""
    cols = max(1, int(math.ceil(math.sqrt(n * WIDTH / HEIGHT))))
    cell_w, cell_h = WIDTH / cols, HEIGHT / max(1, int(math.ceil(n / cols)))
    out = []
    for i in range(n):
        size = 32 + (i * 41 + camera * 13) % 129
        x = (i % cols) * cell_w + (t * 3) % max(1, int(cell_w - size))
        y = (i // cols) * cell_h
        out.append(TrackBox(str(i), x, y, x + size, y + size * 0.8))
    return out


def engine(args: argparse.Namespace) -> LightStateEngine:
    """An engine of the shipped model (or a fresh default one) on ``args.backend``."""
    try:
        return engine_from_checkpoint(None, backend=args.backend, device=args.device,
                                      threads=args.threads)
    except Exception as exc:  # noqa: BLE001 - no shipped weights: time a fresh model
        if args.backend != "torch":
            raise
        print(f"(shipped weights not usable: {exc}; timing a fresh default model)",
              file=sys.stderr)
        from signal_light_node.model import ModelConfig, build_model

        config = ModelConfig()
        return LightStateEngine(build_model(config).eval())


def figures(times_s: Sequence[float]) -> Dict[str, float]:
    """Median, mean and p95 in ms."""
    ms = np.asarray(times_s) * 1e3
    return {"median_ms": float(np.median(ms)), "mean_ms": float(ms.mean()),
            "p95_ms": float(np.percentile(ms, 95))}


def run(args: argparse.Namespace) -> Dict[str, Dict[str, float]]:
    """Time both ways; returns per way its figures."""
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    shared = engine(args)
    separate = [engine(args) for _ in range(args.cameras)]
    rng = np.random.default_rng(0)
    images = [[frame(c, t, rng) for c in range(args.cameras)] for t in range(4)]
    times: Dict[str, List[float]] = {"shared": [], "separate": [], "step_shared": [],
                                     "step_separate": []}
    backend = shared.backend
    for t in range(args.warmup + args.ticks):
        stamp = T0 + t * 100_000_000
        frames = [(f"cam{c}", images[t % 4][c], stamp, boxes(args.tracks, t, c))
                  for c in range(args.cameras)]
        order = ("shared", "separate") if t % 2 else ("separate", "shared")
        took = {}
        for way in order:
            start = time.perf_counter()
            if way == "shared":
                shared.process_many(frames)
            else:
                for eng, (_, image, stamp_ns, bxs) in zip(separate, frames):
                    eng.process(image, stamp_ns, bxs)
            took[way] = time.perf_counter() - start
        crops = [crop_vehicles(image, bxs, shared.crop)[0] for _, image, _, bxs in frames]
        everything = np.concatenate(crops)
        for way in order:
            start = time.perf_counter()
            if way == "shared":
                backend.step(everything, backend.initial_state(len(everything)))
            else:
                for part in crops:
                    backend.step(part, backend.initial_state(len(part)))
            took[f"step_{way}"] = time.perf_counter() - start
        if t >= args.warmup:
            for key, value in took.items():
                times[key].append(value)
    return {key: figures(values) for key, values in times.items()}


def main(argv: Sequence[str] = ()) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--tracks", type=int, default=16, help="tracks per camera")
    parser.add_argument("--ticks", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--backend", default="torch", choices=("torch", "onnxruntime"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=2, help="intra-op threads (0: default)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(list(argv) or None)
    result = run(args)
    n = args.cameras * args.tracks
    print(f"{args.cameras} cameras x {args.tracks} tracks, {args.backend} on {args.device}, "
          f"{args.threads or 'default'} threads, {args.ticks} ticks after {args.warmup}:")
    for key, label in (("shared", f"engine, one step of {n}"),
                       ("separate", f"engine, {args.cameras} steps of {args.tracks}"),
                       ("step_shared", f"backend.step of {n}"),
                       ("step_separate", f"{args.cameras} x backend.step of {args.tracks}")):
        f = result[key]
        print(f"  {label:34s} median {f['median_ms']:7.1f} ms  mean {f['mean_ms']:7.1f} ms  "
              f"p95 {f['p95_ms']:7.1f} ms")
    for what, a, b in (("engine", "shared", "separate"), ("step", "step_shared",
                                                          "step_separate")):
        print(f"  {what}: shared / separate = "
              f"{result[a]['median_ms'] / result[b]['median_ms']:.2f} (medians)")
    if args.json is not None:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "figures": result}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
