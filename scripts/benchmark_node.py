#!/usr/bin/env python3
"""End-to-end latency of the live ``detector`` node: image published -> output received.

Starts ``detector`` in its own process on a private ROS domain, publishes synthetic
1280x720 camera frames (JPEG-compressed or raw bgr8) with a ``Detection2DArray`` of N
tracked boxes at a fixed rate from this process, and times each frame from just before
its image is published until its ``VehicleLightStateArray`` arrives back here. The first
seconds are warm-up and not counted. Prints mean / p50 / p95 / max latency, frames
without output (dropped), the output rate, and the node's own ``/diagnostics`` figures.

Usage::

    python scripts/benchmark_node.py                          # shipped weights, 32 tracks, 10 Hz
    python scripts/benchmark_node.py --untrained              # same network, random weights
    python scripts/benchmark_node.py --transport raw --tracks 64 --seconds 30
    python scripts/benchmark_node.py --busy-cores 1           # idle, then one core kept busy
    python scripts/benchmark_node.py -p backend:=onnxruntime  # any node parameter
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor

from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import boxes_to_detections, make_header, stamp_to_ns
from signal_light_node.ros.messages import rclpy_make
from signal_light_node.ros.ros_io import message_class, qos, ros_context
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, DIAGNOSTICS_TOPIC,
                                      DIAGNOSTICS_TYPE, IMAGE_TYPE, INPUT_COMPRESSED_TOPIC,
                                      INPUT_DETECTIONS_TOPIC, INPUT_IMAGE_TOPIC, OUTPUT_TOPIC,
                                      VEHICLE_LIGHTS_TYPE)

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv: List[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tracks", type=int, default=32, help="tracked boxes per frame")
    p.add_argument("--rate", type=float, default=10.0, help="camera frame rate, Hz")
    p.add_argument("--seconds", type=float, default=20.0, help="measured duration")
    p.add_argument("--warmup", type=float, default=3.0, help="seconds not counted at the start")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--transport", choices=("compressed", "raw"), default="compressed")
    p.add_argument("--model", help="checkpoint (default: the shipped weights)")
    p.add_argument("--untrained", action="store_true",
                   help="use the default network with random weights (same cost as trained)")
    p.add_argument("--num-threads", type=int, default=0, help="the node's num_threads")
    p.add_argument("--work-queue", type=int, default=2, help="the node's work_queue_size")
    p.add_argument("-p", "--param", dest="params", action="append", default=[],
                   metavar="NAME:=VALUE", help="one more node parameter (repeatable), e.g. "
                   "-p backend:=onnxruntime")
    p.add_argument("--busy-cores", type=int, default=0, metavar="N",
                   help="run a second time with N other processes keeping one core busy each, "
                        "and print idle and shared figures side by side")
    p.add_argument("--json", help="also write the figures to this JSON file")
    return p.parse_args(argv)


def model_path(args: argparse.Namespace, tmp: Path) -> str:
    from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS, save_checkpoint
    from signal_light_node.model.config import ModelConfig
    from signal_light_node.model.registry import build_model

    if args.model:
        return str(Path(args.model).resolve())
    if args.untrained:
        config = ModelConfig()
        return str(save_checkpoint(tmp / "untrained.pt", build_model(config), config))
    if not Path(DEFAULT_WEIGHTS).is_file():
        sys.exit(f"benchmark_node: the shipped weights {DEFAULT_WEIGHTS} do not exist; "
                 "pass --model PATH or --untrained")
    return ""


def make_frames(args: argparse.Namespace, n_distinct: int = 12) -> Tuple[List[dict], List[dict]]:
    """Pre-built image payloads (encoded once) and per-frame box layouts of ``--tracks`` boxes."""
    from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields
    from signal_light_node.synth import SceneRenderer

    renderer = SceneRenderer(7, width=args.width, height=args.height, fps=args.rate,
                             lighting="day", night_fraction=0.0)
    payloads = []
    for frame in renderer.frames(n_distinct):
        fields = (bgr_to_compressed_fields(frame.image) if args.transport == "compressed"
                  else bgr_to_image_fields(frame.image))
        payloads.append(fields)
    return payloads, _grid_boxes(args.tracks, args.width, args.height)


def _grid_boxes(n: int, width: int, height: int) -> List[dict]:
    """``n`` vehicle-sized boxes spread over the lower two thirds of the image."""
    cols = int(np.ceil(np.sqrt(n * 2)))
    rows = int(np.ceil(n / cols))
    cell_w, cell_h = width / cols, (height * 2 / 3) / rows
    boxes = []
    for i in range(n):
        r, c = divmod(i, cols)
        boxes.append({"id": f"track_{i}", "cx": (c + 0.5) * cell_w,
                      "cy": height / 3 + (r + 0.5) * cell_h,
                      "w": cell_w * 0.8, "h": cell_h * 0.8})
    return boxes


def main(argv: List[str]) -> int:
    args = parse_args(argv)
    # A private domain: the node and this client see nobody else (read at rclpy.init).
    os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 101))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

    with tempfile.TemporaryDirectory() as tmp:
        model = model_path(args, Path(tmp))
        print(f"rendering {args.width}x{args.height} frames ({args.transport}) ...", flush=True)
        payloads, layout = make_frames(args)
        figures = run_node(args, model, payloads, layout, Path(tmp) / "idle.log")
        if figures is None:
            return 1
        shared = None
        if args.busy_cores > 0:
            with busy_cores(args.busy_cores):
                shared = run_node(args, model, payloads, layout, Path(tmp) / "shared.log")
            if shared is None:
                return 1
    for f in (figures, shared):
        if f is not None:
            f.update(transport=args.transport, width=args.width, height=args.height,
                     tracks=args.tracks, rate_hz=args.rate,
                     model=("untrained default network" if args.untrained and not args.model
                            else model or "shipped weights"),
                     cpus=os.cpu_count())
    print_figures(figures)
    if shared is not None:
        print(f"with {args.busy_cores} core(s) kept busy by another process:")
        print_figures(shared)
        print_comparison(figures, shared)
    if args.json:
        out = figures if shared is None else {"idle": figures, "shared": shared,
                                              "busy_cores": args.busy_cores}
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


def run_node(args: argparse.Namespace, model: str, payloads: List[dict], layout: List[dict],
             log: Path) -> Optional[Dict[str, object]]:
    """Start ``detector``, play the frames at it, stop it; the figures, or None if it failed."""
    image_type = COMPRESSED_TYPE if args.transport == "compressed" else IMAGE_TYPE
    node_args = ["detector", "--ros-args", "-p", f"image_transport:={args.transport}",
                 "-p", "reliability:=reliable", "-p", f"num_threads:={args.num_threads}",
                 "-p", f"work_queue_size:={args.work_queue}"]
    if model:
        node_args += ["-p", f"model_path:={model}"]
    for param in args.params:
        if ":=" not in param:
            raise SystemExit(f"benchmark_node: -p needs NAME:=VALUE, got {param!r}")
        node_args += ["-p", param]
    proc = subprocess.Popen(node_args, cwd=REPO, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while "ready:" not in log.read_text():
            if proc.poll() is not None or time.monotonic() > deadline:
                print(log.read_text(), file=sys.stderr)
                return None
            time.sleep(0.1)
        figures = run_client(args, payloads, layout, image_type)
    finally:
        stop_node(proc)
    figures["load_avg_1m"] = os.getloadavg()[0]
    return figures


def stop_node(proc: subprocess.Popen) -> Optional[int]:
    """SIGINT the detector, wait, SIGKILL it if it does not end; its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    return proc.returncode


