"""int8 convolutions for an exported step (``signal-light export --onnx OUT --int8``).

On a CPU without AVX-512 the float32 step of 32 tracks costs ~55 ms on one core, and
a node that shares its computer gets about one core. Most of that is convolutions; as
int8 (8-bit weights, one scale per output channel, 8-bit activations) onnxruntime runs
them about twice as fast. What is quantised and how (measured on a 2-core AVX2 CPU,
32 tracks, one thread; docs/model.md has the accuracy):

* Only the backbone's (the pretrained trunk's from block ``TRUNK_INT8_FROM`` on) and the
  ConvLSTM's convolutions: 0.76x the float32 step. The
  attention net's convolutions too: 1.0x (the quantise/dequantise steps around its
  small layers eat what they save), so they stay float32, as do the heads, the gates'
  nonlinearities, the temporal evidence and the state, so the recurrent state is not
  rounded to 8 bits from frame to frame.
* Static ranges (min/max of each quantised tensor over recorded step inputs): no
  per-frame range computation at run time.
* The file keeps the float export's interface and metadata, plus
  ``onnx_format.KEY_QUANTIZATION`` saying what was done and on which data, so the
  onnxruntime backend loads it as any export.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence

import numpy as np

from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.model import onnx_format as fmt
from signal_light_node.model.onnx_export import publish_file

LOG = logging.getLogger(__name__)

#: Convolutions whose node names start with these are quantised (the exporter names
#: nodes after the torch modules: ``/backbone/...``, ``/cells.0/gates/Conv``,
#: ``/trunk/blocks/blocks.7/...``).
QUANTIZED_MODULES = ("/backbone/", "/cells.", "/trunk/")
#: Of the pretrained trunk, only blocks from this one on (its stride-16 stages) are
#: quantised: with the stem and the first five blocks at 8 bits too, a trunk fine-tuned
#: frame by frame picked the float export's intent class on 93.1 % of the calibration
#: bags' steps (the export's check wants 95 %); from block 5 on, 98.5 %, and the step of
#: 32 tracks still takes 0.84x the float one (docs/model.md, "The trunk fine-tuned frame
#: by frame").
TRUNK_INT8_FROM = 5

#: Calibration inputs run through the float model per batch.
CALIBRATION_BATCH = 32


class _Batches:
    """Recorded step inputs in batches, as onnxruntime's ``CalibrationDataReader`` (any
    class with ``get_next`` is one) hands them to the calibration."""

    def __init__(self, crops: np.ndarray, states: np.ndarray, batch: int) -> None:
        self._feeds: Iterator[Dict[str, np.ndarray]] = iter(
            {fmt.CROPS_INPUT: crops[i:i + batch], fmt.STATE_INPUT: states[i:i + batch]}
            for i in range(0, len(crops), batch))

    def get_next(self) -> Optional[Dict[str, np.ndarray]]:
        return next(self._feeds, None)


def _late_enough(name: str) -> bool:
    """False for a node of the trunk's stem or of a block before :data:`TRUNK_INT8_FROM`."""
    if not name.startswith("/trunk/"):
        return True
    match = re.match(r"/trunk/blocks/blocks\.(\d+)/", name)
    return match is not None and int(match.group(1)) >= TRUNK_INT8_FROM


def quantized_nodes(model: Any) -> List[str]:
    """Names of the ``Conv`` nodes of an ONNX graph that :func:`quantize_export` quantises."""
    return [n.name for n in model.graph.node
            if n.op_type == "Conv" and n.name.startswith(QUANTIZED_MODULES)
            and _late_enough(n.name)]


