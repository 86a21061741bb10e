"""The scene bootstrap (``evaluation.bootstrap``): scores from per-track confusions are the
scorer's, and intervals come from resampling scenes, not tracks."""

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.bootstrap import (scene_bootstrap, scene_groups,
                                                    score_from_confusions, track_confusions)
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.streaming import scorer_result
from signal_light_node.evaluation.tracks import TrackSequence, track_from_item
from signal_light_node.labels import TASKS
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from signal_light_node.training.unknown_bias import score

INTENT, BRAKE = TASKS.index("intent"), TASKS.index("brake")
SETTINGS = EvalSettings(warmup_frames=2, warmup_seconds=0.0)


def _track(name, scene, intent, brake):
    n = len(intent)
    labels = np.zeros((n, len(TASKS)), np.int64)
    labels[:, INTENT], labels[:, BRAKE] = intent, brake
    return TrackSequence(track_id=name, labels=labels, mask=np.ones(n, bool),
                         stamps_ns=np.arange(n, dtype=np.int64) * 100_000_000,
                         box_size=np.full(n, 40.0), occlusion=np.zeros(n), scene=scene)


def _tracks_and_preds(rng, n_tracks=12, scenes=4, frames=20):
    tracks, truth = [], []
    for i in range(n_tracks):
        intent, brake = rng.integers(0, 4, frames), rng.integers(0, 2, frames)
        tracks.append(_track(f"t{i}", f"s{i % scenes}", intent, brake))
        truth.append(tracks[-1].labels.copy())
    return tracks, truth


def _noisy(truth, rng, wrong):
    preds = []
    for labels in truth:
        pred = labels.copy()
        flip = rng.random(len(pred)) < wrong
        pred[flip, INTENT] = (pred[flip, INTENT] + 1) % 4
        pred[flip, BRAKE] = 1 - pred[flip, BRAKE]
        preds.append(pred)
    return preds


def test_summed_confusions_give_the_scorers_score():
    rng = np.random.default_rng(3)
    tracks, truth = _tracks_and_preds(rng)
    preds = _noisy(truth, rng, 0.3)
    scorer = TrackScorer(SETTINGS)
    for track, pred in zip(tracks, preds):
        scorer.add(track, pred)
    expected = score(scorer_result(scorer, IntentFilterConfig()))
    mats = track_confusions(tracks, preds, SETTINGS)
    assert mats["intent"].shape == (12, 5, 5)
    assert score_from_confusions(mats["intent"].sum(0), mats["brake"].sum(0)) == \
        pytest.approx(expected)
    # The warm-up is left out: 18 scored frames per track.
    assert mats["brake"].sum() == 12 * 18


def test_a_file_better_in_every_scene_is_above_the_first_in_every_resample():
    rng = np.random.default_rng(4)
    tracks, truth = _tracks_and_preds(rng)
    worse = track_confusions(tracks, _noisy(truth, rng, 0.4), SETTINGS)
    perfect = track_confusions(tracks, truth, SETTINGS)
    groups = scene_groups(tracks)
    first, second, same = scene_bootstrap([worse, perfect, worse], groups, resamples=200)
    assert first.difference == 0.0 and first.difference_interval == (0.0, 0.0)
    assert second.score == pytest.approx(1.0) and second.share_above == 1.0
    assert second.difference_interval[0] > 0
    assert same.share_above == 0.0 and same.difference_interval == (0.0, 0.0)
    assert first.interval[0] <= first.score <= first.interval[1]


def test_scenes_are_resampled_whole():
    rng = np.random.default_rng(5)
    tracks, truth = _tracks_and_preds(rng, n_tracks=8, scenes=2)
    # Scene s0 is judged perfectly, scene s1 always wrong: a resample of whole scenes can
    # only score all-s0, all-s1 or both, so the interval spans both extremes.
    preds = [t if i % 2 == 0 else _noisy([t], rng, 1.0)[0] for i, t in enumerate(truth)]
    groups = scene_groups(tracks)
    assert [list(g) for g in groups] == [[0, 2, 4, 6], [1, 3, 5, 7]]
    (row,) = scene_bootstrap([track_confusions(tracks, preds, SETTINGS)], groups, resamples=400)
    assert row.interval[0] == pytest.approx(0.0) and row.interval[1] == pytest.approx(1.0)


def test_tracks_without_a_scene_are_scenes_of_their_own_and_splits_name_theirs():
    tracks = [_track(f"t{i}", "", [0] * 4, [0] * 4) for i in range(3)]
    assert len(scene_groups(tracks)) == 3
    item = {"crops": np.zeros((4, 8, 8, 3), np.uint8), "labels": np.zeros((4, len(TASKS))),
            "meta": {"fps": 10.0, "seed": 1234}}
    assert track_from_item(item, "0").scene == "1234"


def test_bad_inputs_are_refused():
    rng = np.random.default_rng(6)
    tracks, truth = _tracks_and_preds(rng, n_tracks=4, scenes=2)
    mats = track_confusions(tracks, truth, SETTINGS)
    with pytest.raises(ConfigError):
        scene_bootstrap([], scene_groups(tracks))
    with pytest.raises(ConfigError):
        scene_bootstrap([mats, track_confusions(tracks[:2], truth[:2], SETTINGS)],
                        scene_groups(tracks))
    with pytest.raises(ConfigError):
        track_confusions(tracks, truth[:3], SETTINGS)
