#!/usr/bin/env python3
"""One model pass per data set, then the node's filter under many settings.

The model is stepped over every track once (``evaluation.streaming.model_track_probs``,
cached in ``--cache`` as one pickle per data set and checkpoint), and each filter setting
(``--config``, a JSON object of ``IntentFilterConfig`` fields; ``{}`` is the node's
defaults) and each shift of the brake's ON logit (``--brake-shift``, on top of the file's
own ``on_offsets``), each with each ``--brake-side-shift`` (more ON log-odds in proportion
to the view head's side mass, P(LEFT) + P(RIGHT)), is scored on that pass as ``signal-light
evaluate`` scores it (no grace). Besides the headline it prints brake F1 on rear views
alone, the one face from which a brake is always in sight, and on side views, and the share
of judged frames published braking (on a bag whose vehicles never brake, the false brakes)
and the share of brake-OFF frames published ON (on night negatives with braking vehicles
among them, ``training.night_bound``'s false brakes), the same share of judged blinker
frames published ON, the view head's accuracy and the share of lamps published UNKNOWN
where their truth is OFF or ON (``evaluation.metrics.unknown_where_visible``). With
``--blinkers PART`` the blinker heads' outputs are taken in part from the truth
(:data:`BLINKER_PARTS`), which tells where the intent is lost: in whether a blinker can be
seen, in ON against OFF, or in the filter itself (docs/model.md, "Where the intent is
lost"); ``--blinkers lit`` gives them a perfect
per-frame eye instead (a split's lit labels). ``--blinker-lag ONSET OFFSET`` makes the truth's
blinker states late as a causal detector must be (ON from ``ONSET`` seconds into an episode
until ``OFFSET`` seconds after it ends): what a perfect but causal eye would give (docs/model.md,
"What a causal eye could reach"). Usage::

    python scripts/filter_sweep.py --checkpoint signal_light_node/weights/default.pt \\
        --data cal=runs/fillf/family_cal_split --data night=bags/night_tail_lamps \\
        --config '{}' --config '{"hold_s": 0.3}' --brake-shift 0 --brake-shift 0.5 \\
        --cache runs/sweep --json OUT.json

A data set is a split directory or a directory of recorded bags with ground truth.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import metrics_from_confusion, unknown_where_visible
from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
from signal_light_node.evaluation.streaming import chunks, model_track_probs, score_batch
from signal_light_node.labels import TASKS, LightStatus
from signal_light_node.model.backends.registry import create_backend
from signal_light_node.runtime import box_sight, brake_onset
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from signal_light_node.training import sources

Pass = List[Tuple[list, Dict[str, np.ndarray]]]
_OFF, _ON, _UNKNOWN = int(LightStatus.OFF), int(LightStatus.ON), int(LightStatus.UNKNOWN)
#: What ``--blinkers`` takes from the truth: nothing (``model``), whether each blinker can be
#: seen (``sight``), ON or OFF where it can (``state``), both (``truth``), or both from the
#: lit labels of a split (``lit``: ON in the lit half of a blink, OFF in its dark half, a
#: perfect per-frame eye with no temporal model).
TRUTH_PARTS = ("model", "sight", "state", "truth")
BLINKER_PARTS = TRUTH_PARTS + ("lit",)
#: Tracks per model pass batch; ``--blinkers lit`` batches the lit labels the same way.
BATCH_TRACKS = 32


def load_tracks(path: Path, crop: Any) -> list:
    """The tracks of a split directory, or of every bag under (or at) ``path``."""
    if sources.is_split_dir(path):
        return sources.split_tracks(path, crop)
    bags = [path] if list(path.glob("*.mcap")) else sorted(p for p in path.iterdir() if p.is_dir())
    tracks: list = []
    for bag in bags:
        tracks += sources.load_bag_tracks(bag, crop, lighting="unknown")
    return tracks


def model_pass(backend: Any, path: Path, cache: Optional[Path], checkpoint: Path) -> Pass:
    """``(tracks, raw outputs)`` per batch of :data:`BATCH_TRACKS` tracks, read from
    ``cache`` when there."""
    key = hashlib.sha1(f"{checkpoint.resolve()}:{checkpoint.stat().st_mtime_ns}:"
                       f"{path.resolve()}".encode()).hexdigest()[:16]
    file = cache / f"{path.name}_{key}.pkl" if cache else None
    if file is not None and file.is_file():
        return pickle.loads(file.read_bytes())
    tracks = load_tracks(path, backend.config.crop_config())
    batches = [(batch, model_track_probs(backend, batch)) for batch in chunks(tracks, BATCH_TRACKS)]
    if file is not None:
        file.parent.mkdir(parents=True, exist_ok=True)
        file.write_bytes(pickle.dumps(batches))
    return batches


def shift_brake(raw: Dict[str, np.ndarray], shift: float, side: float = 0.0
                ) -> Dict[str, np.ndarray]:
    """``raw`` with the brake's ON logit moved by ``shift`` plus ``side`` times the view
    head's P(LEFT) + P(RIGHT) on each frame (its UNKNOWN kept)."""
    if shift == 0.0 and side == 0.0:
        return raw
    total: "float | np.ndarray" = shift
    if side != 0.0:
        total = shift + side * box_sight.side_mass(raw["view"])
    return dict(raw, brake=brake_onset.shift_on(raw["brake"], total))


