"""The light-state model: config (`config`), factory (`registry`), network, streaming
interface and checkpoint file I/O (`checkpoint`)."""

from signal_light_node.model.checkpoint import (
    DEFAULT_WEIGHTS,
    FORMAT_VERSION,
    LoadedModel,
    load_checkpoint,
    save_checkpoint,
)
from signal_light_node.model.config import ModelConfig
from signal_light_node.model.registry import build_model, known_archs, register_arch
from signal_light_node.model.interface import (
    LightStateModel,
    State,
    concat_states,
    select_state,
    split_state,
    state_batch_size,
    to_input,
)
from signal_light_node.model.network import LightStateNet

__all__ = [
    "DEFAULT_WEIGHTS",
    "FORMAT_VERSION",
    "LightStateModel",
    "LightStateNet",
    "LoadedModel",
    "ModelConfig",
    "State",
    "build_model",
    "concat_states",
    "known_archs",
    "load_checkpoint",
    "register_arch",
    "save_checkpoint",
    "select_state",
    "split_state",
    "state_batch_size",
    "to_input",
]
