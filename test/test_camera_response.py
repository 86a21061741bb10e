"""Random camera response of training crops (data/camera_response.py)."""

import numpy as np

from signal_light_node.data.camera_response import CameraResponse, apply_camera, randomise_camera


def _crops() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 200, (6, 32, 32, 3), dtype=np.uint8)


def test_identity_response_changes_nothing():
    crops = _crops()
    same = CameraResponse(gain=1.0, gamma=1.0, saturation=1.0, noise=0.0, blur=0.0,
                          scale=1.0, jpeg_quality=0)
    out = apply_camera(crops, same, np.random.default_rng(1))
    assert out.shape == crops.shape and out.dtype == np.uint8
    assert np.abs(out.astype(int) - crops.astype(int)).max() <= 1


def test_gain_clips_bright_lamps_and_zero_saturation_greys():
    crops = _crops()
    bright = CameraResponse(gain=3.0, gamma=1.0, saturation=0.0, noise=0.0, blur=0.0,
                            scale=1.0, jpeg_quality=0)
    out = apply_camera(crops, bright, np.random.default_rng(1))
    assert (out == 255).mean() > 0.3
    assert np.abs(out[..., 0].astype(int) - out[..., 2].astype(int)).max() <= 2


def test_one_response_per_sequence_is_deterministic_from_the_rng():
    crops = _crops()
    a = randomise_camera(crops, np.random.default_rng(5))
    b = randomise_camera(crops, np.random.default_rng(5))
    assert np.array_equal(a, b)
    assert a.shape == crops.shape


def test_shape_warp_is_one_warp_for_the_whole_sequence():
    from signal_light_node.data.shape_warp import warp_sequence

    frame = np.random.default_rng(3).integers(0, 255, (32, 32, 3), dtype=np.uint8)
    crops = np.stack([frame, frame, frame])
    out = warp_sequence(crops, np.random.default_rng(4))
    assert out.shape == crops.shape and out.dtype == np.uint8
    assert np.array_equal(out[0], out[2])  # the same warp on every frame
    assert not np.array_equal(out[0], frame)  # and it moved something
    none = warp_sequence(crops, np.random.default_rng(4), strength=0.0)
    assert np.abs(none.astype(int) - crops.astype(int)).max() <= 1


def test_white_balance_scales_each_channel_before_the_tone_curve():
    crops = np.full((2, 8, 8, 3), 100, np.uint8)
    warm = CameraResponse(gain=1.0, gamma=1.0, saturation=1.0, noise=0.0, blur=0.0,
                          scale=1.0, jpeg_quality=0, white_balance=(0.8, 1.0, 1.3))
    out = apply_camera(crops, warm, np.random.default_rng(1))
    assert tuple(int(v) for v in out[0, 0, 0]) == (80, 100, 130)


def test_white_balance_draws_gains_in_range_and_leaves_the_rest_alone_when_off():
    off = CameraResponse.draw(np.random.default_rng(7))
    assert off.white_balance == (1.0, 1.0, 1.0)
    assert off == CameraResponse.draw(np.random.default_rng(7), white_balance=0.0)
    gains = np.array([CameraResponse.draw(np.random.default_rng(s), white_balance=0.3)
                      .white_balance for s in range(200)])
    assert gains.min() >= np.exp(-0.3) - 1e-6 and gains.max() <= np.exp(0.3) + 1e-6
    assert gains.std(axis=0).min() > 0.1  # every channel moves, each on its own
    assert abs(np.corrcoef(gains[:, 0], gains[:, 2])[0, 1]) < 0.3
