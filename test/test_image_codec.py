"""Image conversions: exact for every raw encoding (with step padding), JPEG/PNG decode, and
every kind of bad input gives ImageConversionError naming topic and stamp."""

from __future__ import annotations

import array
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.io.conversions import make_header
from signal_light_node.errors import BagIOError, ImageConversionError
from signal_light_node.io.image_codec import (SUPPORTED_ENCODINGS, bgr_to_compressed_fields,
                                           bgr_to_image_fields, compressed_msg_to_bgr,
                                           image_msg_to_bgr, msg_to_bgr)

STAMP = 1_234_567_890_000_000_042
H, W = 7, 11  # odd sizes catch row/column mix-ups

# encoding -> (channels, bytes per channel)
LAYOUT = {"bgr8": (3, 1), "rgb8": (3, 1), "bgra8": (4, 1), "rgba8": (4, 1), "mono8": (1, 1),
          "mono16": (1, 2), "8UC3": (3, 1), "8UC4": (4, 1), "8UC1": (1, 1), "16UC1": (1, 2)}


def _rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _colour() -> np.ndarray:
    return _rng().integers(0, 256, (H, W, 3), dtype=np.uint8)


def _grey() -> np.ndarray:
    return np.repeat(_rng().integers(0, 256, (H, W, 1), dtype=np.uint8), 3, axis=2)


def _raw_image(encoding: str, pad: int, bigendian: int = 0):
    """A message with random pixels and ``pad`` junk bytes at the end of every row."""
    channels, depth = LAYOUT[encoding]
    row = W * channels * depth
    data = _rng().integers(0, 256, (H, row + pad), dtype=np.uint8)
    msg = bagio.make("sensor_msgs/msg/Image", header=make_header(STAMP, "cam", bagio.make),
                     height=H, width=W, encoding=encoding, is_bigendian=bigendian,
                     step=row + pad, data=data.reshape(-1))
    return msg, data[:, :row]


def _expected_bgr(encoding: str, pixels: np.ndarray, bigendian: int) -> np.ndarray:
    channels, depth = LAYOUT[encoding]
    if depth == 2:
        grey = pixels.copy().view(">u2" if bigendian else "<u2").reshape(H, W)
        return np.repeat((grey >> 8).astype(np.uint8)[:, :, None], 3, axis=2)
    px = pixels.reshape(H, W, channels)
    if channels == 1:
        return np.repeat(px, 3, axis=2)
    if encoding in ("rgb8", "rgba8"):
        return np.ascontiguousarray(px[:, :, [2, 1, 0]])
    return np.ascontiguousarray(px[:, :, :3])


@pytest.mark.parametrize("pad", [0, 5])
@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_raw_decode_is_exact_with_step_padding(encoding: str, pad: int) -> None:
    for bigendian in ((0, 1) if LAYOUT[encoding][1] == 2 else (0,)):
        msg, pixels = _raw_image(encoding, pad, bigendian)
        out = image_msg_to_bgr(msg, "/cam")
        assert out.shape == (H, W, 3) and out.dtype == np.uint8
        assert out.flags.c_contiguous and out.flags.writeable
        assert np.array_equal(out, _expected_bgr(encoding, pixels, bigendian))


@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_encode_then_decode_gives_the_image_back(encoding: str) -> None:
    image = _grey() if LAYOUT[encoding][0] == 1 else _colour()
    fields = bgr_to_image_fields(image, encoding)
    channels, depth = LAYOUT[encoding]
    assert (fields["height"], fields["width"], fields["encoding"]) == (H, W, encoding)
    assert fields["step"] == W * channels * depth
    assert fields["data"].dtype == np.uint8 and fields["data"].size == H * fields["step"]
    msg = bagio.make("sensor_msgs/msg/Image", header=make_header(STAMP, "c", bagio.make),
                     **fields)
    assert np.array_equal(image_msg_to_bgr(msg), image)


@pytest.mark.parametrize("encoding", ["bgr8", "rgb8", "bgra8", "rgba8", "mono8", "mono16"])
def test_decode_then_encode_gives_the_bytes_back(encoding: str) -> None:
    # The inverse direction for layouts that carry no information lost in BGR.
    msg, pixels = _raw_image(encoding, pad=0)
    if encoding in ("bgra8", "rgba8"):
        pixels = pixels.reshape(H, W, 4).copy()
        pixels[:, :, 3] = 255  # alpha is not kept
        msg.data = pixels.reshape(-1)
    if encoding == "mono16":
        pixels = (pixels.copy().view("<u2") >> 8).astype("<u2") * 257  # 8-bit content
        msg.data = pixels.view(np.uint8).reshape(-1)
    fields = bgr_to_image_fields(image_msg_to_bgr(msg), encoding)
    assert np.array_equal(fields["data"], np.asarray(msg.data).reshape(-1))


