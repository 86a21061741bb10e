"""``signal-light export --onnx OUT [--weights CKPT] [--int8 --calibration BAG ...]``.

Writes a checkpoint's step as an ONNX file. The file runs with ``--backend
onnxruntime`` (replay) or the node's ``backend: onnxruntime``; its metadata carries the
model config, so it needs nothing else. ``--int8`` writes the same step with int8
convolutions (``model.onnx_quantize``), their ranges measured on what the float export's
steps see when the calibration bags are replayed through it, and refuses a file whose
per-step classes agree with the float export's on those bags less than
``MIN_AGREEMENT`` of the time. The shipped files are made with::

    signal-light export --onnx signal_light_node/weights/default.onnx
    signal-light export --onnx signal_light_node/weights/default_int8.onnx --int8 \\
        --calibration bags/day_street bags/night_street
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from signal_light_node.errors import CheckpointError, ConfigError

#: Least share of track steps, per task, in which the int8 file must pick the float
#: export's class on the calibration bags (the shipped file: 0.98-1.0).
MIN_AGREEMENT = 0.95


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light export``."""
    from signal_light_node.model.onnx_format import DEFAULT_OPSET

    parser.add_argument("--onnx", type=Path, required=True, metavar="OUT",
                        help="the .onnx file to write (replaced if it exists)")
    parser.add_argument("--weights", type=Path, default=None, metavar="CKPT",
                        help="checkpoint to export (default: the shipped weights)")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                        help=f"ONNX opset version (default {DEFAULT_OPSET})")
    parser.add_argument("--no-verify", action="store_true",
                        help="skip running synthetic tracks through torch and onnxruntime "
                             "to check that the file matches")
    int8 = parser.add_argument_group("int8 (onnxruntime on the CPU)")
    int8.add_argument("--int8", action="store_true",
                      help="quantise the backbone and ConvLSTM convolutions to int8")
    int8.add_argument("--calibration", nargs="+", type=Path, default=[], metavar="BAG",
                      help="bags whose replay gives the int8 ranges and the agreement check")
    int8.add_argument("--calibration-rows", type=int, default=1024,
                      help="track steps drawn from the replay for the ranges (default 1024)")
    int8.add_argument("--calibration-seed", type=int, default=0,
                      help="seed of that draw (default 0)")


def run(args: argparse.Namespace) -> int:
    """Export (and quantise), print where and how well it matches."""
    from signal_light_node.model.onnx_export import VERIFY_TOLERANCE, export_onnx

    if args.onnx.suffix.lower() != ".onnx":
        raise ConfigError(f"--onnx must name a .onnx file, got {str(args.onnx)!r}")
    if args.int8 != bool(args.calibration):
        raise ConfigError("--int8 and --calibration BAG ... go together")
    if not args.int8:
        report = export_onnx(args.onnx, args.weights, opset=args.opset,
                             verify=not args.no_verify)
    else:
        with tempfile.TemporaryDirectory(prefix="signal_light_export_") as tmp:
            report = export_onnx(Path(tmp) / "fp32.onnx", args.weights, opset=args.opset,
                                 verify=not args.no_verify)
            _quantize(report.path, args)
    check = ("not checked" if report.max_abs_diff is None else
             f"max |torch - onnxruntime| {report.max_abs_diff:.1e} (limit {VERIFY_TOLERANCE:g})")
    print(f"wrote {args.onnx} ({args.onnx.stat().st_size / 1e6:.2f} MB) from "
          f"{report.checkpoint}; float export {check}")
    return 0


def _quantize(fp32: Path, args: argparse.Namespace) -> None:
    """The int8 file from the float export ``fp32``, checked on the calibration bags.

    Raises:
        CheckpointError: It agrees with the float export less than ``MIN_AGREEMENT``.
    """
    from signal_light_node.model.onnx_quantize import quantize_export, sample_rows
    from signal_light_node.tools.calibration import record_steps, step_agreement

    reference = record_steps(fp32, args.calibration)
    crops, states = sample_rows(reference.crops, reference.states, args.calibration_rows,
                                args.calibration_seed)
    calibration = {"bags": [p.name for p in args.calibration], "rows": int(len(crops)),
                   "seed": int(args.calibration_seed)}
    args.onnx.parent.mkdir(parents=True, exist_ok=True)
    # The candidate sits beside OUT, so that it replaces OUT in one rename when it passes.
    candidate = args.onnx.with_name(f".{args.onnx.name}.{os.getpid()}.int8")
    try:
        quantize_export(fp32, candidate, crops, states, calibration)
        agreement = step_agreement(reference, record_steps(candidate, args.calibration,
                                                           inputs=False))
        text = ", ".join(f"{task} {share:.3f}" for task, share in agreement.items())
        if min(agreement.values()) < MIN_AGREEMENT:
            raise CheckpointError(f"the int8 file picks the float export's class too rarely on "
                                  f"the calibration bags ({text}; need >= {MIN_AGREEMENT})")
        os.replace(candidate, args.onnx)
    finally:
        candidate.unlink(missing_ok=True)
    print(f"int8: {calibration['rows']} calibration steps from {calibration['bags']}; class "
          f"agreement with the float export per track step: {text}")
