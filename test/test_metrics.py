"""Metric functions against values computed by hand on small arrays."""

import math

import cv2
import numpy as np
import pytest

from signal_light_node.evaluation import metrics as M
from signal_light_node.errors import ConfigError

# Intent: OFF=0 LEFT=1 RIGHT=2 HAZARD=3 UNKNOWN=4.
INTENT_TRUE = [0, 0, 1, 1, 2, 2, 3, 4, 4]
INTENT_PRED = [0, 1, 1, 0, 2, 2, 1, 4, 0]


def test_confusion_layout_rows_are_ground_truth():
    m = M.confusion_matrix([0, 0, 1], [1, 1, 2], 3)
    assert m.tolist() == [[0, 2, 0], [0, 0, 1], [0, 0, 0]]
    norm = M.normalise_rows(m)
    assert norm.tolist() == [[0, 1, 0], [0, 0, 1], [0, 0, 0]]


def test_intent_metrics_by_hand():
    r = M.task_metrics("intent", INTENT_TRUE, INTENT_PRED)
    assert r["confusion"] == [
        [1, 1, 0, 0, 0],
        [1, 1, 0, 0, 0],
        [0, 0, 2, 0, 0],
        [0, 1, 0, 0, 0],
        [1, 0, 0, 0, 1],
    ]
    assert r["n"] == 9
    assert r["accuracy"] == pytest.approx(5 / 9)
    # recalls 1/2, 1/2, 1, 0, 1/2
    assert r["macro_recall"] == pytest.approx(0.5)
    # F1 = 2TP/(true+pred): 2/5, 2/5, 4/4, 0/1, 2/3
    assert r["macro_f1"] == pytest.approx((0.4 + 0.4 + 1.0 + 0.0 + 2 / 3) / 5)
    # FP: GT OFF/UNKNOWN (4 frames), 2 predicted as something else.
    assert r["fp_rate"] == pytest.approx(0.5)
    # FN: GT LEFT/RIGHT/HAZARD (5 frames), LEFT->OFF and HAZARD->LEFT wrong.
    assert r["fn_rate"] == pytest.approx(0.4)
    assert r["per_class"]["precision"][3] is None  # HAZARD never predicted
    assert r["per_class"]["precision"][0] == pytest.approx(1 / 3)
    assert r["confusion_normalised"][4] == [0.5, 0, 0, 0, 0.5]


def test_light_metrics_and_class_only_predicted_counts_in_f1():
    # brake: OFF=0 ON=1 UNKNOWN=2; UNKNOWN never true but predicted once.
    r = M.task_metrics("brake", [0, 0, 1, 1], [0, 2, 1, 1])
    assert r["accuracy"] == pytest.approx(0.75)
    assert r["macro_recall"] == pytest.approx(0.75)  # UNKNOWN left out (0/0)
    assert r["macro_f1"] == pytest.approx((2 / 3 + 1.0 + 0.0) / 3)
    assert r["fp_rate"] == pytest.approx(0.5)
    assert r["fn_rate"] == pytest.approx(0.0)


def test_unknown_ground_truth_misread_is_false_positive():
    # GT UNKNOWN predicted ON is a false positive; GT ON predicted UNKNOWN a false negative.
    r = M.task_metrics("left", [2, 2, 1, 1, 1, 1], [1, 2, 2, 1, 1, 1])
    assert r["fp_rate"] == pytest.approx(0.5)
    assert r["fn_rate"] == pytest.approx(0.25)


def test_absent_classes_and_view_rates():
    r = M.task_metrics("view", [0, 0], [0, 0])
    assert r["macro_f1"] == 1.0 and r["macro_recall"] == 1.0
    assert r["fp_rate"] is None and r["fn_rate"] is None
    empty = M.task_metrics("brake", [], [])
    assert empty["accuracy"] is None and empty["fp_rate"] is None and empty["n"] == 0


def test_bad_input_is_rejected():
    with pytest.raises(ConfigError, match="differ in length"):
        M.accuracy([0, 1], [0])
    with pytest.raises(ConfigError, match="outside"):
        M.confusion_matrix([0, 3], [0, 0], 3)
    with pytest.raises(ConfigError, match="unknown task"):
        M.task_metrics("horn", [0], [0])


