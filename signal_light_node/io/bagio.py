"""Reading and writing ROS 2 bags without ROS, on top of ``rosbags``.

The project's own interfaces (``signal_light_msgs``) and ``vision_msgs`` are registered
from their ``.msg`` files, so the schemas in ``msg_schemas/`` stay the one source of truth:
in a source checkout they are read from ``<repo>/msg_schemas/<pkg>/msg``, elsewhere from
``share/<pkg>/msg`` of a prefix on ``AMENT_PREFIX_PATH``.

Reading accepts rosbag2 directories (MCAP or sqlite3 storage) and bare ``.mcap`` /
``.db3`` files; writing always produces an MCAP rosbag2 directory that ``ros2 bag``,
Foxglove and the ``mcap`` tools read. Messages are ``rosbags`` message objects
(dataclasses with the ROS field names; ``uint8[]`` fields are numpy arrays).
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import (Any, Dict, Iterable, Iterator, List, Mapping, NamedTuple, Optional,
                    Sequence, Tuple)

from signal_light_node.errors import BagIOError
from signal_light_node.io.mcap_recovery import _RecoveredMcap

LOG = logging.getLogger(__name__)

#: Interface packages registered from ``.msg`` files on top of the stock Jazzy types.
SCHEMA_PACKAGES: Tuple[str, ...] = ("signal_light_msgs", "vision_msgs")

#: rosbag2 metadata version written (9 = Jazzy's).
ROSBAG2_VERSION = 9

_REPO_SCHEMAS = Path(__file__).resolve().parents[2] / "msg_schemas"
# Files that may make up a bag directory; ``overwrite=True`` refuses to delete anything else.
_BAG_FILE_SUFFIXES = (".mcap", ".db3", ".yaml", ".zstd", ".db3-shm", ".db3-wal")


class TopicInfo(NamedTuple):
    """One topic of a bag.

    Attributes:
        msgtype: Full type name, e.g. ``sensor_msgs/msg/Image``.
        count: Number of messages on the topic.
    """

    msgtype: str
    count: int


class BagMessage(NamedTuple):
    """One deserialized message of a bag.

    Attributes:
        topic: Topic name.
        msgtype: Full type name.
        log_time_ns: Time the message was recorded (bag time), in ns since the epoch.
        msg: The ``rosbags`` message object.
    """

    topic: str
    msgtype: str
    log_time_ns: int
    msg: Any


def normalize_msgtype(msgtype: str) -> str:
    """Return the full ``pkg/msg/Name`` form of ``pkg/Name`` or ``pkg/msg/Name``.

    Raises:
        BagIOError: If the name has neither form.
    """
    parts = msgtype.strip().split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and all(parts):
        return "/".join(parts)
    raise BagIOError(f"{msgtype!r} is not a message type name (expected pkg/msg/Name)")


def schema_dir(package: str) -> Path:
    """Directory holding the ``.msg`` files of one of ``SCHEMA_PACKAGES``.

    The source checkout wins over installed copies so that an edit of ``msg_schemas/``
    is seen at once; outside a checkout the ament index (``AMENT_PREFIX_PATH``) is used.

    Raises:
        BagIOError: If no directory with ``.msg`` files is found.
    """
    candidates = [_REPO_SCHEMAS / package / "msg"]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / "share" / package / "msg")
    for cand in candidates:
        if cand.is_dir() and any(cand.glob("*.msg")):
            return cand
    raise BagIOError(f"no .msg files for {package} in any of: "
                     + ", ".join(str(c) for c in candidates))


def _stock_typestore():
    from rosbags.typesys import Stores, get_typestore

    # Jazzy is what the project targets; older rosbags releases only know earlier distros.
    for name in ("ROS2_JAZZY", "ROS2_IRON", "ROS2_HUMBLE", "LATEST"):
        store = getattr(Stores, name, None)
        if store is not None:
            if name != "ROS2_JAZZY":
                LOG.warning("rosbags has no ROS2_JAZZY type store; using %s", name)
            return get_typestore(store)
    raise BagIOError("rosbags offers no ROS 2 type store")


def _schema_types() -> Dict[str, Any]:
    from rosbags.typesys import get_types_from_msg

    typs: Dict[str, Any] = {}
    for package in SCHEMA_PACKAGES:
        folder = schema_dir(package)
        for path in sorted(folder.glob("*.msg")):
            try:
                typs.update(get_types_from_msg(path.read_text(encoding="utf-8"),
                                               f"{package}/msg/{path.stem}"))
            except Exception as exc:  # rosbags raises its own parser errors
                raise BagIOError(f"cannot parse {path}: {exc}") from exc
    return typs


@functools.lru_cache(maxsize=1)
def typestore():
    """The ``rosbags`` typestore: ROS 2 Jazzy plus ``signal_light_msgs`` and ``vision_msgs``.

    Cached: every call returns the same object. Registering checks every type that
    the stock store already holds against the ``.msg`` definition.

    Raises:
        BagIOError: If a schema is missing, unparsable or contradicts a stock type.
    """
    from rosbags.typesys import TypesysError

    store = _stock_typestore()
    try:
        store.register(_schema_types())
    except TypesysError as exc:
        raise BagIOError(f"msg_schemas contradict the stock ROS 2 types: {exc}") from exc
    return store


def make(msgtype: str, **fields: Any) -> Any:
    """Build a ``rosbags`` message of a registered type.

    Args:
        msgtype: ``pkg/msg/Name`` (or ``pkg/Name``).
        **fields: Every field of the type; nested messages must be built with ``make`` too.

    Returns:
        The message object.

    Raises:
        BagIOError: If the type is unknown or fields are missing or unknown.
    """
    store = typestore()
    name = normalize_msgtype(msgtype)
    if name not in store.fielddefs:
        raise BagIOError(f"unknown message type {name!r}")
    names = [f for f, _ in store.fielddefs[name][1]]
    missing = [f for f in names if f not in fields]
    unknown = [f for f in fields if f not in names]
    if missing or unknown:
        what = []
        if missing:
            what.append("missing field(s) " + ", ".join(missing))
        if unknown:
            what.append("unknown field(s) " + ", ".join(unknown))
        raise BagIOError(f"cannot build {name}: {'; '.join(what)}")
    return store.types[name](**fields)


def _reader_errors() -> Tuple[type, ...]:
    from rosbags.rosbag2 import ReaderError
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    # rosbags lets struct/assert errors escape from damaged files.
    return (ReaderError, SerdeError, TypesysError, OSError, KeyError, ValueError, AssertionError,
            struct.error)


class BagReader:
    """An open bag; use :func:`open_bag` to get one.

    Attributes:
        path: The bag's path as given.
        recovered: Messages recovered from a cut MCAP file; None for an intact bag.
        skipped: Per topic, messages skipped because they could not be deserialized
            (only by ``messages(..., skip_undecodable=True)``).
    """

    #: Skipped messages warned about one by one; later ones only at debug level.
    MAX_SKIP_WARNINGS = 20

    def __init__(self, path: Path, reader: Any) -> None:
        self.path = path
        self._reader = reader
        self.recovered: Optional[int] = (reader.message_count
                                         if isinstance(reader, _RecoveredMcap) else None)
        self.skipped: Dict[str, int] = {}
        self._store = typestore()
        self._conns: Dict[str, List[Any]] = {}
        for conn in reader.connections:
            self._conns.setdefault(conn.topic, []).append(conn)
        self._decoders = self._decoding_stores()

    def _decoding_stores(self) -> Dict[int, Any]:
        """Pick, per connection, the typestore that decodes it.

        Our store is used whenever it knows the type with the same definition hash;
        otherwise the definition embedded in the bag (if any) is trusted, so bags with
        foreign or older types still decode.
        """
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        ours = self._store
        decoders: Dict[int, Any] = {}
        foreign: Dict[str, Any] = {}
        for conn in self._reader.connections:
            known = conn.msgtype in ours.fielddefs
            if known and (not conn.digest or not conn.digest.startswith("RIHS01_")
                          or conn.digest == ours.hash_rihs01(conn.msgtype)):
                decoders[conn.id] = ours
                continue
            fmt, text = conn.msgdef.format, conn.msgdef.data
            if fmt == MessageDefinitionFormat.MSG and text:
                foreign.update(get_types_from_msg(text, conn.msgtype))
            elif fmt == MessageDefinitionFormat.IDL and text:
                sep = "=" * 80 + "\n"
                parts = text.split(sep)[1:] if text.startswith(sep + "IDL: ") else [text]
                for part in parts:
                    foreign.update(get_types_from_idl(part.split("\n", 1)[1]
                                                      if part.startswith("IDL: ") else part))
            elif known:
                LOG.warning("%s: %s on %s has hash %s, ours differs; decoding with ours",
                            self.path, conn.msgtype, conn.topic, conn.digest)
                decoders[conn.id] = ours
                continue
            else:
                continue  # undecodable: messages() raises when asked for it
            decoders[conn.id] = None
        if foreign:
            from rosbags.typesys import Stores, get_typestore

            local = get_typestore(Stores.EMPTY)
            # The bag's own definitions override ours; ours fill in everything else.
            typs = {k: v for k, v in ours.fielddefs.items() if k not in foreign}
            typs.update(foreign)
            local.register(typs)
            decoders = {cid: local if store is None else store for cid, store in decoders.items()}
            LOG.debug("%s: decoding %s with the bag's own definitions", self.path,
                      sorted(foreign))
        return decoders

    @property
    def storage(self) -> str:
        """``"mcap"`` or ``"sqlite3"``."""
        inner = self._reader.storage
        plugin = inner.storages[0] if getattr(inner, "storages", None) else inner
        return "sqlite3" if "sqlite" in type(plugin).__name__.lower() else "mcap"

    @property
    def message_count(self) -> int:
        """Number of messages in the bag."""
        return int(self._reader.message_count)

    @property
    def start_ns(self) -> int:
        """Log time of the first message (0 for an empty bag)."""
        return int(self._reader.start_time) if self.message_count else 0

    @property
    def end_ns(self) -> int:
        """Log time of the last message (0 for an empty bag)."""
        return int(self._reader.end_time) - 1 if self.message_count else 0

    @property
    def duration_ns(self) -> int:
        """Time between the first and the last message."""
        return self.end_ns - self.start_ns if self.message_count else 0

    def topics(self) -> Dict[str, TopicInfo]:
        """Every topic with its type and message count, sorted by name."""
        out = {}
        for topic in sorted(self._conns):
            conns = self._conns[topic]
            types = sorted({c.msgtype for c in conns})
            out[topic] = TopicInfo("|".join(types), sum(int(c.msgcount) for c in conns))
        return out

    def messages(self, topics: Optional[Iterable[str]] = None, start_ns: Optional[int] = None,
                 stop_ns: Optional[int] = None,
                 skip_undecodable: bool = False) -> Iterator[BagMessage]:
        """Deserialized messages in log-time order.

        Args:
            topics: Only these topics (all when None); topics absent from the bag are ignored.
            start_ns: Only messages logged at or after this time.
            stop_ns: Only messages logged before this time.
            skip_undecodable: Skip a message that cannot be deserialized (truncated,
                invalid UTF-8...) with a one-line warning, counted in ``skipped``,
                instead of raising.

        Yields:
            One ``BagMessage`` per message.

        Raises:
            BagIOError: If the bag cannot be read, or a message cannot be deserialized
                and ``skip_undecodable`` is False.
        """
        if topics is None:
            conns = [c for cs in self._conns.values() for c in cs]
        else:
            conns = [c for t in set(topics) for c in self._conns.get(t, [])]
            if not conns:
                return
        errors = _reader_errors()
        it = self._reader.messages(conns, start=start_ns, stop=stop_ns)
        while True:
            try:
                conn, stamp, raw = next(it)
            except StopIteration:
                return
            except errors as exc:
                raise BagIOError(f"{self.path}: cannot read messages: {exc}") from exc
            store = self._decoders.get(conn.id)
            if store is None:
                raise BagIOError(f"{self.path}: topic {conn.topic} has type {conn.msgtype}, "
                                 "which is neither known nor defined in the bag")
            try:
                msg = store.deserialize_cdr(raw, conn.msgtype)
            except (*errors, UnicodeDecodeError, IndexError, TypeError) as exc:
                text = (f"{self.path}: cannot deserialize {conn.msgtype} on {conn.topic} at "
                        f"{stamp} ns: {type(exc).__name__}: {str(exc)[:200]}")
                if not skip_undecodable:
                    raise BagIOError(text) from exc
                self.note_skipped(conn.topic, text)
                continue
            yield BagMessage(conn.topic, conn.msgtype, int(stamp), msg)

    def note_skipped(self, topic: str, text: str) -> None:
        """Count a message of ``topic`` skipped (by the reader or a caller that could not
        convert it) and warn in one line; after ``MAX_SKIP_WARNINGS`` only count."""
        self.skipped[topic] = self.skipped.get(topic, 0) + 1
        n = sum(self.skipped.values())
        level = logging.WARNING if n <= self.MAX_SKIP_WARNINGS else logging.DEBUG
        LOG.log(level, "skipping a message: %s", text)
        if n == self.MAX_SKIP_WARNINGS:
            LOG.warning("%s: further skipped messages are only counted", self.path)

    def close(self) -> None:
        """Close the bag's files."""
        if self._reader.is_open:
            self._reader.close()


