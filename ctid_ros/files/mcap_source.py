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
from dataclasses import dataclass, replace
import functools
import heapq
from io import BytesIO
import math
import os
from pathlib import Path
import re
import struct
from typing import (Any, Callable, Dict, FrozenSet, Iterator, List, Mapping, NamedTuple,
                    Optional, Sequence, Tuple, Union)
import zlib

from ctid_ros.core.limits import MAX_CHUNK_BYTES, MAX_COMPRESSION_RATIO, MIB, size_text
from ctid_ros.errors import BagError
import lz4.frame
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Schema
from mcap_ros2.decoder import DecoderFactory
import numpy as np
from rosbags.typesys import get_types_from_idl, get_types_from_msg, get_typestore, Stores
import zstandard

__all__ = ['BagMessage', 'BagRecord', 'MCAP_MAGIC', 'McapSource', 'PathLike', 'RawBlock',
           'RawStream', 'field_definitions',
           'TopicSchema', 'byte_rows', 'check_chunk_sizes', 'chunk_records', 'chunk_size_problem',
           'is_service_event', 'raw_block',
           'reading_errors', 'service_event_error']

PathLike = Union[str, os.PathLike]

MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEADER = struct.Struct('<BQ')
# A message record: channel id, sequence, log time and publish time, then the data.
_MESSAGE_FIELDS = struct.Struct('<HIQQ')
# A chunk record's fixed fields: message start and end time, uncompressed size and CRC.
_CHUNK_FIELDS = struct.Struct('<QQQI')
_LENGTH = struct.Struct('<I')
# A message index record's fixed fields: channel id and byte length of its (log time, offset)
# pairs.
_MESSAGE_INDEX_FIELDS = struct.Struct('<HI')
# A message record as it lies in a chunk, up to its data (opcode and length, then the fields).
_MESSAGE_HEAD = np.dtype([('opcode', 'u1'), ('length', '<u8'), ('channel', '<u2'),
                          ('sequence', '<u4'), ('log_time', '<u8'), ('publish_time', '<u8')])
# Message heads read from a chunk at once, from the offsets its message index gives.
_GATHERED_HEADS = 1 << 16
_RECORDS_LENGTH = struct.Struct('<Q')
# Bytes read at the start of compressed records: enough for a zstd or lz4 frame header.
_FRAME_HEADER_BYTES = 32
_READ_PIECE = MIB


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


class RawBlock(NamedTuple):
    """
    Serialised messages of the selected topics, in arrival (log-time) order, not decoded.

    Attributes
    ----------
    data : ndarray of uint8
        A buffer holding the messages (a decompressed chunk, or several).
    starts, lengths : ndarray of int64
        Where each message (CDR, with its encapsulation header) starts in ``data``, its size.
    log_time_ns : ndarray of int64
        The recorder's log time of each message.
    topic : ndarray of int
        Index of each message's topic in the topics asked for.

    """

    data: np.ndarray
    starts: np.ndarray
    lengths: np.ndarray
    log_time_ns: np.ndarray
    topic: np.ndarray

    def __len__(self) -> int:
        return int(self.starts.size)

    def message(self, index: int) -> bytes:
        """Return the bytes of message ``index``."""
        start = int(self.starts[index])
        return self.data[start:start + int(self.lengths[index])].tobytes()


def raw_block(messages: Sequence[Tuple[int, int, bytes]]) -> RawBlock:
    """Pack ``(topic index, log time, bytes)`` triples, in arrival order, into a block."""
    lengths = np.fromiter((len(item[2]) for item in messages), dtype=np.int64,
                          count=len(messages))
    starts = np.concatenate(([0], np.cumsum(lengths)[:-1])).astype(np.int64) if \
        len(messages) else np.zeros(0, dtype=np.int64)
    data = np.frombuffer(b''.join(item[2] for item in messages), dtype=np.uint8)
    return RawBlock(data, starts, lengths,
                    np.fromiter((item[1] for item in messages), dtype=np.int64,
                                count=len(messages)),
                    np.fromiter((item[0] for item in messages), dtype=np.int64,
                                count=len(messages)))


class RawStream(NamedTuple):
    """
    One stream of serialised messages of a bag (an MCAP channel, a rosbags connection).

    Attributes
    ----------
    topic, msgtype : str
        Its topic and message type.
    fielddefs : mapping or None
        Field definitions of the type and the types it uses (a rosbags typestore's
        ``fielddefs``), for a columnar CDR decoder; None if the messages are not CDR or the
        definitions could not be parsed.
    decode : callable
        ``decode(log_time_ns, data)``: one message decoded as the streaming reader does it,
        raising the same :class:`~ctid_ros.errors.BagError` for bytes that do not fit.

    """

    topic: str
    msgtype: str
    fielddefs: Optional[Mapping[str, Any]]
    decode: Callable[[int, bytes], Any]


