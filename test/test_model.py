"""Tests of the light-state network and the streaming state helpers (tiny configs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from signal_light_node.errors import ConfigError, CropError
from signal_light_node.labels import CLASS_NAMES, TASKS
from signal_light_node.model import (
    LightStateModel,
    LightStateNet,
    ModelConfig,
    build_model,
    concat_states,
    select_state,
    split_state,
    state_batch_size,
    to_input,
)

TINY = dict(input_size=24, attention_channels=(4, 4, 4), backbone_channels=(6, 8, 8),
            lstm_hidden=(6, 5), head_channels=4, head_grid=2, fc_hidden=16)


def tiny_model(seed: int = 0, **changes) -> LightStateNet:
    torch.manual_seed(seed)
    model = build_model(ModelConfig(**{**TINY, **changes}))
    return model.eval()


def random_crops(n: int, size: int = 24, t: int | None = None, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    shape = (n, 3, size, size) if t is None else (n, t, 3, size, size)
    return torch.rand(shape, generator=gen)


def assert_states_equal(a, b) -> None:
    assert len(a) == len(b)
    for (ha, ca), (hb, cb) in zip(a, b):
        torch.testing.assert_close(ha, hb, rtol=0, atol=0)
        torch.testing.assert_close(ca, cb, rtol=0, atol=0)


def test_default_config_is_the_research_design() -> None:
    config = ModelConfig()
    model = build_model(config)
    assert isinstance(model, LightStateNet)
    assert isinstance(model, LightStateModel)
    assert config.arch == "convlstm_attention" and config.input_size == 64
    assert len(config.lstm_hidden) == 2 and config.feature_size == 8
    assert config.class_names == {t: CLASS_NAMES[t] for t in TASKS}
    assert config.crop_config().size == 64 and config.crop_config().margin == pytest.approx(0.15)
    dilations = [m.dilation[0] for m in model.attention_net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert dilations == [1, 2, 2, 1]


def test_step_shapes_and_probabilities() -> None:
    model = tiny_model()
    state = model.initial_state(5)
    with torch.no_grad():
        probs, new_state = model.step(random_crops(5), state)
    assert set(probs) == set(TASKS)
    for task in TASKS:
        assert probs[task].shape == (5, len(CLASS_NAMES[task]))
        assert torch.all(probs[task] >= 0)
        torch.testing.assert_close(probs[task].sum(1), torch.ones(5))
    assert [tuple(h.shape) for h, _ in new_state] == [(5, 6, 3, 3), (5, 5, 3, 3)]
    assert [tuple(c.shape) for _, c in new_state] == [(5, 6, 3, 3), (5, 5, 3, 3)]


def test_initial_state_is_zero_with_the_feature_map_shape() -> None:
    model = tiny_model()
    state = model.initial_state(3)
    assert len(state) == 2 and state_batch_size(state) == 3
    for (h, c), hidden in zip(state, TINY["lstm_hidden"]):
        assert h.shape == c.shape == (3, hidden, 3, 3)
        assert not h.any() and not c.any()
    assert state_batch_size(model.initial_state(0)) == 0


def test_step_by_step_equals_forward_sequence() -> None:
    model = tiny_model()
    crops = random_crops(3, t=6)
    with torch.no_grad():
        seq_logits, seq_state = model.forward_sequence(crops)
        state = model.initial_state(3)
        steps = []
        for t in range(crops.shape[1]):
            logits, state = model.step_logits(crops[:, t], state)
            steps.append(logits)
    for task in TASKS:
        assert seq_logits[task].shape == (3, 6, len(CLASS_NAMES[task]))
        stepped = torch.stack([s[task] for s in steps], 1)
        torch.testing.assert_close(seq_logits[task], stepped, rtol=0, atol=1e-5)
    for (hs, cs), (hq, cq) in zip(seq_state, state):
        torch.testing.assert_close(hs, hq, rtol=0, atol=1e-5)
        torch.testing.assert_close(cs, cq, rtol=0, atol=1e-5)


def test_zero_state_shortcut_gives_the_same_gradients() -> None:
    # forward_sequence without a state skips the h half of the first step's gate conv;
    # per-frame training relies on it learning exactly what an explicit zero state would.
    crops = random_crops(4, t=2)
    grads = []
    for explicit in (False, True):
        model = tiny_model().train()
        torch.manual_seed(3)  # same dropout masks
        state = model.initial_state(4) if explicit else None
        logits, _ = model.forward_sequence(crops, state)
        sum(v.square().sum() for v in logits.values()).backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters()})
    for name, grad in grads[0].items():
        torch.testing.assert_close(grad, grads[1][name], rtol=1e-5, atol=1e-6, msg=name)


def test_forward_sequence_continues_from_a_given_state() -> None:
    model = tiny_model()
    crops = random_crops(2, t=4)
    with torch.no_grad():
        whole, _ = model.forward_sequence(crops)
        _, mid = model.forward_sequence(crops[:, :2])
        rest, _ = model.forward_sequence(crops[:, 2:], mid)
    torch.testing.assert_close(whole["intent"][:, 2:], rest["intent"], rtol=0, atol=1e-5)


def test_state_carries_information() -> None:
    model = tiny_model()
    last = random_crops(2, seed=7)
    with torch.no_grad():
        _, state_a = model.forward_sequence(random_crops(2, t=3, seed=2))
        _, state_b = model.forward_sequence(random_crops(2, t=3, seed=3) * 0.2)
        logits_a, _ = model.step_logits(last, state_a)
        logits_b, _ = model.step_logits(last, state_b)
        logits_0, _ = model.step_logits(last, model.initial_state(2))
    assert (state_a[-1][0] - state_b[-1][0]).abs().max() > 1e-3
    # Same crop, different history: the outputs differ far beyond float rounding (~1e-7).
    for task in TASKS:
        assert (logits_a[task] - logits_b[task]).abs().max() > 1e-4
        assert (logits_a[task] - logits_0[task]).abs().max() > 1e-4


def test_tracks_in_a_batch_are_independent() -> None:
    model = tiny_model()
    crops = random_crops(4)
    state = model.initial_state(4)
    with torch.no_grad():
        batch, _ = model.step(crops, state)
        single, _ = model.step(crops[2:3], select_state(state, torch.tensor([2])))
    torch.testing.assert_close(batch["brake"][2:3], single["brake"], rtol=0, atol=1e-5)


def test_state_helpers_round_trip() -> None:
    model = tiny_model()
    with torch.no_grad():
        _, state = model.forward_sequence(random_crops(4, t=2))
    rows = split_state(state)
    assert len(rows) == 4 and all(state_batch_size(r) == 1 for r in rows)
    assert_states_equal(concat_states(rows), state)
    # Reordering by select equals concatenating the rows in that order.
    order = torch.tensor([3, 0, 2])
    assert_states_equal(select_state(state, order), concat_states([rows[3], rows[0], rows[2]]))
    assert_states_equal(select_state(state, torch.tensor([1])), rows[1])
    # A batch stepped together equals the rows stepped after split + concat.
    crops = random_crops(4, seed=5)
    with torch.no_grad():
        a, _ = model.step(crops, state)
        b, _ = model.step(crops, concat_states(split_state(state)))
    torch.testing.assert_close(a["intent"], b["intent"], rtol=0, atol=0)
    with pytest.raises(ConfigError):
        concat_states([])
    with pytest.raises(ConfigError, match="layer counts"):
        concat_states([state, state[:1]])


def test_split_state_makes_views_not_copies() -> None:
    model = tiny_model()
    state = model.initial_state(3)
    rows = split_state(state)
    assert rows[1][0][0].data_ptr() != state[0][0].data_ptr()
    assert rows[1][0][0].untyped_storage().data_ptr() == state[0][0].untyped_storage().data_ptr()


def test_attention_mask_range_and_size() -> None:
    model = tiny_model()
    crops = random_crops(3)
    with torch.no_grad():
        mask = model.attention(crops)
    assert mask.shape == (3, 1, 24, 24)
    assert mask.min() >= 0 and mask.max() <= 1
    assert mask.std() > 0  # a real per-pixel mask, not a constant


def test_model_without_attention() -> None:
    model = tiny_model(use_attention=False)
    assert model.attention_net is None
    assert not any("attention" in k for k in model.state_dict())
    crops = random_crops(2)
    with torch.no_grad():
        probs, _ = model.step(crops, model.initial_state(2))
        mask = model.attention(crops)
    torch.testing.assert_close(probs["view"].sum(1), torch.ones(2))
    assert torch.equal(mask, torch.ones(2, 1, 24, 24))


@pytest.mark.parametrize("size", [17, 32])
def test_any_input_size(size: int) -> None:
    model = tiny_model(input_size=size)
    with torch.no_grad():
        probs, state = model.step(random_crops(2, size), model.initial_state(2))
    assert state[0][0].shape[-1] == model.config.feature_size
    torch.testing.assert_close(probs["left"].sum(1), torch.ones(2))


def test_training_mode_has_gradients_and_dropout() -> None:
    model = tiny_model(dropout=0.5).train()
    crops = random_crops(4, t=3)
    logits, _ = model.forward_sequence(crops)
    loss = sum(torch.nn.functional.cross_entropy(v.flatten(0, 1), torch.zeros(12, dtype=torch.long))
               for v in logits.values())
    loss.backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None for g in grads)
    assert model.attention_net.body[0].weight.grad.abs().sum() > 0
    again, _ = model.forward_sequence(crops)
    assert not torch.allclose(logits["intent"], again["intent"])  # dropout is active


def test_frozen_encoder_gets_no_gradients_and_keeps_its_norm_statistics() -> None:
    model = tiny_model()
    model.freeze_encoder()
    model.train()
    # Norm layers of the frozen part stay in eval mode, whatever train() is asked for.
    assert not model.backbone.training and not model.attention_net.training
    assert model.cells.training and model.fc.training
    running_before = model.backbone[0][1].running_mean.clone()
    logits, _ = model.forward_sequence(random_crops(4, t=3))
    sum(v.sum() for v in logits.values()).backward()
    assert all(p.grad is None for p in model.backbone.parameters())
    assert all(p.grad is None for p in model.attention_net.parameters())
    assert all(p.grad is not None for p in model.cells.parameters())
    torch.testing.assert_close(model.backbone[0][1].running_mean, running_before)


def test_to_input_layout_and_range() -> None:
    crops = np.zeros((2, 24, 24, 3), np.uint8)
    crops[0, 3, 5] = (255, 128, 0)  # B, G, R of one pixel
    x = to_input(crops)
    assert x.shape == (2, 3, 24, 24) and x.dtype == torch.float32
    assert x[0, :, 3, 5].tolist() == pytest.approx([1.0, 128 / 255, 0.0])
    assert float(x.max()) == 1.0 and float(x.min()) == 0.0
    with pytest.raises(CropError, match="uint8"):
        to_input(crops.astype(np.float32))
    with pytest.raises(CropError):
        to_input(crops[0])


def test_bad_inputs_raise_clear_errors() -> None:
    model = tiny_model()
    with pytest.raises(CropError, match="S=24"):
        model.step(random_crops(2, 32), model.initial_state(2))
    with pytest.raises(ConfigError, match="3 tracks but 2 crops"):
        model.step(random_crops(2), model.initial_state(3))
    with pytest.raises(ConfigError, match="attention_channels"):
        build_model(ModelConfig(**{**TINY, "attention_channels": (4, 4)}))
    with pytest.raises(ConfigError, match="norm"):
        ModelConfig(norm="layer")
    with pytest.raises(ConfigError, match="use_attention must be true or false"):
        ModelConfig(use_attention="false")  # a string would have switched attention on
    with pytest.raises(ConfigError, match="unknown model architecture"):
        build_model(ModelConfig(arch="transformer"))


def test_group_norm_variant_works_for_any_batch_size() -> None:
    model = tiny_model(norm="group")
    with torch.no_grad():
        for n in (1, 3):
            probs, _ = model.step(random_crops(n), model.initial_state(n))
            assert probs["intent"].shape == (n, 5)


def test_config_dict_round_trip() -> None:
    config = ModelConfig(**TINY)
    again = ModelConfig.from_dict(config.to_dict())
    assert again == config
    assert config.replace(dropout=0.1).dropout == 0.1
    with pytest.raises(ConfigError, match="unknown keys"):
        ModelConfig.from_dict({**config.to_dict(), "colour": "red"})


def test_empty_batch_steps() -> None:
    model = tiny_model()
    with torch.no_grad():
        probs, state = model.step(random_crops(0), model.initial_state(0))
    assert probs["intent"].shape == (0, 5)
    assert state_batch_size(state) == 0 and split_state(state) == []


def test_gradient_flows_back_through_time() -> None:
    # Training unrolls the recurrence: the last output must depend on the first frame.
    model = tiny_model()
    crops = random_crops(2, t=4).requires_grad_(True)
    logits, _ = model.forward_sequence(crops)
    logits["intent"][:, -1].sum().backward()
    assert crops.grad[:, 0].abs().sum() > 0
    assert crops.grad[:, -1].abs().sum() > 0
