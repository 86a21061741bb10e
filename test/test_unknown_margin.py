"""``signal-light calibrate``: one UNKNOWN margin fitted on labelled tracks, carried by the
heads' biases; before/after on held-out tracks; refusals in one line, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from signal_light_node.cli import main
from signal_light_node.model import load_checkpoint
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS
from signal_light_node.model.interface import to_input
from signal_light_node.training.unknown_bias import (MARGIN_HEADS, META_KEY, ON_HEADS,
                                                     add_on_offsets, apply_offsets,
                                                     apply_unknown_margin, class_index,
                                                     MarginFit, fit_unknown_margin, grid_edges,
                                                     head_offsets, on_offsets, summary_lines,
                                                     task_heads, unknown_index, with_offsets)
from cli_refusal import refused

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "day_street"

needs_bag = pytest.mark.skipif(not (BAG / "metadata.yaml").exists(),
                               reason="bags/day_street is not committed")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_the_margin_lowers_only_the_unknown_logits_and_their_probability() -> None:
    model = load_checkpoint(DEFAULT_WEIGHTS).model
    before = {k: v.clone() for k, v in model.state_dict().items()}
    crops = np.random.default_rng(0).integers(0, 255, (4, 64, 64, 3), dtype=np.uint8)
    p0, _ = model.step(to_input(crops), model.initial_state(4))
    apply_unknown_margin(model, 1.5)
    p1, _ = model.step(to_input(crops), model.initial_state(4))
    after = model.state_dict()
    # one head per task, or one per member of a model averaging members
    moved = {k for k in before for t in MARGIN_HEADS if k.endswith(f"heads.{t}.bias")}
    assert len(moved) >= len(MARGIN_HEADS)
    for key in before:
        if key in moved:
            task = key.split(".")[-2]
            k = unknown_index(model, task)
            delta = before[key] - after[key]
            assert torch.allclose(delta[k], torch.tensor(1.5)), key
            assert torch.count_nonzero(delta) == 1, key
        else:
            assert torch.equal(before[key], after[key]), key
    for task in MARGIN_HEADS:
        k = unknown_index(model, task)
        assert bool((p1[task][:, k] < p0[task][:, k]).all()), task
    assert torch.equal(p0["view"], p1["view"])


def test_offsets_applied_to_outputs_equal_the_offsets_in_the_biases() -> None:
    """The fit runs the model once and moves its outputs; that must be what the moved
    biases give, temperatures included."""
    import dataclasses

    loaded = load_checkpoint(DEFAULT_WEIGHTS)
    model = loaded.model.eval()
    before = dict(model.config.on_offsets)  # the shipped file's own (its calibration)
    model.config = dataclasses.replace(model.config, temperatures={"left": 1.7, "brake": 0.6})
    crops = np.random.default_rng(1).integers(0, 255, (5, 64, 64, 3), dtype=np.uint8)
    offsets, shifts = head_offsets(model, 1.25), on_offsets(ON_HEADS, -0.5)
    with torch.no_grad():
        p0, _ = model.step(to_input(crops), model.initial_state(5))
        apply_offsets(model, offsets)
        margin_only, _ = model.step(to_input(crops), model.initial_state(5))
        add_on_offsets(model, shifts)
        p1, _ = model.step(to_input(crops), model.initial_state(5))
    moved = with_offsets({t: v.numpy() for t, v in p0.items()}, offsets,
                         dict(model.config.temperatures), shifts)
    for task in p0:
        np.testing.assert_allclose(moved[task], p1[task].numpy(), atol=1e-5, err_msg=task)
    for task in ON_HEADS:  # the ON offset moves ON against OFF; UNKNOWN is the margin's
        k, on = unknown_index(model, task), class_index(model, task, "ON")
        torch.testing.assert_close(p1[task][:, k], margin_only[task][:, k])
        assert bool((p1[task][:, on] < margin_only[task][:, on]).all()), task
    assert offsets["left"].tolist() == [0.0, 0.0, -1.25]  # OFF, ON, UNKNOWN
    assert offsets["brake"].tolist() == [0.0, 0.0, -1.25] and ON_HEADS == ("left", "right")
    assert model.config.on_offsets == _summed(before, {"left": -0.5, "right": -0.5})


def _summed(before: dict, shifts: dict) -> dict:
    """ON offsets after ``shifts`` are added to ``before`` (sums of 0 dropped)."""
    total = {t: before.get(t, 0.0) + shifts.get(t, 0.0) for t in {*before, *shifts}}
    return {t: v for t, v in total.items() if v != 0.0}


@needs_bag
def test_the_fit_scores_as_evaluate_scores_the_model_moved_by_its_choice() -> None:
    from signal_light_node.evaluation.streaming import evaluate_tracks
    from signal_light_node.training.sources import load_bag_tracks
    from signal_light_node.training.unknown_bias import score

    model = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    tracks = load_bag_tracks(BAG, model.config.crop_config())[:3]
    fit = fit_unknown_margin(model, tracks, (0.0, 2.5), (-1.0, 0.0, 1.5))
    moved = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    apply_offsets(moved, head_offsets(moved, fit.margin))
    add_on_offsets(moved, on_offsets(ON_HEADS, fit.on_offset))
    assert fit.scores[fit.margin] == pytest.approx(
        score(evaluate_tracks(moved, tracks, progress=False)), abs=1e-9)
    plain = fit_unknown_margin(model, tracks, (0.0,))
    assert plain.on_offset == 0.0
    assert plain.scores[0.0] == pytest.approx(score(evaluate_tracks(model, tracks,
                                                                    progress=False)))


@needs_bag
def test_the_fit_keeps_the_best_and_ties_go_to_the_smaller_margin_and_offset_0(
        monkeypatch) -> None:
    from signal_light_node.training import unknown_bias
    from signal_light_node.training.sources import load_bag_tracks

    model = load_checkpoint(DEFAULT_WEIGHTS).model
    tracks = load_bag_tracks(BAG, model.config.crop_config())[:2]
    fit = fit_unknown_margin(model, tracks, (2.0, 0.0, 1.0), (0.5, -0.5))
    assert sorted(fit.scores) == [0.0, 1.0, 2.0]
    assert fit.scores[fit.margin] == max(fit.scores.values())
    monkeypatch.setattr(unknown_bias, "score", lambda result: 0.5)
    tied = fit_unknown_margin(model, tracks, (2.0, 1.0), (1.0, -0.5, 0.5))
    assert tied.margin == 1.0 and tied.on_offset == -0.5
    assert fit_unknown_margin(model, tracks, (1.0,), (1.0, 0.0, -1.0)).on_offset == 0.0


@needs_bag
def test_calibrate_writes_the_margin_and_a_held_out_report(tmp_path: Path, capsys) -> None:
    out = tmp_path / "cal.pt"
    assert main(["calibrate", str(BAG), "--grid", "0,3", "--on-grid=-1,0,1",
                 "--holdout-fraction", "0.5", "--out", str(out), "--threads", "1",
                 "--gain-confidence", "0"]) == 0  # the best wins (test_fit_guard: the guard)
    printed = capsys.readouterr().out
    loaded = load_checkpoint(out)
    info = loaded.meta[META_KEY]
    margin = info["margin"]
    assert set(info["scores"]) == {"0", "3"} and margin in (0.0, 3.0)
    assert info["scores"][f"{margin:g}"] == max(info["scores"].values())
    assert info["held_out_tracks"] > 0 and info["fit_tracks"] > 0
    on = info["on_offset"]
    assert on in (-1.0, 0.0, 1.0) and info["on_heads"] == list(ON_HEADS)
    shipped_file = load_checkpoint(DEFAULT_WEIGHTS)
    shipped = shipped_file.model
    expected = head_offsets(shipped, margin)
    assert loaded.config.on_offsets == _summed(shipped_file.config.on_offsets,
                                               on_offsets(ON_HEADS, on))
    for task in MARGIN_HEADS:
        for new, old in zip(task_heads(loaded.model, task), task_heads(shipped, task)):
            moved = (new.bias - old.bias).detach()
            assert torch.allclose(moved, torch.as_tensor(expected[task], dtype=moved.dtype)), task
            assert moved[unknown_index(shipped, task)] == pytest.approx(-margin), task
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert set(report) == {"held_out_tracks", "before", "after"}
    assert report["before"]["scored_frames"] == report["after"]["scored_frames"] > 0
    assert "UNKNOWN margin and ON offsets" in out.with_suffix(".report.md").read_text()
    assert f"UNKNOWN margin {margin:g}" in printed and "held-out after" in printed
    assert f"blinker ON offset {on:+g}" in printed
    # Margin 3 of (0, 3) and offsets -1 / +1 of (-1, 0, 1) lie at a grid's end.
    assert ("a wider grid may score better" in printed) == (margin == 3.0 or on != 0.0)


def test_a_choice_at_the_end_of_its_grid_is_named() -> None:
    grid, on_grid = (0.0, 1.0, 2.0), (-1.0, 0.0, 1.0)
    assert grid_edges(1.0, 0.0, grid, on_grid) == []
    assert grid_edges(0.0, 0.0, grid, on_grid) == []  # 0 is the end of the margin's range
    assert grid_edges(2.0, -1.0, grid, on_grid) == [
        "UNKNOWN margin 2 is the largest of --grid",
        "blinker ON offset -1 is the smallest of --on-grid"]
    assert grid_edges(0.0, 1.0, grid, on_grid) == [
        "blinker ON offset +1 is the largest of --on-grid"]
    assert grid_edges(2.0, 0.0, (2.0,), (0.0,)) == []  # a single value is no grid to widen
    lines = summary_lines(MarginFit(margin=2.0, edges=grid_edges(2.0, 0.0, grid, on_grid)),
                          Path("m.pt"), None)
    assert lines[-1] == ("note: UNKNOWN margin 2 is the largest of --grid: a wider grid may "
                         "score better")


def _refused(capsys, args, out: Path) -> str:
    return refused(capsys, "calibrate", args, out)


def test_a_missing_bag_is_refused(tmp_path: Path, capsys) -> None:
    assert "does not exist" in _refused(capsys, [tmp_path / "nowhere"], tmp_path / "a.pt")


@needs_bag
def test_a_negative_margin_is_refused(tmp_path: Path, capsys) -> None:
    err = _refused(capsys, [BAG, "--grid=-1,0"], tmp_path / "a.pt")
    assert ">= 0" in err


@needs_bag
def test_holding_out_everything_is_refused(tmp_path: Path, capsys) -> None:
    err = _refused(capsys, [BAG, "--holdout-fraction", "1"], tmp_path / "a.pt")
    assert "--holdout-fraction" in err
