"""
A standalone MCAP file read without ROS, and what every bag reader yields.

:class:`McapSource` reads a ``.mcap`` file with mcap and mcap-ros2-support: a complete file
through its summary, a file without a usable summary (cut short by a crash, or written without
one) by scanning it once for the readable chunks, so that a recording cut short still replays up
to the cut. Messages are decoded from the definitions stored in the file itself.

:class:`BagMessage` and :func:`reading_errors` are shared with the rosbag2 reader
(:mod:`ctid_ros.files.bag_reader`). Times are integer nanoseconds since the epoch (the
recorder's log time).
"""

from contextlib import contextmanager
from dataclasses import dataclass
import heapq
from io import BytesIO
import math
import os
from pathlib import Path
import struct
from typing import (Any, Dict, FrozenSet, Iterator, List, Mapping, NamedTuple, Optional,
                    Sequence, Union)

from ctid_ros.errors import BagError
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap_ros2.decoder import DecoderFactory

__all__ = ['BagMessage', 'BagRecord', 'MCAP_MAGIC', 'McapSource', 'PathLike', 'TopicSchema',
           'reading_errors']

PathLike = Union[str, os.PathLike]

MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEADER = struct.Struct('<BQ')


class BagMessage(NamedTuple):
    """One recorded message: its topic, recorder log time (ns) and decoded message."""

    topic: str
    log_time_ns: int
    msg: Any


class BagRecord(NamedTuple):
    """One recorded message as :class:`BagMessage`, with its serialised bytes as recorded."""

    topic: str
    log_time_ns: int
    msg: Any
    data: bytes


class TopicSchema(NamedTuple):
    """
    How the messages of a topic are encoded, as an MCAP channel and its schema record say.

    Attributes
    ----------
    msgtype : str
        Message type, e.g. ``'std_msgs/msg/Float64'``.
    encoding : str
        Encoding of the definition: ``'ros2msg'`` or ``'ros2idl'``.
    definition : bytes
        The message definition, with those of the types it uses.
    message_encoding : str
        Encoding of the messages, ``'cdr'`` for ROS 2.

    """

    msgtype: str
    encoding: str
    definition: bytes
    message_encoding: str = 'cdr'


@contextmanager
def reading_errors(what: str) -> Iterator[None]:
    """
    Turn any failure inside the third-party readers into a :class:`BagError`.

    Damaged bytes can make rosbags, apsw, mcap, zstd or the CDR decoder fail with almost any
    exception type; for the user they all mean the same thing: this part of the bag is unreadable.

    """
    try:
        yield
    except BagError:
        raise
    except Exception as error:
        raise BagError(f'{what}: {type(error).__name__}: {error}') from error


@dataclass(frozen=True)
class _Block:
    """
    A chunk (or one message stored outside chunks) of an MCAP file.

    ``channel_ids`` is None when the file does not say which channels the chunk holds.

    """

    offset: int
    start_ns: int
    end_ns: int
    channel_ids: Optional[FrozenSet[int]]


def _parse(opcode: int, body: bytes) -> List[Any]:
    """Parse one top-level MCAP record, expanding a chunk into its records."""
    stream = ReadDataStream(BytesIO(body))
    if opcode == Opcode.CHUNK:
        return breakup_chunk(Chunk.read(stream), validate_crc=True)
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, len(body))]
    if opcode == Opcode.SCHEMA:
        return [Schema.read(stream)]
    if opcode == Opcode.CHANNEL:
        return [Channel.read(stream)]
    return []


