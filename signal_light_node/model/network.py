"""The per-track light-state network: attention FCN, CNN, stacked ConvLSTM, task heads.

One step maps a batch of crops and the tracks' recurrent states to per-task logits
and new states::

    crop [N,3,S,S] in [0,1] BGR
      -> normalise (config mean/std)
      -> attention FCN (3x3 convs, dilations 1,2,2,1, last layer 1 channel + sigmoid)
         mask [N,1,S,S], multiplied with the normalised crop       (skipped if disabled)
      -> with ``temporal_input``: 6 more channels, the crop minus the track's previous
         crop and minus its running mean, both re-aligned (``model.temporal``); the
         previous crop and the mean are part of the track's state
      -> backbone: per stage a stride-2 3x3 conv and a 3x3 conv, norm + ReLU
         -> [N,C,S/8,S/8] for three stages
      -> ConvLSTM layer 1 -> ConvLSTM layer 2  (explicit (h, c) per layer)
      -> heads on the last h: 1x1 conv pooled to a small grid (keeps where a lamp is:
         the vehicle's left/right side) + global max of h (is any lamp lit), a shared
         dense layer with dropout, one linear layer per task.

The per-frame part (normalisation, attention, backbone) has no state, so
``forward_sequence`` runs it on all frames at once and only unrolls the recurrence;
in eval mode this is the same computation as stepping frame by frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Dict, List, Mapping, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from signal_light_node.errors import ConfigError, CropError
from signal_light_node.labels import TASKS
from signal_light_node.model.interface import State, state_batch_size
from signal_light_node.model.temporal import EVIDENCE_CHANNELS, evidence_step

#: Memory layout of activations, weights and states: on CPU (oneDNN) channels-last
#: convolutions run about 1.5x faster than NCHW ones for these small maps.
MEMORY_FORMAT = torch.channels_last

if TYPE_CHECKING:  # pragma: no cover - typing only
    from signal_light_node.model.config import ModelConfig

#: Output key of the training-only lit-map head (``lit_map_head``), channels: brake,
#: left, right (``synth.lit_maps.LIT_MAP_CHANNELS``); flattened to ``[N, T, 3 F F]``.
LIT_MAP_KEY = "lit_map"
LIT_MAP_OUTPUTS = 3

#: Dilations of the attention FCN's four 3x3 layers (as in the research design).
ATTENTION_DILATIONS: Tuple[int, ...] = (1, 2, 2, 1)


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    # Largest group count <= 8 that divides the channels.
    groups = next(g for g in (8, 4, 2, 1) if channels % g == 0)
    return nn.GroupNorm(groups, channels)


def _conv_block(c_in: int, c_out: int, stride: int, norm: str) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
        _norm(norm, c_out),
        nn.ReLU(inplace=True),
    )


def register_normalisation(module: nn.Module, config: "ModelConfig") -> None:
    """Give ``module`` the ``_mean`` / ``_inv_std`` buffers of the config's input statistics.

    Not persistent: the config is the source of truth for normalisation.
    """
    mean = torch.tensor(config.mean, dtype=torch.float32).view(1, 3, 1, 1)
    std = torch.tensor(config.std, dtype=torch.float32).view(1, 3, 1, 1)
    module.register_buffer("_mean", mean, persistent=False)
    module.register_buffer("_inv_std", 1.0 / std, persistent=False)


def check_crops(crops: Tensor, ndim: int, size: int) -> None:
    """Raise :class:`CropError` unless ``crops`` is ``[N, 3, S, S]`` (ndim 4) or
    ``[N, T, 3, S, S]`` (ndim 5) with ``S == size``."""
    if crops.dim() != ndim or crops.shape[-3] != 3 or crops.shape[-1] != size \
            or crops.shape[-2] != size:
        want = "[N, 3, S, S]" if ndim == 4 else "[N, T, 3, S, S]"
        raise CropError(f"model input must be {want} with S={size}, got {tuple(crops.shape)}")
    if ndim == 5 and crops.shape[1] == 0:
        raise CropError("forward_sequence needs at least one frame, got T=0")


def eval_frozen(model: nn.Module, frozen: List[nn.Module], norms_frozen: bool) -> None:
    """After ``model.train(mode)``: frozen parts and, if asked, every batch norm stay in
    eval mode (their running statistics are kept)."""
    for module in frozen:
        module.eval()
    if norms_frozen:
        for module in model.modules():
            if isinstance(module, nn.modules.batchnorm._BatchNorm):
                module.eval()


def apply_temperatures(logits: Dict[str, Tensor], temperatures: Mapping[str, float]
                       ) -> Dict[str, Tensor]:
    """Each task's logits divided by its temperature (``ModelConfig.temperatures``; a
    task without one, or with 1.0, is left as it is, so an uncalibrated graph is unchanged)."""
    return {t: v if temperatures.get(t, 1.0) == 1.0 else v * (1.0 / temperatures[t])
            for t, v in logits.items()}


def apply_on_offsets(logits: Dict[str, Tensor], on_offsets: Mapping[str, float],
                     class_names: Mapping[str, Sequence[str]]) -> Dict[str, Tensor]:
    """Each task of ``on_offsets`` with ON shifted against OFF by its offset in log-odds
    (``ModelConfig.on_offsets``), P(UNKNOWN) unchanged: the pair's total stays, split anew.
    An offset added to the ON logit alone would move probability to UNKNOWN too, and make
    UNKNOWNs where a threshold was meant to move between ON and OFF (docs/model.md)."""
    out = dict(logits)
    for task, offset in on_offsets.items():
        if offset == 0.0:
            continue
        on, off = class_names[task].index("ON"), class_names[task].index("OFF")
        columns = list(logits[task].unbind(-1))
        pair = torch.logsumexp(torch.stack((columns[on], columns[off]), -1), -1)
        gap = columns[on] - columns[off] + offset
        columns[on], columns[off] = pair + F.logsigmoid(gap), pair + F.logsigmoid(-gap)
        out[task] = torch.stack(columns, -1)
    return out


def calibrated_logits(logits: Dict[str, Tensor], config: "ModelConfig") -> Dict[str, Tensor]:
    """The heads' logits as published: temperatures, then ON offsets (both from ``config``)."""
    return apply_on_offsets(apply_temperatures(logits, config.temperatures), config.on_offsets,
                            config.class_names)


