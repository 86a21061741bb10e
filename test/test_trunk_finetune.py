"""The trunk recipe's per-frame stage: frames in memory, which blocks learn, its checkpoint."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from signal_light_node.data.split import write_split
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import roc_auc
from signal_light_node.labels import TASKS, LightStatus, View
from signal_light_node.model.config import ModelConfig, trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.training import frame_pool, trunk_finetune, trunk_recipe
from signal_light_node.training.frame_pool import FramePool, sample_batch
from signal_light_node.training.trunk_finetune import (FROZEN, frame_scores, load_trunk_weights,
                                                       rank_loss, set_trainable)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    out = tmp_path_factory.mktemp("frames") / "pool_1"
    write_split(out, seed=7, n_sequences=3, seq_len=12, crop=trunk_config().crop_config(),
                full_tracks=True, progress=False)
    return out


def test_roc_auc_ranks_and_says_none_without_both_sides():
    assert roc_auc([0.9, 0.8], [0.1, 0.2]) == 1.0
    assert roc_auc([0.1], [0.9]) == 0.0
    assert roc_auc([0.5, 0.2], [0.4, 0.1]) == 0.75
    assert roc_auc([], [0.3]) is None


def test_pool_holds_every_frame_with_its_track_slices(split):
    pool = FramePool.load([split])
    assert pool.n_tracks == 3 and len(pool) == pool.offsets[-1]
    targets = pool.targets(np.arange(len(pool)))
    assert targets.shape == (len(pool), 4)
    lit = pool.lit_labels[:, TASKS.index("left")]
    assert np.array_equal(targets[:, 1], lit)
    assert np.array_equal(targets[:, 3], pool.labels[:, TASKS.index("view")])


def test_joining_shards_gives_their_concatenation_and_lets_each_go():
    parts = [np.full((n, 2, 3), n, np.uint8) for n in (3, 1, 2)]
    want = np.concatenate(parts)
    joined = frame_pool.join_releasing(parts)
    assert parts == [] and joined.dtype == np.uint8 and np.array_equal(joined, want)


def test_a_folder_that_is_no_split_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="not a rendered split"):
        FramePool.load([tmp_path])


def test_mirroring_swaps_the_blinkers_and_side_views():
    crops = np.zeros((2, 8, 8, 3), np.uint8)
    crops[:, :, :2] = 200  # bright on the image's left
    labels = np.zeros((2, len(TASKS)), np.int64)
    labels[:, TASKS.index("view")] = int(View.LEFT)
    lit = np.zeros((2, len(TASKS)), np.int64)
    lit[:, TASKS.index("left")] = int(LightStatus.ON)
    lit[:, TASKS.index("right")] = int(LightStatus.UNKNOWN)
    rng = np.random.default_rng(0)
    seen = set()
    for _ in range(20):
        out, out_lit, out_labels = frame_pool._augment_track(crops, lit, labels, rng, augment=0.0)
        mirrored = out[0, 0, -1, 0] == 200
        seen.add(bool(mirrored))
        want_left = LightStatus.UNKNOWN if mirrored else LightStatus.ON
        assert out_lit[0, TASKS.index("left")] == want_left
        assert out_labels[0, TASKS.index("view")] == (View.RIGHT if mirrored else View.LEFT)
    assert seen == {True, False}


def test_a_batch_takes_frames_of_many_tracks(split):
    pool = FramePool.load([split])
    x, y = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=1.0)
    assert x.shape == (12, 3, 64, 64) and x.dtype == torch.uint8
    assert y.shape == (12, 4) and int(y.min()) >= -1


def test_white_balance_reaches_the_batches_camera(split):
    pool = FramePool.load([split])
    plain, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=1.0)
    again, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=1.0,
                            white_balance=0.0)
    tinted, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3,
                             augment=1.0, white_balance=0.3)
    assert torch.equal(plain, again)
    assert not torch.equal(plain, tinted)


def test_grey_tracks_lose_their_colour_and_none_keeps_the_stream(split):
    pool = FramePool.load([split])
    plain, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=1.0)
    again, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=1.0,
                            grey=0.0)
    grey, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=0.0,
                           grey=1.0)
    coloured, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3,
                               augment=0.0)
    assert torch.equal(plain, again)
    assert torch.equal(grey[:, 0], grey[:, 1]) and torch.equal(grey[:, 1], grey[:, 2])
    assert not torch.equal(coloured[:, 0], coloured[:, 2])


def test_grey_frames_keep_a_pixels_luma():
    bgr = np.array([[[0, 0, 255], [255, 255, 255], [10, 200, 30]]], np.uint8)
    out = frame_pool.grey_frames(bgr)
    assert out.shape == bgr.shape and out.dtype == np.uint8
    assert out[0, :, 0].tolist() == [76, 255, 128]  # 0.299*255; 255; 1.14+117.4+8.97
    assert (out[..., 0] == out[..., 2]).all()


def test_value_grey_keeps_a_pixels_largest_channel_whatever_its_hue():
    # An orange and a yellow lamp at full power: luma tells them apart, value does not.
    bgr = np.array([[[20, 90, 255], [20, 190, 255], [40, 50, 60]]], np.uint8)
    value = frame_pool.grey_frames(bgr, "value")
    assert value[0, :, 1].tolist() == [255, 255, 60]
    assert (value[..., 0] == value[..., 2]).all()
    luma = frame_pool.grey_frames(bgr)
    assert luma[0, 0, 0] < luma[0, 1, 0]


def test_an_unknown_grey_mode_is_refused():
    with pytest.raises(ConfigError, match="grey mode"):
        frame_pool.grey_frames(np.zeros((1, 1, 3), np.uint8), "hue")


def test_value_grey_reaches_the_batches(split):
    pool = FramePool.load([split])
    luma, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=0.0,
                           grey=1.0)
    value, _ = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3,
                            augment=0.0, grey=1.0, grey_mode="value")
    assert torch.equal(value[:, 0], value[:, 2]) and not torch.equal(luma, value)


def test_a_partner_is_the_same_tracks_earlier_frame_clipped_at_its_start():
    offsets = np.array([0, 5, 12])
    index = np.array([0, 2, 4, 5, 6, 11])
    assert frame_pool.partner_index(offsets, index, 3).tolist() == [0, 0, 1, 5, 5, 8]


def test_pairs_stack_each_frame_with_its_partner_through_one_camera(split):
    pool = FramePool.load([split])
    x, y = sample_batch(pool, np.random.default_rng(1), tracks=4, per_track=3, augment=0.0,
                        pair_gap=2)
    assert x.shape == (12, 6, 64, 64) and y.shape == (12, 4)
    arrays = frame_pool.frame_arrays(pool, stride=1, pair_gap=2)
    first = pool.offsets[:-1]
    # A track's first frame has no earlier one: its partner is itself.
    assert np.array_equal(arrays["crops"][first, ..., :3], arrays["crops"][first, ..., 3:])
    later = first[0] + 3
    assert np.array_equal(arrays["crops"][later, ..., 3:], pool.crops[later - 2])
    # Without augmentation every stacked pair is a frame of the pool and the one before it.
    frames = {pool.crops[i].tobytes(): i for i in range(len(pool))}
    for pair in x.permute(0, 2, 3, 1).numpy():
        now, before = frames.get(pair[..., :3].tobytes()), frames.get(pair[..., 3:].tobytes())
        if now is None:  # mirrored (mirroring is drawn even without augmentation)
            now = frames[pair[:, ::-1, :3].tobytes()]
            before = frames[pair[:, ::-1, 3:].tobytes()]
        assert before == frame_pool.partner_index(pool.offsets, np.array([now]), 2)[0]


@pytest.mark.parametrize("train_from,blocks", [(FROZEN, 0), (8, 3), (0, 11), (-1, 11)])
def test_train_from_chooses_the_blocks_that_learn(train_from, blocks):
    model = build_model(trunk_config())
    params = set_trainable(model.trunk, train_from)
    learning = {name.split(".")[1] for name, p in model.trunk.named_parameters()
                if p.requires_grad and name.startswith("blocks.")}
    assert len(learning) == blocks
    stem = any(p.requires_grad for p in model.trunk.stem.parameters())
    assert stem == (train_from == -1)
    assert len(params) == sum(p.requires_grad for p in model.trunk.parameters())
    with pytest.raises(ConfigError, match="train-from"):
        set_trainable(model.trunk, 12)


def test_frame_scores_rank_each_lamp_over_its_seen_frames():
    targets = np.array([[1, 0, 2, 0], [0, 1, 2, 1], [1, 0, 2, 2]])
    on = np.array([[0.1, 0.8, 0.1], [0.7, 0.2, 0.1], [0.2, 0.3, 0.5]])
    probs = [on, on[::-1], on, np.eye(4)[[0, 1, 3]]]
    scores = frame_scores(probs, targets)
    assert scores["brake_auc"] == 1.0 and scores["right_auc"] is None
    assert scores["brake_unknown"] == pytest.approx(1 / 3)
    assert scores["view_acc"] == pytest.approx(2 / 3)


def test_stage_trains_resumes_and_hands_its_trunk_to_the_temporal_recipe(split, tmp_path):
    out = tmp_path / "frames"
    args = ["--out", str(out), "--pool", str(split), "--val", str(split), "--tracks", "2",
            "--per-track", "2", "--val-every", "2", "--threads", "1", "--train-from", "9"]
    assert trunk_finetune.main(args + ["--steps", "2"]) == 0
    assert trunk_finetune.main(args + ["--steps", "3", "--resume"]) == 0
    history = [json.loads(line) for line in (out / "history.jsonl").read_text().splitlines()]
    assert [h["step"] for h in history] == [2, 3]
    saved = torch.load(out / "last.pt", weights_only=False)
    fresh = build_model(trunk_config(), pretrained=True)
    fresh_trunk = fresh.trunk.state_dict()
    changed = {k for k, v in saved["trunk"].items() if not torch.equal(v, fresh_trunk[k])}
    assert changed and all(k.startswith(("blocks.9.", "blocks.10.")) for k in changed)

    model = build_model(trunk_config(), pretrained=True)
    assert load_trunk_weights(model, out / "last.pt")["train_from"] == 9
    assert torch.equal(model.trunk.blocks[10].project[0].weight,
                       saved["trunk"]["blocks.10.project.0.weight"])
    run = tmp_path / "run"
    assert trunk_recipe.main(["--out", str(run), "--pool", str(split), "--val", str(split),
                              "--batch", "2", "--seq-len", "8", "--val-every", "2", "--steps", "2",
                              "--threads", "1", "--trunk-weights", str(out / "best.pt")]) == 0
    meta = torch.load(run / "last.pt", weights_only=False)["meta"]
    assert meta["trunk_weights"]["train_from"] == 9


def _two_steps(split, out, *options: str) -> int:
    """A two-step run of the per-frame stage on ``split`` (later options win)."""
    return trunk_finetune.main(["--out", str(out), "--pool", str(split), "--val", str(split),
                                "--tracks", "2", "--per-track", "2", "--val-every", "2",
                                "--threads", "1", "--train-from", "10", "--steps", "2",
                                *options])


def test_the_stage_trains_on_pairs_and_its_trunk_loads_as_any_other(split, tmp_path):
    out = tmp_path / "pairs"
    assert _two_steps(split, out, "--pair-gap", "3") == 0
    saved = torch.load(out / "best.pt", weights_only=False)
    width = build_model(trunk_config()).trunk.out_channels
    assert saved["head"]["conv.0.weight"].shape[1] == 2 * width  # frame and difference
    assert load_trunk_weights(build_model(trunk_config()), out / "best.pt")["step"] == 2
    with pytest.raises(SystemExit):
        trunk_finetune.main(["--out", str(out), "--pool", str(split), "--val", str(split),
                             "--pair-gap", "-1"])


def _lamp_logits(on_minus_off):
    """Per-frame logits of the four targets whose lamps score ``on_minus_off`` (ON over OFF)."""
    score = torch.tensor(on_minus_off, dtype=torch.float32)
    lamp = torch.stack([torch.zeros_like(score), score, torch.zeros_like(score)], 1)
    return [lamp.clone().requires_grad_(True) for _ in range(3)] + [torch.zeros(len(score), 4)]


def _targets(lamp_states):
    rows = torch.tensor(lamp_states, dtype=torch.int64)[:, None].repeat(1, 4)
    rows[:, 3] = 0
    return rows


def test_the_ranking_asks_a_lit_frame_to_score_above_the_same_tracks_unlit_one():
    # One track of two frames: lit, then unlit (LightStatus ON = 1, OFF = 0).
    targets = _targets([1, 0])
    right = rank_loss(_lamp_logits([3.0, -3.0]), targets, group=2).item()
    wrong = rank_loss(_lamp_logits([-3.0, 3.0]), targets, group=2).item()
    assert right < 0.01 < 5.0 < wrong
    logits = _lamp_logits([0.0, 0.0])
    rank_loss(logits, targets, group=2).backward()
    assert float(logits[1].grad[0, 1]) < 0 < float(logits[1].grad[1, 1])  # lit up, unlit down


def test_the_ranking_never_compares_two_tracks_nor_unknown_frames():
    # Track 0 lit twice, track 1 unlit twice: no pair within a track, however they score;
    # an UNKNOWN frame (2) pairs with nothing.
    assert float(rank_loss(_lamp_logits([-5.0, -5.0, 5.0, 5.0]), _targets([1, 1, 0, 0]),
                           group=2)) == 0.0
    assert float(rank_loss(_lamp_logits([-5.0, 5.0]), _targets([2, 0]), group=2)) == 0.0


def test_the_stage_trains_with_the_ranking_and_refuses_a_negative_weight(split, tmp_path):
    out = tmp_path / "ranked"
    assert _two_steps(split, out, "--per-track", "4", "--rank-weight", "1") == 0
    assert load_trunk_weights(build_model(trunk_config()), out / "last.pt")["step"] == 2
    with pytest.raises(SystemExit):
        trunk_finetune.main(["--out", str(out), "--pool", str(split), "--val", str(split),
                             "--rank-weight", "-1"])


def test_the_stage_goes_on_from_an_earlier_trunk(split, tmp_path):
    first, second = tmp_path / "first", tmp_path / "second"
    assert _two_steps(split, first) == 0
    # A frozen trunk (--train-from 11) keeps exactly what it started from.
    assert _two_steps(split, second, "--init-trunk", str(first / "last.pt"),
                      "--train-from", str(FROZEN)) == 0
    started = torch.load(first / "last.pt", weights_only=False)["trunk"]
    kept = torch.load(second / "last.pt", weights_only=False)["trunk"]
    fresh = build_model(trunk_config(), pretrained=True).trunk.state_dict()
    weight = "blocks.10.project.0.weight"
    assert not torch.equal(started[weight], fresh[weight])
    assert all(torch.equal(kept[k], v) for k, v in started.items())
    with pytest.raises(ConfigError, match="not a per-frame"):
        torch.save({"x": 1}, tmp_path / "bad.pt")
        _two_steps(split, tmp_path / "third", "--init-trunk", str(tmp_path / "bad.pt"))


@pytest.mark.parametrize("share", ["-0.1", "1.5"])
def test_a_grey_share_outside_zero_to_one_is_refused(split, tmp_path, share, capsys):
    with pytest.raises(SystemExit):
        trunk_finetune.main(["--out", str(tmp_path / "frames"), "--pool", str(split),
                             "--val", str(split), "--grey", share])
    assert "--grey must be a share in [0, 1]" in capsys.readouterr().err
    assert not (tmp_path / "frames").exists()


@pytest.fixture(scope="module")
def one_step_run(split, tmp_path_factory):
    """The directory of a one-step per-frame run on ``split`` (64-pixel crops)."""
    out = tmp_path_factory.mktemp("one_step") / "frames"
    assert trunk_finetune.main(["--out", str(out), "--pool", str(split), "--val", str(split),
                                "--tracks", "2", "--per-track", "2", "--steps", "1",
                                "--threads", "1"]) == 0
    return out


def test_a_trunk_of_another_shape_is_refused(one_step_run, tmp_path):
    out = one_step_run
    other = build_model(trunk_config(trunk_stride=8))
    with pytest.raises(ConfigError, match="trunk_stride"):
        load_trunk_weights(other, out / "best.pt")
    with pytest.raises(ConfigError, match="not a per-frame"):
        torch.save({"x": 1}, tmp_path / "bad.pt")
        load_trunk_weights(other, tmp_path / "bad.pt")


def test_a_trunk_of_another_crop_size_loads_only_when_asked(one_step_run):
    """A trunk trained on 64-pixel crops goes on at 96 pixels with ``any_size``; without
    it the size is refused, and the stride is refused either way."""
    out = one_step_run
    larger = build_model(trunk_config(input_size=96))
    with pytest.raises(ConfigError, match="input_size"):
        load_trunk_weights(larger, out / "best.pt")
    load_trunk_weights(larger, out / "best.pt", any_size=True)
    trained = torch.load(out / "best.pt", map_location="cpu", weights_only=False)["trunk"]
    assert all(torch.equal(v, trained[k]) for k, v in larger.trunk.state_dict().items())
    with pytest.raises(ConfigError, match="trunk_stride"):
        load_trunk_weights(build_model(trunk_config(trunk_stride=8)), out / "best.pt",
                           any_size=True)


def test_a_model_files_trunk_loads_as_a_per_frame_one(tmp_path):
    """A run can start from the shipped file's trunk on a machine without the per-frame
    file: the trunk it loads is the shipped one, fingerprint and all."""
    from signal_light_node.model import DEFAULT_WEIGHTS
    from signal_light_node.training.feature_cache import trunk_fingerprint

    shipped = torch.load(DEFAULT_WEIGHTS, map_location="cpu", weights_only=False)
    model = build_model(ModelConfig.from_dict(shipped["config"]))
    before = trunk_fingerprint(model)
    load_trunk_weights(model, DEFAULT_WEIGHTS)
    assert trunk_fingerprint(model) == shipped["meta"]["trunk_fingerprint"] != before
    weight = "blocks.10.project.0.weight"
    assert torch.equal(model.trunk.state_dict()[weight], shipped["state_dict"]["trunk." + weight])
    torch.save({"format_version": 1, "config": shipped["config"], "state_dict": {}},
               tmp_path / "headless.pt")
    with pytest.raises(ConfigError, match="nor a model file with a trunk"):
        load_trunk_weights(model, tmp_path / "headless.pt")


def test_every_flag_the_recipe_script_passes_to_the_stage_exists():
    """scripts/train_trunk.sh calls this stage; a renamed flag would only fail hours in."""
    script = (Path(__file__).parents[1] / "scripts" / "train_trunk.sh").read_text()
    call = script[script.index("training.trunk_finetune"):]
    call = call[:call.index("\n", call.index('"${resume[@]}"'))]
    passed = set(re.findall(r"(--[a-z][a-z-]*)", call))
    known = {flag for action in trunk_finetune._parser()._actions
             for flag in action.option_strings}
    passed |= set(re.findall(r"init=\((--[a-z][a-z-]*)", script))  # set apart, then passed
    assert {"--pair-gap", "--white-balance", "--steps", "--rank-weight", "--init-trunk",
            "--trunk-lr-scale"} <= passed
    assert passed <= known, passed - known