def field_definitions(msgtype: str, encoding: str, definition: bytes
                      ) -> Optional[Mapping[str, Any]]:
    """Parse a stored definition (``ros2msg`` or ``ros2idl``) into rosbags field definitions."""
    try:
        text = definition.decode()
        if encoding == 'ros2msg':
            types = get_types_from_msg(text, msgtype)
        elif encoding == 'ros2idl':
            separator = '=' * 80 + '\n'
            types = {}
            parts = text.split(separator)[1:] if text.startswith(separator + 'IDL: ') \
                else [text]
            for part in parts:
                types.update(get_types_from_idl(part.split('\n', 1)[1] if part.startswith(
                    'IDL: ') else part))
        else:
            return None
        store = get_typestore(Stores.EMPTY)
        store.register(types)
        return store.fielddefs
    except Exception:   # an unparsable definition: the per-message decoder reports it
        return None


def _split_pool(pool: List[Tuple[np.ndarray, Tuple[np.ndarray, ...], int]],
                bound: Tuple[float, int]
                ) -> Tuple[Optional[RawBlock], List[Tuple[np.ndarray, Tuple[np.ndarray, ...],
                                                          int]]]:
    """
    Take from the pooled chunks every message that precedes ``bound``, in arrival order.

    Messages are ordered by log time, then file offset of their chunk, then position in it;
    ``bound`` is the (start time, offset) of the next chunk to read.
    """
    if not pool:
        return None, pool
    data = pool[0][0] if len(pool) == 1 else np.concatenate([item[0] for item in pool])
    bases = np.cumsum([0] + [item[0].size for item in pool[:-1]])
    columns = [np.concatenate([item[1][column] for item in pool]) for column in range(5)]
    index, starts, lengths, times, topics = columns
    offsets = np.concatenate([np.full(item[1][0].size, item[2]) for item in pool])
    starts = starts + np.concatenate([np.full(item[1][0].size, base)
                                      for item, base in zip(pool, bases)])
    before = (times < bound[0]) | ((times == bound[0]) & (offsets < bound[1]))
    order = np.lexsort((index, offsets, times))
    order = order[before[order]]
    block = RawBlock(data, starts[order], lengths[order], times[order], topics[order])
    keep = []
    for item in pool:
        times = item[1][3]
        remaining = ~((times < bound[0]) | ((times == bound[0]) & (item[2] < bound[1])))
        if np.any(remaining):
            keep.append((item[0], tuple(column[remaining] for column in item[1]), item[2]))
    return block, keep


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


_SERVICE_EVENT = re.compile(r'/srv/\w+_Event\Z')


def is_service_event(topic: str, msgtype: str) -> bool:
    """Tell whether a topic carries service events (``ros2 bag record --services``)."""
    return bool(_SERVICE_EVENT.search(msgtype or '')) or topic.endswith('/_service_event')


def service_event_error(path: PathLike, topic: str, msgtype: str) -> BagError:
    """Return the error for a service-event topic selected as an input or output."""
    return BagError(f'{path}: {topic} carries service events ({msgtype}, recorded with '
                    '`ros2 bag record --services` or --all-services), not messages; ctid replay '
                    'reads message topics: select the topics of the signals')


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

    ``channel_ids`` is None when the file does not say which channels the chunk holds;
    ``message_index`` is the (file offset, length) of the chunk's message index records, None
    when the file has none for it.

    """

    offset: int
    start_ns: int
    end_ns: int
    channel_ids: Optional[FrozenSet[int]]
    message_index: Optional[Tuple[int, int]] = None


class _ChunkRefused(BagError):
    """A chunk beyond the limits: refused, never decompressed (not a truncation)."""


def chunk_size_problem(declared: int, compressed: int, compression: str) -> Optional[str]:
    """Say why a chunk of these sizes is refused before decompressing it, or None."""
    if declared > MAX_CHUNK_BYTES:
        return (f'declares {size_text(declared)} uncompressed, more than the limit of '
                f'{size_text(MAX_CHUNK_BYTES)} per chunk')
    if compression and declared > MIB and declared > MAX_COMPRESSION_RATIO * max(compressed, 1):
        return (f'declares {size_text(declared)} uncompressed from {size_text(compressed)}, a '
                f'ratio of {declared / max(compressed, 1):.0f} (the limit is '
                f'{MAX_COMPRESSION_RATIO}): a decompression bomb or a damaged chunk')
    return None


def _frame_problem(declared: int, compression: str, start: bytes) -> Optional[str]:
    """Check the content size a zstd or lz4 frame header states against the chunk's size."""
    try:
        if compression == 'zstd':
            stated = zstandard.frame_content_size(start)
        elif compression == 'lz4':
            stated = lz4.frame.get_frame_info(start)['content_size'] or -1
        else:
            return None
    except Exception:  # a damaged frame header is reported when the chunk is decompressed
        return None
    if stated >= 0 and stated != declared:
        return (f'holds {compression} data of {size_text(stated)} (as its frame header says) '
                f'but declares {size_text(declared)} uncompressed: a decompression bomb or a '
                'damaged chunk')
    return None


