"""Evidence relative to the vehicle itself: lamp maps, track history and blink frequency.

A brake lamp is a lamp brighter than the same vehicle's own tail lamps, switched on at a
moment; a blinker is a lamp that flashes 1-2 times a second, all lamps of one side in
phase (hazard: both sides); a tail lamp, a running lamp or a reflection is bright but
steady. None of this depends on how a scene is drawn, and all of it is relative to the
track's own past. The functions here turn crops into such evidence, batched over tracks,
with the per-track memory passed in and returned (it lives in the model's state):

* :func:`lamp_maps`: per cell of a ``grid x grid`` map of the crop, the mean and the peak
  brightness and the peak red and warm (red or amber) excess of its pixels, each also
  relative to the crop's mean brightness (the vehicle body's level); with ``area``, also
  the share of its pixels that are bright and that are lit red (a lamp's lit area: at
  night a brake outshines its tail lamps by the area it clips, where the peak colour of a
  clipped lamp is white on one camera and red on another).
* :func:`relative_step`: a map against the track's previous frame and its running mean.
* :func:`resonator_step`: a bank of damped complex resonators per signal (the left and
  right halves of the lamp maps), one per blink period in frames; their amplitude is the
  periodic energy near that period over the last few periods, and the phase agreement of
  the left and right resonators tells a hazard (in phase) from noise. A steady lamp,
  however bright, drives none of them after its onset.
* :func:`contrast_step`: the same resonators on the left half's brightest lamp cell
  minus the right half's: a blinker flashes one side against the other, where light
  that changes the whole crop (exposure, a brake, the box's scale) drives nothing.
* :func:`floor_step`: the lit area of the whole crop and of its halves against the
  track's own floor and ceiling (a minimum that rises slowly and a maximum that falls
  slowly): at night a brake is a step in lit area over the vehicle's own tail-lamp
  level, which no single frame's lamp size tells across vehicles.
* :func:`cell_blink_step`: the same resonators on every cell of the fine lamp grid (peak
  brightness and peak warm excess), each amplitude also over the cell's own broadband
  change (box jitter and passing light change a cell too, but not at one period). The
  largest per image half and a per-cell map: a lamp of a few pixels that flashes stands
  out against its own cell's history, whatever its colour or how it is drawn.

The frame rate is not known to a step, so the periods are in frames (``PERIODS`` covers
0.8-2.2 Hz blinks from 10 to 30 frames per second); the heads learn which ones matter.
"""

from __future__ import annotations

import math
from typing import List, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

#: Channels of :func:`lamp_maps`, and what ``area`` adds.
LAMP_CHANNELS = 6
AREA_CHANNELS = 2
#: A bright pixel: its largest channel at least this (in [0, 1]).
AREA_BRIGHT = 0.78
#: A lit red pixel: red at least the first, and over the larger of green and blue by at
#: least the second.
AREA_RED = (0.59, 0.16)
#: Resonator periods in frames.
PERIODS: Tuple[float, ...] = (4.5, 6.5, 9.0, 13.0, 19.0, 27.0, 38.0)
#: Signals fed to the resonators: the left and right halves of lamp-map channels 1-3.
SIGNAL_CHANNELS = (1, 2, 3)
#: Decay of each resonator: its memory spans about this many periods.
MEMORY_PERIODS = 2.0


def lamp_channels(area: bool) -> int:
    """Channels of :func:`lamp_maps` with or without ``area``."""
    return LAMP_CHANNELS + (AREA_CHANNELS if area else 0)


def lamp_maps(crops: Tensor, grid: int, area: bool = False) -> Tensor:
    """Lamp evidence ``[N, lamp_channels(area), grid, grid]`` of ``[N, 3, S, S]`` BGR crops
    in [0, 1].

    Channels: mean brightness, peak brightness, peak red excess (red over the larger of
    green and blue), peak warm excess (red over blue: red and amber lamps), and the peak
    brightness and peak red excess minus the crop's mean brightness; with ``area``, the
    share of bright pixels (:data:`AREA_BRIGHT`) and of lit red ones (:data:`AREA_RED`).
    """
    b, g, r = crops[:, 0:1], crops[:, 1:2], crops[:, 2:3]
    value = torch.maximum(torch.maximum(b, g), r)
    red = F.relu(r - torch.maximum(g, b))
    warm = F.relu(r - b)
    # Fixed pools (the config makes the crop side a multiple of the grid): the ONNX
    # export keeps their shapes, which adaptive pools lose behind a dynamic batch.
    cell = crops.shape[-1] // grid
    peaks = F.max_pool2d(torch.cat((value, red, warm), 1), cell)
    mean = F.avg_pool2d(value, cell)
    body = value.mean(dim=(2, 3), keepdim=True)
    maps = [mean, peaks, peaks[:, 0:1] - body, peaks[:, 1:2] - body]
    if area:
        lit = torch.cat(((value >= AREA_BRIGHT).to(crops.dtype),
                         ((r >= AREA_RED[0]) & (red >= AREA_RED[1])).to(crops.dtype)), 1)
        maps.append(F.avg_pool2d(lit, cell))
    return torch.cat(maps, 1)