class AttentionFCN(nn.Module):
    """Fully convolutional net giving one attention value in [0, 1] per pixel."""

    def __init__(self, channels: Tuple[int, ...]) -> None:
        super().__init__()
        widths = tuple(channels) + (1,)
        if len(widths) != len(ATTENTION_DILATIONS):
            raise ConfigError(f"attention FCN has {len(ATTENTION_DILATIONS)} layers, so "
                              f"attention_channels needs {len(ATTENTION_DILATIONS) - 1} widths, "
                              f"got {tuple(channels)}")
        layers: List[nn.Module] = []
        c_in = 3
        for i, (c_out, dilation) in enumerate(zip(widths, ATTENTION_DILATIONS)):
            layers.append(nn.Conv2d(c_in, c_out, 3, padding=dilation, dilation=dilation))
            if i < len(widths) - 1:
                layers.append(nn.ReLU(inplace=True))
            c_in = c_out
        self.body = nn.Sequential(*layers)
        # Start mostly open (sigmoid(1) ~ 0.73) so the backbone sees the crop from step one.
        nn.init.constant_(self.body[-1].bias, 1.0)

    def forward(self, x: Tensor) -> Tensor:
        return torch.sigmoid(self.body(x))


class ConvLSTMCell(nn.Module):
    """Convolutional LSTM cell: all four gates from one conv over ``[x, h]``."""

    def __init__(self, c_in: int, hidden: int, kernel: int) -> None:
        super().__init__()
        self.hidden = hidden
        self.gates = nn.Conv2d(c_in + hidden, 4 * hidden, kernel, padding=kernel // 2)
        with torch.no_grad():
            # Forget-gate bias 1: remember by default early in training.
            self.gates.bias.zero_()
            self.gates.bias[hidden:2 * hidden].fill_(1.0)

    def forward(self, x: Tensor, h: Optional[Tensor], c: Optional[Tensor]
                ) -> Tuple[Tensor, Tensor]:
        """One step; ``h`` and ``c`` None stand for the zero state (a new track)."""
        if h is None or c is None:
            # h = 0 adds nothing to the gates and c = 0 nothing to the cell: convolving x
            # alone saves about a third of the ConvLSTM work for a zero state, which is
            # every frame of per-frame training.
            weight = self.gates.weight[:, :x.shape[1]].contiguous(memory_format=MEMORY_FORMAT)
            i, _, o, g = F.conv2d(x, weight, self.gates.bias,
                                  padding=self.gates.padding).chunk(4, 1)
            c = torch.sigmoid(i) * torch.tanh(g)
        else:
            i, f, o, g = self.gates(torch.cat((x, h), 1)).chunk(4, 1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        return h, c


def convlstm_stack(c_in: int, config: "ModelConfig") -> nn.ModuleList:
    """The stacked ConvLSTM cells of ``config.lstm_hidden`` on ``c_in`` input channels."""
    cells = []
    for hidden in config.lstm_hidden:
        cells.append(ConvLSTMCell(c_in, hidden, config.lstm_kernel))
        c_in = hidden
    return nn.ModuleList(cells)


class LightStateNet(nn.Module):
    """Attention + CNN + two ConvLSTM layers + multi-task heads (see module doc).

    Implements :class:`signal_light_node.model.interface.LightStateModel`.
    """

    def __init__(self, config: "ModelConfig") -> None:
        super().__init__()
        self.config = config
        self.input_size = config.input_size
        register_normalisation(self, config)

        self.attention_net: Optional[AttentionFCN] = (
            AttentionFCN(config.attention_channels) if config.use_attention else None)

        stages: List[nn.Module] = []
        c_in = 3 + (EVIDENCE_CHANNELS if config.temporal_input else 0)
        for width in config.backbone_channels:
            stages.append(_conv_block(c_in, width, 2, config.norm))
            stages.append(_conv_block(width, width, 1, config.norm))
            c_in = width
        self.backbone = nn.Sequential(*stages)

        # Training only (``lit_map_head``): where each signal's lamps are lit, per cell.
        self.lit_map_head: Optional[nn.Conv2d] = (
            nn.Conv2d(c_in, LIT_MAP_OUTPUTS, 1) if config.lit_map_head else None)

        self.cells = convlstm_stack(c_in, config)
        self.lstm_dropout = nn.Dropout(config.lstm_dropout)

        last = config.lstm_hidden[-1]
        self.head_conv = nn.Conv2d(last, config.head_channels, 1)
        grid = config.head_grid
        self.fc = nn.Sequential(
            nn.Linear(config.head_channels * grid * grid + last, config.fc_hidden),
            nn.ReLU(inplace=True),
            nn.Dropout(config.dropout),
        )
        self.heads = nn.ModuleDict({t: nn.Linear(config.fc_hidden, config.num_classes[t])
                                    for t in TASKS})
        self._encoder_frozen = False
        self._norms_frozen = False
        self._init_weights()
        self.to(memory_format=MEMORY_FORMAT)

    def _init_weights(self) -> None:
        # He init keeps activations at unit scale through the ReLU stack (PyTorch's default
        # shrinks them ~2.5x per layer, which starves an untrained eval-mode net of signal).
        convs = list(self.backbone.modules())
        if self.attention_net is not None:
            convs += list(self.attention_net.body)[:-1]
        for module in convs:
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_in", nonlinearity="relu")
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

    # ------------------------------------------------------------------ per-frame part

    def _normalise(self, crops: Tensor) -> Tensor:
        x = crops.contiguous(memory_format=MEMORY_FORMAT)  # no copy for to_input's tensors
        return (x - self._mean) * self._inv_std

    def _check_crops(self, crops: Tensor, ndim: int) -> None:
        check_crops(crops, ndim, self.input_size)

    def attention(self, crops: Tensor) -> Tensor:
        """Attention mask ``[N, 1, S, S]`` in [0, 1] of ``[N, 3, S, S]`` crops in [0, 1].

        All ones when the model was built with ``use_attention=False``.
        """
        self._check_crops(crops, 4)
        if self.attention_net is None:
            return crops.new_ones((crops.shape[0], 1) + tuple(crops.shape[2:]))
        return self.attention_net(self._normalise(crops))

    def encode(self, crops: Tensor, evidence: Optional[Tensor] = None) -> Tensor:
        """Per-frame features ``[N, C, F, F]`` (no recurrence) of ``[N, 3, S, S]`` crops.

        Args:
            crops: ``[N, 3, S, S]`` in [0, 1].
            evidence: ``[N, 6, S, S]`` temporal evidence (``model.temporal``); required
                exactly when the config has ``temporal_input``.
        """
        return self._encode(crops, evidence)[0]

    def _encode(self, crops: Tensor, evidence: Optional[Tensor]) -> Tuple[Tensor, Optional[Tensor]]:
        """:meth:`encode` and the attention mask it applied (None without attention)."""
        x = self._normalise(crops)
        mask = None
        if self.attention_net is not None:
            mask = self.attention_net(x)
            x = x * mask
        if self.config.temporal_input:
            if evidence is None:
                raise ConfigError("this model takes temporal evidence with its crops")
            # Differences are scaled like the crop, by 1/std per channel.
            scale = torch.cat((self._inv_std, self._inv_std), 1)
            x = torch.cat((x, (evidence * scale).contiguous(memory_format=MEMORY_FORMAT)), 1)
        return self.backbone(x), mask

    def _evidence(self, crops: Tensor, state: Optional[State]) -> Tuple[Tensor, Tuple[Tensor, Tensor]]:
        """Temporal evidence of one frame and the track history after it."""
        if state is None:
            n, _, size, _ = crops.shape
            history = crops.new_zeros((n, EVIDENCE_CHANNELS, size, size))
            seen = crops.new_zeros((n, 1, 1, 1))
        else:
            history, seen = state[-1]
        evidence, history = evidence_step(crops, history, seen, self.config.align_radius,
                                          self.config.mean_rate)
        return evidence, (history, torch.ones_like(seen))

    def _encoder_modules(self) -> List[nn.Module]:
        return [m for m in (self.attention_net, self.backbone) if m is not None]

    def freeze_encoder(self) -> None:
        """Fix the per-frame part (attention, backbone): no gradients, norms in eval mode.

        Training then only moves the ConvLSTM and the heads, and back-propagation stops
        at the features, so a step costs a fraction of a full one (used to learn time
        on top of a per-frame pre-trained encoder).
        """
        for module in self._encoder_modules():
            module.requires_grad_(False)
        self._encoder_frozen = True
        self.train(self.training)

    def freeze_norms(self) -> None:
        """Keep every normalisation layer's running statistics as they are.

        Fine-tuning on augmented data would otherwise move the batch-norm statistics
        towards the augmented distribution, which the node never sees; the weights still
        learn.
        """
        self._norms_frozen = True
        self.train(self.training)

    def train(self, mode: bool = True) -> "LightStateNet":
        """``nn.Module.train``, except that a frozen encoder or frozen norms stay in eval mode."""
        super().train(mode)
        eval_frozen(self, self._encoder_modules() if self._encoder_frozen else [],
                    self._norms_frozen)
        return self

    def output_layers(self, task: str) -> List[nn.Module]:
        """The layers whose logits are ``task``'s (one: its head)."""
        return [self.heads[task]]

    # ------------------------------------------------------------------ recurrent part

    def initial_state(self, n: int) -> State:
        """Zero state for ``n`` new tracks, on the model's device."""
        ref = self._mean
        side = self.config.feature_size
        def zeros(channels: int) -> Tensor:
            return ref.new_zeros((n, channels, side, side)).contiguous(memory_format=MEMORY_FORMAT)

        state = tuple((zeros(cell.hidden), zeros(cell.hidden)) for cell in self.cells)
        if self.config.temporal_input:
            # The track's history: previous crop + running mean, and whether it has one.
            size = self.input_size
            state += ((ref.new_zeros((n, EVIDENCE_CHANNELS, size, size)),
                       ref.new_zeros((n, 1, 1, 1))),)
        return state

    def _state_layers(self) -> int:
        return len(self.cells) + (1 if self.config.temporal_input else 0)

    def _check_state(self, state: State, n: int) -> None:
        if len(state) != self._state_layers():
            raise ConfigError(f"state has {len(state)} layers but the model has "
                              f"{self._state_layers()}")
        if state_batch_size(state) != n:
            raise ConfigError(f"state holds {state_batch_size(state)} tracks but {n} crops were given")

    def _recur(self, features: Tensor, state: Optional[State]) -> Tuple[Tensor, State]:
        """One ConvLSTM step of both layers; ``state`` None is the zero state."""
        x = features
        new_state = []
        for index, cell in enumerate(self.cells):
            h = c = None
            if state is not None:
                # States may come back NCHW (e.g. via a flat state bank); the convs want
                # channels-last.
                h = state[index][0].contiguous(memory_format=MEMORY_FORMAT)
                c = state[index][1].contiguous(memory_format=MEMORY_FORMAT)
            h, c = cell(x, h, c)
            new_state.append((h, c))
            x = self.lstm_dropout(h)  # dropout on the output only, never on the carried state
        return x, tuple(new_state)

    def _heads(self, hidden: Tensor) -> Dict[str, Tensor]:
        grid = F.adaptive_avg_pool2d(F.relu(self.head_conv(hidden)), self.config.head_grid)
        pooled = torch.cat((grid.flatten(1), hidden.amax(dim=(2, 3))), 1)
        z = self.fc(pooled)
        return calibrated_logits({t: head(z) for t, head in self.heads.items()}, self.config)

    # ---------------------------------------------------------------------- public API

    def step_logits(self, crops: Tensor, state: State) -> Tuple[Dict[str, Tensor], State]:
        """One frame for ``N`` tracks: logits ``[N, K]`` per task and the new state.

        Args:
            crops: float32 ``[N, 3, S, S]`` in [0, 1], BGR.
            state: The tracks' states (batch ``N``), e.g. from :meth:`initial_state`.
        """
        logits, state, _ = self._step(crops, state)
        return logits, state

    def _step(self, crops: Tensor, state: State
              ) -> Tuple[Dict[str, Tensor], State, Optional[Tensor]]:
        """Logits, new state and the attention mask applied (None without attention)."""
        self._check_crops(crops, 4)
        self._check_state(state, crops.shape[0])
        if not self.config.temporal_input:
            features, mask = self._encode(crops, None)
            hidden, state = self._recur(features, state)
            return self._heads(hidden), state, mask
        evidence, history = self._evidence(crops, state)
        features, mask = self._encode(crops, evidence)
        hidden, lstm_state = self._recur(features, state[:len(self.cells)])
        return self._heads(hidden), lstm_state + (history,), mask

    def step(self, crops: Tensor, state: State) -> Tuple[Dict[str, Tensor], State]:
        """Like :meth:`step_logits` but with probabilities (softmax over classes)."""
        logits, state = self.step_logits(crops, state)
        return {t: torch.softmax(v, dim=1) for t, v in logits.items()}, state

    def step_with_attention(self, crops: Tensor, state: State
                            ) -> Tuple[Dict[str, Tensor], State, Tensor]:
        """:meth:`step` plus the attention mask ``[N, 1, S, S]`` it applied (what
        :meth:`attention` gives for the same crops), so an overlay costs no second pass."""
        logits, state, mask = self._step(crops, state)
        if mask is None:
            mask = crops.new_ones((crops.shape[0], 1) + tuple(crops.shape[2:]))
        return {t: torch.softmax(v, dim=1) for t, v in logits.items()}, state, mask

    def forward_sequence(self, crops: Tensor,
                         state: Optional[State] = None) -> Tuple[Dict[str, Tensor], State]:
        """Run ``T`` frames of ``N`` tracks; equals calling :meth:`step_logits` T times.

        Args:
            crops: float32 ``[N, T, 3, S, S]`` in [0, 1], BGR.
            state: Initial state (batch ``N``); zeros when None.

        Returns:
            Logits ``[N, T, K]`` per task and the state after the last frame.
        """
        self._check_crops(crops, 5)
        n, t = crops.shape[:2]
        if state is not None:
            self._check_state(state, n)
        evidence = history = None
        if self.config.temporal_input:
            # The evidence is recursive (the running mean) but cheap: unroll it first,
            # then encode every frame at once.
            steps = []
            for i in range(t):
                ev, history = self._evidence(crops[:, i], state if i == 0 else (history,))
                steps.append(ev)
            evidence = torch.stack(steps, 1).flatten(0, 1)
            if state is not None:
                state = state[:len(self.cells)]
        features = self.encode(crops.flatten(0, 1), evidence)
        lit_map = None if self.lit_map_head is None else self.lit_map_head(features)
        features = features.reshape((n, t) + tuple(features.shape[1:]))
        hidden = []
        for i in range(t):
            h, state = self._recur(features[:, i], state)
            hidden.append(h)
        if history is not None:
            state = state + (history,)
        # Heads have no state either: run them once on every frame.
        logits = self._heads(torch.stack(hidden, 1).flatten(0, 1))
        if lit_map is not None:
            logits[LIT_MAP_KEY] = lit_map.contiguous()
        return {k: v.reshape(n, t, -1) for k, v in logits.items()}, state

    def forward(self, crops: Tensor, state: Optional[State] = None
                ) -> Tuple[Dict[str, Tensor], State]:
        """Alias of :meth:`forward_sequence` (so DistributedDataParallel can wrap the model)."""
        return self.forward_sequence(crops, state)
