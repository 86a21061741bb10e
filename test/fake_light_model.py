"""A deterministic stand-in for the light-state model, for engine and replay tests.

Its outputs expose what the engine did with the recurrent state:

* brake P(ON) follows the brightness of the current crop (0.9 * mean pixel value);
* left P(ON) grows with the number of steps the track's state has seen
  (0.9 * n / (n + 4)), so a reset shows up as a drop;
* right P(ON) is 0.9 times the running mean brightness over those steps.

The state has two "layers" of different shapes so that flattening and splitting
in the state bank are exercised.
"""

from __future__ import annotations

from typing import Dict, List, Tuple

import torch

from signal_light_node.model.config import ModelConfig

State = Tuple[Tuple[torch.Tensor, torch.Tensor], ...]


def _light(p_on: torch.Tensor) -> torch.Tensor:
    p_on = p_on.clamp(0.0, 1.0) * 0.9
    return torch.stack([0.9 - p_on, p_on, torch.full_like(p_on, 0.1)], dim=1)


class FakeLightModel:
    """Implements the ``LightStateModel`` protocol without any learning."""

    def __init__(self, input_size: int = 16) -> None:
        self.config = ModelConfig(input_size=input_size)
        self.input_size = input_size
        self.batch_sizes: List[int] = []

    @property
    def calls(self) -> int:
        return len(self.batch_sizes)

    def initial_state(self, n: int) -> State:
        return ((torch.zeros(n, 1, 2, 2), torch.zeros(n, 1, 2, 2)),
                (torch.zeros(n, 2, 1, 1), torch.zeros(n, 2, 1, 1)))

    def step(self, crops: torch.Tensor, state: State) -> Tuple[Dict[str, torch.Tensor], State]:
        n = crops.shape[0]
        assert crops.dtype == torch.float32 and crops.shape[1:] == (3, self.input_size,
                                                                    self.input_size)
        assert all(t.shape[0] == n for pair in state for t in pair)
        self.batch_sizes.append(n)
        brightness = crops.mean(dim=(1, 2, 3))
        steps = state[1][0][:, 0, 0, 0] + 1.0
        total = state[1][1][:, 0, 0, 0] + brightness
        phase = torch.remainder(steps, 5.0)
        intent = torch.softmax(-(torch.arange(5.0)[None, :] - phase[:, None]).abs() * 3.0, dim=1)
        view = torch.softmax(brightness[:, None] * torch.arange(4.0)[None, :] * 4.0, dim=1)
        probs = {"intent": intent, "brake": _light(brightness),
                 "left": _light(steps / (steps + 4.0)), "right": _light(total / steps),
                 "view": view}
        h0 = state[0][0] + brightness[:, None, None, None]
        # layer 1: h holds the step count, c the summed brightness (both in channel 0)
        new_state = ((h0, state[0][1] + 1.0),
                     (torch.stack([steps, steps], 1)[:, :, None, None],
                      torch.stack([total, total], 1)[:, :, None, None]))
        return probs, new_state

    def attention(self, crops: torch.Tensor) -> torch.Tensor:
        return crops.mean(dim=1, keepdim=True)


def state_of(values, model: "FakeLightModel | None" = None):
    """A batched state of ``model`` (a FakeLightModel by default) whose every element of
    row i equals values[i]."""
    template = (model or FakeLightModel()).initial_state(len(values))
    v = torch.tensor(values, dtype=torch.float32)
    return tuple(tuple(torch.ones_like(t) * v.view(-1, *([1] * (t.dim() - 1))) for t in pair)
                 for pair in template)


def row_values(state) -> List[float]:
    """Per row, the single value all its elements hold (asserts they agree)."""
    out = []
    for i in range(state[0][0].shape[0]):
        vals = torch.cat([t[i].flatten() for pair in state for t in pair])
        assert torch.all(vals == vals[0]), vals
        out.append(float(vals[0]))
    return out