def quantize_export(source: "str | Path", output: "str | Path", crops: np.ndarray,
                    states: np.ndarray, calibration: Dict[str, Any]) -> Path:
    """Write ``output``: the float export ``source`` with int8 convolutions.

    Args:
        source: A float32 export (``onnx_export.export_onnx``).
        output: The ``.onnx`` file to write (replaced).
        crops: uint8 ``[M, S, S, 3]`` step inputs the ranges are measured on.
        states: float32 ``[M, W]`` the states that went with them.
        calibration: What the inputs were (bags, rows, seed), kept in the metadata.

    Returns:
        ``output``.

    Raises:
        ConfigError: The quantisation tools (``onnx``, ``onnxruntime``) are missing or
            there are no calibration inputs.
        CheckpointError: ``source`` is not a float export of this package.
    """
    try:
        import onnx
        from onnxruntime.quantization import (CalibrationMethod, QuantFormat, QuantType,
                                              quantize_static)
    except ImportError as exc:
        raise ConfigError(f"--int8 needs onnx and onnxruntime ({exc}); "
                          "pip install -r requirements.txt") from None
    if len(crops) == 0 or len(crops) != len(states):
        raise ConfigError(f"calibration needs step inputs: got {len(crops)} crops and "
                          f"{len(states)} states")
    model = onnx.load(str(source))
    meta = {p.key: p.value for p in model.metadata_props}
    if fmt.KEY_CONFIG not in meta or fmt.precision_of(meta) != "fp32":
        raise CheckpointError(f"{source} is not a float32 export of signal-light export --onnx")
    nodes = quantized_nodes(model)
    output = Path(output)
    fd, tmp = tempfile.mkstemp(prefix=output.name + ".", suffix=".tmp", dir=output.parent)
    os.close(fd)
    try:
        reader = _Batches(crops, states, CALIBRATION_BATCH)
        with _quiet_root_logger():
                quantize_static(str(source), tmp, reader, quant_format=QuantFormat.QDQ,
                            per_channel=True, weight_type=QuantType.QInt8,
                            activation_type=QuantType.QUInt8, nodes_to_quantize=nodes,
                            calibrate_method=CalibrationMethod.MinMax)
        quantized = onnx.load(tmp)
        _write_metadata(quantized, meta, {
            "weights": "int8, one scale per output channel",
            "activations": "uint8, static min/max ranges", "format": "QDQ",
            "nodes": nodes, "calibration": calibration})
        onnx.checker.check_model(quantized)
        onnx.save(quantized, tmp)
        publish_file(tmp, output)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    LOG.info("quantised %d convolutions of %s into %s", len(nodes), source, output)
    return output


@contextlib.contextmanager
def _quiet_root_logger() -> Iterator[None]:
    """Drop the quantiser's advice to pre-process the graph (logged on the root logger):
    shape inference and graph optimisation beforehand made no difference here."""
    def advice(record: logging.LogRecord) -> bool:
        return "pre-process" not in record.getMessage()

    root = logging.getLogger()
    root.addFilter(advice)
    try:
        yield
    finally:
        root.removeFilter(advice)


def _write_metadata(model: Any, meta: Dict[str, str], quantization: Dict[str, Any]) -> None:
    """The float export's metadata (only ours: the tools add their own) plus how it was
    quantised."""
    del model.metadata_props[:]
    ours = {k: v for k, v in meta.items() if k.startswith("signal_light.")}
    ours[fmt.KEY_QUANTIZATION] = json.dumps(quantization, sort_keys=True)
    for key, value in ours.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value


def sample_rows(crops: Sequence[np.ndarray], states: Sequence[np.ndarray], rows: int,
                seed: int) -> "tuple[np.ndarray, np.ndarray]":
    """At most ``rows`` (crop, state) rows drawn without replacement from recorded steps.

    Args:
        crops: Each step's uint8 ``[N, S, S, 3]`` crops.
        states: Each step's float32 ``[N, W]`` states.
        rows: How many rows to keep.
        seed: The draw's seed (the same inputs and seed give the same rows).
    """
    sizes = [len(c) for c in crops]
    total = sum(sizes)
    if total <= rows:
        return np.concatenate(list(crops)), np.concatenate(list(states))
    keep = np.sort(np.random.default_rng(seed).choice(total, rows, replace=False))
    # Gather the drawn rows step by step: concatenating every state first would copy
    # ~150 kB per recorded track step only to keep a few of them.
    starts = np.cumsum([0] + sizes[:-1])
    step = np.searchsorted(starts, keep, side="right") - 1
    row = keep - starts[step]
    return (np.stack([crops[s][r] for s, r in zip(step, row)]),
            np.stack([states[s][r] for s, r in zip(step, row)]))
