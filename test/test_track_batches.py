"""Frame and lane batches from in-memory tracks, and the trainer's two modes that use them."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from signal_light_node.runtime.crops import CropConfig
from signal_light_node.data.split import SequenceSplit, write_split
from signal_light_node.data.stream import PAD_LABEL
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.training.track_batches import FrameBatches, LaneBatches
from signal_light_node.training.loop import Trainer
from signal_light_node.training.loss import batch_loss_warmup
from signal_light_node.training.options import TrainOptions

from test_training import TINY

SIZE = 4


def numbered_track(number: int, length: int, fps: float = 10.0) -> TrackSequence:
    """A track whose crop pixels and brake label say (track number, frame index)."""
    crops = np.zeros((length, SIZE, SIZE, 3), np.uint8)
    crops[..., 0] = number
    crops[..., 1] = np.arange(length)[:, None, None]
    labels = np.zeros((length, 5), np.int64)
    labels[:, 1] = np.arange(length) % 3
    stamps = (np.arange(length) * 1e9 / fps).astype(np.int64)
    return TrackSequence(track_id=f"t{number}", labels=labels, mask=np.ones(length, bool),
                         stamps_ns=stamps, box_size=np.full(length, 50.0),
                         occlusion=np.zeros(length), crops=crops)


def test_lanes_continue_each_track_and_flag_new_ones():
    tracks = [numbered_track(n, length) for n, length in ((1, 7), (2, 5), (3, 4))]
    batches = iter(LaneBatches(tracks, lanes=2, seq_len=3, seed=0))
    expected_next = {}  # lane -> (track number, next frame index)
    for k in range(12):
        batch = next(batches)
        crops, mask, reset = batch["crops"].numpy(), batch["mask"].numpy(), batch["reset"].numpy()
        assert crops.shape == (2, 3, SIZE, SIZE, 3) and batch["labels"].shape == (2, 3, 5)
        if k == 0:
            assert reset.all()
        for lane in range(2):
            number, first = int(crops[lane, 0, 0, 0, 0]), int(crops[lane, 0, 0, 0, 1])
            if reset[lane]:
                assert first == 0  # a new track starts at its first frame ...
            else:
                assert (number, first) == expected_next[lane]  # ... else the same one goes on
            n = int(mask[lane].sum())
            assert n >= 1 and mask[lane, :n].all() and not mask[lane, n:].any()
            assert (crops[lane, :n, 0, 0, 1] == np.arange(first, first + n)).all()
            assert (batch["labels"][lane, n:] == PAD_LABEL).all()
            assert batch["start"][lane] == first
            expected_next[lane] = (number, first + n)


def test_frame_batches_draw_single_labelled_frames():
    tracks = [numbered_track(n, 6) for n in (1, 2)]
    # a frame without a crop is never served
    tracks[1].mask[:] = [True, False, True, False, True, False]
    batch = next(iter(FrameBatches(tracks, batch=40, seed=3)))
    crops, labels = batch["crops"].numpy(), batch["labels"].numpy()
    assert crops.shape == (40, 1, SIZE, SIZE, 3) and batch["mask"].all()
    numbers, frames = crops[:, 0, 0, 0, 0], crops[:, 0, 0, 0, 1]
    assert set(numbers) == {1, 2}
    assert set(frames[numbers == 2]) <= {0, 2, 4}
    assert (labels[:, 0, 1] == frames % 3).all()  # each frame keeps its own label


def test_lanes_rehearse_their_share_of_tracks():
    labelled = [numbered_track(n, 2) for n in (1, 2)]
    rehearsed = [numbered_track(n, 2) for n in (7, 8)]
    for share in (0.25, 0.5):
        batches = iter(LaneBatches(labelled, lanes=4, seq_len=2, seed=0, rehearse=rehearsed,
                                   rehearse_share=share))
        # each 2-frame track fills one batch, so every batch takes four new tracks
        numbers = np.concatenate([next(batches)["crops"].numpy()[:, 0, 0, 0, 0]
                                  for _ in range(300)])
        assert set(numbers) == {1, 2, 7, 8}
        assert abs(np.isin(numbers, (7, 8)).mean() - share) < 0.05


def test_batchers_need_tracks_in_memory():
    track = numbered_track(1, 3)
    track.crops = None
    with pytest.raises(ConfigError, match="in memory"):
        LaneBatches([track], lanes=1, seq_len=2)


@pytest.fixture(scope="module")
def tiny_pool(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pool") / "pool"
    write_split(out, seed=5, n_sequences=6, seq_len=20, crop=CropConfig(size=16),
                full_tracks=True, progress=False)
    return out


def pool_options(out: Path, pool: Path, **changes) -> TrainOptions:
    opts = dict(out=out, max_steps=4, batch=3, seq_len=5, lr=1e-3, model=dict(TINY),
                pools=[pool], val_fraction=0.34, val_every=2, workers=0, progress=False,
                threads=1, seed=1)
    opts.update(changes)
    return TrainOptions(**opts)


@pytest.mark.parametrize("mode", ["frames", "lanes"])
def test_trainer_runs_on_a_pool(tmp_path, tiny_pool, mode):
    trainer = Trainer(pool_options(tmp_path / mode, tiny_pool, mode=mode))
    summary = trainer.run()
    assert summary["steps"] == 4 and summary["last_validation"] is not None
    if mode == "lanes":  # the lanes' state is carried: one (h, c) row per lane
        assert trainer.lanes.carried is not None and trainer.lanes.carried[0][0].shape[0] == 3
    else:
        assert trainer.lanes.carried is None
    meta = torch.load(tmp_path / mode / "best.pt", weights_only=False)
    assert "pool" in str(meta)


def test_bf16_lanes_carry_a_float32_state(tmp_path, tiny_pool):
    trainer = Trainer(pool_options(tmp_path / "bf16", tiny_pool, mode="lanes",
                                   precision="bf16"))
    assert trainer.run()["steps"] == 4
    assert {x.dtype for h, c in trainer.lanes.carried for x in (h, c)} == {torch.float32}


def test_lane_state_is_zeroed_where_a_track_starts(tmp_path, tiny_pool):
    trainer = Trainer(pool_options(tmp_path / "z", tiny_pool, mode="lanes"))
    lanes, model, device = trainer.lanes, trainer.model, trainer.device
    assert lanes.begin(torch.tensor([False, False, False]), model, device)[0][0].abs().sum() == 0
    lanes.carried = tuple((torch.ones_like(h), torch.ones_like(c))
                          for h, c in model.initial_state(3))
    state = lanes.begin(torch.tensor([True, False, True]), model, device)
    for h, c in state:
        for x in (h, c):
            assert x[0].abs().sum() == 0 and x[2].abs().sum() == 0 and (x[1] == 1).all()


def test_lane_warmup_counts_from_the_track_start(tmp_path, tiny_pool):
    trainer = Trainer(pool_options(tmp_path / "w", tiny_pool, mode="lanes", loss_warmup=4,
                                   loss_warmup_seconds=0.0))
    batch = {"labels": torch.zeros(3, 3, 5), "start": torch.tensor([0, 3, 6]),
             "meta": {"fps": [10.0, 10.0, 10.0]}}
    opts = trainer.opts
    warm = batch_loss_warmup(batch, opts.loss_warmup, opts.loss_warmup_seconds,
                             per_frame=False, device=trainer.device)
    assert warm.tolist() == [4, 1, 0]  # max(0, 4 - first)


def test_pool_cropped_for_another_model_is_refused(tmp_path, tiny_pool):
    with pytest.raises(ConfigError, match="pool .* was cropped with"):
        Trainer(pool_options(tmp_path / "c", tiny_pool, mode="lanes", model={}))


@pytest.mark.parametrize("mode", ["windows", "lanes"])
def test_rehearsed_tracks_only_train(tmp_path, tiny_pool, mode):
    rehearse = tmp_path / "rehearse"
    shutil.copytree(tiny_pool, rehearse)
    trainer = Trainer(pool_options(tmp_path / "r", tiny_pool, mode=mode, rehearse=[rehearse],
                                   rehearse_share=0.5))
    # held-out and validation draws see the labelled pool's six tracks only ...
    kept = trainer.train_tracks + trainer.val_tracks + trainer.holdout_tracks
    assert len(kept) == 6 and trainer.val_tracks
    # ... and the batches also come from the rehearsed pool's six
    data = trainer.loader.dataset
    rehearsed = data.rehearse if mode == "lanes" else data.parts[-1].tracks
    assert len(rehearsed) == 6 and not {id(t) for t in rehearsed} & {id(t) for t in kept}
    assert trainer.run()["steps"] == 4


def test_rehearsal_is_checked(tmp_path, tiny_pool):
    from signal_light_node.cli import build_parser
    from signal_light_node.commands.train import options_from_args

    args = build_parser(["train"]).parse_args(
        ["train", "--out", str(tmp_path), "--pool", str(tiny_pool), "--rehearse", "r1",
         "--rehearse", "r2", "--rehearse-share", "0.3"])
    opts = options_from_args(args)
    assert opts.rehearse == [Path("r1"), Path("r2")] and opts.rehearse_share == 0.3
    with pytest.raises(ConfigError, match="beside labelled tracks"):
        TrainOptions(out=tmp_path, max_steps=1, rehearse=[tiny_pool]).validate()
    with pytest.raises(ConfigError, match="windows or lanes"):
        TrainOptions(out=tmp_path, max_steps=1, mode="frames", pools=[tiny_pool],
                     rehearse=[tiny_pool]).validate()
    with pytest.raises(ConfigError, match="rehearse-share must be in"):
        TrainOptions(out=tmp_path, max_steps=1, pools=[tiny_pool], rehearse=[tiny_pool],
                     rehearse_share=1.0).validate()


def test_modes_are_checked(tmp_path, tiny_pool):
    with pytest.raises(ConfigError, match="needs in-memory tracks"):
        TrainOptions(out=tmp_path, max_steps=1, mode="lanes").validate()
    with pytest.raises(ConfigError, match="mode must be one of"):
        TrainOptions(out=tmp_path, max_steps=1, mode="clips", pools=[tiny_pool]).validate()
    with pytest.raises(ConfigError, match="cannot mix"):
        TrainOptions(out=tmp_path, max_steps=1, mode="frames", pools=[tiny_pool],
                     synthetic_fraction=0.5).validate()


def test_frames_can_learn_what_each_frame_shows(tmp_path, tiny_pool):
    with pytest.raises(ConfigError, match="frame-targets lit is for --mode frames"):
        TrainOptions(out=tmp_path, max_steps=1, mode="lanes", pools=[tiny_pool],
                     frame_targets="lit").validate()
    with pytest.raises(ConfigError, match="frame targets must be one of"):
        TrainOptions(out=tmp_path, max_steps=1, mode="frames", pools=[tiny_pool],
                     frame_targets="glow").validate()
    split = SequenceSplit(tiny_pool)
    trainer = Trainer(pool_options(tmp_path / "lit", tiny_pool, mode="frames",
                                   frame_targets="lit", val_fraction=0.0, val_split=tiny_pool))
    for track, index in zip(trainer.train_tracks, range(len(split))):
        item = split[index]
        np.testing.assert_array_equal(track.labels, item["lit_labels"])
    assert all(np.array_equal(v["labels"], split[i]["lit_labels"])
               for i, v in enumerate(trainer.val_items))
    # The pool has blinks, so the two kinds of labels really differ somewhere.
    assert any(not np.array_equal(split[i]["labels"], split[i]["lit_labels"])
               for i in range(len(split)))
    assert trainer.run()["steps"] == 4


def test_a_split_without_lit_labels_is_refused_for_lit_targets(tmp_path, tiny_pool):
    old = tmp_path / "old"
    shutil.copytree(tiny_pool, old)
    for shard in old.glob("shard_*.npz"):  # as written before lit labels existed
        with np.load(shard) as data:
            arrays = {k: data[k] for k in data.files if k != "lit_labels"}
        np.savez_compressed(shard, **arrays)
    assert "lit_labels" not in SequenceSplit(old)[0]
    Trainer(pool_options(tmp_path / "state", old, mode="frames"))  # logical states still work
    with pytest.raises(ConfigError, match="render it again"):
        Trainer(pool_options(tmp_path / "lit", old, mode="frames", frame_targets="lit"))
