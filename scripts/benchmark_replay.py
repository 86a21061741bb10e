#!/usr/bin/env python3
"""Measure ``signal-light replay`` throughput and the engine's per-frame latency.

For each number of tracks per frame (1, 8, 32, 64 by default) a bag of 1280x720 JPEG
frames with that many tracked boxes is written to a temporary directory and replayed
through the engine exactly as ``signal-light replay`` does (decode, crop, one batched
model step, output message, MCAP write), once per backend (``--backend``, torch and
onnxruntime by default, alternating). Printed per backend and row:

* replay throughput in frames/s and track-steps/s (wall time of the whole replay);
* the engine's ``process`` latency per frame, mean and p95 (crop + step + results),
  leaving out the first ``--warmup`` frames;

then, at ``--stage-tracks`` (32) tracks, where a frame's time goes: decode, the engine's
stages (crops, state gather, step, intent filter, state store, results), building the
output messages and writing them, mean / p95 / share per backend side by side, and the
ratio of the whole frame to the model step (inside the engine, and timed alone). The
instruction set each framework uses is printed first.

The model is the shipped one (``weights/default.pt``; ``default.onnx`` for
onnxruntime) unless ``--weights`` (exported on the fly for onnxruntime) or ``--onnx``.

Usage::

    python scripts/benchmark_replay.py                 # 2 threads, 1/8/32/64 tracks, both backends
    python scripts/benchmark_replay.py --tracks 32 --frames 100 --rounds 3 --json out.json
    python scripts/benchmark_replay.py --backend onnxruntime --threads 1 --tracks 32
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

from signal_light_node.boxes import TrackBox  # noqa: E402
from signal_light_node.errors import SignalLightError  # noqa: E402
from signal_light_node.io import bagio  # noqa: E402
from signal_light_node.io.conversions import boxes_to_detections, make_header  # noqa: E402
from signal_light_node.io.image_codec import bgr_to_compressed_fields  # noqa: E402
from signal_light_node.runtime.engine import EngineConfig, LightStateEngine  # noqa: E402
from signal_light_node.tools import benchmarking as bench  # noqa: E402
from signal_light_node.tools.replay import REPLAY_STAGES, replay_bag  # noqa: E402
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", nargs="+", default=["torch", "onnxruntime"],
                        help="backends to time side by side (default: torch onnxruntime)")
    parser.add_argument("--weights", type=Path, default=None,
                        help="checkpoint (default: the shipped weights)")
    parser.add_argument("--onnx", type=Path, default=None,
                        help="ONNX export for onnxruntime (default: the shipped one, or "
                             "--weights exported on the fly)")
    parser.add_argument("--tracks", type=int, nargs="+", default=[1, 8, 32, 64])
    parser.add_argument("--frames", type=int, default=60, help="frames per bag")
    parser.add_argument("--warmup", type=int, default=5, help="frames left out of latency")
    parser.add_argument("--rounds", type=int, default=1,
                        help="replays per backend and track count, the backends alternating "
                             "(figures pool every round's frames; the round means show the "
                             "noise)")
    parser.add_argument("--threads", type=int, default=2, help="intra-op threads, 0 = the "
                        "backend's default")
    parser.add_argument("--stage-tracks", type=int, default=32,
                        help="track count of the per-stage table")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--device", default="cpu", help="device (cpu, cuda, cuda:1)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    if args.frames <= args.warmup:
        parser.error("--frames must be larger than --warmup")
    try:
        names = bench.require_known(args.backend)
    except SignalLightError as exc:
        parser.error(str(exc))

    print(f"frames {args.width}x{args.height} JPEG, {args.frames} per run ({args.warmup} "
          f"warm-up), threads {args.threads or 'default'}, OMP_WAIT_POLICY "
          f"{os.environ.get('OMP_WAIT_POLICY')}, load average {os.getloadavg()[0]:.2f}")
    for line in bench.isa_lines(names):
        print(line)
    frames = make_frames(args.frames, args.width, args.height)
    rows: List[Dict[str, Any]] = []
    stages: Dict[str, Dict[str, List[float]]] = {name: {} for name in names}
    step_only: Dict[str, List[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        backends = {name: bench.bench_backend(name, args.weights, args.onnx, args.threads,
                                              args.device, Path(tmp)) for name in names}
        for name, backend in backends.items():
            print(f"{name}: {bench.describe(backend)}")
        bags = {n: write_bench_bag(Path(tmp) / f"bench{n}", frames, n, args.width, args.height)
                for n in args.tracks}
        print(f"{'backend':>12} {'tracks':>6} {'frames/s':>9} {'steps/s':>9} {'lat mean':>9} "
              f"{'lat p95':>9} {'lat max':>9}  (engine latency in ms){'  round means' if args.rounds > 1 else ''}")
        runs = 0
        for n in args.tracks:
            pooled: Dict[str, Dict[str, Any]] = {name: {"lat": [], "wall": 0.0, "images": 0,
                                                        "judged": 0, "means": []}
                                                 for name in names}
            for _ in range(max(args.rounds, 1)):
                for name in names:
                    engine = LightStateEngine(backends[name], EngineConfig(device=args.device))
                    start = time.perf_counter()
                    summary = replay_bag(bags[n], Path(tmp) / f"out{runs}", engine,
                                         progress=False)
                    runs += 1
                    acc = pooled[name]
                    acc["wall"] += time.perf_counter() - start
                    acc["images"] += summary.images
                    acc["judged"] += summary.counters.get("judged", 0)
                    lat = summary.latencies_s[args.warmup:]
                    acc["lat"] += lat
                    acc["means"].append(float(np.mean(lat)) * 1e3)
                    if n == args.stage_tracks:
                        for stage, values in summary.stages_s.items():
                            stages[name].setdefault(stage, []).extend(values[args.warmup:])
                        # The model-only step right after, so both see the same load.
                        step_only.setdefault(name, []).extend(
                            bench.time_backend_steps(backends[name], n, 20, 3))
            for name in names:
                acc = pooled[name]
                lat = np.asarray(acc["lat"]) * 1e3
                row = {"backend": name, "tracks": n, "frames": acc["images"],
                       "wall_s": acc["wall"], "frames_per_s": acc["images"] / acc["wall"],
                       "track_steps_per_s": acc["judged"] / acc["wall"],
                       "latency_mean_ms": float(lat.mean()),
                       "latency_p95_ms": float(np.percentile(lat, 95)),
                       "latency_max_ms": float(lat.max()), "round_means_ms": acc["means"]}
                rows.append(row)
                means = " ".join(f"{m:.1f}" for m in acc["means"]) if args.rounds > 1 else ""
                print(f"{name:>12} {n:>6} {row['frames_per_s']:>9.1f} "
                      f"{row['track_steps_per_s']:>9.1f} {row['latency_mean_ms']:>9.1f} "
                      f"{row['latency_p95_ms']:>9.1f} {row['latency_max_ms']:>9.1f}  {means}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    ratios: Dict[str, Dict[str, float]] = {}
    if args.stage_tracks in args.tracks:
        print(f"\nper stage at {args.stage_tracks} tracks, ms per frame (decode + engine + "
              f"outputs + write = frame; 'share' of the mean frame):")
        print(bench.stage_table(stages, REPLAY_STAGES))
        for name in names:
            per = stages[name]
            frame = float(np.mean(np.sum([per[s] for s in REPLAY_STAGES], axis=0)))
            step = float(np.mean(per["step"]))
            alone = float(np.mean(step_only[name]))
            ratios[name] = {"frame_ms": frame * 1e3, "step_in_engine_ms": step * 1e3,
                            "step_alone_ms": alone * 1e3}
            print(f"{name}: frame {frame * 1e3:.1f} ms = {frame / step:.2f} x the step inside "
                  f"the engine ({step * 1e3:.1f} ms) = {frame / alone:.2f} x the model-only "
                  f"step ({alone * 1e3:.1f} ms, {args.stage_tracks} tracks, timed alone after each "
                  f"replay)")
    for row in rows:
        if row["tracks"] == 32:
            ok = row["frames_per_s"] >= 10.0 and row["latency_p95_ms"] < 100.0
            print(f"{row['backend']}, 32 tracks: {row['frames_per_s']:.1f} frames/s, engine p95 "
                  f"{row['latency_p95_ms']:.1f} ms -> {'meets' if ok else 'MISSES'} the 10 Hz / "
                  f"100 ms target (engine only; end-to-end node latency is measured separately)")
    if args.json:
        args.json.write_text(json.dumps({
            "backends": names, "threads": args.threads, "device": args.device,
            "isa": bench.isa_lines(names),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "width": args.width, "height": args.height, "runs": rows,
            "stages_ms": {name: {s: {"mean": float(np.mean(v)) * 1e3,
                                     "p95": bench.percentile(v, 95) * 1e3}
                                 for s, v in per.items()} for name, per in stages.items()},
            "ratios": ratios}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
