"""``signal-light adapt``: batch-norm statistics moved to unlabelled data (shifted from the
reference, or replaced), nothing else changed; refusals in one line with nothing written."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import torch

from signal_light_node.boxes import TrackBox
from signal_light_node.cli import main
from signal_light_node.errors import ConfigError
from signal_light_node.io import bagio
from signal_light_node.io.conversions import boxes_to_detections, make_header
from signal_light_node.io.image_codec import bgr_to_compressed_fields
from signal_light_node.model import load_checkpoint, save_checkpoint
from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS
from signal_light_node.model.interface import to_input
from signal_light_node.training.adapt_norms import (REFERENCE_KEY, AdaptSettings,
                                                    adapt_checkpoint, batch_norm_layers,
                                                    check_stats, measure_batch_norms,
                                                    cap_frames, stepped_crops)
from signal_light_node.training.sources import load_unlabelled_bag_tracks
from cli_refusal import refused

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "day_street"
NIGHT = REPO / "bags" / "night_street"

needs_bag = pytest.mark.skipif(not (BAG / "metadata.yaml").exists()
                               or not (NIGHT / "metadata.yaml").exists(),
                               reason="bags/day_street and bags/night_street are not committed")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def adapted(tmp_path_factory) -> Path:
    """The shipped model's statistics replaced by bags/day_street's (a few hundred crops),
    every layer, the stem too."""
    out = tmp_path_factory.mktemp("adapt") / "day.pt"
    assert main(["adapt", str(BAG), "--out", str(out), "--method", "replace",
                 "--keep-first", "0", "--threads", "1", "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def shifted(tmp_path_factory) -> Path:
    """The shipped model shifted to bags/day_street from the reference it carries."""
    out = tmp_path_factory.mktemp("shift") / "day.pt"
    assert main(["adapt", str(BAG), "--out", str(out), "--threads", "1", "--no-progress"]) == 0
    return out


def _stats(path, bag: Path = BAG):
    """The batch-norm statistics ``bag`` gives the checkpoint at ``path`` (the default
    settings; its own statistics untouched)."""
    model = load_checkpoint(path).model
    tracks = load_unlabelled_bag_tracks(bag, model.config.crop_config())
    return measure_batch_norms(model, stepped_crops(tracks))


def _state(path: Path) -> Dict[str, torch.Tensor]:
    return load_checkpoint(path).model.state_dict()


def _bn_buffers(model: torch.nn.Module) -> set:
    return {f"{name}.{b}" for name, _ in batch_norm_layers(model)
            for b in ("running_mean", "running_var", "num_batches_tracked")}


def _first_norm_input_mean(model: torch.nn.Module, tracks) -> torch.Tensor:
    """Per channel, the mean of the first batch norm's input over every stepped crop
    (the model in eval mode: that input does not depend on any batch norm)."""
    first = batch_norm_layers(model)[0][1]
    total, count = [], []

    def hook(module, inputs):
        total.append(inputs[0].sum(dim=(0, 2, 3)))
        count.append(inputs[0].shape[0] * inputs[0].shape[2] * inputs[0].shape[3])

    handle = first.register_forward_pre_hook(hook)
    model.eval()
    with torch.no_grad():
        for track in tracks:
            crops = track.crops[track.mask]
            if len(crops):
                model.forward_sequence(to_input(crops).unsqueeze(0))
    handle.remove()
    return torch.stack(total).sum(0) / sum(count)


@needs_bag
def test_only_batch_norm_buffers_change_toward_the_new_data(adapted: Path) -> None:
    before, after = _state(DEFAULT_WEIGHTS), _state(adapted)
    model = load_checkpoint(adapted).model
    norms = _bn_buffers(model)
    assert before.keys() == after.keys()
    for key in before:
        if key not in norms:
            assert torch.equal(before[key], after[key]), key
    moved = [k for k in norms if k.endswith("running_mean")
             and not torch.equal(before[k], after[k])]
    assert len(moved) == len(batch_norm_layers(model)) > 0
    # The first layer's input does not depend on any batch norm: its new running mean is
    # the mean over the bag's stepped crops, which the shipped statistics were not.
    first = batch_norm_layers(model)[0][0]
    tracks = load_unlabelled_bag_tracks(BAG, model.config.crop_config())
    data_mean = _first_norm_input_mean(model, tracks)
    new, old = after[f"{first}.running_mean"], before[f"{first}.running_mean"]
    assert torch.allclose(new, data_mean, atol=1e-4, rtol=1e-3)
    assert (new - data_mean).abs().mean() < 0.1 * (old - data_mean).abs().mean()


@needs_bag
def test_meta_says_what_it_was_adapted_from_and_on(adapted: Path, capsys) -> None:
    loaded = load_checkpoint(adapted)
    info = loaded.meta["adapted"]
    assert Path(info["from"]) == DEFAULT_WEIGHTS and info["data"] == [str(BAG)]
    assert info["frames"] > 100 and info["tracks"] == 8
    assert info["batch_norm_layers"] == len(batch_norm_layers(loaded.model)) > 0
    assert loaded.meta["training_data"] == load_checkpoint(DEFAULT_WEIGHTS).meta["training_data"]
    # It loads and steps like any checkpoint.
    model, size = loaded.model, loaded.config.input_size
    crops = np.random.default_rng(0).integers(0, 255, (3, size, size, 3), dtype=np.uint8)
    probs, state = model.step(to_input(crops), model.initial_state(3))
    probs, _ = model.step(to_input(crops), state)
    for p in probs.values():
        assert torch.allclose(p.sum(1), torch.ones(3), atol=1e-5)


@needs_bag
def test_the_adapted_checkpoint_exports_to_onnx(adapted: Path, tmp_path: Path) -> None:
    from signal_light_node.model.onnx_export import VERIFY_TOLERANCE, export_onnx

    report = export_onnx(tmp_path / "adapted.onnx", adapted)  # checked against torch
    assert report.path.is_file() and report.max_abs_diff <= VERIFY_TOLERANCE


@needs_bag
def test_the_same_data_gives_the_same_tensors(adapted: Path, tmp_path: Path) -> None:
    again = tmp_path / "again.pt"
    assert main(["adapt", str(BAG), "--out", str(again), "--method", "replace",
                 "--keep-first", "0", "--threads", "1", "--no-progress"]) == 0
    first, second = _state(adapted), _state(again)
    assert all(torch.equal(first[k], second[k]) for k in first)


@needs_bag
def test_max_frames_caps_the_crops_with_the_seed(tmp_path: Path) -> None:
    runs = [adapt_checkpoint(tmp_path / f"{i}.pt", [BAG],
                             settings=AdaptSettings(max_frames=100, seed=seed))
            for i, seed in enumerate((3, 3, 4))]
    assert [r.frames for r in runs] == [100, 100, 100]
    a, b, c = (_state(r.out) for r in runs)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_the_shipped_weights_carry_a_reference_that_covers_every_norm() -> None:
    loaded = load_checkpoint(DEFAULT_WEIGHTS)
    entry = loaded.meta[REFERENCE_KEY]
    assert entry["frames"] > 10000 and entry["data"]
    check_stats(entry["layers"], loaded.model, "the shipped reference")


@needs_bag
def test_a_shift_moves_each_mean_by_the_data_less_the_reference(shifted: Path) -> None:
    """Means: stored + (bag - reference), but the trunk's stem; variances and every other
    tensor as shipped."""
    before, after = _state(DEFAULT_WEIGHTS), _state(shifted)
    reference = load_checkpoint(DEFAULT_WEIGHTS).meta[REFERENCE_KEY]["layers"]
    target = _stats(DEFAULT_WEIGHTS)
    model = load_checkpoint(shifted).model
    layers = batch_norm_layers(model)
    means = {f"{name}.running_mean": name for name, _ in layers[1:]}
    stem = f"{layers[0][0]}.running_mean"
    assert stem.startswith("trunk.stem") and torch.equal(after[stem], before[stem])
    for key in before:
        if key in means:
            name = means[key]
            expected = before[key] + target[name]["mean"] - reference[name]["mean"]
            assert torch.allclose(after[key], expected, atol=1e-5), key
            assert not torch.equal(after[key], before[key]), key
        elif not key.endswith("num_batches_tracked"):
            assert torch.equal(before[key], after[key]), key


@needs_bag
def test_a_shift_on_the_reference_data_itself_changes_nothing(tmp_path: Path) -> None:
    """Data like the training data (here: the reference itself) leave the model as it
    was, where a replacement would move it."""
    ref = main(["adapt", "--reference", str(NIGHT), "--out", str(tmp_path / "ref.pt"),
                "--threads", "1", "--no-progress"])
    assert ref == 0
    shipped, recorded = _state(DEFAULT_WEIGHTS), _state(tmp_path / "ref.pt")
    assert all(torch.equal(shipped[k], recorded[k]) for k in shipped)
    assert main(["adapt", str(NIGHT), "--checkpoint", str(tmp_path / "ref.pt"),
                 "--out", str(tmp_path / "same.pt"), "--threads", "1", "--no-progress"]) == 0
    same = _state(tmp_path / "same.pt")
    assert all(torch.allclose(shipped[k].float(), same[k].float(), atol=1e-5) for k in shipped)
    assert main(["adapt", str(NIGHT), "--method", "replace", "--out", str(tmp_path / "r.pt"),
                 "--threads", "1", "--no-progress"]) == 0
    replaced = _state(tmp_path / "r.pt")
    assert not all(torch.allclose(shipped[k].float(), replaced[k].float(), atol=1e-3)
                   for k in shipped)


@needs_bag
def test_adapting_twice_shifts_from_the_last_data_not_twice(shifted: Path,
                                                              tmp_path: Path) -> None:
    """The adapted checkpoint's reference is the data it was adapted on: adapting it to
    another recording gives what adapting the shipped model to that recording gives."""
    assert load_checkpoint(shifted).meta[REFERENCE_KEY]["data"] == [str(BAG)]
    for source, out in ((shifted, "twice.pt"), (DEFAULT_WEIGHTS, "once.pt")):
        assert main(["adapt", str(NIGHT), "--checkpoint", str(source), "--out",
                     str(tmp_path / out), "--threads", "1", "--no-progress"]) == 0
    twice, once = _state(tmp_path / "twice.pt"), _state(tmp_path / "once.pt")
    assert all(torch.allclose(twice[k].float(), once[k].float(), atol=1e-5) for k in once)


def test_a_rendered_split_adapts_a_trunk_model(tmp_path: Path) -> None:
    """A split directory is read as data (labels unused); the trunk's norms are adapted."""
    from signal_light_node.data.split import write_split
    from signal_light_node.model.config import ModelConfig
    from signal_light_node.model.registry import build_model

    config = ModelConfig(encoder="efficientnet_lite0")
    split = tmp_path / "split"
    write_split(split, seed=5, n_sequences=3, seq_len=8, crop=config.crop_config(),
                full_tracks=True, progress=False, vehicles=(1, 2))
    source = save_checkpoint(tmp_path / "trunk.pt", build_model(config), config)
    result = adapt_checkpoint(tmp_path / "adapted.pt", [split], source,
                              AdaptSettings(window_frames=4, method="replace", keep_first=0))
    assert result.layers == len(batch_norm_layers(load_checkpoint(source).model)) > 10
    before, after = _state(source), _state(result.out)
    norms = _bn_buffers(load_checkpoint(source).model)
    assert all(torch.equal(before[k], after[k]) for k in before if k not in norms)
    trunk_norms = [k for k in norms if k.startswith("trunk.") and k.endswith("running_mean")]
    assert len(trunk_norms) == result.layers
    assert all(not torch.equal(before[k], after[k]) for k in trunk_norms)