def _decompressed(chunk: Chunk) -> bytes:
    """Return the records of a chunk, decompressing at most its declared size (bounded)."""
    declared = chunk.uncompressed_size
    if not chunk.compression:
        data = bytes(chunk.data)
    elif chunk.compression == 'zstd':
        reader = zstandard.ZstdDecompressor().stream_reader(chunk.data, read_across_frames=True)
        pieces, total = [], 0
        while total <= declared:
            piece = reader.read(min(_READ_PIECE, declared + 1 - total))
            if not piece:
                break
            pieces.append(piece)
            total += len(piece)
        data = b''.join(pieces)
    elif chunk.compression == 'lz4':
        data, rest = b'', bytes(chunk.data)
        while rest and len(data) <= declared:
            decompressor = lz4.frame.LZ4FrameDecompressor()
            data += decompressor.decompress(rest, max_length=declared + 1 - len(data))
            if not decompressor.eof:
                break
            rest = decompressor.unused_data
    else:
        raise BagError(f'chunk compression {chunk.compression!r} is not supported (only zstd '
                       'and lz4)')
    if len(data) != declared:
        more = 'more than' if len(data) > declared else 'only'
        raise BagError(f'chunk decompresses to {more} {size_text(len(data))}, not the '
                       f'{size_text(declared)} it declares: damaged')
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise BagError('chunk CRC mismatch: damaged')
    return data


def chunk_bytes(chunk: Chunk) -> bytes:
    """Return the records of a chunk, decompressed within the limits of :func:`chunk_records`."""
    problem = (chunk_size_problem(chunk.uncompressed_size, len(chunk.data), chunk.compression)
               or _frame_problem(chunk.uncompressed_size, chunk.compression,
                                 bytes(chunk.data[:_FRAME_HEADER_BYTES])))
    if problem:
        raise _ChunkRefused(f'chunk {problem}')
    return _decompressed(chunk)


def _message_positions(data: bytes, wanted: Mapping[int, int], lo: int, hi: float
                       ) -> Tuple[np.ndarray, ...]:
    """
    Find the message records of the wanted channels in a chunk's records.

    Returns the record index, data start, data length, log time and topic index of each, in
    record order (one pass over the record headers; the message data are not touched).
    """
    found: List[Tuple[int, int, int, int, int]] = []
    position, index, size = 0, 0, len(data)
    unpack_header, unpack_message = _RECORD_HEADER.unpack_from, _MESSAGE_FIELDS.unpack_from
    header, fields = _RECORD_HEADER.size, _MESSAGE_FIELDS.size
    while position < size:
        if size - position < header:
            raise BagError('chunk ends inside a record header: damaged')
        opcode, length = unpack_header(data, position)
        start = position + header
        end = start + length
        if opcode == 0 or end > size:
            raise BagError(f'chunk holds an invalid record (opcode {opcode}, {length} bytes) at '
                           f'byte {position}: damaged')
        if opcode == Opcode.MESSAGE:
            if length < fields:
                raise BagError(f'chunk holds a message record of {length} bytes at byte '
                               f'{position}: damaged')
            channel, _, log_time, _ = unpack_message(data, start)
            topic = wanted.get(channel)
            if topic is not None and lo <= log_time < hi:
                found.append((index, start + fields, length - fields, log_time, topic))
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            index += 1
        position = end
    columns = np.array(found, dtype=np.int64).reshape(-1, 5)
    return tuple(columns[:, column] for column in range(5))