def test_bands():
    assert M.box_size_band([10, 32, 63.9, 64, 128, 500, math.nan]).tolist() == [
        "<32px", "32-64px", "32-64px", "64-128px", ">=128px", ">=128px", "unknown"]
    assert M.occlusion_band([0, 0.09, 0.1, 0.49, 0.5, 1.0]).tolist() == [
        "none", "none", "partial", "partial", "heavy", "heavy"]


def test_accumulator_grouped_breakdown_and_summary():
    acc = M.MetricAccumulator()
    lighting = ["day"] * 5 + ["night"] * 4
    acc.add("intent", INTENT_TRUE, INTENT_PRED, {"lighting": lighting, "source": "a"})
    acc.add("brake", [0, 1, 1, -1], [0, 1, 0, 2], {"lighting": "night"})  # -1 is skipped
    acc.add("left", [1, 1, 0], [1, 0, 0])
    report = acc.report()
    assert report["overall"]["intent"]["n"] == 9
    assert report["overall"]["brake"]["n"] == 3
    day = report["groups"]["lighting"]["day"]["intent"]
    night = report["groups"]["lighting"]["night"]["intent"]
    # day = first five frames: OFF ok, OFF->LEFT, LEFT ok, LEFT->OFF, RIGHT ok
    assert day["n"] == 5 and day["accuracy"] == pytest.approx(3 / 5)
    assert day["fp_rate"] == pytest.approx(0.5) and day["fn_rate"] == pytest.approx(1 / 3)
    assert night["n"] == 4 and night["accuracy"] == pytest.approx(2 / 4)
    assert np.add(day["confusion"], night["confusion"]).tolist() == \
        report["overall"]["intent"]["confusion"]
    assert report["groups"]["lighting"]["night"]["brake"]["accuracy"] == pytest.approx(2 / 3)
    assert report["groups"]["source"]["a"]["intent"]["n"] == 9
    s = report["summary"]
    assert s["brake_accuracy"] == pytest.approx(2 / 3)
    assert s["intent_fp_rate"] == pytest.approx(0.5)
    # pooled light FN: brake 1 of 2 ON wrong, left 1 of 2 ON wrong -> 2/4
    assert s["lights_fn_rate"] == pytest.approx(0.5)
    assert s["lights_fp_rate"] == pytest.approx(0.0)
    assert M.selection_score(s) == pytest.approx(0.5 * (s["intent_macro_f1"] + 2 / 3))
    # an intent-only ablation is picked by intent alone; an untrained brake head does not vote
    assert M.selection_score(s, ["intent"]) == pytest.approx(s["intent_macro_f1"])
    assert M.selection_score(s, ["brake", "view"]) == pytest.approx(2 / 3)
    assert M.selection_score(s, (t for t in ["brake", "view"])) == pytest.approx(2 / 3)
    # a second add accumulates
    acc.add("intent", [3], [3])
    assert acc.confusion("intent")[3, 3] == 1


def test_accumulator_add_frames_and_group_length_check():
    acc = M.MetricAccumulator()
    t = np.array([[0, 1, 0, 0, 0], [3, 0, 1, 1, 2]])
    acc.add_frames(t, t, {"view": ["BEHIND", "FRONT"]})
    rep = acc.report()
    assert all(rep["overall"][task]["accuracy"] == 1.0 for task in rep["overall"])
    assert set(rep["groups"]["view"]) == {"BEHIND", "FRONT"}
    with pytest.raises(ConfigError, match="group"):
        acc.add("intent", [0, 1], [0, 1], {"view": ["BEHIND"]})


