"""The debug image: engine results drawn onto the camera frame, as an output adapter.

:class:`DebugImageOutput` is the node's ``~/output/debug/image`` (parameter
``publish_debug_image``); :func:`draw_results` draws the same picture for
``signal-light replay --video`` and the demo report (``tools.visualize.VideoSink`` writes
the frames), so all show the same: each vehicle's box and track ID, an amber arrow on the side of each
blinker judged ON, a red bar for a brake light judged ON, and optionally the model's
attention masks as a colour overlay.

Blinker sides: "left"/"right" are the vehicle's own sides. Seen from behind (and from
the sides) the vehicle's left lamp is on the image's left; seen from the front it is
on the image's right, so there the arrows swap sides. Each arrow points outwards, in
the direction of the turn as seen in the image for a car seen from behind.
"""

from __future__ import annotations

from typing import Any, ClassVar, Optional, Sequence

import cv2
import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.io.conversions import MessageFactory, stamp_to_ns
from signal_light_node.io.image_codec import bgr_to_image_fields
from signal_light_node.io.topics import DEBUG_IMAGE_TOPIC, IMAGE_TYPE
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.outputs.adapter import OutputAdapter
from signal_light_node.runtime.results import VehicleResult

# BGR colours.
_GREEN = (80, 200, 80)
_GREY = (150, 150, 150)
_RED = (40, 40, 235)
_AMBER = (0, 180, 255)
_WHITE = (255, 255, 255)
_BLACK = (0, 0, 0)

_INTENT_TEXT = {Intent.OFF: "", Intent.LEFT: "L", Intent.RIGHT: "R", Intent.HAZARD: "HAZ",
                Intent.UNKNOWN: "?"}


def overlay_attention(image: np.ndarray, heat: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Blend a ``[H, W]`` mask in [0, 1] onto ``image`` as a colour map (where it is > 0)."""
    if heat.shape[:2] != image.shape[:2]:
        raise ConfigError(f"attention mask {heat.shape[:2]} does not match the image "
                          f"{image.shape[:2]}")
    colour = cv2.applyColorMap(np.clip(heat * 255.0, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)
    weight = (np.clip(heat, 0.0, 1.0) * alpha)[:, :, None]
    # Only where a crop was: elsewhere the weight is 0 and the image is unchanged.
    return (image * (1.0 - weight) + colour * weight).astype(np.uint8)


def _text(image: np.ndarray, text: str, x: int, y: int, colour, scale: float = 0.45) -> None:
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    y = max(y, th + base)
    cv2.rectangle(image, (x, y - th - base), (x + tw + 2, y + 1), _BLACK, thickness=-1)
    cv2.putText(image, text, (x + 1, y - base + 1), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1,
                cv2.LINE_AA)


def _arrow(image: np.ndarray, x: int, y: int, direction: int, length: int) -> None:
    """An amber arrow starting at (x, y) pointing left (-1) or right (+1)."""
    tip = (x + direction * length, y)
    cv2.arrowedLine(image, (x, y), tip, _AMBER, thickness=max(2, length // 6),
                    line_type=cv2.LINE_AA, tipLength=0.45)


def draw_result(image: np.ndarray, result: VehicleResult) -> None:
    """Draw one vehicle's result onto ``image`` in place."""
    x, y, w, h = result.roi
    if w <= 0 or h <= 0:
        return
    brake_on = result.judged and result.brake.state == LightStatus.ON
    colour = _GREY if not result.judged else (_RED if brake_on else _GREEN)
    cv2.rectangle(image, (x, y), (x + w - 1, y + h - 1), colour, thickness=2)
    if brake_on:
        bar = max(3, h // 10)
        cv2.rectangle(image, (x + w // 5, y + h - 1 - bar), (x + w - 1 - w // 5, y + h - 1),
                      _RED, thickness=-1)
    length = int(np.clip(w * 0.35, 10, 60))
    mirrored = result.view == View.FRONT
    for light, side in ((result.left, -1), (result.right, +1)):
        if result.judged and light.state == LightStatus.ON:
            direction = -side if mirrored else side
            start = x - 2 if direction < 0 else x + w + 1
            _arrow(image, start, y + h // 2, direction, length)
    label = str(result.track_id)
    if not result.judged:
        label += " ?"
    elif _INTENT_TEXT.get(result.intent):
        label += f" {_INTENT_TEXT[result.intent]}"
    _text(image, label, x, y - 2, _WHITE if result.judged else _GREY)


def draw_results(image: np.ndarray, results: Sequence[VehicleResult],
                 attention: Optional[np.ndarray] = None, caption: Optional[str] = None
                 ) -> np.ndarray:
    """An annotated copy of a frame.

    Args:
        image: The camera frame, HxWx3 uint8 BGR (not modified).
        results: The engine's results for the frame.
        attention: Optional ``[H, W]`` mask in [0, 1] (``LightStateEngine.attention_masks``).
        caption: Optional text for the top-left corner (e.g. the stamp).

    Returns:
        The annotated frame.
    """
    out = overlay_attention(image, attention) if attention is not None else image.copy()
    for result in results:
        draw_result(out, result)
    if caption:
        _text(out, caption, 4, 16, _WHITE, scale=0.5)
    return out


class DebugImageOutput(OutputAdapter):
    """``sensor_msgs/Image`` on ``~/output/debug/image``: the frame with its results drawn
    (:func:`draw_results`; the attention masks of the boxes when the model has them) and
    the stamp as caption; header = the image's. Built only while subscribed, and only for
    a frame whose image was decoded (:attr:`~OutputAdapter.draws_image`)."""

    name = "debug_image"
    msgtype = IMAGE_TYPE
    topic = DEBUG_IMAGE_TOPIC
    node_topic = "~/output/debug/image"
    depth: ClassVar[int] = 2
    when_subscribed: ClassVar[bool] = True
    draws_image: ClassVar[bool] = True

    def build(self, header: Any, results: Sequence[VehicleResult], make: MessageFactory,
              image: Optional[np.ndarray] = None,
              attention: Optional[np.ndarray] = None) -> Any:
        """The annotated frame as an ``Image`` (bgr8).

        Raises:
            ConfigError: No ``image`` was given.
        """
        if image is None:
            raise ConfigError("the debug image is drawn on the decoded frame; none was given")
        drawn = draw_results(image, results, attention=attention,
                             caption=f"{stamp_to_ns(header.stamp) / 1e9:.3f}")
        return make(IMAGE_TYPE, header=header, **bgr_to_image_fields(drawn))