def byte_rows(buffer: np.ndarray, at: np.ndarray, size: int) -> np.ndarray:
    """
    Return the ``size`` bytes of ``buffer`` (uint8) from each position ``at``, a row each.

    A copy, positions clipped to the buffer byte by byte (the row of a position near the end
    repeats the last byte). When every row lies within the buffer the rows are taken from a
    strided view of it: one gather of rows, not one of ``size`` times as many single bytes.
    """
    if at.size and size <= buffer.size and int(at.min()) >= 0 and \
            int(at.max()) <= buffer.size - size:
        step = buffer.strides[0]
        rows = np.lib.stride_tricks.as_strided(buffer, (buffer.size - size + 1, size),
                                               (step, step), writeable=False)
        return rows[at]
    return buffer[np.clip(at[:, None] + np.arange(size), 0, max(buffer.size - 1, 0))]


def _indexed_positions(data: bytes, offsets: np.ndarray, wanted: Mapping[int, int], lo: int,
                       hi: float) -> Optional[Tuple[np.ndarray, ...]]:
    """
    Find the message records of the wanted channels in a chunk's records from its index.

    ``offsets`` are where the chunk's message index records say its messages start, for every
    channel in the chunk. They are checked against the records, with numpy: each must hold a
    message record, and those records with the few other records between them (schema and
    channel records, walked one by one) must fill the chunk exactly, end to end. Then the result
    is that of :func:`_message_positions`; None if the index does not fit the records (damaged,
    or written by another rule), for the sequential walk to decide.
    """
    size = len(data)
    head = _MESSAGE_HEAD.itemsize
    if offsets.size == 0 or offsets.min() < 0 or offsets.max() > size - head:
        return None
    if np.any(offsets[1:] <= offsets[:-1]):    # several channels, or a repeated entry
        offsets = np.sort(offsets)
        offsets = offsets[np.concatenate(([True], offsets[1:] != offsets[:-1]))]
    buffer = np.frombuffer(data, dtype=np.uint8)
    heads = np.empty(offsets.size, dtype=_MESSAGE_HEAD)
    # In slices: the byte positions of a whole chunk of tiny messages would take gigabytes.
    for first in range(0, offsets.size, _GATHERED_HEADS):
        part = offsets[first:first + _GATHERED_HEADS]
        heads[first:first + part.size] = byte_rows(buffer, part, head).view(_MESSAGE_HEAD)[:, 0]
    if np.any(heads['opcode'] != Opcode.MESSAGE) or \
            np.any(heads['length'] < _MESSAGE_FIELDS.size) or \
            np.any(heads['length'] > size) or np.any(heads['log_time'] >= 1 << 63):
        return None
    lengths = heads['length'].astype(np.int64)
    ends = offsets + _RECORD_HEADER.size + lengths
    # Between consecutive messages (and before the first, after the last): other records.
    gap_starts = np.concatenate(([0], ends))
    gap_ends = np.concatenate((offsets, [size]))
    if np.any(gap_starts > gap_ends):
        return None
    others = np.zeros(gap_starts.size, dtype=np.int64)
    for gap in np.flatnonzero(gap_starts < gap_ends).tolist():
        count = _other_records(data, int(gap_starts[gap]), int(gap_ends[gap]))
        if count is None:
            return None
        others[gap] = count
    index = np.arange(offsets.size, dtype=np.int64) + np.cumsum(others)[:-1]
    channels = heads['channel']
    topic = np.zeros(offsets.size, dtype=np.int64)
    selected = np.zeros(offsets.size, dtype=bool)
    for channel, topic_index in wanted.items():
        on_channel = channels == channel
        topic[on_channel] = topic_index
        selected |= on_channel
    log_time = heads['log_time'].astype(np.int64)
    selected &= (log_time >= lo) & (log_time < hi)
    return (index[selected], offsets[selected] + head, lengths[selected] - _MESSAGE_FIELDS.size,
            log_time[selected], topic[selected])


def _other_records(data: bytes, position: int, stop: int) -> Optional[int]:
    """
    Count the records from ``position`` to ``stop`` of a chunk, which hold no message.

    Returns the number of schema and channel records among them; None if a record is invalid,
    a message, or does not end exactly at ``stop``.
    """
    count = 0
    while position < stop:
        if stop - position < _RECORD_HEADER.size:
            return None
        opcode, length = _RECORD_HEADER.unpack_from(data, position)
        position += _RECORD_HEADER.size + length
        if opcode in (0, Opcode.MESSAGE) or position > stop:
            return None
        count += opcode in (Opcode.SCHEMA, Opcode.CHANNEL)
    return count


