"""The learning-rate schedule: plateau drops, and an optional cosine decay at the end.

``ReduceLROnPlateau`` on the validation loss sets the rate the optimiser keeps; with
``TrainOptions.anneal_fraction`` each step is taken at a lower, annealed rate over the
last part of the run's budget (:func:`annealed_lr`), which the plateau schedule never
sees, for runs that end by their budget while the loss still falls.
"""

from __future__ import annotations

import math
from typing import Optional

import torch


def plateau_scheduler(optimizer: torch.optim.Optimizer, patience: int, factor: float,
                      min_lr: float) -> torch.optim.lr_scheduler.ReduceLROnPlateau:
    """The rate drops by ``factor`` after ``patience`` validations without improvement."""
    return torch.optim.lr_scheduler.ReduceLROnPlateau(
        optimizer, mode="min", factor=factor, patience=patience, threshold=1e-3,
        min_lr=min_lr)


def annealed_lr(lr: float, progress: float, fraction: float, min_lr: float) -> float:
    """The learning rate after the final cosine decay of ``TrainOptions.anneal_fraction``.

    Args:
        lr: The plateau schedule's learning rate.
        progress: Share of the run's budget used so far (0 at the start, 1 at the end).
        fraction: Final share of the budget over which the rate decays (0: never).
        min_lr: The rate at the end of the budget (never raised above ``lr``).

    Returns:
        ``lr`` before the last ``fraction`` of the budget, then a cosine from ``lr`` down to
        ``min_lr``.
    """
    if fraction <= 0 or lr <= min_lr:
        return lr
    into = min(1.0, max(0.0, (progress - (1.0 - fraction)) / fraction))
    return min_lr + (lr - min_lr) * 0.5 * (1.0 + math.cos(math.pi * into))


def budget_progress(elapsed: float, budget: float, step: int,
                    max_steps: Optional[int]) -> float:
    """Share of a run's budget used: its seconds or its steps, whichever ends it first.

    Args:
        elapsed: Seconds this invocation has run.
        budget: Seconds it may run (``math.inf``: no limit).
        step: Steps taken in total.
        max_steps: Steps the run ends at (None or 0: no limit).
    """
    shares = [elapsed / budget] if math.isfinite(budget) else []
    if max_steps:
        shares.append(step / max_steps)
    return max(shares, default=0.0)


def annealed_step(optimizer: torch.optim.Optimizer, progress: float, fraction: float,
                  min_lr: float) -> float:
    """One optimiser step at the annealed rate; the scheduled rates are restored after it.

    Returns:
        The rate of the step (of the first parameter group).
    """
    scheduled = [group["lr"] for group in optimizer.param_groups]
    for group, lr in zip(optimizer.param_groups, scheduled):
        group["lr"] = annealed_lr(lr, progress, fraction, min_lr)
    used = optimizer.param_groups[0]["lr"]
    optimizer.step()
    for group, lr in zip(optimizer.param_groups, scheduled):
        group["lr"] = lr
    return used
