"""Recovery of a cut MCAP file: read it record by record, without its index.

A recorder that is killed leaves an MCAP file without summary section, footer or end
magic, which ``rosbags`` refuses to open. :class:`_RecoveredMcap` walks such a file from
its start magic and keeps every complete Schema, Channel and Message record, those inside
chunks included (uncompressed or zstd; a chunk the file ends in gives its complete
records), up to the data end or the first record the file cuts short.

Used only by :func:`signal_light_node.io.bagio.open_bag`, when ``rosbags`` cannot open a
bare ``.mcap`` file or the one ``.mcap`` of a bag directory: the ``BagReader`` it returns
then reads the recovered messages like those of an intact bag, and
``BagReader.recovered`` says how many there are.
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, Optional, Tuple

from signal_light_node.errors import BagIOError

LOG = logging.getLogger(__name__)


class _RecoveredMcap:
    """Sequential reader for an MCAP file without summary or end magic.

    A recorder that is killed leaves such a file; ``rosbags`` refuses it, the ``mcap``
    stream reader reads every complete record up to the cut. It mimics the part of
    ``rosbags.rosbag2.Reader`` that :class:`BagReader` uses. Messages come in file order,
    which is arrival order for a recorder.
    """

    def __init__(self, path: Path) -> None:
        from rosbags.interfaces import (Connection, ConnectionExtRosbag2, MessageDefinition,
                                        MessageDefinitionFormat)

        self.path = path
        self.storage = self
        self.is_open = True
        schemas: Dict[int, Any] = {}
        channels: Dict[int, Any] = {}
        counts: Dict[int, int] = {}
        first, last, ordered = None, None, True
        for record in self._records():
            kind = type(record).__name__
            if kind == "Schema":
                schemas[record.id] = record
            elif kind == "Channel":
                channels[record.id] = record
            elif kind == "Message":
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                ordered = ordered and (last is None or record.log_time >= last)
                first = record.log_time if first is None else min(first, record.log_time)
                last = record.log_time if last is None else max(last, record.log_time)
        if not channels:
            raise BagIOError(f"{path}: no readable channel in the MCAP data")
        if not ordered:
            LOG.warning("%s: messages of the recovered MCAP are not in time order", path)
        formats = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
        self.connections = []
        for cid, chan in sorted(channels.items()):
            schema = schemas.get(chan.schema_id)
            fmt = formats.get(schema.encoding) if schema is not None else None
            self.connections.append(Connection(
                id=cid, topic=chan.topic, msgtype=schema.name if schema else "",
                msgdef=MessageDefinition(fmt or MessageDefinitionFormat.NONE,
                                         schema.data.decode() if fmt else ""),
                digest="", msgcount=counts.get(cid, 0),
                ext=ConnectionExtRosbag2(chan.message_encoding, []), owner=self))
        self.message_count = sum(counts.values())
        self.start_time = first if first is not None else 2**63 - 1
        # rosbags' convention: end_time is one past the last message.
        self.end_time = last + 1 if last is not None else 0

    def _records(self) -> Iterator[Any]:
        import mmap

        with open(self.path, "rb") as stream:
            if os.fstat(stream.fileno()).st_size == 0:
                return
            with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
                yield from _mcap_records(data, self.path)

    def messages(self, connections: Iterable[Any], start: Optional[int] = None,
                 stop: Optional[int] = None) -> Iterator[Tuple[Any, int, bytes]]:
        wanted = {c.id: c for c in connections}
        for record in self._records():
            if type(record).__name__ != "Message" or record.channel_id not in wanted:
                continue
            if (start is None or record.log_time >= start) and (
                    stop is None or record.log_time < stop):
                yield wanted[record.channel_id], record.log_time, record.data

    def close(self) -> None:
        self.is_open = False


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, content length
_CHUNK_HEAD = struct.Struct("<QQQI")  # start time, end time, uncompressed size, CRC


def _mcap_records(data: Any, path: Path) -> Iterator[Any]:
    """Schema, Channel and Message records of MCAP bytes, up to the last complete one.

    Tolerates a cut anywhere: a record the file ends in is dropped, except a chunk,
    whose complete inner records are read (uncompressed or zstd chunks).
    """
    from mcap.opcode import Opcode

    if bytes(data[:8]) != _MCAP_MAGIC:
        LOG.debug("%s: no MCAP magic", path)
        return
    pos, end = 8, len(data)
    while pos + _RECORD_HEAD.size <= end:
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        body = data[pos + _RECORD_HEAD.size: pos + _RECORD_HEAD.size + length]
        cut = len(body) < length
        if opcode == Opcode.CHUNK:
            yield from _chunk_records(body, path)
        elif opcode == Opcode.DATA_END:
            return
        elif not cut:
            record = _parse_record(opcode, body)
            if record is not None:
                yield record
        if cut:
            LOG.debug("%s: the file ends inside a record at byte %d", path, pos)
            return
        pos += _RECORD_HEAD.size + length


def _parse_record(opcode: int, body: bytes) -> Any:
    """A Schema, Channel or Message record from its content; None for other kinds."""
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.MESSAGE:
        return Message.read(stream, len(body))
    if opcode == Opcode.SCHEMA:
        return Schema.read(stream)
    if opcode == Opcode.CHANNEL:
        return Channel.read(stream)
    return None


def _chunk_records(body: bytes, path: Path) -> Iterator[Any]:
    """The complete records of a chunk, which may itself be cut short."""
    head = _CHUNK_HEAD.size + 4
    if len(body) < head:
        return
    (name_len,) = struct.unpack_from("<I", body, _CHUNK_HEAD.size)
    compression = bytes(body[head:head + name_len]).decode("utf-8", "replace")
    payload = bytes(body[head + name_len + 8:])  # after the records' length
    if compression == "zstd":
        import zstandard

        try:
            payload = zstandard.ZstdDecompressor().decompressobj().decompress(payload)
        except zstandard.ZstdError as exc:
            LOG.warning("%s: a zstd chunk cannot be decompressed (%s); skipped", path, exc)
            return
    elif compression:
        LOG.warning("%s: chunk compression %r is not supported here; chunk skipped", path,
                    compression)
        return
    pos = 0
    while pos + _RECORD_HEAD.size <= len(payload):
        opcode, length = _RECORD_HEAD.unpack_from(payload, pos)
        inner = payload[pos + _RECORD_HEAD.size: pos + _RECORD_HEAD.size + length]
        if len(inner) < length:
            return
        record = _parse_record(opcode, inner)
        if record is not None:
            yield record
        pos += _RECORD_HEAD.size + length
