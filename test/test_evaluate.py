"""Streaming evaluation: warm-up and grace-window rules, and the evaluate command's files."""

import dataclasses
import json
import logging

import cv2
import numpy as np
import pytest
import torch

from signal_light_node.cli import main
from signal_light_node.runtime import flash_gate
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig
from signal_light_node.labels import TASKS, Intent
from signal_light_node.model import ModelConfig, build_model, save_checkpoint
from signal_light_node.evaluation.scoring import EvalSettings, grace_mask, warmup_mask
from signal_light_node.evaluation.streaming import evaluate_tracks, predict_track_batch
from signal_light_node.evaluation.tracks import TrackSequence

TINY = {"input_size": 16, "attention_channels": [4, 4, 4], "backbone_channels": [8, 16],
        "lstm_hidden": [8, 8], "head_channels": 4, "head_grid": 2, "fc_hidden": 16}


class CountingModel:
    """Fake model: its state counts the steps of each track; intent turns LEFT at 16."""

    config = ModelConfig(**TINY)

    def __init__(self):
        self.stepped = 0

    def eval(self):
        return self

    def initial_state(self, n):
        return ((torch.zeros(n, 1), torch.zeros(n, 1)),)

    def step(self, crops, state):
        h = state[0][0] + 1
        self.stepped += crops.shape[0]
        n = crops.shape[0]
        probs = {t: torch.zeros(n, k) for t, k in zip(TASKS, (5, 3, 3, 3, 4))}
        for t in TASKS:
            probs[t][:, 0] = 1.0
        left = (h[:, 0] >= 16)
        probs["intent"][left] = torch.tensor([0.0, 1.0, 0.0, 0.0, 0.0])
        return probs, ((h, state[0][1]),)


def make_track(name, n=30, fps=10.0, change_at=15, masked=()):
    labels = np.zeros((n, len(TASKS)), np.int64)
    labels[change_at:, 0] = int(Intent.LEFT)
    mask = np.ones(n, bool)
    mask[list(masked)] = False
    return TrackSequence(track_id=name, labels=labels, mask=mask,
                         stamps_ns=(np.arange(n) * 1e9 / fps).astype(np.int64),
                         box_size=np.full(n, 40.0), occlusion=np.zeros(n), lighting="day",
                         crops=np.zeros((n, 16, 16, 3), np.uint8))


def test_warmup_and_grace_masks_by_hand():
    s = EvalSettings(warmup_frames=10, warmup_seconds=1.0, grace_seconds=0.5)
    a = make_track("a")
    assert np.flatnonzero(warmup_mask(a, s)).tolist() == list(range(10, 30))
    # with frame 3 missing, frame 10 has only 9 observations before it
    b = make_track("b", masked=[3])
    assert np.flatnonzero(warmup_mask(b, s)).tolist() == list(range(11, 30))
    # the time rule dominates at 30 fps: 1 s = 30 frames
    fast = make_track("fast", n=40, fps=30.0)
    assert np.flatnonzero(warmup_mask(fast, s)).tolist() == list(range(30, 40))
    # grace: 0.5 s after the change at frame 15 = frames 15..19, only for intent
    assert np.flatnonzero(~grace_mask(a, 0, s)).tolist() == [15, 16, 17, 18, 19]
    assert grace_mask(a, 1, s).all()


def test_streaming_evaluation_counts_and_scores():
    s = EvalSettings(warmup_frames=10, warmup_seconds=1.0, grace_seconds=0.5, batch_tracks=2)
    model = CountingModel()
    # Track b misses frame 3, so its step counter lags by one and intent flips to LEFT at
    # frame 16 instead of 15: exactly one wrong frame, inside the grace window.
    # The raw model (filter off): the intent comes from the intent head alone.
    raw = IntentFilterConfig(enabled=False)
    res = evaluate_tracks(model, [make_track("a"), make_track("b", masked=[3])], s,
                          progress=False, intent_filter=raw)
    assert res["intent_filter"]["enabled"] is False
    # One change of the intent per track, predicted and true, after the warm-up.
    switches = res["switches"]["intent"]
    assert (switches["predicted"], switches["true"], switches["ratio"]) == (2, 2, 1.0)
    assert switches["per_track"] == {"a": {"predicted": 1, "true": 1},
                                     "b": {"predicted": 1, "true": 1}}
    assert res["switches"]["brake"] == {"predicted": 0, "true": 0, "ratio": None,
                                        "per_track": {"a": {"predicted": 0, "true": 0},
                                                      "b": {"predicted": 0, "true": 0}}}
    assert model.stepped == 59  # the masked frame is never stepped
    c = res["counts"]
    assert (c["tracks"], c["frames"], c["stepped"], c["scored"]) == (2, 60, 59, 39)
    assert c["warmup_excluded"] == 20
    assert c["grace_excluded"]["intent"] == 10 and c["grace_excluded"]["brake"] == 0
    strict = res["no_grace"]["overall"]["intent"]
    assert strict["n"] == 39 and strict["accuracy"] == pytest.approx(38 / 39)
    assert strict["fn_rate"] == pytest.approx(1 / 30) and strict["fp_rate"] == 0.0
    assert strict["confusion"][1][0] == 1
    graced = res["grace"]["overall"]["intent"]
    assert graced["n"] == 29 and graced["accuracy"] == 1.0
    assert res["grace"]["overall"]["brake"]["n"] == 39
    groups = res["no_grace"]["groups"]
    assert set(groups) == {"lighting", "view", "box_size", "occlusion"}
    assert groups["box_size"]["32-64px"]["intent"]["n"] == 39
    assert groups["view"]["BEHIND"]["intent"]["n"] == 39
    assert groups["occlusion"]["none"]["intent"]["n"] == 39


