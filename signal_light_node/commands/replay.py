"""``signal-light replay BAG -o OUT``: the detector engine over a bag, without ROS.

Several cameras: ``signal-light replay FRONT_BAG REAR_BAG -o OUT`` (one camera per bag,
named after the bags or by ``--camera NAME`` per bag), or ``signal-light replay BAG -o OUT
--camera front=/front/image,/front/dets --camera rear`` (pairs of one bag; a bare name is
found by namespace) or ``--all-cameras`` (every pair found by namespace); each camera's
outputs go to ``/signal_light_detector/<camera>/output/...``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any, Dict

from signal_light_node.commands.options import (add_input_topic_options,
                                                add_intent_filter_options, add_model_options,
                                                add_pairing_options, add_torch_options,
                                                add_track_timeout_option, engine_from_args,
                                                pairing_from_args)
from signal_light_node.errors import ConfigError
from signal_light_node.runtime.pairing import PairingConfig

LOG = logging.getLogger(__name__)


def _threshold(text: str) -> tuple:
    """``brake=0.6`` / ``100=0.6`` -> ("brake", 0.6)."""
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected CODE=P or LIGHT=P (e.g. brake=0.6), got "
                                         f"{text!r}")
    try:
        return key.strip(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"threshold {value!r} is not a number") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light replay``."""
    parser.add_argument("bag", type=Path, nargs="+",
                        help="input bag (rosbag2 directory or .mcap); several bags = one "
                             "camera each, replayed together as a node with cameras")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="output MCAP rosbag2 directory")
    add_model_options(parser)
    add_input_topic_options(parser)
    parser.add_argument("--camera", action="append", default=[],
                        metavar="NAME[=IMAGE_TOPIC,DETECTIONS_TOPIC]",
                        help="a camera (repeatable): with several bags one per bag in order "
                             "(default names: the bags'); with one bag a camera topic pair of "
                             "it (a bare NAME: the pair under namespace NAME); each camera's "
                             "outputs go to /signal_light_detector/NAME/output/...")
    parser.add_argument("--all-cameras", action="store_true",
                        help="one bag: every camera found by namespace (a detection topic "
                             "and the image topic sharing the longest namespace with it)")
    parser.add_argument("--with-inputs", action="store_true",
                        help="also write the image, detection and ground-truth topics")
    parser.add_argument("--video", type=Path, default=None,
                        help="write an annotated .mp4 or .gif of the frames")
    parser.add_argument("--attention", action="store_true",
                        help="overlay the attention masks in the video")
    parser.add_argument("--threshold", type=_threshold, action="append", default=[],
                        metavar="LIGHT=P",
                        help="ON-probability threshold of a light for the classification "
                             "codes, e.g. brake=0.6 or 101=0.4 (repeatable; default 0.5)")
    add_track_timeout_option(parser)
    parser.add_argument("--markers", action="store_true",
                        help="also write the results drawn for RViz (visualization_msgs/"
                             "MarkerArray) on the node's ~/output/markers topic")
    add_pairing_options(parser)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_intent_filter_options(parser.add_argument_group("intent filter (as the node's)"))
    add_torch_options(parser)


def run(args: argparse.Namespace) -> int:
    """Replay the bag, print the summary and, with ground truth, the metrics."""
    from signal_light_node.tools.replay import replay_bag

    if args.video is not None and args.video.suffix.lower() not in (".mp4", ".gif"):
        raise ConfigError(f"--video must end in .mp4 or .gif, got {args.video.name!r}")
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    thresholds: Dict[str, float] = dict(args.threshold)
    pairing = pairing_from_args(args)  # before loading the model: a bad option is the quicker error
    if len(args.bag) > 1 or args.camera or args.all_cameras:
        return _run_cameras(args, thresholds, pairing)
    bag = args.bag[0]
    engine = engine_from_args(args, thresholds)
    summary = replay_bag(bag, args.output, engine, image_topic=args.image_topic,
                         detections_topic=args.detections_topic, with_inputs=args.with_inputs,
                         video=args.video, video_attention=args.attention,
                         overwrite=args.overwrite, progress=not args.no_progress,
                         pairing=pairing, markers=args.markers)
    _print_summary(summary, engine, bag)
    return 0


def _run_cameras(args: argparse.Namespace, thresholds: Dict[str, float],
                 pairing: PairingConfig) -> int:
    """Several cameras through the multi-camera engine (``tools.replay_cameras``)."""
    from signal_light_node.tools.replay_cameras import camera_sources, replay_cameras

    for option, value in (("--image-topic", args.image_topic),
                          ("--detections-topic", args.detections_topic),
                          ("--video", args.video)):
        if value is not None:
            raise ConfigError(f"{option} takes a single camera; with several cameras name "
                              "each camera's topics with --camera NAME=IMAGE,DETECTIONS")
    sources = camera_sources(args.bag, args.camera, args.all_cameras)
    engine = engine_from_args(args, thresholds)
    summary = replay_cameras(sources, args.output, engine, with_inputs=args.with_inputs,
                             overwrite=args.overwrite, progress=not args.no_progress,
                             pairing=pairing, markers=args.markers)
    _print_summary(summary, engine, ", ".join(
        f"{name} ({c.bag})" for name, c in summary.cameras.items() if c.has_ground_truth))
    return 0


def _print_summary(summary: Any, engine: Any, scored: "Path | str") -> None:
    """The replay summary and, with ground truth, its scores (``scored`` names what was
    scored: the bag, or the cameras with ground truth)."""
    from signal_light_node.tools.replay import score_summary

    print(summary.text())
    if not summary.has_ground_truth:
        return
    result = score_summary(summary)
    if result is None:
        print("ground truth present, but no judged detection matched it")
        return
    print(render_scores(result, scored, engine.config.intent_filter.describe()))


def render_scores(result: dict, bag: "Path | str", intent_filter: str = "") -> str:
    """The replay's agreement with the ground truth as Markdown.

    Args:
        result: ``replay.score_summary``'s result.
        bag: The bag replayed.
        intent_filter: ``IntentFilterConfig.describe()`` of the engine, if known.
    """
    from signal_light_node.evaluation.metrics import (flicker_markdown, light_outcomes_markdown,
                                                      markdown_report, switches_markdown)

    st, c = result["settings"], result["counts"]
    head = (f"Agreement with the ground truth of {bag}: {c['frames']} judged frames with ground "
            f"truth in {c['tracks']} track segments, {c['scored']} scored after the warm-up "
            f"(first max({st['warmup_frames']} frames, {st['warmup_seconds']:g} s) of each "
            f"track state).")
    if intent_filter:
        head += f" Intent filter: {intent_filter}."
    if c["scored"] == 0:
        return head + " Nothing left to score."
    return "\n".join([head, "", markdown_report(result["no_grace"], "After warm-up"),
                      markdown_report(result["grace"], f"After warm-up, "
                                      f"{st['grace_seconds']:g} s grace window after label "
                                      f"changes"),
                      "### Switches (after warm-up: class changes along the tracks)", "",
                      switches_markdown(result["switches"]),
                      "### Flicker per track (after warm-up)", "",
                      flicker_markdown(result["flicker"]),
                      "### UNKNOWN published where the truth is OFF or ON, calibration (ECE)",
                      "", light_outcomes_markdown(result["unknown_share"],
                                                  result["calibration"])])