def _index_offsets(records: bytes) -> Optional[np.ndarray]:
    """
    Return the message offsets that a chunk's message index records list, of every channel.

    None if ``records`` are not message index records end to end.
    """
    found = []
    position = 0
    header, fields = _RECORD_HEADER.size, _MESSAGE_INDEX_FIELDS.size
    while position < len(records):
        if len(records) - position < header + fields:
            return None
        opcode, length = _RECORD_HEADER.unpack_from(records, position)
        _, pairs = _MESSAGE_INDEX_FIELDS.unpack_from(records, position + header)
        start = position + header + fields
        position += header + length
        if opcode != Opcode.MESSAGE_INDEX or pairs % 16 or length != fields + pairs or \
                position > len(records):
            return None
        found.append(np.frombuffer(records, dtype='<u8', count=pairs // 8,
                                   offset=start)[1::2])
    if not found:
        return None
    offsets = np.concatenate(found)
    if np.any(offsets >= 1 << 62):
        return None
    return offsets.astype(np.int64)


def chunk_records(chunk: Chunk) -> List[Any]:
    """
    Return the schema, channel and message records of a chunk, decompressed within limits.

    Raises
    ------
    BagError
        If the chunk declares more than :data:`~ctid_ros.core.limits.MAX_CHUNK_BYTES`, or a
        compression ratio above :data:`~ctid_ros.core.limits.MAX_COMPRESSION_RATIO` (both
        before decompressing), if a frame states another size than the chunk, or if the chunk
        does not decompress to its declared size, fails its CRC or holds an invalid record.

    """
    return _records(chunk_bytes(chunk))


def _records(data: bytes) -> List[Any]:
    """Return the schema, channel and message records of a chunk's decompressed records."""
    records: List[Any] = []
    position = 0
    while position < len(data):
        if len(data) - position < _RECORD_HEADER.size:
            raise BagError('chunk ends inside a record header: damaged')
        opcode, length = _RECORD_HEADER.unpack_from(data, position)
        start = position + _RECORD_HEADER.size
        end = start + length
        if opcode == 0 or end > len(data):
            raise BagError(f'chunk holds an invalid record (opcode {opcode}, {length} bytes) at '
                           f'byte {position}: damaged')
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            stream = ReadDataStream(BytesIO(data[start:end]))
            if opcode == Opcode.SCHEMA:
                records.append(Schema.read(stream))
            elif opcode == Opcode.CHANNEL:
                records.append(Channel.read(stream))
            else:
                records.append(Message.read(stream, length))
        position = end
    return records


def _cut_chunk(body: bytes) -> bytes:
    """
    Return the whole records at the start of a chunk that the end of the file cuts short.

    ``body`` is what the file holds of the chunk record after its opcode and length. Its
    records are decompressed as far as the bytes go (a zstd or lz4 stream yields its blocks
    before the cut), within the size the chunk declares and the limits of
    :func:`chunk_bytes`; the record the cut splits is left out. The CRC covers the whole
    chunk and cannot be checked. ``b''`` if nothing of the records is there.
    """
    head = _CHUNK_FIELDS.size + _LENGTH.size
    if len(body) < head:
        return b''
    declared = _CHUNK_FIELDS.unpack_from(body)[2]
    (name_length,) = _LENGTH.unpack_from(body, _CHUNK_FIELDS.size)
    start = head + name_length + _RECORDS_LENGTH.size
    if name_length > 64 or len(body) < start:
        return b''
    compression = body[head:head + name_length].decode('utf-8', 'replace')
    (compressed,) = _RECORDS_LENGTH.unpack_from(body, head + name_length)
    data = body[start:start + compressed]
    problem = (chunk_size_problem(declared, compressed, compression)
               or _frame_problem(declared, compression, data[:_FRAME_HEADER_BYTES]))
    if problem:
        raise _ChunkRefused(f'chunk {problem}')
    if not compression:
        records = data[:declared]
    elif compression == 'zstd':
        reader = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True)
        pieces, total = [], 0
        try:
            while total < declared:
                piece = reader.read(min(_READ_PIECE, declared - total))
                if not piece:
                    break
                pieces.append(piece)
                total += len(piece)
        except zstandard.ZstdError:
            pass
        records = b''.join(pieces)
    elif compression == 'lz4':
        try:
            records = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=declared)
        except RuntimeError:
            records = b''
    else:
        return b''
    position = 0
    while len(records) - position >= _RECORD_HEADER.size:
        opcode, length = _RECORD_HEADER.unpack_from(records, position)
        end = position + _RECORD_HEADER.size + length
        if opcode == 0 or end > len(records):
            break
        position = end
    return records[:position]