AMBER = (20, 150, 250)  # BGR


class BlinkModel(CountingModel):
    """Fake model: the left blinker's P(ON) is the crop's brightness, the rest OFF."""

    def step(self, crops, state):
        probs, new_state = super().step(crops, state)
        b = crops.mean(dim=(1, 2, 3)) * 0.98
        probs["left"] = torch.stack([0.98 - b, b, torch.full_like(b, 0.02)], dim=1)
        return probs, new_state


def blink_track(name, fps, n, masked=()):
    """A left blink at 1.5 Hz, 50 % duty, from 1 s to 3 s; labels as the node should say."""
    track = make_track(name, n=n, fps=fps, change_at=n, masked=masked)
    t = track.stamps_ns / 1e9
    lit = (t >= 1.0) & (t < 3.0) & (((t - 1.0) * 1.5) % 1.0 < 0.5)
    track.crops[lit] = AMBER  # a flash the flash gate sees (white has no lamp colour)
    return track


def test_evaluation_applies_the_engine_filter_with_each_tracks_stamps():
    tracks = [blink_track("slow", 10.0, 50, masked=[12]), blink_track("fast", 30.0, 150)]
    # The intent from the held blinkers: the hold over the tracks' stamps is what is tested.
    lights = IntentFilterConfig(intent_source="lights")
    preds = predict_track_batch(BlinkModel(), tracks, torch.device("cpu"), lights)
    for track, pred in zip(tracks, preds):
        filt = IntentFilter(lights)
        rows = filt.initial_rows(1)
        for i in np.flatnonzero(track.mask):
            b = track.crops[i].mean() / 255 * 0.98
            probs = {t: np.eye(k)[[0]] for t, k in zip(TASKS, (5, 3, 3, 3, 4))}
            probs["left"] = np.array([[0.98 - b, b, 0.02]])
            out = filt.step(probs, track.stamps_ns[i], rows,
                            flash_gate.lamp_levels(track.crops[i][None]))
            rows = out.rows
            assert pred[i].tolist() == [int(out.states[t][0]) for t in TASKS], (track.track_id, i)
        assert (pred[~track.mask] == -1).all()
        # Held through the blink: LEFT in one piece, at both frame rates.
        intent = pred[track.mask, 0]
        assert [k for k, prev in zip(intent[1:], intent) if k != prev] == [Intent.LEFT,
                                                                          Intent.OFF]
    raw = predict_track_batch(BlinkModel(), tracks, torch.device("cpu"),
                              IntentFilterConfig(enabled=False))
    # The raw model: the left blinker is ON in the lit frames only, flickering.
    lit = tracks[0].crops.reshape(len(tracks[0]), -1).max(axis=1) > 0
    valid = tracks[0].mask
    assert raw[0][valid, 2].tolist() == np.where(lit[valid], 1, 0).tolist()


