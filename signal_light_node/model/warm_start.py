"""Start a model from another checkpoint's weights where its architecture grew.

Used to fine-tune a model whose config adds input channels (``temporal_input``) from
weights trained without them: every tensor whose name and shape match is copied; a
convolution weight that only gained input channels keeps the trained ones and gets, for
the new ones, zeros (the new model then computes exactly what the old one did) or small
random weights (``grown_scale`` times the spread of the trained ones). Zeros learn slowly:
from zero-filled evidence channels, 450 fine-tuning steps at lr 2e-4 left their weights
50 times smaller than the crop's, so the model had barely begun to use them.
"""

from __future__ import annotations

import logging
from typing import List, Mapping

import torch
from torch import Tensor, nn

from signal_light_node.errors import CheckpointError

LOG = logging.getLogger(__name__)


def _grown_input(ours: Tensor, theirs: Tensor) -> bool:
    return (ours.dim() == theirs.dim() == 4 and ours.shape[0] == theirs.shape[0]
            and ours.shape[2:] == theirs.shape[2:] and ours.shape[1] > theirs.shape[1])


def warm_start(model: nn.Module, state_dict: Mapping[str, Tensor],
               grown_scale: float = 0.0) -> List[str]:
    """Copy ``state_dict`` into ``model`` as far as it fits.

    Args:
        model: The new model (its own initialisation stays where nothing fits).
        state_dict: Weights of the old model.
        grown_scale: New input channels get normal weights with this share of the
            standard deviation of the trained ones; 0 gives zeros.

    Returns:
        Names of the tensors that gained input channels (zero-filled there).

    Raises:
        CheckpointError: A tensor of both exists with shapes that are neither equal nor
            grown input channels, or nothing at all could be copied.
    """
    ours = model.state_dict()
    grown: List[str] = []
    copied = 0
    with torch.no_grad():
        for name, value in state_dict.items():
            if name not in ours:
                continue
            target = ours[name]
            if target.shape == value.shape:
                target.copy_(value)
            elif _grown_input(target, value):
                target.normal_(0.0, float(value.float().std()) * grown_scale)
                target[:, :value.shape[1]].copy_(value)
                grown.append(name)
            else:
                raise CheckpointError(f"cannot warm-start {name}: shape {tuple(value.shape)} "
                                      f"does not fit {tuple(target.shape)}")
            copied += 1
    if copied == 0:
        raise CheckpointError("cannot warm-start: no tensor of the checkpoint fits the model")
    missing = sorted(set(ours) - set(state_dict))
    if missing:
        LOG.info("warm start: %d tensors keep their initialisation (%s ...)", len(missing),
                 ", ".join(missing[:3]))
    return grown
