"""The model factory: architecture names -> builders (``config.arch`` picks one)."""

from __future__ import annotations

from typing import Callable, Dict, Tuple

from torch import nn

from signal_light_node.errors import ConfigError
from signal_light_node.model.config import ModelConfig

#: ``builder(config, pretrained)``: ``pretrained`` True loads what a fresh training run
#: starts from (the trunk's ImageNet weights); False leaves the initialisation to the
#: seed, as for a checkpoint whose weights are loaded next.
Builder = Callable[[ModelConfig, bool], nn.Module]
_REGISTRY: Dict[str, Builder] = {}


def register_arch(name: str, builder: Builder) -> None:
    """Make ``build_model`` build ``builder(config)`` for ``config.arch == name``."""
    _REGISTRY[name] = builder


def known_archs() -> Tuple[str, ...]:
    """Architecture names the factory can build."""
    return tuple(sorted(_REGISTRY))


def _build_convlstm_attention(config: ModelConfig, pretrained: bool) -> nn.Module:
    if config.encoder == "efficientnet_lite0":
        from signal_light_node.model.trunk_ensemble import TrunkEnsemble
        from signal_light_node.model.trunk_network import TrunkLightNet

        imagenet = pretrained and config.trunk_init == "imagenet"
        if config.members > 1:
            return TrunkEnsemble(config, pretrained=imagenet)
        return TrunkLightNet(config, pretrained=imagenet)
    from signal_light_node.model.network import LightStateNet

    return LightStateNet(config)


register_arch("convlstm_attention", _build_convlstm_attention)


def build_model(config: ModelConfig, pretrained: bool = False) -> nn.Module:
    """Build a freshly initialised model for ``config``.

    Args:
        config: The model configuration.
        pretrained: Start from pretrained parts where the config has them (a fresh
            training run); False for a model whose weights are loaded next.

    Raises:
        ConfigError: ``config.arch`` is not a registered architecture.
    """
    builder = _REGISTRY.get(config.arch)
    if builder is None:
        raise ConfigError(f"unknown model architecture {config.arch!r}; known: {list(known_archs())}")
    return builder(config, pretrained)
