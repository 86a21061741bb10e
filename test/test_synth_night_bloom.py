"""The training camera's bloom (``night_bloom``, ``CameraParams.bloom``): over-exposed light
spreads into a round halo whose size follows how much of a lamp is clipped, drawn from a
stream of its own so that every other draw of a scene stays as it was."""

from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.camera import BLOOM_GAIN, BLOOM_SIGMA, Camera, CameraParams

from scene_helpers import camera_option_params, first_frame_renderer, split_overrides

QUIET = CameraParams(noise=0.0)  # no noise, blur, JPEG or haze: only the tone curve
BLOOM = replace(QUIET, bloom=20.0, bloom_sigma=1 / 40)


def _shot(params: CameraParams, img: np.ndarray) -> np.ndarray:
    camera = Camera(params, img.shape[1], img.shape[0], horizon=50.0, seed=1)
    return camera.apply(img, 0.0, np.random.default_rng(0)).astype(int)


def _halo(params: CameraParams, lamp: "tuple[int, int, int]", size: int) -> int:
    """Pixels outside a square lamp of ``size`` that the camera lights over the background."""
    img = np.full((120, 160, 3), 30, np.uint8)
    y0, x0 = 60 - size // 2, 80 - size // 2
    img[y0:y0 + size, x0:x0 + size] = lamp
    out = _shot(params, img)
    outside = np.ones(out.shape[:2], bool)
    outside[y0:y0 + size, x0:x0 + size] = False
    return int(((out[..., 2] > 40) & outside).sum())


def test_clipped_light_blooms_and_a_larger_clipped_lamp_blooms_wider():
    red = (40, 40, 255)  # BGR: a saturated red lamp
    assert _halo(QUIET, red, 6) == 0
    small, large = _halo(BLOOM, red, 6), _halo(BLOOM, red, 12)
    assert small > 0
    assert large > 1.5 * small


def test_light_under_the_floor_does_not_bloom():
    img = np.full((60, 80, 3), 40, np.uint8)
    img[20:26, 30:36] = (30, 30, 190)  # a lit red lamp, not over-exposed
    assert np.array_equal(_shot(QUIET, img), _shot(BLOOM, img))


def _renderer(lighting: str, share: float) -> SceneRenderer:
    return first_frame_renderer(lighting, night_bloom=share)


@pytest.mark.parametrize("lighting", ["dusk", "night"])
def test_a_dusk_or_night_camera_blooms_and_nothing_else_changes(lighting):
    p0, p1 = camera_option_params(lighting, "night_bloom")
    assert p0.bloom == 0.0 and BLOOM_GAIN[0] <= p1.bloom <= BLOOM_GAIN[1]
    assert BLOOM_SIGMA[0] <= p1.bloom_sigma <= BLOOM_SIGMA[1]
    assert asdict(replace(p1, bloom=0.0, bloom_sigma=0.0)) == asdict(p0)


def test_a_day_camera_does_not_bloom_and_the_share_is_checked(tmp_path, monkeypatch):
    p = _renderer("day", 1.0)._camera.p
    assert p.bloom == 0.0 and asdict(p) == asdict(_renderer("day", 0.0)._camera.p)
    with pytest.raises(ConfigError, match="night_bloom must be a share"):
        SceneRenderer(seed=1, night_bloom=1.5)
    assert split_overrides(monkeypatch, tmp_path / "s", ["--night-bloom", "0.5"]) == \
        {"night_bloom": 0.5}
