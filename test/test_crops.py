"""Tests of the shared crop code (signal_light_node.runtime.crops)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from signal_light_node.boxes import TrackBox
from signal_light_node.runtime.crops import (CropConfig, _halve_alone, clip_roi, crop_region,
                                             crop_vehicle, crop_vehicles)
from signal_light_node.errors import ConfigError, CropError


@pytest.fixture()
def image() -> np.ndarray:
    """A 200x300 image whose every pixel is different (so positions can be checked)."""
    rng = np.random.default_rng(0)
    return rng.integers(1, 256, size=(200, 300, 3), dtype=np.uint8)


def test_config_defaults_and_validation():
    assert CropConfig() == CropConfig(64, 0.15)
    assert CropConfig(size=np.int64(32)).size == 32
    for bad in (dict(size=15), dict(size=513), dict(size=32.5), dict(size=True),
                dict(margin=-0.01), dict(margin=1.01), dict(margin=math.nan), dict(margin="a")):
        with pytest.raises(ConfigError):
            CropConfig(**bad)
    with pytest.raises(Exception):
        CropConfig().size = 32  # frozen
    assert CropConfig(fill=np.bool_(True)).fill is True
    with pytest.raises(ConfigError, match="fill"):
        CropConfig(fill="yes")


def test_fill_stretches_the_grown_box_to_the_square(image):
    # 40 wide, 20 high, margin 0.25 -> 60x30 around the centre (100, 80), not squared.
    box = TrackBox("a", 80, 70, 120, 90)
    fill = CropConfig(size=60, margin=0.25, fill=True)
    assert crop_region(box, 300, 200, fill) == (70, 65, 60, 30)
    crop = crop_vehicle(image, box, fill)
    assert crop.shape == (60, 60, 3)
    # Every row of the 30 rows cut is stretched over two crop rows; columns are kept.
    reference = cv2.resize(image[65:95, 70:130], (60, 60), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_array_equal(crop, reference)
    # A square box is cut as without fill.
    square = TrackBox("b", 40, 30, 72, 62)
    np.testing.assert_array_equal(crop_vehicle(image, square, CropConfig(32, 0.0, True)),
                                  crop_vehicle(image, square, CropConfig(32, 0.0)))


def test_fill_halves_each_side_on_its_own():
    smooth = cv2.GaussianBlur(np.random.default_rng(2).integers(0, 256, (720, 1280, 3),
                                                                dtype=np.uint8), (0, 0), 4)
    for w, h in ((520, 130), (130, 520), (300, 40), (700, 260)):
        box = TrackBox("a", 50, 60, 50 + w, 60 + h)
        crop = crop_vehicle(smooth, box, CropConfig(size=64, margin=0.0, fill=True))
        _, _, cw, ch = crop_region(box, 1280, 720, CropConfig(64, 0.0, True))
        # Each side rounded up on its own halving grid, by under 1/64 of it.
        assert w <= cw < w * (1 + 1 / 64) + 1 and h <= ch < h * (1 + 1 / 64) + 1
        reference = cv2.resize(smooth[60:60 + h, 50:50 + w], (64, 64),
                               interpolation=cv2.INTER_AREA).astype(int)
        assert np.abs(crop.astype(int) - reference).mean() < 3.0
    # A region past the border is zero there, at both scales.
    flat = np.full((200, 300, 3), 200, np.uint8)
    crop = crop_vehicle(flat, TrackBox("b", 100, -100, 300, 100), CropConfig(32, 0.0, True))
    assert not crop[:15].any() and (crop[17:] == 200).all()


def _area_halvings(patch, times_x, times_y):
    for _ in range(times_x + times_y):
        h, w = patch.shape[:2]
        size = (w // 2, h) if times_x else (w, h // 2)
        patch = cv2.resize(patch, size, interpolation=cv2.INTER_AREA)
    return patch


@pytest.mark.parametrize("shape", [(96, 256, 3), (40, 130, 3), (64, 64, 1), (97, 255, 3), (2, 2, 3)])
@pytest.mark.parametrize("times", [(1, 0), (0, 1), (2, 0), (0, 3)])
def test_a_side_halved_alone_is_the_area_resize_pixel_for_pixel(shape, times):
    # The crops the data were cut with come from cv2's area resize: the faster form must
    # not move a single grey level (odd sides included, which fall back to cv2).
    patch = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8).squeeze()
    if min(patch.shape[:2]) < 2 ** max(times):
        pytest.skip("too small to halve that often")
    assert np.array_equal(_halve_alone(patch, *times), _area_halvings(patch, *times))


def test_a_side_halved_alone_rounds_every_pair_of_grey_levels_as_the_area_resize():
    levels = np.arange(256, dtype=np.uint8)
    pairs = np.stack(np.meshgrid(levels, levels), -1).reshape(-1, 2, 1).repeat(3, 2)
    assert np.array_equal(_halve_alone(pairs, 1, 0), _area_halvings(pairs, 1, 0))
    rows = np.ascontiguousarray(pairs.transpose(1, 0, 2))
    assert np.array_equal(_halve_alone(rows, 0, 1), _area_halvings(rows, 0, 1))


def test_interior_square_box_is_exact_slice(image):
    box = TrackBox("a", 40, 30, 72, 62)  # 32x32, no margin, size 32: no resampling
    crop = crop_vehicle(image, box, CropConfig(size=32, margin=0.0))
    assert crop.shape == (32, 32, 3) and crop.dtype == np.uint8
    np.testing.assert_array_equal(crop, image[30:62, 40:72])
    crop[:] = 0  # a new array, not a view into the frame
    assert image[30:62, 40:72].any()


def test_margin_and_squareness(image):
    # 40 wide, 20 high, margin 0.25 -> 60x30 -> square of side 60 around the centre (100, 80).
    box = TrackBox("a", 80, 70, 120, 90)
    crop = crop_vehicle(image, box, CropConfig(size=60, margin=0.25))
    np.testing.assert_array_equal(crop, image[50:110, 70:130])
    # A tall box squares on its height.
    tall = TrackBox("b", 95, 60, 105, 100)
    crop = crop_vehicle(image, tall, CropConfig(size=40, margin=0.0))
    np.testing.assert_array_equal(crop, image[60:100, 80:120])


def test_crop_region_is_the_square_that_is_cut(image):
    box = TrackBox("a", 80, 70, 120, 90)
    assert crop_region(box, 300, 200, CropConfig(size=60, margin=0.25)) == (70, 50, 60, 60)
    region = crop_region(TrackBox("b", -10, -20, 30, 20), 300, 200, CropConfig(40, 0.0))
    assert region == (-10, -20, 40, 40)
    # Large squares are rounded up so that they halve exactly down to [size, 2 size).
    _, _, side, _ = crop_region(TrackBox("c", 0, 0, 150, 150), 300, 200, CropConfig(32, 0.0))
    assert side >= 150 and side % 4 == 0 and 32 <= side // 4 < 64
    with pytest.raises(CropError):
        crop_region(TrackBox("d", 400, 0, 420, 20), 300, 200)


def test_border_is_zero_padded(image):
    # Square of side 40 at (-10, -20): the first 20 rows and 10 columns lie outside.
    box = TrackBox("a", -10, -20, 30, 20)
    crop = crop_vehicle(image, box, CropConfig(size=40, margin=0.0))
    assert not crop[:20].any() and not crop[:, :10].any()
    np.testing.assert_array_equal(crop[20:, 10:], image[0:20, 0:30])
    # Bottom-right corner.
    box = TrackBox("b", 280, 190, 320, 230)
    crop = crop_vehicle(image, box, CropConfig(size=40, margin=0.0))
    np.testing.assert_array_equal(crop[:10, :20], image[190:200, 280:300])
    assert not crop[10:].any() and not crop[:, 20:].any()


def test_box_larger_than_image_is_padded_on_all_sides(image):
    box = TrackBox("a", -50, -100, 350, 300)  # 400x400 around the image centre
    crop = crop_vehicle(image, box, CropConfig(size=64, margin=0.0))
    assert crop.shape == (64, 64, 3)
    # The image covers rows 100..300 and columns 50..350 of the 400 square -> 16..48, 8..56.
    assert not crop[:15].any() and not crop[49:].any()
    assert not crop[:, :7].any() and not crop[:, 57:].any()
    assert crop[20:44, 12:52].all()


def test_shrinking_averages_and_enlarging_interpolates():
    smooth = cv2.GaussianBlur(np.random.default_rng(1).integers(0, 256, (720, 1280, 3),
                                                                dtype=np.uint8), (0, 0), 4)
    for side in (40, 64, 90, 129, 200, 300, 517):
        box = TrackBox("a", 100, 50, 100 + side, 50 + side)
        crop = crop_vehicle(smooth, box, CropConfig(size=64, margin=0.0))
        assert crop.shape == (64, 64, 3)
        patch = smooth[50:50 + side, 100:100 + side]
        interp = cv2.INTER_AREA if side > 64 else cv2.INTER_LINEAR
        reference = cv2.resize(patch, (64, 64), interpolation=interp).astype(int)
        # Large sides are rounded up by < 1/64 of the side, so compare loosely there.
        assert np.abs(crop.astype(int) - reference).mean() < (1.0 if side in (40, 64, 129) else 3.0)
    # A uniform region stays exactly uniform whatever the scale.
    flat = np.full((720, 1280, 3), (10, 120, 250), np.uint8)
    for side in (20, 100, 333, 700):
        box = TrackBox.from_center("a", 640, 360, side, side * 0.7)  # square stays inside
        crop = crop_vehicle(flat, box, CropConfig(size=48, margin=0.0))
        assert (crop == (10, 120, 250)).all()


@pytest.mark.parametrize("box, reason", [
    (TrackBox("z", 10, 10, 10, 40), "zero or negative size"),
    (TrackBox("z", 10, 10, 40, 5), "zero or negative size"),
    (TrackBox("z", math.nan, 10, 40, 40), "non-finite"),
    (TrackBox("z", 10, 10, math.inf, 40), "non-finite"),
    (TrackBox("z", 300, 10, 340, 40), "entirely outside"),
    (TrackBox("z", -50, 10, -1, 40), "entirely outside"),
    (TrackBox("z", 10, 200, 40, 240), "entirely outside"),
])
def test_bad_boxes_raise_crop_error(image, box, reason):
    with pytest.raises(CropError, match=reason):
        crop_vehicle(image, box)


def test_bad_image_raises_crop_error(image):
    box = TrackBox("a", 10, 10, 50, 50)
    for bad in (image[..., 0], image.astype(np.float32), np.zeros((0, 10, 3), np.uint8)):
        with pytest.raises(CropError):
            crop_vehicle(bad, box)
    with pytest.raises(CropError):
        crop_vehicles(image[..., :2], [box])


def test_crop_vehicles_batches_and_reports_failures(image):
    config = CropConfig(size=32, margin=0.1)
    boxes = [TrackBox("a", 20, 20, 60, 50), TrackBox("b", math.nan, 0, 1, 1),
             TrackBox("c", 400, 0, 420, 20), TrackBox("d", 250, 150, 310, 210)]
    crops, reasons = crop_vehicles(image, boxes, config)
    assert crops.shape == (4, 32, 32, 3) and crops.dtype == np.uint8
    assert reasons[0] is None and reasons[3] is None
    assert "non-finite" in reasons[1] and "outside" in reasons[2] and "'c'" in reasons[2]
    assert not crops[1].any() and not crops[2].any()
    np.testing.assert_array_equal(crops[0], crop_vehicle(image, boxes[0], config))
    np.testing.assert_array_equal(crops[3], crop_vehicle(image, boxes[3], config))
    empty, no_reasons = crop_vehicles(image, [], config)
    assert empty.shape == (0, 32, 32, 3) and no_reasons == []


def test_clip_roi():
    assert clip_roi(TrackBox("a", 10.2, 20.7, 50.5, 60.0), 100, 80) == (10, 20, 41, 40)
    assert clip_roi(TrackBox("a", -10, -5, 30, 100), 100, 80) == (0, 0, 30, 80)
    assert clip_roi(TrackBox("a", 90, 70, 130, 90), 100, 80) == (90, 70, 10, 10)
    assert clip_roi(TrackBox("a", 120, 10, 130, 20), 100, 80) == (0, 0, 0, 0)
    assert clip_roi(TrackBox("a", math.nan, 10, 130, 20), 100, 80) == (0, 0, 0, 0)
    assert clip_roi(TrackBox("a", 30, 10, 20, 20), 100, 80) == (0, 0, 0, 0)
    assert all(isinstance(v, int) for v in clip_roi(TrackBox("a", 1.5, 2.5, 3.5, 4.5), 10, 10))
