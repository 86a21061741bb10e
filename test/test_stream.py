"""Tests of the training stream and the materialised splits (signal_light_node.data)."""

from __future__ import annotations

import json
from itertools import islice
from typing import List

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from signal_light_node.runtime.crops import CropConfig
from signal_light_node.data import SyntheticSequenceStream, collate_sequences
from signal_light_node.data.split import SequenceSplit, write_split
from signal_light_node.data.stream import PAD_LABEL, Item, jitter_colours, mirror_sequence
from signal_light_node.errors import ConfigError
from signal_light_node.labels import CLASS_NAMES, TASKS, Intent, LightStatus, View, intent_from_lights

T = 8
CROP = CropConfig(size=32, margin=0.15)
# Small, cheap scenes: the tests check behaviour, not variety.
SMALL = dict(sizes=((640, 360),), vehicles=(3, 4), fps=15.0)
COL = {task: i for i, task in enumerate(TASKS)}


def take(stream: SyntheticSequenceStream, n: int, worker_id: int = 0) -> List[Item]:
    return list(islice(stream.sequences(worker_id), n))


def assert_same_item(a: Item, b: Item) -> None:
    np.testing.assert_array_equal(a["crops"], b["crops"])
    np.testing.assert_array_equal(a["labels"], b["labels"])
    np.testing.assert_array_equal(a["lit_labels"], b["lit_labels"])
    np.testing.assert_array_equal(a["mask"], b["mask"])
    assert a["meta"].keys() == b["meta"].keys()
    for key, value in a["meta"].items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, b["meta"][key], err_msg=key)
            assert value.dtype == b["meta"][key].dtype, key
        else:
            assert value == b["meta"][key], key


def same_item(a: Item, b: Item) -> bool:
    try:
        assert_same_item(a, b)
    except AssertionError:
        return False
    return True


@pytest.fixture(scope="module")
def plain_items() -> List[Item]:
    return take(SyntheticSequenceStream(7, T, CROP, mirror_prob=0.0, **SMALL), 12)


def test_items_have_the_documented_shapes_and_types(plain_items):
    for item in plain_items:
        assert item["crops"].shape == (T, 32, 32, 3) and item["crops"].dtype == np.uint8
        assert item["labels"].shape == (T, len(TASKS)) and item["labels"].dtype == np.int64
        assert item["mask"].shape == (T,) and item["mask"].dtype == bool
        assert item["mask"].all()  # windows are full by default
        meta = item["meta"]
        assert meta["lighting"] in ("day", "dusk", "night")
        assert meta["box_size"].dtype == np.float32 and meta["box_size"].shape == (T,)
        assert (meta["box_size"] > 0).all()
        assert meta["occlusion"].dtype == np.float32 and meta["occlusion"].shape == (T,)
        assert ((meta["occlusion"] >= 0) & (meta["occlusion"] <= 1)).all()
        assert np.all(np.diff(meta["frame_index"]) > 0)  # consecutive observations, in order
        assert meta["fps"] == 15.0 and isinstance(meta["seed"], int)
        assert isinstance(meta["track_id"], str) and meta["track_id"]
        assert meta["mirrored"] is False
        assert item["crops"].any(axis=(1, 2, 3)).all()  # every observation is a real crop
    # One render serves several sequences: some scene seed recurs.
    seeds = [item["meta"]["seed"] for item in plain_items]
    assert len(set(seeds)) < len(seeds)


def test_labels_are_in_range_and_consistent(plain_items):
    labels = np.concatenate([item["labels"] for item in plain_items])
    lit = np.concatenate([item["lit_labels"] for item in plain_items])
    for rows in (labels, lit):
        for task, column in COL.items():
            assert rows[:, column].min() >= 0
            assert rows[:, column].max() < len(CLASS_NAMES[task])
        for row in rows:
            assert row[COL["intent"]] == intent_from_lights(row[COL["left"]], row[COL["right"]])
    # A frame shows a blinker lit only while it is on, and hides only what is hidden.
    for side in ("left", "right"):
        state, shown = labels[:, COL[side]], lit[:, COL[side]]
        assert not ((shown == LightStatus.ON) & (state != LightStatus.ON)).any()
        np.testing.assert_array_equal(shown == LightStatus.UNKNOWN, state == LightStatus.UNKNOWN)
    for task in ("brake", "view"):
        np.testing.assert_array_equal(lit[:, COL[task]], labels[:, COL[task]])