@contextlib.contextmanager
def busy_cores(n: int) -> Iterator[None]:
    """``n`` processes that each keep one core busy while the block runs.

    Each burner runs in its own session, as another program on the car computer would
    (Linux's autogroup scheduler shares the CPU between sessions, not threads).
    """
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                                start_new_session=True) for _ in range(n)]
    time.sleep(1.0)  # let the scheduler see them
    try:
        yield
    finally:
        for proc in burners:
            proc.kill()
            proc.wait()


def subscribe_outputs(node, on_output, diagnostics: Dict[str, str]) -> None:
    """Subscribe ``node`` to the detector's output (``on_output``) and to ``/diagnostics``.

    ``diagnostics`` is replaced in place by the key-value pairs of the detector's latest
    status (the soak reads its counters there too).
    """
    def on_diag(msg) -> None:
        for status in msg.status:
            if status.name.startswith("signal_light_detector"):
                diagnostics.clear()
                diagnostics.update({kv.key: kv.value for kv in status.values})

    node.create_subscription(message_class(VEHICLE_LIGHTS_TYPE), OUTPUT_TOPIC, on_output,
                             qos("reliable", 100))
    node.create_subscription(message_class(DIAGNOSTICS_TYPE), DIAGNOSTICS_TOPIC, on_diag,
                             qos("reliable", 10))


