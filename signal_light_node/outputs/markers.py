"""The results drawn for RViz: a ``visualization_msgs/MarkerArray`` per frame.

What a frame's array holds, in order:

* one ``DELETEALL`` marker, so RViz shows only this frame's vehicles;
* per vehicle with a non-empty ROI (``i`` = its index in the frame):

  - ``box``/``i``: the ROI's outline (``LINE_STRIP``): green, red while the brake is ON,
    translucent grey for a vehicle that is UNKNOWN (not judged, or every light UNKNOWN);
  - ``track_id``/``i``: the track ID above the box (``TEXT_VIEW_FACING``), followed by
    the intent (``L``, ``R``, ``HAZ``) or `` ?`` for an UNKNOWN vehicle;
  - ``blinker``/``2i`` and ``2i+1``: an amber ``ARROW`` beside the box for each blinker
    that is ON, pointing outwards on the side where the lamp appears in the image (the
    vehicle's left is the image's left except when seen from the front), as in the
    debug image (:mod:`signal_light_node.outputs.debug_image`);
  - ``brake``/``i``: a red bar (``CUBE``) along the bottom of the box while the brake is ON.

Coordinates: the drawing lies in the image's ``frame_id`` with the image's stamp, at
``z = 0``, pixel ``(u, v)`` at ``x = u * metres_per_pixel``, ``y = v * metres_per_pixel``
(default :data:`METRES_PER_PIXEL` = 0.01 m: a 1280x720 image spans 12.8 m x 7.2 m). In a
camera optical frame (x right, y down) that is the image as seen from behind the camera.
Every marker has a ``lifetime`` (default 1 s), so the drawing vanishes when the node stops.
No rclpy here: messages are built with a message factory.
"""

from __future__ import annotations

import math
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.io.conversions import MessageFactory, ns_to_stamp_fields, stamp_to_ns
from signal_light_node.io.topics import MARKER_ARRAY_TYPE, MARKERS_TOPIC
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.outputs.adapter import OutputAdapter
from signal_light_node.runtime.results import VehicleResult

#: Metres per image pixel of the drawing.
METRES_PER_PIXEL = 0.01
#: Seconds a marker stays without being replaced.
LIFETIME_S = 1.0

MARKER_TYPE = "visualization_msgs/msg/Marker"
# visualization_msgs/Marker constants.
ARROW, CUBE, LINE_STRIP, TEXT_VIEW_FACING = 0, 1, 4, 9
ADD, DELETEALL = 0, 3

#: Marker namespaces, one per kind of mark.
NAMESPACES = ("box", "track_id", "blinker", "brake")

Colour = Tuple[float, float, float, float]
#: RGBA colours.
GREEN: Colour = (0.31, 0.78, 0.31, 1.0)
RED: Colour = (0.92, 0.16, 0.16, 1.0)
UNKNOWN_GREY: Colour = (0.6, 0.6, 0.6, 0.6)
AMBER: Colour = (1.0, 0.7, 0.0, 1.0)
WHITE: Colour = (1.0, 1.0, 1.0, 1.0)

# Sizes in pixels (scaled like the coordinates).
_LINE_PX = 2.0
_TEXT_PX = 14.0

_INTENT_TEXT = {Intent.LEFT: "L", Intent.RIGHT: "R", Intent.HAZARD: "HAZ"}


def is_unknown(result: VehicleResult) -> bool:
    """Whether a vehicle is drawn as UNKNOWN: not judged, or every light UNKNOWN."""
    return not result.judged or all(light.state == LightStatus.UNKNOWN
                                    for light in (result.brake, result.left, result.right))


def marker_label(result: VehicleResult) -> str:
    """The text drawn above a vehicle: its track ID, then its intent or ``?``."""
    if is_unknown(result):
        return f"{result.track_id} ?"
    extra = _INTENT_TEXT.get(result.intent)
    return f"{result.track_id} {extra}" if extra else str(result.track_id)


