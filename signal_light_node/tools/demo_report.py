"""The report at the end of the demo (``make demo``): what went into the live detector,
what came out, how each track's lights evolved, how fast it was, and an annotated video.

Reads the played input bag and the bag ``signal-light record`` wrote from the node's
output and ``/diagnostics``; never imports rclpy. Command line::

    python -m signal_light_node.tools.demo_report inspect BAG
    python -m signal_light_node.tools.demo_report report --input BAG --output REC --out-dir DIR
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from signal_light_node.io.bagio import find_topic, open_bag
from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
from signal_light_node.outputs.vehicle_lights import (result_row, truth_row,
                                                      vehicle_light_array_to_results)
from signal_light_node.errors import BagIOError, SignalLightError
from signal_light_node.labels import Intent, LightStatus
from signal_light_node.runtime.results import VehicleResult
from signal_light_node.io.topics import (DETECTIONS_TYPE, DIAGNOSTICS_TOPIC, GROUND_TRUTH_TOPIC,
                                      IMAGE_TYPES, OUTPUT_TOPIC)

LOG = logging.getLogger(__name__)

_LIGHT_WORD = {LightStatus.OFF: "off", LightStatus.ON: "ON", LightStatus.UNKNOWN: "?"}
_INTENT_WORD = {Intent.OFF: "off", Intent.LEFT: "LEFT", Intent.RIGHT: "RIGHT",
                Intent.HAZARD: "HAZARD", Intent.UNKNOWN: "?"}


@dataclass(frozen=True)
class BagInputs:
    """The detector's inputs in a bag.

    Attributes:
        image_topic: The image topic (compressed preferred).
        image_type: Its type.
        detections_topic: The ``Detection2DArray`` topic.
        frames: Messages on the image topic.
    """

    image_topic: str
    image_type: str
    detections_topic: str
    frames: int

    @property
    def transport(self) -> str:
        """``compressed`` or ``raw`` (the node's ``image_transport``)."""
        return "compressed" if self.image_type.endswith("CompressedImage") else "raw"


def inspect_inputs(path: "str | Path") -> BagInputs:
    """Find the image and detection topics of a bag.

    Raises:
        BagIOError: The bag lacks one of them.
    """
    path = Path(path)
    with open_bag(path) as bag:
        topics = bag.topics()
    image = find_topic(topics, IMAGE_TYPES, None, "image", path)
    detections = find_topic(topics, (DETECTIONS_TYPE,), None, "detections", path)
    return BagInputs(image, topics[image].msgtype, detections, topics[image].count)


def run_lengths(values: Sequence[str]) -> List[Tuple[str, int]]:
    """``["a", "a", "b"]`` -> ``[("a", 2), ("b", 1)]``."""
    runs: List[Tuple[str, int]] = []
    for v in values:
        if runs and runs[-1][0] == v:
            runs[-1] = (v, runs[-1][1] + 1)
        else:
            runs.append((v, 1))
    return runs


def _rle_text(values: Sequence[str]) -> str:
    return " ".join(f"{v}({n})" for v, n in run_lengths(values))


@dataclass
class TrackTimeline:
    """One track's states over the frames it was output in.

    Attributes:
        first: Index of the first frame (0-based, in input order).
        last: Index of the last frame.
        brake: Brake state per output frame.
        left: Left blinker state per output frame.
        right: Right blinker state per output frame.
        intent: Intent per output frame.
        agree: Per output frame with ground truth, how many of brake/left/right match.
        compared: Lights compared with the ground truth.
    """

    first: int
    last: int
    brake: List[str] = field(default_factory=list)
    left: List[str] = field(default_factory=list)
    right: List[str] = field(default_factory=list)
    intent: List[str] = field(default_factory=list)
    agree: int = 0
    compared: int = 0

    def line(self, track_id: str, width: int) -> str:
        """``id  frames a-b (n)  brake ... | left ... | right ... | intent ...``."""
        agreement = (f"  [{100.0 * self.agree / self.compared:.0f}% of lights as ground truth]"
                     if self.compared else "")
        return (f"  {track_id:<{width}}  frames {self.first}-{self.last} ({len(self.brake)}): "
                f"brake {_rle_text(self.brake)} | left {_rle_text(self.left)} | "
                f"right {_rle_text(self.right)} | intent {_rle_text(self.intent)}{agreement}")


@dataclass
class DemoReport:
    """Everything the demo prints.

    Attributes:
        input_bag: The played bag.
        output_bag: The recorded bag.
        frames_in: Images in the input bag.
        detections_in: Detection arrays in the input bag.
        boxes_in: Boxes over all detection arrays.
        outputs: Output messages recorded.
        outputs_matched: Outputs whose stamp is an input image's stamp.
        missing: Input stamps without an output.
        entries: Vehicle entries over all matched outputs.
        id_mismatches: Matched outputs whose track IDs differ from the detections'.
        codes: Classification codes seen.
        timelines: Per track ID.
        diagnostics: The node's last diagnostics values.
        diagnostics_level: Its level (0 OK, 1 WARN, 2 ERROR).
        diagnostics_message: Its message.
        ground_truth: Per-task accuracy against the bag's ground truth, if it has one.
        video: The annotated video written.
        contact_sheet: The contact sheet written.
    """

    input_bag: Path
    output_bag: Path
    frames_in: int = 0
    detections_in: int = 0
    boxes_in: int = 0
    outputs: int = 0
    outputs_matched: int = 0
    missing: List[int] = field(default_factory=list)
    entries: int = 0
    id_mismatches: int = 0
    codes: Dict[int, int] = field(default_factory=dict)
    timelines: Dict[str, TrackTimeline] = field(default_factory=dict)
    diagnostics: Dict[str, str] = field(default_factory=dict)
    diagnostics_level: Optional[int] = None
    diagnostics_message: str = ""
    ground_truth: Dict[str, Optional[float]] = field(default_factory=dict)
    video: Optional[Path] = None
    contact_sheet: Optional[Path] = None

    @property
    def complete(self) -> bool:
        """Every input frame has exactly one output with the right track IDs."""
        return (self.frames_in > 0 and not self.missing and self.id_mismatches == 0
                and self.outputs == self.outputs_matched == self.frames_in)

    def text(self) -> str:
        """The report for the terminal."""
        d = self.diagnostics
        lines = [
            "=" * 78,
            "signal_light_node demo report",
            "=" * 78,
            f"input bag:  {self.input_bag}",
            f"output bag: {self.output_bag}",
            f"frames in:  {self.frames_in} images, {self.detections_in} detection arrays, "
            f"{self.boxes_in} boxes",
            f"frames out: {self.outputs} VehicleLightStateArray messages, {self.outputs_matched}"
            f" stamped like an input image, {self.entries} vehicle entries"
            + (f"; {self.id_mismatches} with track IDs other than the detections'"
               if self.id_mismatches else ""),
        ]
        if self.missing:
            shown = ", ".join(str(s) for s in self.missing[:5])
            lines.append(f"            {len(self.missing)} input frame(s) without output "
                         f"(first stamps: {shown})")
        else:
            lines.append("            every input frame has its output")
        codes = ", ".join(f"{code}: {n}" for code, n in sorted(self.codes.items())) or "none"
        lines.append(f"codes:      lights reported ON (100 brake, 101 left, 102 right): {codes}")
        if d:
            lines += [
                "latency:    image received -> output published: mean "
                f"{d.get('latency_mean_ms', 'nan')} ms, p95 {d.get('latency_p95_ms', 'nan')} "
                f"ms, max {d.get('latency_max_ms', 'nan')} ms (over {d.get('latency_frames', '?')}"
                " frames)",
                f"            pair complete -> published: mean {d.get('processing_mean_ms')} "
                f"ms, p95 {d.get('processing_p95_ms')} ms (engine alone: mean "
                f"{d.get('engine_mean_ms')} ms, p95 {d.get('engine_p95_ms')} ms)",
                "node:       received {images} images, {detections} detection arrays, paired "
                "{paired}, published {outputs} (undecodable images among them {b}); dropped: "
                "in the middleware {w}, pairing timeouts {t}, overflow {o}, work queue {q}; "
                "unjudged boxes {u}; model {m}".format(
                    w=int(d.get("dropped_image_middleware", 0))
                    + int(d.get("dropped_detections_middleware", 0)),
                    t=int(d.get("dropped_image_timeout", 0))
                    + int(d.get("dropped_detections_timeout", 0)),
                    o=int(d.get("dropped_image_overflow", 0))
                    + int(d.get("dropped_detections_overflow", 0)),
                    q=d.get("dropped_work_queue"), b=d.get("bad_images"),
                    u=d.get("unjudged_boxes"), m=d.get("model_path"),
                    **{k: d.get(k) for k in ("images", "detections", "paired", "outputs")}),
            ]
        else:
            lines.append("latency:    no /diagnostics message was recorded")
        if self.ground_truth:
            acc = ", ".join(f"{task} {100 * v:.1f}%" for task, v in self.ground_truth.items()
                            if v is not None)
            lines.append(f"agreement:  with the bag's ground truth (judged entries): {acc}")
        lines.append(f"tracks:     {len(self.timelines)} (states per output frame, "
                     "run-length encoded: state(frames))")
        width = max((len(t) for t in self.timelines), default=1)
        for track_id in sorted(self.timelines, key=_natural):
            lines.append(self.timelines[track_id].line(track_id, width))
        lines.append(f"video:      {self.video or 'not written'}")
        lines.append(f"contact:    {self.contact_sheet or 'not written'}")
        lines.append("result:     " + ("OK: one output per input frame" if self.complete
                                       else "INCOMPLETE: see the lines above"))
        return "\n".join(lines)


def _natural(text: str) -> Tuple[int, object]:
    return (0, int(text)) if text.isdigit() else (1, text)


def build_report(input_bag: "str | Path", output_bag: "str | Path",
                 out_dir: "str | Path | None" = None, video: bool = True) -> DemoReport:
    """Compare the recorded output with the played input and render the video.

    Args:
        input_bag: The bag that was played into the node.
        output_bag: The bag ``signal-light record`` wrote.
        out_dir: Where the annotated ``demo.mp4`` and ``contact_sheet.jpg`` go.
        video: Render them.

    Returns:
        The report.

    Raises:
        BagIOError: A bag cannot be read or lacks the input topics.
    """
    inputs = inspect_inputs(input_bag)
    report = DemoReport(Path(input_bag), Path(output_bag))

    outputs: Dict[int, Tuple[str, List[VehicleResult]]] = {}
    with open_bag(output_bag) as bag:
        topics = bag.topics()
        for m in bag.messages([OUTPUT_TOPIC]):
            report.outputs += 1
            stamp, results = vehicle_light_array_to_results(m.msg)
            outputs.setdefault(stamp, (m.msg.header.frame_id, results))
        if DIAGNOSTICS_TOPIC in topics:
            for m in bag.messages([DIAGNOSTICS_TOPIC]):
                for status in m.msg.status:
                    if status.name.startswith("signal_light_detector"):
                        report.diagnostics = {kv.key: kv.value for kv in status.values}
                        report.diagnostics_level = int(status.level)
                        report.diagnostics_message = status.message

    detections: Dict[int, List[str]] = {}
    truth: Dict[int, object] = {}
    with open_bag(input_bag) as bag:
        topics = bag.topics()
        for m in bag.messages([inputs.detections_topic]):
            ids = [b.track_id for b in detections_to_boxes(m.msg)]
            detections.setdefault(stamp_to_ns(m.msg.header.stamp), ids)
            report.detections_in += 1
            report.boxes_in += len(ids)
        if GROUND_TRUTH_TOPIC in topics:
            for m in bag.messages([GROUND_TRUTH_TOPIC]):
                truth.setdefault(stamp_to_ns(m.msg.header.stamp), m.msg)
        stamps = [stamp_to_ns(m.msg.header.stamp) for m in bag.messages([inputs.image_topic])]
    report.frames_in = len(stamps)

    from signal_light_node.evaluation.metrics import MetricAccumulator

    accumulator = MetricAccumulator() if truth else None
    for index, stamp in enumerate(stamps):
        if stamp not in outputs:
            report.missing.append(stamp)
            continue
        report.outputs_matched += 1
        _, results = outputs[stamp]
        report.entries += len(results)
        if [r.track_id for r in results] != detections.get(stamp, []):
            report.id_mismatches += 1
        gt = {v.track_id: v for v in truth[stamp].vehicles} if stamp in truth else {}
        for res in results:
            for code, _ in res.classification:
                report.codes[code] = report.codes.get(code, 0) + 1
            _add_to_timeline(report.timelines, res, index, gt.get(res.track_id), accumulator)
    if accumulator is not None and any(t.compared for t in report.timelines.values()):
        overall = accumulator.report()["overall"]
        report.ground_truth = {task: overall[task].get("accuracy") for task in overall}

    if video and out_dir is not None:
        report.video, report.contact_sheet = render_video(input_bag, inputs, outputs,
                                                          Path(out_dir))
    return report


def _add_to_timeline(timelines: Dict[str, TrackTimeline], res: VehicleResult, index: int,
                     gt: object, accumulator: object) -> None:
    tl = timelines.setdefault(res.track_id, TrackTimeline(index, index))
    tl.last = index
    tl.brake.append(_LIGHT_WORD[res.brake.state])
    tl.left.append(_LIGHT_WORD[res.left.state])
    tl.right.append(_LIGHT_WORD[res.right.state])
    tl.intent.append(_INTENT_WORD[res.intent])
    if gt is None or not res.judged:
        return
    pairs = ((res.brake, gt.brake), (res.left, gt.left_blinker), (res.right, gt.right_blinker))
    tl.agree += sum(int(est.state) == int(g.state) for est, g in pairs)
    tl.compared += 3
    if accumulator is not None:
        accumulator.add_frames(truth_row(gt)[None], result_row(res)[None])


def render_video(input_bag: "str | Path", inputs: BagInputs,
                 outputs: Dict[int, Tuple[str, List[VehicleResult]]], out_dir: Path,
                 sheet_tiles: int = 12) -> Tuple[Optional[Path], Optional[Path]]:
    """Draw the node's results onto the input frames: ``demo.mp4`` and ``contact_sheet.jpg``.

    Returns:
        The paths written (None where nothing could be drawn).
    """
    from signal_light_node.io.image_codec import msg_to_bgr
    from signal_light_node.outputs.debug_image import draw_results
    from signal_light_node.tools.visualize import VideoSink

    out_dir.mkdir(parents=True, exist_ok=True)
    with open_bag(input_bag) as bag:
        stamps = [stamp_to_ns(m.msg.header.stamp) for m in bag.messages([inputs.image_topic])]
        if len(stamps) > 1 and stamps[-1] > stamps[0]:
            fps = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)
        else:
            fps = 10.0
        picks = set(np.linspace(0, max(0, len(stamps) - 1), min(sheet_tiles, len(stamps)))
                    .round().astype(int).tolist())
        sink = VideoSink(out_dir / "demo.mp4", fps=fps)
        tiles: List[np.ndarray] = []
        for index, m in enumerate(bag.messages([inputs.image_topic])):
            stamp = stamp_to_ns(m.msg.header.stamp)
            try:
                image = msg_to_bgr(m.msg, inputs.image_topic, stamp)
            except SignalLightError as exc:
                LOG.warning("video: %s", exc)
                continue
            results = outputs.get(stamp, ("", []))[1]
            caption = f"frame {index}  t={(stamp - stamps[0]) / 1e9:.2f} s" + (
                "" if stamp in outputs else "  NO OUTPUT")
            drawn = draw_results(image, results, caption=caption)
            sink.add(drawn)
            if index in picks:
                tiles.append(drawn)
        video = sink.close()
    return video, _contact_sheet(tiles, out_dir / "contact_sheet.jpg")


