"""Helpers of the benchmark scripts (``scripts/benchmark_*.py``): backends, ISA, tables.

The scripts time the same model in several backends side by side; this module builds
those backends from one set of options (a ``.pt`` checkpoint, exported on the fly for
``onnxruntime`` when no ``.onnx`` is given), says which CPU instruction set each
framework uses, and formats per-stage timing tables. It imports torch only when a
torch model has to be built.
"""

from __future__ import annotations

import math
import os
import platform
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.model.backends.registry import create_backend
from signal_light_node.runtime.backend import ModelBackend

#: Environment variables that cap oneDNN's instruction set (torch's convolutions).
ONEDNN_ISA_VARIABLES = ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA")

#: CPU flags (``/proc/cpuinfo``) worth naming for these kernels.
_FLAGS = ("avx2", "fma", "f16c", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile")


def _cpuinfo(key: str) -> Optional[str]:
    """The value of the first ``key`` line of ``/proc/cpuinfo`` (None where missing)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(key):
            return line.split(":", 1)[1].strip()
    return None


def cpu_flags() -> List[str]:
    """The flags of :data:`_FLAGS` this CPU has (empty where ``/proc/cpuinfo`` is missing)."""
    have = set((_cpuinfo("flags") or "").split())
    return [flag for flag in _FLAGS if flag in have]


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    return _cpuinfo("model name") or platform.processor() or platform.machine()


def isa_lines(backends: Sequence[str]) -> List[str]:
    """Lines saying which instruction set each backend's kernels use on this machine.

    torch: ``torch.backends.cpu.get_cpu_capability()`` (the ATen kernels' level) and the
    oneDNN cap variables as set; onnxruntime: its version and that it ignores them (MLAS
    picks its kernels from CPUID).
    """
    flags = cpu_flags()
    lines = [f"CPU: {cpu_model()}, {os.cpu_count()} CPUs, "
             f"flags {' '.join(flags) or 'unknown'}"
             f"{'' if 'avx512f' in flags else ' (no AVX-512)'}"]
    caps = ", ".join(f"{name}={os.environ[name]}" for name in ONEDNN_ISA_VARIABLES
                     if name in os.environ) or "ONEDNN_MAX_CPU_ISA not set"
    if "torch" in backends:
        import torch

        lines.append(f"torch {torch.__version__}: CPU capability "
                     f"{torch.backends.cpu.get_cpu_capability()}, {caps}")
    if "onnxruntime" in backends:
        try:
            import onnxruntime

            version = onnxruntime.__version__
        except ImportError:
            version = "(not installed)"
        lines.append(f"onnxruntime {version}: MLAS kernels chosen from CPUID; it ignores "
                     f"ONEDNN_MAX_CPU_ISA ({caps})")
    return lines


def bench_backend(name: str, weights: Optional[Path], onnx: Optional[Path], threads: int,
                  device: str, workdir: Path) -> ModelBackend:
    """The backend ``name`` for a benchmark.

    Args:
        name: ``torch`` or ``onnxruntime`` (``model.backends.registry.known_backends``).
        weights: The ``.pt`` checkpoint (None: the shipped one).
        onnx: The ``.onnx`` export for ``onnxruntime``; None exports ``weights`` into
            ``workdir`` (or takes the shipped ``default.onnx`` when ``weights`` is None).
        threads: Intra-op threads (0: the backend's default).
        device: ``cpu`` or ``cuda[:N]``.
        workdir: Where an on-the-fly export is written.

    Raises:
        ConfigError: Unknown backend or unusable device.
        CheckpointError: A model file is missing or cannot be exported.
    """
    if name == "onnxruntime" and onnx is None and weights is not None:
        from signal_light_node.model.onnx_export import export_onnx

        onnx = export_onnx(Path(workdir) / f"{Path(weights).stem}.onnx", weights).path
    path = onnx if name == "onnxruntime" else weights
    return create_backend(name, None if path is None else str(path), device=device,
                          threads=threads or None)


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (NaN for no values)."""
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) \
        else math.nan


def stage_table(stages: Mapping[str, Mapping[str, Sequence[float]]], order: Sequence[str],
                total_stages: Optional[Sequence[str]] = None) -> str:
    """A per-stage table: rows = stages, columns = mean and p95 (ms) per backend.

    Args:
        stages: ``backend -> stage -> seconds per frame``.
        order: The stages, in row order.
        total_stages: The stages summed into the ``frame`` row (all of ``order`` when None).

    Returns:
        The table as text, with a ``frame`` (sum per frame) row and each stage's share of
        the mean frame.
    """
    names = list(stages)
    total_stages = list(order if total_stages is None else total_stages)
    head = f"{'stage':<14}" + "".join(f"{name + ' mean':>18}{'p95':>8}{'share':>7}"
                                      for name in names)
    lines = [head, "-" * len(head)]
    totals: Dict[str, np.ndarray] = {}
    for name in names:
        per = [np.asarray(stages[name].get(s, ()), dtype=np.float64) for s in total_stages]
        n = min((len(p) for p in per), default=0)
        totals[name] = np.sum([p[:n] for p in per], axis=0) if n else np.zeros(0)
    for stage in list(order) + ["frame"]:
        cells = ""
        for name in names:
            values = totals[name] if stage == "frame" else \
                np.asarray(stages[name].get(stage, ()), dtype=np.float64)
            frame_mean = float(totals[name].mean()) if totals[name].size else math.nan
            mean = float(values.mean()) if values.size else math.nan
            share = mean / frame_mean if frame_mean > 0 else math.nan
            cells += f"{mean * 1e3:>18.2f}{percentile(values, 95) * 1e3:>8.2f}{share:>7.0%}"
        lines.append(f"{stage:<14}{cells}")
    return "\n".join(lines)


def time_backend_steps(backend: ModelBackend, n: int, reps: int, warmup: int,
                       seed: int = 0) -> List[float]:
    """Seconds of ``reps`` batched ``step`` calls on ``n`` tracks (state carried over).

    The crops are drifting, blinking synthetic tracks (``onnx_export.synthetic_tracks``)
    cycled, so the temporal evidence is exercised.
    """
    import time

    from signal_light_node.model.onnx_export import synthetic_tracks

    frames = synthetic_tracks(int(backend.config.input_size), n, 8, seed=seed)
    state = backend.initial_state(n)
    for i in range(warmup):
        state = backend.step(frames[i % len(frames)], state).state
    out = []
    for i in range(reps):
        crops = frames[i % len(frames)]
        start = time.perf_counter()
        state = backend.step(crops, state).state
        out.append(time.perf_counter() - start)
    return out


def require_known(names: Sequence[str]) -> List[str]:
    """``names`` checked against the registry, duplicates removed (order kept).

    Raises:
        ConfigError: A name is not a known backend.
    """
    from signal_light_node.model.backends.registry import known_backends

    out: List[str] = []
    for name in names:
        if name not in known_backends():
            raise ConfigError(f"unknown backend {name!r}; known: {', '.join(known_backends())}")
        if name not in out:
            out.append(name)
    return out


def describe(backend: Any) -> str:
    """``name (file)`` of a backend, for headers."""
    return f"{backend.name} ({backend.source or 'in memory'})"
