"""Measure ``rosbags-image`` against the project's ``io/image_codec.py`` (decoding to BGR).

Not a test and not a dependency: ``pip install rosbags-image==0.10.4`` into a scratch
place (e.g. ``pip install --target /tmp/rbimg --no-deps rosbags-image==0.10.4`` and
``PYTHONPATH=/tmp/rbimg``) and run ``python scripts/compare_image_codecs.py``. It prints,
per encoding, whether both give the same BGR image and the median decode time of each,
then the awkward cases (row padding, grey JPEG/PNG, short or broken data) and what each
library does with them. The decision and the numbers are in docs/ARCHITECTURE.md.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any, Callable, List, Sequence, Tuple

import cv2
import numpy as np

from signal_light_node.io.bagio import make
from signal_light_node.io.conversions import make_header
from signal_light_node.io.image_codec import (bgr_to_compressed_fields, bgr_to_image_fields,
                                              msg_to_bgr)


def _scene(width: int, height: int) -> np.ndarray:
    """A camera-like frame: smooth gradients, edges and noise (JPEG/PNG sizes realistic)."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    image = np.stack([x / width * 200, y / height * 180, (x + y) / (width + height) * 255], -1)
    for _ in range(40):
        x0, y0 = int(rng.integers(0, width - 80)), int(rng.integers(0, height - 60))
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.rectangle(image, (x0, y0), (x0 + 80, y0 + 60), colour, -1)
    image += rng.normal(0, 6, image.shape).astype(np.float32)
    return np.clip(image, 0, 255).astype(np.uint8)


def _image(fields: dict) -> Any:
    return make("sensor_msgs/msg/Image", header=make_header(0, "cam", make), **fields)


def _compressed(fields: dict) -> Any:
    return make("sensor_msgs/msg/CompressedImage", header=make_header(0, "cam", make), **fields)


def _median_ms(fns: Sequence[Callable[[], Any]], reps: int) -> List[float]:
    """Median time of each function in ms, the calls interleaved (A B A B ...) so that a
    busy machine slows both alike."""
    times: List[List[float]] = [[] for _ in fns]
    for fn in fns:
        fn()
    for _ in range(reps):
        for fn, out in zip(fns, times):
            start = time.perf_counter()
            fn()
            out.append(time.perf_counter() - start)
    return [statistics.median(t) * 1e3 for t in times]


def _try(fn: Callable[[], np.ndarray]) -> Tuple[str, Any]:
    try:
        return "ok", fn()
    except Exception as exc:  # noqa: BLE001 - reporting whatever each library raises
        return f"{type(exc).__name__}: {str(exc)[:60]}", None


def main() -> None:
    from rosbags.image import message_to_cvimage

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--reps", type=int, default=100)
    args = parser.parse_args()

    bgr = _scene(args.width, args.height)
    grey = cv2.cvtColor(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    cases: List[Tuple[str, Any]] = [
        ("bgr8", _image(bgr_to_image_fields(bgr, "bgr8"))),
        ("rgb8", _image(bgr_to_image_fields(bgr, "rgb8"))),
        ("mono8", _image(bgr_to_image_fields(grey, "mono8"))),
        ("jpeg", _compressed(bgr_to_compressed_fields(bgr, "jpeg", 90))),
        ("png", _compressed(bgr_to_compressed_fields(bgr, "png"))),
    ]
    print(f"{args.width}x{args.height}, median of {args.reps} decodes to BGR uint8")
    print("| encoding | same image | image_codec ms | rosbags-image ms |")
    print("| --- | --- | ---: | ---: |")
    for name, msg in cases:
        ours = msg_to_bgr(msg)
        theirs = np.asarray(message_to_cvimage(msg, "bgr8"))
        same = theirs.shape == ours.shape and bool(np.array_equal(theirs, ours))
        t_ours, t_theirs = _median_ms([lambda: msg_to_bgr(msg),
                                       lambda: message_to_cvimage(msg, "bgr8")], args.reps)
        print(f"| {name} | {'yes' if same else 'NO'} | {t_ours:.2f} | {t_theirs:.2f} |")

    # Awkward inputs a camera driver or a damaged bag can produce.
    padded = bgr_to_image_fields(bgr, "bgr8")
    row = padded["step"]
    padded["data"] = np.concatenate([padded["data"].reshape(args.height, row),
                                     np.zeros((args.height, 64), np.uint8)], 1).reshape(-1)
    padded["step"] = row + 64
    short = bgr_to_image_fields(bgr, "bgr8")
    short["data"] = short["data"][:1000]
    grey_jpeg = bgr_to_compressed_fields(bgr, "jpeg")
    grey_jpeg["data"] = cv2.imencode(".jpg", cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))[1].reshape(-1)
    grey_png = bgr_to_compressed_fields(bgr, "png")
    grey_png["data"] = cv2.imencode(".png", cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))[1].reshape(-1)
    broken = {"format": "jpeg", "data": np.frombuffer(b"not a jpeg at all", np.uint8).copy()}
    awkward = [
        ("bgr8, step padded by 64 bytes", _image(padded), bgr),
        ("bgr8, data shorter than step x height", _image(short), None),
        ("grey JPEG", _compressed(grey_jpeg), None),
        ("grey PNG", _compressed(grey_png), grey),
        ("undecodable JPEG", _compressed(broken), None),
    ]
    print()
    print("| input | image_codec | rosbags-image |")
    print("| --- | --- | --- |")
    for name, msg, want in awkward:
        cells = []
        for fn in (lambda: msg_to_bgr(msg), lambda: np.asarray(message_to_cvimage(msg, "bgr8"))):
            status, got = _try(fn)
            if got is not None:
                status = f"shape {got.shape}"
                if want is not None:
                    status += ", right" if got.shape == want.shape and \
                        np.array_equal(got, want) else ", WRONG pixels"
            cells.append(status)
        print(f"| {name} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
