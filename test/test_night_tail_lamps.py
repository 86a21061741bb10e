"""Steady bright tail lamps at night are not blinkers (shipped weights, committed bag).

``bags/night_tail_lamps`` comes from the independent evaluation generator
(``signal_light_node.evalgen``, never trained on): vehicles at night with their tail
lamps lit, saturated and bloomed, and no signal at all. Replayed through the engine as
the node runs it, fewer than 5 % of the judged vehicle-frames may report a blinker ON:
the target of the model issue, not met yet (the weights shipped 2026-11-22: 17.7 %, the
previous ones 43.3 %), so that test is a strict expected failure that turns red once the
target is met. A second test keeps the measured level from regressing.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from signal_light_node.labels import LightStatus
from signal_light_node.tools.replay import replay_bag

BAG = Path(__file__).resolve().parents[1] / "bags" / "night_tail_lamps"
#: The target.
MAX_BLINKER_ON = 0.05
#: What the shipped weights must not get worse than (measured 0.177; the previous weights
#: 0.433, the same weights without the intent filter 0.474).
REGRESSION_BOUND = 0.25


def _blinker_on_share(tmp_path) -> float:
    from signal_light_node.runtime.engine import engine_from_checkpoint

    judged = blinker_on = 0

    def count(image, boxes, frame) -> None:
        nonlocal judged, blinker_on
        for result in frame.results:
            if not result.judged:
                continue
            judged += 1
            blinker_on += int(LightStatus.ON in (result.left.state, result.right.state))

    summary = replay_bag(BAG, tmp_path / "out", engine_from_checkpoint(), progress=False,
                         on_frame=count)
    assert summary.images >= 50 and judged >= 200, (summary.images, judged)
    return blinker_on / judged


@pytest.mark.skipif(not BAG.exists(), reason="bags/night_tail_lamps is not committed")
def test_tail_lamps_at_night_stay_below_the_measured_level(tmp_path):
    assert _blinker_on_share(tmp_path) < REGRESSION_BOUND


@pytest.mark.skipif(not BAG.exists(), reason="bags/night_tail_lamps is not committed")
@pytest.mark.xfail(strict=True, reason="target not met yet: 17.7 % of judged frames report "
                   "a blinker ON (docs/model.md, Results)")
def test_tail_lamps_at_night_are_not_blinkers(tmp_path):
    assert _blinker_on_share(tmp_path) < MAX_BLINKER_ON
