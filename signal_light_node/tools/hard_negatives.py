"""How often a model reports a light ON in a bag where no vehicle signals anything.

The hard-negative bags (``bags/night_tail_lamps``, ``bags/night_no_signals``,
``bags/day_running_lamps``) come from the independent evaluation generator with
``--events none``: steady tail lamps, head lamps, daytime running lamps, glare and
reflections, and no brake or blinker at all. Every light the node reports ON there is a
false one. The bag is replayed through an engine exactly as the node runs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from signal_light_node.labels import LightStatus
from signal_light_node.tools.replay import replay_bag

#: The committed hard-negative bags, relative to the repository root.
HARD_NEGATIVE_BAGS = ("bags/night_tail_lamps", "bags/night_no_signals", "bags/day_running_lamps")


@dataclass(frozen=True)
class FalseLights:
    """Shares of judged vehicle-frames reporting a light ON.

    Attributes:
        judged: Vehicle-frames judged (a box that could be cropped).
        blinker_on: Share with the left or the right blinker ON.
        brake_on: Share with the brake ON.
        images: Frames replayed.
    """

    judged: int
    blinker_on: float
    brake_on: float
    images: int


def false_lights(bag: "str | Path", engine: Any, out_dir: "str | Path") -> FalseLights:
    """Replay ``bag`` through ``engine`` and count the lights it reports ON.

    Args:
        bag: A bag without any signal.
        engine: A ``runtime.engine.LightStateEngine`` (e.g. ``engine_from_checkpoint``).
        out_dir: Where the replay writes its output bag.
    """
    counts = [0, 0, 0]

    def count(image: Any, boxes: Any, frame: Any) -> None:
        for result in frame.results:
            if result.judged:
                counts[0] += 1
                counts[1] += int(LightStatus.ON in (result.left.state, result.right.state))
                counts[2] += int(result.brake.state == LightStatus.ON)

    summary = replay_bag(Path(bag), Path(out_dir), engine, progress=False, on_frame=count)
    judged = max(1, counts[0])
    return FalseLights(counts[0], counts[1] / judged, counts[2] / judged, summary.images)
