"""``evaluation.still_looks``: a track's looks held still, and whether each is read ON."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.still_looks import held_still, on_share, still_look_reads
from signal_light_node.labels import LightStatus
from signal_light_node.model import load_checkpoint
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS
from signal_light_node.training.night_bound import light_offsets
from signal_light_node.training.sources import load_bag_tracks
from signal_light_node.training.unknown_bias import add_on_offsets

NIGHT = Path(__file__).resolve().parents[1] / "bags" / "night_tail_lamps"
needs_bag = pytest.mark.skipif(not (NIGHT / "metadata.yaml").exists(),
                               reason="bags/night_tail_lamps not committed")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _night_track(model):
    return load_bag_tracks(NIGHT, model.config.crop_config())[0]


def test_on_share_counts_only_judged_frames() -> None:
    on, off, unknown = int(LightStatus.ON), int(LightStatus.OFF), int(LightStatus.UNKNOWN)
    assert on_share(np.array([on, off, unknown, -1, on])) == pytest.approx(2 / 3)
    assert on_share(np.array([unknown, -1])) == 0.0


@needs_bag
def test_a_look_held_still_repeats_one_crop_and_keeps_the_timing() -> None:
    track = _night_track(load_checkpoint(DEFAULT_WEIGHTS).model)
    still = held_still(track, 7)
    assert len(still) == len(track) and still.crops.shape == track.crops.shape
    assert (still.crops == track.crops[7]).all()
    assert (still.stamps_ns == track.stamps_ns).all() and (still.mask == track.mask).all()
    assert not (track.crops == track.crops[7]).all()  # the bag's vehicle does change


@needs_bag
@pytest.mark.parametrize("offset, expected", [(+12.0, True), (-12.0, False)])
def test_each_look_is_read_as_the_model_moved_by_an_offset_publishes(offset: float,
                                                                     expected: bool) -> None:
    model = load_checkpoint(DEFAULT_WEIGHTS).model.eval()
    add_on_offsets(model, light_offsets("brake", offset))
    track = _night_track(model)
    with torch.no_grad():
        reads = still_look_reads(model, track, "brake", every=40)
    assert len(reads) == len(range(0, len(track), 40))
    assert reads == [expected] * len(reads)


def test_a_task_that_is_not_a_light_and_a_step_below_1_are_refused() -> None:
    with pytest.raises(ConfigError, match="every"):
        still_look_reads(None, None, every=0)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="task must be one of brake, left, right"):
        still_look_reads(None, None, task="intent")  # type: ignore[arg-type]