class _Frame:
    """The parts every marker of one frame shares, built once per frame."""

    def __init__(self, header: Any, make: MessageFactory, scale: float,
                 lifetime_s: float) -> None:
        self.make, self.scale = make, scale
        sec, nanosec = ns_to_stamp_fields(stamp_to_ns(header.stamp))
        self.header = make("std_msgs/msg/Header",
                           stamp=make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec),
                           frame_id=str(header.frame_id))
        life_sec, life_ns = ns_to_stamp_fields(int(round(lifetime_s * 1e9)))
        self.lifetime = make("builtin_interfaces/msg/Duration", sec=life_sec, nanosec=life_ns)
        self.identity = self.pose(0.0, 0.0)
        self.texture = make("sensor_msgs/msg/CompressedImage", header=self.header, format="",
                            data=np.zeros(0, np.uint8))
        self.mesh = make("visualization_msgs/msg/MeshFile", filename="",
                         data=np.zeros(0, np.uint8))
        self._colours: dict = {}

    def point(self, u: float, v: float) -> Any:
        return self.make("geometry_msgs/msg/Point", x=float(u) * self.scale,
                         y=float(v) * self.scale, z=0.0)

    def pose(self, u: float, v: float) -> Any:
        return self.make("geometry_msgs/msg/Pose", position=self.point(u, v),
                         orientation=self.make("geometry_msgs/msg/Quaternion",
                                               x=0.0, y=0.0, z=0.0, w=1.0))

    def vector(self, x_px: float, y_px: float, z_px: float) -> Any:
        return self.make("geometry_msgs/msg/Vector3", x=float(x_px) * self.scale,
                         y=float(y_px) * self.scale, z=float(z_px) * self.scale)

    def colour(self, rgba: Colour) -> Any:
        if rgba not in self._colours:
            r, g, b, a = rgba
            self._colours[rgba] = self.make("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a)
        return self._colours[rgba]

    def marker(self, ns: str, marker_id: int, marker_type: int, colour: Colour,
               scale: Any, pose: Optional[Any] = None, points: Sequence[Any] = (),
               text: str = "", action: int = ADD) -> Any:
        return self.make(
            MARKER_TYPE, header=self.header, ns=ns, id=int(marker_id), type=marker_type,
            action=action, pose=pose if pose is not None else self.identity, scale=scale,
            color=self.colour(colour), lifetime=self.lifetime, frame_locked=False,
            points=list(points), colors=[], texture_resource="", texture=self.texture,
            uv_coordinates=[], text=text, mesh_resource="", mesh_file=self.mesh,
            mesh_use_embedded_materials=False)


class MarkerOutput(OutputAdapter):
    """``visualization_msgs/MarkerArray`` on ``~/output/markers`` (see the module docstring).

    Args:
        metres_per_pixel: Scale of the drawing.
        lifetime_s: Lifetime of every marker.

    Raises:
        ConfigError: A non-positive scale or a negative lifetime.
    """

    name = "markers"
    msgtype = MARKER_ARRAY_TYPE
    topic = MARKERS_TOPIC
    node_topic = "~/output/markers"
    when_subscribed = True

    def __init__(self, metres_per_pixel: float = METRES_PER_PIXEL,
                 lifetime_s: float = LIFETIME_S) -> None:
        if not metres_per_pixel > 0 or not lifetime_s >= 0:
            raise ConfigError(f"markers need metres_per_pixel > 0 and lifetime_s >= 0, got "
                              f"{metres_per_pixel} and {lifetime_s}")
        self.metres_per_pixel = float(metres_per_pixel)
        self.lifetime_s = float(lifetime_s)

    def build(self, header: Any, results: Sequence[VehicleResult], make: MessageFactory,
              image: Optional[np.ndarray] = None,
              attention: Optional[np.ndarray] = None) -> Any:
        """The frame's markers: a DELETEALL, then each vehicle's marks."""
        frame = _Frame(header, make, self.metres_per_pixel, self.lifetime_s)
        markers = [frame.marker("", 0, CUBE, WHITE, frame.vector(1, 1, 1), action=DELETEALL)]
        for index, result in enumerate(results):
            markers += _vehicle(frame, index, result)
        return make(MARKER_ARRAY_TYPE, markers=markers)


def _vehicle(frame: _Frame, index: int, result: VehicleResult) -> List[Any]:
    x, y, w, h = (float(v) for v in result.roi)
    if not (w > 0 and h > 0 and math.isfinite(x + y + w + h)):
        return []  # wholly outside the image: nothing to draw
    unknown = is_unknown(result)
    brake_on = not unknown and result.brake.state == LightStatus.ON
    colour = UNKNOWN_GREY if unknown else (RED if brake_on else GREEN)
    corners = [(x, y), (x + w, y), (x + w, y + h), (x, y + h), (x, y)]
    out = [
        frame.marker("box", index, LINE_STRIP, colour, frame.vector(_LINE_PX, 0, 0),
                     points=[frame.point(u, v) for u, v in corners]),
        frame.marker("track_id", index, TEXT_VIEW_FACING, UNKNOWN_GREY if unknown else WHITE,
                     frame.vector(0, 0, _TEXT_PX),
                     pose=frame.pose(x + w / 2.0, y - 0.75 * _TEXT_PX),
                     text=marker_label(result)),
    ]
    if unknown:
        return out
    length = float(np.clip(w * 0.35, 10.0, 60.0))
    shaft = max(2.0, length / 6.0)
    mirrored = result.view == View.FRONT
    for slot, (light, side) in enumerate(((result.left, -1), (result.right, +1))):
        if light.state != LightStatus.ON:
            continue
        direction = -side if mirrored else side
        start = x - 2.0 if direction < 0 else x + w + 2.0
        out.append(frame.marker(
            "blinker", 2 * index + slot, ARROW, AMBER,
            frame.vector(shaft, 2.0 * shaft, 0.45 * length),
            points=[frame.point(start, y + h / 2.0),
                    frame.point(start + direction * length, y + h / 2.0)]))
    if brake_on:
        bar = max(3.0, h / 10.0)
        out.append(frame.marker("brake", index, CUBE, RED, frame.vector(0.6 * w, bar, _LINE_PX),
                                pose=frame.pose(x + w / 2.0, y + h - bar / 2.0)))
    return out
