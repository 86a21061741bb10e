"""The scene bags committed under bags/ (made by scripts/make_bags.sh) are there and complete."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.io.image_codec import msg_to_bgr
from signal_light_node.synth.bag import (COMPRESSED_TOPIC, DETECTIONS_TOPIC, GROUND_TRUTH_TOPIC,
                                         coverage_gaps, ground_truth_coverage)

REPO = Path(__file__).resolve().parents[1]
BAGS = {"day": REPO / "bags" / "day_street", "night": REPO / "bags" / "night_street"}
#: 20 MiB since 2026-11-24: two hard-negative bags (no signal at all) joined the five.
MAX_TOTAL_BYTES = 20 * 1024 * 1024


def test_bags_exist_and_are_small():
    for bag in BAGS.values():
        assert (bag / "metadata.yaml").is_file(), f"{bag} is missing; run scripts/make_bags.sh"
        assert len(list(bag.glob("*.mcap"))) == 1
    total = sum(f.stat().st_size for f in (REPO / "bags").rglob("*") if f.is_file())
    assert total < MAX_TOTAL_BYTES, f"bags/ holds {total / 2**20:.1f} MiB"


@pytest.mark.parametrize("name", sorted(BAGS))
def test_bag_covers_every_class(name):
    coverage = ground_truth_coverage(BAGS[name])
    assert coverage_gaps(coverage, min_tracks=4) == []  # the rule make_bags.sh checks
    assert 9.0 <= coverage["duration_s"] <= 11.0
    assert set(coverage["views"]) == {"BEHIND", "LEFT", "FRONT", "RIGHT"}
    assert set(coverage["intents"]) == {"OFF", "LEFT", "RIGHT", "HAZARD", "UNKNOWN"}
    assert coverage["brake"]["ON"] > 0 and coverage["brake"]["OFF"] > 0


@pytest.mark.parametrize("name", sorted(BAGS))
def test_every_frame_has_detections_and_truth(name):
    with bagio.open_bag(BAGS[name]) as bag:
        topics = bag.topics()
        counts = {t: i.count for t, i in topics.items()}
        assert counts[COMPRESSED_TOPIC] == counts[DETECTIONS_TOPIC] == counts[GROUND_TRUTH_TOPIC]
        stamps = {t: [m.log_time_ns for m in bag.messages([t])] for t in topics}
        vehicles = max(len(m.msg.vehicles) for m in bag.messages([GROUND_TRUTH_TOPIC]))
    assert stamps[COMPRESSED_TOPIC] == stamps[DETECTIONS_TOPIC] == stamps[GROUND_TRUTH_TOPIC]
    assert vehicles >= 4


def _mean_brightness(path: Path) -> float:
    with bagio.open_bag(path) as bag:
        images = [msg_to_bgr(m.msg) for _, m in zip(range(5), bag.messages([COMPRESSED_TOPIC]))]
    return float(np.mean([img.mean() for img in images]))


def test_night_bag_is_darker_than_day_bag():
    assert _mean_brightness(BAGS["night"]) < 0.7 * _mean_brightness(BAGS["day"])
