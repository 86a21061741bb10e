"""``python -m signal_light_node.evalgen -o OUT --seed N --lighting day|night``: write an
evaluation bag (see the package docstring)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import List, Optional

from signal_light_node.errors import SignalLightError
from signal_light_node.evalgen.bag import write_eval_bag
from signal_light_node.evalgen.preview import write_sheet
from signal_light_node.evalgen.config import EVENTS, LIGHTINGS, VIEW_MIXES, SceneConfig
from signal_light_node.evalgen.truth import EvalFrame


def build_parser() -> argparse.ArgumentParser:
    """The command's options."""
    p = argparse.ArgumentParser(prog="python -m signal_light_node.evalgen",
                                description="Write an independent evaluation scene bag.")
    p.add_argument("-o", "--output", type=Path, required=True, help="bag directory to create")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--lighting", choices=LIGHTINGS, default="day")
    p.add_argument("--frames", type=int, default=100, help="number of frames")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--vehicles", type=int, default=None, help="number of vehicles (default random)")
    p.add_argument("--views", choices=VIEW_MIXES, default="all",
                   help="all: ahead, oncoming, crossing, parked; behind: a one-way road, all ahead")
    p.add_argument("--events", choices=EVENTS, default="mixed",
                   help="mixed: blinks, hazards, braking; none: no signal at all")
    p.add_argument("--jpeg-quality", type=int, default=80)
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    p.add_argument("--preview", type=Path, default=None,
                   help="also write a contact sheet of four frames (PNG)")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    """Run the command; returns the exit status."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    picked: List[EvalFrame] = []
    try:
        config = SceneConfig(frames=args.frames, fps=args.fps, width=args.width, height=args.height,
                             lighting=args.lighting, n_vehicles=args.vehicles, views=args.views,
                             events=args.events)
        wanted = {int(args.frames * q) for q in (0.1, 0.35, 0.6, 0.85)}

        def keep(frame: EvalFrame) -> None:
            if args.preview is not None and frame.index in wanted:
                picked.append(frame)

        summary = write_eval_bag(args.output, args.seed, config, jpeg_quality=args.jpeg_quality,
                                 overwrite=args.overwrite, on_frame=keep)
        if args.preview is not None:
            write_sheet(args.preview, picked)
    except SignalLightError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {summary.path}: {summary.frames} frames, {summary.detections} detections, "
          f"{len(summary.track_ids)} tracks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