def _labels(tracks: list, shape: Tuple[int, int], task: str) -> np.ndarray:
    """The tracks' labels of ``task`` as ``shape`` (tracks x frames), -1 past a track's end."""
    labels = np.full(shape, -1, np.int64)
    for i, track in enumerate(tracks):
        labels[i, :len(track)] = track.labels[:, TASKS.index(task)]
    return labels


def require_lit_labels(path: Path) -> None:
    """Raise ConfigError unless ``path`` is a split directory (bags keep no lit labels)."""
    if not sources.is_split_dir(path):
        raise ConfigError(f"--blinkers lit needs a split directory: {path} is not one "
                          f"(bags keep no lit labels)")


def lit_tracks(path: Path) -> list:
    """A split's tracks labelled with its lit labels, in the order :func:`load_tracks` gives.

    Raises:
        ConfigError: ``path`` is not a split directory.
    """
    require_lit_labels(path)
    return sources.split_tracks(path, None, label_key="lit_labels")


def with_blinkers(batches: Pass, part: str, path: Path,
                  lag: Tuple[float, float] = (0.0, 0.0)) -> Pass:
    """``batches`` with :func:`blinkers_from_truth`'s ``part`` of their labels (made late by
    ``lag`` where the truth's states are taken); ``lit`` takes both from the split's lit
    labels (:func:`lit_tracks`)."""
    if part != "lit":
        return [(tracks, blinkers_from_truth(raw, tracks, part, lag)) for tracks, raw in batches]
    lit = list(chunks(lit_tracks(path), BATCH_TRACKS))
    same = [[(t.track_id, len(t)) for t in b] for b in lit] == \
        [[(t.track_id, len(t)) for t in tracks] for tracks, _ in batches]
    if not same:
        raise ConfigError(f"{path}: the lit labels' tracks do not match the model pass's "
                          f"(a cached pass of another split of that name?)")
    return [(tracks, blinkers_from_truth(raw, lit_batch, "truth"))
            for (tracks, raw), lit_batch in zip(batches, lit)]


def late_labels(tracks: list, labels: np.ndarray, onset: float, offset: float) -> np.ndarray:
    """``labels`` (tracks x frames) of a blinker with every ON episode made late: ON from
    ``onset`` seconds after it starts until ``offset`` seconds after it ends, in whole frames
    of each track's median frame interval (an episode shorter than ``onset`` is missed);
    UNKNOWN and unlabelled frames kept."""
    out = labels.copy()
    for i, track in enumerate(tracks):
        n = len(track)
        row = labels[i, :n]
        gaps = np.diff(np.asarray(track.stamps_ns[:n], np.float64)) / 1e9
        frame = float(np.median(gaps)) if n > 1 else 0.0
        on = row == _ON
        late = []
        for seconds in (onset, offset):
            k = min(int(round(seconds / frame)) if frame > 0 else 0, n)
            late.append(np.concatenate((np.zeros(k, bool), on[:n - k])))  # on, k frames ago
        published = (on & late[0]) | (~on & late[1])
        known = on | (row == _OFF)
        out[i, :n] = np.where(known, np.where(published, _ON, _OFF), row)
    return out


