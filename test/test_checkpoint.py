"""Tests of the checkpoint format: round trip, safety and every compatibility check."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from signal_light_node import __version__
from signal_light_node.errors import CheckpointError
from signal_light_node.labels import CLASS_NAMES, LIGHT_CODES
from signal_light_node.model import (
    DEFAULT_WEIGHTS,
    FORMAT_VERSION,
    LightStateNet,
    ModelConfig,
    build_model,
    load_checkpoint,
    save_checkpoint,
)

TINY = ModelConfig(input_size=16, attention_channels=(3, 3, 3), backbone_channels=(4, 6),
                   lstm_hidden=(4, 4), head_channels=2, head_grid=2, fc_hidden=8)


@pytest.fixture()
def saved(tmp_path: Path):
    torch.manual_seed(0)
    model = build_model(TINY)
    # Make the BatchNorm running statistics non-trivial so that they must be saved too.
    model.train()
    with torch.no_grad():
        model.forward_sequence(torch.rand(3, 2, 3, 16, 16))
    model.eval()
    meta = {"training_data": {"source": "synthetic", "seeds": [1, 2, 3]},
            "metrics": {"intent_f1": 0.5}, "notes": "unit test"}
    path = save_checkpoint(tmp_path / "sub" / "model.pt", model, TINY, meta)
    return path, model, meta


def _rewrite(path: Path, change) -> Path:
    payload = torch.load(path, weights_only=True)
    change(payload)
    torch.save(payload, path)
    return path


def test_round_trip_gives_identical_outputs(saved) -> None:
    path, model, meta = saved
    loaded = load_checkpoint(path)
    assert isinstance(loaded.model, LightStateNet)
    assert not loaded.model.training
    assert loaded.config == TINY
    for key, value in meta.items():
        assert loaded.meta[key] == value
    assert loaded.meta["package_version"] == __version__
    assert "created" in loaded.meta
    crops = torch.rand(2, 4, 3, 16, 16)
    with torch.no_grad():
        want, want_state = model.forward_sequence(crops)
        got, got_state = loaded.model.forward_sequence(crops)
    for task in want:
        assert torch.equal(want[task], got[task])
    assert torch.equal(want_state[1][1], got_state[1][1])


def test_file_is_plain_and_loads_with_weights_only(saved) -> None:
    path, _, _ = saved
    payload = torch.load(path, weights_only=True)
    assert payload["format_version"] == FORMAT_VERSION
    assert payload["config"]["class_names"]["intent"] == list(CLASS_NAMES["intent"])
    assert payload["config"]["light_codes"] == LIGHT_CODES
    assert payload["config"]["crop_margin"] == pytest.approx(0.15)
    assert all(isinstance(v, torch.Tensor) for v in payload["state_dict"].values())
    # No temporary file is left next to it.
    assert [p.name for p in path.parent.iterdir()] == ["model.pt"]


def test_meta_that_cannot_be_stored_safely_is_refused(tmp_path: Path) -> None:
    model = build_model(TINY)
    with pytest.raises(CheckpointError, match=r"meta\.bad holds a object"):
        save_checkpoint(tmp_path / "m.pt", model, TINY, {"bad": object()})


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")


def test_garbage_file(tmp_path: Path) -> None:
    path = tmp_path / "garbage.pt"
    path.write_bytes(b"this is not a checkpoint at all")
    with pytest.raises(CheckpointError, match="cannot be read as a checkpoint"):
        load_checkpoint(path)


def test_foreign_torch_file(tmp_path: Path) -> None:
    path = tmp_path / "weights.pt"
    torch.save({"weight": torch.zeros(2)}, path)
    with pytest.raises(CheckpointError, match="no format_version"):
        load_checkpoint(path)


def test_unsupported_format_version(saved) -> None:
    path = _rewrite(saved[0], lambda p: p.update(format_version=99))
    with pytest.raises(CheckpointError, match=r"format version 99 but this code supports \[1\]"):
        load_checkpoint(path)


def test_unknown_architecture(saved) -> None:
    path = _rewrite(saved[0], lambda p: p["config"].update(arch="vit_huge"))
    with pytest.raises(CheckpointError, match="architecture 'vit_huge'"):
        load_checkpoint(path)


def test_class_names_differ(saved) -> None:
    def change(payload):
        payload["config"]["class_names"]["intent"] = ["OFF", "LEFT", "RIGHT", "HAZARD"]
    path = _rewrite(saved[0], change)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert "class names for 'intent'" in message
    assert "('OFF', 'LEFT', 'RIGHT', 'HAZARD')" in message
    assert "('OFF', 'LEFT', 'RIGHT', 'HAZARD', 'UNKNOWN')" in message


def test_light_codes_differ(saved) -> None:
    path = _rewrite(saved[0], lambda p: p["config"]["light_codes"].update(brake=7))
    with pytest.raises(CheckpointError, match="light codes are .*'brake': 7"):
        load_checkpoint(path)


def test_tensor_shape_differs(saved) -> None:
    def change(payload):
        payload["state_dict"]["heads.view.weight"] = torch.zeros(5, 8)
    path = _rewrite(saved[0], change)
    with pytest.raises(CheckpointError,
                       match=r"'heads.view.weight' has shape \(5, 8\) .* expects \(4, 8\)"):
        load_checkpoint(path)


def test_config_and_weights_disagree(saved) -> None:
    path = _rewrite(saved[0], lambda p: p["config"].update(fc_hidden=9))
    with pytest.raises(CheckpointError, match="'fc.0.weight' has shape"):
        load_checkpoint(path)


def test_missing_and_unexpected_tensors(saved) -> None:
    def change(payload):
        payload["state_dict"]["extra.weight"] = payload["state_dict"].pop("heads.brake.bias")
    path = _rewrite(saved[0], change)
    with pytest.raises(CheckpointError, match=r"missing tensors \['heads.brake.bias'\].*"
                                              r"unexpected tensors \['extra.weight'\]"):
        load_checkpoint(path)


def test_bad_config_value(saved) -> None:
    path = _rewrite(saved[0], lambda p: p["config"].update(norm="layer"))
    with pytest.raises(CheckpointError, match="norm must be"):
        load_checkpoint(path)


def test_default_weights_path_is_inside_the_package() -> None:
    assert DEFAULT_WEIGHTS.name == "default.pt"
    assert DEFAULT_WEIGHTS.parent.name == "weights"
    assert DEFAULT_WEIGHTS.parent.parent.name == "signal_light_node"


def test_numpy_and_str_subclass_meta_values_are_stored_as_plain(tmp_path: Path) -> None:
    import numpy as np

    model = build_model(TINY)
    meta = {"f1": np.float64(0.25), "n": np.int64(3), "torch": torch.__version__,
            "per_class": np.array([1.0, 2.0]).tolist()}
    loaded = load_checkpoint(save_checkpoint(tmp_path / "m.pt", model, TINY, meta))
    assert loaded.meta["f1"] == 0.25 and type(loaded.meta["f1"]) is float
    assert loaded.meta["n"] == 3 and type(loaded.meta["torch"]) is str
