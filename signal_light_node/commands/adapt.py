"""``signal-light adapt BAG... --out MODEL``: fit a model's normalisation to your camera,
without labels.

Moves the batch-norm running statistics of a checkpoint (default: the shipped weights)
to unlabelled recordings and refits nothing else
(:mod:`signal_light_node.training.adapt_norms`). By default (``--method shift``) each
running mean moves by the recordings' mean less the reference the checkpoint carries
(the same statistic on data like its training data; the shipped weights carry one), and
the variances stay; ``--method replace`` takes the recordings' means and variances. The
inputs are bags, read and paired as the node reads them (``--image-topic``,
``--detections-topic``, ``--sync-slop`` as in ``replay``), or materialised split
directories (their labels are not read). Examples::

    signal-light adapt my_recording_1 my_recording_2 --out runs/mine/adapted.pt
    signal-light evaluate --checkpoint runs/mine/adapted.pt --bags my_labelled --out runs/mine/eval
    signal-light export --weights runs/mine/adapted.pt --onnx runs/mine/adapted.onnx
    # a model of your own: record its reference on (a sample of) its training data first
    signal-light adapt --reference runs/mine/pool --checkpoint mine.pt --out mine_ref.pt

A model without batch norm, data without a usable crop, or a shift without a reference is
refused in one line and nothing is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from signal_light_node.commands.options import (add_input_topic_options, add_pairing_options,
                                                add_torch_options, pairing_from_args,
                                                require_pt_checkpoints)
from signal_light_node.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light adapt``."""
    from signal_light_node.training.adapt_norms import METHODS, AdaptSettings

    default = AdaptSettings()
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    parser.add_argument("inputs", nargs="*", type=Path, metavar="BAG",
                        help="unlabelled recordings (bags), or materialised split directories; "
                             "none, with --reference: only record the reference")
    parser.add_argument("--out", type=Path, required=True, metavar="MODEL",
                        help="the adapted checkpoint to write (.pt; replaced if it exists)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="the .pt checkpoint to adapt (default: the shipped weights)")
    parser.add_argument("--method", choices=METHODS, default=default.method,
                        help="shift: running means move by the data's mean less the "
                             "reference's, variances kept; replace: take the data's "
                             "means and variances")
    parser.add_argument("--reference", nargs="+", type=Path, default=[], metavar="DATA",
                        help="bags or splits like the model's training data: measure the "
                             "reference on them (default: the one the checkpoint carries)")
    parser.add_argument("--keep-first", type=int, default=default.keep_first, metavar="N",
                        help="leave the first N batch-norm layers as they are (default: the "
                             "trunk model's stem, 1; the CNN's none, 0)")
    parser.add_argument("--max-frames", type=int, default=default.max_frames, metavar="N",
                        help="use at most N crops: whole tracks drawn with --seed, the last "
                             "one cut short (default: all)")
    parser.add_argument("--seed", type=int, default=default.seed,
                        help="seed of the --max-frames draw")
    parser.add_argument("--batch-tracks", type=int, default=default.batch_tracks,
                        help="tracks stepped side by side")
    parser.add_argument("--window", type=int, default=default.window_frames, metavar="FRAMES",
                        help="frames per track and model call (the state is carried across)")
    add_input_topic_options(parser)
    add_pairing_options(parser)
    add_torch_options(parser)


def run(args: argparse.Namespace) -> int:
    """Adapt, write the checkpoint, print what changed."""
    import torch

    from signal_light_node.training.adapt_norms import (AdaptSettings, InputReading,
                                                        adapt_checkpoint, record_reference)

    require_pt_checkpoints(args, "adapt", "an ONNX export has its batch norms folded into "
                                          "the convolutions")
    if args.threads:
        torch.set_num_threads(int(args.threads))
    if not args.inputs and not args.reference:
        raise ConfigError("give at least one bag or split directory to adapt on (or "
                          "--reference alone to record a reference)")
    if args.inputs and args.reference and args.method == "replace":
        raise ConfigError("--reference is what a shift starts from; --method replace "
                          "does not use one")
    settings = AdaptSettings(batch_tracks=args.batch_tracks, window_frames=args.window,
                             max_frames=args.max_frames, seed=args.seed, device=args.device,
                             method=args.method, keep_first=args.keep_first)
    reading = InputReading(image_topic=args.image_topic, detection_topic=args.detections_topic,
                           pairing=pairing_from_args(args))
    if args.inputs:
        result = adapt_checkpoint(args.out, args.inputs, args.checkpoint, settings, reading,
                                  progress=not args.no_progress, reference=args.reference)
    else:
        result = record_reference(args.out, args.reference, args.checkpoint, settings,
                                  reading, progress=not args.no_progress)
    print("\n".join(result.summary_lines()))
    return 0