def blinkers_from_truth(raw: Dict[str, np.ndarray], tracks: list, part: str,
                        lag: Tuple[float, float] = (0.0, 0.0)) -> Dict[str, np.ndarray]:
    """``raw`` with the blinker heads' outputs taken in part from the tracks' labels.

    ``sight``: P(UNKNOWN) is 1 where the label is UNKNOWN, else 0, the heads' ON:OFF ratio
    kept; ``state``: where the label is ON or OFF, the judged mass 1 - P(UNKNOWN) goes all
    to it, with ``lag`` (onset, offset seconds) the labels made late first
    (:func:`late_labels`); ``truth``: both. Unlabelled frames and frames the model did not
    step keep the heads' outputs; ``model`` returns ``raw`` itself.
    """
    if part not in TRUTH_PARTS:
        raise ValueError(f"blinkers must be one of {TRUTH_PARTS}, got {part!r}")
    if part == "model":
        return raw
    out = dict(raw)
    for task in ("left", "right"):
        p = raw[task].copy()
        label = _labels(tracks, p.shape[:2], task)
        if any(lag):
            label = late_labels(tracks, label, *lag)
        if part in ("sight", "truth"):
            judged = p[..., :2].sum(-1, keepdims=True)
            p[..., :2] = np.where(judged > 0, p[..., :2] / np.maximum(judged, 1e-9), 0.5)
            p[..., _UNKNOWN] = 0.0
            p[label == _UNKNOWN] = np.eye(3)[_UNKNOWN]
        if part in ("state", "truth"):
            known = (label == _ON) | (label == _OFF)
            judged = 1.0 - p[..., _UNKNOWN]
            on = np.where(known, np.where(label == _ON, judged, 0.0), p[..., _ON])
            p[..., _OFF] = np.where(known, judged - on, p[..., _OFF])
            p[..., _ON] = on
        keep = (label < 0) | np.isnan(raw[task]).any(-1)
        p[keep] = raw[task][keep]
        out[task] = p
    return out


def _on_f1(report: Dict[str, Any]) -> Optional[float]:
    per_class = report.get("per_class") if report else None
    return per_class["f1"][_ON] if per_class and len(per_class["f1"]) > _ON else None


def side_brake_f1(report: Dict[str, Any]) -> Optional[float]:
    """Brake ON F1 over the frames whose true view is a side (LEFT and RIGHT pooled)."""
    views = report["groups"].get("view", {})
    sides = [np.asarray(views[v]["brake"]["confusion"]) for v in ("LEFT", "RIGHT")
             if "brake" in views.get(v, {})]
    return _on_f1(metrics_from_confusion("brake", sum(sides))) if sides else None


def blinker_f1(report: Dict[str, Any]) -> Optional[float]:
    """The blinkers' ON F1, left and right pooled (None without a judged blinker)."""
    lights = [np.asarray(report["overall"][t]["confusion"]) for t in ("left", "right")
              if t in report["overall"]]
    return _on_f1(metrics_from_confusion("left", sum(lights))) if lights else None


def pooled_ratio(switches: Dict[str, Any], tasks: Tuple[str, ...]) -> Optional[float]:
    """Predicted over true changes of ``tasks`` pooled (None when the truth never changed)."""
    true = sum(switches[t]["true"] for t in tasks)
    return sum(switches[t]["predicted"] for t in tasks) / true if true else None


def brake_false_on(report: Dict[str, Any]) -> Optional[float]:
    """The share of true brake-OFF frames published ON (None without such a frame)."""
    brake = report["overall"].get("brake")
    if not brake:
        return None
    off = np.asarray(brake["confusion"])[_OFF]
    return float(off[_ON] / off.sum()) if off.sum() else None


def score(batches: Pass, config: IntentFilterConfig, shift: float, side: float = 0.0
          ) -> Dict[str, Any]:
    """Intent and brake figures of one pass under one setting (no grace); ``shift`` and
    ``side`` as :func:`shift_brake`'s."""
    scorer = TrackScorer(EvalSettings())
    published = {task: [0, 0] for task in ("brake", "left", "right")}  # ON, judged
    for tracks, raw in batches:
        for pred in score_batch(scorer, tracks, shift_brake(raw, shift, side), config):
            for task, counts in published.items():
                column = pred[:, TASKS.index(task)]
                column = column[column >= 0]
                counts[0] += int((column == _ON).sum())
                counts[1] += int((column != _UNKNOWN).sum())
    result = scorer.result()
    report, switches = result["no_grace"], result["switches"]
    summary = report["summary"]
    rear = report["groups"].get("view", {}).get("BEHIND", {}).get("brake")
    return {"intent_macro_f1": summary["intent_macro_f1"], "intent_fp": summary["intent_fp_rate"],
            "intent_fn": summary["intent_fn_rate"],
            "brake_f1": _on_f1(report["overall"].get("brake")), "brake_f1_rear": _on_f1(rear),
            "brake_f1_side": side_brake_f1(report),
            "brake_on_of_judged": _share(*published["brake"]),
            "blinker_on_of_judged": _share(published["left"][0] + published["right"][0],
                                           published["left"][1] + published["right"][1]),
            "view_accuracy": (report["overall"].get("view") or {}).get("accuracy"),
            "unknown_visible": unknown_where_visible(report["overall"]),
            "brake_false_on": brake_false_on(report),
            "intent_switches": switches["intent"].get("ratio"),
            "brake_switches": switches["brake"].get("ratio"),
            "blinker_f1": blinker_f1(report),
            "blinker_switches": pooled_ratio(switches, ("left", "right"))}