def test_rclpy_style_message_with_array_data_decodes() -> None:
    # rclpy carries uint8[] as array.array('B'); plain attribute objects stand in for it.
    image = _colour()
    fields = bgr_to_image_fields(image, "rgb8")
    msg = SimpleNamespace(**{**fields, "data": array.array("B", fields["data"].tobytes())})
    assert np.array_equal(image_msg_to_bgr(msg), image)
    msg.data = fields["data"].tobytes()
    assert np.array_equal(msg_to_bgr(msg), image)


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_round_trip(fmt: str) -> None:
    # Smooth content: JPEG is meant for it (noise would test chroma subsampling instead).
    image = cv2.resize(_colour(), (64, 48), interpolation=cv2.INTER_LINEAR)
    fields = bgr_to_compressed_fields(image, fmt, quality=95)
    assert fmt in fields["format"]
    msg = bagio.make("sensor_msgs/msg/CompressedImage",
                     header=make_header(STAMP, "c", bagio.make), **fields)
    out = compressed_msg_to_bgr(msg, "/cam/compressed")
    assert out.shape == image.shape
    if fmt == "png":
        assert np.array_equal(out, image)
    else:  # lossy, but close to the original and not channel-swapped
        assert np.abs(out.astype(int) - image.astype(int)).mean() < 6
    assert np.array_equal(msg_to_bgr(msg), out)


@pytest.mark.parametrize("fmt", ["jpeg", "png", "bgr8; jpeg compressed bgr8",
                                 "rgb8; jpeg compressed bgr8", "rgb8; png compressed bgr8", ""])
def test_compressed_format_strings(fmt: str) -> None:
    image = np.zeros((16, 16, 3), np.uint8)
    image[:, :, 2] = 200  # pure red in BGR: a channel swap would show as blue
    kind = "png" if "png" in fmt else "jpeg"
    data = bgr_to_compressed_fields(image, kind)["data"]
    out = compressed_msg_to_bgr(SimpleNamespace(format=fmt, data=data.tobytes()))
    assert out[8, 8, 2] > 180 and out[8, 8, 0] < 30


def _where_ok(exc: ImageConversionError, topic: str) -> None:
    text = str(exc)
    assert topic in text and str(STAMP) in text


BAD_RAW = {
    "unknown encoding": (dict(encoding="yuv422_yuy2"), "unsupported encoding"),
    "short data": (dict(data=np.zeros(H * W * 3 - 1, np.uint8)), "fewer than"),
    "step too small": (dict(step=W * 3 - 1, data=np.zeros(H * W * 3, np.uint8)), "step"),
    "empty image": (dict(height=0, data=np.zeros(0, np.uint8)), "empty"),
}


@pytest.mark.parametrize("case", sorted(BAD_RAW))
def test_bad_raw_image_raises_with_topic_and_stamp(case: str) -> None:
    changes, words = BAD_RAW[case]
    fields = {**bgr_to_image_fields(_colour(), "bgr8"), **changes}
    msg = bagio.make("sensor_msgs/msg/Image", header=make_header(STAMP, "c", bagio.make),
                     **fields)
    with pytest.raises(ImageConversionError, match=words) as info:
        image_msg_to_bgr(msg, "/front/image_raw")
    _where_ok(info.value, "/front/image_raw")
    assert isinstance(info.value, BagIOError)


BAD_COMPRESSED = {
    "undecodable jpeg": ("jpeg", b"\xff\xd8\xff\xe0 this is not really a jpeg", "cannot be decoded"),
    "truncated png": ("png", None, "cannot be decoded"),
    "empty data": ("jpeg", b"", "empty"),
    "unsupported format": ("theora", b"\x00\x01", "unsupported compressed format"),
}


@pytest.mark.parametrize("case", sorted(BAD_COMPRESSED))
def test_bad_compressed_image_raises_with_topic_and_stamp(case: str) -> None:
    fmt, data, words = BAD_COMPRESSED[case]
    if data is None:
        data = bgr_to_compressed_fields(_colour(), "png")["data"].tobytes()[:20]
    msg = SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(
        sec=STAMP // 10**9, nanosec=STAMP % 10**9)), format=fmt, data=data)
    with pytest.raises(ImageConversionError, match=words) as info:
        compressed_msg_to_bgr(msg, "/front/image/compressed")
    _where_ok(info.value, "/front/image/compressed")


def test_explicit_stamp_wins_and_missing_header_is_tolerated() -> None:
    msg = SimpleNamespace(format="jpeg", data=b"")
    with pytest.raises(ImageConversionError, match="unknown stamp"):
        compressed_msg_to_bgr(msg, "/t")
    with pytest.raises(ImageConversionError, match="stamp 99 ns"):
        compressed_msg_to_bgr(msg, "/t", stamp_ns=99)


@pytest.mark.parametrize("image, encoding", [
    (np.zeros((4, 4), np.uint8), "bgr8"),
    (np.zeros((4, 4, 3), np.float32), "bgr8"),
    (np.zeros((4, 4, 3), np.uint8), "yuv422"),
])
def test_bad_encoder_input_raises(image: np.ndarray, encoding: str) -> None:
    with pytest.raises(ImageConversionError):
        bgr_to_image_fields(image, encoding)
    if encoding == "bgr8":
        with pytest.raises(ImageConversionError):
            bgr_to_compressed_fields(image, "jpeg")
    with pytest.raises(ImageConversionError):
        bgr_to_compressed_fields(np.zeros((4, 4, 3), np.uint8), "webm")
