"""
Bag input/output for offline replay, without ROS.

Reading (:class:`BagReader`) accepts a rosbag2 directory (sqlite3 or mcap storage, read with
rosbags), a single ``.db3`` file, or a standalone ``.mcap`` file (read with mcap and
mcap-ros2-support, so that a recording cut short still replays up to the cut). Messages are
decoded from the definitions stored in the bag itself: custom types need not be installed.

Writing creates a new standalone MCAP file, readable by Foxglove, PlotJuggler, rosbags and
mcap-ros2-support: :class:`EstimateWriter` holds the topics the live node publishes,
:class:`RecordingWriter` records serialised messages as they come off the wire (what
``ros2 bag record`` does, for machines without the ros2 CLI).

Times are integers in nanoseconds since the epoch (the recorder's log time) wherever a name ends
in ``_ns``; ``start`` and ``end`` given to :meth:`BagReader.messages` are seconds from the first
message of the bag.
"""

from contextlib import contextmanager
from dataclasses import dataclass
import heapq
from io import BytesIO
import math
import os
from pathlib import Path
import re
import struct
from typing import (Any, Dict, FrozenSet, Iterable, Iterator, List, Mapping, NamedTuple,
                    Optional, Sequence, Tuple, TypeVar, Union)

from ctid_ros.errors import BagError, ConfigError, DataError
from ctid_ros.streaming.session import format_diagnostic
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as McapRos2Writer
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores, TypesysError

PathLike = Union[str, os.PathLike]

MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEADER = struct.Struct('<BQ')


class BagMessage(NamedTuple):
    """One recorded message: its topic, recorder log time (ns) and decoded message."""

    topic: str
    log_time_ns: int
    msg: Any


@contextmanager
def _reading(what: str) -> Iterator[None]:
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


class _RosbagsSource:
    """A rosbag2 directory or a ``.db3`` file, read with rosbags."""

    def __init__(self, path: Path) -> None:
        # The Jazzy store is only used by bags without stored definitions (pre-Iron sqlite3).
        with _reading(f'cannot read bag {path} (damaged, or a format rosbags does not support)'):
            reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))
            reader.open()
        self._reader = reader
        self.path = path
        self.truncated = False
        self.warnings: List[str] = []
        infos = reader.topics
        self.topics = {name: info.msgtype for name, info in infos.items()}
        self.counts: Dict[str, Optional[int]] = {name: info.msgcount
                                                 for name, info in infos.items()}
        if reader.message_count:
            self.start_ns: Optional[int] = reader.start_time
            # rosbags reports the end as one nanosecond after the last message
            self.end_ns: Optional[int] = reader.end_time - 1
        else:
            self.start_ns = self.end_ns = None

    def messages(self, topics: Sequence[str], start_ns: Optional[int],
                 end_ns: Optional[int]) -> Iterator[BagMessage]:
        """Check that the topics can be decoded, then stream them in log-time order."""
        connections = [conn for conn in self._reader.connections if conn.topic in topics]
        known = self._reader.typestore.fielddefs
        for conn in connections:
            if conn.msgtype not in known:
                raise BagError(f'{self.path}: topic {conn.topic} has type {conn.msgtype}, which '
                               'the bag does not define and is not a standard ROS 2 Jazzy type; '
                               're-record it with a recent rosbag2 (which stores definitions)')
        return self._iterate(connections, start_ns, end_ns)

    def _iterate(self, connections: list, start_ns: Optional[int],
                 end_ns: Optional[int]) -> Iterator[BagMessage]:
        what = f'{self.path} is corrupted and cannot be read further'
        with _reading(what):
            raw = self._reader.messages(connections, start=start_ns, stop=end_ns)
        while True:
            with _reading(what):
                item = next(raw, None)
                if item is None:
                    return
                conn, log_time_ns, data = item
                msg = self._reader.deserialize(data, conn.msgtype)
            yield BagMessage(conn.topic, log_time_ns, msg)

    def close(self) -> None:
        """Release the files."""
        self._reader.close()


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


