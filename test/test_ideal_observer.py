"""The ideal causal observer: the ceiling of every metric under the evaluation's rules."""

import json

import numpy as np
import torch

from signal_light_node.cli import main
from signal_light_node.labels import TASKS, Intent
from signal_light_node.model import ModelConfig, build_model, save_checkpoint
from signal_light_node.evaluation.ideal_observer import ideal_observer, longest_dark_run

from test_evaluate import TINY

ON, OFF, UNKNOWN = 1, 0, 2
LEFT, RIGHT, INTENT, BRAKE = (TASKS.index(t) for t in ("left", "right", "intent", "brake"))


def test_longest_dark_run_counts_only_while_switched_on():
    lit = np.array([1, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1])
    state = np.array([1] * 8 + [0] * 5 + [1])
    # 2, then 3 dark frames inside the episode; the 5 after it are a switch-off, not a blink
    assert longest_dark_run(lit, state) == 3
    assert longest_dark_run(np.array([1, 0, 0]), np.array([1, 1, 1])) == 0  # one flash only
    hidden = np.array([1, 2, 2, 2, 2, 1])  # a hidden lamp counts as not lit
    assert longest_dark_run(hidden, np.ones(6, int)) == 4


def test_observer_holds_a_blink_through_its_dark_phases_and_lags_a_switch_off():
    n = 20
    labels = np.zeros((n, len(TASKS)), np.int64)
    lit = np.zeros_like(labels)
    labels[:14, LEFT] = ON                      # switched on for 14 frames, then off
    lit[:14, LEFT] = [1, 1, 0, 0] * 3 + [1, 1]  # lit 2, dark 2
    labels[5:8, RIGHT] = lit[5:8, RIGHT] = UNKNOWN  # right lamp hidden for 3 frames
    labels[:, BRAKE] = lit[:, BRAKE] = ON
    labels[:14, INTENT] = int(Intent.LEFT)
    pred = ideal_observer(labels, lit, fps=10.0)
    # dark phases inside the blink stay ON; after the last flash (frame 13) the observer
    # waits one dark run plus a frame before it may say OFF: frames 14-16 are its lag
    assert pred[:17, LEFT].tolist() == [ON] * 17
    assert pred[17:, LEFT].tolist() == [OFF] * 3
    assert pred[5:8, RIGHT].tolist() == [UNKNOWN] * 3
    assert (pred[:, BRAKE] == ON).all()
    assert pred[:17, INTENT].tolist() == [int(Intent.LEFT)] * 17
    assert pred[17:, INTENT].tolist() == [int(Intent.OFF)] * 3


def test_evaluate_scores_the_ideal_observer(tmp_path, capsys):
    from signal_light_node.data.split import write_split

    config = ModelConfig().replace(**TINY)
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(config), config)
    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=4, seq_len=40, crop=config.crop_config(),
                full_tracks=True, progress=False, sizes=[(160, 96)], vehicles=(1, 2))
    out = tmp_path / "ceiling"
    rc = main(["evaluate", "--ideal-observer", "--checkpoint", str(ckpt), "--split", str(split),
               "--out", str(out), "--no-progress"])
    assert rc == 0
    result = json.loads((out / "metrics.json").read_text())
    assert result["ideal_observer"] is True and result["checkpoint"] == "the ideal observer"
    assert "frames judged" in (out / "metrics.md").read_text()
    for key in ("no_grace", "grace"):
        assert result[key]["summary"]["brake_accuracy"] == 1.0
        assert result[key]["overall"]["view"]["accuracy"] == 1.0
    # bags carry no per-frame lamp labels: refused with the reason
    rc = main(["evaluate", "--ideal-observer", "--checkpoint", str(ckpt), "--bags",
               str(tmp_path / "none"), "--out", str(tmp_path / "x")])
    assert rc == 2
    assert "needs --split or --synthetic-seed" in capsys.readouterr().err
