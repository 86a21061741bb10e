"""``signal-light calibrate --fit-filter``: the node's output filter chosen on labelled
tracks within a switch bound, written as node parameters and used for the held-out
report."""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from signal_light_node.cli import main
from signal_light_node.model import load_checkpoint
from signal_light_node.ros.params import DetectorParams
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from signal_light_node.training.filter_fit import (FILTER_GRID, cli_options, fit_filter,
                                                   node_parameters, parameter_file)
from signal_light_node.training.unknown_bias import FILTER_META_KEY

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "day_street"


def _result(score: float, intent_switches: float, brake_switches: "float | None" = 1.0) -> dict:
    return {"score": score, "switches": {"intent": {"ratio": intent_switches},
                                         "brake": {"ratio": brake_switches}}}


def test_the_best_setting_within_the_switch_bound_is_kept() -> None:
    results = {IntentFilterConfig(): _result(0.60, 1.2),
               IntentFilterConfig(hold_s=0.8): _result(0.70, 1.4),
               IntentFilterConfig(hold_s=0.4): _result(0.90, 2.0),  # flickers: refused
               IntentFilterConfig(brake_hysteresis=1.0): _result(0.65, 1.0, None)}
    grid = [{"hold_s": 0.8}, {"hold_s": 0.4}, {"brake_hysteresis": 1.0}]
    fit = fit_filter(results.__getitem__, lambda r: r["score"], grid)
    assert fit.changes == {"hold_s": 0.8} and fit.score == 0.70
    assert fit.default_score == 0.60 and (fit.tried, fit.allowed) == (3, 2)
    assert fit.config == IntentFilterConfig(hold_s=0.8)


def test_defaults_that_already_flicker_set_the_bound_and_win_ties() -> None:
    results = {IntentFilterConfig(): _result(0.60, 2.0),
               IntentFilterConfig(hold_s=0.8): _result(0.60, 1.9)}
    fit = fit_filter(results.__getitem__, lambda r: r["score"], [{"hold_s": 0.8}])
    assert fit.changes == {} and fit.allowed == 1  # 1.9x is within the defaults' 2.0x


def test_every_grid_setting_is_a_node_parameter_file() -> None:
    declared = {f.name for f in fields(DetectorParams)}
    for changes in FILTER_GRID:
        IntentFilterConfig(**changes)  # valid
        params = yaml.safe_load(parameter_file(changes))["signal_light_detector"]
        assert set(params["ros__parameters"]) <= declared
        assert DetectorParams(**params["ros__parameters"]).intent_filter_config == \
            IntentFilterConfig(**changes)
    assert yaml.safe_load(parameter_file({}))["signal_light_detector"]["ros__parameters"] == {}
    assert node_parameters({"enabled": False, "hold_s": 0.4}) == {
        "intent_filter": False, "filter_hold_s": 0.4}


def test_the_printed_options_set_evaluate_to_the_fitted_filter() -> None:
    from signal_light_node.cli import build_parser
    from signal_light_node.commands.options import intent_filter_from_args

    others = {"enabled": False, "flash_min_evidence": 0.2, "confirm_s": 0.1, "on_threshold": 0.6}
    for changes in FILTER_GRID + [others]:
        args = build_parser(["evaluate"]).parse_args(["evaluate", "--out", "OUT"]
                                                     + cli_options(changes))
        assert intent_filter_from_args(args) == IntentFilterConfig(**changes), changes


@pytest.mark.skipif(not (BAG / "metadata.yaml").exists(), reason="bags/day_street is not committed")
@pytest.mark.usefixtures("one_torch_thread")
def test_calibrate_fits_the_filter_and_reports_with_it(tmp_path: Path, capsys) -> None:
    out = tmp_path / "cal.pt"
    assert main(["calibrate", str(BAG), "--grid", "0", "--on-grid", "0", "--fit-filter",
                 "--holdout-fraction", "0.5", "--out", str(out), "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    info = load_checkpoint(out).meta[FILTER_META_KEY]
    assert info["tried"] == len(FILTER_GRID) and 0 < info["allowed"] <= info["tried"]
    assert info["score"] >= info["default_score"]
    params = yaml.safe_load(out.with_suffix(".filter.yaml").read_text())
    chosen = params["signal_light_detector"]["ros__parameters"]
    assert chosen == node_parameters(info["changes"])
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert report["after"]["filter"] == IntentFilterConfig(**info["changes"]).describe()
    assert "filter fitted" in printed and "the filter" in out.with_suffix(".report.md").read_text()
