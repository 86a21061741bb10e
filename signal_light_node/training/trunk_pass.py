"""The frozen trunk's pass over a track's crops, for the feature cache, in torch or onnxruntime.

Writing the caches is the trunk's only work in the temporal recipe, and on a CPU most of a
cache's time: one forward pass per frame of every pool, look and mirror. The same graph
in onnxruntime runs about three times faster there than torch eager (2-core AMD EPYC,
AVX2, one thread: 512 crops in 0.44 s against 1.42 s), so :func:`trunk_pass` can export
:meth:`TrunkLightNet.frame_features` once to a temporary ONNX file and run that. Its
outputs differ from torch's by float rounding only (about 1e-5 on the features, which
the cache then stores as float16).
"""

from __future__ import annotations

import logging
import tempfile
import warnings
from pathlib import Path
from typing import Callable, Tuple

import numpy as np
import torch
from torch import Tensor, nn

from signal_light_node.errors import ConfigError
from signal_light_node.model.interface import to_input

LOG = logging.getLogger(__name__)

#: The backends a cache's trunk pass runs on (``write_cache(backend=...)``).
PASS_BACKENDS = ("torch", "onnxruntime")

#: ``crops uint8 [N, S, S, 3] -> (features, maps)``, both float16 arrays.
TrunkPass = Callable[[np.ndarray], Tuple[np.ndarray, np.ndarray]]


class _FrameFeatures(nn.Module):
    """uint8 ``[N, S, S, 3]`` crops in, the network's per-frame features and lamp maps out,
    the crops converted as :func:`~signal_light_node.model.interface.to_input` does it (its
    array checks and memory layout are not graph operations)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, crops: Tensor) -> Tuple[Tensor, Tensor]:
        x = crops.permute(0, 3, 1, 2).float() * (1.0 / 255.0)
        return self.net.frame_features(x)


def _in_batches(crops: np.ndarray, batch: int,
                run: Callable[[np.ndarray], Tuple[np.ndarray, np.ndarray]]
                ) -> Tuple[np.ndarray, np.ndarray]:
    """``run`` over ``batch`` crops at a time; its outputs joined as float16."""
    feats, maps = [], []
    for start in range(0, len(crops), batch):
        f, m = run(crops[start:start + batch])
        feats.append(f.astype(np.float16, copy=False))
        maps.append(m.astype(np.float16, copy=False))
    return np.concatenate(feats), np.concatenate(maps)


def _torch_pass(net: nn.Module, batch: int) -> TrunkPass:
    device = next(net.parameters()).device

    @torch.inference_mode()
    def one(crops: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        f, m = net.frame_features(to_input(crops).to(device))
        return f.half().cpu().numpy(), m.half().cpu().numpy()
    return lambda crops: _in_batches(crops, batch, one)


def _onnx_pass(net: nn.Module, batch: int, threads: int) -> TrunkPass:
    try:
        import onnxruntime as ort
    except ImportError:
        raise ConfigError("a cache's onnxruntime pass needs the onnxruntime package "
                          "(pip install -r requirements.txt); or use the torch pass") from None
    size = int(net.config.input_size)
    example = torch.zeros((2, size, size, 3), dtype=torch.uint8)  # 2: keep the batch free
    with tempfile.TemporaryDirectory(prefix="trunk_pass_") as folder:
        path = Path(folder) / "frame_features.onnx"
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
            torch.onnx.export(_FrameFeatures(net).cpu().float().eval(), (example,), str(path),
                              dynamo=False, input_names=["crops"],
                              output_names=["features", "maps"],
                              dynamic_axes={k: {0: "frames"} for k in ("crops", "features",
                                                                       "maps")},
                              opset_version=17, do_constant_folding=True)
        options = ort.SessionOptions()
        options.intra_op_num_threads = max(1, int(threads))
        options.inter_op_num_threads = 1
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])

    def one(crops: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        f, m = session.run(None, {"crops": np.ascontiguousarray(crops)})
        return f, m
    return lambda crops: _in_batches(crops, batch, one)


def trunk_pass(net: nn.Module, backend: str = "torch", batch: int = 512, threads: int = 1
               ) -> TrunkPass:
    """The per-frame pass of ``net`` (an inference copy in eval mode) over uint8 crops.

    Args:
        net: The network whose :meth:`frame_features` is run.
        backend: ``torch`` (on the network's device) or ``onnxruntime`` (CPU; the graph
            exported once, here).
        batch: Crops per call.
        threads: onnxruntime's intra-op threads (torch keeps its own setting).

    Returns:
        ``crops [N, S, S, 3] uint8 -> (features [N, C, G, G], maps [N, K, G, G])`` float16.

    Raises:
        ConfigError: An unknown backend, or onnxruntime is not installed.
    """
    if backend not in PASS_BACKENDS:
        raise ConfigError(f"trunk pass backend must be one of {list(PASS_BACKENDS)}, "
                          f"got {backend!r}")
    if backend == "torch":
        return _torch_pass(net, batch)
    LOG.info("trunk pass in onnxruntime (%d thread(s))", threads)
    return _onnx_pass(net, batch, threads)
