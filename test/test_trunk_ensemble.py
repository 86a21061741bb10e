"""Members over one shared trunk: averaging, stepping, joining checkpoints, export."""

import pytest
import torch

from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.model.checkpoint import load_checkpoint, save_checkpoint
from signal_light_node.model.config import trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.model.trunk_ensemble import TrunkEnsemble
from signal_light_node.training import join_members as join_cli
from signal_light_node.training.join_members import join_members

RECIPE = {"frequency_evidence": False, "lamp_detail": 2, "lit_hidden": 16, "blink_levels": False}


def _member(seed: int, trunk_from=None, **changes):
    """A single model whose recurrent part is drawn with ``seed``, on ``trunk_from``'s trunk."""
    torch.manual_seed(seed)
    model = build_model(trunk_config(**dict(RECIPE, **changes))).eval()
    if trunk_from is not None:
        model.trunk.load_state_dict(trunk_from.trunk.state_dict())
    return model


def _pair(tmp_path):
    first = _member(1)
    second = _member(2, trunk_from=first)
    paths = [save_checkpoint(tmp_path / f"m{i}.pt", m, m.config) for i, m in
             enumerate((first, second))]
    return first, second, paths


def test_members_must_be_two_or_more_and_need_the_trunk():
    with pytest.raises(ConfigError, match="members"):
        trunk_config(members=0)
    with pytest.raises(ConfigError, match="trunk encoder"):
        trunk_config(members=2, encoder="cnn")
    assert isinstance(build_model(trunk_config(members=3, **RECIPE)), TrunkEnsemble)


def test_the_recipe_trains_one_member_at_a_time():
    from signal_light_node.training.trunk_recipe import build_fresh

    with pytest.raises(ConfigError, match="one run per seed"):
        build_fresh(dict(RECIPE, members=2), seed=1)


def test_joined_model_steps_the_mean_of_its_members_logits(tmp_path):
    first, second, paths = _pair(tmp_path)
    joined = load_checkpoint(join_members(paths, tmp_path / "j.pt")).model
    assert joined.config.members == 2
    # one trunk in the file, not one per member
    assert sum(k.startswith("trunk.") for k in joined.state_dict()) == \
        sum(k.startswith("trunk.") for k in first.state_dict())
    crops = torch.rand(2, 4, 3, 64, 64)
    with torch.no_grad():
        a, _ = first.forward_sequence(crops)
        b, _ = second.forward_sequence(crops)
        mean, _ = joined.forward_sequence(crops)
        state = joined.initial_state(2)
        for t in range(4):
            logits, state = joined.step_logits(crops[:, t], state)
    for task in ("intent", "brake", "view"):
        assert torch.allclose(mean[task], (a[task] + b[task]) / 2, atol=1e-5)
        assert torch.allclose(logits[task], mean[task][:, 3], atol=1e-4)
    assert len(state) == len(first.initial_state(1)) + len(second.initial_state(1))


def _joined(tmp_path):
    """Two members joined, loaded from the file."""
    return load_checkpoint(join_members(_pair(tmp_path)[2], tmp_path / "j.pt")).model


@torch.no_grad()
def _first_logits(model, crops):
    """Logits of one step of new tracks."""
    return model.step_logits(crops, model.initial_state(len(crops)))[0]


def test_the_command_line_joins_what_the_recipe_script_names(tmp_path, capsys):
    """scripts/train_trunk.sh runs this entry point after hours of training."""
    paths = _pair(tmp_path)[2]
    args = [a for p in paths for a in ("--member", str(p))] + ["--out", str(tmp_path / "j.pt")]
    assert join_cli.main(args) == 0
    assert load_checkpoint(tmp_path / "j.pt").config.members == 2
    assert str(tmp_path / "j.pt") in capsys.readouterr().out


