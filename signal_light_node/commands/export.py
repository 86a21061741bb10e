"""``signal-light export --onnx OUT [--weights CKPT]``: a checkpoint's step as an ONNX file.

The file runs with ``--backend onnxruntime`` (replay) or the node's ``backend:
onnxruntime``; its metadata carries the model config, so it needs nothing else. The
shipped ``weights/default.onnx`` is made with::

    signal-light export --onnx signal_light_node/weights/default.onnx
"""

from __future__ import annotations

import argparse
from pathlib import Path

from signal_light_node.errors import ConfigError


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


def run(args: argparse.Namespace) -> int:
    """Export, print where and how well it matches torch."""
    from signal_light_node.model.onnx_export import VERIFY_TOLERANCE, export_onnx

    if args.onnx.suffix.lower() != ".onnx":
        raise ConfigError(f"--onnx must name a .onnx file, got {str(args.onnx)!r}")
    report = export_onnx(args.onnx, args.weights, opset=args.opset, verify=not args.no_verify)
    check = ("not checked" if report.max_abs_diff is None else
             f"max |torch - onnxruntime| {report.max_abs_diff:.1e} (limit {VERIFY_TOLERANCE:g})")
    print(f"wrote {report.path} ({report.size_bytes / 1e6:.2f} MB) from {report.checkpoint}; "
          f"{check}")
    return 0
