"""Fixed validation/test splits: the stream's sequences written to disk and read back.

A split is a directory with ``manifest.json`` and ``shard_NNN.npz`` files. Each shard
stores its sequences ragged (only the real observations, with each sequence's length), so
long evaluation tracks padded to ``seq_len`` cost no disk or memory for the padding.
``SequenceSplit`` gives back exactly the items that
``SyntheticSequenceStream(seed, seq_len, crop, mirror_prob=0, jitter=False, ...)`` yields,
in the same order.

From the shell::

    python -m signal_light_node.data.split OUT --seed 900001 --sequences 400 --seq-len 24
    python -m signal_light_node.data.split OUT --seed 900002 --sequences 200 --seq-len 90 --full-tracks
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections import OrderedDict
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
from torch.utils.data import Dataset
from tqdm import tqdm

from signal_light_node import __version__
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.data.stream import PAD_LABEL, Item, SyntheticSequenceStream
from signal_light_node.errors import ConfigError, SignalLightError
from signal_light_node.labels import CLASS_NAMES, TASKS

LOG = logging.getLogger(__name__)

MANIFEST = "manifest.json"
FORMAT_VERSION = 1
_STRING_META = ("lighting", "track_id", "kind", "lamp_design")
_PER_FRAME_META = ("box_size", "occlusion", "frame_index")


def _json_ready(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _write_shard(path: Path, items: List[Item]) -> None:
    lengths = np.array([int(item["mask"].sum()) for item in items], dtype=np.int64)
    for item, n in zip(items, lengths):
        if not item["mask"][:n].all():
            raise SignalLightError("split items must have their padding at the end only")

    def ragged(get) -> np.ndarray:
        return np.concatenate([get(item)[:n] for item, n in zip(items, lengths)])

    arrays = {
        "lengths": lengths,
        "crops": ragged(lambda it: it["crops"]),
        "labels": ragged(lambda it: it["labels"]),
        "lit_labels": ragged(lambda it: it["lit_labels"]),
        "fps": np.array([item["meta"]["fps"] for item in items], dtype=np.float64),
        "seed": np.array([item["meta"]["seed"] for item in items], dtype=np.int64),
    }
    if all("lit_maps" in item for item in items):
        arrays["lit_maps"] = ragged(lambda it: it["lit_maps"])
    for key in _PER_FRAME_META:
        arrays[key] = ragged(lambda it, k=key: it["meta"][k])
    for key in _STRING_META:
        arrays[key] = np.array([str(item["meta"][key]) for item in items])
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


def write_split(out_dir: "str | os.PathLike[str]", seed: int, n_sequences: int, seq_len: int,
                crop: CropConfig = CropConfig(), *, full_tracks: bool = False,
                shard_size: int = 256, overwrite: bool = False, progress: bool = True,
                **stream_kwargs: Any) -> Path:
    """Render a fixed split (no mirroring, no jitter) and write it to ``out_dir``.

    Args:
        out_dir: Directory to create (or reuse when empty or ``overwrite``).
        seed: Stream seed; use seeds never used for training.
        n_sequences: Number of items (windows, or whole tracks with ``full_tracks``).
        seq_len: Items' length T; with ``full_tracks`` the scene length in frames.
        crop: Crop configuration (must match the model's).
        full_tracks: Keep each track's whole observation list (padded to ``seq_len``).
        shard_size: Items per ``.npz`` shard.
        overwrite: Replace an existing split.
        progress: Show a tqdm progress bar.
        **stream_kwargs: Further ``SyntheticSequenceStream`` options (sizes, vehicles, fps,
            lighting, night_fraction, scene_frames, min_observations, renderer_overrides).

    Returns:
        The manifest's path.

    Raises:
        ConfigError: Bad counts, augmentation options, or an existing split without
            ``overwrite``.
    """
    if n_sequences < 1 or shard_size < 1:
        raise ConfigError(f"n_sequences and shard_size must be positive, got {n_sequences}, "
                          f"{shard_size}")
    for key in ("mirror_prob", "jitter", "rank"):
        if stream_kwargs.pop(key, None):
            raise ConfigError(f"a fixed split is written without augmentation; drop {key!r}")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise ConfigError(f"{out} is not empty; choose another directory or overwrite")
        for old in list(out.glob("shard_*.npz")) + [out / MANIFEST]:
            old.unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    stream = SyntheticSequenceStream(seed, seq_len, crop, mirror_prob=0.0, jitter=False,
                                     full_tracks=full_tracks, rank=0, **stream_kwargs)
    histogram = {task: np.zeros(len(CLASS_NAMES[task]), dtype=np.int64) for task in TASKS}
    lighting: Dict[str, int] = {}
    shards: List[Dict[str, Any]] = []
    n_observations = 0
    batch: List[Item] = []

    def flush() -> None:
        name = f"shard_{len(shards):03d}.npz"
        _write_shard(out / name, batch)
        shards.append({"file": name, "count": len(batch)})
        batch.clear()

    items = islice(stream.sequences(worker_id=0), n_sequences)
    for item in tqdm(items, total=n_sequences, desc=f"split {out.name}", unit="seq",
                     disable=not progress):
        valid = item["labels"][item["mask"]]
        n_observations += len(valid)
        for column, task in enumerate(TASKS):
            histogram[task] += np.bincount(valid[:, column], minlength=len(CLASS_NAMES[task]))
        lighting[item["meta"]["lighting"]] = lighting.get(item["meta"]["lighting"], 0) + 1
        batch.append(item)
        if len(batch) == shard_size:
            flush()
    if batch:
        flush()
    manifest = {
        "format": FORMAT_VERSION,
        "created_by": f"signal_light_node {__version__}",
        "seed": int(seed),
        "seq_len": int(seq_len),
        "full_tracks": bool(full_tracks),
        "n_sequences": int(n_sequences),
        "n_observations": int(n_observations),
        # fill only when set, so that the manifests of square crops read as before.
        "crop": dict({"size": crop.size, "margin": crop.margin},
                     **({"fill": True} if crop.fill else {})),
        "stream": _json_ready({k: v for k, v in stream_kwargs.items()}),
        "tasks": list(TASKS),
        "label_histogram": {task: {name: int(histogram[task][i])
                                   for i, name in enumerate(CLASS_NAMES[task])}
                            for task in TASKS},
        "lighting": lighting,
        "shards": shards,
    }
    path = out / MANIFEST
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    LOG.info("wrote %d sequences (%d observations) to %s", n_sequences, n_observations, out)
    return path


class SequenceSplit(Dataset):
    """A split written by :func:`write_split`, as a map-style dataset of sequence items.

    Shards are loaded whole on first use and the two most recent kept in memory, so
    reading in order (as evaluation does) decompresses each shard once.

    Args:
        out_dir: The split's directory.
        cache_shards: How many decoded shards to keep.

    Raises:
        SignalLightError: If the manifest is missing, of another format, or inconsistent.
    """

    def __init__(self, out_dir: "str | os.PathLike[str]", cache_shards: int = 2) -> None:
        self.root = Path(out_dir)
        path = self.root / MANIFEST
        try:
            manifest = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise SignalLightError(f"{self.root} is not a sequence split: cannot read "
                                   f"{path.name}: {exc}") from exc
        if manifest.get("format") != FORMAT_VERSION:
            raise SignalLightError(f"{path}: split format {manifest.get('format')!r} is not "
                                   f"the supported {FORMAT_VERSION}")
        if list(manifest.get("tasks", [])) != list(TASKS):
            raise SignalLightError(f"{path}: tasks {manifest.get('tasks')} differ from {list(TASKS)}")
        self.manifest = manifest
        self.seq_len = int(manifest["seq_len"])
        self.crop = CropConfig(**manifest["crop"])
        self._starts: List[Tuple[int, str, int]] = []  # (first index, file, count)
        total = 0
        for shard in manifest["shards"]:
            self._starts.append((total, shard["file"], int(shard["count"])))
            total += int(shard["count"])
        if total != int(manifest["n_sequences"]):
            raise SignalLightError(f"{path}: shards hold {total} sequences, manifest says "
                                   f"{manifest['n_sequences']}")
        self._length = total
        self._cache: "OrderedDict[str, Dict[str, np.ndarray]]" = OrderedDict()
        self._cache_shards = max(1, int(cache_shards))

    def __len__(self) -> int:
        return self._length

    def require_crop(self, crop: CropConfig, role: str = "split") -> None:
        """Raise ConfigError unless the split was cropped with ``crop`` (the model's).

        Args:
            crop: The crop settings the model was trained with.
            role: What the split is used as, for the message ("pool", "validation split").
        """
        if self.crop != crop:
            raise ConfigError(f"{role} {self.root} was cropped with {self.crop}, the model "
                              f"uses {crop}")

    def _shard(self, name: str) -> Dict[str, np.ndarray]:
        shard = self._cache.get(name)
        if shard is not None:
            self._cache.move_to_end(name)
            return shard
        try:
            with np.load(self.root / name, allow_pickle=False) as data:
                shard = {key: data[key] for key in data.files}
        except (OSError, ValueError, KeyError) as exc:
            raise SignalLightError(f"cannot read shard {self.root / name}: {exc}") from exc
        shard["offsets"] = np.concatenate([[0], np.cumsum(shard["lengths"])])
        self._cache[name] = shard
        while len(self._cache) > self._cache_shards:
            self._cache.popitem(last=False)
        return shard

    def __getitem__(self, index: int) -> Item:
        if index < 0:
            index += self._length
        if not 0 <= index < self._length:
            raise IndexError(f"index {index} out of range for a split of {self._length}")
        first, name, count = next(s for s in reversed(self._starts) if s[0] <= index)
        shard = self._shard(name)
        i = index - first
        a, b = int(shard["offsets"][i]), int(shard["offsets"][i + 1])
        n, t, s = b - a, self.seq_len, self.crop.size
        crops = np.zeros((t, s, s, 3), dtype=np.uint8)
        crops[:n] = shard["crops"][a:b]
        labels = np.full((t, len(TASKS)), PAD_LABEL, dtype=np.int64)
        labels[:n] = shard["labels"][a:b]
        item: Item = {"crops": crops, "labels": labels}
        if "lit_labels" in shard:  # splits written before 2026-11-21 16:00 lack them
            lit_labels = np.full((t, len(TASKS)), PAD_LABEL, dtype=np.int64)
            lit_labels[:n] = shard["lit_labels"][a:b]
            item["lit_labels"] = lit_labels
        if "lit_maps" in shard:  # only splits written with --lit-maps
            maps = shard["lit_maps"]
            item["lit_maps"] = np.zeros((t,) + maps.shape[1:], dtype=np.uint8)
            item["lit_maps"][:n] = maps[a:b]
        mask = np.zeros(t, dtype=bool)
        mask[:n] = True
        meta: Dict[str, Any] = {"fps": float(shard["fps"][i]), "seed": int(shard["seed"][i]),
                                "mirrored": False}
        for key in _STRING_META:
            meta[key] = str(shard[key][i])
        for key in _PER_FRAME_META:
            column = shard[key]
            values = np.full(t, -1 if key == "frame_index" else 0, dtype=column.dtype)
            values[:n] = column[a:b]
            meta[key] = values
        item.update(mask=mask, meta=meta)
        return item

    def summary(self) -> Dict[str, Any]:
        """The manifest's counts and label histogram."""
        return {k: self.manifest[k] for k in ("seed", "seq_len", "full_tracks", "n_sequences",
                                               "n_observations", "label_histogram", "lighting")}


#: The renderer's share overrides the command takes (``synth.SceneRenderer``), with what
#: each is a share of. Evaluation splits are drawn without any of them.
RENDERER_SHARES = {
    "oblique": "front and rear views drawn turned (10-40 degrees: foreshortened, flank in view)",
    "tail_glare": "lit vehicles in dusk and night scenes whose tail lamps are drawn clipped "
                  "like a brake (synth.traffic.Vehicle.glare)",
    "rear_bar": "rear views given a full-width tail bar joining their side clusters "
                "(synth.lamps.tail_bar)",
    "wide_truck_lamps": "truck and bus rear views whose side clusters are drawn as wide as "
                        "real combination lamps (synth.lamps.widen_clusters)",
    "night_streak": "dusk and night scenes whose camera smears over-exposed light along its "
                    "row (synth.camera.CameraParams.streak)",
    "night_clip": "night scenes whose camera exposes for a lit street and turns clipped light "
                  "white (synth.camera.CameraParams.white_clip)",
    "night_bloom": "dusk and night scenes whose camera spreads over-exposed light into a round "
                   "halo (synth.camera.CameraParams.bloom)",
    "glare_tail_hot": "tail_glare vehicles whose tail lamps' core and glow are drawn at their "
                      "brake's colour (synth.traffic.Vehicle.tail_hot)",
    "glare_tail_bright": "tail_glare vehicles whose tail lamps shine over the clip as brightly "
                         "as another vehicle's brake, their brake brighter still "
                         "(synth.traffic.BRIGHT_TAIL_LEVEL)",
    "foreign_lamp": "vehicles with a lamp beyond them, over the roof or beside, inside their "
                    "crop (synth.foreign_lamps)",
    "foreign_high": "foreign_lamp lamps drawn red over the middle of the roof, where a centre "
                    "high-mounted stop lamp would be (synth.foreign_lamps.high_foreign_lamp)",
    "brake_share": "the time a brake is pressed and tracks first seen braking (0: the "
                   "renderer's own, about 40 %; synth.lamps.brake_timeline)",
    "turn_hue": "vehicles whose blinkers, and the amber markers that match them, shine in a "
                "random hue (synth.lamps.recolour_turn_lamps)",
}


def main(argv: Optional[List[str]] = None) -> int:
    """Write a split from the command line (``python -m signal_light_node.data.split``)."""
    from signal_light_node.synth.truth import TRUTH_RULES  # heavy; the command renders anyway

    parser = argparse.ArgumentParser(prog="python -m signal_light_node.data.split",
                                     description="materialise a fixed synthetic split")
    parser.add_argument("out", help="directory to write")
    parser.add_argument("--seed", type=int, required=True, help="stream seed (never trained on)")
    parser.add_argument("--sequences", type=int, required=True, help="number of items")
    parser.add_argument("--seq-len", type=int, default=16, help="T, or frames per scene "
                        "with --full-tracks (default 16)")
    parser.add_argument("--full-tracks", action="store_true",
                        help="whole tracks of each scene instead of windows")
    parser.add_argument("--crop-size", type=int, default=CropConfig.size)
    parser.add_argument("--crop-margin", type=float, default=CropConfig.margin)
    parser.add_argument("--crop-fill", action="store_true",
                        help="stretch each grown box to the square crop instead of squaring "
                        "it (crops.CropConfig.fill)")
    parser.add_argument("--lighting", choices=("day", "dusk", "night"), default=None,
                        help="one lighting for every scene (default: drawn per scene)")
    parser.add_argument("--lit-maps", action="store_true",
                        help="store where each vehicle's signal lamps are lit (training target)")
    for key, text in RENDERER_SHARES.items():
        parser.add_argument("--" + key.replace("_", "-"), type=float, default=0.0,
                            metavar="SHARE", help=f"share of {text}; default 0")
    parser.add_argument("--truth-rule", choices=TRUTH_RULES, default=TRUTH_RULES[0],
                        help="how large the seen lamps of a light must be for it to be "
                        "labelled (synth.truth.TRUTH_RULES); default %(default)s")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    overrides = {key: getattr(args, key) for key in RENDERER_SHARES if getattr(args, key)}
    if args.truth_rule != TRUTH_RULES[0]:
        overrides["truth_rule"] = args.truth_rule
    extra = {"renderer_overrides": overrides} if overrides else {}
    return write_and_summarise(lambda: write_split(
        args.out, args.seed, args.sequences, args.seq_len,
        CropConfig(args.crop_size, args.crop_margin, args.crop_fill),
        full_tracks=args.full_tracks, overwrite=args.overwrite, lighting=args.lighting,
        lit_maps=args.lit_maps, **extra))


def write_and_summarise(write: Callable[[], Path]) -> int:
    """A command's end: run ``write`` (it returns the new split's manifest path), print the
    split's summary as JSON and return 0, or print its error in one line and return 2."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        path = write()
    except SignalLightError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(SequenceSplit(path.parent).summary(), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