class _McapSource:
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
            with _reading('unreadable summary'):
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
                with _reading(f'damaged record at byte {offset}'):
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

    def messages(self, topics: Sequence[str], start_ns: Optional[int],
                 end_ns: Optional[int]) -> Iterator[BagMessage]:
        """Check that the topics can be decoded, then stream them in log-time order."""
        factory = DecoderFactory()
        decoders = {}
        for channel_id, channel in self._channels.items():
            if channel.topic not in topics:
                continue
            schema = self._schemas.get(channel.schema_id)
            with _reading(f'{self.path}: cannot parse the definition of {channel.topic}'):
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
                 end_ns: Optional[int]) -> Iterator[BagMessage]:
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
            with _reading(f'{self.path}: cannot decode the message on {channel.topic} at '
                          f'{log_time_ns} ns'):
                msg = decoders[item.channel_id](item.data)
            yield BagMessage(channel.topic, log_time_ns, msg)

    def _read_block(self, offset: int) -> List[Any]:
        with _reading(f'{self.path} is corrupted at byte {offset} and cannot be read further'):
            self._stream.seek(offset)
            opcode, length = _RECORD_HEADER.unpack(self._stream.read(_RECORD_HEADER.size))
            return _parse(opcode, self._stream.read(length))

    def close(self) -> None:
        """Release the file."""
        self._stream.close()


_Source = Union[_RosbagsSource, _McapSource]


def _open_file(path: Path) -> _Source:
    try:
        with open(path, 'rb') as stream:
            magic = stream.read(len(MCAP_MAGIC))
    except OSError as error:
        raise BagError(f'cannot read {path}: {error.strerror}') from None
    if magic == MCAP_MAGIC or path.suffix == '.mcap':
        return _McapSource(path)
    if path.suffix == '.db3':
        return _RosbagsSource(path)
    raise BagError(f'{path} is not a bag: give a rosbag2 directory (with metadata.yaml), an '
                   '.mcap file or a .db3 file')


def _open_directory(path: Path) -> _Source:
    storage = sorted(path.glob('*.mcap')) + sorted(path.glob('*.db3'))
    if (path / 'metadata.yaml').is_file():
        try:
            return _RosbagsSource(path)
        except BagError as error:
            if len(storage) != 1 or storage[0].suffix != '.mcap':
                raise
            # A recording cut short leaves an MCAP file without its index, which rosbags
            # rejects; the MCAP reader replays what was written before the cut.
            try:
                source = _McapSource(storage[0])
            except BagError:
                raise error from None
            source.warnings.insert(0, f'rosbags cannot read {path} ({error}); reading '
                                      f'{storage[0].name} directly')
            return source
    if not storage:
        raise BagError(f'{path} is not a bag: it has no metadata.yaml and no .mcap or .db3 file')
    if len(storage) > 1:
        names = ', '.join(file.name for file in storage)
        raise BagError(f'{path} has no metadata.yaml and several storage files ({names}); give '
                       f'one of them, or restore the metadata with `ros2 bag reindex {path}`')
    source = _open_file(storage[0])
    source.warnings.insert(0, f'{path} has no metadata.yaml; reading {storage[0].name} directly')
    return source


