"""Data-parallel training under ``torchrun``: the process group, the device and the model.

Under ``torchrun`` (``WORLD_SIZE`` > 1) every rank trains its own copy of the model
wrapped in ``DistributedDataParallel`` (gloo on CPU, NCCL on CUDA). Rank 0 alone
validates and writes files; what every rank must agree on (the validation loss, the stop
decision) is broadcast from it with :func:`broadcast_float`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import torch
from torch import nn

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DistInfo:
    """Process group facts: rank, world size and whether DDP is active."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def active(self) -> bool:
        """Whether there is more than one process."""
        return self.world > 1

    @property
    def main(self) -> bool:
        """Whether this is rank 0 (the one that validates and writes files)."""
        return self.rank == 0


def init_distributed(device: str) -> DistInfo:
    """Join the process group when started by torchrun (``WORLD_SIZE`` > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    import torch.distributed as dist

    backend = "nccl" if device.startswith("cuda") else "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend=backend)
    info = DistInfo(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", 0)))
    logger.info("DDP: rank %d of %d (%s)", info.rank, info.world, backend)
    return info


def rank_device(device: str, info: DistInfo) -> torch.device:
    """The device of this process: ``device``, or its local rank's GPU under DDP on CUDA."""
    if str(device).startswith("cuda") and info.active:
        return torch.device("cuda", info.local_rank)
    return torch.device(device)


def wrap_model(model: nn.Module, info: DistInfo, device: torch.device) -> nn.Module:
    """``model`` in ``DistributedDataParallel`` under DDP, else ``model`` itself."""
    if not info.active:
        return model
    from torch.nn.parallel import DistributedDataParallel

    return DistributedDataParallel(
        model, device_ids=[device.index] if device.type == "cuda" else None)


def broadcast_float(value: float, info: DistInfo, device: torch.device) -> float:
    """Rank 0's ``value`` on every rank (``value`` itself without DDP)."""
    if not info.active:
        return value
    import torch.distributed as dist

    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.broadcast(t, 0)
    return float(t.item())


def barrier(info: DistInfo) -> None:
    """Wait for every rank (nothing without DDP)."""
    if info.active:
        import torch.distributed as dist

        dist.barrier()


def leave(info: DistInfo) -> None:
    """Leave the process group (if any)."""
    if info.active:
        import torch.distributed as dist

        if dist.is_initialized():
            dist.destroy_process_group()