def check_chunk_sizes(path: Path) -> None:
    """
    Check the chunk headers of an MCAP file against the limits, without decompressing.

    Reads the header of every top-level record (a few bytes per chunk) up to the end of the
    data section, or up to where the file is cut short; run it before handing a file to a
    reader that decompresses chunks without bounds (rosbags).

    Raises
    ------
    BagError
        If the file cannot be read, or a chunk declares more than
        :data:`~ctid_ros.core.limits.MAX_CHUNK_BYTES`, a compression ratio above
        :data:`~ctid_ros.core.limits.MAX_COMPRESSION_RATIO`, or holds a frame stating another
        size than the chunk's.

    """
    try:
        with open(path, 'rb') as stream:
            size = os.fstat(stream.fileno()).st_size
            offset = len(MCAP_MAGIC)
            while True:
                stream.seek(offset)
                head = stream.read(_RECORD_HEADER.size)
                if len(head) < _RECORD_HEADER.size:
                    return
                opcode, length = _RECORD_HEADER.unpack(head)
                if opcode in (Opcode.DATA_END, Opcode.FOOTER) or \
                        offset + _RECORD_HEADER.size + length > size:
                    return
                if opcode == Opcode.CHUNK:
                    _check_chunk_header(stream, path, offset)
                offset += _RECORD_HEADER.size + length
    except BagError:
        raise
    except OSError as error:
        raise BagError(f'cannot read {path}: {error.strerror or error}') from None


def _check_chunk_header(stream: Any, path: Path, offset: int) -> None:
    fields = stream.read(_CHUNK_FIELDS.size + _LENGTH.size)
    if len(fields) < _CHUNK_FIELDS.size + _LENGTH.size:
        return
    declared = _CHUNK_FIELDS.unpack_from(fields)[2]
    (name_length,) = _LENGTH.unpack_from(fields, _CHUNK_FIELDS.size)
    if name_length > 64:
        return      # not a compression name: the reader reports the damaged chunk
    compression = stream.read(name_length).decode('utf-8', 'replace')
    counted = stream.read(_RECORDS_LENGTH.size)
    if len(counted) < _RECORDS_LENGTH.size:
        return
    (compressed,) = _RECORDS_LENGTH.unpack(counted)
    problem = (chunk_size_problem(declared, compressed, compression)
               or _frame_problem(declared, compression, stream.read(_FRAME_HEADER_BYTES)))
    if problem:
        raise _ChunkRefused(f'{path}: the chunk at byte {offset} {problem}; refusing to read '
                            'the file')


