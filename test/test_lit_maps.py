"""Lit maps: where a vehicle's signal lamps are lit, from the renderer through the splits
and augmentation to the model's training-only head and its loss."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from signal_light_node.data.split import SequenceSplit, write_split
from signal_light_node.data.stream import LIT_MAP_SCALE, mirror_sequence
from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, Intent, LightStatus, View
from signal_light_node.model import ModelConfig, build_model
from signal_light_node.model.network import LIT_MAP_KEY
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.synth import SceneRenderer
from signal_light_node.training.loop import Trainer
from signal_light_node.training.loss import lit_map_loss
from signal_light_node.training.options import TrainOptions

CROP = CropConfig(size=32, margin=0.15)
BRAKE, LEFT, RIGHT = 0, 1, 2
CROP_SIZE = 64


def _one_vehicle(**vehicle) -> list:
    """Frames of one large vehicle seen from behind, parked in daylight, lit maps on."""
    spec = dict(view=View.BEHIND, kind="car", width_px=200, center_x=320, speed=0.0,
                lamp_design="amber", **vehicle)
    renderer = SceneRenderer(3, lighting="day", fps=20, lit_maps=True, vehicles=[spec],
                             occluders=[], poles=0, distractors=False, effects=False)
    return [f for f in renderer.frames(24) if f.vehicles]


def test_renderer_maps_the_lit_lamps_and_leaves_the_image_alone():
    braking = _one_vehicle(brake=True, intent=Intent.OFF)
    maps = [f.vehicles[0].lit_map.image for f in braking]
    assert all((m[..., BRAKE] > 0).sum() > 20 for m in maps)
    assert all(not m[..., LEFT].any() and not m[..., RIGHT].any() for m in maps)

    left = _one_vehicle(brake=False, intent=Intent.LEFT)
    lit = [f.vehicles[0].left_lit == LightStatus.ON for f in left]
    drawn = [bool(f.vehicles[0].lit_map.image[..., LEFT].any()) for f in left]
    assert any(lit) and not all(lit)  # both halves of the blink are in the frames
    assert drawn == lit
    assert not any(f.vehicles[0].lit_map.image[..., (BRAKE, RIGHT)].any() for f in left)

    plain = SceneRenderer(3, lighting="day", fps=20, vehicles=[dict(
        view=View.BEHIND, kind="car", width_px=200, center_x=320, speed=0.0,
        lamp_design="amber", brake=False, intent=Intent.LEFT)], occluders=[], poles=0,
        distractors=False, effects=False)
    for a, b in zip(plain.frames(24), left):
        assert a.vehicles[0].lit_map is None
        assert np.array_equal(a.image, b.image)


def test_lit_maps_lie_in_the_vehicles_own_half():
    frames = _one_vehicle(brake=False, intent=Intent.LEFT)
    m = next(f.vehicles[0].lit_map.image for f in frames
             if f.vehicles[0].lit_map.image[..., LEFT].any())
    xs = np.nonzero(m[..., LEFT])[1]
    # Seen from behind, the vehicle's own left is on the image's left.
    assert xs.mean() < m.shape[1] / 2


def test_split_keeps_the_maps_and_mirroring_swaps_their_sides(tmp_path):
    write_split(tmp_path / "s", seed=5, n_sequences=3, seq_len=20, crop=CROP,
                full_tracks=True, progress=False, lit_maps=True,
                sizes=((320, 180),), vehicles=(2, 3))
    split = SequenceSplit(tmp_path / "s")
    item = split[0]
    size = CROP.size // LIT_MAP_SCALE
    assert item["lit_maps"].shape == (20, size, size, 3)
    assert item["lit_maps"].dtype == np.uint8
    assert not item["lit_maps"][~item["mask"]].any()

    maps = np.zeros_like(item["lit_maps"])
    maps[:, 1, 0, LEFT] = 200
    mirrored = mirror_sequence(dict(item, lit_maps=maps))["lit_maps"]
    assert mirrored[:, 1, -1, RIGHT].min() == 200
    assert mirrored[..., LEFT].sum() == 0

    write_split(tmp_path / "plain", seed=5, n_sequences=1, seq_len=20, crop=CROP,
                full_tracks=True, progress=False, sizes=((320, 180),), vehicles=(2, 3))
    assert "lit_maps" not in SequenceSplit(tmp_path / "plain")[0]


def test_lit_map_loss_prefers_the_right_map_and_checks_shapes():
    maps = torch.zeros((2, 1, 16, 16, 3), dtype=torch.uint8)
    maps[0, 0, 4:6, 2:4, LEFT] = 255
    target = torch.nn.functional.max_pool2d(
        maps.reshape(2, 16, 16, 3).permute(0, 3, 1, 2).float() / 255, 2)
    right = (target * 16 - 8).reshape(2, 1, -1)
    wrong = -right
    assert lit_map_loss(right, maps) < 0.01 < lit_map_loss(wrong, maps)
    with pytest.raises(ConfigError, match="do not fit"):
        lit_map_loss(torch.zeros((2, 1, 3 * 5 * 5)), maps)


def test_lit_map_head_is_trained_only_and_steps_are_unchanged():
    config = ModelConfig(lit_map_head=True)
    model = build_model(config).eval()
    plain = build_model(ModelConfig()).eval()
    crops = torch.rand((2, 3, 3, 64, 64))
    logits, _ = model.forward_sequence(crops)
    assert logits[LIT_MAP_KEY].shape == (2, 3, 3 * 8 * 8)
    probs, _ = model.step(crops[:, 0], model.initial_state(2))
    assert set(probs) == set(TASKS)
    assert LIT_MAP_KEY not in plain.forward_sequence(crops)[0]


def test_lit_map_weight_needs_frames_without_warp_and_maps_on_the_pools(tmp_path):
    base = dict(out=tmp_path / "run", max_steps=1, mode="frames", frame_targets="lit",
                pools=[tmp_path / "pool"], lit_map_weight=1.0, workers=0, progress=False,
                threads=1, val_fraction=0.0)
    with pytest.raises(ConfigError, match="--mode frames"):
        TrainOptions(**dict(base, mode="lanes")).validate()
    with pytest.raises(ConfigError, match="shape-warp"):
        TrainOptions(**dict(base, shape_warp=True)).validate()
    with pytest.raises(ConfigError, match=">= 0"):
        TrainOptions(**dict(base, lit_map_weight=-1.0)).validate()

    crop = ModelConfig().crop_config()
    write_split(tmp_path / "pool", seed=6, n_sequences=2, seq_len=12, crop=crop,
                full_tracks=True, progress=False, sizes=((320, 180),), vehicles=(2, 2))
    with pytest.raises(ConfigError, match="lit_map_head"):
        Trainer(TrainOptions(**base))
    with pytest.raises(ConfigError, match="no lit maps"):
        Trainer(TrainOptions(**dict(base, model={"lit_map_head": True})))


def test_a_frames_run_learns_the_lit_maps(tmp_path):
    crop = ModelConfig().crop_config()
    write_split(tmp_path / "pool", seed=8, n_sequences=4, seq_len=16, crop=crop,
                full_tracks=True, progress=False, lit_maps=True, sizes=((320, 180),),
                vehicles=(3, 3), lighting="night")
    opts = TrainOptions(out=tmp_path / "run", max_steps=25, mode="frames", frame_targets="lit",
                        pools=[tmp_path / "pool"], lit_map_weight=1.0, workers=0,
                        progress=False, threads=1, val_fraction=0.0, batch=16, lr=3e-3,
                        model={"lit_map_head": True}, task_weights={"brake": 1e-6},
                        seed=2)
    trainer = Trainer(opts)
    batch = next(iter(trainer.loader))
    assert batch["lit_maps"].shape[:2] == (16, 1)

    def map_loss() -> float:
        trainer.model.eval()
        with torch.no_grad():
            logits, _ = trainer.model.forward_sequence(
                batch["crops"].permute(0, 1, 4, 2, 3).float() / 255.0)
        trainer.model.train()
        return float(lit_map_loss(logits[LIT_MAP_KEY], batch["lit_maps"]))

    before = map_loss()
    trainer.run()
    assert map_loss() < 0.7 * before


def test_stream_cuts_the_maps_where_the_crop_shows_the_lit_lamps():
    from signal_light_node.data import SyntheticSequenceStream

    vehicle = dict(view=View.BEHIND, kind="car", width_px=160, center_x=320, speed=0.0,
                   lamp_design="amber", brake=True, intent=Intent.OFF, lights_on=True)
    stream = SyntheticSequenceStream(
        4, 8, CropConfig(CROP_SIZE, 0.15), mirror_prob=0.0, lit_maps=True, sizes=((640, 360),),
        vehicles=(1, 1), lighting="night", full_tracks=True,
        renderer_overrides=dict(vehicles=[vehicle], occluders=[], poles=0,
                                distractors=False, effects=False))
    item = next(stream.sequences())
    n = int(item["mask"].sum())
    crops = item["crops"][:n].astype(np.float32)
    red = np.clip(crops[..., 2] - crops[..., :2].max(-1), 0, None)  # BGR: red over the rest
    size = CROP_SIZE // LIT_MAP_SCALE
    for frame_red, lit in zip(red, item["lit_maps"][:n, ..., BRAKE].astype(np.float32)):
        seen = cv2.resize(frame_red, (size, size), interpolation=cv2.INTER_AREA)

        def match(dy: int, dx: int) -> float:
            moved = np.roll(lit, (dy, dx), axis=(0, 1))
            return float(np.corrcoef(seen.ravel(), moved.ravel())[0, 1])

        # The brake channel lies on the red lamps of the crop (their glow spreads wider),
        # and better where it is than one cell off in any direction.
        assert match(0, 0) > 0.5
        assert match(0, 0) > max(match(-1, 0), match(1, 0), match(0, -1), match(0, 1))
