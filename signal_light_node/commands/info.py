"""``signal-light info BAG``: what a bag holds.

Topics with types and counts, the duration, the image size of each image topic (from its
first message) and the number of distinct track IDs over all ``Detection2DArray`` topics.
"""

from __future__ import annotations

import argparse
import json
from typing import Any, Dict, Optional, Set

from signal_light_node.io import bagio
from signal_light_node.errors import ImageConversionError
from signal_light_node.io.image_codec import compressed_msg_to_bgr
from signal_light_node.io.topics import (DETECTIONS_TYPE, IMAGE_TYPE, IMAGE_TYPES,
                                      VEHICLE_LIGHTS_TYPE)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light info``."""
    parser.add_argument("bag", metavar="BAG",
                        help="rosbag2 directory (mcap or sqlite3) or a bare .mcap file")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object instead of text")


def _image_size(bag: bagio.BagReader, topic: str, msgtype: str) -> Optional[Dict[str, Any]]:
    first = next(bag.messages([topic], skip_undecodable=True), None)
    if first is None:
        return None
    msg = first.msg
    if msgtype == IMAGE_TYPE:
        return {"width": int(msg.width), "height": int(msg.height), "encoding": msg.encoding}
    try:
        image = compressed_msg_to_bgr(msg, topic)
    except ImageConversionError as exc:
        return {"width": None, "height": None, "encoding": msg.format, "error": str(exc)}
    return {"width": int(image.shape[1]), "height": int(image.shape[0]),
            "encoding": msg.format}


def _track_ids(bag: bagio.BagReader, topic: str, msgtype: str) -> Set[str]:
    ids: Set[str] = set()
    for item in bag.messages([topic], skip_undecodable=True):
        if msgtype == DETECTIONS_TYPE:
            ids.update(str(d.id) for d in item.msg.detections)
        else:
            ids.update(str(v.track_id) for v in item.msg.vehicles)
    return ids


def describe(path: str) -> Dict[str, Any]:
    """Everything ``info`` reports, as a JSON-ready dict.

    Raises:
        BagIOError: If the bag cannot be read.
    """
    with bagio.open_bag(path) as bag:
        topics = []
        detection_ids: Set[str] = set()
        for topic, info in bag.topics().items():
            entry: Dict[str, Any] = {"topic": topic, "msgtype": info.msgtype,
                                     "count": info.count}
            if info.msgtype in IMAGE_TYPES:
                entry["image"] = _image_size(bag, topic, info.msgtype)
            elif info.msgtype in (DETECTIONS_TYPE, VEHICLE_LIGHTS_TYPE):
                ids = _track_ids(bag, topic, info.msgtype)
                entry["track_ids"] = len(ids)
                if info.msgtype == DETECTIONS_TYPE:
                    detection_ids |= ids
            topics.append(entry)
        return {
            "path": str(path),
            "storage": bag.storage,
            "message_count": bag.message_count,
            "start_ns": bag.start_ns,
            "duration_ns": bag.duration_ns,
            "duration_s": bag.duration_ns / 1e9,
            "topics": topics,
            "track_ids": len(detection_ids),
            "skipped": dict(bag.skipped),
            "recovered": bag.recovered,
        }


def format_text(report: Dict[str, Any]) -> str:
    """Human-readable form of :func:`describe`'s report."""
    lines = [
        f"bag:        {report['path']} ({report['storage']})",
        f"duration:   {report['duration_s']:.3f} s",
        f"messages:   {report['message_count']}",
        "topics:",
    ]
    width = max([len(t["topic"]) for t in report["topics"]] + [5])
    type_width = max([len(t["msgtype"]) for t in report["topics"]] + [4])
    for t in report["topics"]:
        extra = ""
        image = t.get("image")
        if image and image.get("width") is not None:
            extra = f"  {image['width']}x{image['height']} {image['encoding']}"
        elif image:
            extra = f"  undecodable first image: {image.get('error')}"
        if "track_ids" in t:
            extra = f"  {t['track_ids']} track IDs"
        lines.append(f"  {t['topic']:<{width}}  {t['msgtype']:<{type_width}}  "
                     f"{t['count']:>7} msgs{extra}")
    lines.append(f"track IDs:  {report['track_ids']} distinct (over all Detection2DArray topics)")
    if report.get("skipped"):
        lines.append("skipped:    " + ", ".join(f"{n} undecodable on {topic}" for topic, n in
                                                 sorted(report["skipped"].items())))
    if report.get("recovered") is not None:
        lines.append(f"recovered:  {report['recovered']} messages of a cut MCAP file")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Print the report; returns the exit code."""
    report = describe(args.bag)
    print(json.dumps(report, indent=2) if args.json else format_text(report))
    return 0
