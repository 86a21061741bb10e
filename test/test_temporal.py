"""Temporal evidence (model/temporal.py), the temporal model's state and its warm start."""

import numpy as np
import pytest
import torch

from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.model import ModelConfig, build_model
from signal_light_node.model.temporal import (EVIDENCE_CHANNELS, best_shifts, evidence_step,
                                              shift_images)
from signal_light_node.model.warm_start import warm_start
from signal_light_node.runtime.state_bank import StateBank


def _textured(n: int = 2, size: int = 32, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, 3, size, size, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("dy,dx", [(0, 0), (2, -1), (-2, 2), (1, 0)])
def test_best_shift_recovers_a_known_shift(dy, dx):
    ref = _textured()
    cur = torch.roll(ref, shifts=(dy, dx), dims=(2, 3))
    offsets = best_shifts(ref, cur, 2)
    aligned = shift_images(ref, offsets, 2)
    assert torch.allclose(aligned[..., 3:-3, 3:-3], cur[..., 3:-3, 3:-3])


def test_flat_crops_are_not_shifted():
    flat = torch.full((1, 3, 16, 16), 0.5)
    assert best_shifts(flat, flat, 2).tolist() == [[2, 2]]


def test_steady_lamp_gives_no_evidence_a_flashing_one_does():
    base = _textured(1, 32)
    lit = base.clone()
    lit[:, 2, 8:12, 4:8] = 1.0  # a bright red patch
    history = torch.zeros(1, EVIDENCE_CHANNELS, 32, 32)
    seen = torch.zeros(1, 1, 1, 1)
    steady = []
    for _ in range(12):  # the same lit lamp every frame
        ev, history = evidence_step(lit, history, seen, 2, 0.15)
        seen = torch.ones_like(seen)
        steady.append(float(ev.abs().max()))
    assert steady[0] == 0.0  # a new track has no history
    assert max(steady[1:]) < 1e-6
    flashing = []
    for i in range(12):  # lit, dark, lit, dark ...
        ev, history = evidence_step(lit if i % 2 else base, history, seen, 2, 0.15)
        # The red channel of both differences (frame and running mean) at the lamp.
        flashing.append(float(ev[:, [2, 5], 8:12, 4:8].abs().mean()))
    assert min(flashing[2:]) > 0.2


def test_temporal_model_steps_equal_the_sequence_and_carry_history():
    model = build_model(ModelConfig(input_size=32, temporal_input=True,
                                    backbone_channels=(8, 8, 8), lstm_hidden=(8, 8))).eval()
    crops = torch.rand(3, 5, 3, 32, 32)
    with torch.no_grad():
        logits, final = model.forward_sequence(crops)
        state = model.initial_state(3)
        assert len(state) == 3 and state[-1][0].shape == (3, EVIDENCE_CHANNELS, 32, 32)
        for t in range(5):
            step, state = model.step_logits(crops[:, t], state)
            assert torch.allclose(step["intent"], logits["intent"][:, t], atol=1e-5)
    for (a, b), (c, d) in zip(state, final):
        assert torch.allclose(a, c, atol=1e-5) and torch.allclose(b, d, atol=1e-5)
    assert float(state[-1][1].min()) == 1.0  # every track has a history now


def test_state_bank_keeps_the_history_per_track():
    model = build_model(ModelConfig(input_size=32, temporal_input=True,
                                    backbone_channels=(8, 8, 8), lstm_hidden=(8, 8))).eval()
    bank = StateBank(model, track_timeout_s=1.0, max_tracks=8, max_gap_s=2.0)
    crops = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        state = bank.gather(["a", "b"], 0)
        _, new = model.step(crops, state)
        bank.store(["a", "b"], new, 0)
        again = bank.gather(["b"], 100_000_000)
    assert torch.allclose(again[-1][0][0, :3], crops[1], atol=1e-6)
    assert float(again[-1][1]) == 1.0


def test_config_checks_temporal_fields():
    with pytest.raises(ConfigError, match="temporal_input"):
        ModelConfig(temporal_input="yes")
    with pytest.raises(ConfigError, match="align_radius"):
        ModelConfig(align_radius=40)
    with pytest.raises(ConfigError, match="mean_rate"):
        ModelConfig(mean_rate=0.0)


def test_warm_start_keeps_the_old_outputs():
    small = dict(input_size=32, backbone_channels=(8, 8, 8), lstm_hidden=(8, 8))
    old = build_model(ModelConfig(**small)).eval()
    new = build_model(ModelConfig(temporal_input=True, **small)).eval()
    grown = warm_start(new, old.state_dict())
    assert grown == ["backbone.0.0.weight"]
    crops = torch.rand(2, 4, 3, 32, 32)
    with torch.no_grad():
        a, _ = old.forward_sequence(crops)
        b, _ = new.forward_sequence(crops)
    for task in a:
        assert torch.allclose(a[task], b[task], atol=1e-5)


def test_warm_start_refuses_what_does_not_fit():
    a = build_model(ModelConfig(input_size=32, backbone_channels=(8, 8, 8), lstm_hidden=(8, 8)))
    b = build_model(ModelConfig(input_size=32, backbone_channels=(8, 16, 8), lstm_hidden=(8, 8)))
    with pytest.raises(CheckpointError, match="does not fit"):
        warm_start(b, a.state_dict())
    with pytest.raises(CheckpointError, match="no tensor"):
        warm_start(b, {"unrelated": torch.zeros(1)})


def test_freeze_norms_keeps_batch_norm_statistics_while_weights_train():
    model = build_model(ModelConfig(input_size=32, backbone_channels=(8, 8, 8), lstm_hidden=(8, 8)))
    model.freeze_norms()
    model.train()
    norms = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    before = [m.running_mean.clone() for m in norms]
    logits, _ = model.forward_sequence(torch.rand(2, 3, 3, 32, 32) * 3.0)
    logits["intent"].sum().backward()
    assert all(torch.equal(a, m.running_mean) for a, m in zip(before, norms))
    assert model.backbone[0][0].weight.grad is not None  # the weights still learn


def test_warm_start_can_give_new_channels_small_random_weights():
    small = dict(input_size=32, backbone_channels=(8, 8, 8), lstm_hidden=(8, 8))
    old = build_model(ModelConfig(**small))
    new = build_model(ModelConfig(temporal_input=True, **small))
    warm_start(new, old.state_dict(), grown_scale=0.25)
    weight = new.backbone[0][0].weight.detach()
    trained = old.backbone[0][0].weight.detach()
    assert torch.equal(weight[:, :3], trained)
    ratio = float(weight[:, 3:].std() / trained.std())
    assert 0.15 < ratio < 0.35, ratio
