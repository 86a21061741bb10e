"""What the engine says about one vehicle in one frame; plain Python, no ROS types."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Tuple

from signal_light_node.labels import LIGHT_CODES, Intent, LightStatus, View


@dataclass(frozen=True)
class LightEstimate:
    """State of one light with its class probabilities.

    Attributes:
        state: The most likely state.
        off: Probability of OFF.
        on: Probability of ON.
        unknown: Probability of UNKNOWN; the three sum to 1.
    """

    state: LightStatus
    off: float
    on: float
    unknown: float

    @classmethod
    def unjudged(cls) -> "LightEstimate":
        """The estimate for a light that could not be judged at all."""
        return cls(LightStatus.UNKNOWN, 0.0, 0.0, 1.0)

    @classmethod
    def certain(cls, state: LightStatus) -> "LightEstimate":
        """A one-hot estimate, as ground truth is written."""
        probs = [0.0, 0.0, 0.0]
        probs[int(state)] = 1.0
        return cls(LightStatus(state), *probs)


@dataclass(frozen=True)
class VehicleResult:
    """Light state of one tracked vehicle in one frame.

    Attributes:
        track_id: The input ``Detection2D.id``.
        roi: ``(x_offset, y_offset, width, height)`` of the box clipped to the image, in pixels.
        brake: Brake light estimate.
        left: The vehicle's own left blinker.
        right: The vehicle's own right blinker.
        intent: Most likely driver intent.
        intent_probability: Its probability.
        view: Most likely viewed face.
        view_probability: Its probability.
        classification: ``(code, probability)`` for every light judged ON (codes 100/101/102).
        frames_observed: Frames seen of this track so far, this one included.
        judged: False when the box could not be cropped and nothing was judged.
    """

    track_id: str
    roi: Tuple[int, int, int, int]
    brake: LightEstimate
    left: LightEstimate
    right: LightEstimate
    intent: Intent
    intent_probability: float
    view: View
    view_probability: float
    classification: Tuple[Tuple[int, float], ...] = field(default_factory=tuple)
    frames_observed: int = 0
    judged: bool = True

    @classmethod
    def certain(cls, track_id: str, roi: Tuple[int, int, int, int], brake: int, left: int,
                right: int, intent: int, view: int, frames_observed: int) -> "VehicleResult":
        """A ground-truth entry: every state with probability 1, ``classification`` = the
        lights ON (each with probability 1), judged.

        Args:
            track_id: The track ID.
            roi: The box clipped to the image (``runtime.crops.clip_roi``).
            brake: The brake's ``LightStatus`` value.
            left: The vehicle's own left blinker's.
            right: Its right blinker's.
            intent: The ``Intent`` value.
            view: The ``View`` value.
            frames_observed: Frames this track has been in the detections so far, this one
                included.
        """
        lights = {"brake": LightStatus(brake), "left": LightStatus(left),
                  "right": LightStatus(right)}
        return cls(track_id=str(track_id), roi=roi,
                   brake=LightEstimate.certain(lights["brake"]),
                   left=LightEstimate.certain(lights["left"]),
                   right=LightEstimate.certain(lights["right"]), intent=Intent(intent),
                   intent_probability=1.0, view=View(view), view_probability=1.0,
                   classification=tuple((LIGHT_CODES[name], 1.0) for name, state
                                        in lights.items() if state == LightStatus.ON),
                   frames_observed=int(frames_observed), judged=True)
