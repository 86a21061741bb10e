"""Steady bright tail lamps at night are not blinkers (shipped weights, committed bags).

``bags/night_tail_lamps`` comes from the independent evaluation generator
(``signal_light_node.evalgen``, never trained on): vehicles at night with their tail
lamps lit, saturated and bloomed, and no signal at all. Replayed through the engine as
the node runs it, fewer than 5 % of the judged vehicle-frames may report a blinker ON:
the target of the model issue, met since the filled-crop members shipped 2026-11-29
(2.8 %). Before: the weights shipped 2026-11-22: 17.7 % with the filter's former 0.8 s
hold, 16.9 % with the 0.6 s hold, 7.3 % since the flash gate of 2026-11-25 (a blinker must
flash); the weights before them 43.3 %; the fine-tuned trunk shipped 2026-11-26: 6.1 %; its
two members over three times the tracks shipped the same day, fourth session: 11.2 %; the
same file with its blinkers' ON offset fitted on the held-out family, fifth session: 7.3 %.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from signal_light_node.tools.hard_negatives import FalseLights, false_lights

BAG = Path(__file__).resolve().parents[1] / "bags" / "night_tail_lamps"
#: The target (the model issue's); the shipped weights measure 0.028.
MAX_BLINKER_ON = 0.05


def _false_lights(bag: Path, tmp_path) -> "FalseLights":
    from signal_light_node.runtime.engine import engine_from_checkpoint

    result = false_lights(bag, engine_from_checkpoint(), tmp_path / "out")
    assert result.images >= 50 and result.judged >= 200, result
    return result


def _blinker_on_share(tmp_path) -> float:
    return _false_lights(BAG, tmp_path).blinker_on


@pytest.mark.skipif(not BAG.exists(), reason="bags/night_tail_lamps is not committed")
def test_tail_lamps_at_night_are_not_blinkers(tmp_path):
    assert _blinker_on_share(tmp_path) < MAX_BLINKER_ON


#: The other hard negatives (no signal at all) and what the shipped weights must not get
#: worse than: measured 2026-11-24 (blinker ON / brake ON share of judged vehicle-frames)
#: night_no_signals 0.121 / 0.331, day_running_lamps 0.000 / 0.005; with the 0.6 s hold
#: (2026-11-25) night_no_signals 0.096 blinker ON; with the flash gate (2026-11-25, later)
#: 0.000 / 0.331 and 0.000 / 0.005; the fine-tuned trunk (2026-11-26) 0.000 / 0.217 and
#: 0.000 / 0.008; its two members over three times the tracks (2026-11-26, fourth session)
#: 0.000 / 0.118 and 0.000 / 0.000, the same with the blinkers' ON offset (fifth session)
#: the same figures; the filled-crop members shipped 2026-11-29 (brake sight ``rear``, 0.2 s
#: visibility hold) 0.000 / 0.132 and 0.000 / 0.044.
OTHER_HARD_NEGATIVES = {"night_no_signals": (0.05, 0.20), "day_running_lamps": (0.05, 0.05)}


@pytest.mark.parametrize("name", sorted(OTHER_HARD_NEGATIVES))
def test_no_signal_bags_stay_below_the_measured_false_lights(name, tmp_path):
    bag = BAG.parent / name
    if not bag.exists():
        pytest.skip(f"bags/{name} is not committed")
    result = _false_lights(bag, tmp_path)
    blinker_bound, brake_bound = OTHER_HARD_NEGATIVES[name]
    assert result.blinker_on < blinker_bound, result
    assert result.brake_on < brake_bound, result