def test_the_trunk_model_keeps_its_stem_and_the_stems_reference(tmp_path: Path) -> None:
    """By default the trunk's first batch norm (the stem: raw colour and tone) is left as
    it is, and so is its reference; ``keep_first`` leaves more, or none."""
    from signal_light_node.data.split import write_split
    from signal_light_node.model.config import ModelConfig
    from signal_light_node.model.registry import build_model

    config = ModelConfig(encoder="efficientnet_lite0")
    split = tmp_path / "split"
    write_split(split, seed=6, n_sequences=2, seq_len=8, crop=config.crop_config(),
                full_tracks=True, progress=False, vehicles=(1, 2))
    source = save_checkpoint(tmp_path / "trunk.pt", build_model(config), config)
    layers = [name for name, _ in batch_norm_layers(load_checkpoint(source).model)]
    before = _state(source)
    for keep, kept in ((None, 1), (3, 3)):
        result = adapt_checkpoint(tmp_path / f"a{keep}.pt", [split], source,
                                  AdaptSettings(window_frames=4, method="replace", keep_first=keep))
        assert result.kept == layers[:kept] and result.layers == len(layers) - kept
        after = _state(result.out)
        for i, name in enumerate(layers):
            same = torch.equal(before[f"{name}.running_mean"], after[f"{name}.running_mean"])
            assert same == (i < kept), name
        meta = load_checkpoint(result.out).meta
        assert meta["adapted"]["kept_layers"] == layers[:kept]
        reference = meta[REFERENCE_KEY]["layers"]
        assert torch.equal(reference[layers[0]]["mean"], before[f"{layers[0]}.running_mean"])
    with pytest.raises(ConfigError, match="leaves none"):
        adapt_checkpoint(tmp_path / "none.pt", [split], source,
                         AdaptSettings(method="replace", keep_first=len(layers)))
    assert not (tmp_path / "none.pt").exists()