class BagReader:
    """
    Read recorded messages from a rosbag2 directory, a ``.db3`` file or a ``.mcap`` file.

    Use as a context manager (or call :meth:`close`)::

        with BagReader('run1') as bag:
            for topic, log_time_ns, msg in bag.messages(['/plant/u', '/plant/y'], 10, 40):
                ...

    Parameters
    ----------
    path : str or os.PathLike
        A rosbag2 directory (sqlite3 or mcap storage), a directory holding a single ``.mcap`` or
        ``.db3`` file but no metadata.yaml, or a single ``.mcap``/``.db3`` file.

    Attributes
    ----------
    path : pathlib.Path
        The path given.
    start_time_ns, end_time_ns : int or None
        Log times of the first and the last readable message (None for an empty bag).
    truncated : bool
        True when only a prefix of the recording could be read: the MCAP file was cut short or
        a record is damaged. :meth:`messages` yields the readable messages and then stops.
    warnings : list of str
        What was found wrong with the bag and how it was worked around, for the user.

    Raises
    ------
    BagError
        If the path does not exist, is not a bag, or cannot be read (a damaged sqlite3 database,
        an unreadable MCAP file, unsupported storage).

    """

    def __init__(self, path: PathLike) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        if self.path.is_dir():
            self._source = _open_directory(self.path)
        else:
            self._source = _open_file(self.path)
        self.start_time_ns = self._source.start_ns
        self.end_time_ns = self._source.end_ns
        self.truncated = self._source.truncated
        self.warnings = self._source.warnings

    def __enter__(self) -> 'BagReader':
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the bag; iterators from :meth:`messages` cannot be used afterwards."""
        self._source.close()

    @property
    def duration_s(self) -> float:
        """Return the time from the first to the last message in seconds (0 if empty)."""
        if self.start_time_ns is None:
            return 0.0
        return (self.end_time_ns - self.start_time_ns) / 1e9

    def topics(self) -> Dict[str, str]:
        """Return the message type of each topic, e.g. ``{'/u': 'std_msgs/msg/Float64'}``."""
        return dict(self._source.topics)

    def message_counts(self) -> Dict[str, Optional[int]]:
        """Return the number of (readable) messages on each topic, None where unknown."""
        return dict(self._source.counts)

    def message_count(self, topics: Union[str, Iterable[str], None] = None) -> Optional[int]:
        """
        Return the number of messages on the given topics (all if None), None if unknown.

        The count ignores any start/end selection; a progress display over a time window can use
        ``(log_time_ns - start_ns) / (end_ns - start_ns)`` with :meth:`time_range_ns` instead.

        """
        counts = [self._source.counts[topic] for topic in self._select(topics)]
        return None if None in counts else sum(counts)

    def time_range_ns(self, start: Optional[float] = None,
                      end: Optional[float] = None) -> Tuple[Optional[int], Optional[int]]:
        """
        Convert a window in seconds from the bag start into absolute log times.

        Parameters
        ----------
        start, end : float, optional
            Seconds from the first message of the bag; None leaves that side open.

        Returns
        -------
        tuple of (int or None, int or None)
            ``(start_ns, end_ns)``: the window is ``start_ns <= log_time_ns < end_ns``.

        Raises
        ------
        BagError
            If a bound is not finite, ``start`` is negative or after the last message, or
            ``end <= start``.

        """
        for name, value in (('start', start), ('end', end)):
            if value is not None and not math.isfinite(value):
                raise BagError(f'{name} must be a finite number of seconds, got {value!r}')
        if start is not None and start < 0:
            raise BagError(f'start must be >= 0 s from the bag start, got {start} s')
        if start is not None and end is not None and end <= start:
            raise BagError(f'end ({end} s) must be after start ({start} s)')
        if start is not None and start > self.duration_s:
            raise BagError(f'start {start} s is after the last message of {self.path}, which '
                           f'comes {self.duration_s:.3f} s after the first')
        origin = self.start_time_ns or 0
        return (None if start is None else origin + round(start * 1e9),
                None if end is None else origin + round(end * 1e9))

    def messages(self, topics: Union[str, Iterable[str], None] = None,
                 start: Optional[float] = None, end: Optional[float] = None, *,
                 start_ns: Optional[int] = None,
                 end_ns: Optional[int] = None) -> Iterator[BagMessage]:
        """
        Stream messages in log-time order, decoded from the bag's own definitions.

        The bag is read a chunk (MCAP) or a row (sqlite3) at a time, never loaded whole.

        Parameters
        ----------
        topics : str or iterable of str, optional
            Topics to read; all topics if None.
        start, end : float, optional
            Window in seconds from the first message of the bag (``--start 10 --end 40``):
            messages with ``start <= t - t_first < end``.
        start_ns, end_ns : int, optional
            The same window as absolute log times in nanoseconds; use instead of start/end.

        Returns
        -------
        iterator of BagMessage
            ``(topic, log_time_ns, msg)``; ``msg`` exposes the message fields as attributes
            (arrays may be numpy arrays or lists).

        Raises
        ------
        BagError
            Immediately for unknown topics (the message lists the topics of the bag), an invalid
            window, or a topic whose type cannot be decoded; while iterating if the bag turns out
            to be damaged beyond what was found when it was opened.

        """
        selected = self._select(topics)
        if start is not None and start_ns is not None or end is not None and end_ns is not None:
            raise BagError('give the window either in seconds (start/end) or in nanoseconds '
                           '(start_ns/end_ns), not both')
        lo, hi = self.time_range_ns(start, end)
        lo = start_ns if start_ns is not None else lo
        hi = end_ns if end_ns is not None else hi
        return self._source.messages(selected, lo, hi)

    def _select(self, topics: Union[str, Iterable[str], None]) -> List[str]:
        available = self._source.topics
        if topics is None:
            return list(available)
        selected = [topics] if isinstance(topics, str) else list(topics)
        if not selected:
            raise BagError('no topics selected')
        missing = [topic for topic in selected if topic not in available]
        if missing:
            listing = '; '.join(f'{topic} ({msgtype}, {self._source.counts[topic]} messages)'
                                for topic, msgtype in sorted(available.items())) or 'none'
            raise BagError(f'topic(s) {", ".join(missing)} not in {self.path}; it has: '
                           f'{listing}')
        return selected


def open_bag(path: PathLike) -> BagReader:
    """Open a bag for reading; see :class:`BagReader`."""
    return BagReader(path)


_SEP = '=' * 80 + '\n'
_TIME = 'MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n'
_HEADER = 'MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n'
_LAYOUT = ('MSG: std_msgs/MultiArrayLayout\nMultiArrayDimension[] dim\nuint32 data_offset\n'
           f'{_SEP}MSG: std_msgs/MultiArrayDimension\nstring label\nuint32 size\n'
           'uint32 stride\n')
_STATUS = ('MSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\nbyte WARN=1\nbyte ERROR=2\n'
           'byte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\n'
           f'KeyValue[] values\n{_SEP}MSG: diagnostic_msgs/KeyValue\nstring key\n'
           'string value\n')
# Definitions in the concatenated form rosbag2 stores, so any reader can decode without ROS.
_MSGDEFS = {
    'std_msgs/msg/Float64': 'float64 data\n',
    'std_msgs/msg/Float64MultiArray': f'MultiArrayLayout layout\nfloat64[] data\n{_SEP}{_LAYOUT}',
    'diagnostic_msgs/msg/DiagnosticArray': ('std_msgs/Header header\nDiagnosticStatus[] status\n'
                                            f'{_SEP}{_HEADER}{_SEP}{_TIME}{_SEP}{_STATUS}'),
}
DIAGNOSTIC_OK = 0
DIAGNOSTIC_WARN = 1
_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*\Z')


def _node_prefix(namespace: str, node_name: str) -> str:
    tokens = [token for token in namespace.split('/') if token]
    for token in (*tokens, node_name):
        if not _NAME.match(token):
            raise ConfigError(f'invalid ROS name {token!r} in namespace {namespace!r} / node '
                              f'{node_name!r}: use letters, digits and underscores, not '
                              'starting with a digit')
    return '/' + '/'.join((*tokens, node_name))


def _check_output(path: Path, inputs: Iterable[PathLike], overwrite: bool) -> None:
    if path.suffix != '.mcap':
        raise BagError(f'estimate output {path} must end in .mcap')
    target = path.resolve()
    for source in inputs:
        source = Path(source).resolve()
        if target == source or source in target.parents or (
                target.exists() and source.exists() and os.path.samefile(target, source)):
            raise BagError(f'refusing to write estimates to {path}: it is (inside) the input bag '
                           f'{source}; choose another output file')
    if not target.parent.is_dir():
        raise BagError(f'cannot write {path}: directory {target.parent} does not exist')
    if target.is_dir():
        raise BagError(f'cannot write {path}: it is a directory')
    if target.exists() and not overwrite:
        raise BagError(f'{path} already exists; choose another output file or allow '
                       'overwriting it')


def _stamp(time_ns: int) -> Dict[str, int]:
    return {'sec': time_ns // 1_000_000_000, 'nanosec': time_ns % 1_000_000_000}


def _time_ns(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise DataError(f'times must be non-negative integer nanoseconds, got {value!r}')
    return int(value)


def _status_level(diagnostics: Mapping[str, Any]) -> Tuple[int, str]:
    """Return WARN with the reason if the estimate did not converge or has warnings, else OK."""
    warnings = list(diagnostics.get('warnings') or [])
    if warnings:
        return DIAGNOSTIC_WARN, '; '.join(str(warning) for warning in warnings)
    if diagnostics.get('converged') is False:
        return DIAGNOSTIC_WARN, 'not converged'
    return DIAGNOSTIC_OK, 'ok'


_Output = TypeVar('_Output', bound='_McapOutput')


class _McapOutput:
    """
    A new standalone MCAP file: created by the constructor, indexed and closed by :meth:`close`.

    Subclasses set ``_writer`` (an mcap or mcap_ros2 writer on ``_stream``) and check
    :meth:`_check_open` before writing.
    """

    _writer: Any

    def __init__(self, path: Path, inputs: Iterable[PathLike], overwrite: bool) -> None:
        self.path = path
        _check_output(path, inputs, overwrite)
        try:
            self._stream = open(path, 'wb' if overwrite else 'xb')
        except OSError as error:
            raise BagError(f'cannot create {path}: {error.strerror}') from None
        self._closed = False

    def __enter__(self: _Output) -> _Output:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Write the MCAP index and close the file (also after an error: messages so far stay)."""
        if not self._closed:
            self._closed = True
            try:
                self._writer.finish()
            finally:
                self._stream.close()

    def _check_open(self) -> None:
        if self._closed:
            raise BagError(f'{self.path} is already closed')


