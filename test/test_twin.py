"""Tests of a split's twin in another style family (signal_light_node.data.twin)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from signal_light_node.data.split import SequenceSplit, write_split
from signal_light_node.data.twin import main, write_twin
from signal_light_node.errors import ConfigError
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.synth.lamps import HELD_OUT_FAMILY

CROP = CropConfig(size=32, margin=0.15, fill=True)
SMALL = dict(sizes=((640, 360),), vehicles=(3, 4), fps=15.0)


@pytest.fixture(scope="module")
def family_split(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "family"
    write_split(out, seed=5, n_sequences=3, seq_len=30, crop=CROP, full_tracks=True,
                progress=False, lighting="day",
                renderer_overrides={"family": HELD_OUT_FAMILY, "truth_rule": "function"},
                **SMALL)
    return out


def _arrays(split):
    items = [split[i] for i in range(len(split))]
    return {key: np.concatenate([item[key][item["mask"]] for item in items])
            for key in ("crops", "labels", "lit_labels")}


def test_the_twin_holds_the_same_scenes_in_other_colours(family_split, tmp_path):
    write_twin(family_split, tmp_path / "own", progress=False)
    a, b = SequenceSplit(family_split), SequenceSplit(tmp_path / "own")
    assert len(a) == len(b) == 3
    old, new = _arrays(a), _arrays(b)
    np.testing.assert_array_equal(old["labels"], new["labels"])
    np.testing.assert_array_equal(old["lit_labels"], new["lit_labels"])
    for i in range(3):
        for key in ("box_size", "lamp_design", "lighting", "track_id"):
            np.testing.assert_array_equal(a[i]["meta"][key], b[i]["meta"][key], err_msg=key)
    # The pixels differ: lamp colours and the camera's tone.
    assert np.abs(old["crops"].astype(int) - new["crops"]).mean() > 1.0
    stream = b.manifest["stream"]
    assert stream["renderer_overrides"] == {"truth_rule": "function"}
    assert stream["lighting"] == "day" and b.manifest["crop"]["fill"] is True


def test_a_twin_back_in_the_held_out_family_is_the_split_itself(family_split, tmp_path):
    write_twin(family_split, tmp_path / "own", progress=False)
    write_twin(tmp_path / "own", tmp_path / "back", family=HELD_OUT_FAMILY, progress=False)
    np.testing.assert_array_equal(_arrays(SequenceSplit(family_split))["crops"],
                                  _arrays(SequenceSplit(tmp_path / "back"))["crops"])


def test_refusals(family_split, tmp_path):
    with pytest.raises(ConfigError, match="already drawn in family"):
        write_twin(family_split, tmp_path / "same", family=HELD_OUT_FAMILY)
    write_twin(family_split, tmp_path / "own", progress=False)
    with pytest.raises(ConfigError, match="already drawn in the training families"):
        write_twin(tmp_path / "own", tmp_path / "again")
    with pytest.raises(ConfigError, match="family must be one of"):
        write_twin(family_split, tmp_path / "bad", family=7)
    assert main([str(tmp_path / "missing"), str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out").exists()


def test_command_line(family_split, tmp_path, capsys):
    assert main([str(family_split), str(tmp_path / "cli")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_sequences"] == 3 and summary["seed"] == 5
