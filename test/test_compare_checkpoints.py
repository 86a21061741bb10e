"""``scripts/compare_checkpoints.py`` pairs files that crop differently on twin splits: each
reads the splits cut as it crops (``sources.paths_cut_with``), and the tracks must be the
same (``bootstrap.require_same_tracks``)."""

import json
from pathlib import Path

import numpy as np
import pytest

from signal_light_node.data.split import write_split
from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.bootstrap import require_same_tracks
from signal_light_node.model.checkpoint import save_checkpoint
from signal_light_node.model.config import ModelConfig
from signal_light_node.model.registry import build_model
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.training.sources import paths_cut_with, split_tracks
from script_loader import load_script

SMALL = dict(input_size=32, attention_channels=(4, 4, 4), backbone_channels=(8, 8),
             lstm_hidden=(8, 8), head_channels=4, fc_hidden=16)


def _script():
    return load_script("compare_checkpoints")


def _twins(root: Path, seed: int = 3):
    """The same tracks cut square and filled; and one other split, square."""
    square, fill = CropConfig(32, 0.15), CropConfig(32, 0.15, True)
    paths = {}
    for name, crop, s in (("square", square, seed), ("fill", fill, seed), ("other", square, seed + 1)):
        paths[name] = root / name
        write_split(paths[name], seed=s, n_sequences=2, seq_len=8, crop=crop, full_tracks=True,
                    progress=False)
    return paths, square, fill


def _checkpoint(path: Path, **changes) -> Path:
    config = ModelConfig(**SMALL, **changes)
    return save_checkpoint(path, build_model(config), config)


def test_each_file_reads_the_twin_cut_as_it_crops(tmp_path):
    paths, square, fill = _twins(tmp_path)
    both = [paths["square"], paths["fill"]]
    assert paths_cut_with(both, square) == [paths["square"]]
    assert paths_cut_with(both, fill) == [paths["fill"]]
    with pytest.raises(ConfigError, match="no bag, and no split cut with"):
        paths_cut_with([paths["square"]], fill)
    a, b = split_tracks(paths["square"], square), split_tracks(paths["fill"], fill)
    require_same_tracks(a, b, "fill")
    assert not np.array_equal(a[0].crops, b[0].crops)  # twins differ in pixels only


def test_tracks_that_do_not_pair_are_refused(tmp_path):
    paths, square, _ = _twins(tmp_path)
    a = split_tracks(paths["square"], square)
    with pytest.raises(ConfigError, match="tracks, the first file's data"):
        require_same_tracks(a, a[:1], "short")
    with pytest.raises(ConfigError, match="is not the first file's"):
        require_same_tracks(a, split_tracks(paths["other"], square), "other")
    changed = split_tracks(paths["square"], square)
    changed[1].labels = changed[1].labels.copy()
    changed[1].labels[-1, 1] = 1 - max(changed[1].labels[-1, 1], 0)
    with pytest.raises(ConfigError, match="track 1"):
        require_same_tracks(a, changed, "changed")


def test_a_square_and_a_fill_file_are_compared_on_twin_splits(tmp_path):
    paths, _, _ = _twins(tmp_path)
    first = _checkpoint(tmp_path / "square.pt")
    second = _checkpoint(tmp_path / "fill.pt", crop_fill=True)
    out = tmp_path / "cmp.json"
    script = _script()
    assert script.main(["--data", str(paths["square"]), "--data", str(paths["fill"]),
                        "--checkpoint", str(first), "--checkpoint", str(second),
                        "--resamples", "20", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["tracks"] == 2 and set(report["files"]) == {str(first), str(second)}
    # The fill file alone on the square split has nothing it can read.
    with pytest.raises(ConfigError, match="no bag, and no split cut with"):
        script.main(["--data", str(paths["square"]), "--checkpoint", str(first),
                     "--checkpoint", str(second), "--resamples", "5"])
    # Twin paths that are not twins: the fill file's tracks do not pair with the first's.
    other_fill = tmp_path / "other_fill"
    write_split(other_fill, seed=4, n_sequences=2, seq_len=8, crop=CropConfig(32, 0.15, True),
                full_tracks=True, progress=False)
    with pytest.raises(ConfigError, match="is not the first file's"):
        script.main(["--data", str(paths["square"]), "--data", str(other_fill),
                     "--checkpoint", str(first), "--checkpoint", str(second), "--resamples", "5"])
