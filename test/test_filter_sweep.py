"""``scripts/filter_sweep.py`` scores one model pass under many settings: a brake shift moves
only the brake's ON against its OFF, and what the node publishes follows it."""

import numpy as np
import pytest

from signal_light_node.labels import CLASS_NAMES, TASKS
from signal_light_node.model.config import trunk_config
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from script_loader import load_script


def _script():
    return load_script("filter_sweep")


def test_brake_shift_moves_on_against_off_and_keeps_unknown():
    sweep = _script()
    brake = np.array([[[0.6, 0.3, 0.1], [np.nan, np.nan, np.nan]]])
    raw = {"brake": brake, "left": np.zeros((1, 2, 3))}
    assert sweep.shift_brake(raw, 0.0) is raw
    shifted = sweep.shift_brake(raw, 1.0)["brake"]
    assert shifted[0, 0, 2] == pytest.approx(0.1)
    assert shifted[0, 0, :2].sum() == pytest.approx(0.9)
    assert shifted[0, 0, 1] / shifted[0, 0, 0] == pytest.approx(0.5 * np.e)
    assert np.isnan(shifted[0, 1]).all()
    assert np.array_equal(brake[0, 0], [0.6, 0.3, 0.1])  # the pass itself is not changed


def _uncertain_pass(tracks):
    """Every head OFF, the brake at P(ON) 0.4 against P(OFF) 0.6 on every frame."""
    n, length = len(tracks), max(len(t) for t in tracks)
    raw = {}
    for task in TASKS:
        p = np.zeros((n, length, len(CLASS_NAMES[task])), np.float32)
        p[..., 0] = 1.0
        raw[task] = p
    raw["brake"][..., :2] = (0.6, 0.4)
    return raw


def _split_tracks(path, seed, n_sequences, seq_len):
    """The tracks of a small rendered split, cut as the trunk model cuts them."""
    from signal_light_node.data.split import write_split
    from signal_light_node.training.sources import split_tracks

    crop = trunk_config().crop_config()
    write_split(path, seed=seed, n_sequences=n_sequences, seq_len=seq_len, crop=crop,
                full_tracks=True, progress=False)
    return split_tracks(path, crop)


def test_a_brake_shift_changes_what_is_published(tmp_path):
    tracks = _split_tracks(tmp_path / "split", seed=3, n_sequences=3, seq_len=12)
    sweep = _script()
    batches = [(tracks, _uncertain_pass(tracks))]
    config = IntentFilterConfig(brake_sight="model")
    assert sweep.score(batches, config, 0.0)["brake_on_of_judged"] == 0.0
    assert sweep.score(batches, config, 1.0)["brake_on_of_judged"] == 1.0


def test_side_brake_f1_pools_both_sides_and_leaves_the_rear_out():
    sweep = _script()

    def view(on_hit, on_missed, off_called_on):
        # rows: truth OFF / ON / UNKNOWN; columns: published OFF / ON / UNKNOWN
        return {"brake": {"confusion": [[10, off_called_on, 0], [on_missed, on_hit, 0],
                                        [0, 0, 0]]}}

    report = {"groups": {"view": {"LEFT": view(3, 1, 0), "RIGHT": view(1, 3, 0),
                                  "BEHIND": view(50, 0, 0)}}}
    # pooled sides: 4 hits, 4 misses, no false ON -> precision 1, recall 0.5
    assert sweep.side_brake_f1(report) == pytest.approx(2 / 3)
    assert sweep.side_brake_f1({"groups": {"view": {"BEHIND": view(5, 0, 0)}}}) is None


def test_a_side_shift_acts_in_proportion_to_the_view_heads_side_mass():
    sweep = _script()
    brake = np.array([[[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]]])
    view = np.zeros((1, 2, 4))
    view[0, 0, 0] = 1.0  # BEHIND: no side mass, nothing moves
    view[0, 1, 1] = view[0, 1, 3] = 0.5  # LEFT + RIGHT = 1: the whole side shift
    shifted = sweep.shift_brake({"brake": brake, "view": view}, 0.0, 2.0)["brake"]
    assert shifted[0, 0, 1] == pytest.approx(0.5)
    assert shifted[0, 1, 1] / shifted[0, 1, 0] == pytest.approx(np.exp(2.0))
    both = sweep.shift_brake({"brake": brake, "view": view}, 1.0, 2.0)["brake"]
    assert both[0, 0, 1] / both[0, 0, 0] == pytest.approx(np.e)
    assert both[0, 1, 1] / both[0, 1, 0] == pytest.approx(np.exp(3.0))


