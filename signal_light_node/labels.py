"""Class vocabularies shared by the data, the model, the metrics and the node.

The integer values equal the constants of ``signal_light_msgs`` so that a class
index can be written into a message without a lookup table.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Dict, Tuple


class LightStatus(IntEnum):
    """Logical state of one light (``signal_light_msgs/LightState``)."""

    OFF = 0
    ON = 1
    UNKNOWN = 2


class Intent(IntEnum):
    """Driver intent read from the blinkers (``VehicleLightState.INTENT_*``)."""

    OFF = 0
    LEFT = 1
    RIGHT = 2
    HAZARD = 3
    UNKNOWN = 4


class View(IntEnum):
    """Face of the vehicle that the camera sees (``VehicleLightState.VIEW_*``)."""

    BEHIND = 0
    LEFT = 1
    FRONT = 2
    RIGHT = 3


#: Model heads, in the order used everywhere (checkpoints, metrics, reports).
TASKS: Tuple[str, ...] = ("intent", "brake", "left", "right", "view")

#: Class names per head; index i is the class with integer value i.
CLASS_NAMES: Dict[str, Tuple[str, ...]] = {
    "intent": tuple(m.name for m in Intent),
    "brake": tuple(m.name for m in LightStatus),
    "left": tuple(m.name for m in LightStatus),
    "right": tuple(m.name for m in LightStatus),
    "view": tuple(m.name for m in View),
}

#: The per-light heads, each judged ON / OFF / UNKNOWN.
LIGHT_TASKS: Tuple[str, ...] = ("brake", "left", "right")

#: Autoware-style codes of ``signal_light_msgs/LightClassification``.
LIGHT_CODES: Dict[str, int] = {"brake": 100, "left": 101, "right": 102}


def intent_from_lights(left: int, right: int) -> Intent:
    """Derive the intent label from the two blinker states.

    The rule only uses what can be seen: a lit side whose partner is hidden still
    tells the turn direction (a side view of a left blink is LEFT), but an unlit
    side whose partner is hidden tells nothing, so it is UNKNOWN.

    Args:
        left: State of the vehicle's own left blinker (a ``LightStatus`` value).
        right: State of the vehicle's own right blinker.

    Returns:
        The intent class.
    """
    left, right = LightStatus(left), LightStatus(right)
    on, off = LightStatus.ON, LightStatus.OFF
    if left == on and right == on:
        return Intent.HAZARD
    if left == on:
        return Intent.LEFT
    if right == on:
        return Intent.RIGHT
    if left == off and right == off:
        return Intent.OFF
    return Intent.UNKNOWN


_MIRROR_INTENT = {Intent.LEFT: Intent.RIGHT, Intent.RIGHT: Intent.LEFT}
_MIRROR_VIEW = {View.LEFT: View.RIGHT, View.RIGHT: View.LEFT}


def mirror_labels(labels: Dict[str, int]) -> Dict[str, int]:
    """Labels of the horizontally mirrored image.

    Mirroring turns the vehicle's left side into its right side, so the blinker
    labels swap, LEFT/RIGHT intents swap and LEFT/RIGHT views swap; brake and the
    other classes stay.

    Args:
        labels: One label per task name (any subset of ``TASKS``).

    Returns:
        A new dict with the mirrored labels.
    """
    out = dict(labels)
    if "left" in labels or "right" in labels:
        out["left"], out["right"] = labels.get("right"), labels.get("left")
        out = {k: v for k, v in out.items() if v is not None}
    if "intent" in labels:
        out["intent"] = int(_MIRROR_INTENT.get(Intent(labels["intent"]), labels["intent"]))
    if "view" in labels:
        out["view"] = int(_MIRROR_VIEW.get(View(labels["view"]), labels["view"]))
    return out