class McapSource:
    """
    A standalone MCAP file, read with mcap and mcap-ros2-support.

    A complete file is read through its summary (chunk index and statistics). A file without a
    usable summary (cut short by a crash or power loss, or written without one) is scanned once
    when opened, a chunk at a time, to index the readable chunks; the scan stops at the first
    incomplete or damaged record and the messages before it remain available.

    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.truncated = False
        self.warnings: List[str] = []
        self._schemas: Dict[int, Schema] = {}
        self._channels: Dict[int, Channel] = {}
        self._counts: Dict[int, int] = {}
        self._blocks: List[_Block] = []
        self.start_ns: Optional[int] = None
        self.end_ns: Optional[int] = None
        try:
            self._stream = open(path, 'rb')
        except OSError as error:
            raise BagError(f'cannot open {path}: {error.strerror}') from None
        try:
            self._index()
        except BaseException:
            self._stream.close()
            raise
        self.topics = {channel.topic: self._type_name(channel)
                       for channel in self._channels.values()}
        self.counts: Dict[str, Optional[int]] = dict.fromkeys(self.topics, 0)
        for channel_id, count in self._counts.items():
            self.counts[self._channels[channel_id].topic] += count

    def _type_name(self, channel: Channel) -> str:
        schema = self._schemas.get(channel.schema_id)
        return schema.name if schema is not None else '(no schema)'

    def _index(self) -> None:
        size = os.fstat(self._stream.fileno()).st_size
        if self._stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise BagError(f'{self.path} is not an MCAP file (it does not start with the MCAP '
                           'magic bytes); a compressed file (.mcap.zstd) must be decompressed '
                           'first')
        self._stream.seek(size - len(MCAP_MAGIC))
        complete = size >= 2 * len(MCAP_MAGIC) and self._stream.read() == MCAP_MAGIC
        if not (complete and self._index_from_summary()):
            self._scan(size, complete)

    def _index_from_summary(self) -> bool:
        """Index a complete file from its summary; False if there is none to use."""
        try:
            with reading_errors('unreadable summary'):
                self._stream.seek(0)
                summary = SeekingReader(self._stream).get_summary()
        except BagError as error:
            self.warnings.append(f'{self.path}: the index at the end of the file is damaged '
                                 f'({error}); scanning the whole file instead')
            return False
        if summary is None or summary.statistics is None:
            return False
        stats = summary.statistics
        if stats.message_count and not summary.chunk_indexes:
            return False
        self._schemas = dict(summary.schemas)
        self._channels = dict(summary.channels)
        self._counts = dict(stats.channel_message_counts)
        self._blocks = [_Block(index.chunk_start_offset, index.message_start_time,
                               index.message_end_time,
                               frozenset(index.message_index_offsets) or None)
                        for index in summary.chunk_indexes]
        if stats.message_count:
            self.start_ns, self.end_ns = stats.message_start_time, stats.message_end_time
        return True

    def _scan(self, size: int, complete: bool) -> None:
        """Index the file by reading it from the start, stopping at the first bad record."""
        offset = len(MCAP_MAGIC)
        while True:
            self._stream.seek(offset)
            head = self._stream.read(_RECORD_HEADER.size)
            if len(head) < _RECORD_HEADER.size:
                self._stop(offset, size, 'the file ends in the middle of a record')
                return
            opcode, length = _RECORD_HEADER.unpack(head)
            if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                break
            end = offset + _RECORD_HEADER.size + length
            if end > size:
                self._stop(offset, size, 'the file ends in the middle of a record')
                return
            try:
                with reading_errors(f'damaged record at byte {offset}'):
                    records = _parse(opcode, self._stream.read(length))
            except BagError as error:
                self._stop(offset, size, str(error))
                return
            self._add_block(offset, records)
            offset = end
        if not complete:
            self.truncated = True
            self.warnings.append(f'{self.path} is truncated after its data section (the index '
                                 'is missing); all its messages were read by scanning')

    def _stop(self, offset: int, size: int, reason: str) -> None:
        self.truncated = True
        count = sum(self._counts.values())
        self.warnings.append(f'{self.path} is truncated or corrupted: {reason} (byte {offset} '
                             f'of {size}); replaying the {count} messages before that point')

    def _add_block(self, offset: int, records: List[Any]) -> None:
        times = []
        channel_ids = set()
        for record in records:
            if isinstance(record, Schema):
                self._schemas[record.id] = record
            elif isinstance(record, Channel):
                self._channels[record.id] = record
            elif isinstance(record, Message):
                times.append(record.log_time)
                channel_ids.add(record.channel_id)
                self._counts[record.channel_id] = self._counts.get(record.channel_id, 0) + 1
        if times:
            self._blocks.append(_Block(offset, min(times), max(times), frozenset(channel_ids)))
            self.start_ns = min(times) if self.start_ns is None else min(self.start_ns, *times)
            self.end_ns = max(times) if self.end_ns is None else max(self.end_ns, *times)

    def schema(self, topic: str) -> TopicSchema:
        """Return how the messages of ``topic`` are encoded (its first channel's schema)."""
        channel = next(channel for channel in self._channels.values() if channel.topic == topic)
        schema = self._schemas.get(channel.schema_id)
        if schema is None:
            raise BagError(f'{self.path}: topic {topic} has no schema')
        return TopicSchema(schema.name, schema.encoding, bytes(schema.data),
                           channel.message_encoding)

    def records(self, topics: Sequence[str], start_ns: Optional[int],
                end_ns: Optional[int]) -> Iterator[BagRecord]:
        """Check that the topics can be decoded, then stream them in log-time order."""
        factory = DecoderFactory()
        decoders = {}
        for channel_id, channel in self._channels.items():
            if channel.topic not in topics:
                continue
            schema = self._schemas.get(channel.schema_id)
            with reading_errors(f'{self.path}: cannot parse the definition of {channel.topic}'):
                decoder = factory.decoder_for(channel.message_encoding, schema)
            if decoder is None:
                encoding = schema.encoding if schema is not None else 'none'
                raise BagError(f'{self.path}: topic {channel.topic} cannot be decoded: it uses '
                               f'message encoding {channel.message_encoding!r} with schema '
                               f'encoding {encoding!r}; only CDR messages with ros2msg '
                               'definitions are supported')
            decoders[channel_id] = decoder
        return self._iterate(decoders, start_ns, end_ns)

    def _iterate(self, decoders: Mapping[int, Any], start_ns: Optional[int],
                 end_ns: Optional[int]) -> Iterator[BagRecord]:
        lo = -1 if start_ns is None else start_ns
        hi = math.inf if end_ns is None else end_ns
        wanted = frozenset(decoders)
        # Entries are (log time, file offset, position, item); blocks use position -1 and are
        # keyed by their earliest message, so a message leaves the heap only once no unread
        # block can hold an earlier one. This keeps at most the overlapping chunks in memory.
        heap = [(block.start_ns, block.offset, -1, block) for block in self._blocks
                if block.end_ns >= lo and block.start_ns < hi
                and (block.channel_ids is None or block.channel_ids & wanted)]
        heapq.heapify(heap)
        while heap:
            log_time_ns, offset, position, item = heapq.heappop(heap)
            if position < 0:
                for index, record in enumerate(self._read_block(offset)):
                    if (isinstance(record, Message) and record.channel_id in wanted
                            and lo <= record.log_time < hi):
                        heapq.heappush(heap, (record.log_time, offset, index, record))
                continue
            channel = self._channels[item.channel_id]
            with reading_errors(f'{self.path}: cannot decode the message on {channel.topic} '
                                f'at {log_time_ns} ns'):
                msg = decoders[item.channel_id](item.data)
            yield BagRecord(channel.topic, log_time_ns, msg, item.data)

    def _read_block(self, offset: int) -> List[Any]:
        with reading_errors(f'{self.path} is corrupted at byte {offset} and cannot be read '
                            'further'):
            self._stream.seek(offset)
            opcode, length = _RECORD_HEADER.unpack(self._stream.read(_RECORD_HEADER.size))
            return _parse(opcode, self._stream.read(length))

    def close(self) -> None:
        """Release the file."""
        self._stream.close()
