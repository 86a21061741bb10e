"""``calibrate``'s gain guard (``training.fit_guard``): a setting fitted on labelled tracks
replaces the model as it is, or the default filter, only where its gain holds on resamples
of the fit tracks' scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from signal_light_node.cli import main
from signal_light_node.errors import ConfigError
from signal_light_node.model import load_checkpoint
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from signal_light_node.training import unknown_bias
from signal_light_node.training.filter_fit import fit_filter
from signal_light_node.training.fit_guard import GainGuard, Verdict
from signal_light_node.training.unknown_bias import (FILTER_META_KEY, META_KEY, ModelPass,
                                                     fit_unknown_margin)
from cli_refusal import refused
from test_bootstrap import SETTINGS, _noisy, _tracks_and_preds

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "day_street"
needs_bag = pytest.mark.skipif(not (BAG / "metadata.yaml").exists(),
                               reason="bags/day_street is not committed")


def test_a_gain_in_every_scene_is_kept_and_no_gain_is_not() -> None:
    rng = np.random.default_rng(7)
    tracks, truth = _tracks_and_preds(rng)
    worse = _noisy(truth, rng, 0.4)
    guard = GainGuard(tracks, 0.9, SETTINGS, resamples=200)
    better = guard.judge(worse, truth)
    assert better == Verdict(share_above=1.0, kept=True)
    assert guard.judge(worse, worse) == Verdict(share_above=0.0, kept=False)  # a tie is no gain
    assert guard.judge(truth, worse).kept is False


def test_a_gain_in_half_the_scenes_is_not_enough() -> None:
    rng = np.random.default_rng(8)
    tracks, truth = _tracks_and_preds(rng, n_tracks=8, scenes=2)
    reference = _noisy(truth, rng, 0.3)
    # Perfect on scene s0, wrong on every frame of s1: better or worse by which scene a
    # resample draws more of.
    candidate = [t if i % 2 == 0 else _noisy([t], rng, 1.0)[0] for i, t in enumerate(truth)]
    verdict = GainGuard(tracks, 0.9, SETTINGS, resamples=400).judge(reference, candidate)
    assert 0.1 < verdict.share_above < 0.9 and not verdict.kept
    assert GainGuard(tracks, 0.0, SETTINGS).judge(reference, candidate).kept  # no guard


def test_tracks_of_too_few_scenes_are_resampled_one_by_one() -> None:
    rng = np.random.default_rng(10)
    tracks, truth = _tracks_and_preds(rng, n_tracks=12, scenes=1)  # one recording
    guard = GainGuard(tracks, 0.9, SETTINGS, resamples=200)
    assert [list(g) for g in guard.groups] == [[i] for i in range(12)]
    reference = _noisy(truth, rng, 0.3)
    # Better on two tracks of twelve, the same elsewhere: one scene would call it a sure
    # gain; resampling the tracks finds resamples without the two.
    candidate = [t if i < 2 else r for i, (t, r) in enumerate(zip(truth, reference))]
    verdict = guard.judge(reference, candidate)
    assert 0.5 < verdict.share_above < 0.99
    many, _ = _tracks_and_preds(rng, n_tracks=12, scenes=6)
    assert len(GainGuard(many, 0.9).groups) == 6


def test_a_confidence_outside_0_to_1_or_no_track_is_refused() -> None:
    tracks, _ = _tracks_and_preds(np.random.default_rng(9), n_tracks=2, scenes=1)
    for bad in (-0.1, 1.0):
        with pytest.raises(ConfigError, match="gain confidence"):
            GainGuard(tracks, bad)
    with pytest.raises(ConfigError, match="no fit track"):
        GainGuard([], 0.9)


def _result(score: float) -> dict:
    return {"score": score, "switches": {"intent": {"ratio": 1.0}, "brake": {"ratio": 1.0}}}


def test_a_filter_the_guard_declines_leaves_the_defaults() -> None:
    results = {IntentFilterConfig(): _result(0.60), IntentFilterConfig(hold_s=0.4): _result(0.61)}
    asked = []

    def guard(config: IntentFilterConfig) -> Verdict:
        asked.append(config)
        return Verdict(share_above=0.55, kept=False)

    fit = fit_filter(results.__getitem__, lambda r: r["score"], [{"hold_s": 0.4}], guard)
    assert asked == [IntentFilterConfig(hold_s=0.4)]
    assert fit.changes == {} and fit.declined == {"hold_s": 0.4}
    assert fit.score == fit.default_score == 0.60 and fit.verdict.share_above == 0.55
    kept = fit_filter(results.__getitem__, lambda r: r["score"], [{"hold_s": 0.4}],
                      lambda config: Verdict(share_above=0.95, kept=True))
    assert kept.changes == {"hold_s": 0.4} and kept.declined is None


@needs_bag
@pytest.mark.usefixtures("one_torch_thread")
def test_the_published_states_are_those_the_scorer_scores() -> None:
    from signal_light_node.evaluation.bootstrap import score_from_confusions, track_confusions
    from signal_light_node.evaluation.streaming import scorer_result
    from signal_light_node.training.sources import load_bag_tracks
    from signal_light_node.training.unknown_bias import head_offsets, score

    model = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    passed = ModelPass(model, load_bag_tracks(BAG, model.config.crop_config())[:4])
    offsets = head_offsets(model, 1.0)
    mats = track_confusions(passed.tracks, passed.published(offsets))
    expected = score(scorer_result(passed.scorer(offsets), passed.light_filter))
    assert score_from_confusions(mats["intent"].sum(0), mats["brake"].sum(0)) == \
        pytest.approx(expected)


@needs_bag
@pytest.mark.usefixtures("one_torch_thread")
def test_a_margin_the_guard_declines_goes_back_to_0(monkeypatch) -> None:
    from signal_light_node.training.sources import load_bag_tracks

    model = load_checkpoint(DEFAULT_WEIGHTS).model
    tracks = load_bag_tracks(BAG, model.config.crop_config())[:2]
    monkeypatch.setattr(unknown_bias, "score", lambda result: 0.5)  # every setting ties ...
    judged = []

    def judge(self, reference, candidate):
        judged.append((len(reference), len(candidate)))
        return Verdict(share_above=0.5, kept=False)

    monkeypatch.setattr(GainGuard, "judge", judge)
    fit = fit_unknown_margin(model, tracks, (2.0,), (1.0,), confidence=0.9)  # ... but 2 / +1
    assert judged == [(2, 2)]  # both settings' published states, per fit track
    assert (fit.margin, fit.on_offset, fit.declined) == (0.0, 0.0, (2.0, 1.0))
    assert fit.verdict is not None and not fit.verdict.kept
    lines = unknown_bias.summary_lines(fit, Path("m.pt"), None)
    assert any(line.startswith("declined: margin 2 with ON offset +1") for line in lines)
    fit.verdict, fit.declined = Verdict(share_above=0.95, kept=True), None
    kept = unknown_bias.summary_lines(fit, Path("m.pt"), None)
    assert "above 0 / 0 on 95 % of scene resamples" in kept[1]
    plain = fit_unknown_margin(model, tracks, (2.0,), (1.0,))  # no guard asked
    assert (plain.margin, plain.on_offset, plain.declined) == (2.0, 1.0, None)


@needs_bag
@pytest.mark.usefixtures("one_torch_thread")
def test_calibrate_records_the_guard_in_the_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "cal.pt"
    assert main(["calibrate", str(BAG), "--grid", "0,3", "--on-grid", "0", "--fit-filter",
                 "--holdout-fraction", "0.5", "--out", str(out), "--threads", "1",
                 "--gain-confidence", "0.99"]) == 0
    meta = load_checkpoint(out).meta
    info, filtered = meta[META_KEY], meta[FILTER_META_KEY]
    assert info["gain_confidence"] == 0.99
    for fitted, kept in ((info, info["margin"] != 0.0), (filtered, bool(filtered["changes"]))):
        if fitted["verdict"] is not None:  # something beat the model as it is on the fit half
            assert fitted["verdict"]["kept"] == kept == (fitted["verdict"]["share_above"] >= 0.99)
            assert (fitted["declined"] is None) == kept
        else:
            assert fitted["declined"] is None and not kept


@needs_bag
def test_a_confidence_of_1_is_refused(tmp_path: Path, capsys) -> None:
    err = refused(capsys, "calibrate", [BAG, "--gain-confidence", "1"], tmp_path / "a.pt")
    assert "--gain-confidence must be in [0, 1)" in err