def _single_mcap(path: Path) -> Path:
    """The one ``.mcap`` file of a bag directory.

    Raises:
        BagIOError: There is none, or more than one.
    """
    files = sorted(path.glob("*.mcap"))
    if len(files) != 1:
        raise BagIOError(f"{path} is a directory without metadata.yaml (or with one that "
                         f"cannot be used) and {len(files)} .mcap files; cannot tell what "
                         "to read")
    return files[0]


def _open_rosbags_reader(path: Path) -> Any:
    from rosbags.rosbag2 import Reader

    target = path
    if path.is_dir() and not (path / "metadata.yaml").exists():
        # A recording that died before writing metadata.yaml still has readable MCAP data.
        target = _single_mcap(path)
        LOG.warning("%s has no metadata.yaml; reading %s directly", path, target.name)
    if target.is_file() and target.suffix not in (".mcap", ".db3"):
        raise BagIOError(f"{path} is neither a rosbag2 directory nor an .mcap/.db3 file")
    reader = Reader(target)
    try:
        reader.open()
    except _reader_errors() as exc:
        # A cut MCAP (a killed recorder), bare or inside a bag directory with metadata.yaml.
        try:
            mcap = target if target.suffix == ".mcap" else _single_mcap(target)
        except BagIOError:
            raise exc from None
        if (target.is_file() and target.suffix != ".mcap") or mcap.stat().st_size == 0:
            raise
        try:
            recovered = _RecoveredMcap(mcap)
        except BagIOError:
            raise exc from None
        LOG.warning("%s is incomplete (%s); recovered %d messages up to where it ends",
                    mcap, exc, recovered.message_count)
        return recovered
    return reader


