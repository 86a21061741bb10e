"""Annotated video/GIF output of replayed frames.

``signal-light replay --video`` and the demo report draw each frame with
:func:`signal_light_node.outputs.debug_image.draw_results` (the node's debug image, so all
show the same picture) and collect the frames here.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np

from signal_light_node.errors import ConfigError

LOG = logging.getLogger(__name__)


class VideoSink:
    """Collects annotated frames into an MP4 (``mp4v``) or an animated GIF.

    GIF frames are kept in memory until ``close`` and scaled down to ``gif_width``
    pixels wide; MP4 frames are written as they come.

    Args:
        path: Output file; ``.mp4`` or ``.gif``.
        fps: Frame rate of the output.
        gif_width: Width of GIF frames.
        max_gif_frames: GIF frames kept; later ones are dropped with a warning.

    Raises:
        ConfigError: The suffix is neither ``.mp4`` nor ``.gif``, or fps is not positive.
    """

    def __init__(self, path: "str | Path", fps: float, gif_width: int = 480,
                 max_gif_frames: int = 600) -> None:
        self.path = Path(path)
        self.kind = self.path.suffix.lower().lstrip(".")
        if self.kind not in ("mp4", "gif"):
            raise ConfigError(f"video output must end in .mp4 or .gif, got {self.path.name!r}")
        if not fps > 0:
            raise ConfigError(f"video fps must be positive, got {fps}")
        self.fps = float(fps)
        self.gif_width = int(gif_width)
        self.max_gif_frames = int(max_gif_frames)
        self.count = 0
        self._writer: Optional[cv2.VideoWriter] = None
        self._frames: List[np.ndarray] = []
        self._dropped = 0

    def add(self, frame: np.ndarray) -> None:
        """Append one BGR frame (all frames must have the same size)."""
        if self.kind == "mp4":
            if self._writer is None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                h, w = frame.shape[:2]
                self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"),
                                               self.fps, (w, h))
                if not self._writer.isOpened():
                    raise ConfigError(f"cannot open {self.path} for writing an mp4v video")
            self._writer.write(frame)
        else:
            if len(self._frames) >= self.max_gif_frames:
                self._dropped += 1
                return
            h, w = frame.shape[:2]
            if w > self.gif_width:
                size = (self.gif_width, max(1, round(h * self.gif_width / w)))
                frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
            self._frames.append(frame)
        self.count += 1

    def close(self) -> Optional[Path]:
        """Finish the file; returns its path, or None when no frame was added."""
        if self.kind == "mp4":
            if self._writer is None:
                return None
            self._writer.release()
            self._writer = None
            return self.path
        if not self._frames:
            return None
        if self._dropped:
            LOG.warning("%s: kept the first %d frames, dropped %d", self.path,
                        self.max_gif_frames, self._dropped)
        animation = cv2.Animation()
        animation.frames = self._frames
        animation.durations = [int(round(1000.0 / self.fps))] * len(self._frames)
        animation.loop_count = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwriteanimation(str(self.path), animation):
            raise ConfigError(f"cannot write the GIF {self.path}")
        self._frames = []
        return self.path
