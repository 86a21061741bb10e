"""The streaming model contract shared by training, evaluation and the online engine.

A light-state model is stepped once per frame for a batch of tracks. Everything a
track remembers between frames lives in an explicit :data:`State`, so the engine can
keep one state per track, gather the states of the tracks seen in a frame into one
batch, step them together and scatter the new states back. The helpers here do that
gathering and scattering; they only slice and concatenate tensors.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Dict, List, Protocol, Sequence, Tuple, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from signal_light_node.errors import ConfigError, CropError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from signal_light_node.model.config import ModelConfig

#: ``(h, c)`` per ConvLSTM layer, each ``[N, C, H, W]`` with the track in dimension 0.
State = Tuple[Tuple[Tensor, Tensor], ...]


@runtime_checkable
class LightStateModel(Protocol):
    """What the engine, the trainer and the evaluator need from a model."""

    config: "ModelConfig"
    input_size: int

    def initial_state(self, n: int) -> State:
        """State of ``n`` tracks that have not been seen yet."""
        ...

    def step(self, crops: Tensor, state: State) -> Tuple[Dict[str, Tensor], State]:
        """Advance ``N`` tracks by one frame.

        Args:
            crops: float32 ``[N, 3, S, S]`` in [0, 1], BGR channel order.
            state: The tracks' states, batch size ``N``.

        Returns:
            Probabilities ``[N, K]`` per task of ``labels.TASKS`` (rows sum to 1) and the
            new state.
        """
        ...

    def attention(self, crops: Tensor) -> Tensor:
        """Spatial attention mask ``[N, 1, S, S]`` in [0, 1] (for debug overlays)."""
        ...


def to_input(crops_uint8: np.ndarray) -> Tensor:
    """Turn uint8 crops as cut by ``crops.crop_vehicles`` into the model's input.

    Args:
        crops_uint8: ``[N, S, S, 3]`` uint8 BGR crops.

    Returns:
        float32 ``[N, 3, S, S]`` tensor in [0, 1], BGR channel order (stored
        channels-last; the shape and values are those of any NCHW tensor).

    Raises:
        CropError: The array is not ``[N, S, S, 3]`` uint8.
    """
    if not isinstance(crops_uint8, np.ndarray) or crops_uint8.dtype != np.uint8 \
            or crops_uint8.ndim != 4 or crops_uint8.shape[3] != 3 \
            or crops_uint8.shape[1] != crops_uint8.shape[2]:
        shape = getattr(crops_uint8, "shape", None)
        dtype = getattr(crops_uint8, "dtype", type(crops_uint8).__name__)
        raise CropError(f"model input must be [N, S, S, 3] uint8 crops, got shape {shape} "
                        f"dtype {dtype}")
    # The permuted HWC array already has channels-last strides, which the network's
    # convolutions run fastest on, so the only copy is the conversion to float.
    tensor = torch.from_numpy(np.ascontiguousarray(crops_uint8)).permute(0, 3, 1, 2)
    return tensor.to(torch.float32, memory_format=torch.channels_last).mul_(1.0 / 255.0)


def state_batch_size(state: State) -> int:
    """Number of tracks in ``state`` (0 for a state without layers)."""
    return int(state[0][0].shape[0]) if state else 0


def select_state(state: State, index: Tensor) -> State:
    """Rows ``index`` of every tensor of ``state`` (gather tracks from a batch).

    Args:
        state: A batched state.
        index: 1-D int64 tensor of row indices (repeats allowed).

    Returns:
        A new state whose batch size is ``len(index)``.
    """
    return tuple((h.index_select(0, index), c.index_select(0, index)) for h, c in state)


def concat_states(states: Sequence[State]) -> State:
    """Stack the states of several batches (or single tracks) into one batch.

    Args:
        states: States with the same number of layers and the same per-row shapes.

    Returns:
        The concatenated state, rows in the order given.

    Raises:
        ConfigError: ``states`` is empty or the states have different layer counts.
    """
    if not states:
        raise ConfigError("concat_states needs at least one state")
    n_layers = len(states[0])
    if any(len(s) != n_layers for s in states):
        raise ConfigError(f"cannot concatenate states with different layer counts "
                          f"{sorted({len(s) for s in states})}")
    if len(states) == 1:
        return states[0]
    return tuple((torch.cat([s[i][0] for s in states], 0), torch.cat([s[i][1] for s in states], 0))
                 for i in range(n_layers))


def split_state(state: State) -> List[State]:
    """Split a batched state into one state of batch size 1 per row.

    The rows are views of the batched tensors, so splitting copies nothing.

    Args:
        state: A batched state.

    Returns:
        ``N`` states, each with batch size 1.
    """
    n = state_batch_size(state)
    per_layer = [(h.split(1, 0), c.split(1, 0)) for h, c in state]
    return [tuple((hs[i], cs[i]) for hs, cs in per_layer) for i in range(n)]