def space_to_depth(maps: Tensor, factor: int) -> Tensor:
    """``[N, C, H, W]`` -> ``[N, C * factor**2, H / factor, W / factor]``: each coarse cell
    holds its ``factor x factor`` fine cells as channels (reshape and permute only, so the
    ONNX export needs no special operator)."""
    if factor == 1:
        return maps
    n, c, h, w = maps.shape
    cells = maps.reshape(n, c, h // factor, factor, w // factor, factor)
    return cells.permute(0, 1, 3, 5, 2, 4).reshape(n, c * factor * factor, h // factor,
                                                   w // factor)


def relative_step(current: Tensor, previous: Tensor, mean: Tensor, seen: Tensor,
                  rate: float) -> Tuple[Tensor, Tensor]:
    """A map against the track's previous frame and running mean.

    Args:
        current: ``[N, C, H, W]`` this frame's map.
        previous: ``[N, C, H, W]`` the previous frame's map.
        mean: ``[N, C, H, W]`` the running mean of the track's maps.
        seen: ``[N, 1, 1, 1]`` 1 where the track has a previous frame.
        rate: Weight of a new frame in the running mean.

    Returns:
        ``[N, 2C, H, W]`` (current - previous, current - mean; zero for a new track) and
        the new running mean.
    """
    evidence = torch.cat((current - previous, current - mean), 1) * seen
    new_mean = mean + (current - mean) * (seen * rate + (1.0 - seen))
    return evidence, new_mean


def half_signals(maps: Tensor) -> Tensor:
    """``[N, 2K]`` signals: the left then the right half's mean of ``SIGNAL_CHANNELS``."""
    chosen = maps[:, list(SIGNAL_CHANNELS)]
    half = chosen.shape[3] // 2
    left = chosen[..., :half].mean(dim=(2, 3))
    right = chosen[..., chosen.shape[3] - half:].mean(dim=(2, 3))
    return torch.cat((left, right), 1)


def resonator_coefficients(periods: Sequence[float], like: Tensor
                           ) -> Tuple[Tensor, Tensor, Tensor]:
    """``(rho * cos w, rho * sin w, rho)`` per period, each ``[P]`` (``w = 2 pi / period``,
    ``rho`` the decay per frame)."""
    p = torch.tensor([float(x) for x in periods], dtype=like.dtype, device=like.device)
    rho = torch.exp(-1.0 / (MEMORY_PERIODS * p))
    w = 2.0 * math.pi / p
    return rho * torch.cos(w), rho * torch.sin(w), rho


def resonate(signals: Tensor, resonators: Tensor, level: Tensor, seen: Tensor,
             periods: Sequence[float]) -> Tuple[Tensor, Tensor]:
    """One frame of a resonator bank over any signals.

    Args:
        signals: ``[N, S]`` this frame's signals.
        resonators: ``[N, 2, S, P]`` real and imaginary parts per signal and period.
        level: ``[N, S]`` running level of each signal (removes its steady part).
        seen: ``[N, 1]`` 1 where the track has a previous frame.
        periods: The ``P`` periods in frames.

    Returns:
        The new resonators and the new level.
    """
    cos_w, sin_w, rho = resonator_coefficients(periods, signals)
    # A new track starts its level at its first signal, so its onset drives nothing.
    level = level * seen + signals * (1.0 - seen)
    drive = (signals - level).unsqueeze(-1) * (1.0 - rho)
    re, im = resonators[:, 0] * seen.unsqueeze(-1), resonators[:, 1] * seen.unsqueeze(-1)
    new_re = cos_w * re - sin_w * im + drive
    new_im = sin_w * re + cos_w * im
    return torch.stack((new_re, new_im), 1), level + (signals - level) * 0.1


def log_amplitude(resonators: Tensor) -> Tensor:
    """``[N, S, P]`` log amplitude of ``[N, 2, S, P]`` resonators (floor 1e-3)."""
    power = resonators[:, 0] ** 2 + resonators[:, 1] ** 2
    return torch.log(torch.sqrt(power + 1e-8) + 1e-3)


def resonator_step(signals: Tensor, resonators: Tensor, level: Tensor, seen: Tensor,
                   periods: Sequence[float]) -> Tuple[Tensor, Tensor, Tensor]:
    """One frame of the left/right resonator bank of the lamp maps (:func:`half_signals`).

    Args:
        signals: ``[N, 2K]`` this frame's signals (left K, then right K).
        resonators: ``[N, 2, 2K, P]`` real and imaginary parts per signal and period.
        level: ``[N, 2K]`` running level of each signal.
        seen: ``[N, 1]`` 1 where the track has a previous frame.
        periods: The ``P`` periods in frames.

    Returns:
        ``[N, 3K * P]`` features (log amplitude of the left and the right resonators,
        their phase agreement in [-1, 1]), the new resonators and the new level.
    """
    resonators, level = resonate(signals, resonators, level, seen, periods)
    re, im = resonators[:, 0], resonators[:, 1]
    k = signals.shape[1] // 2
    power = re * re + im * im
    cross = re[:, :k] * re[:, k:] + im[:, :k] * im[:, k:]
    agreement = cross / torch.sqrt(power[:, :k] * power[:, k:] + 1e-10)
    features = torch.cat((log_amplitude(resonators).flatten(1), agreement.flatten(1)), 1)
    return features, resonators, level


def resonator_features(n_signals: int, n_periods: int) -> int:
    """Length of :func:`resonator_step`'s features for ``n_signals`` (= 2K) signals."""
    return (n_signals + n_signals // 2) * n_periods


#: Lamp-map channels whose left-minus-right contrast drives :func:`contrast_step`: peak
#: brightness, peak red and peak warm excess (and, with the lit area, the lit red share).
CONTRAST_CHANNELS = (1, 2, 3)


def contrast_signals(fine_maps: Tensor, area: bool = False) -> Tensor:
    """``[N, K]``: the left image half's largest cell minus the right half's, per channel of
    :data:`CONTRAST_CHANNELS` (and the lit red share with ``area``) of ``[N, C, F, F]``
    fine lamp maps. A blinker modulates one side; light that changes the whole crop
    (exposure, a brake lit on both sides, the box's scale) cancels."""
    chosen = fine_maps[:, contrast_channels(area)]
    half = chosen.shape[3] // 2
    left = chosen[..., :half].amax(dim=(2, 3))
    right = chosen[..., chosen.shape[3] - half:].amax(dim=(2, 3))
    return left - right


def contrast_channels(area: bool = False) -> List[int]:
    """The lamp-map channels :func:`contrast_signals` reads (the lit red share's last)."""
    return list(CONTRAST_CHANNELS) + ([LAMP_CHANNELS + 1] if area else [])


def contrast_features(area: bool = False) -> int:
    """Length of :func:`contrast_step`'s features."""
    return len(contrast_channels(area)) * len(PERIODS)


def contrast_step(signals: Tensor, resonators: Tensor, level: Tensor, seen: Tensor
                  ) -> Tuple[Tensor, Tensor, Tensor]:
    """One frame of resonators over :func:`contrast_signals` ``[N, K]``: ``[N, K * P]`` log
    amplitudes per blink period (:data:`PERIODS`), the new ``[N, 2, K, P]`` resonators and
    the new ``[N, K]`` level."""
    resonators, level = resonate(signals, resonators, level, seen, PERIODS)
    return log_amplitude(resonators).flatten(1), resonators, level


#: Regions whose lit area :func:`floor_step` follows: the whole crop, its left and right half
#: (and with ``high_lamp`` the upper centre, :data:`HIGH_LAMP_BOX`).
FLOOR_REGIONS = 3
#: Rows and columns of the crop's upper centre, as fractions of its side: where a centre
#: high-mounted stop lamp sits on the rear glass or the roof edge, dark unless braking. Its
#: lit red ranked night brakes at 0.86-0.88 on both generators, the whole crop's at
#: 0.70-0.84 (docs/model.md, "The centre high-mounted stop lamp").
HIGH_LAMP_BOX = (0.1, 0.5, 0.35, 0.65)


def floor_regions(high_lamp: bool = False) -> int:
    """Regions of :func:`area_shares`."""
    return FLOOR_REGIONS + int(high_lamp)


def floor_features(high_lamp: bool = False) -> int:
    """Length of :func:`floor_step`'s vector: per region and area channel the share, its
    rise over the floor and its fall under the ceiling."""
    return 3 * floor_regions(high_lamp) * AREA_CHANNELS


def _box_cells(grid: int, low: float, high: float) -> slice:
    """The cells of a ``grid`` side that a fraction range covers (at least one)."""
    start = int(low * grid)
    return slice(start, max(start + 1, int(high * grid)))


def area_shares(fine_maps: Tensor, high_lamp: bool = False) -> Tensor:
    """``[N, R * A]``: the bright and lit-red shares (:func:`lamp_maps` with ``area``) of the
    whole crop, its left half and its right half (and with ``high_lamp`` its upper centre),
    from ``[N, C, F, F]`` fine lamp maps."""
    area = fine_maps[:, LAMP_CHANNELS:LAMP_CHANNELS + AREA_CHANNELS]
    half = area.shape[3] // 2
    regions = [area, area[..., :half], area[..., half:]]
    if high_lamp:
        top, bottom, left, right = HIGH_LAMP_BOX
        grid = area.shape[3]
        regions.append(area[..., _box_cells(grid, top, bottom), _box_cells(grid, left, right)])
    return torch.cat([r.mean(dim=(2, 3)) for r in regions], 1)


def floor_step(shares: Tensor, floor: Tensor, ceiling: Tensor, seen: Tensor, rate: float
               ) -> Tuple[Tensor, Tensor, Tensor]:
    """One frame of lit area against the track's own range.

    The floor follows a fall at once and a rise at ``rate`` per frame, the ceiling the
    reverse: a brake held for a few seconds stays a rise over the tail-lamp level, while a
    vehicle that turns or nears moves both within a few seconds.

    Args:
        shares: ``[N, S]`` this frame's shares (:func:`area_shares`).
        floor: ``[N, S]`` the track's floor.
        ceiling: ``[N, S]`` the track's ceiling.
        seen: ``[N, 1]`` 1 where the track has a previous frame (a new track starts both
            at its first shares).
        rate: Weight of a frame in the slow direction.

    Returns:
        ``[N, 3S]`` vector (shares, shares - floor, ceiling - shares), new floor and ceiling.
    """
    floor = floor * seen + shares * (1.0 - seen)
    ceiling = ceiling * seen + shares * (1.0 - seen)
    floor = torch.minimum(shares, floor + (shares - floor) * rate)
    ceiling = torch.maximum(shares, ceiling + (shares - ceiling) * rate)
    return torch.cat((shares, shares - floor, ceiling - shares), 1), floor, ceiling


def expert_features(red_only: bool = False, high_lamp: bool = False) -> int:
    """Length of :func:`expert_inputs`."""
    floor = floor_features(high_lamp)
    return 2 * (floor // AREA_CHANNELS if red_only else floor) + 1


def expert_inputs(floor_vector: Tensor, fine_maps: Tensor, red_only: bool = False) -> Tensor:
    """``[N, 2V + 1]``: :func:`floor_step`'s vector (with ``red_only`` its lit-red part: the
    second area channel of every region's share, rise and fall), the same times the crop's
    mean brightness, and that brightness (from the mean-brightness channel of
    ``[N, C, F, F]`` fine lamp maps): a linear judge of it can weigh the lit area by how
    dark the scene is, since by day a red body or the sun moves the shares as much as a
    brake does."""
    if red_only:
        floor_vector = floor_vector[:, 1::AREA_CHANNELS]
    body = crop_brightness(fine_maps)
    return torch.cat((floor_vector, floor_vector * body, body), 1)


def crop_brightness(fine_maps: Tensor) -> Tensor:
    """``[N, 1]`` the crop's mean brightness from the mean-brightness channel of
    ``[N, C, F, F]`` lamp maps."""
    return fine_maps[:, 0].mean(dim=(1, 2))[:, None]


#: Lamp-map channels whose fine cells drive :func:`cell_blink_step`: peak brightness and
#: peak warm excess.
CELL_CHANNELS = (1, 3)
#: Per-frame rate of a cell's broadband change (about the resonators' memory).
BROADBAND_RATE = 0.1
#: Floor of the broadband change in the ratio (brightness units in [0, 1]).
BROADBAND_FLOOR = 0.01


def depth_to_space(maps: Tensor, factor: int) -> Tensor:
    """The inverse of :func:`space_to_depth`: ``[N, C * f**2, H, W]`` -> ``[N, C, fH, fW]``."""
    if factor == 1:
        return maps
    n, c, h, w = maps.shape
    c //= factor * factor
    cells = maps.reshape(n, c, factor, factor, h, w).permute(0, 1, 4, 2, 5, 3)
    return cells.reshape(n, c, h * factor, w * factor)


def cell_blink_sizes(fine: int, pooled: bool = False) -> Tuple[int, int, int]:
    """``(signals, vector features, map channels at the fine grid)`` of
    :func:`cell_blink_step` on a ``fine x fine`` lamp grid."""
    signals = len(CELL_CHANNELS) * fine * fine
    if pooled:
        return signals, len(CELL_CHANNELS) * 2, len(CELL_CHANNELS)
    return signals, 2 * len(CELL_CHANNELS) * 2 * len(PERIODS), 2 * len(CELL_CHANNELS)


def cell_blink_step(fine_maps: Tensor, resonators: Tensor, memory: Tensor, seen: Tensor,
                    periods: Sequence[float] = PERIODS, pooled: bool = False
                    ) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """One frame of periodic energy per cell of the fine lamp grid.

    Args:
        fine_maps: ``[N, K, F, F]`` lamp maps (:func:`lamp_maps`, K channels) on the fine grid.
        resonators: ``[N, 2, S, P]`` real and imaginary parts per cell signal and period
            (``S = 2 F F``, :data:`CELL_CHANNELS`).
        memory: ``[N, 3, S]`` each signal's previous value, slow level and broadband change.
        seen: ``[N, 1]`` 1 where the track has a previous frame.
        periods: The ``P`` periods in frames.
        pooled: Only the raw amplitudes, each cell's largest over the periods: a
            ``[N, 2C]`` vector (per channel and half) and a ``[N, C, F, F]`` map. Which
            period a blink has depends on the frame rate, and the ratio to the broadband
            change on how a renderer or camera adds noise; a probe fitted on one renderer
            carried these few numbers to another where the full set did not
            (``docs/model.md``).

    Returns:
        ``[N, 4 * C * P]`` vector (per amplitude kind -- raw, over the broadband change --,
        channel and image half: the largest log amplitude over the half's cells per
        period), ``[N, 2C, F, F]`` map (per cell the largest log amplitude over periods,
        raw and over the broadband change), the new resonators and the new memory.
    """
    n, fine = fine_maps.shape[0], fine_maps.shape[-1]
    channels = len(CELL_CHANNELS)
    signals = fine_maps[:, list(CELL_CHANNELS)].reshape(n, -1)
    previous, level, broad = memory.unbind(1)
    previous = previous * seen + signals * (1.0 - seen)
    broad = (broad + ((signals - previous).abs() - broad) * BROADBAND_RATE) * seen
    resonators, level = resonate(signals, resonators, level, seen, periods)
    amplitude = torch.sqrt(resonators[:, 0] ** 2 + resonators[:, 1] ** 2 + 1e-8)
    half = fine // 2
    # The pooled form keeps the broadband memory too: one state layout for both forms.
    memory = torch.stack((signals, level, broad), 1)
    if pooled:
        raw = torch.log(amplitude + 1e-3).reshape(n, channels, fine, fine, len(periods))
        cell_map = raw.amax(dim=-1)  # [N, C, F, F]
        vector = torch.stack((cell_map[..., :half].amax(dim=(2, 3)),
                              cell_map[..., fine - half:].amax(dim=(2, 3))), 2)
        return vector.flatten(1), cell_map, resonators, memory
    ratio = amplitude / (broad.unsqueeze(-1) + BROADBAND_FLOOR)
    kinds = torch.stack((amplitude, ratio), 1).reshape(n, 2, channels, fine, fine, len(periods))
    kinds = torch.log(kinds + 1e-3)
    vector = torch.stack((kinds[:, :, :, :, :half].amax(dim=(3, 4)),
                          kinds[:, :, :, :, fine - half:].amax(dim=(3, 4))), 3)
    cell_map = kinds.amax(dim=-1).reshape(n, 2 * channels, fine, fine)
    return vector.flatten(1), cell_map, resonators, memory
