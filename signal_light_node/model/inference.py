"""Inference-only rewrites of a trained network: the same function, cheaper to run.

Training and inference share the network class (``model/network.py``), so nothing here
touches it: :func:`inference_copy` rewrites a deep copy, which the torch backend steps
and the ONNX export traces. Each rewrite computes the same function; only the order of
float additions changes (outputs agree to ~1e-6):

* a ``Conv2d`` followed by an eval-mode ``BatchNorm2d`` becomes one conv with the
  norm's affine map in its weight and bias (``torch.nn.utils.fusion.fuse_conv_bn_eval``);
* a ``Conv2d`` of several input channels to ONE output channel (the attention FCN's last
  layer) becomes :class:`ChannelSumConv`: a depthwise conv and a sum over the channels.
  Blocked conv kernels (oneDNN, onnxruntime's NCHWc) pad a single output channel to a
  whole block of 8 and do 8x the work; measured at 32 tracks on the 2-core AVX2 machine,
  the step took 0.94-0.95 x the time in onnxruntime and 0.97 x in torch.
"""

from __future__ import annotations

import copy
from typing import Any, List, Tuple

import torch
from torch import Tensor, nn


class ChannelSumConv(nn.Module):
    """A ``C -> 1`` convolution computed as a depthwise conv summed over the channels.

    Args:
        conv: The ``Conv2d`` to replace (one output channel, ``groups=1``, zero
            padding); its weight and bias are copied.
    """

    def __init__(self, conv: nn.Conv2d) -> None:
        super().__init__()
        channels = conv.in_channels
        self.depthwise = nn.Conv2d(channels, channels, conv.kernel_size, stride=conv.stride,
                                   padding=conv.padding, dilation=conv.dilation,
                                   groups=channels, bias=False)
        with torch.no_grad():
            self.depthwise.weight.copy_(conv.weight.reshape(channels, 1, *conv.kernel_size))
        bias = conv.bias.detach().clone() if conv.bias is not None else \
            torch.zeros(1, dtype=conv.weight.dtype, device=conv.weight.device)
        self.register_buffer("bias", bias.reshape(1, 1, 1, 1))

    def forward(self, x: Tensor) -> Tensor:
        return self.depthwise(x).sum(1, keepdim=True) + self.bias


def _is_single_output_conv(module: nn.Module) -> bool:
    return type(module) is nn.Conv2d and module.out_channels == 1 and module.in_channels > 1 \
        and module.groups == 1 and module.padding_mode == "zeros" \
        and isinstance(module.padding, tuple)


def _foldable_pairs(model: nn.Module) -> List[Tuple[nn.Sequential, int, int]]:
    """``(container, conv index, norm index)`` of every ``Conv2d`` directly followed by an
    eval-mode ``BatchNorm2d`` with running statistics, inside an ``nn.Sequential``."""
    pairs = []
    for container in model.modules():
        if not isinstance(container, nn.Sequential):
            continue
        children = list(container.children())
        for i in range(len(children) - 1):
            conv, norm = children[i], children[i + 1]
            if type(conv) is nn.Conv2d and type(norm) is nn.BatchNorm2d \
                    and norm.track_running_stats and norm.running_mean is not None \
                    and conv.out_channels == norm.num_features:
                pairs.append((container, i, i + 1))
    return pairs


def _single_output_convs(model: nn.Module) -> List[Tuple[nn.Sequential, int]]:
    """``(container, index)`` of every single-output ``Conv2d`` inside an ``nn.Sequential``."""
    return [(container, i) for container in model.modules()
            if isinstance(container, nn.Sequential)
            for i, child in enumerate(container.children()) if _is_single_output_conv(child)]


def _like(new: nn.Module, old: nn.Conv2d) -> nn.Module:
    """``new`` in ``old``'s memory format (channels-last stays channels-last)."""
    weight = old.weight
    if weight.is_contiguous(memory_format=torch.channels_last) and not weight.is_contiguous():
        return new.to(memory_format=torch.channels_last)
    return new


def inference_copy(model: Any) -> Any:
    """A deep copy of ``model`` with the rewrites of the module doc applied, in eval mode.

    The model itself is left alone. A model with nothing to rewrite, one in training
    mode, or one that is not an ``nn.Module`` is returned as it is.

    Args:
        model: The model, in eval mode.

    Returns:
        The rewritten copy, or ``model``.
    """
    if not isinstance(model, nn.Module) or model.training \
            or not (_foldable_pairs(model) or _single_output_convs(model)):
        return model
    out = copy.deepcopy(model)
    for container, i, j in _foldable_pairs(out):
        conv, norm = container[i], container[j]
        with torch.no_grad():
            container[i] = _like(torch.nn.utils.fusion.fuse_conv_bn_eval(conv, norm), conv)
        container[j] = nn.Identity()
    for container, i in _single_output_convs(out):
        container[i] = _like(ChannelSumConv(container[i]), container[i])
    return out.eval()
