"""Scoring on your own data (issue 26, item 3): per-track flicker, UNKNOWN share and the
reliability diagrams of ``signal-light evaluate`` on a labelled bag."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from signal_light_node.cli import main
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import LightOutcomes, reliability_report
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LIGHT_TASKS, TASKS, LightStatus
from signal_light_node.model import DEFAULT_WEIGHTS, load_checkpoint

BAG = Path(__file__).resolve().parents[1] / "bags" / "day_street"
OFF, ON, UNK = int(LightStatus.OFF), int(LightStatus.ON), int(LightStatus.UNKNOWN)
BRAKE = TASKS.index("brake")


def _track(name, brake_true):
    n = len(brake_true)
    labels = np.zeros((n, len(TASKS)), np.int64)
    labels[:, BRAKE] = brake_true
    return TrackSequence(track_id=name, labels=labels, mask=np.ones(n, bool),
                         stamps_ns=np.arange(n, dtype=np.int64) * 100_000_000,
                         box_size=np.full(n, 40.0), occlusion=np.zeros(n))


def test_flicker_table_and_unknown_share_by_hand():
    scorer = TrackScorer(EvalSettings(warmup_frames=0, warmup_seconds=0.0))
    # Track a: truth OFF OFF ON ON UNKNOWN (1 true change among the labelled frames,
    # UNKNOWN truth counts as a class too: 2); published ON OFF ON UNKNOWN OFF (4 changes).
    a = _track("a", [OFF, OFF, ON, ON, UNK])
    pred_a = np.zeros((5, len(TASKS)), np.int64)
    pred_a[:, BRAKE] = [ON, OFF, ON, UNK, OFF]
    # Track b: truth ON throughout, published ON ON UNKNOWN (1 change).
    b = _track("b", [ON, ON, ON])
    pred_b = np.zeros((3, len(TASKS)), np.int64)
    pred_b[:, BRAKE] = [ON, ON, UNK]
    scorer.add(a, pred_a)
    scorer.add(b, pred_b)
    result = scorer.result()
    flicker = result["flicker"]
    assert [row["track"] for row in flicker] == ["a", "b"]  # worst first
    assert flicker[0]["brake"] == {"predicted": 4, "true": 2}
    assert flicker[0]["excess"] == 2
    assert flicker[1]["brake"] == {"predicted": 1, "true": 0}
    assert flicker[1]["excess"] == 1
    # Brake frames with a true OFF/ON: 4 of a, 3 of b; UNKNOWN published on 1 + 1 of them.
    assert result["unknown_share"]["brake"] == {"unknown": 2, "frames": 7, "share": 2 / 7}
    # left/right: truth OFF everywhere (8 frames), never UNKNOWN.
    assert result["unknown_share"]["left"] == {"unknown": 0, "frames": 8, "share": 0.0}
    assert result["unknown_share"]["overall"] == {"unknown": 2, "frames": 23, "share": 2 / 23}
    assert result["calibration"] == {}  # no probabilities given


def test_unknown_by_view_names_the_view_the_unknowns_came_with():
    scorer = TrackScorer(EvalSettings(warmup_frames=0, warmup_seconds=0.0))
    view = TASKS.index("view")
    # Truth: a rear view (BEHIND) throughout, brake ON; the view head calls the last two
    # frames FRONT, and brake is published UNKNOWN on one BEHIND frame and both FRONT ones.
    track = _track("a", [ON, ON, ON, ON])
    pred = np.zeros((4, len(TASKS)), np.int64)
    pred[:, BRAKE] = [ON, UNK, UNK, UNK]
    pred[:, view] = [0, 0, 2, 2]
    scorer.add(track, pred)
    rows = {(r["true_view"], r["published_view"]): r
            for r in scorer.result()["unknown_by_view"]}
    # Three heads' frames with a true OFF/ON: brake ON, left and right OFF (never UNKNOWN).
    assert rows[("BEHIND", "FRONT")] == {"true_view": "BEHIND", "published_view": "FRONT",
                                         "frames": 6, "unknown": 2, "share": 2 / 6,
                                         "share_of_unknown": 2 / 3}
    assert rows[("BEHIND", "BEHIND")]["unknown"] == 1 and rows[("BEHIND", "BEHIND")]["frames"] == 6
    assert scorer.result()["unknown_by_view"][0]["published_view"] == "FRONT"  # most first
    unbroken = TrackScorer(EvalSettings(warmup_frames=0, warmup_seconds=0.0))
    unbroken.add(track, pred, breakdowns=False)
    assert unbroken.result()["unknown_by_view"] == []
    with pytest.raises(ConfigError, match="views of"):
        LightOutcomes().add("brake", [ON, OFF], [ON, OFF], views=(["BEHIND"], ["BEHIND"]))


def test_reliability_report_by_hand():
    probs = np.array([[0.9, 0.1, 0.0], [0.85, 0.15, 0.0], [0.3, 0.7, 0.0], [0.35, 0.65, 0.0]])
    labels = np.array([OFF, ON, ON, ON])
    rep = reliability_report(probs, labels, bins=5)
    counts = [b["count"] for b in rep["bins"]]
    assert counts == [0, 0, 0, 2, 2]  # 0.65, 0.7 in [0.6, 0.8); 0.85, 0.9 in [0.8, 1]
    assert rep["bins"][3]["accuracy"] == 1.0 and rep["bins"][4]["accuracy"] == 0.5
    assert rep["ece"] == pytest.approx(0.5 * abs(1.0 - 0.675) + 0.5 * abs(0.5 - 0.875))
    outcomes = LightOutcomes()
    outcomes.add("brake", labels, probs.argmax(1), probs)
    assert outcomes.calibration()["brake"]["ece"] == pytest.approx(
        reliability_report(probs, labels)["ece"])


def test_evaluate_on_a_committed_bag_writes_flicker_unknown_and_reliability(tmp_path):
    out = tmp_path / "eval"
    assert main(["evaluate", "--bags", str(BAG), "--out", str(out), "--no-progress"]) == 0
    result = json.loads((out / "metrics.json").read_text())
    assert result["flicker"] and {"track", "excess", "brake", "left", "right", "intent"} \
        <= set(result["flicker"][0])
    excess = [row["excess"] for row in result["flicker"]]
    assert excess == sorted(excess, reverse=True)
    assert {row["track"] for row in result["flicker"]} == \
        set(result["switches"]["brake"]["per_track"])
    share = result["unknown_share"]
    assert set(share) == set(LIGHT_TASKS) | {"overall"}
    assert share["overall"]["frames"] == sum(share[t]["frames"] for t in LIGHT_TASKS) > 0
    by_view = result["unknown_by_view"]
    assert sum(r["frames"] for r in by_view) == share["overall"]["frames"]
    assert sum(r["unknown"] for r in by_view) == share["overall"]["unknown"]
    markdown = (out / "metrics.md").read_text()
    assert "Flicker per track" in markdown and "UNKNOWN published" in markdown
    assert "Where the UNKNOWNs come from" in markdown
    for light in LIGHT_TASKS:
        image = cv2.imread(str(out / f"reliability_{light}.png"))
        assert image is not None and image.ndim == 3 and image.shape[0] > 100
        assert 0.0 <= result["calibration"][light]["ece"] <= 1.0
        assert sum(b["count"] for b in result["calibration"][light]["bins"]) == \
            result["calibration"][light]["frames"] == share[light]["frames"]


def test_replay_on_a_committed_bag_prints_flicker_unknown_and_ece(tmp_path, capsys):
    assert main(["replay", str(BAG), "-o", str(tmp_path / "out"), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "Flicker per track" in printed and "UNKNOWN published" in printed
    assert "| overall |" in printed and "ECE" in printed


def test_split_by_track_id_is_deterministic_and_whole_tracks():
    from signal_light_node.errors import ConfigError
    from signal_light_node.training.holdout import split_by_track_id

    tracks = [_track(f"bag:{i % 5}", [OFF] * 3) for i in range(10)]  # 5 IDs, 2 tracks each
    kept, held = split_by_track_id(tracks, 0.3, seed=7)
    assert len({t.track_id for t in held}) == 2 and len(held) == 4  # round(0.3 x 5) IDs
    assert not {t.track_id for t in kept} & {t.track_id for t in held}
    again = split_by_track_id(tracks, 0.3, seed=7)[1]
    assert [t.track_id for t in again] == [t.track_id for t in held]
    assert split_by_track_id(tracks, 0.0, seed=7) == (tracks, [])
    with pytest.raises(ConfigError, match="holdout-fraction"):
        split_by_track_id(tracks[:1], 0.5, seed=7)


def test_holdout_fraction_accepts_pool_tracks_and_needs_some_labelled_tracks(tmp_path):
    from signal_light_node.errors import ConfigError
    from signal_light_node.training.options import TrainOptions

    common = dict(out=tmp_path, max_steps=1, init_from=Path("default"), holdout_fraction=0.5)
    TrainOptions(pools=[tmp_path / "split"], **common).validate()  # a --pool split counts
    with pytest.raises(ConfigError, match="--bags, --ucm or --pool"):
        TrainOptions(**common).validate()


def test_select_by_published_needs_whole_labelled_validation_tracks(tmp_path):
    from signal_light_node.errors import ConfigError
    from signal_light_node.training.options import TrainOptions

    common = dict(out=tmp_path, max_steps=1, init_from=Path("default"), select_by="published")
    TrainOptions(bags=[BAG], val_fraction=0.3, **common).validate()
    for wrong in (dict(bags=[BAG], val_fraction=0.0), dict(val_fraction=0.3),
                  dict(bags=[BAG], val_fraction=0.3, val_split=tmp_path / "split")):
        with pytest.raises(ConfigError, match="--select-by published"):
            TrainOptions(**wrong, **common).validate()
    with pytest.raises(ConfigError, match="--select-by must be one of"):
        TrainOptions(bags=[BAG], **dict(common, select_by="loss")).validate()


def test_select_by_published_keeps_the_step_the_node_would_publish_best(tmp_path):
    """Each validation's score is the mean of intent macro-F1 and brake F1 as the node's
    filter publishes them on the validation tracks, and best.pt is the step that scored
    highest by it (a large learning rate makes the steps differ)."""
    out = tmp_path / "ft"
    assert main(["train", "--out", str(out), "--init-from", "default", "--bags", str(BAG),
                 "--select-by", "published", "--val-fraction", "0.3", "--heads-only",
                 "--lr", "0.05", "--steps", "4", "--batch", "2", "--seq-len", "4",
                 "--workers", "0", "--threads", "1", "--val-every", "2", "--no-progress"]) == 0
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [0, 2, 4]
    for r in records:
        published = r["published"]
        assert published["scored_frames"] > 0
        expected = 0.5 * ((published["intent_macro_f1"] or 0.0) + (published["brake_f1"] or 0.0))
        assert r["score"] == pytest.approx(expected, abs=1e-5)
    best = max(records, key=lambda r: r["score"])  # the first of equal scores, as the run
    assert load_checkpoint(out / "best.pt").meta["training"]["step"] == best["step"]



def test_train_trunk_from_moves_the_last_trunk_blocks_and_the_output_layers_only(tmp_path, capsys):
    out = tmp_path / "ft"
    common = ["train", "--init-from", "default", "--bags", str(BAG), "--heads-only", "--lr", "0.05",
              "--steps", "2", "--batch", "2", "--seq-len", "4", "--workers", "0", "--threads", "1",
              "--no-progress"]
    assert main(common + ["--out", str(out), "--train-trunk-from", "9"]) == 0
    before = load_checkpoint(DEFAULT_WEIGHTS).model.state_dict()
    after = load_checkpoint(out / "last.pt").model.state_dict()
    moved = {name for name, value in before.items() if not torch.equal(value, after[name])}
    assert any(name.startswith("trunk.blocks.9.") for name in moved)
    assert any(name.startswith("trunk.blocks.10.") for name in moved)
    assert any(".heads." in name for name in moved)
    for name in moved:  # nothing earlier in the trunk, and no batch-norm statistics
        assert name.startswith(("trunk.blocks.9.", "trunk.blocks.10.")) or ".heads." in name \
            or ".fc." in name, name
        assert not name.endswith(("running_mean", "running_var")), name
    # Refused in one line: without --heads-only, or naming no block.
    assert main(common[:-1] + ["--out", str(tmp_path / "a"), "--train-trunk-from", "11",
                               "--no-progress"]) == 2
    assert "--train-trunk-from must name a block 0..10" in capsys.readouterr().err
    no_heads = [a for a in common if a != "--heads-only"]
    assert main(no_heads + ["--out", str(tmp_path / "b"), "--train-trunk-from", "9"]) == 2
    assert "goes with --heads-only" in capsys.readouterr().err


def test_train_trunk_norms_moves_the_trunks_norm_scales_and_the_brake_head_only(tmp_path, capsys):
    out = tmp_path / "ft"
    common = ["train", "--init-from", "default", "--bags", str(BAG), "--heads-only", "--lr", "0.05",
              "--steps", "2", "--batch", "2", "--seq-len", "4", "--workers", "0", "--threads", "1",
              "--no-progress", "--head-tasks", "brake"]
    assert main(common + ["--out", str(out), "--train-trunk-norms"]) == 0
    model = load_checkpoint(DEFAULT_WEIGHTS).model
    norms = {f"trunk.{name}" for name, m in model.trunk.named_modules()
             if isinstance(m, torch.nn.BatchNorm2d)}
    before, after = model.state_dict(), load_checkpoint(out / "last.pt").model.state_dict()
    moved = {name for name, value in before.items() if not torch.equal(value, after[name])}
    moved_norms = {name.rsplit(".", 1)[0] for name in moved if name.startswith("trunk.")}
    assert len(moved_norms) > len(norms) // 2 and moved_norms <= norms  # the stem's too
    for name in moved:  # the norms' scale and shift, and the brake head: nothing else
        assert name.endswith((".weight", ".bias")), name
        assert name.rsplit(".", 1)[0] in norms or ".heads.brake." in name, name
    no_heads = [a for a in common if a not in ("--heads-only", "--head-tasks", "brake")]
    assert main(no_heads + ["--out", str(tmp_path / "b"), "--train-trunk-norms"]) == 2
    assert "--train-trunk-norms goes with --heads-only" in capsys.readouterr().err


def test_train_holdout_fraction_writes_a_before_after_report(tmp_path, capsys):
    out = tmp_path / "ft"
    assert main(["train", "--out", str(out), "--init-from", "default", "--bags", str(BAG),
                 "--holdout-fraction", "0.3", "--steps", "2", "--batch", "2", "--seq-len", "4",
                 "--workers", "0", "--threads", "1", "--val-every", "2", "--no-progress"]) == 0
    report = json.loads((out / "adapt_report.json").read_text())
    assert len(report["held_out_tracks"]) == 2  # round(0.3 x 8 track IDs of day_street)
    for key in ("before", "after"):
        for figure in ("intent_macro_f1", "brake_f1", "unknown_share"):
            assert report[key][figure] is None or 0.0 <= report[key][figure] <= 1.0
        assert report[key]["scored_frames"] > 0
    assert report["before"]["scored_frames"] == report["after"]["scored_frames"]
    assert "before" in (out / "adapt_report.md").read_text()
    assert "held-out tracks" in capsys.readouterr().out
