"""The ONNX file a light-state model is exported to: input and output names, metadata keys.

Written by :mod:`signal_light_node.model.onnx_export` (``signal-light export --onnx``),
read by the ``onnxruntime`` backend. One graph is one batched step::

    inputs   crops      uint8   [N, S, S, 3]   BGR crops as ``crops.crop_vehicles`` cuts them
             state      float32 [N, W]         each track's state, flattened (see below)
    outputs  intent, brake, left, right, view
                        float32 [N, K]         probabilities per task (``labels.TASKS``)
             state_out  float32 [N, W]         the new states
             attention  float32 [N, S, S]      the attention mask the step applied

``N`` is dynamic. A state row is the model's state tensors (``(h, c)`` per ConvLSTM
layer, then the temporal history pair) flattened in that order; their per-track shapes
are in the metadata, and a new track's row is all zeros. The metadata
(``metadata_props``) holds everything else the backend needs, so the ``.onnx`` file is
self-contained: the ``ModelConfig`` as JSON, the state shapes and where the file came
from (the checkpoint's SHA-256).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Mapping, Tuple

from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.labels import CLASS_NAMES, LIGHT_CODES, TASKS
from signal_light_node.model.config import ModelConfig

#: Version of the graph interface and metadata below.
ONNX_FORMAT_VERSION = 1

#: The export of ``weights/default.pt`` shipped with the package.
DEFAULT_ONNX = Path(__file__).resolve().parent.parent / "weights" / "default.onnx"
#: The same export with int8 convolutions (``signal-light export --onnx OUT --int8``).
DEFAULT_ONNX_INT8 = DEFAULT_ONNX.with_name("default_int8.onnx")

CROPS_INPUT = "crops"
STATE_INPUT = "state"
STATE_OUTPUT = "state_out"
ATTENTION_OUTPUT = "attention"
#: Outputs in graph order.
OUTPUTS: Tuple[str, ...] = tuple(TASKS) + (STATE_OUTPUT, ATTENTION_OUTPUT)

KEY_FORMAT = "signal_light.format_version"
KEY_CONFIG = "signal_light.model_config"
KEY_STATE_SHAPES = "signal_light.state_shapes"
KEY_SOURCE = "signal_light.source"
KEY_SOURCE_SHA256 = "signal_light.source_sha256"
KEY_PACKAGE_VERSION = "signal_light.package_version"
#: JSON of how the file was quantised (absent: float32 weights throughout).
KEY_QUANTIZATION = "signal_light.quantization"

#: Opset of the export (onnxruntime 1.17+ runs it).
DEFAULT_OPSET = 17


def state_width(shapes: List[Tuple[int, ...]]) -> int:
    """Floats in a state row of tensors of these per-track shapes."""
    return sum(math.prod(shape) for shape in shapes)


def parse_metadata(meta: Mapping[str, str], path: "str | Path"
                   ) -> Tuple[ModelConfig, List[Tuple[int, ...]]]:
    """The model config and the per-track state shapes of an exported file.

    Args:
        meta: The file's ``metadata_props`` (onnxruntime: ``custom_metadata_map``).
        path: The file, for messages.

    Raises:
        CheckpointError: The metadata is missing, of another format version, or its
            config does not fit this code (class names, light codes).
    """
    hint = ("; export a checkpoint with `signal-light export --onnx OUT --weights CKPT`")
    if KEY_CONFIG not in meta:
        raise CheckpointError(f"ONNX model {path} has no signal_light metadata (not written by "
                              f"signal-light export){hint}")
    version = meta.get(KEY_FORMAT)
    if version != str(ONNX_FORMAT_VERSION):
        raise CheckpointError(f"ONNX model {path} has format version {version!r} but this code "
                              f"reads {ONNX_FORMAT_VERSION}{hint}")
    try:
        data = json.loads(meta[KEY_CONFIG])
        shapes = [tuple(int(v) for v in shape) for shape in json.loads(meta[KEY_STATE_SHAPES])]
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"ONNX model {path} has unreadable metadata: {exc}") from None
    try:
        config = ModelConfig.from_dict(data)
    except ConfigError as exc:
        raise CheckpointError(f"ONNX model {path}: {exc}") from None
    names = {t: tuple(config.class_names.get(t, ())) for t in TASKS}
    if names != {t: tuple(CLASS_NAMES[t]) for t in TASKS}:
        raise CheckpointError(f"ONNX model {path}: class names {names} differ from this code's "
                              f"{ {t: tuple(CLASS_NAMES[t]) for t in TASKS} }")
    if dict(config.light_codes) != dict(LIGHT_CODES):
        raise CheckpointError(f"ONNX model {path}: light codes {dict(config.light_codes)} differ "
                              f"from this code's {dict(LIGHT_CODES)}")
    if not shapes or len(shapes) % 2:
        raise CheckpointError(f"ONNX model {path}: state shapes {shapes} are not (h, c) pairs")
    return config, shapes


def precision_of(meta: Mapping[str, str]) -> str:
    """``int8`` for a quantised export, else ``fp32`` (from its metadata)."""
    return "int8" if KEY_QUANTIZATION in meta else "fp32"


def metadata(config: ModelConfig, shapes: List[Tuple[int, ...]],
             extra: Mapping[str, Any]) -> Dict[str, str]:
    """The ``metadata_props`` of an export (all values strings)."""
    out = {KEY_FORMAT: str(ONNX_FORMAT_VERSION),
           KEY_CONFIG: json.dumps(config.to_dict(), sort_keys=True),
           KEY_STATE_SHAPES: json.dumps([list(s) for s in shapes])}
    out.update({k: str(v) for k, v in extra.items()})
    return out
