"""The ``onnxruntime`` model backend: a step exported by ``signal-light export --onnx``.

Everything comes from the ``.onnx`` file: the graph (uint8 crops and flattened state
rows in, probabilities, new state rows and attention masks out) and, in its metadata,
the ``ModelConfig`` (:mod:`signal_light_node.model.onnx_format`). States are numpy
float32 rows: a frame's states are gathered with one fancy index and stored with one
assignment. The session runs on the CPU provider, or on CUDA (TensorRT first when the
installed onnxruntime has it) for ``device="cuda[:N]"``.

On the CPU the threads split the batch, not each operator: the session runs single-
threaded and a frame's tracks are cut into chunks (tracks are independent, so the
outputs are bit-identical to one batched run) that the calling thread and
``threads - 1`` helper threads take one by one. A thread whose core is busy with
another process just takes fewer chunks, where onnxruntime's own intra-op threads
would wait for it at every operator; and no operator pays the intra-op
synchronisation. Measured at 32 tracks on the 2-core AVX2 machine, interleaved, median
of the per-step ratio: 0.96 x the time of 2 intra-op threads on a quiet machine, 0.85-0.90 x
while other processes load it (where 2 intra-op threads are slower than 1).

Unless a thread count is given, the count follows the load
(:class:`~signal_light_node.model.backends.thread_choice.ThreadChoice`): every thread
while that makes the steps faster, one thread while another process holds the cores
and a second thread would only take CPU from the node's other work.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.errors import CheckpointError, ConfigError, CropError
from signal_light_node.labels import TASKS
from signal_light_node.model import onnx_format as fmt
from signal_light_node.model.backends.thread_choice import ThreadChoice
from signal_light_node.runtime.backend import StepOutput, check_device

LOG = logging.getLogger(__name__)

_INSTALL_HINT = "pip install onnxruntime (pinned in requirements.txt)"

#: Fewest tracks in a chunk of a split batch (a run has a fixed cost of its own).
MIN_CHUNK_TRACKS = 4

#: Chunks per thread a batch is cut into, so that a thread slowed down by another
#: process hands its share to the others.
CHUNKS_PER_THREAD = 2


def default_threads() -> int:
    """The CPUs this process may run on (its affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def chunk_bounds(n: int, threads: int) -> List[Tuple[int, int]]:
    """``(start, stop)`` of the chunks a batch of ``n`` tracks is split into.

    ``CHUNKS_PER_THREAD`` chunks per thread of near-equal size, none smaller than
    ``MIN_CHUNK_TRACKS`` tracks (one chunk when the batch is that small or there is one
    thread).
    """
    chunks = max(1, min(threads * CHUNKS_PER_THREAD, n // MIN_CHUNK_TRACKS)) if threads > 1 \
        else 1
    base, extra = divmod(n, chunks)
    bounds, start = [], 0
    for k in range(chunks):
        stop = start + base + (1 if k < extra else 0)
        bounds.append((start, stop))
        start = stop
    return bounds


def _onnxruntime() -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise ConfigError(f"backend onnxruntime needs the onnxruntime package ({_INSTALL_HINT})"
                          ) from None
    return onnxruntime


def execution_providers(device: str, available: List[str]) -> List[Any]:
    """The providers for ``device`` given the installed onnxruntime's ``available`` ones.

    Raises:
        ConfigError: CUDA asked for but neither the CUDA nor the TensorRT provider exists.
    """
    device = check_device(device)
    if device == "cpu":
        return ["CPUExecutionProvider"]
    index = int(device.partition(":")[2] or 0)
    chosen: List[Any] = [(name, {"device_id": index}) for name in
                         ("TensorrtExecutionProvider", "CUDAExecutionProvider")
                         if name in available]
    if not chosen:
        raise ConfigError(f"CUDA requested but not available (device {device!r}): the "
                          f"installed onnxruntime has only the providers {available}; install "
                          "onnxruntime-gpu or use device cpu")
    return chosen + ["CPUExecutionProvider"]


class OnnxRuntimeBackend:
    """Runs an exported light-state step with onnxruntime.

    Args:
        path: The ``.onnx`` file (``signal-light export --onnx``).
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        threads: CPU threads a step uses; None: up to one per CPU this process may run
            on, as many as pay under the current load (see the module doc). On the CPU
            they run chunks of the batch in parallel; on CUDA it is the session's
            intra-op thread count (None: onnxruntime's).

    Raises:
        ConfigError: onnxruntime is missing or cannot use the device.
        CheckpointError: The file is missing, not an ONNX model, or not a light-state
            export this code can run.
    """

    name = "onnxruntime"

    def __init__(self, path: str, device: str = "cpu", threads: Optional[int] = None) -> None:
        ort = _onnxruntime()
        device = check_device(device)
        source = Path(path)
        if not source.is_file():
            raise CheckpointError(f"ONNX model {source} does not exist or is not a file")
        providers = execution_providers(device, list(ort.get_available_providers()))
        #: Most threads splitting a batch (1: every step runs in the calling thread).
        self.threads = int(threads or default_threads()) if device == "cpu" else 1
        #: Picks 1 or ``threads`` per step when no count was given.
        self.thread_choice: Optional[ThreadChoice] = (
            ThreadChoice(self.threads) if threads is None and self.threads > 1 else None)
        #: Threads of the last step.
        self.threads_in_use = self.threads
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1 if device == "cpu" else int(threads or 0)
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.log_severity_level = 3  # errors only: the node logs what matters
        # Idle intra-op threads (CUDA sessions') sleep instead of spinning: on a small
        # shared CPU (the node's worker, rclpy and the camera driver) spinning threads slow
        # everyone down, as OMP_WAIT_POLICY=PASSIVE does for torch
        # (signal_light_node/__init__.py).
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        # onnxruntime's NHWC rewrite of int8 convolutions wraps every elementwise op
        # around them in transposes (an int8 export ran 0.88x fp32 with it, 0.76x
        # without: docs/model.md); it does nothing to the fp32 export.
        disabled = ["NhwcTransformer"] if device == "cpu" else []
        try:
            self._session = ort.InferenceSession(str(source), options, providers=providers,
                                                 disabled_optimizers=disabled)
        except Exception as exc:  # onnxruntime raises its own pybind types for a bad file
            raise CheckpointError(
                f"{source} cannot be loaded as an ONNX model ({type(exc).__name__}: "
                f"{str(exc).splitlines()[0] if str(exc) else ''}); a .pt checkpoint must be "
                f"exported first: signal-light export --onnx OUT.onnx --weights {source}"
            ) from None
        meta = self._session.get_modelmeta().custom_metadata_map
        self.config, shapes = fmt.parse_metadata(meta, source)
        self.input_size = self.config.input_size
        self.device = device
        self.source = str(source)
        self.metadata: Dict[str, str] = dict(meta)
        #: ``int8`` for an export with int8 convolutions, else ``fp32``.
        self.precision = fmt.precision_of(meta)
        self._width = fmt.state_width(shapes)
        self._check_graph(source)
        self._initial = np.zeros(self._width, dtype=np.float32)
        self._no_attention = [name for name in fmt.OUTPUTS if name != fmt.ATTENTION_OUTPUT]
        self._helpers: Optional[ThreadPoolExecutor] = None
        if self.threads > 1:
            self._helpers = ThreadPoolExecutor(self.threads - 1,
                                               thread_name_prefix="onnxruntime_batch")
        LOG.info("onnxruntime %s: %s (%s) on %s, %d thread(s)", ort.__version__, source,
                 self.precision, self._session.get_providers()[0], self.threads)

    @classmethod
    def from_file(cls, path: Optional[str] = None, device: str = "cpu",
                  threads: Optional[int] = None) -> "OnnxRuntimeBackend":
        """Load an export (None: the shipped ``weights/default.onnx``)."""
        return cls(str(fmt.DEFAULT_ONNX if path is None else path), device=device,
                   threads=threads)

    def _check_graph(self, source: Path) -> None:
        inputs = {i.name: i for i in self._session.get_inputs()}
        outputs = {o.name for o in self._session.get_outputs()}
        missing = [n for n in (fmt.CROPS_INPUT, fmt.STATE_INPUT) if n not in inputs]
        missing += [n for n in fmt.OUTPUTS if n not in outputs]
        if missing:
            raise CheckpointError(f"ONNX model {source} lacks the inputs/outputs {missing}")
        crops = inputs[fmt.CROPS_INPUT].shape
        state = inputs[fmt.STATE_INPUT].shape
        size = self.input_size
        if list(crops[1:]) != [size, size, 3] or list(state[1:]) != [self._width]:
            raise CheckpointError(f"ONNX model {source}: inputs crops {crops} and state {state} "
                                  f"do not fit its config (S={size}, state width {self._width})")

    @property
    def state_width(self) -> int:
        """Floats per track row."""
        return self._width

    # ------------------------------------------------------------------ the step
    def initial_state(self, n: int) -> np.ndarray:
        """float32 ``[n, W]`` zeros: the state of ``n`` new tracks."""
        return np.tile(self._initial, (int(n), 1))

    def step(self, crops: np.ndarray, state: np.ndarray, *,
             attention: bool = False) -> StepOutput:
        """One batched step (see ``runtime.backend.ModelBackend.step``).

        Raises:
            CropError: ``crops`` is not ``[N, S, S, 3]`` uint8 of the model's size.
        """
        crops = self._check_crops(crops)
        n = crops.shape[0]
        state = np.ascontiguousarray(state, dtype=np.float32)
        if state.shape != (n, self._width):
            raise ConfigError(f"state must be [{n}, {self._width}], got {state.shape}")
        if n == 0:
            size = self.input_size
            probs = {t: np.zeros((0, len(self.config.class_names[t])), np.float32)
                     for t in TASKS}
            return StepOutput(probs, state, np.zeros((0, size, size), np.float32)
                              if attention else None)
        names = list(fmt.OUTPUTS) if attention else self._no_attention
        values = self._run(names, crops, state)
        out = dict(zip(names, values))
        return StepOutput({t: out[t] for t in TASKS}, out[fmt.STATE_OUTPUT],
                          out.get(fmt.ATTENTION_OUTPUT))

    def _run(self, names: List[str], crops: np.ndarray, state: np.ndarray) -> List[np.ndarray]:
        """The session's outputs for the batch, on as many threads as pay (module doc)."""
        n = crops.shape[0]
        splits = len(chunk_bounds(n, self.threads)) > 1
        threads = self.thread_choice.next() if splits and self.thread_choice else self.threads
        bounds = chunk_bounds(n, threads)
        start = time.perf_counter()
        if len(bounds) == 1:
            values = self._session.run(names, {fmt.CROPS_INPUT: crops, fmt.STATE_INPUT: state})
        else:
            values = self._run_chunks(names, crops, state, bounds, threads)
        if splits and self.thread_choice:
            self.thread_choice.record(threads, n, time.perf_counter() - start)
        self.threads_in_use = min(threads, len(bounds))
        return values

    def _run_chunks(self, names: List[str], crops: np.ndarray, state: np.ndarray,
                    bounds: Sequence[Tuple[int, int]], threads: int) -> List[np.ndarray]:
        """The outputs of one batch run as chunks by this thread and the helpers.

        Each thread takes the next chunk not yet taken until none is left, so a thread
        held up by another process takes fewer. The outputs are joined in batch order.
        """
        results: List[Optional[List[np.ndarray]]] = [None] * len(bounds)
        taken = iter(range(len(bounds)))
        lock = threading.Lock()

        def work() -> None:
            while True:
                with lock:
                    k = next(taken, None)
                if k is None:
                    return
                a, b = bounds[k]
                results[k] = self._session.run(names, {fmt.CROPS_INPUT: crops[a:b],
                                                       fmt.STATE_INPUT: state[a:b]})

        assert self._helpers is not None
        helpers = [self._helpers.submit(work) for _ in range(min(threads - 1, len(bounds) - 1))]
        work()
        for future in helpers:
            future.result()  # re-raises a helper's exception here
        return [np.concatenate([part[i] for part in results]) for i in range(len(names))]

    def attention(self, crops: np.ndarray) -> Optional[np.ndarray]:
        """float32 ``[N, S, S]`` attention masks of uint8 crops (a step from new tracks)."""
        crops = self._check_crops(crops)
        return self.step(crops, self.initial_state(crops.shape[0]), attention=True).attention

    def _check_crops(self, crops: Any) -> np.ndarray:
        size = self.input_size
        if not isinstance(crops, np.ndarray) or crops.dtype != np.uint8 \
                or crops.shape[1:] != (size, size, 3):
            raise CropError(f"model input must be [N, {size}, {size}, 3] uint8 crops, got "
                            f"shape {getattr(crops, 'shape', None)} dtype "
                            f"{getattr(crops, 'dtype', type(crops).__name__)}")
        return np.ascontiguousarray(crops)

    # ---------------------------------------------------------------- the rows
    def new_rows(self, n: int) -> np.ndarray:
        """float32 ``[n, W]`` rows, each the initial state."""
        return self.initial_state(n)

    def gather_rows(self, rows: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Rows ``index`` as a new contiguous ``[N, W]`` batch."""
        return rows[np.asarray(index, dtype=np.int64)]

    def store_rows(self, rows: np.ndarray, index: np.ndarray, state: np.ndarray,
                   select: Optional[np.ndarray] = None) -> None:
        """Write ``state`` (its rows ``select``) into rows ``index``."""
        rows[np.asarray(index, dtype=np.int64)] = state if select is None else state[select]

    def reset_rows(self, rows: np.ndarray, index: np.ndarray) -> None:
        """Set rows ``index`` to the initial state."""
        rows[np.asarray(index, dtype=np.int64)] = self._initial

