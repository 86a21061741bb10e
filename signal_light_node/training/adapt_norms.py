"""Adapting without labels: move a model's batch-norm statistics to new recordings.

``signal-light adapt BAG... --out MODEL`` (``commands/adapt.py``) takes a checkpoint and
unlabelled recordings of the user's camera (bags, read and paired as the node reads
them, :func:`.sources.load_unlabelled_bag_tracks`; or materialised splits, whose labels
are ignored) and writes a copy of the checkpoint whose batch-norm running statistics
follow the new data. Nothing else is refit: every weight and every other buffer stays as
it was, so the adapted model has the same architecture, loads and exports (ONNX, int8)
like the one it came from.

Two methods (``AdaptSettings.method``):

* ``shift`` (the default): each running mean moves by how far the new data's mean lies
  from the **reference**, the same statistic measured the same way on data like the
  model's training data; the running variances stay. The stored statistics of a model
  need not be those of its training data as stepped here (the shipped CNN's last stage
  trained with frozen norms on top of an earlier stage's statistics), and the heads are
  tuned to them: on data like the training data a shift changes nothing, where a
  replacement would. Variances are kept because a camera with stronger contrast then
  still gives the first layer stronger lamp evidence, which the heads read (measured:
  docs/results/adapt_family.md). The reference is stored in the checkpoint
  (``meta["norm_reference"]``), measured from ``--reference DATA`` or carried over; an
  adapted checkpoint's reference is the data it was adapted on, so adapting it again
  shifts from there and never twice.
* ``replace``: the running means and variances become the new data's (plain AdaBN).

The first ``keep_first`` batch-norm layers are left as they are (default
:func:`default_keep_first`: the trunk model's stem, none of the CNN's). The trunk's stem
normalises the raw colour and tone; its per-frame stage learnt under random camera
responses, so what a shift there removes on a new camera is partly the lamps' own colour
(measured on the held-out style family: the stem's shift alone costs 0.9 points of brake
F1, the shift of every other layer costs nothing; docs/results/adapt_family.md). A kept
layer keeps its reference too, so a later adaptation shifts it from the same place.

How the statistics are taken:

* every track is stepped in frame order from a fresh state (``model.initial_state``,
  ``model.forward_sequence`` in windows with the state carried), so inputs that depend on
  a track's history (the CNN's temporal channels, the trunk model's relative evidence)
  are what they are in the node; frames without a usable crop are skipped, as the engine
  never steps them;
* tracks are batched (``batch_tracks`` side by side, ``window_frames`` frames per call),
  so a batch-norm layer sees many vehicles and moments per call;
* only the batch-norm layers are in train mode (everything else in eval mode: no
  dropout), under ``torch.no_grad()``; their running statistics are reset first and then
  averaged cumulatively over every call, each call weighted by its frames (``momentum``
  set per call to ``frames of the call / frames so far``; with calls of equal size this
  is ``momentum=None``'s plain cumulative average, but the last, short windows of the
  longest tracks would otherwise weigh as much as full ones).

The same data, settings and torch thread count give the same tensors (another thread
count changes the sums' rounding: about 1e-4 on the running variances).

A model without batch norm (``norm: group``), data without a single usable crop, or a
``shift`` without a reference is refused (:class:`~signal_light_node.errors.ConfigError`)
before anything is written; the checkpoint is written through
:func:`~signal_light_node.model.checkpoint.save_checkpoint` (a temporary file renamed into
place) with ``meta["adapted"]`` saying from what, on what and how.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import nn

from signal_light_node.errors import BagIOError, ConfigError
from signal_light_node.evaluation.streaming import chunks
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.model.checkpoint import FILE_META
from signal_light_node.model.interface import State, select_state, to_input
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.runtime.pairing import PairingConfig

logger = logging.getLogger(__name__)

#: How adapted statistics are formed (see the module doc).
METHODS = ("shift", "replace")
#: Where a checkpoint keeps the reference statistics a ``shift`` starts from.
REFERENCE_KEY = "norm_reference"

#: Per batch-norm layer name, ``{"mean": [C], "var": [C]}`` float tensors (on the CPU).
NormStats = Dict[str, Dict[str, torch.Tensor]]


@dataclass(frozen=True)
class AdaptSettings:
    """How the statistics are taken.

    Attributes:
        batch_tracks: Tracks stepped side by side.
        window_frames: Frames of each track per ``forward_sequence`` call.
        max_frames: Cap on the frames (crops) used; tracks are then drawn in an order
            shuffled with ``seed`` and the last one taken is cut short. None: all.
        seed: Seed of that draw (the only randomness).
        device: Where the model runs.
        method: ``shift`` or ``replace`` (see the module doc).
        keep_first: The first N batch-norm layers (in the model's order) are left as
            they are; None: :func:`default_keep_first` of the model.
    """

    batch_tracks: int = 16
    window_frames: int = 32
    max_frames: Optional[int] = None
    seed: int = 0
    device: str = "cpu"
    method: str = "shift"
    keep_first: Optional[int] = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got "
                              f"{self.method!r}")
        if self.batch_tracks < 1 or self.window_frames < 1:
            raise ConfigError(f"batch tracks and window frames must be >= 1, got "
                              f"{self.batch_tracks} and {self.window_frames}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ConfigError(f"--max-frames must be >= 1, got {self.max_frames}")
        if self.keep_first is not None and self.keep_first < 0:
            raise ConfigError(f"--keep-first must be >= 0, got {self.keep_first}")


def default_keep_first(config: Any) -> int:
    """Batch-norm layers ``adapt`` leaves alone by default: the pretrained trunk's stem (1),
    none of the CNN's (module doc)."""
    return 0 if config.encoder == "cnn" else 1


@dataclass(frozen=True)
class InputReading:
    """How bags are read (a split needs none of it): topics and pairing, as in ``replay``."""

    image_topic: Optional[str] = None
    detection_topic: Optional[str] = None
    pairing: PairingConfig = field(default_factory=PairingConfig)


@dataclass
class AdaptResult:
    """What :func:`adapt_checkpoint` did.

    Attributes:
        out: The checkpoint written.
        source: The checkpoint adapted.
        inputs: The bags and splits read.
        layers: Batch-norm layers adapted.
        tracks: Tracks stepped.
        frames: Frames (crops) stepped.
        mean_shift: Per layer, the mean over channels of ``|new mean - old mean| / old sd``.
        var_ratio: Per layer, the median over channels of ``new var / old var``.
        method: ``shift`` or ``replace``.
        reference: What the reference statistics were measured on (empty: none used).
        kept: The batch-norm layers left as they were (``keep_first``).
    """

    out: Path
    source: Path
    inputs: List[Path]
    layers: int
    tracks: int
    frames: int
    mean_shift: Dict[str, float]
    var_ratio: Dict[str, float]
    method: str = "shift"
    reference: List[str] = field(default_factory=list)
    kept: List[str] = field(default_factory=list)

    def summary_lines(self) -> List[str]:
        """What the command prints."""
        shifts = np.array(list(self.mean_shift.values()))
        ratios = np.array(list(self.var_ratio.values()))
        names = ", ".join(str(p) for p in self.inputs)
        how = (f"running means of {self.layers} batch-norm layers shifted by this data's "
               f"mean less the reference's ({', '.join(self.reference)}); variances kept"
               if self.method == "shift" else
               f"batch-norm statistics of {self.layers} layers replaced by this data's")
        if self.kept:
            how += f"; the first {len(self.kept)} left as they were ({', '.join(self.kept)})"
        moved = (f"running means moved {shifts.mean():.2f} old sd on average over the "
                 f"adapted layers (largest layer "
                 f"{shifts.max():.2f})")
        if self.method != "shift":  # a shift keeps every variance
            moved += (f"; running variances x{np.median(ratios):.2f} (median layer, range "
                      f"x{ratios.min():.2f}-x{ratios.max():.2f})")
        return [
            f"adapted {self.source} on {self.frames} frames of {self.tracks} tracks ({names})",
            f"{how}; every other weight and buffer unchanged",
            moved,
            f"wrote {self.out}",
        ]


@dataclass
class ReferenceResult:
    """What :func:`record_reference` did: a checkpoint copy that carries reference statistics.

    Attributes:
        out: The checkpoint written.
        source: The checkpoint it copies.
        data: The bags and splits the reference was measured on.
        layers: Batch-norm layers measured.
        tracks: Tracks stepped.
        frames: Frames (crops) stepped.
    """

    out: Path
    source: Path
    data: List[Path]
    layers: int
    tracks: int
    frames: int

    def summary_lines(self) -> List[str]:
        """What the command prints."""
        names = ", ".join(str(p) for p in self.data)
        return [f"measured the reference statistics of {self.layers} batch-norm layers of "
                f"{self.source} on {self.frames} frames of {self.tracks} tracks ({names})",
                "weights and running statistics unchanged; a later 'adapt' shifts from this "
                "reference",
                f"wrote {self.out}"]


# ---------------------------------------------------------------------------- data


def check_inputs(paths: Sequence[Path]) -> None:
    """Refuse an empty list or a path that does not exist (before anything is loaded).

    Raises:
        ConfigError: No input given.
        BagIOError: A path does not exist.
    """
    if not paths:
        raise ConfigError("give at least one bag or split directory to adapt on")
    for path in paths:
        if not Path(path).exists():
            raise BagIOError(f"bag {path} does not exist")


def load_unlabelled_tracks(paths: Sequence[Path], crop: CropConfig,
                           reading: InputReading = InputReading()) -> List[TrackSequence]:
    """Every track of the bags and splits, in the order given (labels are not used).

    Raises:
        BagIOError: A bag cannot be read or has no image with detections.
        ConfigError: A split was cropped with other settings than ``crop``.
    """
    from signal_light_node.training.sources import load_unlabelled_bag_tracks, tracks_from

    return tracks_from(paths, crop, "adaptation data", lambda path: load_unlabelled_bag_tracks(
        path, crop, reading.image_topic, reading.detection_topic, pairing=reading.pairing))


def stepped_crops(tracks: Sequence[TrackSequence], max_frames: Optional[int] = None,
                  seed: int = 0) -> List[np.ndarray]:
    """Per track, the uint8 crops ``[n, S, S, 3]`` of the frames the engine would step
    (mask True), in order; tracks without such a frame are left out. With ``max_frames``,
    only the tracks ``cap_frames`` keeps are cut out (a copy of every pool's crops would
    not fit in memory)."""
    stepped = [(track, np.asarray(track.mask, bool)) for track in tracks]
    stepped = [(track, mask) for track, mask in stepped if mask.any()]
    plan = cap_plan([int(mask.sum()) for _, mask in stepped], max_frames, seed)
    return [stepped[i][0].crop_window(0, len(stepped[i][0]))[stepped[i][1]][:take]
            for i, take in plan]


def cap_plan(lengths: Sequence[int], max_frames: Optional[int], seed: int
             ) -> List[Tuple[int, int]]:
    """``(index, frames kept)`` of the sequences of ``lengths`` that ``cap_frames`` keeps."""
    if max_frames is None or sum(lengths) <= max_frames:
        return [(i, n) for i, n in enumerate(lengths)]
    plan, left = [], int(max_frames)
    for index in np.random.default_rng(seed).permutation(len(lengths)):
        if left <= 0:
            break
        plan.append((int(index), min(int(lengths[index]), left)))
        left -= plan[-1][1]
    return plan


def cap_frames(sequences: List[np.ndarray], max_frames: Optional[int], seed: int
               ) -> List[np.ndarray]:
    """At most ``max_frames`` frames: whole tracks in an order shuffled with ``seed``, the
    last one cut short; all of them, in their order, when under the cap or uncapped."""
    plan = cap_plan([len(s) for s in sequences], max_frames, seed)
    return [sequences[i][:take] for i, take in plan]


# -------------------------------------------------------------------------- stepping


def batch_norm_layers(model: nn.Module) -> List[Tuple[str, nn.Module]]:
    """``(name, module)`` of every batch-norm layer of ``model``."""
    return [(name, m) for name, m in model.named_modules()
            if isinstance(m, nn.modules.batchnorm._BatchNorm)]


def _frame_weighting(seen: Dict[nn.Module, int]) -> Callable[[nn.Module, Any], None]:
    """A forward pre-hook that weights each call of a batch-norm layer by its frames."""

    def hook(module: nn.Module, inputs: Any) -> None:
        n = int(inputs[0].shape[0])
        seen[module] = seen.get(module, 0) + n
        module.momentum = n / seen[module]

    return hook


def _step_chunk(model: nn.Module, chunk: List[np.ndarray], window: int, device: str) -> None:
    """Step one batch of tracks through the model, windows of ``window`` frames, the state
    carried; a track that has ended drops out of the batch (tracks sorted longest first)."""
    chunk = sorted(chunk, key=len, reverse=True)
    lengths = [len(s) for s in chunk]
    state: State = model.initial_state(len(chunk))
    start = 0
    while start < lengths[0]:
        k = sum(1 for n in lengths if n > start)
        stop = min(start + window, lengths[k - 1])
        crops = np.stack([s[start:stop] for s in chunk[:k]])
        t, size = crops.shape[1], crops.shape[2]
        x = to_input(crops.reshape((k * t,) + crops.shape[2:])).to(device)
        x = x.reshape(k, t, 3, size, size)
        if k < state[0][0].shape[0]:
            state = select_state(state, torch.arange(k, device=x.device))
        _, state = model.forward_sequence(x, state)
        start = stop


def reestimate_batch_norms(model: nn.Module, sequences: Sequence[np.ndarray],
                           settings: AdaptSettings = AdaptSettings(),
                           progress: bool = False) -> int:
    """Replace the running statistics of every batch-norm layer of ``model`` by those of
    the activations on ``sequences`` (see the module doc); returns the frames stepped.

    The model is left in eval mode with its layers' ``momentum`` as it was.

    Raises:
        ConfigError: The model has no batch-norm layer, or ``sequences`` no frame.
    """
    from tqdm import tqdm

    layers = [m for _, m in batch_norm_layers(model)]
    if not layers:
        raise ConfigError("the model has no batch-norm layer: nothing to re-estimate")
    frames = sum(len(s) for s in sequences)
    if not frames:
        raise ConfigError("no frame to re-estimate the batch norms on")
    momenta = [m.momentum for m in layers]
    seen: Dict[nn.Module, int] = {}
    hooks = [m.register_forward_pre_hook(_frame_weighting(seen)) for m in layers]
    model.eval()
    for m in layers:
        m.reset_running_stats()
        m.train()
    try:
        batches = list(chunks(sequences, settings.batch_tracks))
        with torch.no_grad():
            for chunk in tqdm(batches, desc="adapt", unit="batch", disable=not progress):
                _step_chunk(model, chunk, settings.window_frames, settings.device)
    finally:
        for hook in hooks:
            hook.remove()
        for m, momentum in zip(layers, momenta):
            m.momentum = momentum
        model.eval()
    unseen = [name for name, m in batch_norm_layers(model) if m not in seen]
    if unseen:
        raise ConfigError(f"batch-norm layers never reached by a step: {unseen[:3]}")
    return frames


def measure_batch_norms(model: nn.Module, sequences: Sequence[np.ndarray],
                        settings: AdaptSettings = AdaptSettings(),
                        progress: bool = False) -> NormStats:
    """The running statistics every batch-norm layer of ``model`` takes on ``sequences``
    (as :func:`reestimate_batch_norms` takes them); the model's own are left as they were.

    Raises:
        ConfigError: The model has no batch-norm layer, or ``sequences`` no frame.
    """
    layers = batch_norm_layers(model)
    saved = {name: {k: v.clone() for k, v in m.state_dict().items()} for name, m in layers}
    try:
        reestimate_batch_norms(model, sequences, settings, progress)
        return {name: {"mean": m.running_mean.detach().cpu().clone(),
                       "var": m.running_var.detach().cpu().clone()} for name, m in layers}
    finally:
        for name, m in layers:
            m.load_state_dict(saved[name])


def check_stats(stats: NormStats, model: nn.Module, what: str) -> None:
    """Refuse statistics that do not cover every batch-norm layer of ``model`` channel for
    channel (another architecture's, or a damaged checkpoint's).

    Raises:
        ConfigError: Naming the first layer that does not match.
    """
    for name, m in batch_norm_layers(model):
        entry = stats.get(name)
        if (not isinstance(entry, dict) or any(
                not isinstance(entry.get(k), torch.Tensor)
                or tuple(entry[k].shape) != tuple(m.running_mean.shape) for k in ("mean", "var"))):
            raise ConfigError(f"{what} do not match the model's batch-norm layer {name!r}")


def apply_stats(model: nn.Module, target: NormStats, method: str,
                reference: Optional[NormStats] = None, keep: Sequence[str] = ()) -> None:
    """Set the running statistics of ``model`` from the ``target`` data's: ``replace``
    takes them; ``shift`` moves each running mean by ``target - reference`` and keeps the
    variances (see the module doc). Layers named in ``keep`` are left alone."""
    for name, m in batch_norm_layers(model):
        if name in keep:
            continue
        mean, var = target[name]["mean"], target[name]["var"]
        with torch.no_grad():
            if method == "replace":
                m.running_mean.copy_(mean.to(m.running_mean))
                m.running_var.copy_(var.to(m.running_var))
            else:
                assert reference is not None, "a shift needs reference statistics"
                m.running_mean.add_((mean - reference[name]["mean"]).to(m.running_mean))


def _changes(before: Dict[str, torch.Tensor], model: nn.Module
             ) -> Tuple[Dict[str, float], Dict[str, float]]:
    """Per layer: mean |shift of the running mean| in old sd, median new/old variance."""
    shift, ratio = {}, {}
    for name, m in batch_norm_layers(model):
        old_mean, old_var = before[f"{name}.running_mean"], before[f"{name}.running_var"]
        sd = old_var.clamp_min(m.eps).sqrt()
        shift[name] = float(((m.running_mean.cpu() - old_mean).abs() / sd).mean())
        ratio[name] = float((m.running_var.cpu() / old_var.clamp_min(m.eps)).median())
    return shift, ratio


# ------------------------------------------------------------------------ checkpoint


def reference_entry(stats: NormStats, data: Sequence[Path], tracks: int,
                    frames: int) -> Dict[str, Any]:
    """``meta["norm_reference"]``: the statistics and what they were measured on."""
    return {"data": [str(p) for p in data], "tracks": int(tracks), "frames": int(frames),
            "layers": stats}


def stored_reference(meta: Dict[str, Any]) -> Optional[NormStats]:
    """The reference statistics a checkpoint carries, or None."""
    entry = meta.get(REFERENCE_KEY)
    return None if not isinstance(entry, dict) else entry.get("layers")


def adapted_meta(meta: Dict[str, Any], source: Path, result: AdaptResult,
                 settings: AdaptSettings) -> Dict[str, Any]:
    """The adapted checkpoint's metadata: the source's (training data, metrics, notes),
    less what describes the file itself, plus ``adapted`` (from what, on what, how)."""
    info = {k: v for k, v in meta.items() if k not in FILE_META}
    info["adapted"] = {
        "method": ("batch-norm running means shifted by the data's mean less the "
                   "reference's, variances kept" if settings.method == "shift" else
                   "batch-norm running statistics replaced by the data's")
                  + " (signal-light adapt, without labels); every other weight as in 'from'",
        "from": str(source), "from_created": meta.get("created"),
        "previous": meta.get("adapted"),
        "data": [str(p) for p in result.inputs], "reference": result.reference,
        "tracks": result.tracks, "frames": result.frames, "batch_norm_layers": result.layers,
        "kept_layers": list(result.kept),
        "settings": {k: v for k, v in asdict(settings).items() if k != "device"},
        "mean_shift_sd": result.mean_shift, "var_ratio": result.var_ratio,
    }
    return info


def _kept_reference(target: NormStats, keep: Sequence[str], model: nn.Module,
                    old: Optional[Dict[str, Any]]) -> NormStats:
    """The adapted file's reference: the new data's statistics, except that a kept layer
    keeps its old reference (or, without one, its own running statistics)."""
    layers = dict(target)
    bns = dict(batch_norm_layers(model))
    for name in keep:
        if old is not None and name in old.get("layers", {}):
            layers[name] = old["layers"][name]
        else:
            m = bns[name]
            layers[name] = {"mean": m.running_mean.detach().cpu().clone(),
                            "var": m.running_var.detach().cpu().clone()}
    return layers


def _load_adaptable(checkpoint: Optional[Path], device: str) -> Tuple[Path, Any]:
    """The checkpoint's path and loaded model; refused when it has no batch norm."""
    from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint

    source = Path(DEFAULT_WEIGHTS if checkpoint is None else checkpoint)
    loaded = load_checkpoint(source, map_location=device)
    if not batch_norm_layers(loaded.model):
        raise ConfigError(f"{source} has no batch-norm layer (norm: {loaded.config.norm}): "
                          "there are no statistics to adapt")
    return source, loaded


def _stepped(inputs: Sequence[Path], loaded: Any, settings: AdaptSettings,
             reading: InputReading) -> List[np.ndarray]:
    """The crop sequences of ``inputs`` the statistics are taken on (capped, refused if
    there is none)."""
    tracks = load_unlabelled_tracks(inputs, loaded.config.crop_config(), reading)
    sequences = stepped_crops(tracks, settings.max_frames, settings.seed)
    if not sequences:
        raise ConfigError(f"no usable crop in {', '.join(map(str, inputs))}: "
                          f"{len(tracks)} tracks, none with a box that can be cropped")
    return sequences


def _measured_reference(loaded: Any, data: Sequence[Path], settings: AdaptSettings,
                        reading: InputReading, progress: bool) -> Dict[str, Any]:
    """``meta["norm_reference"]`` measured on ``data``."""
    sequences = _stepped(data, loaded, settings, reading)
    stats = measure_batch_norms(loaded.model, sequences, settings, progress)
    return reference_entry(stats, data, len(sequences), sum(len(s) for s in sequences))


def adapt_checkpoint(out: Path, inputs: Sequence[Path], checkpoint: Optional[Path] = None,
                     settings: AdaptSettings = AdaptSettings(),
                     reading: InputReading = InputReading(),
                     progress: bool = False,
                     reference: Sequence[Path] = ()) -> AdaptResult:
    """Load ``checkpoint``, adapt its batch norms to ``inputs``, write ``out``.

    Args:
        out: The adapted checkpoint (a temporary file renamed into place).
        inputs: Bags and split directories (labels, if any, are not read).
        checkpoint: The checkpoint to adapt (default: the shipped weights).
        settings: How the statistics are taken and applied.
        reading: Topics and pairing of the bags.
        progress: Show a progress bar.
        reference: Data like the model's training data to measure the reference on
            (``shift``); empty: the reference the checkpoint carries.

    Returns:
        What was done (:class:`AdaptResult`); ``out`` carries the statistics of
        ``inputs`` as its reference.

    Raises:
        ConfigError: The model has no batch norm, the data no usable crop, or a ``shift``
            has no reference (or one of another model); nothing is written.
        BagIOError: An input is missing or unreadable.
        CheckpointError: The checkpoint cannot be loaded or ``out`` written.
    """
    from signal_light_node.model.checkpoint import save_checkpoint

    inputs, reference = [Path(p) for p in inputs], [Path(p) for p in reference]
    check_inputs(inputs)
    if reference:
        check_inputs(reference)
    source, loaded = _load_adaptable(checkpoint, settings.device)
    ref_entry = loaded.meta.get(REFERENCE_KEY)
    if settings.method == "shift" and not reference and stored_reference(loaded.meta) is None:
        raise ConfigError(f"{source} carries no reference statistics ({REFERENCE_KEY}) to "
                          "shift from: give --reference with data like its training data, "
                          "or --method replace")
    if reference:
        ref_entry = _measured_reference(loaded, reference, settings, reading, progress)
    if settings.method == "shift":
        check_stats(ref_entry["layers"], loaded.model, f"the reference statistics of {source}")
    sequences = _stepped(inputs, loaded, settings, reading)
    layers = [name for name, _ in batch_norm_layers(loaded.model)]
    n_keep = settings.keep_first
    if n_keep is None:
        n_keep = default_keep_first(loaded.config)
    if n_keep >= len(layers):
        raise ConfigError(f"--keep-first {n_keep} leaves none of the {len(layers)} batch-norm "
                          f"layers of {source} to adapt")
    keep = layers[:n_keep]
    before = {k: v.detach().cpu().clone() for k, v in loaded.model.state_dict().items()}
    target = measure_batch_norms(loaded.model, sequences, settings, progress)
    apply_stats(loaded.model, target, settings.method,
                ref_entry["layers"] if settings.method == "shift" else None, keep)
    frames = sum(len(s) for s in sequences)
    shift, ratio = _changes(before, loaded.model)
    for name in keep:  # unchanged by design: not part of the "moved" figures
        del shift[name], ratio[name]
    result = AdaptResult(out=Path(out), source=source, inputs=inputs,
                         layers=len(shift), tracks=len(sequences), frames=frames,
                         mean_shift=shift, var_ratio=ratio, method=settings.method,
                         reference=list(ref_entry["data"]) if settings.method == "shift"
                         else [], kept=keep)
    meta = adapted_meta(loaded.meta, source, result, settings)
    meta[REFERENCE_KEY] = reference_entry(
        _kept_reference(target, keep, loaded.model, ref_entry), inputs, len(sequences), frames)
    save_checkpoint(out, loaded.model, loaded.config, meta)
    logger.info("adapted %s (%s): %d batch-norm layers on %d frames of %d tracks -> %s",
                source, settings.method, result.layers, frames, result.tracks, out)
    return result


def record_reference(out: Path, data: Sequence[Path], checkpoint: Optional[Path] = None,
                     settings: AdaptSettings = AdaptSettings(),
                     reading: InputReading = InputReading(),
                     progress: bool = False) -> ReferenceResult:
    """Write a copy of ``checkpoint`` that carries reference statistics measured on
    ``data`` (data like its training data), its weights and statistics unchanged.

    Raises:
        ConfigError: The model has no batch norm, or the data no usable crop.
        BagIOError: An input is missing or unreadable.
        CheckpointError: The checkpoint cannot be loaded or ``out`` written.
    """
    from signal_light_node.model.checkpoint import save_checkpoint

    data = [Path(p) for p in data]
    check_inputs(data)
    source, loaded = _load_adaptable(checkpoint, settings.device)
    entry = _measured_reference(loaded, data, settings, reading, progress)
    meta = dict(loaded.meta, **{REFERENCE_KEY: entry})  # the same model: all else kept
    save_checkpoint(out, loaded.model, loaded.config, meta)
    return ReferenceResult(out=Path(out), source=source, data=data,
                           layers=len(entry["layers"]), tracks=entry["tracks"],
                           frames=entry["frames"])