def test_same_seed_and_worker_repeat_others_differ():
    stream = SyntheticSequenceStream(3, T, CROP, mirror_prob=0.5, jitter=True, **SMALL)
    first = take(stream, 4)
    again = take(SyntheticSequenceStream(3, T, CROP, mirror_prob=0.5, jitter=True, **SMALL), 4)
    for a, b in zip(first, again):
        assert_same_item(a, b)
    other_worker = take(stream, 4, worker_id=1)
    other_rank = take(SyntheticSequenceStream(3, T, CROP, mirror_prob=0.5, jitter=True,
                                              rank=1, **SMALL), 4)
    other_seed = take(SyntheticSequenceStream(4, T, CROP, mirror_prob=0.5, jitter=True, **SMALL), 4)
    for others in (other_worker, other_rank, other_seed):
        assert not same_item(first[0], others[0])
        assert first[0]["meta"]["seed"] != others[0]["meta"]["seed"]


def test_dataloader_workers_draw_their_own_series():
    stream = SyntheticSequenceStream(11, T, CROP, mirror_prob=0.0, **SMALL)
    # spawn: a forked worker can deadlock in OpenCV's thread pool if the parent used it.
    loader = DataLoader(stream, batch_size=2, num_workers=2, collate_fn=collate_sequences,
                        multiprocessing_context="spawn")
    got = list(islice(iter(loader), 2))
    # DataLoader takes whole batches from its workers in turn.
    for batch, worker in zip(got, (0, 1)):
        expected = collate_sequences(take(stream, 2, worker_id=worker))
        for key in ("crops", "labels", "mask"):
            assert torch.equal(batch[key], expected[key])
        assert batch["meta"]["seed"] == expected["meta"]["seed"]
    assert not torch.equal(got[0]["crops"], got[1]["crops"])


def test_mirroring_a_forced_case():
    crops = np.zeros((3, 32, 32, 3), np.uint8)
    crops[:, :, :8] = 200  # bright stripe on the image's left
    labels = np.array([
        [Intent.LEFT, LightStatus.OFF, LightStatus.ON, LightStatus.OFF, View.FRONT],
        [Intent.RIGHT, LightStatus.ON, LightStatus.UNKNOWN, LightStatus.ON, View.LEFT],
        [PAD_LABEL] * 5,
    ], dtype=np.int64)
    item = {"crops": crops, "labels": labels, "mask": np.array([True, True, False]),
            "meta": {"mirrored": False}}
    assert "lit_labels" not in mirror_sequence(item)  # items from bags have none
    item["lit_labels"] = labels.copy()
    out = mirror_sequence(item)
    np.testing.assert_array_equal(out["lit_labels"], out["labels"])
    assert out["crops"][:, :, -8:].min() == 200 and out["crops"][:, :, :-8].max() == 0
    np.testing.assert_array_equal(out["labels"], [
        [Intent.RIGHT, LightStatus.OFF, LightStatus.OFF, LightStatus.ON, View.FRONT],
        [Intent.LEFT, LightStatus.ON, LightStatus.ON, LightStatus.UNKNOWN, View.RIGHT],
        [PAD_LABEL] * 5,
    ])
    assert out["meta"]["mirrored"] is True and item["meta"]["mirrored"] is False
    assert item["labels"][0, 0] == Intent.LEFT  # the input is untouched
    np.testing.assert_array_equal(mirror_sequence(out)["labels"], labels)