def test_brake_false_on_counts_off_frames_published_on():
    sweep = _script()
    # rows: truth OFF / ON / UNKNOWN; columns: published OFF / ON / UNKNOWN
    report = {"overall": {"brake": {"confusion": [[6, 3, 1], [2, 8, 0], [0, 0, 5]]}}}
    assert sweep.brake_false_on(report) == pytest.approx(0.3)
    no_off = {"overall": {"brake": {"confusion": [[0, 0, 0], [2, 8, 0], [0, 0, 5]]}}}
    assert sweep.brake_false_on(no_off) is None
    assert sweep.brake_false_on({"overall": {}}) is None


class _Track:
    def __init__(self, left, right):
        self.labels = np.zeros((len(left), len(TASKS)), np.int64)
        self.labels[:, TASKS.index("left")] = left
        self.labels[:, TASKS.index("right")] = right

    def __len__(self):
        return len(self.labels)


def _blinker_pass():
    # frames labelled OFF, ON, UNKNOWN, unlabelled, and a frame the model did not step
    p = np.array([[[0.3, 0.2, 0.5]] * 4 + [[np.nan] * 3]])
    return [_Track([0, 1, 2, -1, 1], [0, 1, 2, -1, 1])], {"left": p, "right": p.copy(),
                                                        "brake": p.copy()}


def test_blinkers_from_truth_replaces_sight_state_or_both():
    sweep = _script()
    tracks, raw = _blinker_pass()
    assert sweep.blinkers_from_truth(raw, tracks, "model") is raw
    sight = sweep.blinkers_from_truth(raw, tracks, "sight")["left"][0]
    np.testing.assert_allclose(sight[:3], [[0.6, 0.4, 0], [0.6, 0.4, 0], [0, 0, 1]])
    state = sweep.blinkers_from_truth(raw, tracks, "state")["right"][0]
    np.testing.assert_allclose(state[:3], [[0.5, 0, 0.5], [0, 0.5, 0.5], [0.3, 0.2, 0.5]])
    truth = sweep.blinkers_from_truth(raw, tracks, "truth")
    np.testing.assert_allclose(truth["left"][0, :3], np.eye(3))
    for part in ("sight", "state", "truth"):
        out = sweep.blinkers_from_truth(raw, tracks, part)
        np.testing.assert_allclose(out["left"][0, 3], [0.3, 0.2, 0.5])  # unlabelled
        assert np.isnan(out["left"][0, 4]).all()  # never stepped
        assert out["brake"] is raw["brake"]
    assert np.allclose(raw["left"][0, 0], [0.3, 0.2, 0.5])  # the pass itself is not changed
    with pytest.raises(ValueError, match="blinkers"):
        sweep.blinkers_from_truth(raw, tracks, "oracle")


def test_the_truths_blinkers_through_a_filter_without_delays_give_the_true_intent(tmp_path):
    tracks = _split_tracks(tmp_path / "split", seed=5, n_sequences=4, seq_len=40)
    sweep = _script()
    raw = sweep.blinkers_from_truth(_uncertain_pass(tracks), tracks, "truth")
    no_delays = IntentFilterConfig(confirm_s=0.0, hold_s=0.0, visibility_confirm_s=0.0,
                                   flash_min_evidence=0.0, intent_source="lights")
    assert sweep.score([(tracks, raw)], no_delays, 0.0)["intent_macro_f1"] == pytest.approx(1.0)
    # the heads as they were (every blinker OFF) miss the split's blinks
    assert any((t.labels[:, TASKS.index("left")] == 1).any() for t in tracks)
    assert sweep.score([(tracks, _uncertain_pass(tracks))], no_delays,
                       0.0)["intent_macro_f1"] < 0.9


def test_blinker_f1_and_switches_pool_left_and_right(tmp_path):
    tracks = _split_tracks(tmp_path / "split", seed=5, n_sequences=4, seq_len=40)
    sweep = _script()
    no_delays = IntentFilterConfig(confirm_s=0.0, hold_s=0.0, visibility_confirm_s=0.0,
                                   flash_min_evidence=0.0, intent_source="lights")
    truth = sweep.score([(tracks, sweep.blinkers_from_truth(_uncertain_pass(tracks), tracks,
                                                            "truth"))], no_delays, 0.0)
    assert truth["blinker_f1"] == pytest.approx(1.0)
    assert sweep.score([(tracks, _uncertain_pass(tracks))], no_delays, 0.0)["blinker_f1"] == 0.0
    switches = {"left": {"predicted": 3, "true": 1}, "right": {"predicted": 1, "true": 3}}
    assert sweep.pooled_ratio(switches, ("left", "right")) == pytest.approx(1.0)
    assert sweep.pooled_ratio({"left": {"predicted": 2, "true": 0}}, ("left",)) is None


