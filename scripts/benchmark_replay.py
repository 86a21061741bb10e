#!/usr/bin/env python3
"""Measure ``signal-light replay`` throughput and the engine's per-frame latency.

For each number of tracks per frame (1, 8, 32, 64 by default) a bag of 1280x720 JPEG
frames with that many tracked boxes is written to a temporary directory and replayed
through the engine exactly as ``signal-light replay`` does (decode, crop, one batched
model step, output message, MCAP write). Printed per row:

* replay throughput in frames/s and track-steps/s (wall time of the whole replay);
* the engine's ``process`` latency per frame, mean and p95 (crop + step + results),
  leaving out the first ``--warmup`` frames.

The model is the shipped one when its weights exist, else a freshly initialised model
of the default ``ModelConfig`` (timing does not depend on the weight values).

Usage::

    python scripts/benchmark_replay.py                 # 2 threads, 1/8/32/64 tracks
    python scripts/benchmark_replay.py --tracks 32 --frames 200 --json out.json
"""

from __future__ import annotations

import os

# OpenMP threads that spin while they wait (libgomp's default) stall every parallel op
# when another process holds one of the two cores: a 1-track step went from 3 ms to
# 170-270 ms at load 3. Sleeping waiters avoid that; set before torch loads libgomp.
# Compare with OMP_WAIT_POLICY=ACTIVE in the environment.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Dict, List, Sequence  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from signal_light_node.io import bagio  # noqa: E402
from signal_light_node.boxes import TrackBox  # noqa: E402
from signal_light_node.io.conversions import boxes_to_detections, make_header  # noqa: E402
from signal_light_node.runtime.engine import EngineConfig, LightStateEngine  # noqa: E402
from signal_light_node.io.image_codec import bgr_to_compressed_fields  # noqa: E402
from signal_light_node.model import (DEFAULT_WEIGHTS, ModelConfig, build_model,  # noqa: E402
                                     load_checkpoint)
from signal_light_node.tools.replay import replay_bag  # noqa: E402
from signal_light_node.io.topics import (CAMERA_COMPRESSED_TOPIC, COMPRESSED_TYPE,  # noqa: E402
                                      DETECTIONS_TYPE, TRACKED_OBJECTS_TOPIC)

T0 = 1_700_000_000 * 1_000_000_000