class _OpenBag:
    """Context manager returned by :func:`open_bag`."""

    def __init__(self, path: Path) -> None:
        self._path = path
        self._bag: Optional[BagReader] = None

    def __enter__(self) -> BagReader:
        path = self._path
        if not path.exists():
            raise BagIOError(f"bag {path} does not exist")
        try:
            reader = _open_rosbags_reader(path)
        except BagIOError:
            raise
        except _reader_errors() as exc:
            raise BagIOError(f"cannot open bag {path}: {exc}") from exc
        try:
            self._bag = BagReader(path, reader)
        except BaseException as exc:
            reader.close()
            if isinstance(exc, _reader_errors()):
                raise BagIOError(f"cannot read the types of bag {path}: {exc}") from exc
            raise
        return self._bag

    def __exit__(self, *exc: Any) -> None:
        if self._bag is not None:
            self._bag.close()


def open_bag(path: "str | os.PathLike[str]") -> _OpenBag:
    """Open a bag for reading: ``with open_bag(p) as bag: ...``.

    Args:
        path: A rosbag2 directory (MCAP or sqlite3 storage) or a bare ``.mcap``/``.db3`` file.

    Returns:
        A context manager yielding a :class:`BagReader`.

    Raises:
        BagIOError: On entering, if the path is missing or not a readable bag.
    """
    return _OpenBag(Path(path))


