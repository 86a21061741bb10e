"""``scripts/transfer_report.py`` scores every set, hard negatives included, under the one
intent filter it is given: a candidate's visibility hold and brake sight reach each evaluate
run and the engine that replays the hard negatives."""

from types import SimpleNamespace

import signal_light_node.runtime.engine as engine_module
import signal_light_node.tools.hard_negatives as negatives_module
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from script_loader import SCRIPTS, load_script


def _script():
    return load_script("transfer_report")


def test_visibility_hold_reaches_every_evaluate_run(tmp_path):
    report = _script()
    held = report.evaluate_options(report.parse_args(
        ["--out", str(tmp_path), "--filter-visibility-confirm", "0.2", "--threads", "1",
         "--filter-brake-sight", "rear"]))
    assert held == ["--threads", "1", "--filter-visibility-confirm", "0.2",
                    "--filter-brake-sight", "rear"]
    plain = report.evaluate_options(report.parse_args(["--out", str(tmp_path)]))
    default = IntentFilterConfig()  # the node's, unless told otherwise
    assert plain[-4:] == ["--filter-visibility-confirm", f"{default.visibility_confirm_s:g}",
                          "--filter-brake-sight", default.brake_sight]
    raw = report.evaluate_options(report.parse_args(["--out", str(tmp_path),
                                                     "--no-intent-filter"]))
    assert raw[-1] == "--no-intent-filter"


def test_visibility_hold_reaches_the_hard_negatives_engine(tmp_path, monkeypatch):
    report = _script()
    seen = []

    def engine(path, **overrides):
        held = overrides["intent_filter"]
        seen.append((held.visibility_confirm_s, held.brake_sight))
        return "engine"

    monkeypatch.setattr(engine_module, "engine_from_checkpoint", engine)
    monkeypatch.setattr(negatives_module, "false_lights",
                        lambda bag, eng, out: SimpleNamespace(judged=1, blinker_on=0.0,
                                                              brake_on=0.0, images=1))
    figures = report.hard_negatives(tmp_path / "model.pt", tmp_path, 0.3)
    assert set(figures) == set(negatives_module.HARD_NEGATIVE_BAGS)
    assert seen == [(0.3, "model")] * len(negatives_module.HARD_NEGATIVE_BAGS)
    seen.clear()
    report.hard_negatives(tmp_path / "model.pt", tmp_path, 0.2, "rear")
    assert seen == [(0.2, "rear")] * len(negatives_module.HARD_NEGATIVE_BAGS)


def test_the_committed_bags_are_scored_as_the_replay_test_bounds_them():
    """The sixth condition: each committed training-renderer bag is a set of its own, and
    the bounds are the replay test's."""
    report = _script()
    import test_replay

    assert report.COMMITTED_BAG_BOUNDS == {"brake_acc": test_replay.MIN_BRAKE_ACCURACY,
                                           "intent_f1": test_replay.MIN_INTENT_MACRO_F1}
    assert all((SCRIPTS.parent / bag).is_dir() for bag in report.COMMITTED_BAGS)