def make_frames(n_frames: int, width: int, height: int, seed: int = 0) -> List[Dict[str, Any]]:
    """JPEG-compressed frames: a road-like gradient, noise and drifting dark blobs."""
    rng = np.random.default_rng(seed)
    base = np.linspace(60, 160, height, dtype=np.float32)[:, None, None]
    frames = []
    for t in range(n_frames):
        image = np.clip(base + rng.normal(0, 12, (height, width, 3)), 0, 255).astype(np.uint8)
        for k in range(12):
            x = int((k * 97 + t * 7) % (width - 120))
            y = int(height * 0.4 + (k * 37) % (height // 3))
            image[y:y + 60, x:x + 100] = (40 + 10 * k) % 255
        frames.append(bgr_to_compressed_fields(image, "jpeg", quality=85))
    return frames


def track_boxes(n_tracks: int, t: int, width: int, height: int) -> List[TrackBox]:
    """``n_tracks`` boxes of 32..160 px spread over the image, drifting slowly."""
    boxes = []
    cols = max(1, int(math.ceil(math.sqrt(n_tracks * width / height))))
    cell_w, cell_h = width / cols, height / max(1, int(math.ceil(n_tracks / cols)))
    for i in range(n_tracks):
        size = 32 + (i * 41) % 129
        cx = (i % cols + 0.5) * cell_w + 3 * math.sin(0.2 * t + i)
        cy = (i // cols + 0.5) * cell_h
        boxes.append(TrackBox.from_center(str(100 + i), cx, cy, size * 1.3, size, "car"))
    return boxes


def write_bench_bag(path: Path, frames: Sequence[Dict[str, Any]], n_tracks: int, width: int,
                    height: int, fps: float = 10.0) -> Path:
    period = int(1e9 / fps)
    with bagio.BagWriter(path) as bag:
        bag.add_topic(CAMERA_COMPRESSED_TOPIC, COMPRESSED_TYPE)
        bag.add_topic(TRACKED_OBJECTS_TOPIC, DETECTIONS_TYPE)
        for t, fields in enumerate(frames):
            stamp = T0 + t * period
            header = make_header(stamp, "camera", bagio.make)
            bag.write(CAMERA_COMPRESSED_TOPIC, stamp,
                      bagio.make(COMPRESSED_TYPE, header=header, **fields))
            bag.write(TRACKED_OBJECTS_TOPIC, stamp, boxes_to_detections(
                header, track_boxes(n_tracks, t, width, height), bagio.make))
    return path


def load_model(weights: Path | None) -> tuple:
    path = weights if weights is not None else (DEFAULT_WEIGHTS if DEFAULT_WEIGHTS.exists()
                                                else None)
    if path is not None:
        return load_checkpoint(path).model, str(path)
    torch.manual_seed(0)
    return build_model(ModelConfig()).eval(), "default ModelConfig, fresh weights"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, default=None,
                        help="checkpoint (default: the shipped weights if present)")
    parser.add_argument("--tracks", type=int, nargs="+", default=[1, 8, 32, 64])
    parser.add_argument("--frames", type=int, default=60, help="frames per bag")
    parser.add_argument("--warmup", type=int, default=5, help="frames left out of latency")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    if args.frames <= args.warmup:
        parser.error("--frames must be larger than --warmup")

    torch.set_num_threads(args.threads)
    model, source = load_model(args.weights)
    config = model.config
    gpu = f" ({torch.cuda.get_device_name(args.device)})" if args.device.startswith("cuda") \
        and torch.cuda.is_available() else ""
    print(f"model: {source}; input {config.input_size}px, ConvLSTM {config.lstm_hidden}; "
          f"device {args.device}{gpu}")
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, OMP_WAIT_POLICY "
          f"{os.environ.get('OMP_WAIT_POLICY')}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; frames "
          f"{args.width}x{args.height} JPEG, {args.frames} per run")
    frames = make_frames(args.frames, args.width, args.height)
    print(f"{'tracks':>6} {'frames/s':>9} {'steps/s':>9} {'lat mean':>9} {'lat p95':>9} "
          f"{'lat max':>9}  (latency in ms)")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.tracks:
            bag = write_bench_bag(Path(tmp) / f"bench{n}", frames, n, args.width, args.height)
            engine = LightStateEngine(model, EngineConfig(device=args.device))
            start = time.perf_counter()
            summary = replay_bag(bag, Path(tmp) / f"out{n}", engine, progress=False)
            wall = time.perf_counter() - start
            lat = np.asarray(summary.latencies_s[args.warmup:]) * 1e3
            row = {"tracks": n, "frames": summary.images, "wall_s": wall,
                   "frames_per_s": summary.frames_per_s,
                   "track_steps_per_s": summary.track_steps_per_s,
                   "latency_mean_ms": float(lat.mean()),
                   "latency_p95_ms": float(np.percentile(lat, 95)),
                   "latency_max_ms": float(lat.max())}
            rows.append(row)
            print(f"{n:>6} {row['frames_per_s']:>9.1f} {row['track_steps_per_s']:>9.1f} "
                  f"{row['latency_mean_ms']:>9.1f} {row['latency_p95_ms']:>9.1f} "
                  f"{row['latency_max_ms']:>9.1f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    for row in rows:
        if row["tracks"] == 32:
            ok = row["frames_per_s"] >= 10.0 and row["latency_p95_ms"] < 100.0
            print(f"32 tracks: {row['frames_per_s']:.1f} frames/s, engine p95 "
                  f"{row['latency_p95_ms']:.1f} ms -> {'meets' if ok else 'MISSES'} the 10 Hz / "
                  f"100 ms target (engine only; end-to-end node latency is measured separately)")
    if args.json:
        args.json.write_text(json.dumps({"model": source, "threads": args.threads,
                                         "device": args.device + gpu,
                                         "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                                         "width": args.width, "height": args.height,
                                         "runs": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
