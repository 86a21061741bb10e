"""``scripts/transfer_report.py`` scores every set, hard negatives included, under the one
intent filter it is given: a candidate's visibility hold reaches each evaluate run and the
engine that replays the hard negatives."""

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import signal_light_node.runtime.engine as engine_module
import signal_light_node.tools.hard_negatives as negatives_module
from signal_light_node.runtime.intent_filter import IntentFilterConfig

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "transfer_report.py"


def _script():
    spec = importlib.util.spec_from_file_location("transfer_report", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_visibility_hold_reaches_every_evaluate_run(tmp_path):
    report = _script()
    held = report.evaluate_options(report.parse_args(
        ["--out", str(tmp_path), "--filter-visibility-confirm", "0.2", "--threads", "1"]))
    assert held == ["--threads", "1", "--filter-visibility-confirm", "0.2"]
    plain = report.evaluate_options(report.parse_args(["--out", str(tmp_path)]))
    default = IntentFilterConfig.visibility_confirm_s  # the node's, unless told otherwise
    assert plain[-2:] == ["--filter-visibility-confirm", f"{default:g}"]
    raw = report.evaluate_options(report.parse_args(["--out", str(tmp_path),
                                                     "--no-intent-filter"]))
    assert raw[-1] == "--no-intent-filter"


def test_visibility_hold_reaches_the_hard_negatives_engine(tmp_path, monkeypatch):
    report = _script()
    seen = []

    def engine(path, **overrides):
        seen.append(overrides["intent_filter"].visibility_confirm_s)
        return "engine"

    monkeypatch.setattr(engine_module, "engine_from_checkpoint", engine)
    monkeypatch.setattr(negatives_module, "false_lights",
                        lambda bag, eng, out: SimpleNamespace(judged=1, blinker_on=0.0,
                                                              brake_on=0.0, images=1))
    figures = report.hard_negatives(tmp_path / "model.pt", tmp_path, 0.3)
    assert set(figures) == set(negatives_module.HARD_NEGATIVE_BAGS)
    assert seen == [0.3] * len(negatives_module.HARD_NEGATIVE_BAGS)