def _contact_sheet(tiles: List[np.ndarray], path: Path, columns: int = 4,
                   tile_width: int = 400) -> Optional[Path]:
    if not tiles:
        return None
    h, w = tiles[0].shape[:2]
    size = (tile_width, max(1, round(h * tile_width / w)))
    small = [cv2.resize(t, size, interpolation=cv2.INTER_AREA) for t in tiles]
    blank = np.zeros_like(small[0])
    rows = []
    for start in range(0, len(small), columns):
        row = small[start:start + columns]
        row += [blank] * (columns - len(row))
        rows.append(np.hstack(row))
    if not cv2.imwrite(str(path), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 85]):
        raise BagIOError(f"cannot write the contact sheet {path}")
    return path


def main(argv: Optional[List[str]] = None) -> int:
    """Command line of the demo's python steps; returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m signal_light_node.tools.demo_report",
                                     description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("inspect", help="print: transport image_topic detections_topic frames")
    p.add_argument("bag")
    p = sub.add_parser("report", help="compare output with input, write the video, print")
    p.add_argument("--input", required=True, help="the played bag")
    p.add_argument("--output", required=True, help="the recorded bag")
    p.add_argument("--out-dir", help="where demo.mp4 and contact_sheet.jpg go")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "inspect":
            i = inspect_inputs(args.bag)
            print(i.transport, i.image_topic, i.detections_topic, i.frames)
            return 0
        report = build_report(args.input, args.output, args.out_dir,
                              video=args.out_dir is not None)
    except SignalLightError as exc:
        print(f"demo report: error: {exc}", file=sys.stderr)
        return 2
    print(report.text())
    return 0 if report.complete else 1


if __name__ == "__main__":
    sys.exit(main())