def _refused(capsys, args, out: Path) -> str:
    return refused(capsys, "adapt", args, out, extra=("--no-progress",))


@needs_bag
def test_a_model_without_batch_norm_is_refused(tmp_path: Path, capsys) -> None:
    from signal_light_node.model.config import ModelConfig
    from signal_light_node.model.registry import build_model

    config = ModelConfig(norm="group")
    source = save_checkpoint(tmp_path / "group.pt", build_model(config), config)
    err = _refused(capsys, [BAG, "--checkpoint", source], tmp_path / "out" / "a.pt")
    assert "no batch-norm layer" in err


@needs_bag
def test_a_shift_without_a_reference_is_refused(tmp_path: Path, capsys) -> None:
    """A model of one's own carries no reference until ``--reference`` records one."""
    from signal_light_node.model.config import ModelConfig
    from signal_light_node.model.registry import build_model

    config = ModelConfig()
    source = save_checkpoint(tmp_path / "mine.pt", build_model(config), config)
    err = _refused(capsys, [BAG, "--checkpoint", source], tmp_path / "out" / "a.pt")
    assert "no reference statistics" in err and "--reference" in err


def test_reference_statistics_of_another_model_are_refused() -> None:
    from signal_light_node.errors import ConfigError

    model = load_checkpoint(DEFAULT_WEIGHTS).model
    first = batch_norm_layers(model)[0][0]
    stats = {name: {"mean": m.running_mean.clone(), "var": m.running_var.clone()}
             for name, m in batch_norm_layers(model)}
    check_stats(stats, model, "these")
    stats[first]["mean"] = stats[first]["mean"][:-1]
    with pytest.raises(ConfigError, match=first):
        check_stats(stats, model, "these")


