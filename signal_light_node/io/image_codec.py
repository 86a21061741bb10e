"""Conversions between image messages and BGR ``uint8`` numpy arrays.

Duck-typed: only attribute access is used, so ``rosbags`` and rclpy messages of
``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` work alike. Every failure is an
:class:`~signal_light_node.errors.ImageConversionError` naming the topic and the stamp.
"""

from __future__ import annotations

import struct
from typing import Any, Dict, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.io.conversions import stamp_to_ns
from signal_light_node.errors import ImageConversionError, ImageTooLargeError

#: Default largest image (width x height) decoded: 4096 x 4096. Larger ones are refused
#: before decoding, so a small PNG of a huge blank image cannot take gigabytes.
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096

# encoding -> (channels, bytes per channel, conversion of the raw pixels to BGR or None)
_ENCODINGS: Dict[str, Tuple[int, int, Optional[int]]] = {
    "bgr8": (3, 1, None),
    "rgb8": (3, 1, cv2.COLOR_RGB2BGR),
    "bgra8": (4, 1, cv2.COLOR_BGRA2BGR),
    "rgba8": (4, 1, cv2.COLOR_RGBA2BGR),
    "mono8": (1, 1, cv2.COLOR_GRAY2BGR),
    "mono16": (1, 2, cv2.COLOR_GRAY2BGR),
}
# OpenCV type names used by some drivers for the same layouts.
_ALIASES = {"8UC3": "bgr8", "8UC4": "bgra8", "8UC1": "mono8", "16UC1": "mono16"}

#: Raw encodings that :func:`image_msg_to_bgr` and :func:`bgr_to_image_fields` support.
SUPPORTED_ENCODINGS: Tuple[str, ...] = tuple(_ENCODINGS) + tuple(_ALIASES)

#: Compressed formats understood (matched as words in ``CompressedImage.format``).
SUPPORTED_FORMATS: Tuple[str, ...] = ("jpeg", "jpg", "png")


def _where(msg: Any, topic: str, stamp_ns: Optional[int]) -> str:
    if stamp_ns is None:
        try:
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except (AttributeError, TypeError, ValueError):
            stamp_ns = None
    stamp = "unknown stamp" if stamp_ns is None else f"stamp {stamp_ns} ns"
    return f"image on {topic or '<no topic>'} at {stamp}"


def _buffer(data: Any) -> np.ndarray:
    """The message's byte payload as a flat uint8 array, without copying where possible."""
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8) if data.dtype.itemsize == 1 else \
            np.frombuffer(data.tobytes(), np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)  # bytes, bytearray, array.array('B')
    except (TypeError, ValueError):
        return np.asarray(list(data), dtype=np.uint8)