def run_client(args: argparse.Namespace, payloads: List[dict], layout: List[dict],
               image_type: str) -> Dict[str, object]:
    """Publish the frames at the rate and time each output; returns the figures."""
    received: Dict[int, float] = {}
    published: Dict[int, float] = {}
    diagnostics: Dict[str, str] = {}
    with ros_context() as context:
        node = rclpy.create_node(f"benchmark_node_client_{os.getpid()}", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        image_topic = (INPUT_COMPRESSED_TOPIC if args.transport == "compressed"
                       else INPUT_IMAGE_TOPIC)
        image_pub = node.create_publisher(message_class(image_type), image_topic,
                                          qos("reliable", 10))
        det_pub = node.create_publisher(message_class(DETECTIONS_TYPE), INPUT_DETECTIONS_TOPIC,
                                        qos("reliable", 10))

        def on_output(msg) -> None:
            received.setdefault(stamp_to_ns(msg.header.stamp), time.monotonic())

        subscribe_outputs(node, on_output, diagnostics)
        deadline = time.monotonic() + 60
        while not (image_pub.get_subscription_count() and det_pub.get_subscription_count()
                   and node.count_publishers(OUTPUT_TOPIC)):
            if time.monotonic() > deadline:
                raise SystemExit("benchmark_node: the detector was not discovered in 60 s")
            executor.spin_once(timeout_sec=0.1)

        # Built once: filling an rclpy uint8[] field from numpy costs ~100 ms for a raw
        # 1280x720 frame, which would be measured as latency otherwise.
        images = [rclpy_make(image_type, **fields) for fields in payloads]
        rng = np.random.default_rng(0)
        period = 1.0 / args.rate
        n_frames = int(round((args.warmup + args.seconds) * args.rate))
        n_warmup = int(round(args.warmup * args.rate))
        base_stamp = time.time_ns()
        start = time.monotonic() + 0.2
        print(f"publishing {n_frames} frames at {args.rate:g} Hz with {args.tracks} tracks "
              f"({n_warmup} warm-up) ...", flush=True)
        for i in range(n_frames):
            due = start + i * period
            while True:
                left = due - time.monotonic()
                if left <= 0:
                    break
                executor.spin_once(timeout_sec=min(left, 0.01))
            stamp = base_stamp + int(i * period * 1e9)
            header = make_header(stamp, "camera", rclpy_make)
            image = images[i % len(images)]
            image.header = header
            jitter = rng.normal(0.0, 1.5, size=(len(layout), 2))
            boxes = [TrackBox.from_center(b["id"], b["cx"] + j[0], b["cy"] + j[1], b["w"], b["h"],
                                          "car") for b, j in zip(layout, jitter)]
            detections = boxes_to_detections(header, boxes, rclpy_make)
            published[stamp] = time.monotonic()
            image_pub.publish(image)
            det_pub.publish(detections)
        # Let the last frames come back (and one more diagnostics period pass).
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        executor.shutdown()
        node.destroy_node()

    stamps = sorted(published)[n_warmup:]
    lat = np.array([received[s] - published[s] for s in stamps if s in received]) * 1e3
    dropped = sum(1 for s in stamps if s not in received)
    span = (max(received[s] for s in stamps if s in received)
            - min(received[s] for s in stamps if s in received)) if len(lat) > 1 else 0.0
    return {
        "frames": len(stamps), "outputs": int(len(lat)), "dropped": dropped,
        "output_rate_hz": (len(lat) - 1) / span if span > 0 else float("nan"),
        "latency_mean_ms": float(lat.mean()) if len(lat) else float("nan"),
        "latency_p50_ms": float(np.percentile(lat, 50)) if len(lat) else float("nan"),
        "latency_p95_ms": float(np.percentile(lat, 95)) if len(lat) else float("nan"),
        "latency_max_ms": float(lat.max()) if len(lat) else float("nan"),
        "node_diagnostics": {k: diagnostics.get(k) for k in (
            "latency_mean_ms", "latency_p95_ms", "processing_mean_ms", "processing_p95_ms",
            "engine_mean_ms", "engine_p95_ms",
            "dropped_work_queue", "dropped_image_timeout", "dropped_detections_timeout",
            "active_tracks", "backend", "precision", "model_threads")},
        "node_stages_ms": {k[len("stage_"):-len("_mean_ms")]: (diagnostics[k],
                           diagnostics.get(k[:-len("_mean_ms")] + "_p95_ms"))
                           for k in diagnostics if k.startswith("stage_") and k.endswith("_mean_ms")},
    }


def print_comparison(idle: Dict[str, object], shared: Dict[str, object]) -> None:
    """Idle against shared: the share of frames answered and the p95 ratio, with the targets."""
    answered = [f["outputs"] / max(f["frames"], 1) for f in (idle, shared)]
    ratio = shared["latency_p95_ms"] / idle["latency_p95_ms"]
    print(f"{'':>22} {'idle':>9} {'shared':>9}")
    print(f"{'answered':>22} {answered[0]:>9.1%} {answered[1]:>9.1%}")
    for key in ("latency_mean_ms", "latency_p50_ms", "latency_p95_ms", "output_rate_hz"):
        print(f"{key:>22} {idle[key]:>9.1f} {shared[key]:>9.1f}")
    ok = answered[1] >= 0.9 and ratio <= 2.0
    print(f"shared: {answered[1]:.1%} answered, p95 {ratio:.2f}x idle -> "
          f"{'meets' if ok else 'MISSES'} the >= 90 % answered / <= 2x p95 target")


def print_figures(f: Dict[str, object]) -> None:
    print(f"live detector, {f['width']}x{f['height']} {f['transport']}, {f['tracks']} tracks at "
          f"{f['rate_hz']:g} Hz, model {f['model']}, {f['cpus']} CPUs (load {f['load_avg_1m']:.2f})")
    print(f"  frames measured {f['frames']}, outputs {f['outputs']}, dropped {f['dropped']}, "
          f"output rate {f['output_rate_hz']:.2f} Hz")
    print(f"  end-to-end latency (published -> output received): mean "
          f"{f['latency_mean_ms']:.1f} ms, p50 {f['latency_p50_ms']:.1f} ms, p95 "
          f"{f['latency_p95_ms']:.1f} ms, max {f['latency_max_ms']:.1f} ms")
    d = f["node_diagnostics"]
    print(f"  node's own figures (last 1000 frames incl. warm-up): receipt -> publish mean "
          f"{d['latency_mean_ms']} ms, p95 {d['latency_p95_ms']} ms; processing mean "
          f"{d['processing_mean_ms']} ms, p95 {d['processing_p95_ms']} ms (engine alone mean "
          f"{d['engine_mean_ms']} ms, p95 {d['engine_p95_ms']} ms); work-queue drops "
          f"{d['dropped_work_queue']}; backend {d.get('backend')} {d.get('precision')}, "
          f"last step on {d.get('model_threads')} thread(s)")
    stages = f.get("node_stages_ms") or {}
    if stages:
        print("  node's stages, mean / p95 ms: " + ", ".join(
            f"{name} {mean}/{p95}" for name, (mean, p95) in stages.items()))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