def test_nothing_to_adapt_on_is_refused(tmp_path: Path, capsys) -> None:
    err = _refused(capsys, [], tmp_path / "a.pt")
    assert "at least one bag" in err


def test_a_reference_with_a_replacement_is_refused(tmp_path: Path, capsys) -> None:
    err = _refused(capsys, [BAG, "--method", "replace", "--reference", NIGHT],
                   tmp_path / "a.pt")
    assert "--reference" in err and "replace" in err


def test_a_missing_bag_is_refused(tmp_path: Path, capsys) -> None:
    err = _refused(capsys, [tmp_path / "nowhere"], tmp_path / "a.pt")
    assert "does not exist" in err


def test_a_bag_without_usable_crops_is_refused(tmp_path: Path, capsys) -> None:
    """Every box lies outside the image: tracks, but not one crop."""
    make, bag = bagio.make, tmp_path / "outside"
    jpeg = bgr_to_compressed_fields(np.full((30, 40, 3), 90, np.uint8), "jpeg")
    with bagio.BagWriter(bag) as writer:
        writer.add_topic("/cam/image/compressed", "sensor_msgs/msg/CompressedImage")
        writer.add_topic("/tracks", "vision_msgs/msg/Detection2DArray")
        for i in range(3):
            stamp = 10**12 + i * 10**8
            header = make_header(stamp, "cam", make)
            writer.write("/cam/image/compressed", stamp,
                         make("sensor_msgs/msg/CompressedImage", header=header, **jpeg))
            writer.write("/tracks", stamp, boxes_to_detections(
                header, [TrackBox("7", 500, 500, 520, 520, "car")], make))
    err = _refused(capsys, [bag], tmp_path / "a.pt")
    assert "no usable crop" in err


class _CountingTrack:
    """A track whose crops are numbered frames; counts how often they are cut out."""

    def __init__(self, n: int, stepped: int, first: int) -> None:
        self.mask = [i < stepped for i in range(n)]
        frames = np.arange(first, first + n, dtype=np.uint8)
        self.crops = np.broadcast_to(frames[:, None, None, None], (n, 2, 2, 3))
        self.cut = 0

    def __len__(self) -> int:
        return len(self.mask)

    def crop_window(self, start: int, stop: int) -> np.ndarray:
        self.cut += 1
        return self.crops[start:stop]


def test_a_cap_cuts_out_only_the_tracks_it_keeps() -> None:
    """The capped crops are those the uncapped ones capped would be; unkept tracks stay
    uncut (18 pools' crops copied at once did not fit in 24 GB)."""
    tracks = [_CountingTrack(10, s, 20 * i) for i, s in enumerate((6, 0, 9, 3, 7, 5))]
    capped = stepped_crops(tracks, max_frames=12, seed=5)
    cut = [t.cut for t in tracks]
    expected = cap_frames(stepped_crops(tracks), 12, 5)
    assert sum(len(c) for c in capped) == 12
    assert [c.tolist() for c in capped] == [c.tolist() for c in expected]
    assert cut[1] == 0 and 0 < sum(cut) < len(tracks) - 1