def _check_size(width: int, height: int, max_pixels: Optional[int], where: Any) -> None:
    if max_pixels is not None and width * height > max_pixels:
        raise ImageTooLargeError(f"{where()}: {width}x{height} = {width * height} pixels "
                                 f"exceeds the limit of {max_pixels} (max_image_pixels)")


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless...; not DHT/JPG/DAC).
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def compressed_dimensions(data: Any) -> Optional[Tuple[int, int]]:
    """``(width, height)`` from a PNG or JPEG header without decoding; None if not found."""
    head = bytes(_buffer(data)[:65536])
    if head.startswith(_PNG_MAGIC) and len(head) >= 24 and head[12:16] == b"IHDR":
        width, height = struct.unpack(">II", head[16:24])
        return int(width), int(height)
    if not head.startswith(b"\xff\xd8"):
        return None
    pos = 2
    while pos + 9 <= len(head):
        if head[pos] != 0xFF:
            return None
        marker = head[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
            continue
        if marker in _SOF_MARKERS:
            height, width = struct.unpack(">HH", head[pos + 5:pos + 9])
            return int(width), int(height)
        pos += 2 + struct.unpack(">H", head[pos + 2:pos + 4])[0]
    return None


def _canonical(encoding: str) -> Optional[str]:
    enc = str(encoding).strip()
    enc = _ALIASES.get(enc, enc.lower())
    return enc if enc in _ENCODINGS else None


def image_msg_to_bgr(msg: Any, topic: str = "", stamp_ns: Optional[int] = None,
                     max_pixels: Optional[int] = None) -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` into a BGR image.

    ``mono16`` is scaled to 8 bits by its high byte; ``step`` padding is honoured.

    Args:
        msg: The message.
        topic: Topic name, for error messages.
        stamp_ns: Stamp for error messages (default: the message header's).
        max_pixels: Refuse images of more pixels than this (None: no limit).

    Returns:
        A writable C-contiguous ``(height, width, 3)`` uint8 array.

    Raises:
        ImageConversionError: Unknown encoding, empty image, bad step or short data.
        ImageTooLargeError: More pixels than ``max_pixels``.
    """
    where = lambda: _where(msg, topic, stamp_ns)  # noqa: E731 (built only on error)
    enc = _canonical(msg.encoding)
    if enc is None:
        raise ImageConversionError(f"{where()}: unsupported encoding {msg.encoding!r} "
                                   f"(supported: {', '.join(SUPPORTED_ENCODINGS)})")
    channels, depth, code = _ENCODINGS[enc]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise ImageConversionError(f"{where()}: empty image ({width}x{height})")
    _check_size(width, height, max_pixels, where)
    row = width * channels * depth
    if step < row:
        raise ImageConversionError(f"{where()}: step {step} is smaller than width {width} x "
                                   f"{channels * depth} bytes per pixel = {row}")
    buf = _buffer(msg.data)
    if buf.size < step * height:
        raise ImageConversionError(f"{where()}: data has {buf.size} bytes, fewer than "
                                   f"step x height = {step} x {height} = {step * height}")
    rows = buf[:step * height].reshape(height, step)[:, :row]
    if depth == 2:
        dtype = ">u2" if int(msg.is_bigendian) else "<u2"
        pixels = (np.ascontiguousarray(rows).view(dtype).reshape(height, width) >> 8)
        pixels = pixels.astype(np.uint8)
    else:
        pixels = rows.reshape(height, width, channels) if channels > 1 else rows
    if code is None:
        return np.array(pixels, dtype=np.uint8, order="C", copy=True)
    return cv2.cvtColor(np.ascontiguousarray(pixels), code)


def _format_kind(fmt: str) -> Optional[str]:
    words = str(fmt).lower().replace(";", " ").split()
    if not words:
        return ""  # unnamed: let the decoder find out
    for word in words:
        if word in ("jpeg", "jpg"):
            return "jpeg"
        if word == "png":
            return "png"
    return None


def compressed_msg_to_bgr(msg: Any, topic: str = "", stamp_ns: Optional[int] = None,
                          max_pixels: Optional[int] = None) -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (JPEG or PNG) into a BGR image.

    Formats such as ``"jpeg"``, ``"png"`` or image_transport's ``"rgb8; jpeg compressed
    bgr8"`` are accepted; the payload is decoded by OpenCV, which yields BGR either way.
    With ``max_pixels`` the size is read from the PNG / JPEG header and a larger image is
    refused before decoding (other payloads are checked after).

    Raises:
        ImageConversionError: Unsupported format, empty or undecodable data.
        ImageTooLargeError: More pixels than ``max_pixels``.
    """
    where = lambda: _where(msg, topic, stamp_ns)  # noqa: E731
    kind = _format_kind(msg.format)
    if kind is None:
        raise ImageConversionError(f"{where()}: unsupported compressed format {msg.format!r} "
                                   f"(supported: {', '.join(SUPPORTED_FORMATS)})")
    buf = _buffer(msg.data)
    if buf.size == 0:
        raise ImageConversionError(f"{where()}: compressed data is empty")
    size = compressed_dimensions(buf) if max_pixels is not None else None
    if size is not None:
        _check_size(size[0], size[1], max_pixels, where)
    image = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise ImageConversionError(f"{where()}: {kind or 'compressed'} data "
                                   f"({buf.size} bytes) cannot be decoded")
    _check_size(image.shape[1], image.shape[0], max_pixels, where)
    return image


def msg_to_bgr(msg: Any, topic: str = "", stamp_ns: Optional[int] = None,
               max_pixels: Optional[int] = None) -> np.ndarray:
    """Decode either image type: a message with ``format`` is compressed, else raw."""
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        return compressed_msg_to_bgr(msg, topic, stamp_ns, max_pixels)
    return image_msg_to_bgr(msg, topic, stamp_ns, max_pixels)


def _check_bgr(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or image.size == 0:
        raise ImageConversionError(f"expected a non-empty HxWx3 uint8 BGR image, got "
                                   f"{image.dtype} array of shape {image.shape}")
    return image


def bgr_to_image_fields(image: np.ndarray, encoding: str = "bgr8") -> Dict[str, Any]:
    """The ``sensor_msgs/Image`` fields (all but ``header``) for a BGR image.

    Exact inverse of :func:`image_msg_to_bgr`: decoding the result gives ``image`` back
    (for ``mono8``/``mono16`` when the image is grey, i.e. B = G = R). No row padding;
    ``mono16`` is written little-endian with each 8-bit value v as v * 257.

    Returns:
        ``dict(height, width, encoding, is_bigendian, step, data)`` with ``data`` a flat
        uint8 numpy array.

    Raises:
        ImageConversionError: Unsupported encoding or not a BGR uint8 image.
    """
    image = _check_bgr(image)
    enc = _canonical(encoding)
    if enc is None:
        raise ImageConversionError(f"cannot encode as {encoding!r} "
                                   f"(supported: {', '.join(SUPPORTED_ENCODINGS)})")
    height, width = image.shape[:2]
    channels, depth, _ = _ENCODINGS[enc]
    if enc == "bgr8":
        pixels = image
    elif enc == "rgb8":
        pixels = image[:, :, ::-1]
    elif enc == "bgra8":
        pixels = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    elif enc == "rgba8":
        pixels = cv2.cvtColor(image, cv2.COLOR_BGR2RGBA)
    else:
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        pixels = grey if enc == "mono8" else (grey.astype("<u2") * 257)
    data = np.ascontiguousarray(pixels).reshape(-1).view(np.uint8)
    return {"height": int(height), "width": int(width), "encoding": str(encoding),
            "is_bigendian": 0, "step": int(width * channels * depth), "data": data.copy()}


def bgr_to_compressed_fields(image: np.ndarray, fmt: str = "jpeg", quality: int = 90
                             ) -> Dict[str, Any]:
    """The ``sensor_msgs/CompressedImage`` fields (all but ``header``) for a BGR image.

    Args:
        image: HxWx3 uint8 BGR.
        fmt: ``"jpeg"`` or ``"png"``.
        quality: JPEG quality 1..100 (ignored for PNG).

    Returns:
        ``dict(format, data)``; ``format`` follows image_transport (``"bgr8; jpeg
        compressed bgr8"``), ``data`` is a flat uint8 numpy array.

    Raises:
        ImageConversionError: Unsupported format or encoder failure.
    """
    image = _check_bgr(image)
    kind = _format_kind(fmt)
    if kind not in ("jpeg", "png"):
        raise ImageConversionError(f"cannot compress as {fmt!r} (use jpeg or png)")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if kind == "jpeg" else []
    ok, encoded = cv2.imencode(".jpg" if kind == "jpeg" else ".png", image, params)
    if not ok:
        raise ImageConversionError(f"OpenCV could not encode a {image.shape} image as {kind}")
    return {"format": f"bgr8; {kind} compressed bgr8", "data": encoded.reshape(-1)}
