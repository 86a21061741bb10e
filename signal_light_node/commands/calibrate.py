"""``signal-light calibrate LABELLED... --out MODEL``: fit how readily the model says
UNKNOWN and ON, on your labelled recordings.

Two numbers per checkpoint: the margin by which the UNKNOWN logit of the brake, left,
right and intent heads is lowered, and the offset of both blinkers' ON against their OFF
in log-odds, P(UNKNOWN) kept (how readily the filter turns a blinker on), chosen on grids
by the mean of intent macro-F1 and brake F1 through the node's intent filter
(:mod:`signal_light_node.training.unknown_bias`); a choice replaces the model as it is only
if its gain holds on resamples of the fit tracks' scenes (``--gain-confidence``,
:mod:`signal_light_node.training.fit_guard`). ``--holdout-fraction`` keeps a share of the
track IDs out of the fit and writes the before/after report beside the checkpoint.
``--night-negatives ... --max-false-brake X`` adds a third: the brake's ON offset nearest 0
that keeps those night tracks' false brakes within X; ``--max-false-blinker Y`` a further
blinker ON offset for their false blinkers (:mod:`signal_light_node.training.night_bound`).
Examples::

    signal-light calibrate out/day_labelled --holdout-fraction 0.5 --out runs/mine/calibrated.pt
    signal-light export --weights runs/mine/calibrated.pt --onnx runs/mine/calibrated.onnx

The inputs are labelled bags (``signal-light annotate import`` writes them) or
materialised split directories.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from signal_light_node.commands.options import add_torch_options, require_pt_checkpoints
from signal_light_node.errors import ConfigError


def _grid(text: str) -> tuple:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"a comma-separated list of numbers, got {text!r}") \
            from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light calibrate``."""
    from signal_light_node.training.fit_guard import DEFAULT_CONFIDENCE
    from signal_light_node.training.night_bound import DEFAULT_OFFSET_GRID, LIGHT_GROUPS
    from signal_light_node.training.unknown_bias import DEFAULT_GRID, DEFAULT_ON_GRID

    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    parser.add_argument("inputs", nargs="+", type=Path, metavar="LABELLED",
                        help="labelled bags (ground-truth topic) or materialised splits")
    parser.add_argument("--out", type=Path, required=True, metavar="MODEL",
                        help="the calibrated checkpoint to write (.pt; replaced if it exists)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="the .pt checkpoint to calibrate (default: the shipped weights)")
    parser.add_argument("--holdout-fraction", type=float, default=0.0, metavar="F",
                        help="share of the track IDs held out of the fit and scored before "
                             "and after (0: fit on all, no report)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the held-out draw")
    parser.add_argument("--grid", type=_grid, default=DEFAULT_GRID, metavar="M,M,...",
                        help="UNKNOWN margins to try (logit units, >= 0)")
    parser.add_argument("--on-grid", type=_grid, default=DEFAULT_ON_GRID, metavar="O,O,...",
                        help="blinker ON offsets to try (ON against OFF, in "
                             "log-odds; 0 alone keeps them; write --on-grid=-1,0,1)")
    parser.add_argument("--night-negatives", type=Path, nargs="+", default=[],
                        metavar="LABELLED",
                        help="night tracks whose steady tail lamps glare as brakes do "
                             "(render_data.sh: NIGHT_NEGATIVE_TRACKS): with --max-false-brake "
                             "or --max-false-blinker, the ON offset nearest 0 that keeps "
                             "their false lights within it")
    parser.add_argument("--fit-filter", action="store_true",
                        help="also fit the node's output filter (blinker hold, visibility "
                             "hold, brake release) on the same tracks; written into the "
                             "checkpoint's metadata and as node parameters to OUT.filter.yaml")
    parser.add_argument("--gain-confidence", type=float, default=DEFAULT_CONFIDENCE,
                        metavar="P",
                        help="a margin, ON offset or filter setting replaces the model as "
                             "it is (the default filter) only if it scores above it on at "
                             "least this share of resamples of the fit tracks' scenes "
                             "(0: the best on the fit tracks, however small its gain)")
    for group in LIGHT_GROUPS:
        parser.add_argument(f"--max-false-{group}", type=float, default=None, metavar="X",
                            help=f"with --night-negatives: the largest share of their "
                                 f"{group}-OFF frames that may be published ON")
        parser.add_argument(f"--{group}-grid", type=_grid, default=DEFAULT_OFFSET_GRID,
                            metavar="O,O,...", help=f"{group} ON offsets to try (0 or below; "
                                                    f"write --{group}-grid=-1,0)")
    add_torch_options(parser)


def run(args: argparse.Namespace) -> int:
    """Fit, write the checkpoint (and report), print what was found."""
    import torch

    from signal_light_node.training.night_bound import summary_line
    from signal_light_node.training.filter_fit import FILTER_GRID
    from signal_light_node.training.unknown_bias import calibrate_checkpoint, summary_lines

    require_pt_checkpoints(args, "calibrate")
    if not 0.0 <= args.holdout_fraction < 1.0:
        raise ConfigError(f"--holdout-fraction must be in [0, 1), got {args.holdout_fraction}")
    if not 0.0 <= args.gain_confidence < 1.0:
        raise ConfigError(f"--gain-confidence must be in [0, 1), got {args.gain_confidence}")
    bounds = _night_bounds(args)
    if args.threads:
        torch.set_num_threads(int(args.threads))
    fit, report = calibrate_checkpoint(args.out, args.inputs, args.checkpoint,
                                       args.holdout_fraction, args.seed, args.grid,
                                       args.on_grid, bounds,
                                       FILTER_GRID if args.fit_filter else None,
                                       args.gain_confidence)
    lines = summary_lines(fit, args.out, report)
    lines += [summary_line(fit) for fit in (bounds.fits if bounds else [])]
    print("\n".join(lines))
    return 0


def _night_bounds(args: argparse.Namespace):
    """The brake and blinker bounds asked for, as one ``after_fit`` (or None)."""
    from signal_light_node.training.night_bound import LIGHT_GROUPS, NightBounds

    asked = [(g, getattr(args, f"max_false_{g}"), getattr(args, f"{g}_grid"))
             for g in LIGHT_GROUPS]
    asked = [a for a in asked if a[1] is not None]
    if bool(args.night_negatives) != bool(asked):
        raise ConfigError("--night-negatives goes with --max-false-brake or "
                          "--max-false-blinker, and they with it")
    return NightBounds(args.night_negatives, asked) if asked else None
