"""Output adapters: what the node publishes and ``signal-light replay`` writes per frame.

:class:`OutputAdapter` is the interface (``build(header, results, make, image=None,
attention=None) -> message``); :class:`VehicleLightsOutput` is the node's result and
always on (the message itself: :mod:`.vehicle_lights`); :class:`MarkerOutput` draws the
results for RViz (node parameter ``publish_markers``, ``replay --markers``);
:class:`DebugImageOutput` draws them on the frame (``publish_debug_image``).
:func:`output_adapters` is the one place that chooses them, for the node and replay alike.
"""

from __future__ import annotations

from typing import List

from signal_light_node.outputs.adapter import OutputAdapter, VehicleLightsOutput
from signal_light_node.outputs.debug_image import DebugImageOutput
from signal_light_node.outputs.markers import METRES_PER_PIXEL, MarkerOutput

__all__ = ["OutputAdapter", "VehicleLightsOutput", "MarkerOutput", "DebugImageOutput",
           "METRES_PER_PIXEL", "output_adapters"]


def output_adapters(markers: bool = False, debug_image: bool = False) -> List[OutputAdapter]:
    """The adapters of a run: the result array first, then the optional ones.

    Args:
        markers: Also draw the results as a ``MarkerArray``.
        debug_image: Also draw them on the frame (an ``Image``; built only for a decoded
            frame, :attr:`OutputAdapter.draws_image`).

    Returns:
        The adapters; the first is always :class:`VehicleLightsOutput`.
    """
    adapters: List[OutputAdapter] = [VehicleLightsOutput()]
    if markers:
        adapters.append(MarkerOutput())
    if debug_image:
        adapters.append(DebugImageOutput())
    return adapters
