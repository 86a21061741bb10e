"""Several recurrent parts over one shared trunk, their logits averaged.

Two runs of the same recipe that differ only in their seed disagree on the generators
they were not trained on by as much as any change of the recipe moves them (docs/model.md,
"What a seed moves, and more tracks"); the average of their outputs beats either and
publishes fewer changes. The trunk is frozen while the rest is trained, so every member
of such a family sees the same per-frame features: the trunk runs once per step and only
the recurrent parts (``TrunkLightNet`` without its trunk) run once per member.

The state is the members' states one after the other, each a tuple of pairs, so the
state bank, the backends and the ONNX export carry it as they carry one member's.
Temperatures apply to the averaged logits (the members' own are 1).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn

from signal_light_node.errors import ConfigError
from signal_light_node.model.interface import State
from signal_light_node.model.network import calibrated_logits
from signal_light_node.model.trunk_network import TrunkFront, TrunkLightNet

if TYPE_CHECKING:  # pragma: no cover - typing only
    from signal_light_node.model.config import ModelConfig


def member_config(config: "ModelConfig") -> "ModelConfig":
    """The config of one member: the same model, alone, without temperatures or ON offsets."""
    return config.replace(members=1, temperatures={}, on_offsets={})


class TrunkEnsemble(TrunkFront):
    """``config.members`` recurrent parts over one trunk (module doc).

    Implements :class:`signal_light_node.model.interface.LightStateModel`.
    """

    def __init__(self, config: "ModelConfig", pretrained: bool = False) -> None:
        if config.members < 2:
            raise ConfigError(f"a trunk ensemble needs members >= 2, got {config.members}")
        super().__init__(config, pretrained)
        one = member_config(config)
        self.members = nn.ModuleList(TrunkLightNet(one, with_trunk=False)
                                     for _ in range(config.members))
        self._sizes = [m.state_layers() for m in self.members]

    def _split(self, state: State) -> List[State]:
        """The members' parts of an ensemble state."""
        parts, start = [], 0
        for size in self._sizes:
            parts.append(tuple(state[start:start + size]))
            start += size
        return parts

    def initial_state(self, n: int) -> State:
        """Zero state for ``n`` new tracks: every member's, one after the other."""
        return tuple(pair for m in self.members for pair in m.initial_state(n))

    def state_layers(self) -> int:
        """Number of ``(a, b)`` pairs in a track's state: every member's."""
        return sum(self._sizes)

    def output_layers(self, task: str) -> List[nn.Module]:
        """The layers whose logits are averaged into ``task``'s: every member's head (an
        offset added to each moves the mean by as much)."""
        return [layer for m in self.members for layer in m.output_layers(task)]

    def _average(self, outputs: List[Dict[str, Tensor]]) -> Dict[str, Tensor]:
        mean = {k: torch.stack([o[k] for o in outputs]).mean(0) for k in outputs[0]}
        return calibrated_logits(mean, self.config)

    def _run_members(self, run: Callable[[nn.Module, Optional[State]],
                                         Tuple[Dict[str, Tensor], State]],
                     state: Optional[State]) -> Tuple[Dict[str, Tensor], State]:
        """``run(member, its part of state)`` for every member: mean logits, new state."""
        parts = self._split(state) if state is not None else [None] * len(self.members)
        outputs, new_state = [], []
        for member, part in zip(self.members, parts):
            logits, part = run(member, part)
            outputs.append(logits)
            new_state.extend(part)
        return self._average(outputs), tuple(new_state)

    def step_features(self, features: Tensor, maps: Tensor, state: State
                      ) -> Tuple[Dict[str, Tensor], State]:
        """One frame from per-frame features: the members' mean logits and the new state."""
        return self._run_members(lambda m, part: m.step_features(features, maps, part), state)

    def sequence_features(self, features: Tensor, maps: Tensor, state: Optional[State] = None
                          ) -> Tuple[Dict[str, Tensor], State]:
        """``T`` frames from per-frame features ``[N, T, ...]``: mean logits, new state."""
        return self._run_members(lambda m, part: m.sequence_features(features, maps, part),
                                 state)
