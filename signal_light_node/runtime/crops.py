"""Turn a tracked box into the model's square input crop.

This is the only crop code of the package: the training stream, the split writer and
the online engine all call it, so the model sees the same crops in training and on
the road. A crop is the box grown by a margin on each side, made square around its
centre, cut from the image (zeros where it reaches past the border) and resized. With
``CropConfig.fill`` the grown box is not made square but stretched to the square crop:
a vehicle seen from its side then fills the crop's height instead of a band of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError, CropError

MIN_SIZE = 16
MAX_SIZE = 512


@dataclass(frozen=True)
class CropConfig:
    """How boxes become crops.

    Attributes:
        size: Side of the square crop in pixels (16..512).
        margin: Fraction of the box's width (height) added on the left and right (top and
            bottom) before squaring, 0..1.
        fill: Stretch the grown box to the square crop instead of squaring it first
            (its shorter side is not padded with the scene around it).
    """

    size: int = 64
    margin: float = 0.15
    fill: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not isinstance(self.size, (int, np.integer)):
            raise ConfigError(f"crop size must be an integer, got {self.size!r}")
        if not MIN_SIZE <= int(self.size) <= MAX_SIZE:
            raise ConfigError(f"crop size must be in {MIN_SIZE}..{MAX_SIZE}, got {self.size}")
        try:
            margin = float(self.margin)
        except (TypeError, ValueError):
            raise ConfigError(f"crop margin must be a number, got {self.margin!r}") from None
        if not (math.isfinite(margin) and 0.0 <= margin <= 1.0):
            raise ConfigError(f"crop margin must be in 0..1, got {self.margin}")
        if not isinstance(self.fill, (bool, np.bool_)):
            raise ConfigError(f"crop fill must be true or false, got {self.fill!r}")
        # Normalise types so that equal configs compare and hash equal.
        object.__setattr__(self, "size", int(self.size))
        object.__setattr__(self, "margin", margin)
        object.__setattr__(self, "fill", bool(self.fill))


def _check_image(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 \
            or image.shape[2] != 3:
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        raise CropError(f"image must be an HxWx3 uint8 array, got shape {shape} dtype {dtype}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise CropError(f"image is empty ({image.shape[1]}x{image.shape[0]})")


def _check_box(box: TrackBox, width: int, height: int, grow: float) -> None:
    """Raise CropError for a box no crop can be cut for (``grow``: its sides' factor)."""
    if not box.is_finite:
        raise CropError(f"track {box.track_id!r}: box has non-finite coordinates "
                        f"({box.x0}, {box.y0}, {box.x1}, {box.y1})")
    w, h = box.width, box.height
    if not (w > 0 and h > 0):
        raise CropError(f"track {box.track_id!r}: box has zero or negative size ({w:g}x{h:g})")
    if box.x1 <= 0 or box.y1 <= 0 or box.x0 >= width or box.y0 >= height:
        raise CropError(f"track {box.track_id!r}: box ({box.x0:g}, {box.y0:g}, {box.x1:g}, "
                        f"{box.y1:g}) lies entirely outside the {width}x{height} image")
    if max(w, h) * grow > 64 * max(width, height):
        # A box this large is a broken detection; cutting it would allocate gigabytes.
        raise CropError(f"track {box.track_id!r}: box of {w:g}x{h:g} is far larger than "
                        f"the {width}x{height} image")


def _halving_side(side: float, size: int) -> int:
    """A region side in whole pixels, rounded up to a multiple of its
    :func:`_halving_step` so that :func:`_cut` halves it exactly (the change is < 1/size
    of the side)."""
    side_px = max(1, int(round(side)))
    step = _halving_step(side_px, size)
    return step * -(-side_px // step)


def _region(box: TrackBox, width: int, height: int, config: CropConfig
            ) -> Tuple[int, int, int, int]:
    """Integer region ``(x0, y0, w, h)`` to cut for ``box`` (``w == h`` unless
    ``config.fill``); raises CropError if none."""
    grow = 1.0 + 2.0 * config.margin
    _check_box(box, width, height, grow)
    if config.fill:
        w_px = _halving_side(box.width * grow, config.size)
        h_px = _halving_side(box.height * grow, config.size)
    else:
        w_px = h_px = _halving_side(max(box.width, box.height) * grow, config.size)
    cx = 0.5 * (box.x0 + box.x1)
    cy = 0.5 * (box.y0 + box.y1)
    x0 = int(math.floor(cx - 0.5 * w_px + 0.5))
    y0 = int(math.floor(cy - 0.5 * h_px + 0.5))
    return x0, y0, w_px, h_px


def crop_region(box: TrackBox, width: int, height: int,
                config: CropConfig = CropConfig()) -> Tuple[int, int, int, int]:
    """The region that :func:`crop_vehicle` cuts for ``box``, in image pixels.

    Useful to map something computed on the crop (an attention mask) back onto the frame.

    Args:
        box: The tracked box.
        width: Image width.
        height: Image height.
        config: Crop size, margin and fill.

    Returns:
        ``(x0, y0, w, h)``, a square (``w == h``) unless ``config.fill``; it may reach past
        the image border.

    Raises:
        CropError: For the boxes that :func:`crop_vehicle` rejects.
    """
    return _region(box, width, height, config)


def _halving_step(side: int, size: int) -> int:
    """``2**j``: how much a region side is halved before the final resize (to below
    ``2 size``; the largest power of 2 at most ``side / size``, or 1)."""
    step = 1
    while side // step >= 2 * size:
        step *= 2
    return step


def _cut(image: np.ndarray, x0: int, y0: int, w: int, h: int, size: int) -> np.ndarray:
    """Cut the region ``(x0, y0, w, h)`` (zeros outside the image) and resize it to
    ``size x size``.

    Shrinking first halves each side as ``INTER_AREA`` does until it is below ``2 size``
    (OpenCV's fast path when both sides halve; its general area resize costs ~10x more, so
    a side halved alone, as a fill crop needs, goes through :func:`_halve_alone`). When the
    region reaches past the border, only the part inside the image, widened to the halving
    grid, is halved and the zeros are added afterwards at the reduced scale: the same pixels
    as padding first, without halving large blocks of zeros.
    """
    height, width = image.shape[:2]
    sx, sy = _halving_step(w, size), _halving_step(h, size)
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + w, width), min(y0 + h, height)
    # The inside part relative to the region, widened outwards to multiples of the steps.
    ax0, ay0 = (cx0 - x0) // sx * sx, (cy0 - y0) // sy * sy
    ax1, ay1 = -(-(cx1 - x0) // sx) * sx, -(-(cy1 - y0) // sy) * sy
    patch = image[cy0:cy1, cx0:cx1]
    fine = (cy0 - y0 - ay0, ay1 - (cy1 - y0), cx0 - x0 - ax0, ax1 - (cx1 - x0))
    if any(fine):
        patch = cv2.copyMakeBorder(patch, *fine, cv2.BORDER_CONSTANT, value=(0, 0, 0))
    hx, hy = sx.bit_length() - 1, sy.bit_length() - 1
    both = min(hx, hy)
    for _ in range(both):
        ph, pw = patch.shape[:2]
        patch = cv2.resize(patch, (pw // 2, ph // 2), interpolation=cv2.INTER_AREA)
    patch = _halve_alone(patch, hx - both, hy - both)
    coarse = (ay0 // sy, (h - ay1) // sy, ax0 // sx, (w - ax1) // sx)
    if any(coarse):
        patch = cv2.copyMakeBorder(patch, *coarse, cv2.BORDER_CONSTANT, value=(0, 0, 0))
    return _finish(patch, size)


def _finish(patch: np.ndarray, size: int) -> np.ndarray:
    """Resize a patch whose sides are below ``2 size`` to ``size x size``.

    Enlarging is bilinear; shrinking is bilinear up to ``2 size`` followed by one area
    halving, which differs from a single ``INTER_AREA`` call by a few grey levels on fine
    texture (the model only ever sees crops made this way) at a fraction of its cost.
    """
    h, w = patch.shape[:2]
    if h == size and w == size:
        return np.ascontiguousarray(patch)
    if h <= size and w <= size:
        return cv2.resize(patch, (size, size), interpolation=cv2.INTER_LINEAR)
    # A side that shrinks goes to 2 size (then halves), one that does not to size.
    patch = cv2.resize(patch, (2 * size if w > size else size, 2 * size if h > size else size),
                       interpolation=cv2.INTER_LINEAR)
    if w > size and h > size:
        return cv2.resize(patch, (size, size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(_halve_alone(patch, int(w > size), int(h > size)))


#: Averages each row with the next: with every other row kept, an area halving of the height.
_NEXT_ROW = np.array([[0.5], [0.5]], np.float32)


def _halve_alone(patch: np.ndarray, times_x: int, times_y: int) -> np.ndarray:
    """Halve the width of ``patch`` ``times_x`` times, then its height ``times_y`` times,
    one side at a time, pixel for pixel as ``cv2.resize(..., INTER_AREA)`` would.

    OpenCV's area resize takes a slow general path when only one side halves; the mean of
    each row and the next, rounded half to even as that path rounds, is the same result at
    a fraction of the cost, and a width is halved as the height of the transposed patch.
    A side of odd length is left to ``cv2.resize``.
    """
    if times_x:
        patch = cv2.transpose(_halve_rows(cv2.transpose(patch), times_x))
    return _halve_rows(patch, times_y)


def _halve_rows(patch: np.ndarray, times: int) -> np.ndarray:
    for _ in range(times):
        rows, cols = patch.shape[:2]
        if rows % 2:
            patch = cv2.resize(patch, (cols, rows // 2), interpolation=cv2.INTER_AREA)
            continue
        patch = cv2.filter2D(patch, -1, _NEXT_ROW, anchor=(0, 0),
                             borderType=cv2.BORDER_REPLICATE)[::2]
    return patch


def crop_vehicle(image: np.ndarray, box: TrackBox, config: CropConfig = CropConfig()) -> np.ndarray:
    """Cut the model crop of one box.

    Args:
        image: The camera frame, HxWx3 uint8 (BGR).
        box: The tracked box in pixels.
        config: Crop size and margin.

    Returns:
        A new ``(size, size, 3)`` uint8 array.

    Raises:
        CropError: The image is not HxWx3 uint8, or the box is not finite, has zero or
            negative size, or lies entirely outside the image.
    """
    _check_image(image)
    height, width = image.shape[:2]
    return _cut(image, *_region(box, width, height, config), config.size)


def crop_vehicles(image: np.ndarray, boxes: Sequence[TrackBox],
                  config: CropConfig = CropConfig()) -> Tuple[np.ndarray, List[Optional[str]]]:
    """Cut the crops of every box of one frame; a bad box never stops the others.

    Args:
        image: The camera frame, HxWx3 uint8 (BGR).
        boxes: The tracked boxes.
        config: Crop size and margin.

    Returns:
        ``(crops, reasons)``: crops ``[N, size, size, 3]`` uint8 in the order of ``boxes``,
        and per box ``None`` or the reason why its crop is all zeros.

    Raises:
        CropError: Only when the image itself is unusable.
    """
    _check_image(image)
    height, width = image.shape[:2]
    size = config.size
    crops = np.zeros((len(boxes), size, size, 3), dtype=np.uint8)
    reasons: List[Optional[str]] = [None] * len(boxes)
    for i, box in enumerate(boxes):
        try:
            region = _region(box, width, height, config)
        except CropError as exc:
            reasons[i] = str(exc)
            continue
        crops[i] = _cut(image, *region, size)
    return crops, reasons


def clip_roi(box: TrackBox, width: int, height: int) -> Tuple[int, int, int, int]:
    """The box clipped to the image as a ``sensor_msgs/RegionOfInterest``.

    Edges are rounded outwards to whole pixels; a non-finite box or one outside the
    image gives a zero-size ROI.

    Args:
        box: The tracked box in pixels.
        width: Image width.
        height: Image height.

    Returns:
        ``(x_offset, y_offset, width, height)`` as non-negative ints.
    """
    if not box.is_finite:
        return 0, 0, 0, 0
    x0 = min(max(int(math.floor(box.x0)), 0), width)
    y0 = min(max(int(math.floor(box.y0)), 0), height)
    x1 = min(max(int(math.ceil(box.x1)), 0), width)
    y1 = min(max(int(math.ceil(box.y1)), 0), height)
    if x1 <= x0 or y1 <= y0:
        return 0, 0, 0, 0
    return x0, y0, x1 - x0, y1 - y0