def test_a_pass_blind_to_every_lamp_is_unknown_where_visible_and_names_one_view(tmp_path):
    tracks = _split_tracks(tmp_path / "split", seed=5, n_sequences=4, seq_len=40)
    sweep = _script()
    no_delays = IntentFilterConfig(confirm_s=0.0, hold_s=0.0, visibility_confirm_s=0.0,
                                   flash_min_evidence=0.0, intent_source="lights",
                                   brake_sight="model")
    blind = _uncertain_pass(tracks)
    for task in ("brake", "left", "right"):
        blind[task][...] = (0.0, 0.0, 1.0)
    r = sweep.score([(tracks, blind)], no_delays, 0.0)
    assert r["unknown_visible"] == pytest.approx(1.0)
    assert r["blinker_on_of_judged"] is None  # nothing judged
    assert r["view_accuracy"] < 1.0  # always BEHIND, where the split has other views
    views = sweep._labels(tracks, blind["view"].shape[:2], "view")
    named = dict(blind, view=np.eye(4, dtype=np.float32)[np.maximum(views, 0)])
    assert sweep.score([(tracks, named)], no_delays, 0.0)["view_accuracy"] == pytest.approx(1.0)
    seen = sweep.score([(tracks, sweep.blinkers_from_truth(_uncertain_pass(tracks), tracks,
                                                           "truth"))], no_delays, 0.0)
    assert seen["unknown_visible"] < 0.5
    assert 0.0 < seen["blinker_on_of_judged"] < 1.0

class _TimedTrack(_Track):
    def __init__(self, left, fps=10.0):
        super().__init__(left, left)
        self.stamps_ns = (np.arange(len(left)) * 1e9 / fps).astype(np.int64)


def test_late_labels_start_and_end_each_episode_late_and_keep_unknown():
    sweep = _script()
    #        frame: 0  1  2  3  4  5  6  7  8  9
    left = np.array([0, 1, 1, 1, 1, 0, 0, 2, 0, 0])
    track = _TimedTrack(left)
    labels = np.full((1, 12), -1)
    labels[0, :10] = left
    late = sweep.late_labels([track], labels, 0.2, 0.1)  # 2 frames in, 1 frame after
    assert late[0].tolist() == [0, 0, 0, 1, 1, 1, 0, 2, 0, 0, -1, -1]
    assert sweep.late_labels([track], labels, 0.0, 0.0).tolist() == labels.tolist()
    # an episode shorter than the onset lag is missed whole
    assert (sweep.late_labels([track], labels, 0.5, 0.0)[0, :10] != 1).all()


def test_a_blinker_lag_lowers_the_truths_intent(tmp_path):
    # seed 7: a right blinker switched on after the warm-up, off and on again
    tracks = _split_tracks(tmp_path / "split", seed=7, n_sequences=4, seq_len=40)
    sweep = _script()
    no_delays = IntentFilterConfig(confirm_s=0.0, hold_s=0.0, visibility_confirm_s=0.0,
                                   flash_min_evidence=0.0, intent_source="lights")
    on_time = sweep.blinkers_from_truth(_uncertain_pass(tracks), tracks, "truth")
    assert sweep.score([(tracks, on_time)], no_delays, 0.0)["intent_macro_f1"] == \
        pytest.approx(1.0)
    late = sweep.blinkers_from_truth(_uncertain_pass(tracks), tracks, "truth", (0.3, 0.3))
    assert sweep.score([(tracks, late)], no_delays, 0.0)["intent_macro_f1"] < 0.99


def test_lit_blinkers_are_a_perfect_per_frame_eye_and_need_a_split(tmp_path):
    from signal_light_node.errors import ConfigError

    tracks = _split_tracks(tmp_path / "split", seed=5, n_sequences=4, seq_len=40)
    sweep = _script()
    (batch,) = sweep.with_blinkers([(tracks, _uncertain_pass(tracks))], "lit", tmp_path / "split")
    lit = sweep.lit_tracks(tmp_path / "split")
    column = TASKS.index("left")
    state = np.concatenate([t.labels[:, column] for t in tracks])
    flash = np.concatenate([t.labels[:, column] for t in lit])
    p_on = np.concatenate([batch[1]["left"][i, :len(t), 1] for i, t in enumerate(tracks)])
    dark_half = (state == 1) & (flash == 0)
    assert dark_half.any() and (flash == 1).any()
    assert (p_on[flash == 1] == 1).all() and (p_on[dark_half] == 0).all()
    with pytest.raises(ConfigError, match="split directory"):
        sweep.with_blinkers([(tracks, _uncertain_pass(tracks))], "lit", tmp_path)
