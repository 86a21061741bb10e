"""Tests of the per-track recurrent state bank."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fake_light_model import FakeLightModel, row_values, state_of
from signal_light_node.errors import ConfigError
from signal_light_node.runtime.state_bank import RESET_BACKWARDS, RESET_GAP, StateBank

MS = 1_000_000


def _step(bank, ids, stamp_ns, values):
    bank.gather(ids, stamp_ns)
    return bank.store(ids, state_of(values), stamp_ns)


def test_new_tracks_start_from_initial_state_with_the_model_layout():
    model = FakeLightModel()
    bank = StateBank(model)
    state = bank.gather(["a", "b"], 0)
    want = model.initial_state(2)
    assert len(state) == len(want)
    for (h, c), (wh, wc) in zip(state, want):
        assert h.shape == wh.shape and c.shape == wc.shape
        assert torch.equal(h, wh) and torch.equal(c, wc)
    frames = bank.store(["a", "b"], state_of([1.0, 2.0]), 0)
    assert frames.tolist() == [1, 1]
    assert bank.frames_observed("a") == 1 and bank.frames_observed("zzz") == 0


def test_states_round_trip_by_track_in_any_order_and_subset():
    bank = StateBank(FakeLightModel())
    _step(bank, ["a", "b", "c"], 0, [1.0, 2.0, 3.0])
    state = bank.gather(["c", "new", "a"], 10 * MS)
    assert row_values(state) == [3.0, 0.0, 1.0]
    frames = bank.store(["c", "new", "a"], state_of([30.0, 40.0, 10.0]), 10 * MS)
    assert frames.tolist() == [2, 1, 2]
    assert row_values(bank.gather(["a", "b", "c", "new"], 20 * MS)) == [10.0, 2.0, 30.0, 40.0]


def test_track_unseen_longer_than_timeout_starts_fresh():
    bank = StateBank(FakeLightModel(), track_timeout_s=0.5, max_gap_s=10.0)
    _step(bank, ["a", "b"], 0, [5.0, 6.0])
    _step(bank, ["b"], 400 * MS, [7.0])
    assert bank.last_seen_ns("a") == 0
    # At 600 ms "a" was last seen 600 ms ago (> 0.5 s), "b" 200 ms ago.
    state = bank.gather(["a", "b"], 600 * MS)
    assert row_values(state) == [0.0, 7.0]
    assert bank.store(["a", "b"], state_of([1.0, 1.0]), 600 * MS).tolist() == [1, 3]
    assert bank.counters["expired"] == 1


def test_expire_drops_only_old_tracks():
    bank = StateBank(FakeLightModel(), track_timeout_s=1.0)
    _step(bank, ["a"], 0, [1.0])
    _step(bank, ["b"], 900 * MS, [2.0])
    assert bank.expire(1500 * MS) == ["a"]
    assert bank.track_ids == ["b"]


def test_cap_evicts_least_recently_seen_track():
    bank = StateBank(FakeLightModel(), max_tracks=2, track_timeout_s=5.0)
    _step(bank, ["a"], 0, [1.0])
    _step(bank, ["b"], 10 * MS, [2.0])
    _step(bank, ["a"], 20 * MS, [3.0])  # now "b" is the least recently seen
    state = bank.gather(["c"], 30 * MS)
    assert row_values(state) == [0.0]
    bank.store(["c"], state_of([4.0]), 30 * MS)
    assert sorted(bank.track_ids) == ["a", "c"]
    assert bank.counters["evictions"] == 1
    assert row_values(bank.gather(["a", "c"], 40 * MS)) == [3.0, 4.0]


def test_more_tracks_in_one_frame_than_the_cap_still_get_states():
    bank = StateBank(FakeLightModel(), max_tracks=2)
    ids = ["a", "b", "c"]
    state = bank.gather(ids, 0)
    assert row_values(state) == [0.0, 0.0, 0.0]
    assert bank.store(ids, state_of([1.0, 2.0, 3.0]), 0).tolist() == [1, 1, 1]
    assert bank.counters["overflow"] == 1
    assert len(bank) == 2
    # The scratch row is not overwritten: a new overflowing track still starts at zero.
    assert row_values(bank.gather(["a", "b", "d"], 10 * MS)) == [1.0, 2.0, 0.0]


def test_stamp_jumping_back_resets_everything():
    bank = StateBank(FakeLightModel())
    _step(bank, ["a"], 500 * MS, [1.0])
    assert row_values(bank.gather(["a"], 100 * MS)) == [0.0]
    assert bank.reset_reasons == {RESET_BACKWARDS: 1}
    assert bank.counters["resets"] == 1


def test_stamp_jumping_forward_past_the_gap_resets_but_small_steps_do_not():
    bank = StateBank(FakeLightModel(), track_timeout_s=10.0, max_gap_s=2.0)
    _step(bank, ["a"], 0, [1.0])
    _step(bank, ["a"], 0, [2.0])  # a repeated stamp is not a jump
    _step(bank, ["a"], 1900 * MS, [3.0])
    assert bank.counters["resets"] == 0
    assert row_values(bank.gather(["a"], 4000 * MS)) == [0.0]
    assert bank.reset_reasons == {RESET_GAP: 1}


def test_manual_reset_clears_tracks_and_stamp():
    bank = StateBank(FakeLightModel())
    _step(bank, ["a", "b"], 100 * MS, [1.0, 2.0])
    bank.reset()
    assert len(bank) == 0 and bank.last_stamp_ns is None
    assert row_values(bank.gather(["a"], 0)) == [0.0]  # no backwards jump after a reset
    assert bank.counters["resets"] == 1


def test_contract_violations_are_refused():
    bank = StateBank(FakeLightModel())
    with pytest.raises(ValueError, match="distinct"):
        bank.gather(["a", "a"], 0)
    bank.gather(["a"], 0)
    with pytest.raises(ValueError, match="same track IDs"):
        bank.store(["b"], state_of([1.0]), 0)


@pytest.mark.parametrize("kwargs", [{"track_timeout_s": 0}, {"track_timeout_s": float("nan")},
                                    {"max_gap_s": -1.0}, {"max_tracks": 0},
                                    {"max_tracks": 2.5}, {"max_tracks": True}])
def test_bad_limits_are_config_errors(kwargs):
    with pytest.raises(ConfigError):
        StateBank(FakeLightModel(), **kwargs)


# ------------------------------------------------------------------ filter rows
INITIAL_ROW = np.array([np.nan, -1.0, 0.5])


def _filter_bank(**kwargs) -> StateBank:
    return StateBank(FakeLightModel(), filter_row=INITIAL_ROW, **kwargs)


def _filter_step(bank, ids, stamp_ns, values):
    """One frame: returns the rows gathered, stores rows filled with ``values``."""
    bank.gather(ids, stamp_ns)
    rows = bank.gather_filter_rows(ids)
    bank.store(ids, state_of([0.0] * len(ids)), stamp_ns,
               np.repeat(np.asarray(values, float)[:, None], len(INITIAL_ROW), axis=1))
    return rows


def _is_initial(rows) -> list:
    return [bool(np.array_equal(r, INITIAL_ROW, equal_nan=True)) for r in rows]


def test_filter_rows_start_initial_and_round_trip_by_track():
    bank = _filter_bank()
    assert _is_initial(_filter_step(bank, ["a", "b"], 0, [1.0, 2.0])) == [True, True]
    rows = _filter_step(bank, ["b", "new", "a"], 10 * MS, [20.0, 30.0, 10.0])
    assert rows[0].tolist() == [2.0] * 3 and _is_initial(rows[1:2]) == [True]
    assert rows[2].tolist() == [1.0] * 3
    bank.gather(["a"], 20 * MS)
    assert bank.gather_filter_rows(["a"]).tolist() == [[10.0] * 3]
    # store without rows leaves them as they were
    bank.store(["a"], state_of([0.0]), 20 * MS)
    bank.gather(["a"], 30 * MS)
    assert bank.gather_filter_rows(["a"]).tolist() == [[10.0] * 3]


def test_filter_rows_go_with_expired_evicted_and_reset_tracks():
    bank = _filter_bank(track_timeout_s=0.5, max_tracks=2, max_gap_s=10.0)
    _filter_step(bank, ["a", "b"], 0, [1.0, 2.0])
    _filter_step(bank, ["b"], 400 * MS, [3.0])
    # "a" expires at 600 ms; "c" evicts nobody (a's row is free again).
    rows = _filter_step(bank, ["a", "b"], 600 * MS, [4.0, 5.0])
    assert _is_initial(rows) == [True, False] and rows[1].tolist() == [3.0] * 3
    rows = _filter_step(bank, ["c"], 700 * MS, [6.0])  # full: evicts "a" or "b"
    assert _is_initial(rows) == [True] and bank.counters["evictions"] == 1
    kept = bank.track_ids
    bank.gather(kept, 800 * MS)
    assert sorted(bank.gather_filter_rows(kept)[:, 0].tolist()) == sorted(
        {"a": 4.0, "b": 5.0, "c": 6.0}[t] for t in kept)
    bank.store(kept, state_of([0.0] * len(kept)), 800 * MS)
    bank.reset()
    bank.gather(kept, 900 * MS)
    assert _is_initial(bank.gather_filter_rows(kept)) == [True, True]


def test_filter_rows_of_overflowing_tracks_are_not_kept():
    bank = _filter_bank(max_tracks=1)
    _filter_step(bank, ["a", "b"], 0, [1.0, 2.0])
    bank.gather(["a", "b"], 10 * MS)
    rows = bank.gather_filter_rows(["a", "b"])
    assert rows[0].tolist() == [1.0] * 3 and _is_initial(rows[1:]) == [True]


def test_filter_rows_need_the_gathered_ids_and_default_to_width_zero():
    bank = _filter_bank()
    bank.gather(["a"], 0)
    with pytest.raises(ValueError, match="same track IDs"):
        bank.gather_filter_rows(["b"])
    plain = StateBank(FakeLightModel())
    plain.gather(["a", "b"], 0)
    assert plain.gather_filter_rows(["a", "b"]).shape == (2, 0)
