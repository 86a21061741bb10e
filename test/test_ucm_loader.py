"""The UC Merced rear-signal layout loader, on a tiny fixture made here."""

from pathlib import Path
from typing import Dict, Sequence

import cv2
import numpy as np
import pytest

from signal_light_node.runtime.crops import CropConfig
from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, Intent, LightStatus, View
from signal_light_node.training.sources import WindowDataset, load_ucm_tracks, ucm_labels

ON, OFF = int(LightStatus.ON), int(LightStatus.OFF)


def draw_rear(code: str, frame: int, height: int = 24, width: int = 32,
              steady: bool = False) -> np.ndarray:
    """A toy rear view: grey body, red brake bar when B, amber blinkers 2 on / 2 off
    (always lit with ``steady``)."""
    img = np.full((height, width, 3), 60, np.uint8)
    img[4:height - 4, 3:width - 3] = (90, 90, 90)
    if code[0] == "B":
        img[6:9, width // 2 - 5:width // 2 + 5] = (0, 0, 255)
    blink_on = steady or (frame // 2) % 2 == 0
    if code[1] == "L" and blink_on:
        img[12:18, 3:9] = (0, 200, 255)
    if code[2] == "R" and blink_on:
        img[12:18, width - 9:width - 3] = (0, 200, 255)
    return img


def make_ucm(root: Path, codes: Sequence[str], frames: int = 12,
             footage: str = "test-clip", steady: bool = False) -> Dict[str, Path]:
    """Write ``root/<footage>/<footage>_<XXX>/<footage>_<XXX>_<start>/light_mask/*.png``."""
    made = {}
    for k, code in enumerate(codes):
        start = 100 * (k + 1)
        seq = root / footage / f"{footage}_{code}" / f"{footage}_{code}_{start}" / "light_mask"
        seq.mkdir(parents=True)
        for f in range(frames):
            cv2.imwrite(str(seq / f"frame{start + f:08d}.png"), draw_rear(code, f, steady=steady))
        made[code] = seq
    return made


@pytest.mark.parametrize("code,brake,left,right,intent", [
    ("OOO", OFF, OFF, OFF, Intent.OFF),
    ("BOO", ON, OFF, OFF, Intent.OFF),
    ("OLO", OFF, ON, OFF, Intent.LEFT),
    ("BLO", ON, ON, OFF, Intent.LEFT),
    ("OOR", OFF, OFF, ON, Intent.RIGHT),
    ("BOR", ON, OFF, ON, Intent.RIGHT),
    ("OLR", OFF, ON, ON, Intent.HAZARD),
    ("BLR", ON, ON, ON, Intent.HAZARD),
])
def test_code_decoding(code, brake, left, right, intent):
    row = dict(zip(TASKS, ucm_labels(code).tolist()))
    assert row == {"intent": int(intent), "brake": brake, "left": left, "right": right,
                   "view": int(View.BEHIND)}


def test_unknown_code_rejected():
    with pytest.raises(ConfigError, match="UCM sequence code"):
        ucm_labels("XYZ")


def test_loader_reads_layout(tmp_path):
    make_ucm(tmp_path, ["OOO", "BLO", "OLR", "BOR"], frames=7)
    # Noise that must be ignored: a wrong code, a folder outside the layout, a stray file.
    bad = tmp_path / "test-clip" / "test-clip_XXX" / "test-clip_XXX_1" / "light_mask"
    bad.mkdir(parents=True)
    cv2.imwrite(str(bad / "frame00000001.png"), draw_rear("OOO", 0))
    (tmp_path / "test-clip" / "test-clip_BLO" / "test-clip_BLO_200" / "light_mask"
     / "notes.txt").write_text("x")
    crop = CropConfig(size=16, margin=0.1)
    tracks = load_ucm_tracks(tmp_path, crop)
    assert [t.source for t in tracks] == ["ucm:BLO", "ucm:BOR", "ucm:OLR", "ucm:OOO"]
    for t in tracks:
        assert len(t) == 7 and t.mask.all()
        assert t.labels.shape == (7, len(TASKS))
        assert (t.labels == ucm_labels(t.source[-3:])).all()
        assert t.lighting == "unknown" and np.isnan(t.occlusion).all()
        assert np.allclose(t.box_size, np.sqrt(24 * 32))
        assert np.all(np.diff(t.stamps_ns) > 0)
        crops = t.crop_window(0, 7)
        assert crops.shape == (7, 16, 16, 3) and crops.dtype == np.uint8
    # The crop is the whole image: with margin 0.1 the 32-wide image fills the middle.
    blo = tracks[0].crop_window(0, 1)[0]
    assert blo[8, 8].tolist() != [0, 0, 0]
    # Frame order follows the frame numbers: blinker lit on frames 0,1 and off on 2,3.
    hazard = tracks[2]
    lit = [int(hazard.crop_window(i, i + 1)[0][:, :, 2].max() > 150) for i in range(4)]
    assert lit == [1, 1, 0, 0]


def test_windows_are_shaped_and_padded(tmp_path):
    make_ucm(tmp_path, ["OOO", "OLR"], frames=5)
    tracks = load_ucm_tracks(tmp_path, CropConfig(size=16))
    ds = WindowDataset(tracks, seq_len=8, seed=3)
    item = next(iter(ds))
    assert item["crops"].shape == (8, 16, 16, 3)
    assert item["labels"].shape == (8, len(TASKS))
    assert item["mask"].tolist() == [True] * 5 + [False] * 3
    assert (item["labels"][5:] < 0).all()
    # stratified: the HAZARD and the plain window are drawn equally likely
    assert sorted(ds.strata) == ["hazard", "plain"]
    assert np.allclose(ds.probabilities, 0.5)


def test_empty_root_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match="no sequence in the UCM layout"):
        load_ucm_tracks(tmp_path)
