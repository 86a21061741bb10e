"""Streaming evaluation: warm-up and grace-window rules, and the evaluate command's files."""

import json

import cv2
import numpy as np
import pytest
import torch

from signal_light_node.cli import main
from signal_light_node.crops import CropConfig
from signal_light_node.labels import TASKS, Intent
from signal_light_node.model import ModelConfig, build_model, save_checkpoint
from signal_light_node.training.evaluation import (
    EvalSettings,
    evaluate_tracks,
    grace_mask,
    warmup_mask,
)
from signal_light_node.training.sources import TrackSequence

TINY = {"input_size": 16, "attention_channels": [4, 4, 4], "backbone_channels": [8, 16],
        "lstm_hidden": [8, 8], "head_channels": 4, "head_grid": 2, "fc_hidden": 16}


class CountingModel:
    """Fake model: its state counts the steps of each track; intent turns LEFT at 16."""

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
    res = evaluate_tracks(model, [make_track("a"), make_track("b", masked=[3])], s,
                          progress=False)
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


def test_evaluate_command_writes_reports(tmp_path, capsys):
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
    from signal_light_node.bagio import open_bag
    from signal_light_node.synth_bag import write_scene_bag
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
