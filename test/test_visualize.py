"""Tests of the result drawing shared by replay videos and the node's debug image."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.runtime.results import LightEstimate, VehicleResult
from signal_light_node.outputs.debug_image import draw_results, overlay_attention
from signal_light_node.tools.visualize import VideoSink

AMBER = np.array([0, 180, 255])
RED = np.array([40, 40, 235])


def _result(left=LightStatus.OFF, right=LightStatus.OFF, brake=LightStatus.OFF,
            view=View.BEHIND, roi=(100, 60, 80, 60)) -> VehicleResult:
    c = LightEstimate.certain
    return VehicleResult("4", roi, c(brake), c(left), c(right), Intent.OFF, 1.0, view, 1.0)


def _count(image: np.ndarray, colour: np.ndarray, x0: int, x1: int) -> int:
    region = image[:, x0:x1].astype(int)
    return int((np.abs(region - colour).sum(axis=2) < 30).sum())


@pytest.mark.parametrize("view, lamp, image_side", [
    (View.BEHIND, "left", "left"), (View.BEHIND, "right", "right"),
    (View.FRONT, "left", "right"), (View.FRONT, "right", "left")])
def test_blinker_arrow_on_the_side_where_the_lamp_is_seen(view, lamp, image_side):
    image = np.zeros((200, 300, 3), np.uint8)
    out = draw_results(image, [_result(view=view, **{lamp: LightStatus.ON})])
    left, right = _count(out, AMBER, 0, 100), _count(out, AMBER, 180, 300)
    assert (left > 20 and right == 0) if image_side == "left" else (right > 20 and left == 0)
    assert not image.any()  # the input is not drawn on


def test_brake_bar_and_no_marks_when_off():
    image = np.zeros((200, 300, 3), np.uint8)
    on = draw_results(image, [_result(brake=LightStatus.ON)])
    off = draw_results(image, [_result()])
    assert _count(on[110:120], RED, 120, 160) > 50
    assert _count(off, RED, 0, 300) == 0 and _count(off, AMBER, 0, 300) == 0


def test_attention_overlay_changes_only_masked_pixels():
    image = np.full((50, 60, 3), 100, np.uint8)
    heat = np.zeros((50, 60), np.float32)
    heat[10:20, 10:20] = 1.0
    out = overlay_attention(image, heat)
    assert not np.array_equal(out[10:20, 10:20], image[10:20, 10:20])
    out[10:20, 10:20] = 100
    assert np.array_equal(out, image)
    with pytest.raises(ConfigError):
        overlay_attention(image, heat[:10])


def test_video_sink_rejects_unknown_suffix(tmp_path):
    with pytest.raises(ConfigError, match="mp4 or .gif"):
        VideoSink(tmp_path / "v.avi", fps=10)
    assert VideoSink(tmp_path / "v.gif", fps=10).close() is None
