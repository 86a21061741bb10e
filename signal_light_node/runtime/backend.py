"""The model backend seam: what the engine and the state bank need from a model.

A backend runs one model, in one framework, on one device. The engine and the state
bank only talk to this protocol and never see a framework's tensor type: crops go in as
the uint8 arrays ``crops.crop_vehicles`` cuts, probabilities come out as numpy arrays,
and the recurrent state is an opaque value the backend owns (torch tensors on the
model's device for ``torch``, numpy arrays for ``onnxruntime``). The bank keeps every
track's state as one row of a backend-owned row store and moves a whole frame's rows
with one ``gather_rows`` and one ``store_rows``.

This module is the protocol only (:class:`ModelBackend`, :class:`StepOutput`,
:func:`check_device`, the names :data:`AUTO_BACKEND` / :data:`PRECISIONS` and the node's
defaults) and imports no backend: the backends in ``model/backends/`` import it, and
their registry, :mod:`signal_light_node.model.backends.registry` (``create_backend``,
``known_backends``, ``resolve_backend``, ``as_backend``), chooses and loads them.

``auto`` (:data:`AUTO_BACKEND`, the node's default, :data:`DEFAULT_BACKEND`, which
``signal-light replay`` and ``evaluate`` share) is not a backend but picks one (the
registry's ``resolve_backend``); the precision ``auto`` (:data:`PRECISIONS`) picks among
the shipped files the same way.

:class:`ModelRun` says what ran once ``auto`` was resolved: the model file, backend,
precision, device and CPU threads (what a replay and an evaluation report).
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Dict, NamedTuple, Optional, Protocol, runtime_checkable

import numpy as np

from signal_light_node.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from signal_light_node.model.config import ModelConfig

#: A backend's batched state or row store: opaque to everyone but the backend.
BackendState = Any

#: The name that picks a backend from the model file and device (the registry's
#: ``resolve_backend``).
AUTO_BACKEND = "auto"

#: Weight precisions the registry's ``create_backend`` takes (``model.onnx_format`` has
#: the same words for a file; ``auto`` picks).
AUTO_PRECISION = "auto"
PRECISIONS = (AUTO_PRECISION, "fp32", "int8")

#: What the node runs unless told otherwise (``ros.params.DetectorParams``), and so what
#: ``signal-light replay`` and ``evaluate`` run: a replay is meant to be the node.
DEFAULT_BACKEND = AUTO_BACKEND
DEFAULT_PRECISION = AUTO_PRECISION

#: Devices a backend may be asked for: ``cpu``, ``cuda`` or ``cuda:N``.
_DEVICE = re.compile(r"(cpu|cuda(:\d+)?)\Z")


class StepOutput(NamedTuple):
    """What one batched step returns.

    Attributes:
        probs: float32 ``[N, K]`` per task of ``labels.TASKS`` (rows sum to 1).
        state: The tracks' new state (the backend's own type).
        attention: float32 ``[N, S, S]`` attention masks in [0, 1] of the crops, when
            asked for and the model computes them inside its step; else None.
    """

    probs: Dict[str, np.ndarray]
    state: BackendState
    attention: Optional[np.ndarray] = None


@runtime_checkable
class ModelBackend(Protocol):
    """A light-state model behind a framework-free interface.

    Attributes:
        name: The registry name (``torch``, ``onnxruntime``).
        config: The model's ``ModelConfig`` (input size, crop margin, class names).
        device: Where it runs (``cpu``, ``cuda``, ``cuda:N``).
        source: The file it was loaded from ("" when built in memory).

    A backend may also say its weights' ``precision`` (``fp32`` when it does not), the
    most CPU ``threads`` a step may use and the ``threads_in_use`` of its last step
    (:func:`step_threads`).
    """

    name: str
    config: "ModelConfig"
    device: str
    source: str

    def initial_state(self, n: int) -> BackendState:
        """The state of ``n`` tracks that have not been seen yet."""
        ...

    def step(self, crops: np.ndarray, state: BackendState, *,
             attention: bool = False) -> StepOutput:
        """Advance ``N`` tracks by one frame.

        Args:
            crops: uint8 ``[N, S, S, 3]`` BGR crops (``crops.crop_vehicles``).
            state: The tracks' state, batch ``N`` (from ``initial_state`` or
                ``gather_rows``).
            attention: Also return the attention masks the step computed.
        """
        ...

    def attention(self, crops: np.ndarray) -> Optional[np.ndarray]:
        """float32 ``[N, S, S]`` attention masks of uint8 crops (no state involved);
        None when the model has no attention."""
        ...

    def new_rows(self, n: int) -> BackendState:
        """A row store of ``n`` tracks, every row the initial state."""
        ...

    def gather_rows(self, rows: BackendState, index: np.ndarray) -> BackendState:
        """The batched state of rows ``index`` (int64 ``[N]``, in that order)."""
        ...

    def store_rows(self, rows: BackendState, index: np.ndarray, state: BackendState,
                   select: Optional[np.ndarray] = None) -> None:
        """Write batch rows ``select`` (all when None) of ``state`` into rows ``index``."""
        ...

    def reset_rows(self, rows: BackendState, index: np.ndarray) -> None:
        """Set rows ``index`` back to the initial state."""
        ...


def is_backend(obj: Any) -> bool:
    """Whether ``obj`` implements :class:`ModelBackend` (rather than being a bare model)."""
    return all(callable(getattr(obj, name, None))
               for name in ("new_rows", "gather_rows", "store_rows", "reset_rows", "step"))


def check_device(device: Any) -> str:
    """``device`` as a normalised string, checked to name a CPU or CUDA device.

    Whether the device is usable is the backend's check (it knows its framework).

    Raises:
        ConfigError: Not ``cpu``, ``cuda`` or ``cuda:N``.
    """
    text = str(device).strip()
    if not _DEVICE.match(text):
        raise ConfigError(f"device must be 'cpu' or 'cuda[:N]', got {device!r}")
    return text


# ------------------------------------------------------------------ what ran
def step_threads(backend: Any) -> Optional[int]:
    """CPU threads the backend's last step ran on, as the node's /diagnostics
    ``model_threads``; None when the backend does not say.

    onnxruntime says so itself (``threads_in_use``: one or all of its threads per step by
    the load, fewer for a batch smaller than that); torch runs its process-wide intra-op
    thread count. torch is only looked up, never imported: a torch backend has loaded it.
    """
    held = getattr(backend, "threads_in_use", None)
    if held is not None:
        return int(held)
    torch = sys.modules.get("torch") if getattr(backend, "name", "") == "torch" else None
    return int(torch.get_num_threads()) if torch is not None else None


@dataclass
class ModelRun:
    """The model a replay or an evaluation ran, after ``auto`` was resolved.

    Attributes:
        model_file: The file it was loaded from ("" when built in memory).
        backend: The backend that ran it (``torch``, ``onnxruntime``).
        precision: Its weights (``fp32``, ``int8``).
        device: Where it ran.
        most_threads: The most CPU threads a step may use; None when the backend does not
            say.
        threads_by_load: Each step runs one or ``most_threads`` threads as the load allows
            (onnxruntime without a thread count).
        last_step_threads: Threads of the last step (:func:`step_threads`).
        steps_by_threads: Steps counted with :meth:`count_step`, per the threads they ran
            on; empty when nobody counted.
    """

    model_file: str
    backend: str
    precision: str
    device: str
    most_threads: Optional[int] = None
    threads_by_load: bool = False
    last_step_threads: Optional[int] = None
    steps_by_threads: Dict[int, int] = field(default_factory=dict)

    @classmethod
    def of(cls, backend: Any) -> "ModelRun":
        """What ``backend`` is and, so far, ran on (its last step's threads)."""
        last = step_threads(backend)
        most = getattr(backend, "threads", None)
        return cls(model_file=str(getattr(backend, "source", "") or ""),
                   backend=str(getattr(backend, "name", type(backend).__name__)),
                   precision=str(getattr(backend, "precision", "fp32")),
                   device=str(getattr(backend, "device", "")),
                   most_threads=last if most is None else int(most),
                   threads_by_load=getattr(backend, "thread_choice", None) is not None,
                   last_step_threads=last)

    def count_step(self, backend: Any) -> None:
        """Count a step ``backend`` has just run, on the threads it ran on."""
        threads = step_threads(backend)
        self.last_step_threads = threads
        if threads is not None:
            self.steps_by_threads[threads] = self.steps_by_threads.get(threads, 0) + 1

    def threads_text(self) -> str:
        """The threads that ran, e.g. ``2 on 80 steps, 1 on 40 steps (1 or 2 per step, by
        the load)``; without counted steps, the last step's."""
        if self.steps_by_threads:
            text = ", ".join(f"{t} on {n} steps" for t, n in
                             sorted(self.steps_by_threads.items(), reverse=True))
        elif self.last_step_threads is not None:
            text = f"{self.last_step_threads} in the last step"
        else:
            return "not known"
        if self.threads_by_load:
            text += f" (1 or {self.most_threads} per step, by the load)"
        elif self.most_threads is not None and (
                set(self.steps_by_threads) or {self.last_step_threads}) != {self.most_threads}:
            text += f" (at most {self.most_threads}: a small batch takes fewer)"
        return text

    def text(self) -> str:
        """One line: ``model: FILE, backend B, precision P, device D, threads: ...``."""
        return (f"model: {self.model_file or 'built in memory'}, backend {self.backend}, "
                f"precision {self.precision}, device {self.device}, threads: "
                f"{self.threads_text()}")

    def as_dict(self) -> Dict[str, Any]:
        """The fields for JSON (thread counts as string keys), with the threads' and the
        whole line's :meth:`text`."""
        return {"model_file": self.model_file, "backend": self.backend,
                "precision": self.precision, "device": self.device,
                "most_threads": self.most_threads, "threads_by_load": self.threads_by_load,
                "last_step_threads": self.last_step_threads,
                "steps_by_threads": {str(t): n for t, n in
                                     sorted(self.steps_by_threads.items(), reverse=True)},
                "threads": self.threads_text(), "text": self.text()}
