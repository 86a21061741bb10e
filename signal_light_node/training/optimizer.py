"""The optimiser: Adam with L2 weight decay on the dense layers' weights only."""

from __future__ import annotations

from typing import Any, Dict, List

import torch
from torch import nn


def dense_parameter_groups(model: nn.Module, weight_decay: float) -> List[Dict[str, Any]]:
    """Adam parameter groups: weight decay on ``nn.Linear`` weights, none elsewhere.

    Frozen parameters (``requires_grad`` False) are left out.
    """
    decay, plain = [], []
    dense_weights = {id(m.weight) for m in model.modules() if isinstance(m, nn.Linear)}
    for p in model.parameters():
        if not p.requires_grad:
            continue
        (decay if id(p) in dense_weights else plain).append(p)
    return [{"params": decay, "weight_decay": weight_decay},
            {"params": plain, "weight_decay": 0.0}]


def build_optimizer(model: nn.Module, lr: float, weight_decay: float) -> torch.optim.Adam:
    """Adam over ``model``'s trainable parameters (:func:`dense_parameter_groups`)."""
    return torch.optim.Adam(dense_parameter_groups(model, weight_decay), lr=lr)
