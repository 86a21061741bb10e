"""``signal-light calibrate --night-negatives ... --max-false-brake X --max-false-blinker Y``:
per light group the ON offset nearest 0 that keeps the night negatives' false lights within
the bound, carried by the group's heads' bias (``training.night_bound``)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from signal_light_node.cli import main
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.streaming import chunks, predict_track_probs
from signal_light_node.model import load_checkpoint
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS
from signal_light_node.training.night_bound import (DEFAULT_OFFSET_GRID, LIGHT_GROUPS, NightBounds,
                                                    choose_offset, fit_light_offset,
                                                    light_offsets, meta_key)
from signal_light_node.training.sources import load_bag_tracks
from signal_light_node.training.unknown_bias import add_on_offsets, task_heads
from cli_refusal import refused

REPO = Path(__file__).resolve().parents[1]
DAY = REPO / "bags" / "day_street"
NIGHT = REPO / "bags" / "night_tail_lamps"
needs_bags = pytest.mark.skipif(not all((b / "metadata.yaml").exists() for b in (DAY, NIGHT)),
                                reason="bags/day_street or bags/night_tail_lamps not committed")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_the_offset_nearest_0_within_the_bound_wins() -> None:
    shares = {0.0: 0.30, -0.5: 0.20, -1.0: 0.10, -2.0: 0.0}
    assert choose_offset(shares, 0.5) == (0.0, True)
    assert choose_offset(shares, 0.2) == (-0.5, True)
    assert choose_offset(shares, 0.15) == (-1.0, True)
    assert choose_offset({0.0: 0.3, -1.0: 0.2}, 0.1) == (-1.0, False)


def test_the_default_grid_does_not_overshoot_a_bound_past_minus_1() -> None:
    # Candidate W's brake: 10.8 % at -1.0, 6.0 % at -1.5; -1.125 already holds 10 %.
    shares = {-0.125 * i: 0.108 - 0.01 * max(i - 8, 0) for i in range(17)}
    picked = choose_offset({o: shares[o] for o in DEFAULT_OFFSET_GRID}, 0.10)
    assert picked == (-1.125, True)
    # "0.0", not "-0.0": the logs and the checkpoint's metadata print the grid.
    assert str(DEFAULT_OFFSET_GRID[0]) == "0.0" and min(DEFAULT_OFFSET_GRID) == -2.0


def _false_on(model, tracks, group: str) -> float:
    scorer = TrackScorer(EvalSettings())
    with torch.no_grad():
        for batch in chunks(tracks, 32):
            for track, pred in zip(batch, predict_track_probs(model, batch)[0]):
                scorer.add(track, pred, breakdowns=False)
    m = sum(scorer.strict.confusion(task) for task in LIGHT_GROUPS[group])
    return float(m[0, 1] / m[0].sum())


@needs_bags
@pytest.mark.parametrize("group", ["brake", "blinker"])
def test_the_fit_counts_as_the_model_moved_by_its_offset_publishes(group: str) -> None:
    model = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    tracks = load_bag_tracks(NIGHT, model.config.crop_config())[:3]
    fit = fit_light_offset(model, tracks, bound=0.0, grid=(0.0, -1.0, -3.0), group=group)
    offsets = sorted(fit.false_on, reverse=True)
    assert offsets == [0.0, -1.0, -3.0] and fit.tracks == 3 and fit.off_frames > 0
    shares = [fit.false_on[o] for o in offsets]
    assert shares == sorted(shares, reverse=True)  # a lower ON logit never adds a light
    assert fit.offset == choose_offset(fit.false_on, 0.0)[0]
    moved = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    add_on_offsets(moved, light_offsets(group, -1.0))
    assert fit.false_on[-1.0] == pytest.approx(_false_on(moved, tracks, group), abs=1e-9)
    assert fit.false_on[0.0] == pytest.approx(_false_on(model, tracks, group), abs=1e-9)


@needs_bags
def test_one_pass_fits_each_group_as_its_own_fit_would() -> None:
    asked = [("brake", 0.0, (0.0, -4.0)), ("blinker", 0.1, (0.0, -1.0, -3.0))]
    bounds = NightBounds([NIGHT], asked)
    model = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    tracks = load_bag_tracks(NIGHT, model.config.crop_config())
    alone = [fit_light_offset(model, tracks, bound, grid, group) for group, bound, grid in asked]
    bounds(model)
    assert [f.group for f in bounds.fits] == ["brake", "blinker"]
    for fit, own in zip(bounds.fits, alone):
        assert fit.false_on == pytest.approx(own.false_on, abs=1e-9)
        assert (fit.offset, fit.bound, fit.tracks) == (own.offset, own.bound, own.tracks)


def test_bad_bounds_and_grids_are_refused() -> None:
    model = load_checkpoint(DEFAULT_WEIGHTS).model
    with pytest.raises(ConfigError, match="bound"):
        fit_light_offset(model, [object()], bound=1.0)
    with pytest.raises(ConfigError, match="0 or below"):
        fit_light_offset(model, [object()], bound=0.1, grid=(0.5, 0.0))
    with pytest.raises(ConfigError, match="no night negative"):
        fit_light_offset(model, [], bound=0.1)
    with pytest.raises(ConfigError, match="no light group"):
        fit_light_offset(model, [object()], bound=0.1, group="horn")


@needs_bags
def test_calibrate_writes_each_offset_into_its_heads(tmp_path: Path, capsys) -> None:
    out = tmp_path / "cal.pt"
    assert main(["calibrate", str(DAY), "--grid", "0", "--on-grid=0", "--out", str(out),
                 "--night-negatives", str(NIGHT), "--max-false-brake", "0.0",
                 "--brake-grid=0,-4", "--max-false-blinker", "0.0", "--blinker-grid=0,-3",
                 "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    loaded = load_checkpoint(out)
    shipped_file = load_checkpoint(DEFAULT_WEIGHTS)
    shipped, before = shipped_file.model, shipped_file.config.on_offsets
    for group, low in (("brake", -4.0), ("blinker", -3.0)):
        info = loaded.meta[meta_key(group)]
        assert set(info["false_on"]) == {"0", f"{low:g}"} and info["data"] == [str(NIGHT)]
        offset = info["offset"]
        assert offset == (0.0 if info["false_on"]["0"] == 0.0 else low)
        for task in LIGHT_GROUPS[group]:  # added to the config's ON offsets, not the biases
            assert loaded.config.on_offsets.get(task, 0.0) == pytest.approx(
                before.get(task, 0.0) + offset)
            for new, old in zip(task_heads(loaded.model, task), task_heads(shipped, task)):
                assert torch.equal(new.bias, old.bias)
        assert f"{group} ON offset {offset:+g}" in printed


def _refused(capsys, args, out: Path) -> str:
    return refused(capsys, "calibrate", args, out)


@needs_bags
def test_a_bound_without_negatives_and_a_positive_offset_are_refused(tmp_path: Path,
                                                                     capsys) -> None:
    err = _refused(capsys, [DAY, "--max-false-brake", "0.1"], tmp_path / "a.pt")
    assert "goes with" in err
    err = _refused(capsys, [DAY, "--night-negatives", NIGHT], tmp_path / "c.pt")
    assert "goes with" in err
    err = _refused(capsys, [DAY, "--night-negatives", NIGHT, "--max-false-brake", "0.1",
                            "--brake-grid=0,0.5", "--grid", "0", "--on-grid=0"], tmp_path / "b.pt")
    assert "0 or below" in err
