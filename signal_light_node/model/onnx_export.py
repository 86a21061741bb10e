"""Export a checkpoint's batched step to ONNX (``signal-light export --onnx``).

The graph is the network's ``step_with_attention`` wrapped so that it takes what the
engine has (uint8 crops, flattened state rows) and gives what the engine wants
(probabilities, flattened new states, the attention masks); its interface and metadata
are described in :mod:`signal_light_node.model.onnx_format`. What is traced is the
network's inference copy (:func:`signal_light_node.model.inference.inference_copy`, as the
torch backend runs it): batch norms folded, the attention's single-output conv as a
depthwise conv and a channel sum. The export is traced with
torch's TorchScript-based exporter (no extra packages) with a dynamic batch axis, then
checked: a few steps of synthetic tracks through onnxruntime must match torch.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, List, Optional, Tuple

import numpy as np
import torch
from torch import Tensor, nn

from signal_light_node import __version__
from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.model import onnx_format as fmt

LOG = logging.getLogger(__name__)

#: Largest difference between torch and onnxruntime the export check accepts.
VERIFY_TOLERANCE = 1e-4


class _OnnxStep(nn.Module):
    """The network's step with the engine's inputs and outputs (see ``onnx_format``)."""

    def __init__(self, net: nn.Module, shapes: List[Tuple[int, ...]]) -> None:
        super().__init__()
        self.net = net
        self.shapes = [tuple(s) for s in shapes]

    def forward(self, crops: Tensor, state: Tensor) -> Tuple[Tensor, ...]:
        # As model.interface.to_input: HWC uint8 -> CHW float in [0, 1].
        x = crops.permute(0, 3, 1, 2).to(torch.float32) * (1.0 / 255.0)
        tensors = []
        offset = 0
        for shape in self.shapes:
            width = int(np.prod(shape))
            tensors.append(state[:, offset:offset + width].reshape((-1,) + shape))
            offset += width
        pairs = tuple((tensors[i], tensors[i + 1]) for i in range(0, len(tensors), 2))
        probs, new_state, mask = self.net.step_with_attention(x, pairs)
        flat = torch.cat([t.flatten(1) for pair in new_state for t in pair], 1)
        return tuple(probs[t] for t in TASKS) + (flat, mask[:, 0])


@dataclass(frozen=True)
class ExportReport:
    """What :func:`export_onnx` wrote.

    Attributes:
        path: The ``.onnx`` file.
        size_bytes: Its size.
        checkpoint: The checkpoint exported.
        max_abs_diff: Largest torch-vs-onnxruntime difference of the check (None when
            not checked).
    """

    path: Path
    size_bytes: int
    checkpoint: Path
    max_abs_diff: Optional[float]


@contextlib.contextmanager
def _static_head_pool(config: Any, opset: int) -> Iterator[None]:
    """Export ``adaptive_avg_pool2d`` (the heads' pool to ``head_grid``) as a fixed pool.

    The tracer loses the spatial size of the ConvLSTM map behind the temporal evidence's
    gathers (their shapes are traced as dynamic), and the stock symbolic needs it. The
    config knows it: ``feature_size`` pooled to ``head_grid`` is an ``AveragePool`` of
    kernel and stride ``feature_size / head_grid``, the same averages.

    Raises:
        ConfigError: ``head_grid`` does not divide ``feature_size``.
    """
    side, grid = config.feature_size, config.head_grid
    if side % grid:
        raise ConfigError(f"the ONNX export needs head_grid ({grid}) to divide the feature map "
                          f"side ({side})")
    kernel = side // grid

    def symbolic(g: Any, x: Any, output_size: Any) -> Any:
        return g.op("AveragePool", x, kernel_shape_i=[kernel, kernel],
                    strides_i=[kernel, kernel])

    torch.onnx.register_custom_op_symbolic("aten::adaptive_avg_pool2d", symbolic, opset)
    try:
        yield
    finally:
        torch.onnx.unregister_custom_op_symbolic("aten::adaptive_avg_pool2d", opset)


def publish_file(tmp: "str | Path", output: "str | Path") -> None:
    """Give a finished temporary file the usual permissions and rename it to ``output``.

    mkstemp's 0600 would make a shipped file private; the process's umask decides.
    """
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, output)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def state_shapes(model: Any) -> List[Tuple[int, ...]]:
    """Per-track shapes of the model's state tensors, in state order.

    Raises:
        ConfigError: The model's initial state is not all zeros (the exported graph
            assumes a new track's row is zeros).
    """
    with torch.inference_mode():
        initial = model.initial_state(1)
    tensors = [t for pair in initial for t in pair]
    if any(bool(t.abs().max() > 0) for t in tensors if t.numel()):
        raise ConfigError("the ONNX export needs a model whose initial state is all zeros")
    return [tuple(int(v) for v in t.shape[1:]) for t in tensors]


def export_onnx(output: "str | Path", weights: "str | Path | None" = None,
                opset: int = fmt.DEFAULT_OPSET, verify: bool = True) -> ExportReport:
    """Export a checkpoint's step to an ONNX file with its config in the metadata.

    Args:
        output: The ``.onnx`` file to write (replaced if it exists; parents created).
        weights: The checkpoint; None for the shipped ``weights/default.pt``.
        opset: ONNX opset version.
        verify: Run a few synthetic steps through torch and onnxruntime and refuse a
            file whose outputs differ by more than ``VERIFY_TOLERANCE``.

    Returns:
        The report.

    Raises:
        CheckpointError: The checkpoint cannot be loaded, the export fails, or the check
            finds a difference.
        ConfigError: The ``onnx`` package is missing or the model cannot be exported.
    """
    from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint

    try:
        import onnx
    except ImportError:
        raise ConfigError("signal-light export --onnx needs the onnx package "
                          "(pip install -r requirements.txt)") from None
    weights = Path(DEFAULT_WEIGHTS if weights is None else weights)
    output = Path(output)
    from signal_light_node.model.inference import inference_copy

    loaded = load_checkpoint(weights)
    reference = loaded.model.float().eval()
    net = inference_copy(reference)
    shapes = state_shapes(net)
    size = loaded.config.input_size
    n = 2  # not 1: a batch of one invites the tracer to bake the batch size in
    crops = torch.zeros((n, size, size, 3), dtype=torch.uint8)
    state = torch.zeros((n, fmt.state_width(shapes)), dtype=torch.float32)
    dynamic = {name: {0: "tracks"} for name in (fmt.CROPS_INPUT, fmt.STATE_INPUT) + fmt.OUTPUTS}
    output.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=output.name + ".", suffix=".tmp", dir=output.parent)
    os.close(fd)
    try:
        with warnings.catch_warnings(), _static_head_pool(loaded.config, int(opset)):
            # The shape checks inside step are Python comparisons the tracer warns about;
            # the legacy exporter's deprecation notice is not the user's concern.
            warnings.simplefilter("ignore")
            with torch.no_grad():
                torch.onnx.export(_OnnxStep(net, shapes), (crops, state), tmp, dynamo=False,
                                  input_names=[fmt.CROPS_INPUT, fmt.STATE_INPUT],
                                  output_names=list(fmt.OUTPUTS), dynamic_axes=dynamic,
                                  opset_version=int(opset), do_constant_folding=True)
        proto = onnx.load(tmp)
        props = fmt.metadata(loaded.config, shapes, {
            fmt.KEY_SOURCE: weights.name, fmt.KEY_SOURCE_SHA256: _sha256(weights),
            fmt.KEY_PACKAGE_VERSION: __version__})
        del proto.metadata_props[:]
        for key, value in props.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        proto.producer_name = "signal_light_node"
        proto.doc_string = (f"signal_light_node light-state step exported from {weights.name}; "
                            "see signal_light_node/model/onnx_format.py")
        onnx.checker.check_model(proto)
        onnx.save(proto, tmp)
        diff = verify_export(tmp, reference) if verify else None
        publish_file(tmp, output)
    except (RuntimeError, ValueError, TypeError, onnx.checker.ValidationError) as exc:
        raise CheckpointError(f"cannot export {weights} to ONNX: {exc}") from exc
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    report = ExportReport(output, output.stat().st_size, weights, diff)
    LOG.info("exported %s to %s (%.2f MB%s)", weights, output, report.size_bytes / 1e6,
             "" if diff is None else f", max |torch - onnxruntime| {diff:.2e}")
    return report


def synthetic_tracks(size: int, n: int, frames: int, seed: int = 0) -> List[np.ndarray]:
    """uint8 ``[n, S, S, 3]`` crops of ``frames`` frames: smooth blobs that drift and blink,
    so the temporal evidence's alignment and differences are exercised."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    base = rng.uniform(30, 120, (n, 1, 1, 3)).astype(np.float32)
    centres = rng.uniform(0.25 * size, 0.75 * size, (n, 2)).astype(np.float32)
    out = []
    for f in range(frames):
        drift = rng.integers(-2, 3, (n, 2)).astype(np.float32)
        centres = centres + drift
        lit = (rng.random(n) < 0.5).astype(np.float32)[:, None, None, None]
        d2 = (yy[None] - centres[:, 0, None, None]) ** 2 + (xx[None] - centres[:, 1, None, None]) ** 2
        blob = np.exp(-d2 / (2 * (0.08 * size) ** 2))[..., None] * np.float32([40, 60, 200])
        noise = rng.normal(0, 4, (n, size, size, 3))
        out.append(np.clip(base + blob * (0.3 + 0.7 * lit) + noise, 0, 255).astype(np.uint8))
    return out


def verify_export(path: "str | Path", net: nn.Module, n: int = 5, frames: int = 4) -> float:
    """Step synthetic tracks through torch and the ONNX file; the largest difference.

    Raises:
        CheckpointError: A probability, state or attention value differs by more than
            ``VERIFY_TOLERANCE``.
        ConfigError: onnxruntime is not installed.
    """
    from signal_light_node.model.backends.onnx_backend import OnnxRuntimeBackend
    from signal_light_node.model.backends.torch_backend import TorchBackend

    reference = TorchBackend(net)
    exported = OnnxRuntimeBackend(str(path))
    a, b = reference.initial_state(n), exported.initial_state(n)
    worst = 0.0
    for crops in synthetic_tracks(net.config.input_size, n, frames):
        out_a = reference.step(crops, a, attention=True)
        out_b = exported.step(crops, b, attention=True)
        a, b = out_a.state, out_b.state
        rows = reference.new_rows(n)
        reference.store_rows(rows, np.arange(n), a)
        pairs = [(out_a.probs[t], out_b.probs[t]) for t in TASKS]
        pairs += [(rows.numpy(), b), (out_a.attention, out_b.attention)]
        worst = max([worst] + [float(np.max(np.abs(x - y))) for x, y in pairs])
    if worst > VERIFY_TOLERANCE:
        raise CheckpointError(f"the ONNX export {path} differs from torch by {worst:.2e} "
                              f"(> {VERIFY_TOLERANCE:g})")
    return worst