class RecordingWriter(_McapOutput):
    """
    Record serialised ROS 2 messages into a new standalone MCAP file, as ``ros2 bag record``.

    The messages are written as received, in CDR (e.g. from an rclpy subscription created with
    ``raw=True``), with the definitions of their types from rosbags' ROS 2 Jazzy type store, so
    :class:`BagReader` and any MCAP tool decode them without ROS.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file to create.
    overwrite : bool, optional
        Replace an existing file at ``path`` instead of refusing.

    Raises
    ------
    BagError
        If ``path`` is not a new ``.mcap`` file or cannot be created.

    """

    def __init__(self, path: PathLike, *, overwrite: bool = False) -> None:
        super().__init__(Path(path), (), overwrite)
        self._writer = McapWriter(self._stream)
        self._writer.start(profile='ros2', library='ctid_ros')
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._schemas: Dict[str, int] = {}
        self._channels: Dict[str, int] = {}

    def add_topic(self, topic: str, msgtype: str) -> None:
        """
        Declare a topic and its message type, e.g. ``'geometry_msgs/msg/PointStamped'``.

        Raises
        ------
        BagError
            If the topic was declared already or the type is not a standard ROS 2 Jazzy type.

        """
        self._check_open()
        if topic in self._channels:
            raise BagError(f'topic {topic} is already recorded in {self.path}')
        if msgtype not in self._schemas:
            try:
                text, _ = self._typestore.generate_msgdef(msgtype, ros_version=2)
            except TypesysError:
                raise BagError(f'cannot record {topic}: {msgtype} is not a standard ROS 2 '
                               'Jazzy message type') from None
            self._schemas[msgtype] = self._writer.register_schema(msgtype, 'ros2msg',
                                                                  text.encode())
        self._channels[topic] = self._writer.register_channel(topic, 'cdr',
                                                              self._schemas[msgtype])

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Write one serialised message of a declared topic at its log (reception) time."""
        self._check_open()
        if topic not in self._channels:
            raise BagError(f'topic {topic} was not declared with add_topic')
        time_ns = _time_ns(log_time_ns)
        self._writer.add_message(self._channels[topic], time_ns, bytes(data), time_ns)


class EstimateWriter(_McapOutput):
    """
    Write estimates to a new standalone MCAP file, on the topics the live node publishes.

    With the default node name and no namespace the topics are ``/ctid_node/estimate`` and
    ``/ctid_node/estimate_std`` (``std_msgs/msg/Float64MultiArray``: values in the order of
    ``names``, the comma-separated names in ``layout.dim[0].label``), ``/ctid_node/params/<name>``
    (``std_msgs/msg/Float64``, one per parameter), ``/ctid_node/prediction``
    (``std_msgs/msg/Float64``, one per predicted sample) and ``/diagnostics``
    (``diagnostic_msgs/msg/DiagnosticArray``, always absolute). Messages are CDR-encoded with
    their definitions embedded, so no ROS installation is needed to read the file.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file to create.
    inputs : iterable of str or os.PathLike, optional
        The bag(s) being replayed: writing to (or into) any of them is refused, even with
        ``overwrite``.
    node_name : str, optional
        Name of the node whose topics are written.
    namespace : str, optional
        ROS namespace of the node, e.g. ``'/plant1'``.
    overwrite : bool, optional
        Replace an existing file at ``path`` instead of refusing.

    Raises
    ------
    BagError
        If ``path`` is not a new ``.mcap`` file outside the inputs, or cannot be created.
    ConfigError
        If the namespace or node name is not a valid ROS name.

    """

    def __init__(self, path: PathLike, *, inputs: Iterable[PathLike] = (),
                 node_name: str = 'ctid_node', namespace: str = '',
                 overwrite: bool = False) -> None:
        prefix = _node_prefix(namespace, node_name)
        super().__init__(Path(path), inputs, overwrite)
        self.estimate_topic = f'{prefix}/estimate'
        self.estimate_std_topic = f'{prefix}/estimate_std'
        self.prediction_topic = f'{prefix}/prediction'
        self.diagnostics_topic = '/diagnostics'
        self._prefix = prefix
        self._writer = McapRos2Writer(self._stream)
        self._schemas = {msgtype: self._writer.register_msgdef(msgtype, text)
                         for msgtype, text in _MSGDEFS.items()}

    def param_topic(self, name: str) -> str:
        """Return the topic of parameter ``name``."""
        return f'{self._prefix}/params/{name}'

    def _write(self, topic: str, msgtype: str, message: Mapping[str, Any], time_ns: int) -> None:
        self._check_open()
        self._writer.write_message(topic, self._schemas[msgtype], message, log_time=time_ns,
                                   publish_time=time_ns)

    def write_estimate(self, time_ns: int, names: Sequence[str], values: Sequence[float],
                       stds: Optional[Sequence[float]] = None,
                       diagnostics: Optional[Mapping[str, Any]] = None) -> None:
        """
        Write one estimate, as the live node publishes it after a window is identified.

        Parameters
        ----------
        time_ns : int
            Log time and header stamp (ns since the epoch), e.g. the window's last sample.
        names : sequence of str
            Parameter names in model order.
        values, stds : sequence of float
            Estimates and their standard deviations (NaN where unknown), in ``names`` order;
            without ``stds`` nothing is written on the ``estimate_std`` topic.
        diagnostics : mapping, optional
            Key/value pairs for ``/diagnostics`` (e.g. ``fit``, ``iterations``, ``converged``,
            ``window_s``, ``samples``, ``warnings``), written in the given order. The status level
            is WARN if ``warnings`` is non-empty or ``converged`` is false, OK otherwise.

        Raises
        ------
        DataError
            If names are not valid, unique ROS name tokens, or lengths differ.

        """
        time_ns = _time_ns(time_ns)
        names = list(names)
        for name in names:
            if not isinstance(name, str) or not _NAME.match(name):
                raise DataError(f'parameter name {name!r} cannot be used in a topic name')
        if len(set(names)) != len(names):
            raise DataError(f'parameter names must be unique, got {names}')
        arrays = {'values': values} if stds is None else {'values': values, 'stds': stds}
        for label, array in arrays.items():
            if len(array) != len(names):
                raise DataError(f'{len(array)} {label} for {len(names)} parameter names')
        layout = {'dim': [{'label': ','.join(names), 'size': len(names),
                           'stride': len(names)}], 'data_offset': 0}
        data = [float(value) for value in values]
        self._write(self.estimate_topic, 'std_msgs/msg/Float64MultiArray',
                    {'layout': layout, 'data': data}, time_ns)
        if stds is not None:
            self._write(self.estimate_std_topic, 'std_msgs/msg/Float64MultiArray',
                        {'layout': layout, 'data': [float(std) for std in stds]}, time_ns)
        for name, value in zip(names, data):
            self._write(self.param_topic(name), 'std_msgs/msg/Float64', {'data': value}, time_ns)
        if diagnostics is not None:
            self._write_diagnostics(time_ns, diagnostics)

    def _write_diagnostics(self, time_ns: int, diagnostics: Mapping[str, Any]) -> None:
        level, message = _status_level(diagnostics)
        status = {'level': level, 'name': f'{self._prefix[1:]}: estimate', 'message': message,
                  'hardware_id': '',
                  'values': [{'key': str(key), 'value': format_diagnostic(value)}
                             for key, value in diagnostics.items()]}
        self._write(self.diagnostics_topic, 'diagnostic_msgs/msg/DiagnosticArray',
                    {'header': {'stamp': _stamp(time_ns), 'frame_id': ''}, 'status': [status]},
                    time_ns)

    def write_prediction(self, times_ns: Sequence[int], values: Sequence[float]) -> None:
        """
        Write predicted output samples, one Float64 message per sample at its own time.

        Parameters
        ----------
        times_ns : sequence of int
            Sample times in integer nanoseconds since the epoch.
        values : sequence of float
            Predicted outputs, one per time.

        Raises
        ------
        DataError
            If the lengths differ or a time is not a non-negative integer.

        """
        times = [_time_ns(time_ns) for time_ns in np.asarray(times_ns).ravel().tolist()]
        data = np.asarray(values, dtype=float).ravel()
        if data.size != len(times):
            raise DataError(f'{data.size} predicted values for {len(times)} times')
        for time_ns, value in zip(times, data.tolist()):
            self._write(self.prediction_topic, 'std_msgs/msg/Float64', {'data': value}, time_ns)
