"""The seeds of a run: the global generators, and the data's seed."""

from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int) -> None:
    """Seed torch (the model's initialisation, dropout), NumPy's and Python's global RNGs."""
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    random.seed(seed)


def data_seed(seed: int, start_step: int) -> int:
    """The seed of a run's data draws (each stream combines it with rank and worker).

    A resumed run (``start_step`` > 0) must not replay the data of the steps already
    taken, so the step it starts from enters the seed.
    """
    return int(seed) * 1_000_003 + start_step
