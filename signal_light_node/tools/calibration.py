"""Step inputs recorded from bags, for the int8 export's ranges and its check.

``signal-light export --onnx OUT --int8 --calibration BAG ...`` replays the bags
through the float32 export as the node would run it (pairing, crops, each track's
recurrent state from frame to frame), records what every model step was given, and
quantises on a sample of those rows (:mod:`signal_light_node.model.onnx_quantize`).
Then it replays the bags through both files and compares the class each step picks
per task, every track carrying its own state in each file, so a drift of the int8
state over time shows up in the agreement.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Dict, List, Sequence

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.model.backends.registry import create_backend
from signal_light_node.runtime.backend import StepOutput
from signal_light_node.runtime.engine import LightStateEngine
from signal_light_node.tools.replay import replay_bag


class RecordingBackend:
    """A backend that keeps what each step was given and the probabilities it gave.

    Everything but ``step`` goes to the wrapped backend.

    Args:
        inner: The backend that runs the steps.
        inputs: Also keep the inputs (numpy states only: the onnxruntime backend's).
    """

    def __init__(self, inner: Any, inputs: bool = True) -> None:
        self._inner = inner
        self._inputs = inputs
        #: Per step: uint8 ``[N, S, S, 3]`` crops, float32 ``[N, W]`` states (with
        #: ``inputs``), and the probabilities per task.
        self.crops: List[np.ndarray] = []
        self.states: List[np.ndarray] = []
        self.probs: List[Dict[str, np.ndarray]] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def step(self, crops: np.ndarray, state: Any, *, attention: bool = False) -> StepOutput:
        if self._inputs:
            self.crops.append(np.array(crops, dtype=np.uint8, copy=True))
            self.states.append(np.array(state, dtype=np.float32, copy=True))
        out = self._inner.step(crops, state, attention=attention)
        self.probs.append({t: p.copy() for t, p in out.probs.items()})
        return out


def record_steps(model_path: "str | Path", bags: Sequence["str | Path"],
                 inputs: bool = True) -> RecordingBackend:
    """Replay each bag (a fresh engine each) through an export; what its steps saw (with
    ``inputs``: ~150 kB of state per track step) and gave.

    Raises:
        ConfigError: No bags, or a bag cannot be replayed.
        CheckpointError: The model file cannot be loaded.
    """
    if not bags:
        raise ConfigError("calibration needs at least one bag (--calibration BAG ...)")
    recorder = RecordingBackend(create_backend("onnxruntime", str(model_path)), inputs=inputs)
    with tempfile.TemporaryDirectory(prefix="signal_light_calibration_") as tmp:
        for i, bag in enumerate(bags):
            replay_bag(bag, Path(tmp) / f"out_{i}", LightStateEngine(recorder), progress=False)
    if not recorder.probs:
        raise ConfigError(f"the calibration bags {[str(b) for b in bags]} gave no tracked "
                          "vehicle to record")
    return recorder


def step_agreement(reference: RecordingBackend, other: RecordingBackend) -> Dict[str, float]:
    """Share of track steps in which both recordings picked the same class, per task.

    Raises:
        ConfigError: The recordings are not of the same steps (other bags or pairing).
    """
    a, b = _classes(reference), _classes(other)
    if a.shape != b.shape:
        raise ConfigError(f"the recordings differ in their steps ({a.shape} vs {b.shape})")
    return {task: float(np.mean(a[:, k] == b[:, k])) for k, task in enumerate(TASKS)}


def _classes(recording: RecordingBackend) -> np.ndarray:
    """int64 ``[rows, len(TASKS)]``: the argmax per task of every recorded track step."""
    if not recording.probs:
        return np.zeros((0, len(TASKS)), np.int64)
    return np.concatenate([np.stack([p[t].argmax(1) for t in TASKS], 1)
                           for p in recording.probs])
