"""The ``torch`` model backend: a ``LightStateModel`` (the network of a checkpoint) on a device.

The backend owns everything torch: the device, eval mode, ``torch.inference_mode``, the
uint8-to-float conversion of the crops and the state's layout. A track's state row is
every layer's ``h`` and ``c`` (and, with ``temporal_input``, the history) flattened
into one float row of a ``[M, W]`` tensor on the model's device, so a frame's states
are gathered with one ``index_select`` and stored with one ``index_copy_``.

Inference-only speed-ups live here and in :mod:`signal_light_node.model.inference`, never
in the network class that training shares: the step runs an inference copy of the model
(:func:`~signal_light_node.model.inference.inference_copy`: batch norms folded into the
convolutions before them, the attention's single-output conv as a depthwise conv and a
channel sum; the same function up to float rounding, as the ONNX export runs it), and on
the CPU the process keeps freed heap memory
(:func:`signal_light_node.runtime.memory.retain_freed_memory`) instead of faulting a
frame's tens of megabytes of activations in again every step.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Optional, Tuple

import numpy as np
import torch

from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.model.inference import inference_copy
from signal_light_node.model.interface import State, to_input
from signal_light_node.runtime.backend import StepOutput, check_device
from signal_light_node.runtime.memory import retain_freed_memory

LOG = logging.getLogger(__name__)


def require_device(device: "str | torch.device") -> torch.device:
    """The torch device, checked to be usable here.

    Raises:
        ConfigError: Not a torch device, or CUDA is asked for on a machine (or torch
            build) without it.
    """
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(f"device {device!r} is not a torch device: {exc}") from None
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"device must be 'cpu' or 'cuda[:N]', got {str(device)!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"CUDA requested but not available (device {str(device)!r}); "
                          "use device cpu")
    return device


@dataclass(frozen=True)
class _Layout:
    """Shapes of the per-track state tensors (without the batch axis) and their widths."""

    shapes: Tuple[torch.Size, ...]
    widths: Tuple[int, ...]


def flatten_state(state: State, n: int) -> torch.Tensor:
    """``[n, W]`` rows holding every layer's tensors of each track, in state order."""
    parts = [t.reshape(n, -1) for pair in state for t in pair]
    return torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]