def _share(part: int, whole: int) -> Optional[float]:
    return part / whole if whole else None


def _pct(value: Optional[float]) -> str:
    return "  -  " if value is None else f"{100 * value:5.1f}"


def _ratio(value: Optional[float]) -> str:
    return "-" if value is None else f"{value:.2f}x"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--backend", default="torch")
    parser.add_argument("--data", action="append", required=True, help="NAME=PATH")
    parser.add_argument("--config", action="append", default=None, help="JSON (default {})")
    parser.add_argument("--brake-shift", type=float, action="append", default=None)
    parser.add_argument("--brake-side-shift", type=float, action="append", default=None,
                        help="more ON log-odds per unit of the view head's side mass")
    parser.add_argument("--blinkers", action="append", choices=BLINKER_PARTS, default=None,
                        help="what of the blinker heads' outputs to take from the truth")
    parser.add_argument("--blinker-lag", type=float, nargs=2, default=(0.0, 0.0),
                        metavar=("ONSET", "OFFSET"),
                        help="seconds the truth's blinker states come late (state, truth)")
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    data = [tuple(d.split("=", 1)) for d in args.data]
    if any(len(d) != 2 for d in data):
        parser.error("--data takes NAME=PATH")
    parts = args.blinkers or ["model"]
    lag = tuple(args.blinker_lag)
    if min(lag) < 0:
        parser.error("--blinker-lag takes seconds >= 0")
    if any(lag) and not {"state", "truth"} & set(parts):
        parser.error("--blinker-lag makes the truth's states late: it needs --blinkers state "
                     "or truth")
    try:  # before any model pass, which takes minutes
        for _, path in data if "lit" in parts else []:
            require_lit_labels(Path(path))
    except ConfigError as exc:
        parser.error(str(exc))
    configs = args.config or ["{}"]
    shifts = [(s, k) for s in args.brake_shift or [0.0] for k in args.brake_side_shift or [0.0]]
    backend = create_backend(args.backend, str(args.checkpoint), threads=args.threads)
    rows = []
    print("data        blinkers config                             shift  side  intent  FP    "
          "FN   brake F1 (rear / side)  brake ON  false ON  switches intent / brake  "
          "blinker F1 / switches  blinker ON  view acc.  UNKNOWN visible")
    for name, path in data:
        model_batches = model_pass(backend, Path(path), args.cache, args.checkpoint)
        for part in parts:
            try:
                batches = with_blinkers(model_batches, part, Path(path), lag)
            except ConfigError as exc:
                parser.error(str(exc))
            rows += _sweep(name, part, batches, configs, shifts)
    if args.json:
        args.json.write_text(json.dumps({"checkpoint": str(args.checkpoint), "rows": rows},
                                        indent=1))


def _sweep(name: str, part: str, batches: Pass, configs: List[str],
           shifts: List[Tuple[float, float]]) -> List[Dict[str, Any]]:
    """Score and print one data set's pass under every filter config and brake shift."""
    rows = []
    for text in configs:
        config = IntentFilterConfig(**json.loads(text))
        for shift, side in shifts:
            r = score(batches, config, shift, side)
            rows.append({"data": name, "blinkers": part, "config": json.loads(text),
                         "brake_shift": shift, "brake_side_shift": side, **r})
            print(f"{name:11s} {part:8s} {text[:34]:34s} {shift:+5.2f} {side:+5.2f} "
                  f"{_pct(r['intent_macro_f1'])} "
                  f"{_pct(r['intent_fp'])} {_pct(r['intent_fn'])}  {_pct(r['brake_f1'])} "
                  f"({_pct(r['brake_f1_rear'])} / {_pct(r['brake_f1_side'])})  "
                  f"{_pct(r['brake_on_of_judged'])}  {_pct(r['brake_false_on'])}  "
                  f"{_ratio(r['intent_switches'])} / {_ratio(r['brake_switches'])}  "
                  f"{_pct(r['blinker_f1'])} / {_ratio(r['blinker_switches'])}  "
                  f"{_pct(r['blinker_on_of_judged'])}  {_pct(r['view_accuracy'])}  "
                  f"{_pct(r['unknown_visible'])}", flush=True)
    return rows


if __name__ == "__main__":
    main()