def find_topic(topics: Mapping[str, TopicInfo], types: Sequence[str], wanted: Optional[str],
               what: str, path: "str | os.PathLike[str]") -> str:
    """The topic a tool reads: ``wanted`` if given, else one found by type.

    Without ``wanted``, ``types`` are tried in order (a preference, e.g. compressed
    images before raw ones) and within a type the alphabetically first topic is taken;
    a warning names the others.

    Args:
        topics: :meth:`BagReader.topics` of the bag.
        types: Acceptable full type names, most preferred first.
        wanted: The topic the user named, or None / empty to choose by type.
        what: What the topic is for, for messages (e.g. ``"image"``).
        path: The bag, for messages.

    Returns:
        The topic name.

    Raises:
        BagIOError: ``wanted`` is not in the bag or has another type, or no topic has
            one of ``types``.
    """
    if wanted:
        info = topics.get(wanted)
        if info is None:
            raise BagIOError(f"bag {path} has no topic {wanted!r} ({what}); it has "
                             f"{sorted(topics)}")
        if info.msgtype not in types:
            raise BagIOError(f"topic {wanted} of bag {path} has type {info.msgtype}, not "
                             f"{' or '.join(types)} ({what})")
        return wanted
    for msgtype in types:
        matches = sorted(t for t, info in topics.items() if info.msgtype == msgtype)
        if matches:
            if len(matches) > 1:
                LOG.warning("bag %s has several %s topics %s; using %s (choose with an option)",
                            path, what, matches, matches[0])
            return matches[0]
    raise BagIOError(f"bag {path} has no {what} topic (of type {' or '.join(types)}); it has "
                     f"{ {t: i.msgtype for t, i in topics.items()} }")


