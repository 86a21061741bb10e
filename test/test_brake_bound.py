"""``signal-light calibrate --night-negatives ... --max-false-brake X``: the brake ON offset
nearest 0 that keeps the night negatives' false brakes within the bound, carried by the
brake head's bias (``training.brake_bound``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from signal_light_node.cli import main
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.streaming import chunks, predict_track_probs
from signal_light_node.model import load_checkpoint
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS
from signal_light_node.training.brake_bound import (BRAKE_META_KEY, brake_offsets,
                                                    choose_offset, fit_brake_offset)
from signal_light_node.training.sources import load_bag_tracks
from signal_light_node.training.unknown_bias import apply_offsets, class_index, task_heads
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


def _false_on(model, tracks) -> float:
    scorer = TrackScorer(EvalSettings())
    with torch.no_grad():
        for batch in chunks(tracks, 32):
            for track, pred in zip(batch, predict_track_probs(model, batch)[0]):
                scorer.add(track, pred, breakdowns=False)
    m = scorer.strict.confusion("brake")
    return float(m[0, 1] / m[0].sum())


@needs_bags
def test_the_fit_counts_as_the_model_moved_by_its_offset_publishes() -> None:
    model = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    tracks = load_bag_tracks(NIGHT, model.config.crop_config())[:3]
    fit = fit_brake_offset(model, tracks, bound=0.0, grid=(0.0, -1.0, -3.0))
    offsets = sorted(fit.false_on, reverse=True)
    assert offsets == [0.0, -1.0, -3.0] and fit.tracks == 3 and fit.off_frames > 0
    shares = [fit.false_on[o] for o in offsets]
    assert shares == sorted(shares, reverse=True)  # a lower ON logit never adds a brake
    assert fit.offset == choose_offset(fit.false_on, 0.0)[0]
    moved = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    apply_offsets(moved, brake_offsets(moved, -1.0))
    assert fit.false_on[-1.0] == pytest.approx(_false_on(moved, tracks), abs=1e-9)
    assert fit.false_on[0.0] == pytest.approx(_false_on(model, tracks), abs=1e-9)


def test_bad_bounds_and_grids_are_refused() -> None:
    model = load_checkpoint(DEFAULT_WEIGHTS).model
    with pytest.raises(ConfigError, match="bound"):
        fit_brake_offset(model, [object()], bound=1.0)
    with pytest.raises(ConfigError, match="0 or below"):
        fit_brake_offset(model, [object()], bound=0.1, grid=(0.5, 0.0))
    with pytest.raises(ConfigError, match="no night negative"):
        fit_brake_offset(model, [], bound=0.1)


@needs_bags
def test_calibrate_writes_the_brake_offset_into_the_brake_head(tmp_path: Path, capsys) -> None:
    out = tmp_path / "cal.pt"
    assert main(["calibrate", str(DAY), "--grid", "0", "--on-grid=0", "--out", str(out),
                 "--night-negatives", str(NIGHT), "--max-false-brake", "0.0",
                 "--brake-grid=0,-4", "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    loaded = load_checkpoint(out)
    info = loaded.meta[BRAKE_META_KEY]
    assert set(info["false_on"]) == {"0", "-4"} and info["data"] == [str(NIGHT)]
    offset = info["offset"]
    assert offset == (0.0 if info["false_on"]["0"] == 0.0 else -4.0)
    shipped = load_checkpoint(DEFAULT_WEIGHTS).model
    on = class_index(shipped, "brake", "ON")
    for new, old in zip(task_heads(loaded.model, "brake"), task_heads(shipped, "brake")):
        moved = (new.bias - old.bias).detach().numpy()
        assert moved[on] == pytest.approx(offset)
        assert np.count_nonzero(np.delete(moved, on)) == 0
    assert f"brake ON offset {offset:+g}" in printed


def _refused(capsys, args, out: Path) -> str:
    return refused(capsys, "calibrate", args, out)


@needs_bags
def test_a_bound_without_negatives_and_a_positive_offset_are_refused(tmp_path: Path,
                                                                     capsys) -> None:
    err = _refused(capsys, [DAY, "--max-false-brake", "0.1"], tmp_path / "a.pt")
    assert "go together" in err
    err = _refused(capsys, [DAY, "--night-negatives", NIGHT, "--max-false-brake", "0.1",
                            "--brake-grid=0,0.5", "--grid", "0", "--on-grid=0"], tmp_path / "b.pt")
    assert "0 or below" in err
