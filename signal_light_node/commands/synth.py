"""``signal-light synth -o OUT``: render a synthetic scene bag with ground truth.

Writes a rosbag2 MCAP directory with JPEG (or, with ``--raw``, bgr8) camera frames, the
simulated tracker's ``Detection2DArray`` and the ground-truth ``VehicleLightStateArray``
(see ``signal_light_node.synth.bag``). The same options always give the same bag.
"""

from __future__ import annotations

import argparse

from signal_light_node.errors import ConfigError

LIGHTINGS = ("day", "dusk", "night", "mix")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light synth``."""
    parser.add_argument("-o", "--output", required=True, metavar="OUT",
                        help="bag directory to create")
    parser.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--frames", type=int, metavar="N", help="number of frames")
    length.add_argument("--duration", type=float, metavar="S",
                        help="length in seconds (default 10 when --frames is not given)")
    parser.add_argument("--fps", type=float, metavar="F",
                        help="frame rate in Hz (default: drawn from the seed, 10..30)")
    parser.add_argument("--width", type=int, default=640, help="image width (default 640)")
    parser.add_argument("--height", type=int, default=360, help="image height (default 360)")
    parser.add_argument("--vehicles", type=int, metavar="N",
                        help="number of vehicles (default: drawn from the seed)")
    parser.add_argument("--lighting", choices=LIGHTINGS, default="mix",
                        help="scene lighting; mix draws it from the seed (default mix)")
    parser.add_argument("--night-fraction", type=float, metavar="X",
                        help="with --lighting mix: probability of a night scene "
                             "(default: the renderer's)")
    parser.add_argument("--family", type=int, metavar="F",
                        help="style family of lamp colours and camera tone "
                             "(synth.lamps.STYLE_FAMILIES): the model trains on 0 and 1, 2 "
                             "is held out, a stand-in for a camera it never saw (default: "
                             "drawn from the seed among the training families)")
    parser.add_argument("--oblique", type=float, default=0.0, metavar="SHARE",
                        help="share of front and rear views drawn turned by 10-40 degrees "
                             "(foreshortened, flank in view; default 0)")
    parser.add_argument("--truth-rule", choices=("lamp", "function"), default="lamp",
                        help="how large a light's seen lamps must be for its ground truth to "
                             "be ON/OFF rather than UNKNOWN (synth.truth.TRUTH_RULES): each "
                             "lamp on its own (lamp, the committed bags') or the lamps of one "
                             "function together (function, the training splits'); default "
                             "%(default)s")
    parser.add_argument("--raw", action="store_true",
                        help="write sensor_msgs/Image bgr8 on /camera/image_raw instead of "
                             "JPEG CompressedImage on /camera/image_raw/compressed")
    parser.add_argument("--jpeg-quality", type=int, default=85, metavar="Q",
                        help="JPEG quality 1..100 (default 85)")
    parser.add_argument("--frame-id", default="camera", help="header.frame_id (default camera)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Write the bag and print a one-line summary."""
    from signal_light_node.synth.bag import write_scene_bag

    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    if args.duration is not None and args.duration <= 0:
        raise ConfigError(f"--duration must be positive, got {args.duration}")
    if args.night_fraction is not None and args.lighting != "mix":
        raise ConfigError("--night-fraction only applies with --lighting mix")
    summary = write_scene_bag(
        args.output, args.seed, n_frames=args.frames, duration_s=args.duration, fps=args.fps,
        width=args.width, height=args.height, n_vehicles=args.vehicles,
        lighting=None if args.lighting == "mix" else args.lighting,
        night_fraction=args.night_fraction, raw=args.raw, jpeg_quality=args.jpeg_quality,
        frame_id=args.frame_id, overwrite=args.overwrite, progress=not args.no_progress,
        **({} if args.family is None else {"family": args.family}),
        **({"oblique": args.oblique} if args.oblique else {}),
        **({"truth_rule": args.truth_rule} if args.truth_rule != "lamp" else {}))
    print(f"wrote {summary.path}: {summary.frames} frames at {summary.fps:g} Hz, "
          f"{summary.width}x{summary.height}, {summary.lighting}, "
          f"{len(summary.track_ids)} tracks, {summary.detections} detections")
    return 0
