"""The arithmetic precision of a run's forward pass (``TrainOptions.precision``).

Under "bf16" the training forward pass runs in ``torch.autocast`` with bfloat16; the
weights, the optimiser, the loss, the state carried between steps and the validation
stay float32.
"""

from __future__ import annotations

import torch


def resolve_precision(precision: str, device: torch.device) -> str:
    """The precision a run uses (``TrainOptions.precision``).

    Args:
        precision: "fp32", "bf16" or "auto".
        device: The device the run trains on.

    Returns:
        ``precision`` itself unless it is "auto"; then "bf16" where ``device`` computes
        bfloat16 natively (a CPU with AVX512-BF16 or AMX, a CUDA device that supports it)
        and "fp32" elsewhere, where bfloat16 is emulated and slower than float32.
    """
    if precision != "auto":
        return precision
    if device.type == "cuda":
        native = torch.cuda.is_bf16_supported()
    else:
        # torch's own probes (private, hence the fallback; torch is pinned in requirements.txt)
        probes = [getattr(torch.cpu, name, lambda: False)
                  for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
        native = any(probe() for probe in probes)
    return "bf16" if native else "fp32"


def forward_autocast(precision: str, device: torch.device) -> torch.autocast:
    """The context of the training forward pass: bfloat16 autocast under "bf16", else off.

    Args:
        precision: A resolved precision ("fp32" or "bf16").
        device: The device the run trains on.
    """
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")
