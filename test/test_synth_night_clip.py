"""The training camera's bright night exposure (``night_clip``, ``CameraParams.white_clip``): a
night camera that exposes for a lit street saturates its lamps and clips them white, drawn
from a stream of its own so that every other draw of a scene stays as it was."""

from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.camera import NIGHT_GAIN, WHITE_CLIP, Camera, CameraParams

from scene_helpers import camera_option_params, first_frame_renderer, split_overrides

QUIET = CameraParams(noise=0.0)  # no noise, blur, JPEG or haze: only the tone curve


def _shot(params: CameraParams, img: np.ndarray) -> np.ndarray:
    camera = Camera(params, img.shape[1], img.shape[0], horizon=50.0, seed=1)
    return camera.apply(img, 0.0, np.random.default_rng(0)).astype(int)


def test_clipped_light_turns_white_and_the_rest_keeps_its_colour():
    img = np.full((60, 80, 3), 40, np.uint8)
    img[20:24, 30:36] = (60, 60, 255)     # a saturated red lamp (BGR)
    img[40:44, 30:36] = (30, 30, 180)     # a dim red lamp, not clipped
    plain, clipped = _shot(QUIET, img), _shot(replace(QUIET, white_clip=0.8), img)
    # The saturated lamp's blue and green move 0.8 of the way to white; red stays at 255.
    assert (clipped[20:24, 30:36, 2] == 255).all()
    assert (clipped[20:24, 30:36, :2] == round(60 + 0.8 * (255 - 60))).all()
    # Nothing that is not over the floor changes: the dim lamp and the background.
    changed = np.argwhere((clipped != plain).any(axis=2))
    assert changed[:, 0].min() >= 20 and changed[:, 0].max() <= 23
    assert np.array_equal(clipped[40:44], plain[40:44])


def _renderer(lighting: str, share: float) -> SceneRenderer:
    return first_frame_renderer(lighting, night_clip=share)


def test_a_night_scene_exposes_brighter_and_clips_white_and_nothing_else_changes():
    p0, p1 = camera_option_params("night", "night_clip")
    assert p0.white_clip == 0.0 and WHITE_CLIP[0] <= p1.white_clip <= WHITE_CLIP[1]
    assert NIGHT_GAIN[0] <= p1.exposure / p0.exposure <= NIGHT_GAIN[1]
    assert asdict(replace(p1, white_clip=0.0, exposure=p0.exposure)) == asdict(p0)


@pytest.mark.parametrize("lighting", ["day", "dusk"])
def test_only_night_scenes_clip_and_the_share_is_checked(tmp_path, monkeypatch, lighting):
    p = _renderer(lighting, 1.0)._camera.p
    assert p.white_clip == 0.0 and asdict(p) == asdict(_renderer(lighting, 0.0)._camera.p)
    with pytest.raises(ConfigError, match="night_clip must be a share"):
        SceneRenderer(seed=1, night_clip=-0.1)
    assert split_overrides(monkeypatch, tmp_path / "s", ["--night-clip", "0.5"]) == \
        {"night_clip": 0.5}
