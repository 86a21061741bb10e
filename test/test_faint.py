"""Faint flashes (training.faint): windows' changes shrunk towards their mean."""

import numpy as np
import pytest
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.training.faint import (FaintFlashes, faint_batch, shrink_window_changes,
                                              window_factors)


def _batch(rng: np.random.Generator, lengths=(6, 4)):
    n, t = len(lengths), max(lengths)
    feats = torch.zeros(n, t, 3, 2, 2)
    maps = torch.zeros(n, t, 5, 2, 2)
    mask = torch.zeros(n, t, dtype=torch.bool)
    for i, length in enumerate(lengths):
        feats[i, :length] = torch.from_numpy(rng.normal(size=(length, 3, 2, 2))).float()
        maps[i, :length] = torch.from_numpy(rng.normal(size=(length, 5, 2, 2))).float()
        mask[i, :length] = True
    labels = torch.zeros(n, t, 5, dtype=torch.long)
    return {"features": feats, "maps": maps, "mask": mask, "labels": labels}


def _window_mean(x, length):
    return x[:length].mean(0)


def test_a_factor_scales_each_frames_change_from_the_window_mean_and_keeps_the_padding():
    batch = _batch(np.random.default_rng(0))
    out = shrink_window_changes(batch, np.array([0.25, 1.0], np.float32))
    for key in ("features", "maps"):
        x, y = batch[key], out[key]
        mean = _window_mean(x[0], 6)
        torch.testing.assert_close(y[0], mean + 0.25 * (x[0] - mean))
        torch.testing.assert_close(_window_mean(y[0], 6), mean)  # the level is kept
        torch.testing.assert_close(y[1, :4], x[1, :4])  # factor 1: as drawn
        assert torch.count_nonzero(y[1, 4:]) == 0  # padding stays zero
    assert out["labels"] is batch["labels"] and out["mask"] is batch["mask"]


def test_factor_zero_makes_a_window_steady_and_a_steady_window_stays_as_it_is():
    batch = _batch(np.random.default_rng(1))
    flat = shrink_window_changes(batch, np.zeros(2, np.float32))["maps"]
    assert torch.allclose(flat[0, :6], flat[0, :1].expand(6, -1, -1, -1))
    steady = dict(batch, maps=batch["maps"][:, :1].repeat(1, 6, 1, 1, 1) * batch["mask"].view(
        2, 6, 1, 1, 1))
    out = shrink_window_changes(steady, np.array([0.3, 0.3], np.float32))
    torch.testing.assert_close(out["maps"], steady["maps"])


def test_factors_fall_in_the_range_and_share_drawn():
    faint = FaintFlashes(share=0.5, low=0.3)
    factors = window_factors(4000, faint, np.random.default_rng(2))
    shrunk = factors < 1.0
    assert 0.45 < shrunk.mean() < 0.55
    assert factors.min() >= 0.3 and factors.max() <= 1.0
    assert np.all(window_factors(50, FaintFlashes(share=0.0), np.random.default_rng(3)) == 1.0)


def test_an_inactive_setting_returns_the_batch_and_leaves_the_generator_alone():
    batch = _batch(np.random.default_rng(4))
    rng = np.random.default_rng(5)
    before = rng.bit_generator.state
    assert faint_batch(batch, FaintFlashes(), rng) is batch
    assert faint_batch(batch, FaintFlashes(share=1.0, low=1.0), rng) is batch
    assert rng.bit_generator.state == before
    out = faint_batch(batch, FaintFlashes(share=1.0, low=0.0), rng)
    assert not torch.equal(out["features"], batch["features"])


@pytest.mark.parametrize("share, low", [(-0.1, 0.3), (1.5, 0.3), (0.5, -0.2), (0.5, 1.2)])
def test_bad_settings_are_refused_with_a_reason(share, low):
    with pytest.raises(ConfigError, match="faint"):
        FaintFlashes(share, low)


def test_the_recipe_refuses_a_bad_share_on_its_command_line(tmp_path):
    from signal_light_node.training import trunk_recipe
    with pytest.raises(SystemExit):
        trunk_recipe.main(["--out", str(tmp_path / "m"), "--pool", str(tmp_path), "--val",
                           str(tmp_path), "--faint-share", "2"])


def test_the_recipe_trains_on_faint_windows_and_records_the_setting(tmp_path):
    from signal_light_node.data.split import write_split
    from signal_light_node.model.checkpoint import load_checkpoint
    from signal_light_node.model.config import trunk_config
    from signal_light_node.training import trunk_recipe

    split = tmp_path / "pool_1"
    write_split(split, seed=7, n_sequences=2, seq_len=10, crop=trunk_config().crop_config(),
                full_tracks=True, progress=False)
    assert trunk_recipe.main(["--out", str(tmp_path / "run"), "--pool", str(split), "--val",
                              str(split), "--looks", "0", "--batch", "2", "--seq-len", "8",
                              "--steps", "1", "--val-every", "1", "--threads", "1",
                              "--faint-share", "1", "--faint-low", "0.2"]) == 0
    meta = load_checkpoint(tmp_path / "run" / "last.pt").meta
    assert meta["args"]["faint_share"] == "1.0" and meta["args"]["faint_low"] == "0.2"
