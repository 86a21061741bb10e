"""Keep a setting fitted on labelled tracks only where its gain is more than their noise.

``signal-light calibrate`` picks the best of a grid on the user's fit tracks. With a few
dozen tracks from a handful of scenes, the best of 49 margins and offsets or 36 filter
settings usually wins by under a point, and such a win is noise as often as not: on the
held-out family a margin that scored 0.7 points above 0 on the fit half lost 4.5 points of
intent on the other half (docs/results/adapt_family.md, thirtieth session). So a fitted
setting replaces the model as it is (or the node's default filter) only if it scores above
it on at least :data:`DEFAULT_CONFIDENCE` of the resamples of the fit tracks' scenes
(:func:`~signal_light_node.evaluation.bootstrap.scene_bootstrap`: the frames of a scene are
not independent draws). A user's labelled recording is often one scene (a bag is one); where
the fit tracks come from fewer than :data:`MIN_SCENES` scenes, the tracks are resampled
instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Sequence

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.bootstrap import scene_bootstrap, scene_groups, track_confusions
from signal_light_node.evaluation.scoring import EvalSettings
from signal_light_node.evaluation.tracks import TrackSequence

#: The share of scene resamples a setting must win against the model as it is.
DEFAULT_CONFIDENCE = 0.9
#: How many resamples of the scenes.
RESAMPLES = 1000
#: Fewer scenes than this and the tracks are resampled instead.
MIN_SCENES = 5


@dataclass(frozen=True)
class Verdict:
    """Whether a fitted setting is kept.

    Attributes:
        share_above: Share of scene resamples where it scores above the reference.
        kept: ``share_above`` reached the guard's confidence.
    """

    share_above: float
    kept: bool

    def as_dict(self) -> Dict[str, Any]:
        """For a checkpoint's metadata."""
        return {"share_above": self.share_above, "kept": self.kept}


class GainGuard:
    """Judges fitted settings against a reference on the same tracks' published states.

    Args:
        tracks: The fit tracks, in the order their published states will come.
        confidence: The share of resamples to win, in [0, 1); 0 keeps every setting.
        settings: Warm-up and grace, as the fit's scorer.
        resamples: Resamples of the scenes.
        seed: Seed of the resampling.

    Raises:
        ConfigError: A confidence outside [0, 1), or no track.
    """

    def __init__(self, tracks: Sequence[TrackSequence], confidence: float = DEFAULT_CONFIDENCE,
                 settings: EvalSettings = EvalSettings(), resamples: int = RESAMPLES,
                 seed: int = 0) -> None:
        if not 0.0 <= confidence < 1.0:
            raise ConfigError(f"the gain confidence must be in [0, 1), got {confidence}")
        if not tracks:
            raise ConfigError("no fit track to judge a gain on")
        self.tracks, self.confidence = list(tracks), float(confidence)
        self.settings, self.resamples, self.seed = settings, resamples, seed
        self.groups = scene_groups(self.tracks)
        if len(self.groups) < MIN_SCENES:  # too few to resample: each track is a unit
            self.groups = [np.array([i]) for i in range(len(self.tracks))]

    def judge(self, reference: Sequence[np.ndarray], candidate: Sequence[np.ndarray]) -> Verdict:
        """The verdict on ``candidate`` against ``reference``: per track the published
        states ``[T, len(TASKS)]`` of each, in the guard's track order."""
        if self.confidence == 0.0:  # no resampling asked for
            return Verdict(share_above=float("nan"), kept=True)
        files: List[Dict[str, np.ndarray]] = [track_confusions(self.tracks, preds, self.settings)
                                              for preds in (reference, candidate)]
        share = scene_bootstrap(files, self.groups, self.resamples, self.seed)[1].share_above
        return Verdict(share_above=share, kept=share >= self.confidence)
