"""The output seam: one interface from a frame's results to one message on one topic.

An :class:`OutputAdapter` builds its message through a message factory
``make(msgtype, **fields)`` (:mod:`signal_light_node.io.conversions`), so the same adapter
serves the live node (:func:`signal_light_node.ros.messages.rclpy_make`) and the bag tools
(:func:`signal_light_node.io.bagio.make`). The node creates one publisher per adapter
(on :attr:`OutputAdapter.node_topic`, remappable); ``signal-light replay`` writes one
topic per adapter (:attr:`OutputAdapter.topic`, the node's topic under its default name).
No rclpy here.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar, Optional, Sequence

import numpy as np

from signal_light_node.io.conversions import MessageFactory
from signal_light_node.io.topics import OUTPUT_TOPIC, VEHICLE_LIGHTS_TYPE
from signal_light_node.outputs.vehicle_lights import vehicle_light_array
from signal_light_node.runtime.results import VehicleResult


class OutputAdapter(abc.ABC):
    """Builds one output message per answered frame.

    Class attributes:
        name: Short name, for logs.
        msgtype: Full message type name (``pkg/msg/Name``).
        topic: Topic in bags and as seen from outside the node under its default name.
        node_topic: The node's private topic name (``~/output/...``).
        depth: Depth of the node's keep-last publisher.
        when_subscribed: The node builds and publishes the message only while someone
            subscribes (for outputs that cost time and that nothing else consumes).
        draws_image: The message is drawn on the decoded camera frame: it is built only
            for a frame whose image was decoded (the engine ran), and ``build`` gets the
            ``image`` and the boxes' ``attention`` masks.
    """

    name: ClassVar[str]
    msgtype: ClassVar[str]
    topic: ClassVar[str]
    node_topic: ClassVar[str]
    depth: ClassVar[int] = 10
    when_subscribed: ClassVar[bool] = False
    draws_image: ClassVar[bool] = False

    @abc.abstractmethod
    def build(self, header: Any, results: Sequence[VehicleResult], make: MessageFactory,
              image: Optional[np.ndarray] = None,
              attention: Optional[np.ndarray] = None) -> Any:
        """The message for one frame.

        Args:
            header: The image's header (``stamp`` and ``frame_id``; rclpy or rosbags).
            results: The engine's results, one per input box, in input order.
            make: The message factory of the receiving side.
            image: The decoded frame, HxWx3 uint8 BGR (given to :attr:`draws_image`
                adapters; others ignore it).
            attention: ``[H, W]`` attention masks of the frame's boxes in [0, 1], or None
                (``LightStateEngine.attention_masks``; for :attr:`draws_image` adapters).

        Returns:
            A message of :attr:`msgtype`.
        """


class VehicleLightsOutput(OutputAdapter):
    """``signal_light_msgs/VehicleLightStateArray`` on ``~/output/vehicle_lights``: the
    node's result, header = the image's header, one entry per detection."""

    name = "vehicle_lights"
    msgtype = VEHICLE_LIGHTS_TYPE
    topic = OUTPUT_TOPIC
    node_topic = "~/output/vehicle_lights"

    def build(self, header: Any, results: Sequence[VehicleResult], make: MessageFactory,
              image: Optional[np.ndarray] = None,
              attention: Optional[np.ndarray] = None) -> Any:
        """See :func:`signal_light_node.outputs.vehicle_lights.vehicle_light_array`."""
        return vehicle_light_array(header, results, make)
