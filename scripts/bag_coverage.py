#!/usr/bin/env python3
"""Check (or search for) scene bags whose ground truth covers every class.

    python scripts/bag_coverage.py bags/day_street bags/night_street
        prints each bag's coverage and exits 1 if one lacks a view, an intent, brake ON
        or OFF, has fewer than --min-tracks tracks, or is not about 10 s long;
    python scripts/bag_coverage.py --search --lighting night --fps 12 --vehicles 6 --seeds 0:40
        renders candidate scenes (ground truth only, no bag written) and prints the seeds
        that cover everything, best first.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from typing import Dict, List

from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.synth.bag import REQUIRED_CLASSES, coverage_gaps, ground_truth_coverage


def check(paths: List[str], min_tracks: int, min_s: float, max_s: float) -> int:
    bad = 0
    for path in paths:
        coverage = ground_truth_coverage(path)
        lacks = coverage_gaps(coverage, min_tracks)
        if not min_s <= coverage["duration_s"] <= max_s:
            lacks.append(f"duration={coverage['duration_s']:.1f}s")
        print(json.dumps({"bag": path, "ok": not lacks, "missing": lacks, **coverage}))
        bad += bool(lacks)
    return 1 if bad else 0


def search(args: argparse.Namespace) -> int:
    from signal_light_node.synth import SceneRenderer

    first, last = (int(v) for v in args.seeds.split(":"))
    found = []
    for seed in range(first, last):
        renderer = SceneRenderer(seed, width=args.width, height=args.height, fps=args.fps,
                                 n_vehicles=args.vehicles, lighting=args.lighting)
        n_frames = int(round(args.duration * renderer.fps))
        counts = {key: Counter() for key in ("views", "intents", "brake")}
        tracks = set()
        for frame in renderer.frames(n_frames):
            for v in frame.vehicles:
                if v.tracker_box is None:
                    continue
                tracks.add(v.track_id)
                counts["views"][View(v.view).name] += 1
                counts["intents"][Intent(v.intent).name] += 1
                counts["brake"][LightStatus(v.brake).name] += 1
        coverage = {"tracks": len(tracks), **{k: dict(c) for k, c in counts.items()}}
        lacks = coverage_gaps(coverage, args.min_tracks)
        # Rank by the rarest required class: more frames of it make a better test bag.
        rarest = min(coverage[k].get(n, 0) for k, names in REQUIRED_CLASSES.items() for n in names)
        print(json.dumps({"seed": seed, "ok": not lacks, "rarest": rarest, "missing": lacks,
                          **coverage}), flush=True)
        if not lacks:
            found.append((rarest, seed))
    print("covering seeds, best first:", [s for _, s in sorted(found, reverse=True)])
    return 0 if found else 1


def main(argv: List[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bags", nargs="*", help="bags to check")
    parser.add_argument("--min-tracks", type=int, default=4)
    parser.add_argument("--min-duration", type=float, default=9.0)
    parser.add_argument("--max-duration", type=float, default=11.0)
    parser.add_argument("--search", action="store_true", help="search seeds instead")
    parser.add_argument("--seeds", default="0:20", help="FIRST:LAST seed range to search")
    parser.add_argument("--lighting", default=None)
    parser.add_argument("--fps", type=float, default=12.0)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--vehicles", type=int, default=6)
    args = parser.parse_args(argv)
    if args.search:
        return search(args)
    if not args.bags:
        parser.error("give bags to check, or --search")
    return check(args.bags, args.min_tracks, args.min_duration, args.max_duration)


if __name__ == "__main__":
    sys.exit(main())