def test_markdown_and_png(tmp_path):
    acc = M.MetricAccumulator()
    acc.add("intent", INTENT_TRUE, INTENT_PRED, {"lighting": "day"})
    acc.add("brake", [0, 1], [0, 1], {"lighting": "day"})
    report = acc.report()
    md = M.markdown_report(report, title="test")
    assert md.startswith("### test")
    assert "| intent | 9 | 55.6 % |" in md
    assert "| **UNKNOWN** | 50.0 % | 0.0 % | 0.0 % | 0.0 % | 50.0 % | 2 |" in md
    assert "By lighting:" in md and "| day | 9 |" in md
    path = tmp_path / "cm.png"
    M.render_confusion_png(np.array(report["overall"]["intent"]["confusion"]),
                           report["overall"]["intent"]["class_names"], str(path), "intent")
    img = cv2.imread(str(path))
    assert img is not None and img.shape[0] > 400 and img.shape[1] > 400
    # The RIGHT->RIGHT cell (100 %) is dark, the RIGHT->OFF cell (0 %) is white.
    cell, left, top = 96, 130, 80
    dark = img[top + 2 * cell + 5, left + 2 * cell + 5]
    white = img[top + 2 * cell + 5, left + 0 * cell + 5]
    assert dark[2] < 50 and white.tolist() == [255, 255, 255]
    with pytest.raises(ConfigError, match="does not match"):
        M.render_confusion_png(np.zeros((2, 2)), ["a", "b", "c"], str(path))


def test_count_changes_by_hand():
    assert M.count_changes([]) == 0 and M.count_changes([3]) == 0
    assert M.count_changes([2, 0, 2, 0, 2, 2, 1]) == 5
    with pytest.raises(ConfigError):
        M.count_changes([[1, 2]])


def test_switch_counter_sums_tracks_skips_unlabelled_frames_and_reports_the_ratio():
    counter = M.SwitchCounter()
    assert counter.report() == {"predicted": 0, "true": 0, "ratio": None, "per_track": {}}
    # RIGHT, off, RIGHT, off ... against a truth that stays RIGHT, then turns OFF once.
    counter.add("33", [2, 2, 2, 2, 2, 0], [2, 0, 2, 0, 2, 0])
    # The unlabelled (-1) frame is left out of both: 1 -> 1 is no change.
    counter.add("7", [1, -1, 1, 0], [1, 3, 1, 1])
    counter.add("7", [0, 0], [0, 1])
    rep = counter.report()
    assert rep["per_track"] == {"33": {"predicted": 5, "true": 1},
                                "7": {"predicted": 1, "true": 1}}
    assert (rep["predicted"], rep["true"]) == (6, 2) and rep["ratio"] == pytest.approx(3.0)
    with pytest.raises(ConfigError, match="differ in length"):
        counter.add("x", [1, 2], [1])


def test_switches_markdown_lists_tasks_and_the_most_flickering_tracks():
    counter = M.SwitchCounter()
    for k in range(5):
        counter.add(f"t{k}", [0] * 6, [0, 1] * k + [0] * (6 - 2 * k) if k < 4 else [0] * 6)
    brake = M.SwitchCounter()
    brake.add("t0", [0, 1], [0, 1])
    md = M.switches_markdown({"intent": counter.report(), "brake": brake.report()},
                             max_tracks=2)
    assert "| intent | 11 | 0 | – |" in md and "| brake | 1 | 1 | 1.00 |" in md
    assert "(2 of 5, most changes first)" in md
    assert md.index("| t3 | 5 | 0 |") < md.index("| t2 | 4 | 0 |") and "| t1 |" not in md


def test_unknown_where_visible_pools_the_lights_true_off_and_on_rows():
    overall = {  # rows: true OFF, ON, UNKNOWN; columns: published OFF, ON, UNKNOWN
        "brake": {"confusion": [[6, 1, 3], [0, 8, 2], [0, 0, 50]]},
        "left": {"confusion": [[10, 0, 0], [0, 0, 0], [0, 0, 9]]},
        "intent": {"confusion": [[0, 0, 0, 0, 99]] * 5},  # not a light: left out
    }
    assert M.unknown_where_visible(overall) == pytest.approx(5 / 30)
    assert M.unknown_where_visible(overall, ("left",)) == 0.0
    assert M.unknown_where_visible({"brake": {"confusion": [[0, 0, 0], [0, 0, 0], [0, 0, 4]]}}) \
        is None
