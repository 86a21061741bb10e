"""CVAT's "CVAT for video 1.1" XML: written for a labelling task, read back when corrected.

The format only, no bags (:mod:`signal_light_node.tools.annotate` pairs it with a bag).
One label, :data:`LABEL` (``vehicle``), with one select attribute per head of
:data:`ATTRIBUTES` (``brake``, ``left``, ``right``: ON / OFF / UNKNOWN; ``intent``: OFF /
LEFT / RIGHT / HAZARD / UNKNOWN; ``view``: BEHIND / LEFT / FRONT / RIGHT; the class
names of :data:`signal_light_node.labels.CLASS_NAMES`, "left"/"right" the vehicle's own
sides), all mutable (they may change from frame to frame), and the immutable text
attribute :data:`TRACK_ID` holding the tracker's ``Detection2D.id`` (CVAT numbers its
tracks itself, 0, 1, ...; the import goes by this attribute).

What is written (:func:`write_video_xml`)::

    <annotations>
      <version>1.1</version>
      <meta>
        <task> name, size (frames), mode interpolation, labels with their attributes,
               original_size </task>
        <signal_light> where the file comes from: bag, model, that the attribute values
               are predictions, the frame list beside it </signal_light>
      </meta>
      <track id="0" label="vehicle" source="auto">
        <box frame="0" outside="0" occluded="0" keyframe="1" xtl ytl xbr ybr z_order="0">
          <attribute name="brake">OFF</attribute> ... <attribute name="track_id">7</attribute>
        </box>
        ... one box per frame the track is in; where it leaves (a gap, or before the last
        frame) a box with outside="1" at the next frame, as CVAT writes them
      </track>
    </annotations>

``source="auto"`` is CVAT's own mark of annotations made by a program; the meta note says
the same in words. CVAT reads tracks and boxes and ignores the ``<signal_light>`` element.

What is read (:func:`read_video_xml`): every ``<track>``'s boxes that are not
``outside``, keyed by (frame, track ID), with their attribute values; the task's
``size`` when the meta has one. CVAT's own export of a task (the same layout, its meta
instead of ours, interpolated boxes with ``keyframe="0"``, the immutable attribute on
every box) reads the same. Anything that cannot be used raises
:class:`~signal_light_node.errors.AnnotationError` in one line naming the first problem:
not well-formed XML, another root or version, the "CVAT for images" layout, another
label or shape, a box without :data:`TRACK_ID` or one of :data:`ATTRIBUTES`, a value
outside its class names, a frame outside the task, two boxes of one track ID in one
frame. Attributes of other names are ignored.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

from signal_light_node.errors import AnnotationError
from signal_light_node.labels import CLASS_NAMES, Intent, LightStatus

VERSION = "1.1"
#: The one label of a task.
LABEL = "vehicle"
#: The attribute holding the tracker's track ID (``Detection2D.id``).
TRACK_ID = "track_id"
#: The per-box attributes a labeller sets: name -> allowed values (the label classes).
ATTRIBUTES: Dict[str, Tuple[str, ...]] = {
    name: CLASS_NAMES[name] for name in ("brake", "left", "right", "intent", "view")}
#: A new box's value of each attribute in CVAT.
DEFAULTS: Dict[str, str] = {"brake": LightStatus.UNKNOWN.name, "left": LightStatus.UNKNOWN.name,
                            "right": LightStatus.UNKNOWN.name, "intent": Intent.UNKNOWN.name,
                            "view": CLASS_NAMES["view"][0]}


@dataclass(frozen=True)
class CvatBox:
    """One box of one track in one frame.

    Attributes:
        frame: The task's frame number (0 = the first image).
        track_id: The tracker's track ID (:data:`TRACK_ID`).
        box: ``(xtl, ytl, xbr, ybr)`` in pixels.
        values: Attribute name -> value, one per :data:`ATTRIBUTES` name.
    """

    frame: int
    track_id: str
    box: Tuple[float, float, float, float]
    values: Mapping[str, str]


@dataclass
class CvatVideo:
    """What :func:`read_video_xml` read.

    Attributes:
        size: The task's frame count from the meta, None when the file has none.
        boxes: ``(frame, track ID) -> CvatBox`` of every box inside the image
            (``outside="0"``).
    """

    size: Optional[int] = None
    boxes: Dict[Tuple[int, str], CvatBox] = field(default_factory=dict)


def label_spec() -> List[dict]:
    """The task's labels as CVAT's raw label constructor takes them (``labels.json``)."""
    attributes = [{"name": name, "mutable": True, "input_type": "select",
                   "default_value": DEFAULTS[name], "values": list(values)}
                  for name, values in ATTRIBUTES.items()]
    attributes.append({"name": TRACK_ID, "mutable": False, "input_type": "text",
                       "default_value": "", "values": [""]})
    return [{"name": LABEL, "type": "any", "attributes": attributes}]


def _element(parent: ET.Element, tag: str, text: Optional[str] = None,
             **attrib: str) -> ET.Element:
    child = ET.SubElement(parent, tag, attrib)
    if text is not None:
        child.text = text
    return child


def _meta(root: ET.Element, size: int, width: int, height: int, task_name: str,
          note: Mapping[str, str]) -> None:
    meta = _element(root, "meta")
    task = _element(meta, "task")
    for tag, text in (("name", task_name), ("size", str(size)), ("mode", "interpolation"),
                      ("overlap", "0"), ("bugtracker", ""), ("flipped", "False"),
                      ("start_frame", "0"), ("stop_frame", str(max(size - 1, 0))),
                      ("frame_filter", "")):
        _element(task, tag, text)
    labels = _element(_element(task, "labels"), "label")
    for spec in label_spec():
        _element(labels, "name", spec["name"])
        _element(labels, "type", spec["type"])
        attributes = _element(labels, "attributes")
        for attr in spec["attributes"]:
            a = _element(attributes, "attribute")
            _element(a, "name", attr["name"])
            _element(a, "mutable", str(attr["mutable"]))
            _element(a, "input_type", attr["input_type"])
            _element(a, "default_value", attr["default_value"])
            _element(a, "values", "\n".join(attr["values"]))
    original = _element(task, "original_size")
    _element(original, "width", str(width))
    _element(original, "height", str(height))
    ours = _element(meta, "signal_light")
    for tag, text in note.items():
        _element(ours, tag, text)


def _box_element(track: ET.Element, box: CvatBox, frame: int, outside: bool) -> None:
    el = _element(track, "box", frame=str(frame), outside=str(int(outside)), occluded="0",
                  keyframe="1", **{k: f"{v:.2f}" for k, v in zip(("xtl", "ytl", "xbr", "ybr"),
                                                                  box.box)}, z_order="0")
    for name in ATTRIBUTES:
        _element(el, "attribute", box.values[name], name=name)
    _element(el, "attribute", box.track_id, name=TRACK_ID)


def write_video_xml(path: "str | Path", boxes: Sequence[CvatBox], size: int, width: int,
                    height: int, task_name: str, note: Mapping[str, str]) -> None:
    """Write a "CVAT for video 1.1" annotation file.

    Args:
        path: The file to write.
        boxes: Every box, each with a value for every :data:`ATTRIBUTES` name; one track
            per track ID, numbered in the order the IDs first appear (by frame).
        size: Frames of the task.
        width: Frame width (``original_size``).
        height: Frame height.
        task_name: The task's name in the meta.
        note: Tag -> text of the ``<signal_light>`` meta element (where the file comes from).
    """
    root = ET.Element("annotations")
    _element(root, "version", VERSION)
    _meta(root, size, width, height, task_name, note)
    tracks: Dict[str, List[CvatBox]] = {}
    for box in sorted(boxes, key=lambda b: b.frame):
        tracks.setdefault(box.track_id, []).append(box)
    for number, track_boxes in enumerate(tracks.values()):
        track = _element(root, "track", id=str(number), label=LABEL, source="auto")
        for box, after in zip(track_boxes, track_boxes[1:] + [None]):
            _box_element(track, box, box.frame, outside=False)
            gone = box.frame + 1
            if gone < size and (after is None or after.frame > gone):
                _box_element(track, box, gone, outside=True)
    ET.indent(root)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)


def _problem(name: str, where: str, what: str) -> AnnotationError:
    return AnnotationError(f"{name}: {where}: {what}" if where else f"{name}: {what}")


def _integer(text: Optional[str], name: str, where: str, what: str) -> int:
    try:
        return int(str(text).strip())
    except ValueError:
        raise _problem(name, where, f"{what} {text!r} is not an integer") from None


def _number(text: Optional[str]) -> float:
    try:
        return float(str(text))
    except ValueError:
        return math.nan


def read_video_xml(data: bytes, name: str) -> CvatVideo:
    """Read a "CVAT for video 1.1" annotation file (ours, or CVAT's export of the task).

    Args:
        data: The file's bytes.
        name: How to name the file in errors.

    Returns:
        The task size (if given) and every box inside the image by (frame, track ID).

    Raises:
        AnnotationError: One line naming the first problem (see the module docstring).
    """
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise _problem(name, "", f"not well-formed XML ({exc})") from None
    if root.tag != "annotations":
        raise _problem(name, "", f"the root element is <{root.tag}>, not <annotations>")
    version = (root.findtext("version") or VERSION).strip()
    if version != VERSION:
        raise _problem(name, "", f"format version {version}, expected {VERSION}")
    if root.find("image") is not None:
        raise _problem(name, "", "holds <image> elements (CVAT for images); export the task "
                                 "as \"CVAT for video 1.1\"")
    video = CvatVideo()
    size_text = root.findtext("meta/task/size") or root.findtext("meta/job/size")
    if size_text is not None:
        video.size = _integer(size_text, name, "meta", "the task size")
    for track in root.findall("track"):
        where = f"track {track.get('id', '?')}"
        if track.get("label") != LABEL:
            raise _problem(name, where, f"label {track.get('label')!r}, expected {LABEL!r}")
        for shape in track:
            _read_box(shape, where, name, video)
    return video


def _read_box(shape: ET.Element, where: str, name: str, video: CvatVideo) -> None:
    """Add one ``<box>`` of a track to ``video`` (nothing for an outside one)."""
    if shape.tag != "box":
        raise _problem(name, where, f"holds a <{shape.tag}>; only boxes are read")
    frame = _integer(shape.get("frame"), name, where, "frame")
    where = f"{where}, frame {frame}"
    if shape.get("outside", "0").strip() not in ("0", "false", "False"):
        return
    if frame < 0 or (video.size is not None and frame >= video.size):
        raise _problem(name, where, f"the frame is outside the task's {video.size} frames")
    values = {a.get("name"): (a.text or "").strip() for a in shape.findall("attribute")}
    track_id = values.get(TRACK_ID)
    if not track_id:
        raise _problem(name, where, f"the box has no {TRACK_ID!r} attribute")
    where = f"{where}, track ID {track_id}"
    for attr, allowed in ATTRIBUTES.items():
        value = values.get(attr)
        if value is None:
            raise _problem(name, where, f"the box has no {attr!r} attribute")
        if value not in allowed:
            raise _problem(name, where, f"{attr} is {value!r}, expected one of "
                                        f"{', '.join(allowed)}")
    key = (frame, track_id)
    if key in video.boxes:
        raise _problem(name, where, "a second box of this track ID in this frame")
    video.boxes[key] = CvatBox(frame, track_id, tuple(_number(shape.get(k)) for k in
                                                      ("xtl", "ytl", "xbr", "ybr")),
                               {attr: values[attr] for attr in ATTRIBUTES})