def test_evaluate_command_writes_reports(tmp_path, capsys, caplog):
    from signal_light_node.data.split import write_split

    config = ModelConfig().replace(**TINY)
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(config), config, {"notes": "test"})
    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=3, seq_len=12, crop=config.crop_config(),
                full_tracks=True, progress=False, sizes=[(160, 96)], vehicles=(1, 2))
    out = tmp_path / "eval"
    rc = main(["evaluate", "--checkpoint", str(ckpt), "--split", str(split), "--out", str(out),
               "--warmup-frames", "2", "--warmup-seconds", "0", "--no-progress"])
    assert rc == 0
    result = json.loads((out / "metrics.json").read_text())
    assert {"checkpoint", "data", "settings", "counts", "no_grace", "grace"} <= set(result)
    assert result["counts"]["tracks"] == 3
    from signal_light_node.data.split import SequenceSplit

    lengths = [int(item["mask"].sum()) for item in SequenceSplit(split)]
    assert result["counts"]["stepped"] == sum(lengths)
    assert result["counts"]["scored"] == sum(max(0, n - 2) for n in lengths)
    for key in ("no_grace", "grace"):
        assert set(result[key]["overall"]) == set(TASKS)
        assert {"intent_macro_f1", "brake_accuracy", "intent_fp_rate", "intent_fn_rate"} <= \
            set(result[key]["summary"])
        assert set(result[key]["groups"]) == {"lighting", "view", "box_size", "occlusion"}
        assert np.asarray(result[key]["overall"]["intent"]["confusion"]).shape == (5, 5)
    md = (out / "metrics.md").read_text()
    assert "| task | frames |" in md and "Intent confusion matrix" in md and "By lighting" in md
    assert md in capsys.readouterr().out
    # What the node publishes is scored by default, with the switches counted.
    assert result["intent_filter"] == dataclasses.asdict(IntentFilterConfig())
    switches = result["switches"]["intent"]
    assert set(result["switches"]) == set(TASKS) and len(switches["per_track"]) == 3
    assert switches["predicted"] == sum(v["predicted"] for v in switches["per_track"].values())
    assert "Intent filter: on" in md and "Intent switches after the warm-up" in md
    assert "### Switches" in md and "Intent changes per track" in md
    # The raw model on request, with the filter's settings from the options.
    raw = tmp_path / "raw"
    assert main(["evaluate", "--checkpoint", str(ckpt), "--split", str(split), "--out", str(raw),
                 "--no-intent-filter", "--filter-hold", "0.5", "--no-progress"]) == 0
    raw_result = json.loads((raw / "metrics.json").read_text())
    assert raw_result["intent_filter"]["enabled"] is False
    assert raw_result["intent_filter"]["hold_s"] == 0.5
    assert "Intent filter: off" in (raw / "metrics.md").read_text()
    assert main(["evaluate", "--checkpoint", str(ckpt), "--split", str(split), "--out", str(raw),
                 "--filter-on-threshold", "1.5", "--no-progress"]) == 2
    assert "on_threshold" in capsys.readouterr().err
    # Geometry needs every box of a frame; a split keeps none, which is said, not hidden.
    with caplog.at_level(logging.WARNING, logger="signal_light_node.commands.evaluate"):
        assert main(["evaluate", "--checkpoint", str(ckpt), "--split", str(split), "--out",
                     str(raw), "--filter-blinker-sight", "geometry", "--no-progress"]) == 0
    assert "only bags keep them" in caplog.text
    assert json.loads((raw / "metrics.json").read_text())["intent_filter"]["blinker_sight"] \
        == "geometry"
    img = cv2.imread(str(out / "confusion_intent.png"))
    assert img is not None and img.shape[0] > 300
    assert (out / "confusion_intent_grace.png").is_file()


def test_evaluate_command_needs_one_data_source(tmp_path, capsys):
    config = ModelConfig().replace(**TINY)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(config), config)
    rc = main(["evaluate", "--checkpoint", str(ckpt), "--out", str(tmp_path / "e")])
    assert rc == 2
    assert "choose exactly one" in capsys.readouterr().err


def test_bag_tracks_and_evaluate_on_bags(tmp_path, capsys):
    from signal_light_node.io.bagio import open_bag
    from signal_light_node.synth.bag import write_scene_bag
    from signal_light_node.training.sources import load_bag_tracks

    bag = tmp_path / "scene"
    write_scene_bag(bag, seed=3, n_frames=15, width=160, height=96, n_vehicles=2)
    config = ModelConfig().replace(**TINY)
    tracks = load_bag_tracks(bag, config.crop_config(), lighting="dusk")
    # Ground truth straight from the bag: track -> list of label rows in stamp order.
    truth = {}
    with open_bag(bag) as reader:
        for m in reader.messages(["/ground_truth/vehicle_lights"]):
            for v in m.msg.vehicles:
                truth.setdefault(str(v.track_id), []).append(
                    [int(v.intent), int(v.brake.state), int(v.left_blinker.state),
                     int(v.right_blinker.state), int(v.view)])
    assert tracks and all(t.lighting == "dusk" for t in tracks)
    for t in tracks:
        rows = truth[t.track_id.split(":", 1)[1]]
        # every frame with a detection has its ground truth (the tracker may miss frames)
        assert 0 < len(t) <= len(rows)
        assert all(row in rows for row in t.labels.tolist())
        assert t.crops.shape == (len(t), 16, 16, 3) and np.all(np.diff(t.stamps_ns) > 0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(config), config)
    out = tmp_path / "eval"
    assert main(["evaluate", "--checkpoint", str(ckpt), "--bags", str(bag), "--out", str(out),
                 "--warmup-frames", "0", "--warmup-seconds", "0", "--no-progress"]) == 0
    result = json.loads((out / "metrics.json").read_text())
    assert result["counts"]["stepped"] == sum(int(t.mask.sum()) for t in tracks)
    assert result["counts"]["scored"] == result["counts"]["stepped"]
    assert set(result["no_grace"]["groups"]["lighting"]) == {"unknown"}
