"""The one-file checkpoint format: saving and loading a model with its config.

A checkpoint is a single ``torch.save`` file holding only plain Python values and
tensors, so it loads with ``torch.load(weights_only=True)``::

    {"format_version": 1,
     "config": ModelConfig as a plain dict,
     "state_dict": {name: tensor},
     "meta": {"package_version", "created", "training_data", "metrics", "notes", ...}}

Loading checks that the file fits this code (format version, architecture, class
names, light codes, tensor names and shapes) and raises :class:`CheckpointError`
naming the first thing that differs.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, Mapping, NamedTuple, Optional, Union

import torch
from torch import nn

from signal_light_node import __version__
from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.labels import CLASS_NAMES, LIGHT_CODES, TASKS
from signal_light_node.model.config import ModelConfig
from signal_light_node.model.registry import build_model, known_archs

logger = logging.getLogger(__name__)

#: Version of the file layout written by :func:`save_checkpoint`.
FORMAT_VERSION = 1
SUPPORTED_FORMAT_VERSIONS = (1,)

#: The weights shipped inside the package and loaded by the node by default.
DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "default.pt"

PathLike = Union[str, os.PathLike]


class LoadedModel(NamedTuple):
    """A model loaded from a checkpoint (in eval mode), its config and its metadata."""

    model: nn.Module
    config: ModelConfig
    meta: Dict[str, Any]


#: The metadata keys that describe the file itself (:func:`save_checkpoint` fills them in
#: when absent): a file derived from a checkpoint drops them so that they are refilled.
FILE_META = ("created", "package_version", "torch_version")


def _plain(value: Any, where: str) -> Any:
    """Copy of ``value`` made of plain types only, so ``weights_only`` loading accepts it."""
    # Exact builtin types: subclasses (torch's TorchVersion, numpy.float64) would be pickled
    # by class name and then refused by the safe loader.
    for kind in (bool, int, float, str):
        if isinstance(value, kind):
            return kind(value)
    if value is None:
        return None
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().clone()
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise CheckpointError(f"checkpoint {where} has a non-string key {k!r}")
            out[k] = _plain(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return _plain(value.item(), where)
    raise CheckpointError(f"checkpoint {where} holds a {type(value).__name__}, which cannot be "
                          f"stored safely; use str/int/float/bool/list/dict")


def save_checkpoint(path: PathLike, model: nn.Module, config: ModelConfig,
                    meta: Optional[Mapping[str, Any]] = None) -> Path:
    """Write ``model`` and everything needed to use it to one file.

    The file is written to a temporary name and renamed, so a crash never leaves a
    truncated checkpoint behind.

    Args:
        path: Destination file (parents are created).
        model: The model whose ``state_dict`` is saved.
        config: The model's config.
        meta: Free-form plain metadata (training data description, metrics, notes...);
            ``package_version`` and ``created`` are filled in when absent.

    Returns:
        The path written.

    Raises:
        CheckpointError: ``meta`` holds values that cannot be stored safely, or the file
            cannot be written.
    """
    path = Path(path)
    info = _plain(dict(meta or {}), "meta")
    info.setdefault("package_version", __version__)
    info.setdefault("created", time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    info.setdefault("torch_version", str(torch.__version__))
    state = {k: v.detach().to("cpu", copy=True).contiguous() for k, v in model.state_dict().items()}
    payload = {"format_version": FORMAT_VERSION, "config": config.to_dict(),
               "state_dict": state, "meta": info}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        os.close(fd)
        try:
            torch.save(payload, tmp)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError as exc:
        raise CheckpointError(f"cannot write checkpoint {path}: {exc}") from exc
    logger.info("saved checkpoint %s (%.2f MB)", path, path.stat().st_size / 1e6)
    return path


def _describe(value: Any) -> str:
    return repr(tuple(value)) if isinstance(value, (list, tuple)) else repr(value)


def _check_vocabulary(path: Path, config_dict: Mapping[str, Any]) -> None:
    names = config_dict.get("class_names")
    if not isinstance(names, Mapping):
        raise CheckpointError(f"checkpoint {path}: config has no class_names")
    if sorted(names) != sorted(TASKS):
        raise CheckpointError(f"checkpoint {path}: tasks are {sorted(names)} but this code "
                              f"expects {sorted(TASKS)}")
    for task in TASKS:
        theirs = tuple(names[task]) if isinstance(names[task], (list, tuple)) else names[task]
        if theirs != tuple(CLASS_NAMES[task]):
            raise CheckpointError(f"checkpoint {path}: class names for {task!r} are "
                                  f"{_describe(theirs)} but this code expects "
                                  f"{_describe(CLASS_NAMES[task])}")
    codes = config_dict.get("light_codes")
    if not isinstance(codes, Mapping) or dict(codes) != dict(LIGHT_CODES):
        raise CheckpointError(f"checkpoint {path}: light codes are {codes!r} but this code "
                              f"expects {dict(LIGHT_CODES)!r}")


def _check_state_dict(path: Path, theirs: Mapping[str, Any], ours: Mapping[str, torch.Tensor]) -> None:
    missing = [k for k in ours if k not in theirs]
    unexpected = [k for k in theirs if k not in ours]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing tensors {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected tensors {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
        raise CheckpointError(f"checkpoint {path}: weights do not fit the architecture: "
                              + "; ".join(parts))
    for key, want in ours.items():
        got = theirs[key]
        if not isinstance(got, torch.Tensor):
            raise CheckpointError(f"checkpoint {path}: weight {key!r} is a {type(got).__name__}, "
                                  f"not a tensor")
        if tuple(got.shape) != tuple(want.shape):
            raise CheckpointError(f"checkpoint {path}: weight {key!r} has shape {tuple(got.shape)} "
                                  f"but the model built from its config expects {tuple(want.shape)}")


def load_checkpoint(path: PathLike = DEFAULT_WEIGHTS,
                    map_location: Union[str, torch.device] = "cpu") -> LoadedModel:
    """Load a checkpoint written by :func:`save_checkpoint` and check that it fits.

    Args:
        path: The checkpoint file (default: the shipped weights).
        map_location: Device for the tensors.

    Returns:
        ``LoadedModel(model in eval mode, config, meta)``.

    Raises:
        CheckpointError: The file is missing, unreadable or not a checkpoint, or its
            format version, architecture, class names, light codes or weight names /
            shapes differ from what this code expects; the message names the difference.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist or is not a file")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types for a bad file; all mean "unreadable"
        # torch's own message suggests weights_only=False, which we never want: say what it is.
        raise CheckpointError(f"checkpoint {path} cannot be read as a checkpoint: it is not a "
                              f"torch.save file of plain values and tensors "
                              f"({type(exc).__name__})") from exc
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(f"checkpoint {path} is not a signal_light_node checkpoint "
                              f"(no format_version)")
    version = payload["format_version"]
    if version not in SUPPORTED_FORMAT_VERSIONS:
        raise CheckpointError(f"checkpoint {path} has format version {version!r} but this code "
                              f"supports {list(SUPPORTED_FORMAT_VERSIONS)}")
    for key in ("config", "state_dict", "meta"):
        if not isinstance(payload.get(key), dict):
            raise CheckpointError(f"checkpoint {path} has no {key} dict")
    config_dict = payload["config"]
    arch = config_dict.get("arch")
    if arch not in known_archs():
        raise CheckpointError(f"checkpoint {path} has architecture {arch!r} but this code knows "
                              f"{list(known_archs())}")
    _check_vocabulary(path, config_dict)
    try:
        config = ModelConfig.from_dict(config_dict)
    except ConfigError as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from exc
    model = build_model(config)
    _check_state_dict(path, payload["state_dict"], model.state_dict())
    model.load_state_dict(payload["state_dict"])
    model.to(map_location)
    model.eval()
    return LoadedModel(model=model, config=config, meta=payload["meta"])
