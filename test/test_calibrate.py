"""Per-head temperatures and the calibration error (training/calibrate.py)."""

import numpy as np
import pytest
import torch

from signal_light_node.model.checkpoint import load_checkpoint, save_checkpoint
from signal_light_node.model.config import ModelConfig
from signal_light_node.model.registry import build_model


def test_calibration_error_and_fitted_temperature():
    from signal_light_node.training.calibrate import expected_calibration_error, fit_temperature

    probs = np.array([[0.9, 0.1], [0.9, 0.1], [0.6, 0.4], [0.6, 0.4]])
    labels = np.array([0, 1, 0, 0])
    # bin 0.9: accuracy 0.5 vs 0.9; bin 0.6: accuracy 1.0 vs 0.6.
    assert expected_calibration_error(probs, labels) == pytest.approx(0.5 * 0.4 + 0.5 * 0.4)
    rng = np.random.default_rng(0)
    true_logits = rng.normal(0, 2, (4000, 3))
    labels = np.array([rng.choice(3, p=np.exp(z) / np.exp(z).sum()) for z in true_logits])
    # A model three times too sure of itself: the fit divides by about 3.
    assert fit_temperature(3.0 * true_logits, labels) == pytest.approx(3.0, rel=0.15)


def test_a_cnn_model_is_calibrated_from_its_crops_and_its_heads_apply_the_temperatures(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.training.calibrate import calibrate

    config = ModelConfig(temporal_input=True)
    split = tmp_path / "cal"
    write_split(split, seed=11, n_sequences=2, seq_len=16, crop=config.crop_config(),
                full_tracks=True, progress=False)
    torch.manual_seed(0)
    model = build_model(config).eval()
    path = save_checkpoint(tmp_path / "m.pt", model, config)
    report = calibrate(path, split, tmp_path / "cal.pt", tmp_path / "cache")
    calibrated = load_checkpoint(tmp_path / "cal.pt")
    assert calibrated.config.temperatures == {t: r["temperature"] for t, r in report.items()}
    crops = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        raw, _ = model.step_logits(crops, model.initial_state(2))
        scaled, _ = calibrated.model.eval().step_logits(crops, calibrated.model.initial_state(2))
    for task, temperature in calibrated.config.temperatures.items():
        assert torch.allclose(scaled[task], raw[task] / temperature, atol=1e-5)


def test_temperatures_are_not_fitted_over_on_offsets(tmp_path):
    from signal_light_node.errors import ConfigError
    from signal_light_node.training.calibrate import calibrate

    config = ModelConfig(on_offsets={"left": -1.0})
    path = save_checkpoint(tmp_path / "m.pt", build_model(config), config)
    with pytest.raises(ConfigError, match="before them"):
        calibrate(path, tmp_path / "no_split", tmp_path / "cal.pt", tmp_path / "cache")
    assert not (tmp_path / "cal.pt").exists()
