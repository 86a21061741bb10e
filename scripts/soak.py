#!/usr/bin/env python3
"""Soak test of the live ``detector`` node: many frames with track churn, memory and books.

Starts ``detector`` in its own process on a private ROS domain and publishes camera frames
with a ``Detection2DArray`` each at a fixed rate. The tracked vehicles churn: every frame
each track ends with probability 1 / (``--track-life`` x rate) and a new ID takes its
place, so over a long run the node sees thousands of distinct tracks come and go. Every
``--report-s`` seconds it prints the node's resident memory (RSS) and its counters; at
the end it checks that every frame published is accounted for (an output, or a drop the
node counted) and prints one summary line starting with ``soak:``.

Not a CI test (the default 36,000 frames at 10 Hz take an hour). Usage::

    python scripts/soak.py                               # 36,000 frames, 10 Hz, shipped weights
    python scripts/soak.py --frames 300 --rate 20 --untrained --report-s 5   # a quick check
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor

from benchmark_node import model_path, stop_node, subscribe_outputs
from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import boxes_to_detections, make_header
from signal_light_node.ros.messages import rclpy_make
from signal_light_node.ros.ros_io import message_class, qos, ros_context
from signal_light_node.runtime.stats import DROP_COUNTERS
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, IMAGE_TYPE,
                                      INPUT_COMPRESSED_TOPIC, INPUT_DETECTIONS_TOPIC,
                                      INPUT_IMAGE_TOPIC, OUTPUT_TOPIC)

REPO = Path(__file__).resolve().parents[1]
#: Counters of unusable images that still produce an output (published unjudged).
_NOT_DROPS = ("bad_images", "oversized_images")


def parse_args(argv: List[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=36_000, help="frames to publish")
    p.add_argument("--rate", type=float, default=10.0, help="frame rate, Hz")
    p.add_argument("--tracks", type=int, default=16, help="tracked vehicles in each frame")
    p.add_argument("--track-life", type=float, default=5.0,
                   help="mean lifetime of a track, seconds (the churn)")
    p.add_argument("--report-s", type=float, default=60.0, help="seconds between reports")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--transport", choices=("compressed", "raw"), default="compressed")
    p.add_argument("--reliability", choices=("best_effort", "reliable"), default="best_effort")
    p.add_argument("--model", help="checkpoint (default: the shipped weights)")
    p.add_argument("--untrained", action="store_true",
                   help="use the default network with random weights (same cost as trained)")
    p.add_argument("--json", help="also write the reports and the summary to this JSON file")
    return p.parse_args(argv)


class Churn:
    """``n`` tracks that each end with probability ``p_end`` per frame; new IDs replace them."""

    def __init__(self, n: int, p_end: float, width: int, height: int, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.p_end, self.width, self.height = p_end, width, height
        self.created = 0
        self.tracks = [self._new() for _ in range(n)]

    def _new(self) -> dict:
        self.created += 1
        w = float(self.rng.uniform(0.06, 0.25) * self.width)
        return {"id": f"v{self.created}", "cx": float(self.rng.uniform(0, self.width)),
                "cy": float(self.rng.uniform(self.height / 3, self.height)), "w": w,
                "h": w * 0.75, "vx": float(self.rng.normal(0, 2))}

    def step(self) -> List[TrackBox]:
        """The boxes of the next frame."""
        for i, track in enumerate(self.tracks):
            if self.rng.random() < self.p_end:
                self.tracks[i] = track = self._new()
            track["cx"] = (track["cx"] + track["vx"]) % self.width
        return [TrackBox.from_center(t["id"], t["cx"], t["cy"], t["w"], t["h"], "car")
                for t in self.tracks]


def rss_mb(pid: int) -> float:
    """Resident memory of a process, MB (nan once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def images(args: argparse.Namespace, n: int = 8) -> List[object]:
    """``n`` distinct camera messages, encoded once (the header is set per frame)."""
    from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields

    rng = np.random.default_rng(1)
    out = []
    for _ in range(n):
        base = np.linspace(40, 200, args.width, dtype=np.float32)[None, :, None]
        image = np.clip(base + rng.normal(0, 20, (args.height, args.width, 3)), 0, 255)
        image = image.astype(np.uint8)
        fields = (bgr_to_compressed_fields(image) if args.transport == "compressed"
                  else bgr_to_image_fields(image))
        out.append(rclpy_make(COMPRESSED_TYPE if args.transport == "compressed" else IMAGE_TYPE,
                              **fields))
    return out


def start_node(args: argparse.Namespace, model: str, log: Path) -> subprocess.Popen:
    cmd = ["detector", "--ros-args", "-p", f"image_transport:={args.transport}",
           "-p", f"reliability:={args.reliability}"]
    if model:
        cmd += ["-p", f"model_path:={model}"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 120
    while "ready:" not in log.read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"soak: the detector did not start:\n{log.read_text()}")
        time.sleep(0.1)
    return proc


def main(argv: List[str]) -> int:
    args = parse_args(argv)
    os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 101))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    with tempfile.TemporaryDirectory() as tmp:
        model = model_path(args, Path(tmp))
        proc = start_node(args, model, Path(tmp) / "detector.log")
        try:
            result = run_client(args, proc.pid)
        finally:
            code = stop_node(proc)
            result["node_exit_code"] = code
            result["node_log_tracebacks"] = (Path(tmp) / "detector.log").read_text().count(
                "Traceback")
    print(summary_line(args, result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0 if result["unaccounted"] == 0 and code == 0 else 1


def run_client(args: argparse.Namespace, pid: int) -> Dict[str, object]:
    """Publish the frames, report every ``--report-s`` and settle; returns the figures."""
    outputs = [0]
    diagnostics: Dict[str, str] = {}
    reports: List[Dict[str, object]] = []
    with ros_context() as context:
        node = rclpy.create_node(f"soak_client_{os.getpid()}", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        compressed = args.transport == "compressed"
        image_pub = node.create_publisher(
            message_class(COMPRESSED_TYPE if compressed else IMAGE_TYPE),
            INPUT_COMPRESSED_TOPIC if compressed else INPUT_IMAGE_TOPIC, qos("reliable", 10))
        det_pub = node.create_publisher(message_class(DETECTIONS_TYPE), INPUT_DETECTIONS_TOPIC,
                                        qos("reliable", 10))

        def on_output(msg) -> None:
            outputs[0] += 1

        subscribe_outputs(node, on_output, diagnostics)
        spin_until(executor, lambda: image_pub.get_subscription_count() > 0
                   and det_pub.get_subscription_count() > 0
                   and node.count_publishers(OUTPUT_TOPIC) > 0, 60.0)
        spin_until(executor, lambda: bool(diagnostics), 10.0)
        start_counts = counters(diagnostics)

        messages = images(args)
        churn = Churn(args.tracks, 1.0 / max(args.track_life * args.rate, 1.0), args.width,
                      args.height)
        period, base_stamp = 1.0 / args.rate, time.time_ns()
        start = next_report = time.monotonic()
        rss0 = rss_mb(pid)
        print(f"soak: {args.frames} frames at {args.rate:g} Hz, {args.tracks} tracks, "
              f"mean track life {args.track_life:g} s; node RSS {rss0:.0f} MB", flush=True)
        for i in range(args.frames):
            due = start + i * period
            while (left := due - time.monotonic()) > 0:
                executor.spin_once(timeout_sec=min(left, 0.01))
            header = make_header(base_stamp + int(i * period * 1e9), "camera", rclpy_make)
            image = messages[i % len(messages)]
            image.header = header
            image_pub.publish(image)
            det_pub.publish(boxes_to_detections(header, churn.step(), rclpy_make))
            if time.monotonic() >= next_report:
                reports.append(report(i + 1, start, pid, outputs[0], diagnostics, churn))
                next_report += args.report_s
        # Let the last frames come back and the node's counters settle.
        settle_end = time.monotonic() + 5.0
        while time.monotonic() < settle_end:
            executor.spin_once(timeout_sec=0.05)
        reports.append(report(args.frames, start, pid, outputs[0], diagnostics, churn))
        executor.shutdown()
        node.destroy_node()
    return books(args.frames, start_counts, counters(diagnostics), outputs[0], reports, rss0,
                 churn.created)


def spin_until(executor: SingleThreadedExecutor, condition, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit("soak: timed out waiting for the detector")
        executor.spin_once(timeout_sec=0.05)


def counters(diagnostics: Dict[str, str]) -> Dict[str, int]:
    keys = ("images", "detections", "outputs", "pending_images", "active_tracks",
            "track_overflow") + DROP_COUNTERS
    return {k: int(diagnostics.get(k, 0)) for k in keys}


def report(frames: int, start: float, pid: int, received: int, diagnostics: Dict[str, str],
           churn: Churn) -> Dict[str, object]:
    c = counters(diagnostics)
    drops = sum(v for k, v in c.items() if k in DROP_COUNTERS and k not in _NOT_DROPS)
    row = {"elapsed_s": round(time.monotonic() - start, 1), "frames": frames,
           "rss_mb": round(rss_mb(pid), 1), "node_outputs": c["outputs"],
           "received": received, "drops": drops, "active_tracks": c["active_tracks"],
           "tracks_created": churn.created}
    print(f"  {row['elapsed_s']:8.1f} s  frames {frames:6d}  RSS {row['rss_mb']:7.1f} MB  "
          f"outputs {c['outputs']:6d}  drops {drops:5d}  active tracks {c['active_tracks']:4d}  "
          f"tracks so far {churn.created}", flush=True)
    return row


def books(published: int, before: Dict[str, int], after: Dict[str, int], received: int,
          reports: List[Dict[str, object]], rss0: float, created: int) -> Dict[str, object]:
    """Every frame published: an output or a counted drop (image side of the books)."""
    d = {k: after[k] - before.get(k, 0) for k in after}
    image_drops = {k: d[k] for k in DROP_COUNTERS
                   if k not in _NOT_DROPS and "detections" not in k and d[k]}
    # Image drops count images; a work-queue drop is a pair, so an image too.
    accounted = d["outputs"] + sum(image_drops.values()) + d["pending_images"]
    rss = [r["rss_mb"] for r in reports]
    return {"published": published, "node_outputs": d["outputs"], "received": received,
            "image_drops": image_drops, "unaccounted": published - accounted,
            "unusable_images": {k: d[k] for k in _NOT_DROPS},
            "rss_start_mb": round(rss0, 1), "rss_max_mb": max(rss), "rss_end_mb": rss[-1],
            "tracks_created": created, "track_overflow": d["track_overflow"],
            "reports": reports}


def summary_line(args: argparse.Namespace, r: Dict[str, object]) -> str:
    drops = r["image_drops"]
    return (f"soak: {r['published']} frames at {args.rate:g} Hz, {r['tracks_created']} tracks; "
            f"outputs {r['node_outputs']} (received {r['received']}), counted drops "
            f"{sum(drops.values())} ({', '.join(f'{k} {v}' for k, v in drops.items()) or 'none'}), "
            f"unaccounted {r['unaccounted']}; RSS start {r['rss_start_mb']:.0f} MB, max "
            f"{r['rss_max_mb']:.0f} MB, end {r['rss_end_mb']:.0f} MB; node exit "
            f"{r['node_exit_code']}, tracebacks {r['node_log_tracebacks']}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