def test_temperatures_apply_to_the_mean(tmp_path):
    joined = _joined(tmp_path)
    crops = torch.rand(3, 3, 64, 64)
    plain = _first_logits(joined, crops)
    joined.config = joined.config.replace(temperatures={"brake": 2.0})
    hot = _first_logits(joined, crops)
    assert torch.allclose(hot["brake"], plain["brake"] / 2, atol=1e-6)
    assert torch.allclose(hot["intent"], plain["intent"])


def test_on_offsets_shift_the_mean_once(tmp_path):
    """The members are built without the file's ON offsets, so they apply once, to the mean."""
    joined = _joined(tmp_path)
    shifted = build_model(joined.config.replace(on_offsets={"left": -1.0})).eval()
    shifted.load_state_dict(joined.state_dict())
    crops = torch.rand(3, 3, 64, 64)
    plain, hot = _first_logits(joined, crops), _first_logits(shifted, crops)
    gap = lambda z: z[:, 1] - z[:, 0]  # noqa: E731 - ON against OFF (classes OFF, ON, UNKNOWN)
    torch.testing.assert_close(gap(hot["left"]), gap(plain["left"]) - 1.0)
    torch.testing.assert_close(hot["left"].logsumexp(1), plain["left"].logsumexp(1))
    assert torch.allclose(hot["right"], plain["right"])


def test_offsets_on_the_heads_move_the_mean_logits(tmp_path):
    from signal_light_node.training.unknown_bias import apply_offsets, head_offsets

    joined = _joined(tmp_path)
    crops = torch.rand(2, 3, 64, 64)
    before = _first_logits(joined, crops)
    offsets = head_offsets(joined, margin=0.5)
    apply_offsets(joined, offsets)
    after = _first_logits(joined, crops)
    for task, delta in offsets.items():
        assert torch.allclose(after[task] - before[task],
                              torch.as_tensor(delta, dtype=torch.float32).expand(2, -1), atol=1e-5)


def test_a_wrong_state_is_refused():
    model = build_model(trunk_config(members=2, **RECIPE)).eval()
    with pytest.raises(ConfigError, match="layers"):
        model.step(torch.rand(1, 3, 64, 64), model.initial_state(1)[:-1])


def test_members_on_another_trunk_or_model_are_refused_and_nothing_is_written(tmp_path):
    first, _, paths = _pair(tmp_path)
    other_trunk = _member(3)
    other_model = _member(4, trunk_from=first, lit_hidden=8)
    for bad, match in ((other_trunk, "trunk weight"), (other_model, "lit_hidden")):
        path = save_checkpoint(tmp_path / "bad.pt", bad, bad.config)
        with pytest.raises(CheckpointError, match=match):
            join_members([paths[0], path], tmp_path / "j.pt")
        assert not (tmp_path / "j.pt").exists()
    with pytest.raises(CheckpointError, match="at least two"):
        join_members(paths[:1], tmp_path / "j.pt")


def test_calibrated_members_lose_their_temperatures_and_keep_their_history(tmp_path):
    first, second, _ = _pair(tmp_path)
    hot = first.config.replace(temperatures={"brake": 3.0})
    data = {"training_data": ["pool_1"]}
    paths = [save_checkpoint(tmp_path / "a.pt", first, hot, dict(data, validation={"score": 0.5})),
             save_checkpoint(tmp_path / "b.pt", second, second.config,
                             dict(data, validation={"score": 0.6}))]
    joined = load_checkpoint(join_members(paths, tmp_path / "j.pt"))
    assert joined.config.temperatures == {}
    assert [m["validation"]["score"] for m in joined.meta["members"]] == [0.5, 0.6]
    assert joined.meta["training_data"] == ["pool_1"]


def test_onnx_export_of_a_joined_model_steps_like_torch(tmp_path):
    from signal_light_node.model.onnx_export import export_onnx

    _, _, paths = _pair(tmp_path)
    report = export_onnx(tmp_path / "j.onnx", join_members(paths, tmp_path / "j.pt"))
    assert report.max_abs_diff is not None and report.max_abs_diff < 1e-4
