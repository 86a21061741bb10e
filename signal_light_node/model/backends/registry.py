"""The model backend registry: which backends there are, how one is chosen and loaded.

The backends implement :class:`signal_light_node.runtime.backend.ModelBackend` (the
protocol, which imports none of them); this module is the one place that names them.
Backends are chosen by name (:func:`create_backend`); the built-in ones are imported only
when asked for, so this module imports neither torch nor onnxruntime:

* ``torch``: :class:`signal_light_node.model.backends.torch_backend.TorchBackend`, the
  network of a checkpoint (``.pt``).
* ``onnxruntime``:
  :class:`signal_light_node.model.backends.onnx_backend.OnnxRuntimeBackend`, a model
  exported by ``signal-light export --onnx`` (``.onnx``).

``auto`` (``runtime.backend.AUTO_BACKEND``, the node's default) is not a backend but picks
one (:func:`resolve_backend`): by the model file's suffix, and for the shipped model
onnxruntime on the CPU, which runs the same network faster there than torch (measured on
a 2-core AVX2 machine, 32 tracks: step 36-41 ms against 48-51 ms). The precision
(``runtime.backend.PRECISIONS``) picks among the shipped files the same way: ``auto``
takes the int8 export where it runs (onnxruntime on the CPU: 0.73-0.78x the float step,
the same scores; :func:`_shipped_int8`).

:func:`known_backends` is where the node's ``backend`` parameter and the commands'
``--backend`` take their choices from.
"""

from __future__ import annotations

import importlib.util
import logging
from typing import Any, Callable, Dict, Optional, Tuple

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.backend import (AUTO_BACKEND, AUTO_PRECISION, PRECISIONS,
                                               ModelBackend, check_device, is_backend)

LOG = logging.getLogger(__name__)

#: A factory builds a backend from a model file (None: the shipped one).
Factory = Callable[..., ModelBackend]


def _torch(path: Optional[str], **options: Any) -> ModelBackend:
    from signal_light_node.model.backends.torch_backend import TorchBackend

    return TorchBackend.from_file(path, **options)


def _onnxruntime(path: Optional[str], **options: Any) -> ModelBackend:
    from signal_light_node.model.backends.onnx_backend import OnnxRuntimeBackend

    return OnnxRuntimeBackend.from_file(path, **options)


#: name -> factory; the built-in ones import their framework only when called.
_REGISTRY: Dict[str, Factory] = {"torch": _torch, "onnxruntime": _onnxruntime}


def register_backend(name: str, factory: Factory) -> None:
    """Make ``create_backend(name, ...)`` call ``factory(path, device=..., threads=...)``.

    Raises:
        ConfigError: ``name`` is empty or not a string.
    """
    if not isinstance(name, str) or not name:
        raise ConfigError(f"backend name must be a non-empty string, got {name!r}")
    _REGISTRY[name] = factory


def known_backends() -> Tuple[str, ...]:
    """Names :func:`create_backend` accepts, sorted."""
    return tuple(sorted(_REGISTRY))


def resolve_backend(name: str, path: Optional[str] = None, device: str = "cpu") -> str:
    """The backend ``name`` stands for: itself, or for ``auto`` the one that fits.

    ``auto``: ``onnxruntime`` for an ``.onnx`` file, ``torch`` for any other file (a
    ``.pt`` checkpoint); without a file (the shipped model), ``onnxruntime`` on the CPU
    when it is installed, else ``torch``.

    Raises:
        ConfigError: ``device`` is not a device name.
    """
    if name != AUTO_BACKEND:
        return name
    if path:
        return "onnxruntime" if str(path).lower().endswith(".onnx") else "torch"
    if check_device(device) == "cpu" and importlib.util.find_spec("onnxruntime") is not None:
        return "onnxruntime"
    return "torch"


def _factory(name: str) -> Factory:
    factory = _REGISTRY.get(name) if isinstance(name, str) else None
    if factory is None:
        raise ConfigError(f"unknown model backend {name!r}; known: {', '.join(known_backends())}")
    return factory


def create_backend(name: str, path: Optional[str] = None, *, device: str = "cpu",
                   threads: Optional[int] = None, precision: str = AUTO_PRECISION
                   ) -> ModelBackend:
    """Load a model file into the backend called ``name``.

    Args:
        name: A name of :func:`known_backends`, or ``auto`` (:func:`resolve_backend`).
        path: The model file (a ``.pt`` checkpoint for ``torch``, an ``.onnx`` export for
            ``onnxruntime``); None takes the one shipped with the package.
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        threads: Intra-op CPU threads; None or 0 keeps the framework's default.
        precision: Weights, one of :data:`PRECISIONS`: ``fp32``, ``int8`` (an export
            with int8 convolutions, onnxruntime on the CPU) or ``auto``: a given file as
            it is; of the shipped files int8 where it runs (onnxruntime on the CPU), else
            fp32. A file of another precision than asked for is refused.

    Raises:
        ConfigError: Unknown backend, bad device, thread count or precision, a model of
            another precision, or the backend's framework is missing or cannot use the
            device.
        CheckpointError: The model file is missing, unreadable or incompatible.
    """
    device = check_device(device)
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                or threads < 0):
        raise ConfigError(f"threads must be a non-negative integer, got {threads!r}")
    if precision not in PRECISIONS:
        raise ConfigError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    name = resolve_backend(name, path, device)
    factory = _factory(name)
    if path is None:
        path = _shipped_int8(name, device, precision)
    LOG.debug("creating model backend %s on %s from %s", name, device, path or "the default")
    backend = factory(path, device=device, threads=threads or None)
    held = getattr(backend, "precision", "fp32")
    if precision != AUTO_PRECISION and held != precision:
        raise ConfigError(
            f"precision {precision} asked for, but {backend.source or 'the model'} holds {held} "
            f"weights (backend {name} on {device}); int8 runs as an int8 export with "
            "onnxruntime on the CPU: the shipped one, or signal-light export --onnx OUT --int8")
    return backend


def _shipped_int8(name: str, device: str, precision: str) -> Optional[str]:
    """The shipped int8 export where precision and backend take it, else None (the
    backend's own default file)."""
    if name == "onnxruntime" and device == "cpu" and precision in ("int8", AUTO_PRECISION):
        from signal_light_node.model.onnx_format import DEFAULT_ONNX_INT8

        return str(DEFAULT_ONNX_INT8)
    return None


def as_backend(model: Any, device: str = "cpu") -> ModelBackend:
    """``model`` itself when it is a backend, else a bare torch model wrapped in ``torch``'s.

    Args:
        model: A :class:`ModelBackend`, or a ``model.interface.LightStateModel``
            (``config``, ``initial_state``, ``step``, torch tensors).
        device: Device of a wrapped model (a backend keeps its own).

    Raises:
        ConfigError: ``model`` is neither, or the device cannot be used.
    """
    if is_backend(model):
        return model
    if not (callable(getattr(model, "step", None)) and callable(getattr(model, "initial_state",
                                                                         None))):
        raise ConfigError(f"{type(model).__name__} is neither a model backend nor a model with "
                          "initial_state and step")
    from signal_light_node.model.backends.torch_backend import TorchBackend

    return TorchBackend(model, device=check_device(device))
