"""``signal-light annotate export BAG OUT`` / ``signal-light annotate import FILE BAG OUT``:
label a recording in CVAT.

``export`` writes a CVAT video task of the bag (frames as JPEG, ``annotations.xml`` in
"CVAT for video 1.1" with the node's predictions as attribute values, ``labels.json``
for CVAT's raw label constructor, and the frame list ``signal_light_export.json``);
``import`` checks the corrected file against that export and the bag and writes a bag
with ground truth. The body is :mod:`signal_light_node.tools.annotate`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from signal_light_node.commands.options import (add_input_topic_options,
                                                add_intent_filter_options, add_model_options,
                                                add_pairing_options, add_torch_options,
                                                add_track_timeout_option, engine_from_args,
                                                pairing_from_args)
from signal_light_node.errors import ConfigError


def _time(text: str):
    """argparse type of ``--start`` / ``--end``."""
    from signal_light_node.tools.annotate import parse_time

    try:
        return parse_time(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Subcommands ``export`` and ``import`` of ``signal-light annotate``."""
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    export = sub.add_parser(
        "export", help="write a CVAT video task of a bag, the node's predictions pre-filled",
        description="Frames as JPEG (OUT/images), OUT/annotations.xml (CVAT for video 1.1: a "
                    "track per track ID, brake/left/right/intent/view per box from the node's "
                    "output as `signal-light replay` makes it), OUT/labels.json (CVAT's raw "
                    "labels) and OUT/signal_light_export.json (the frames' stamps).")
    export.add_argument("bag", type=Path, help="the recording (rosbag2 directory or .mcap)")
    export.add_argument("out", type=Path, help="directory to create")
    export.add_argument("--start", type=_time, default=None, metavar="S|@STAMP",
                        help="first frame: seconds after the bag's first image, or @ and a "
                             "header stamp in seconds (default: the first image)")
    export.add_argument("--end", type=_time, default=None, metavar="S|@STAMP",
                        help="last frame, included (default: the last image)")
    export.add_argument("--every", type=int, default=1, metavar="N",
                        help="export every N-th frame of the range (default 1: all); the "
                             "node still runs over every frame")
    export.add_argument("--min-box", type=float, default=0.0, metavar="PX",
                        help="leave out boxes whose shorter side, clipped to the image, is "
                             "under PX pixels (they get no ground truth)")
    add_input_topic_options(export)
    add_model_options(export)
    add_track_timeout_option(export)
    add_pairing_options(export)
    add_intent_filter_options(export.add_argument_group("intent filter (as the node's)"))
    add_torch_options(export)

    imp = sub.add_parser(
        "import", help="check corrected CVAT labels against the bag, write a labelled bag",
        description="Reads the corrected annotations.xml (or CVAT's export ZIP), checks it "
                    "against its export and the bag (same frames, same track IDs, known "
                    "values; one line naming the first mismatch, nothing written) and writes "
                    "OUT: the bag's images and detections plus /ground_truth/vehicle_lights.")
    imp.add_argument("file", type=Path, help="the corrected annotations.xml or CVAT's .zip")
    imp.add_argument("bag", type=Path, help="the recording it was exported from")
    imp.add_argument("out", type=Path, help="the labelled bag to create")
    imp.add_argument("--export", type=Path, default=None, metavar="JSON",
                     help="the export's signal_light_export.json (default: beside FILE)")


def run(args: argparse.Namespace) -> int:
    """Run ``export`` or ``import`` and print what was written."""
    from signal_light_node.tools import annotate

    if args.action == "import":
        print(annotate.import_labels(args.file, args.bag, args.out, export=args.export).text())
        return 0
    options = annotate.ExportOptions(start=args.start, end=args.end, every=args.every,
                                     min_box=args.min_box, image_topic=args.image_topic,
                                     detections_topic=args.detections_topic,
                                     pairing=pairing_from_args(args))
    annotate.check_new_output(args.out)  # before loading the model: the quicker error
    engine = engine_from_args(args)
    summary = annotate.export_for_labelling(args.bag, args.out, engine, options,
                                            progress=not args.no_progress)
    print(summary.text())
    return 0
