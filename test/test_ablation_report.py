"""The ablation table reads each run's evaluation and training summaries."""

import json

import pytest

from signal_light_node.errors import SignalLightError
from signal_light_node.training import ablation_report


def _fake_run(root, f1, brake, frame_steps, lane_steps):
    (root / "test_eval").mkdir(parents=True)
    summary = {"intent_macro_f1": f1, "brake_accuracy": brake, "intent_fp_rate": 0.1,
               "intent_fn_rate": 0.2, "lights_fp_rate": 0.3, "lights_fn_rate": None}
    (root / "test_eval" / "metrics.json").write_text(json.dumps({
        "no_grace": {"summary": summary}, "grace": {"summary": summary},
        "data_brief": {"split": "s", "seed": 9, "n_sequences": 3, "n_observations": 30}}))
    for stage, steps in (("frames", frame_steps), ("lanes", lane_steps)):
        (root / stage).mkdir()
        (root / stage / "summary.json").write_text(json.dumps({"steps": steps,
                                                               "wall_seconds": 120.0}))


def test_report_has_one_row_per_run_with_its_figures(tmp_path):
    _fake_run(tmp_path / "a", 0.5, 0.75, 100, 10)
    _fake_run(tmp_path / "b", 0.25, 0.5, 100, 10)
    out = tmp_path / "report" / "ablations.md"
    assert ablation_report.main([f"full={tmp_path / 'a'}", f"no_attention={tmp_path / 'b'}",
                                 "--out", str(out), "--command", "x.sh"]) == 0
    text = out.read_text()
    assert "`x.sh`" in text and "seed 9" in text
    rows = [line for line in text.splitlines() if line.startswith("| full") or
            line.startswith("| no_attention")]
    assert rows[0].startswith("| full | 100 + 10 | 4 | 50.0 % | 75.0 % | 10.0 % | 20.0 % |")
    assert rows[1].startswith("| no_attention | 100 + 10 | 4 | 25.0 % | 50.0 %")
    assert rows[0].endswith("| 30.0 % | – |")
    saved = json.loads(out.with_suffix(".json").read_text())
    assert [r["name"] for r in saved] == ["full", "no_attention"]


def test_missing_evaluation_is_a_clear_error(tmp_path):
    with pytest.raises(SignalLightError, match="metrics.json"):
        ablation_report.load_run("full", tmp_path)