class TorchBackend:
    """Runs a ``model.interface.LightStateModel`` with torch.

    Args:
        model: The model (``config``, ``initial_state``, ``step``; optionally
            ``step_with_attention``, ``attention``, ``to``, ``eval``); moved to
            ``device`` and put in eval mode. Steps run an ``inference_copy`` of it
            (``model.inference``), so later changes to its weights are not seen.
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        threads: torch intra-op threads (``torch.set_num_threads``, which is
            process-wide); None keeps torch's choice.
        source: The file the model came from, for messages.

    Raises:
        ConfigError: The device is not usable here.
    """

    name = "torch"
    #: Weight precision (checkpoints are float32).
    precision = "fp32"

    def __init__(self, model: Any, device: str = "cpu", threads: Optional[int] = None,
                 source: str = "") -> None:
        torch_device = require_device(check_device(device))
        if threads:
            torch.set_num_threads(int(threads))
            LOG.info("torch intra-op threads set to %d", threads)
        if hasattr(model, "to"):
            model = model.to(torch_device)
        if hasattr(model, "eval"):
            model.eval()
        if torch_device.type == "cpu":
            retain_freed_memory()
        self.model = model
        self.config = model.config
        self.input_size = int(getattr(model, "input_size", self.config.input_size))
        self.device = str(torch_device)
        self.source = str(source)
        self._device = torch_device
        #: What the steps run: the model's inference copy (``model.inference``).
        self._net = inference_copy(model)
        self._step_with_attention = getattr(self._net, "step_with_attention", None)
        self._attention = getattr(self._net, "attention", None)
        with torch.inference_mode():
            initial = self._net.initial_state(1)
        self._layout = _Layout(tuple(t.shape[1:] for pair in initial for t in pair),
                               tuple(t[0].numel() for pair in initial for t in pair))
        # A clone made outside inference mode can be written into and read anywhere.
        self._initial = flatten_state(initial, 1).to(torch_device).clone()

    @classmethod
    def from_file(cls, path: Optional[str] = None, device: str = "cpu",
                  threads: Optional[int] = None) -> "TorchBackend":
        """Load a checkpoint (None: the shipped ``weights/default.pt``).

        Raises:
            CheckpointError: The file is missing, unreadable or incompatible.
            ConfigError: The device is not usable here.
        """
        from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint

        require_device(check_device(device))  # before loading: torch would blame the file
        path = str(DEFAULT_WEIGHTS if path is None else path)
        if path.lower().endswith(".onnx"):
            raise CheckpointError(f"{path} is an ONNX export; run it with backend onnxruntime "
                                  "(backend torch loads a .pt checkpoint)")
        loaded = load_checkpoint(path, map_location=device)
        return cls(loaded.model, device=device, threads=threads, source=path)

    # ------------------------------------------------------------------ the step
    @property
    def state_width(self) -> int:
        """Floats per track row."""
        return int(self._initial.shape[1])

    def initial_state(self, n: int) -> State:
        """The state of ``n`` new tracks."""
        return self._unflatten(self._initial.expand(n, -1))

    def step(self, crops: np.ndarray, state: State, *, attention: bool = False) -> StepOutput:
        """One batched step (see ``runtime.backend.ModelBackend.step``).

        Raises:
            CropError: ``crops`` is not ``[N, S, S, 3]`` uint8 of the model's size.
        """
        masks = None
        with torch.inference_mode():
            x = to_input(crops).to(self._device)
            if attention and self._step_with_attention is not None:
                probs, new_state, mask = self._step_with_attention(x, state)
                masks = _masks(mask)
            else:
                probs, new_state = self._net.step(x, state)
            out = {t: probs[t].detach().float().cpu().numpy() for t in TASKS}
        return StepOutput(out, new_state, masks)

    def attention(self, crops: np.ndarray) -> Optional[np.ndarray]:
        """Attention masks of uint8 crops, float32 ``[N, S, S]``; None without attention."""
        if self._attention is None:
            return None
        with torch.inference_mode():
            return _masks(self._attention(to_input(crops).to(self._device)))

    # ---------------------------------------------------------------- the rows
    def new_rows(self, n: int) -> torch.Tensor:
        """``[n, W]`` rows on the device, each the initial state."""
        with torch.no_grad():
            return self._initial.repeat(n, 1)

    def gather_rows(self, rows: torch.Tensor, index: np.ndarray) -> State:
        """The state of rows ``index`` (one ``index_select``)."""
        with torch.inference_mode():
            return self._unflatten(rows.index_select(0, self._index(index)))

    def store_rows(self, rows: torch.Tensor, index: np.ndarray, state: State,
                   select: Optional[np.ndarray] = None) -> None:
        """Write ``state`` (its rows ``select``) into rows ``index`` (one ``index_copy_``)."""
        with torch.inference_mode():
            flat = flatten_state(state, int(state[0][0].shape[0]))
            if select is not None:
                flat = flat.index_select(0, self._index(select))
            rows.index_copy_(0, self._index(index), flat.to(rows.dtype))

    def reset_rows(self, rows: torch.Tensor, index: np.ndarray) -> None:
        """Set rows ``index`` to the initial state."""
        with torch.inference_mode():
            rows[self._index(index)] = self._initial

    # ---------------------------------------------------------------- internals
    def _index(self, index: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(index, dtype=np.int64)).to(self._device)

    def _unflatten(self, rows: torch.Tensor) -> State:
        n = rows.shape[0]
        parts = torch.split(rows, self._layout.widths, dim=1)
        tensors = [p.reshape(n, *shape) for p, shape in zip(parts, self._layout.shapes)]
        return tuple((tensors[i], tensors[i + 1]) for i in range(0, len(tensors), 2))


def _masks(mask: torch.Tensor) -> np.ndarray:
    """``[N, 1, S, S]`` (or ``[N, S, S]``) masks as contiguous float32 ``[N, S, S]``."""
    array = mask.detach().float().cpu().numpy()
    return np.ascontiguousarray(array.reshape(array.shape[0], *array.shape[-2:]),
                                dtype=np.float32)
