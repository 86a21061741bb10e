"""Procedural vehicle-light scenes (numpy + OpenCV), deterministic from a seed."""

from signal_light_node.synth.scene import SceneRenderer
from signal_light_node.synth.truth import RenderedFrame, VehicleTruth

__all__ = ["SceneRenderer", "RenderedFrame", "VehicleTruth"]
