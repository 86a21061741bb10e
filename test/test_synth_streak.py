"""The training camera's glare streak (``night_streak``, ``CameraParams.streak``): over-exposed
light smeared along its own row, in dusk and night scenes only, drawn from a stream of its
own so that every other draw of a scene stays as it was."""

from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.camera import STREAK_GAIN, STREAK_LEN, Camera, CameraParams

from scene_helpers import camera_option_params, first_frame_renderer, split_overrides

QUIET = CameraParams(noise=0.0)  # no noise, blur, JPEG or haze: only the tone curve


def _lamp_image() -> np.ndarray:
    """A dark frame with one small clipped lamp at rows 48-51, columns 100-105."""
    img = np.full((120, 200, 3), 20, np.uint8)
    img[48:52, 100:106] = (255, 255, 255)
    return img


def _shot(params: CameraParams) -> np.ndarray:
    camera = Camera(params, 200, 120, horizon=50.0, seed=1)
    return camera.apply(_lamp_image(), 0.0, np.random.default_rng(0)).astype(int)


def test_the_streak_smears_clipped_light_along_its_row_only():
    plain = _shot(QUIET)
    streaked = _shot(replace(QUIET, streak=4.0, streak_len=0.1))
    lift = streaked - plain
    assert (lift >= 0).all()
    # Beside the lamp, on its rows, the streak shows; above and below it nothing changes.
    assert lift[48:52, 92:98].min() > 10 and lift[48:52, 108:114].min() > 10
    assert lift[:48].max() == 0 and lift[52:].max() == 0
    # Its length is streak_len of the width: 21 columns centred on a 6-column lamp.
    assert lift[49, 80:84].max() == 0 and lift[49, 122:126].max() == 0
    # Light that is not over-exposed is not smeared.
    dim = Camera(replace(QUIET, streak=4.0, streak_len=0.1), 200, 120, 50.0, 1)
    img = np.full((120, 200, 3), 120, np.uint8)
    assert np.array_equal(dim.apply(img, 0.0, np.random.default_rng(0)),
                          Camera(QUIET, 200, 120, 50.0, 1).apply(img, 0.0,
                                                                 np.random.default_rng(0)))


def _renderer(lighting: str, share: float) -> SceneRenderer:
    return first_frame_renderer(lighting, night_streak=share)


@pytest.mark.parametrize("lighting", ["dusk", "night"])
def test_a_night_scene_draws_its_streak_and_nothing_else_changes(lighting):
    p0, p1 = camera_option_params(lighting, "night_streak")
    assert p0.streak == 0.0 and p0.streak_len == 0.0
    assert STREAK_GAIN[0] <= p1.streak <= STREAK_GAIN[1]
    assert STREAK_LEN[0] <= p1.streak_len <= STREAK_LEN[1]
    assert asdict(replace(p1, streak=0.0, streak_len=0.0)) == asdict(p0)


def test_day_scenes_never_streak_and_the_share_is_checked(tmp_path, monkeypatch):
    assert _renderer("day", 1.0)._camera.p.streak == 0.0
    with pytest.raises(ConfigError, match="night_streak must be a share"):
        SceneRenderer(seed=1, night_streak=1.5)
    assert split_overrides(monkeypatch, tmp_path / "s", ["--night-streak", "0.5"]) == \
        {"night_streak": 0.5}
