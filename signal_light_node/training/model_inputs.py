"""What the model is given each training step: float crops, and the lanes' carried state."""

from __future__ import annotations

from typing import Optional

import torch

from signal_light_node.model import to_input
from signal_light_node.model.interface import State, state_batch_size


def batch_input(crops: torch.Tensor, device: torch.device) -> torch.Tensor:
    """uint8 ``[B, T, S, S, 3]`` crops -> float ``[B, T, 3, S, S]`` via :func:`model.to_input`."""
    b, t, s = crops.shape[0], crops.shape[1], crops.shape[2]
    x = to_input(crops.reshape(b * t, s, s, 3).numpy())
    return x.reshape(b, t, 3, s, s).to(device, non_blocking=True)


class LaneState:
    """The recurrent state of ``--mode lanes``, carried from one step to the next.

    Each lane plays one track after another (:class:`.track_batches.LaneBatches`); its
    state goes on where the last step left it and starts from zero with a new track.
    Back-propagation is truncated at the step boundary.

    Attributes:
        carried: float32 state of the lanes after the last step (None before the first).
    """

    def __init__(self) -> None:
        self.carried: Optional[State] = None

    def begin(self, reset: Optional[torch.Tensor], model: torch.nn.Module,
              device: torch.device) -> Optional[State]:
        """The state a step starts from, zeroed where a lane starts a new track.

        Args:
            reset: bool ``[lanes]``, True where a lane takes a new track (None: no lanes).
            model: The model (its ``initial_state`` when the lanes are new).
            device: The training device.

        Returns:
            None without lanes, else the state to feed the model.
        """
        if reset is None:
            return None
        reset = reset.to(device)
        if self.carried is None or state_batch_size(self.carried) != reset.numel():
            return model.initial_state(int(reset.numel()))
        keep = (~reset).to(self.carried[0][0].dtype).view(-1, 1, 1, 1)
        return tuple((h * keep, c * keep) for h, c in self.carried)

    def keep(self, new_state: State) -> None:
        """Carry ``new_state`` to the next step: detached, in float32 (also under bf16)."""
        self.carried = tuple((h.detach().float(), c.detach().float()) for h, c in new_state)