def _remove_bag(path: Path) -> None:
    if path.is_file() or path.is_symlink():
        path.unlink()
        return
    foreign = [p.name for p in path.iterdir()
               if not (p.is_file() and p.name.endswith(_BAG_FILE_SUFFIXES))]
    if foreign:
        raise BagIOError(f"refusing to overwrite {path}: it holds more than a bag "
                         f"({', '.join(sorted(foreign)[:5])})")
    shutil.rmtree(path)


@dataclass
class _Topic:
    msgtype: str
    connection: Any


class BagWriter:
    """Writes an MCAP rosbag2 directory: ``with BagWriter(path) as bag: ...``.

    Args:
        path: Directory to create; it must not exist unless ``overwrite`` is True.
        overwrite: Replace an existing bag at ``path``.
        compress: zstd-compress the MCAP chunks (smaller raw-image bags, more CPU).

    Raises:
        BagIOError: If the path exists and ``overwrite`` is False.
    """

    def __init__(self, path: "str | os.PathLike[str]", overwrite: bool = False,
                 compress: bool = False) -> None:
        self.path = Path(path)
        self._overwrite = overwrite
        self._compress = compress
        self._writer: Any = None
        self._topics: Dict[str, _Topic] = {}
        self.count = 0
        if self.path.exists() and not overwrite:
            raise BagIOError(f"{self.path} exists already; choose another path or overwrite")

    def open(self) -> "BagWriter":
        """Create the bag on disk (done by ``with``)."""
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        if self.path.exists():
            if not self._overwrite:
                raise BagIOError(f"{self.path} exists already; choose another path or overwrite")
            _remove_bag(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            writer = Writer(self.path, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
            if self._compress:
                writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            writer.open()
        except Exception as exc:
            raise BagIOError(f"cannot create bag {self.path}: {exc}") from exc
        self._writer = writer
        return self

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic before writing to it; declaring it again with the same type is a no-op.

        Raises:
            BagIOError: If the type is unknown or the topic exists with another type.
        """
        if self._writer is None:
            raise BagIOError(f"{self.path}: add_topic before the bag is open")
        name = normalize_msgtype(msgtype)
        have = self._topics.get(topic)
        if have is not None:
            if have.msgtype != name:
                raise BagIOError(f"{self.path}: topic {topic} already has type {have.msgtype}, "
                                 f"not {name}")
            return
        store = typestore()
        if name not in store.fielddefs:
            raise BagIOError(f"{self.path}: unknown message type {name!r} for topic {topic}")
        conn = self._writer.add_connection(topic, name, typestore=store)
        self._topics[topic] = _Topic(name, conn)

    def write(self, topic: str, log_time_ns: int, msg: Any) -> None:
        """Serialize and append one message.

        Raises:
            BagIOError: If the topic was not added, the message has another type or
                cannot be serialized.
        """
        entry = self._topics.get(topic)
        if entry is None:
            raise BagIOError(f"{self.path}: topic {topic} was not added (call add_topic first)")
        got = getattr(msg, "__msgtype__", None)
        if got != entry.msgtype:
            raise BagIOError(f"{self.path}: topic {topic} takes {entry.msgtype}, got "
                             f"{got or type(msg).__name__}")
        try:
            raw = typestore().serialize_cdr(msg, entry.msgtype)
        except Exception as exc:  # rosbags raises struct/Attribute/Type errors on bad fields
            raise BagIOError(f"{self.path}: cannot serialize {entry.msgtype} for {topic} at "
                             f"{log_time_ns} ns: {exc}") from exc
        self._writer.write(entry.connection, int(log_time_ns), raw)
        self.count += 1

    def close(self) -> None:
        """Finish the MCAP file and write ``metadata.yaml``."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        writer, self._writer = self._writer, None
        if writer is None:
            return
        if exc_type is None:
            writer.close()
        else:
            # Keep what was written readable: an unfinished MCAP has no index.
            try:
                writer.close()
            except Exception:  # the original error matters more
                LOG.exception("could not finish %s after an error", self.path)
