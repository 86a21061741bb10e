"""The ``signal-light`` command-line tool.

Each subcommand lives in its own module under ``signal_light_node.commands`` with two
functions, ``add_arguments(parser)`` and ``run(args) -> int``; modules are imported only
when their subcommand runs, so ``signal-light info`` does not pay for importing torch.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import List, Optional

from signal_light_node.errors import SignalLightError

#: name -> (module under signal_light_node.commands, one-line help)
SUBCOMMANDS = {
    "info": ("info", "describe a bag: topics, types, counts, duration, image size, track IDs"),
    "synth": ("synth", "render a synthetic scene bag with ground truth"),
    "train": ("train", "train the light-state model"),
    "adapt": ("adapt", "move a model's batch-norm statistics to unlabelled recordings of "
                       "your camera (no labels; nothing else refit)"),
    "calibrate": ("calibrate", "fit how readily the model says UNKNOWN on your labelled "
                               "recordings (one margin; before/after on held-out tracks)"),
    "evaluate": ("evaluate", "score a checkpoint on a synthetic split or on labelled bags"),
    "replay": ("replay", "run the detector engine over a bag without ROS, writing an output bag"),
    "export": ("export", "export a checkpoint's model step to ONNX (for the onnxruntime backend)"),
    "annotate": ("annotate", "label a recording in CVAT: export it with the node's predictions, "
                             "import the corrected labels as a labelled bag"),
    "play": ("play", "publish a bag's image and detection topics into a live ROS graph"),
    "record": ("record", "record topics of a live ROS graph into an MCAP bag"),
}


def _load(module: str):
    return importlib.import_module(f"signal_light_node.commands.{module}")


def build_parser(argv: Optional[List[str]] = None) -> argparse.ArgumentParser:
    """Build the argument parser; only the chosen subcommand's module is imported."""
    parser = argparse.ArgumentParser(prog="signal-light", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen = next((a for a in (argv or []) if a in SUBCOMMANDS), None)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            _load(module).add_arguments(p)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point of ``signal-light``; returns the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(argv).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    module = _load(SUBCOMMANDS[args.command][0])
    try:
        return int(module.run(args) or 0)
    except SignalLightError as exc:
        print(f"signal-light {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