def _parse(opcode: int, body: bytes) -> List[Any]:
    """Parse one top-level MCAP record, expanding a chunk into its records."""
    stream = ReadDataStream(BytesIO(body))
    if opcode == Opcode.CHUNK:
        return chunk_records(Chunk.read(stream))
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
    incomplete or damaged record and the messages before it remain available, those of a chunk
    the end of the file cuts short included (its whole records before the cut, as ``mcap
    recover`` reads them: every record of an uncompressed chunk, the whole compressed blocks of
    a zstd or lz4 one).

    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.truncated = False
        self.warnings: List[str] = []
        self._schemas: Dict[int, Schema] = {}
        self._channels: Dict[int, Channel] = {}
        self._counts: Dict[int, int] = {}
        self._blocks: List[_Block] = []
        # The readable records of a chunk cut short by the end of the file, by its offset.
        self._cut: Dict[int, bytes] = {}
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
        for index in summary.chunk_indexes:
            problem = chunk_size_problem(index.uncompressed_size, index.compressed_size,
                                         index.compression)
            if problem:
                raise BagError(f'{self.path}: the chunk at byte {index.chunk_start_offset} '
                               f'{problem}; refusing to read the file')
        self._schemas = dict(summary.schemas)
        self._channels = dict(summary.channels)
        self._counts = dict(stats.channel_message_counts)
        self._blocks = [_Block(index.chunk_start_offset, index.message_start_time,
                               index.message_end_time,
                               frozenset(index.message_index_offsets) or None,
                               (min(index.message_index_offsets.values()),
                                index.message_index_length)
                               if index.message_index_offsets else None)
                        for index in summary.chunk_indexes]
        if stats.message_count:
            self.start_ns, self.end_ns = stats.message_start_time, stats.message_end_time
        return True

    def _scan(self, size: int, complete: bool) -> None:
        """Index the file by reading it from the start, stopping at the first bad record."""
        offset = len(MCAP_MAGIC)
        # Where message index records of the last chunk read start or go on (None: no chunk).
        index_at: Optional[int] = None
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
                recovered = self._recover(offset, size) if opcode == Opcode.CHUNK else 0
                self._stop(offset, size, f'the file ends in the middle of a chunk, of which '
                           f'{recovered} messages are read up to the cut' if recovered else
                           'the file ends in the middle of a record')
                return
            try:
                with reading_errors(f'damaged record at byte {offset}'):
                    records = _parse(opcode, self._stream.read(length))
            except _ChunkRefused as error:
                raise BagError(f'{self.path}: the {error} (at byte {offset}); refusing to read '
                               'the file') from None
            except BagError as error:
                self._stop(offset, size, str(error))
                return
            if opcode == Opcode.MESSAGE_INDEX and offset == index_at:
                block = self._blocks[-1]
                start = offset if block.message_index is None else block.message_index[0]
                self._blocks[-1] = replace(block, message_index=(start, end - start))
                index_at = end
            else:
                blocks = len(self._blocks)
                self._add_block(offset, records)
                index_at = end if opcode == Opcode.CHUNK and len(self._blocks) > blocks else None
            offset = end
        if not complete:
            self.truncated = True
            self.warnings.append(f'{self.path} is truncated after its data section (the index '
                                 'is missing); all its messages were read by scanning')

    def _recover(self, offset: int, size: int) -> int:
        """Index the whole records of the chunk at ``offset`` the end of the file cuts: count."""
        try:
            with reading_errors(f'damaged record at byte {offset}'):
                records = _cut_chunk(self._stream.read(size - offset - _RECORD_HEADER.size))
                parsed = _records(records)
        except _ChunkRefused as error:
            raise BagError(f'{self.path}: the {error} (at byte {offset}); refusing to read '
                           'the file') from None
        except BagError:
            return 0
        messages = sum(isinstance(record, Message) for record in parsed)
        if messages:
            self._cut[offset] = records
        self._add_block(offset, parsed)
        return messages

    def _stop(self, offset: int, size: int, reason: str) -> None:
        self.truncated = True
        count = sum(self._counts.values())
        self.warnings.append(f'{self.path} is truncated or corrupted: {reason} (byte {offset} '
                             f'of {size}); replaying the {count} messages readable before the cut')

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
        return self._iterate(self._decoders(topics), start_ns, end_ns)

    def _decoders(self, topics: Sequence[str]) -> Dict[int, Any]:
        """Return a decoder per channel of the topics, or raise why one cannot be decoded."""
        factory = DecoderFactory()
        decoders = {}
        for channel_id, channel in self._channels.items():
            if channel.topic not in topics:
                continue
            schema = self._schemas.get(channel.schema_id)
            msgtype = schema.name if schema is not None else '(no schema)'
            if is_service_event(channel.topic, msgtype):
                raise service_event_error(self.path, channel.topic, msgtype)
            with reading_errors(f'{self.path}: cannot parse the definition of {channel.topic}'):
                decoder = factory.decoder_for(channel.message_encoding, schema)
            if decoder is None:
                encoding = schema.encoding if schema is not None else 'none'
                raise BagError(f'{self.path}: topic {channel.topic} cannot be decoded: it uses '
                               f'message encoding {channel.message_encoding!r} with schema '
                               f'encoding {encoding!r}; only CDR messages with ros2msg '
                               'definitions are supported')
            decoders[channel_id] = decoder
        return decoders

    def _decode(self, decoder: Any, channel: Channel, log_time_ns: int, data: bytes) -> Any:
        with reading_errors(f'{self.path}: cannot decode the message on {channel.topic} '
                            f'at {log_time_ns} ns'):
            return decoder(data)

    def raw_streams(self, topics: Sequence[str]) -> Dict[int, RawStream]:
        """
        Check that the topics can be decoded; return their channels as :class:`RawStream`.

        The stream ids are the channel ids, as :meth:`raw_blocks` gives them.
        """
        streams = {}
        for channel_id, decoder in self._decoders(topics).items():
            channel = self._channels[channel_id]
            schema = self._schemas.get(channel.schema_id)
            streams[channel_id] = RawStream(
                channel.topic, schema.name, field_definitions(schema.name, schema.encoding,
                                                              bytes(schema.data))
                if channel.message_encoding == 'cdr' else None,
                functools.partial(self._decode, decoder, channel))
        return streams

    def raw_blocks(self, streams: Mapping[int, Any], start_ns: Optional[int],
                   end_ns: Optional[int]) -> Iterator[RawBlock]:
        """
        Yield the serialised messages of the channels ``streams`` in arrival order, by block.

        The order is that of :meth:`records` (log time, then position in the file): a block
        holds the messages that no unread chunk can precede; chunks that overlap in time are
        merged, so at most those are held at once. A chunk that cannot be read raises
        :class:`~ctid_ros.errors.BagError` after every message before it was yielded.
        """
        lo = -1 if start_ns is None else start_ns
        hi = math.inf if end_ns is None else end_ns
        wanted = {channel_id: channel_id for channel_id in streams}
        blocks = sorted((block for block in self._blocks
                         if block.end_ns >= lo and block.start_ns < hi
                         and (block.channel_ids is None or block.channel_ids & set(wanted))),
                        key=lambda block: (block.start_ns, block.offset))
        pool: List[Tuple[np.ndarray, Tuple[np.ndarray, ...], int]] = []
        for block in blocks + [None]:
            bound = (math.inf, 0) if block is None else (block.start_ns, block.offset)
            ready, pool = _split_pool(pool, bound)
            if ready is not None and len(ready):
                yield ready
            if block is None:
                break
            data = self._read_raw(block.offset)
            positions = self._indexed(block, data, wanted, lo, hi)
            if positions is None:
                positions = _message_positions(data, wanted, lo, hi)
            if positions[0].size:
                pool.append((np.frombuffer(data, dtype=np.uint8), positions, block.offset))

    def _indexed(self, block: _Block, data: bytes, wanted: Mapping[int, int], lo: int,
                 hi: float) -> Optional[Tuple[np.ndarray, ...]]:
        """Find the wanted messages of a chunk from its message index; None without one."""
        if block.message_index is None:
            return None
        offset, length = block.message_index
        try:
            self._stream.seek(offset)
            records = self._stream.read(length)
        except (OSError, ValueError, OverflowError):
            return None
        offsets = _index_offsets(records)
        return None if offsets is None else _indexed_positions(data, offsets, wanted, lo, hi)

    def _read_raw(self, offset: int) -> bytes:
        """Return the records of the chunk (or the one message record) at ``offset``."""
        if offset in self._cut:
            return self._cut[offset]
        try:
            with reading_errors(f'{self.path} is corrupted at byte {offset} and cannot be read '
                                'further'):
                self._stream.seek(offset)
                opcode, length = _RECORD_HEADER.unpack(self._stream.read(_RECORD_HEADER.size))
                if opcode == Opcode.MESSAGE:
                    return _RECORD_HEADER.pack(opcode, length) + self._stream.read(length)
                if opcode != Opcode.CHUNK:
                    raise ValueError(f'the index points at a record of opcode {opcode}, not at '
                                     'a chunk')
                return chunk_bytes(Chunk.read(ReadDataStream(BytesIO(
                    self._stream.read(length)))))
        except _ChunkRefused as error:
            raise BagError(f'{self.path}: the {error} (at byte {offset}); refusing to read it'
                           ) from None
        except BagError as error:
            raise self._damaged(offset, error) from None

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
            msg = self._decode(decoders[item.channel_id], channel, log_time_ns, item.data)
            yield BagRecord(channel.topic, log_time_ns, msg, item.data)

    def _read_block(self, offset: int) -> List[Any]:
        if offset in self._cut:
            return _records(self._cut[offset])
        try:
            with reading_errors(f'{self.path} is corrupted at byte {offset} and cannot be read '
                                'further'):
                self._stream.seek(offset)
                opcode, length = _RECORD_HEADER.unpack(self._stream.read(_RECORD_HEADER.size))
                if opcode not in (Opcode.CHUNK, Opcode.MESSAGE):
                    raise ValueError(f'the index points at a record of opcode {opcode}, not at '
                                     'a chunk')
                return _parse(opcode, self._stream.read(length))
        except _ChunkRefused as error:
            raise BagError(f'{self.path}: the {error} (at byte {offset}); refusing to read it'
                           ) from None
        except BagError as error:
            raise self._damaged(offset, error) from None

    def _damaged(self, offset: int, error: BagError) -> BagError:
        """Name the file and the place of a chunk that cannot be read (a CRC mismatch)."""
        text = str(error)
        if text.startswith(str(self.path)):
            return error
        return BagError(f'{self.path} is corrupted at byte {offset} and cannot be read '
                        f'further: {text}')

    def first_message(self) -> Optional[bytes]:
        """Return the serialised first message of the file (any channel), None if it has none."""
        block = next(self.raw_blocks(self._channels, None, None), None)
        return None if block is None else block.message(0)

    def close(self) -> None:
        """Release the file."""
        self._stream.close()
