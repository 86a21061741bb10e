"""Model configuration, the model factory and the one-file checkpoint format.

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
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Dict, Mapping, NamedTuple, Optional, Tuple, Union

import torch
from torch import nn

from signal_light_node import __version__
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.labels import CLASS_NAMES, LIGHT_CODES, TASKS

logger = logging.getLogger(__name__)

#: Version of the file layout written by :func:`save_checkpoint`.
FORMAT_VERSION = 1
SUPPORTED_FORMAT_VERSIONS = (1,)

#: The weights shipped inside the package and loaded by the node by default.
DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "default.pt"

PathLike = Union[str, os.PathLike]


def _int_tuple(value: Any, name: str) -> Tuple[int, ...]:
    try:
        out = tuple(int(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"model config {name} must be a list of integers, got {value!r}") from None
    if not out or any(v <= 0 for v in out):
        raise ConfigError(f"model config {name} must be non-empty positive integers, got {value!r}")
    return out


def _float3(value: Any, name: str) -> Tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"model config {name} must be 3 numbers, got {value!r}") from None
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise ConfigError(f"model config {name} must be 3 finite numbers (B, G, R), got {value!r}")
    return out  # type: ignore[return-value]


@dataclass(frozen=True)
class ModelConfig:
    """Everything needed to build a model and feed it exactly as in training.

    Attributes:
        arch: Architecture name, a key of the factory registry.
        input_size: Side S of the square input crop in pixels.
        attention_channels: Widths of the hidden layers of the attention FCN (its last
            layer always has one channel); dilations are ``ATTENTION_DILATIONS``.
        use_attention: False skips the attention mask (ablation).
        backbone_channels: Width of each backbone stage; each stage halves the
            resolution, so the ConvLSTM map is S / 2**len(backbone_channels).
        lstm_hidden: Hidden channels of each stacked ConvLSTM layer.
        lstm_kernel: Kernel size of the ConvLSTM gate convolutions.
        head_channels: Channels of the 1x1 conv that reduces the last hidden state
            before it is pooled to a ``head_grid`` x ``head_grid`` map.
        head_grid: Side of the pooled map fed to the dense layer (keeps left/right
            position, which a global pool would lose).
        fc_hidden: Width of the shared dense layer before the task heads.
        dropout: Dropout probability of the dense layer.
        lstm_dropout: Dropout probability on each ConvLSTM layer's output in training.
        norm: Normalisation of the backbone convs, "batch" or "group".
        mean: Per-channel mean subtracted from the [0, 1] input, in ``channel_order``.
        std: Per-channel standard deviation dividing the input, in ``channel_order``.
        channel_order: Channel order of the input crops, always "bgr".
        crop_margin: Margin of the crops the model was trained on (``crops.CropConfig``).
        class_names: Class names per task, index i = class value i.
        light_codes: ``LightClassification`` code of each light head.
        temporal_input: Feed the backbone the crop's change against the track's
            previous crop and running mean as well (``model.temporal``); the state then
            carries that history.
        align_radius: Largest shift in pixels tried when re-aligning the history.
        mean_rate: Weight of each new crop in the running mean.
    """

    arch: str = "convlstm_attention"
    input_size: int = 64
    attention_channels: Tuple[int, ...] = (8, 8, 8)
    use_attention: bool = True
    backbone_channels: Tuple[int, ...] = (24, 48, 64)
    lstm_hidden: Tuple[int, ...] = (48, 48)
    lstm_kernel: int = 3
    head_channels: int = 16
    head_grid: int = 4
    fc_hidden: int = 128
    dropout: float = 0.5
    lstm_dropout: float = 0.1
    norm: str = "batch"
    mean: Tuple[float, float, float] = (0.4, 0.4, 0.4)
    std: Tuple[float, float, float] = (0.25, 0.25, 0.25)
    channel_order: str = "bgr"
    crop_margin: float = CropConfig.margin
    # hash=False: dicts are unhashable, the other fields identify a config well enough.
    class_names: Mapping[str, Tuple[str, ...]] = field(
        default_factory=lambda: {t: tuple(CLASS_NAMES[t]) for t in TASKS}, hash=False)
    light_codes: Mapping[str, int] = field(default_factory=lambda: dict(LIGHT_CODES), hash=False)
    temporal_input: bool = False
    align_radius: int = 2
    mean_rate: float = 0.15

    def __post_init__(self) -> None:
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        if not isinstance(self.arch, str) or not self.arch:
            raise ConfigError(f"model config arch must be a non-empty string, got {self.arch!r}")
        try:
            set_("input_size", int(self.input_size))
            set_("lstm_kernel", int(self.lstm_kernel))
            set_("head_channels", int(self.head_channels))
            set_("head_grid", int(self.head_grid))
            set_("fc_hidden", int(self.fc_hidden))
            set_("dropout", float(self.dropout))
            set_("lstm_dropout", float(self.lstm_dropout))
            set_("crop_margin", float(self.crop_margin))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"model config has a value of the wrong type: {exc}") from None
        # bool("false") is True: refuse anything but a real boolean (CLI values are JSON).
        for name in ("use_attention", "temporal_input"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"model config {name} must be true or false, got "
                                  f"{getattr(self, name)!r}")
        set_("mean_rate", float(self.mean_rate))
        if not 0.0 < self.mean_rate <= 1.0:
            raise ConfigError(f"model config mean_rate must be in (0, 1], got {self.mean_rate}")
        if isinstance(self.align_radius, bool) or not isinstance(self.align_radius, int) \
                or not 0 <= self.align_radius <= self.input_size // 4:
            raise ConfigError(f"model config align_radius must be an integer in 0..input_size/4, "
                              f"got {self.align_radius!r}")
        set_("attention_channels", _int_tuple(self.attention_channels, "attention_channels"))
        set_("backbone_channels", _int_tuple(self.backbone_channels, "backbone_channels"))
        set_("lstm_hidden", _int_tuple(self.lstm_hidden, "lstm_hidden"))
        set_("mean", _float3(self.mean, "mean"))
        set_("std", _float3(self.std, "std"))
        if not 8 <= self.input_size <= 512:
            raise ConfigError(f"model config input_size must be in 8..512, got {self.input_size}")
        if self.lstm_kernel < 1 or self.lstm_kernel % 2 == 0:
            raise ConfigError(f"model config lstm_kernel must be odd and >= 1, got {self.lstm_kernel}")
        for name in ("head_channels", "head_grid", "fc_hidden"):
            if getattr(self, name) < 1:
                raise ConfigError(f"model config {name} must be >= 1, got {getattr(self, name)}")
        for name in ("dropout", "lstm_dropout"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ConfigError(f"model config {name} must be in [0, 1), got {getattr(self, name)}")
        if any(s <= 0 for s in self.std):
            raise ConfigError(f"model config std must be positive, got {self.std}")
        if self.norm not in ("batch", "group"):
            raise ConfigError(f"model config norm must be 'batch' or 'group', got {self.norm!r}")
        if self.channel_order != "bgr":
            raise ConfigError(f"model config channel_order must be 'bgr', got {self.channel_order!r}")
        CropConfig(size=self.input_size, margin=self.crop_margin)  # validates the margin
        try:
            set_("class_names", {str(t): tuple(str(n) for n in names)
                                 for t, names in dict(self.class_names).items()})
            set_("light_codes", {str(k): int(v) for k, v in dict(self.light_codes).items()})
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"model config class_names / light_codes are malformed: {exc}") from None

    @property
    def num_classes(self) -> Dict[str, int]:
        """Number of classes per task, in ``TASKS`` order."""
        return {t: len(self.class_names[t]) for t in TASKS}

    @property
    def feature_size(self) -> int:
        """Side of the backbone's output map (the ConvLSTM state) for ``input_size``."""
        side = self.input_size
        for _ in self.backbone_channels:
            side = (side + 1) // 2  # a 3x3 stride-2 conv with padding 1
        return side

    def crop_config(self) -> CropConfig:
        """The crop settings that reproduce the training crops."""
        return CropConfig(size=self.input_size, margin=self.crop_margin)

    def to_dict(self) -> Dict[str, Any]:
        """Plain dict (lists, not tuples) for the checkpoint and for JSON."""
        out = asdict(self)
        for key, value in out.items():
            if isinstance(value, tuple):
                out[key] = list(value)
        out["class_names"] = {t: list(n) for t, n in self.class_names.items()}
        out["light_codes"] = dict(self.light_codes)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ModelConfig":
        """Inverse of :meth:`to_dict`.

        Raises:
            ConfigError: ``data`` has unknown keys or bad values.
        """
        if not isinstance(data, Mapping):
            raise ConfigError(f"model config must be a dict, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"model config has unknown keys {unknown}")
        return cls(**dict(data))

    def replace(self, **changes: Any) -> "ModelConfig":
        """A copy with some fields changed (validated again)."""
        data = asdict(self)
        data.update(changes)
        return ModelConfig(**data)


# ---------------------------------------------------------------------------- factory

Builder = Callable[[ModelConfig], nn.Module]
_REGISTRY: Dict[str, Builder] = {}


def register_arch(name: str, builder: Builder) -> None:
    """Make ``build_model`` build ``builder(config)`` for ``config.arch == name``."""
    _REGISTRY[name] = builder


def known_archs() -> Tuple[str, ...]:
    """Architecture names the factory can build."""
    return tuple(sorted(_REGISTRY))


def _build_convlstm_attention(config: ModelConfig) -> nn.Module:
    from signal_light_node.model.network import LightStateNet

    return LightStateNet(config)


register_arch("convlstm_attention", _build_convlstm_attention)


def build_model(config: ModelConfig) -> nn.Module:
    """Build a freshly initialised model for ``config``.

    Raises:
        ConfigError: ``config.arch`` is not a registered architecture.
    """
    builder = _REGISTRY.get(config.arch)
    if builder is None:
        raise ConfigError(f"unknown model architecture {config.arch!r}; known: {list(known_archs())}")
    return builder(config)


# ------------------------------------------------------------------------- checkpoints

class LoadedModel(NamedTuple):
    """A model loaded from a checkpoint (in eval mode), its config and its metadata."""

    model: nn.Module
    config: ModelConfig
    meta: Dict[str, Any]


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
    if arch not in _REGISTRY:
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