def test_stream_mirrors_rendered_sequences():
    plain = take(SyntheticSequenceStream(5, T, CROP, mirror_prob=0.0, **SMALL), 1)[0]
    flipped = take(SyntheticSequenceStream(5, T, CROP, mirror_prob=1.0, **SMALL), 1)[0]
    assert flipped["meta"]["mirrored"] is True
    np.testing.assert_array_equal(flipped["crops"], plain["crops"][:, :, ::-1])
    p, f = plain["labels"], flipped["labels"]
    np.testing.assert_array_equal(f[:, COL["left"]], p[:, COL["right"]])
    np.testing.assert_array_equal(f[:, COL["right"]], p[:, COL["left"]])
    np.testing.assert_array_equal(f[:, COL["brake"]], p[:, COL["brake"]])
    swap_intent = {0: 0, 1: 2, 2: 1, 3: 3, 4: 4}
    swap_view = {0: 0, 1: 3, 2: 2, 3: 1}
    assert [swap_intent[v] for v in p[:, COL["intent"]]] == list(f[:, COL["intent"]])
    assert [swap_view[v] for v in p[:, COL["view"]]] == list(f[:, COL["view"]])


def test_jitter_changes_colours_only():
    plain = take(SyntheticSequenceStream(5, T, CROP, mirror_prob=0.0, **SMALL), 2)
    jittered = take(SyntheticSequenceStream(5, T, CROP, mirror_prob=0.0, jitter=True, **SMALL), 2)
    for a, b in zip(plain, jittered):
        np.testing.assert_array_equal(a["labels"], b["labels"])
        assert b["crops"].dtype == np.uint8 and b["crops"].shape == a["crops"].shape
        assert not np.array_equal(a["crops"], b["crops"])
        # One global colour change: the images stay strongly correlated.
        corr = np.corrcoef(a["crops"].reshape(-1).astype(float), b["crops"].reshape(-1))[0, 1]
        assert corr > 0.8
    flat = np.full((2, 16, 16, 3), 100, np.uint8)
    out = jitter_colours(flat, np.random.default_rng(0))
    assert out.shape == flat.shape and (out == out[0, 0, 0]).all()


def test_full_tracks_are_padded_at_the_end():
    stream = SyntheticSequenceStream(9, 30, CROP, mirror_prob=0.0, full_tracks=True, **SMALL)
    items = take(stream, 5)
    assert all(item["crops"].shape[0] == 30 for item in items)
    for item in items:
        n = int(item["mask"].sum())
        assert 1 <= n <= 30 and item["mask"][:n].all()
        assert (item["labels"][n:] == PAD_LABEL).all()
        assert not item["crops"][n:].any() and (item["meta"]["frame_index"][n:] == -1).all()
        assert (item["meta"]["frame_index"][:n] < 30).all()  # one scene of 30 frames
    assert len({item["meta"]["track_id"] for item in items
                if item["meta"]["seed"] == items[0]["meta"]["seed"]}) > 1


def test_collate_stacks_and_pads():
    items = take(SyntheticSequenceStream(2, T, CROP, mirror_prob=0.0, **SMALL), 3)
    short = {**items[2], "crops": items[2]["crops"][:5], "labels": items[2]["labels"][:5],
             "mask": items[2]["mask"][:5]}
    batch = collate_sequences([items[0], items[1], short])
    assert batch["crops"].shape == (3, T, 32, 32, 3) and batch["crops"].dtype == torch.uint8
    assert batch["labels"].dtype == torch.int64 and batch["mask"].dtype == torch.bool
    assert batch["mask"][2].tolist() == [True] * 5 + [False] * 3
    assert (batch["labels"][2, 5:] == PAD_LABEL).all()
    assert torch.equal(batch["crops"][0], torch.from_numpy(items[0]["crops"]))
    assert batch["meta"]["track_id"] == [it["meta"]["track_id"] for it in items]
    with pytest.raises(ConfigError):
        collate_sequences([])


def test_bad_options_raise_config_error():
    for bad in (dict(seq_len=0), dict(mirror_prob=1.5), dict(vehicles=(3, 2)),
                dict(sizes=()), dict(size_weights=(1.0,)), dict(seed=-1),
                dict(min_observations=99), dict(scene_frames=5)):
        with pytest.raises(ConfigError):
            SyntheticSequenceStream(**{"seed": 0, "seq_len": T, **bad})


def test_split_round_trip_equals_the_stream(tmp_path):
    manifest_path = write_split(tmp_path / "val", seed=21, n_sequences=10, seq_len=T, crop=CROP,
                                shard_size=4, progress=False, **SMALL)
    manifest = json.loads(manifest_path.read_text())
    assert [s["count"] for s in manifest["shards"]] == [4, 4, 2]
    assert manifest["crop"] == {"size": 32, "margin": 0.15} and manifest["seed"] == 21
    for task in TASKS:
        assert sum(manifest["label_histogram"][task].values()) == manifest["n_observations"]
    split = SequenceSplit(tmp_path / "val")
    assert len(split) == 10 and split.crop == CROP and split.seq_len == T
    expected = take(SyntheticSequenceStream(21, T, CROP, mirror_prob=0.0, **SMALL), 10)
    for i in (0, 5, 9, 3, -1):  # out of order, across shards
        assert_same_item(split[i], expected[i])
    with pytest.raises(IndexError):
        split[10]
    batch = collate_sequences([split[0], split[1]])
    assert batch["crops"].shape == (2, T, 32, 32, 3)


def test_split_of_full_tracks_and_guards(tmp_path):
    write_split(tmp_path / "test", seed=4, n_sequences=6, seq_len=40, crop=CROP,
                full_tracks=True, progress=False, **SMALL)
    split = SequenceSplit(tmp_path / "test")
    expected = take(SyntheticSequenceStream(4, 40, CROP, mirror_prob=0.0, full_tracks=True,
                                            **SMALL), 6)
    for i in range(6):
        assert_same_item(split[i], expected[i])
    with pytest.raises(ConfigError, match="not empty"):
        write_split(tmp_path / "test", seed=4, n_sequences=2, seq_len=8, progress=False)
    with pytest.raises(ConfigError, match="augmentation"):
        write_split(tmp_path / "aug", seed=4, n_sequences=2, seq_len=8, mirror_prob=0.5)
    with pytest.raises(Exception, match="not a sequence split"):
        SequenceSplit(tmp_path / "missing")


def test_split_command_line(tmp_path, capsys):
    from signal_light_node.data.split import main

    assert main([str(tmp_path / "cli"), "--seed", "3", "--sequences", "2", "--seq-len", "6",
                 "--crop-size", "32", "--lighting", "night"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_sequences"] == 2 and summary["lighting"] == {"night": 2}
    assert len(SequenceSplit(tmp_path / "cli")) == 2
    assert main([str(tmp_path / "cli"), "--seed", "3", "--sequences", "2"]) == 2  # not empty
    # --oblique reaches the renderer and the manifest says so.
    assert main([str(tmp_path / "turned"), "--seed", "3", "--sequences", "2", "--seq-len", "6",
                 "--crop-size", "32", "--oblique", "0.5"]) == 0
    manifest = json.loads((tmp_path / "turned" / "manifest.json").read_text())
    assert manifest["stream"]["renderer_overrides"] == {"oblique": 0.5}
    assert main([str(tmp_path / "bad"), "--seed", "3", "--sequences", "2", "--oblique", "2"]) == 2


def test_options_that_never_give_a_sequence_fail_instead_of_looping(monkeypatch):
    import signal_light_node.data.stream as stream_module

    monkeypatch.setattr(stream_module, "MAX_EMPTY_SCENES", 2)
    hidden = SyntheticSequenceStream(0, 4, CROP, scene_frames=4, sizes=((320, 180),),
                                     renderer_overrides={"occluders": [(0, 0, 320, 180)]})
    with pytest.raises(ConfigError, match="2 scenes in a row"):
        take(hidden, 1)
