"""
Recorded messages from a rosbag2 directory, an MCAP file or a ROS 1 bag, without ROS.

:class:`BagReader` accepts a rosbag2 directory (sqlite3 or mcap storage, read with rosbags), a
single ``.db3`` file, a standalone ``.mcap`` file (read by
:class:`~ctid_ros.files.mcap_source.McapSource`, so that a recording cut short still replays up
to the cut), or a ROS 1 ``.bag`` file (read with rosbags' rosbag1 reader). Messages are decoded
from the definitions stored in the bag itself: custom types need not be installed.

A ROS 1 message is converted to CDR as it is read (rosbags' ``ros1_to_cdr``, which drops the
``seq`` of ``std_msgs/Header`` as ``rosbags-convert`` does), so that every reader downstream
sees what the same message recorded by rosbag2 would be: the same field paths, the same
``header.stamp``, and ``--output`` copies that ROS 2 tools read.

Times are integer nanoseconds since the epoch (the recorder's log time) wherever a name ends
in ``_ns``; ``start`` and ``end`` given to :meth:`BagReader.messages` are seconds from the first
message of the bag.
"""

import bz2
import contextlib
import functools
import math
import os
from pathlib import Path
import re
import shutil
import sqlite3
import tempfile
from typing import (Any, Callable, Dict, Iterable, Iterator, List, Mapping, NamedTuple,
                    Optional, Sequence, Tuple, TypeVar, Union)

from ctid_ros.core.limits import (MAX_COMPRESSION_RATIO, MAX_METADATA_BYTES, MIB, read_limited,
                                  size_text)
from ctid_ros.errors import BagError
from ctid_ros.files.mcap_source import (BagMessage, BagRecord, check_chunk_sizes,
                                        chunk_size_problem, is_service_event, MCAP_MAGIC,
                                        McapSource, PathLike,
                                        raw_block, RawBlock, RawStream, reading_errors,
                                        service_event_error, TopicSchema)
from ctid_ros.streaming.contract import NANOSECONDS
from ctid_ros.streaming.params_file import parse_yaml
import lz4.frame
from rosbags.highlevel import AnyReader
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag1.reader import Header as Ros1Header, RecordType as Ros1RecordType
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Typestore
import zstandard

__all__ = ['BagReader', 'open_bag', 'readable_part']

_VERSION = re.compile(rb'^\s*version:\s*(\d+)', re.MULTILINE)
_ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'
_ROS1_MAGIC = b'#ROSBAG V'
# Bytes read from the start of a file to tell what it is.
_HEAD_BYTES = 64
# Magic numbers of file kinds that are given where a bag is expected, and what they are.
_FILE_KINDS = (
    (b'SQLite format 3\x00', 'an SQLite database'),
    (b'\x1f\x8b', 'a gzip-compressed file'),
    (_ZSTD_MAGIC, 'a zstd-compressed file'),
    (b'BZh', 'a bzip2-compressed file'),
    (b'\x04\x22\x4d\x18', 'an lz4-compressed file'),
    (b'PK\x03\x04', 'a zip archive'),
    (b'\xfd7zXZ\x00', 'an xz-compressed file'),
    (b'\x7fELF', 'an executable (ELF)'),
    (b'\x89PNG', 'a PNG image'),
    (b'%PDF', 'a PDF document'),
    (b'PAR1', 'a Parquet file'),
)
# YAML nodes of a metadata.yaml (about 20 per topic and 10 per storage file).
_METADATA_NODES = 1_000_000
# Characters of a third-party error quoted in a warning (rosbags quotes whole definitions).
_QUOTE_LIMIT = 300
# Messages per block of a rosbags-read bag handed to a columnar reader.
_RAW_BLOCK = 1 << 15
# Bytes decompressed at a time when a compressed storage file is measured.
_DECOMPRESSION_PIECE = 1 << 20
# The files SQLite keeps beside a database in WAL mode.
_SQLITE_SIDE_FILES = ('.db3-wal', '.db3-shm')


def _quoted(error: BaseException) -> str:
    text = ' '.join(str(error).split())
    return text if len(text) <= _QUOTE_LIMIT else text[:_QUOTE_LIMIT - 3] + '...'


class _StandardTypes:
    """
    The standard ROS 2 Jazzy types as AnyReader's ``default_typestore``, loaded on first use.

    AnyReader reads only their ``fielddefs``, and only for a bag that stores no definitions
    (pre-Iron sqlite3); loading the store imports the types of every ROS 2 distribution, which
    other bags never need.
    """

    @property
    def fielddefs(self) -> Mapping[str, Any]:
        return get_typestore(Stores.ROS2_JAZZY).fielddefs


def _open_reader(paths: Sequence[Path], path: Path) -> AnyReader:
    what = (f'cannot read ROS 1 bag {path} (damaged, or cut short before its index was '
            'written: `rosbag reindex` on ROS 1 rebuilds it)' if path.suffix == '.bag' else
            f'cannot read bag {path} (damaged, or a format rosbags does not support)')
    with reading_errors(what):
        reader = AnyReader(list(paths), default_typestore=_StandardTypes())
        reader.open()
    if not reader.is2:
        try:
            _guard_ros1_chunks(reader, path)
        except BagError:
            reader.close()
            raise
    return reader


class _Storage(NamedTuple):
    """What the storage files of a rosbag2 directory hold, against its metadata.yaml."""

    counts: Dict[str, int]          # messages stored per topic
    matched: Dict[str, int]         # of those, messages rosbags pairs with the metadata
    reasons: Dict[str, str]         # why the metadata and the storage disagree, per topic
    start_ns: Optional[int]
    end_ns: Optional[int]
    files: List[Path]
    compressed: Optional[bool]      # whether the first stored message is a zstd frame


def _storage(reader: AnyReader) -> Optional[_Storage]:
    """
    Compare a rosbag2 directory's metadata with its storage files, as rosbags pairs them.

    rosbags yields a stored message only if its topic, type, serialization format, QoS
    profiles and type hash equal those of a topic in metadata.yaml; where an older or edited
    metadata.yaml disagrees, the messages are silently skipped. None if rosbags' readers do
    not have the expected structure (another rosbags version), which skips the check.
    """
    directory = getattr(reader.readers[0], 'storage', None) if len(reader.readers) == 1 \
        else None
    storages = getattr(directory, 'storages', None)
    listed = getattr(directory, 'connections', None)
    if not storages or listed is None:
        return None
    counts: Dict[str, int] = {}
    matched: Dict[str, int] = {}
    reasons: Dict[str, str] = {}
    starts, ends = [], []
    for storage in storages:
        if storage.metadata.message_count:
            starts.append(storage.metadata.start_time)
            ends.append(storage.metadata.end_time - 1)
        for conn in storage.connections:
            counts[conn.topic] = counts.get(conn.topic, 0) + conn.msgcount
            same_topic = [item for item in listed if item.topic == conn.topic]
            differences = [_difference(item, conn) for item in same_topic]
            if None in differences:
                matched[conn.topic] = matched.get(conn.topic, 0) + conn.msgcount
            elif conn.msgcount:
                reasons[conn.topic] = differences[0] if differences else 'not listed'
    compressed = None
    for storage in storages:
        if storage.connections and storage.metadata.message_count:
            first = _first_message(storage)
            if first is not None:
                compressed = first[:4] == _ZSTD_MAGIC
                break
    return _Storage(counts, matched, reasons, min(starts, default=None),
                    max(ends, default=None), [Path(storage.path) for storage in storages],
                    compressed)


def _first_message(storage: Any) -> Optional[bytes]:
    """
    Return the first stored message of one of rosbags' storage files, None if it has none.

    An MCAP file's comes from its index and first chunk (:class:`McapSource`); rosbags would
    parse the whole first chunk message by message to yield it. A file that reader refuses is
    read with rosbags, which reports its problem as before.
    """
    if Path(storage.path).suffix == '.mcap':
        try:
            source = McapSource(Path(storage.path))
        except BagError:
            source = None
        if source is not None:
            try:
                return source.first_message()
            except BagError:
                pass
            finally:
                source.close()
    with reading_errors(f'cannot read {storage.path}'):
        first = next(storage.messages(storage.connections), None)
    return None if first is None else bytes(first[2])


def _difference(listed: Any, stored: Any) -> Optional[str]:
    """Name what makes rosbags skip a stored topic of the metadata's, or None if it matches."""
    if listed.msgtype != stored.msgtype:
        return f'type {listed.msgtype} against {stored.msgtype}'
    if listed.ext != stored.ext:
        if getattr(listed.ext, 'serialization_format', None) != \
                getattr(stored.ext, 'serialization_format', None):
            return 'serialization format'
        return 'QoS profiles'
    if listed.digest and stored.digest and listed.digest != stored.digest:
        return 'type hash'
    return None


def _bounded(decompress: Callable[[bytes], bytes], compression: str, declared: int
             ) -> Callable[[bytes], bytes]:
    """Return a decompressor of a ROS 1 chunk that stops past its declared size."""
    if compression == 'none':
        return decompress

    def bounded(data: bytes) -> bytes:
        engine = bz2.BZ2Decompressor() if compression == 'bz2' else \
            lz4.frame.LZ4FrameDecompressor()
        output = engine.decompress(data, max_length=declared + 1)
        if len(output) != declared:
            than = 'more' if len(output) > declared else 'less'
            raise BagError(f'a {compression} chunk decompresses to {than} than the {declared} '
                           'bytes it declares')
        return output
    return bounded


def _guard_ros1_chunks(reader: AnyReader, path: Path) -> None:
    """
    Refuse the ROS 1 chunks whose declared sizes are absurd; bound every decompression.

    rosbags decompresses a whole chunk at once, whatever its size: a chunk that declares
    more than the chunk limit, or a ratio beyond the compression limit, is refused before
    any message is read (as for MCAP), and one that decompresses past what it declares
    raises once it has.
    """
    for bag in reader.readers:
        chunks = getattr(bag, 'chunks', None)
        stream = getattr(bag, 'bio', None)
        if not isinstance(chunks, dict) or stream is None:
            return      # another rosbags version: its own reading stands
        for position, chunk in list(chunks.items()):
            with reading_errors(f'cannot read ROS 1 bag {path}'):
                stream.seek(position)
                header = Ros1Header.read(stream, Ros1RecordType.CHUNK)
                declared = header.get_uint32('size')
                compression = header.get_string('compression')
            problem = chunk_size_problem(declared, chunk.datasize,
                                         '' if compression == 'none' else compression)
            if problem is not None:
                raise BagError(f'{path}: the chunk at byte {position} {problem}')
            chunks[position] = chunk._replace(
                decompressor=_bounded(chunk.decompressor, compression, declared))


def _cdr_typestore(ros1: Typestore) -> Typestore:
    """
    Return the types of a ROS 1 bag as their ROS 2 counterparts, to hold its messages as CDR.

    Every type keeps its fields but ``std_msgs/msg/Header``, which takes the ROS 2 layout
    (without ``seq``), as ``rosbags-convert`` does.
    """
    store = get_typestore(Stores.EMPTY)
    header = 'std_msgs/msg/Header'
    store.register({**ros1.fielddefs,
                    header: get_typestore(Stores.ROS2_JAZZY).fielddefs[header]})
    return store


class _RosbagsSource:
    """A rosbag2 directory, a ``.db3`` file or a ROS 1 ``.bag`` file, read with rosbags."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.truncated = False
        self.warnings: List[str] = []
        opened, self._merged = _merged_logs(path, self.warnings)
        try:
            reader = _open_reader([opened], path)
        except BagError:
            self._remove_merged()
            raise
        storage = _storage(reader) if opened.is_dir() else None
        # One uncompressed MCAP storage file: its blocks are read without rosbags' per-message
        # Python (raw_blocks); rosbags reads the same messages from it.
        self._mcap_file = storage.files[0] if (
            storage is not None and len(storage.files) == 1 and
            storage.files[0].suffix == '.mcap' and not storage.compressed and
            not getattr(reader.readers[0].storage.metadata, 'compression_mode', None)) else None
        self._mcap: Optional[McapSource] = None
        if storage is not None:
            reader = self._checked(reader, storage)
        self._reader = reader
        # A ROS 1 bag's messages are handed on as CDR, decoded with the ROS 2 layout.
        self._cdr: Optional[Typestore] = None if reader.is2 else _cdr_typestore(reader.typestore)
        self._has_definitions = any(conn.msgdef.format != MessageDefinitionFormat.NONE
                                    for conn in reader.connections)
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
        if storage is not None and reader.readers[0].path.is_dir():
            self._use_storage_counts(storage)

    def _checked(self, reader: AnyReader, storage: _Storage) -> AnyReader:
        """Read the storage files directly where metadata.yaml would mislead rosbags."""
        content = (self.path / 'metadata.yaml').read_bytes()
        version = _VERSION.search(content)
        what = f'metadata.yaml (version {version.group(1).decode()})' if version else \
            'metadata.yaml'
        names = ', '.join(file.name for file in storage.files)
        mode = getattr(reader.readers[0].storage.metadata, 'compression_mode', None)
        problems = []
        if mode == 'message' and storage.compressed is False:
            problems.append(f'{what} says the messages are zstd-compressed (compression_mode: '
                            f'message) but {names} hold(s) uncompressed messages')
            mode = None
        elif not mode and storage.compressed:
            reader.close()
            raise BagError(f'{self.path}: {names} hold(s) zstd-compressed messages but {what} '
                           'says they are not compressed: set compression_format: zstd and '
                           'compression_mode: message in metadata.yaml')
        skipped = {topic: storage.counts[topic] - storage.matched.get(topic, 0)
                   for topic in storage.reasons}
        if skipped:
            details = '; '.join(f'{topic}: {storage.reasons[topic]}' for topic in sorted(skipped))
            problems.append(f'{what} and {names} disagree about {len(skipped)} topic(s) '
                            f'({details}), so rosbags would skip {sum(skipped.values())} stored '
                            'message(s)')
        if not problems:
            return reader
        reader.close()
        problem = f'{self.path}: ' + '; '.join(problems)
        if mode:
            raise BagError(f'{problem}; the bag is compressed and cannot be read without its '
                           'metadata: restore metadata.yaml, or re-index the bag (ros2 bag '
                           'reindex)')
        self.warnings.append(f'{problem}; reading {names} directly (their own topic table)')
        return _open_reader(storage.files, self.path)

    def _use_storage_counts(self, storage: _Storage) -> None:
        """Take message counts and times from the storage where metadata.yaml differs."""
        for topic, listed in list(self.counts.items()):
            stored = storage.counts.get(topic, 0)
            if listed != stored:
                self.warnings.append(
                    f'{self.path}: metadata.yaml counts {listed} message(s) on {topic}, the '
                    f'storage holds {stored}; using the storage (ros2 bag reindex rewrites the '
                    'metadata)')
                self.counts[topic] = stored
        if (storage.start_ns, storage.end_ns) != (self.start_ns, self.end_ns):
            if self.start_ns is not None or storage.start_ns is not None:
                self.warnings.append(f'{self.path}: metadata.yaml gives another time span than '
                                     'the stored messages; using the stored messages')
            self.start_ns, self.end_ns = storage.start_ns, storage.end_ns

    def schema(self, topic: str) -> TopicSchema:
        """Return how the messages of ``topic`` are encoded, as recorded."""
        conn = next(conn for conn in self._reader.connections if conn.topic == topic)
        if is_service_event(conn.topic, conn.msgtype):
            raise service_event_error(self.path, conn.topic, conn.msgtype)
        if self._cdr is not None:
            with reading_errors(f'{self.path}: cannot convert the definition of '
                                f'{conn.msgtype} for {topic} to ROS 2'):
                text, _ = self._cdr.generate_msgdef(conn.msgtype, ros_version=2)
            return TopicSchema(conn.msgtype, 'ros2msg', text.encode())
        definition = conn.msgdef
        if definition.format == MessageDefinitionFormat.IDL:
            return TopicSchema(conn.msgtype, 'ros2idl', definition.data.encode())
        if definition.format == MessageDefinitionFormat.MSG and definition.data:
            return TopicSchema(conn.msgtype, 'ros2msg', definition.data.encode())
        # Bags from before Iron store no definitions: take the standard one.
        with reading_errors(f'{self.path}: no definition of {conn.msgtype} for {topic}'):
            text, _ = self._reader.typestore.generate_msgdef(conn.msgtype, ros_version=2)
        return TopicSchema(conn.msgtype, 'ros2msg', text.encode())

    def records(self, topics: Sequence[str], start_ns: Optional[int],
                end_ns: Optional[int]) -> Iterator[BagRecord]:
        """Check that the topics can be decoded, then stream them in log-time order."""
        connections = [conn for conn in self._reader.connections if conn.topic in topics]
        known = self._reader.typestore.fielddefs
        for conn in connections:
            if conn.msgtype in known:
                continue
            if is_service_event(conn.topic, conn.msgtype):
                raise service_event_error(self.path, conn.topic, conn.msgtype)
            if self._has_definitions:
                raise BagError(f'{self.path}: topic {conn.topic} has type {conn.msgtype}, '
                               'whose definition the bag does not store (it stores those of '
                               'other types) and which is not a standard ROS 2 Jazzy type, so '
                               'it cannot be decoded')
            raise BagError(f'{self.path}: topic {conn.topic} has type {conn.msgtype}, which '
                           'the bag does not define and is not a standard ROS 2 Jazzy type; '
                           're-record it with a recent rosbag2 (which stores definitions)')
        return self._iterate(connections, start_ns, end_ns)

    def _iterate(self, connections: list, start_ns: Optional[int],
                 end_ns: Optional[int]) -> Iterator[BagRecord]:
        for conn, log_time_ns, data in self._raw(connections, start_ns, end_ns):
            msg = self._decode(conn, log_time_ns, data)
            yield BagRecord(conn.topic, log_time_ns, msg, bytes(data))

    def _raw(self, connections: list, start_ns: Optional[int],
             end_ns: Optional[int]) -> Iterator[Tuple[Any, int, Any]]:
        what = f'{self.path} is corrupted and cannot be read further'
        with reading_errors(what):
            raw = self._reader.messages(connections, start=start_ns, stop=end_ns)
        while True:
            with reading_errors(what):
                item = next(raw, None)
            if item is None:
                return
            if self._cdr is not None:
                conn, log_time_ns, data = item
                with reading_errors(self._mismatch(conn, log_time_ns)):
                    item = conn, log_time_ns, self._cdr.ros1_to_cdr(data, conn.msgtype)
            yield item

    def _mismatch(self, conn: Any, log_time_ns: int) -> str:
        return (f'{self.path}: the message on {conn.topic} at {log_time_ns} ns does not match '
                f'the definition of {conn.msgtype} the bag stores (a wrong definition, or '
                'damaged data)')

    def _decode(self, conn: Any, log_time_ns: int, data: Any) -> Any:
        with reading_errors(self._mismatch(conn, log_time_ns)):
            if self._cdr is not None:
                return self._cdr.deserialize_cdr(data, conn.msgtype)
            return self._reader.deserialize(data, conn.msgtype)

    def raw_streams(self, topics: Sequence[str]) -> Dict[int, RawStream]:
        """Check that the topics can be decoded; return their connections as streams."""
        self.records(topics, None, None)        # the checks, without reading
        if self._mcap_file is not None:
            if self._mcap is None:
                self._mcap = McapSource(self._mcap_file)
            return self._mcap.raw_streams(topics)
        fielddefs = (self._cdr or self._reader.typestore).fielddefs
        return {index: RawStream(conn.topic, conn.msgtype, fielddefs,
                                 functools.partial(self._decode, conn))
                for index, conn in enumerate(self._reader.connections) if conn.topic in topics}

    def raw_blocks(self, streams: Mapping[int, Any], start_ns: Optional[int],
                   end_ns: Optional[int]) -> Iterator[RawBlock]:
        """Yield the serialised messages of ``streams`` in arrival order, by blocks."""
        if self._mcap is not None:
            yield from self._mcap.raw_blocks(streams, start_ns, end_ns)
            return
        connections = {id(conn): index for index, conn in enumerate(self._reader.connections)
                       if index in streams}
        chosen = [conn for conn in self._reader.connections if id(conn) in connections]
        pending: List[Tuple[int, int, bytes]] = []
        try:
            for conn, log_time_ns, data in self._raw(chosen, start_ns, end_ns):
                pending.append((connections[id(conn)], log_time_ns, bytes(data)))
                if len(pending) == _RAW_BLOCK:
                    yield raw_block(pending)
                    pending = []
        except BagError:
            if pending:     # the messages before the damage, as records() yields them
                yield raw_block(pending)
            raise
        if pending:
            yield raw_block(pending)

    def close(self) -> None:
        """Release the files."""
        self._reader.close()
        if self._mcap is not None:
            self._mcap.close()
        self._remove_merged()

    def _remove_merged(self) -> None:
        if self._merged is not None:
            self._merged.cleanup()
            self._merged = None


def _merged_logs(path: Path, warnings: List[str]
                 ) -> Tuple[Path, Optional[tempfile.TemporaryDirectory]]:
    """
    Return what rosbags is to open for ``path``, with the messages of unmerged SQLite logs.

    rosbags opens a ``.db3`` file as immutable, which ignores its write-ahead log: the
    messages a recorder wrote last (``--storage-preset-profile resilient`` keeps the database
    in WAL mode) are left out without a word when it did not close the database (a crash, a
    power cut, a copy taken while it was written). Such a database is copied with its log into
    a temporary directory and the log merged there (beside links to the bag's other files); the
    bag is left as it is, and ``warnings`` says so. Returns ``(path, None)`` when no database
    has a log that holds anything.
    """
    databases = [path] if path.suffix == '.db3' else sorted(path.glob('*.db3')) \
        if path.is_dir() else []
    pending = [database for database in databases if _log_size(database)]
    if not pending:
        return path, None
    temporary = tempfile.TemporaryDirectory(prefix='ctid-bag-')
    root = Path(temporary.name)
    try:
        if path.is_dir():
            for item in path.iterdir():
                if item.is_file() and item not in pending and \
                        not item.name.endswith(_SQLITE_SIDE_FILES):
                    (root / item.name).symlink_to(item.resolve())
        for database in pending:
            copy = root / database.name
            shutil.copyfile(database, copy)
            shutil.copyfile(f'{database}-wal', f'{copy}-wal')
            with contextlib.closing(sqlite3.connect(copy)) as connection:
                connection.execute('PRAGMA wal_checkpoint(TRUNCATE)')
                connection.execute('PRAGMA journal_mode=DELETE')
            warnings.append(f'{database}-wal holds messages not merged into {database.name} '
                            '(the recorder did not close the database: a crash, or a copy '
                            'taken while it was written); they are read from a merged copy, '
                            'the bag is left as it is')
    except (OSError, sqlite3.Error) as error:
        temporary.cleanup()
        warnings.append(f'the write-ahead log of {pending[0]} cannot be merged ({error}): the '
                        'messages it holds are left out')
        return path, None
    return (root if path.is_dir() else root / path.name), temporary


def _log_size(database: Path) -> int:
    try:
        return os.stat(f'{database}-wal').st_size
    except OSError:
        return 0


_Source = Union[_RosbagsSource, McapSource]


def _file_kind(head: bytes) -> str:
    """Say what a file starting with ``head`` is, for a user who gave it as a bag."""
    if not head:
        return 'an empty file'
    for magic, kind in _FILE_KINDS:
        if head.startswith(magic):
            return kind
    try:
        text = head.decode('utf-8')
    except UnicodeDecodeError:
        return 'a binary file of an unknown format'
    if not text.isprintable() and not all(char.isprintable() or char in '\r\n\t'
                                          for char in text):
        return 'a binary file of an unknown format'
    first = text.splitlines()[0] if text.strip() else ''
    quoted = first if len(first) <= 40 else first[:37] + '...'
    if ',' in first:
        return f'a text file, CSV-like ({quoted!r}; ctid fit reads CSV records)'
    return f'a text file ({quoted!r})'


def _open_file(path: Path) -> _Source:
    try:
        with open(path, 'rb') as stream:
            head = stream.read(_HEAD_BYTES)
    except OSError as error:
        raise BagError(f'cannot read {path}: {error.strerror}') from None
    if head.startswith(MCAP_MAGIC) or path.suffix == '.mcap':
        return McapSource(path)
    if head.startswith(_ROS1_MAGIC):
        version = head[len(_ROS1_MAGIC):].split(b'\n', 1)[0].decode('ascii', 'replace')
        if version != '2.0':
            raise BagError(f'{path} is a ROS 1 bag of format version {version}, which rosbags '
                           'cannot read (it reads version 2.0): migrate it with `rosbag fix` '
                           'on ROS 1')
        if path.suffix != '.bag':
            raise BagError(f'{path} is a ROS 1 bag, but rosbags reads ROS 1 bags only under a '
                           f'name ending in .bag: rename it, or link it (ln -s {path.name} '
                           f'{path.stem}.bag)')
        return _RosbagsSource(path)
    if path.suffix == '.db3':
        return _RosbagsSource(path)
    raise BagError(f'{path} is not a bag: it is {_file_kind(head)}; give a rosbag2 directory '
                   '(with metadata.yaml), an .mcap or .db3 file, or a ROS 1 .bag file')


def _open_directory(path: Path) -> _Source:
    storage = sorted(path.glob('*.mcap')) + sorted(path.glob('*.db3'))
    metadata = path / 'metadata.yaml'
    if metadata.exists():
        content = read_limited(metadata, MAX_METADATA_BYTES, 'bag metadata', BagError)
        # rosbags parses it too, but without limits: deep nesting takes it minutes.
        document = parse_yaml(content, f'bag metadata {metadata}', BagError, _METADATA_NODES)
        information = document.get('rosbag2_bagfile_information') \
            if isinstance(document, dict) else None
        information = information if isinstance(information, dict) else {}
        # rosbags decompresses MCAP chunks and whole compressed files without bounds: their
        # sizes are checked first.
        for file in storage:
            if file.suffix == '.mcap':
                check_chunk_sizes(file)
        if information.get('compression_mode') == 'file':
            listed = information.get('relative_file_paths')
            for name in listed if isinstance(listed, list) else []:
                file = path / Path(str(name)).name
                if file.is_file():
                    _check_compressed_file(file)
        try:
            return _RosbagsSource(path)
        except BagError as error:
            if len(storage) != 1 or storage[0].suffix != '.mcap':
                raise
            # A recording cut short leaves an MCAP file without its index, which rosbags
            # rejects; the MCAP reader replays what was written before the cut.
            try:
                source = McapSource(storage[0])
            except BagError:
                raise error from None
            services = sorted(topic for topic, msgtype in source.topics.items()
                              if is_service_event(topic, msgtype))
            reason = (f'its service-event topics ({", ".join(services)}) have definitions '
                      'rosbags cannot parse' if services else _quoted(error))
            source.warnings.insert(0, f'rosbags cannot read {path} ({reason}); reading '
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


def _check_compressed_file(path: Path) -> None:
    """
    Refuse a zstd-compressed storage file that expands beyond the ratio limit.

    rosbag2 compresses a storage file as a stream (``ZSTD_compressStream2`` over pieces of
    128 KiB), so the frame of any file larger than that does not state its decompressed size,
    and a file may hold several frames: the size is measured by decompressing the file once, a
    piece at a time with nothing kept, and the measurement stops at the limit.
    """
    try:
        with open(path, 'rb') as stream:
            head = stream.read(32)
            size = os.fstat(stream.fileno()).st_size
            try:
                zstandard.frame_content_size(head)
            except zstandard.ZstdError:
                raise BagError(f'metadata.yaml says the storage files are zstd-compressed '
                               f'(compression_mode: file) but {path} is not: fix '
                               'compression_mode and compression_format in metadata.yaml'
                               ) from None
            limit = MAX_COMPRESSION_RATIO * max(size, MIB)
            stream.seek(0)
            expanded = _expanded_size(stream, limit, path)
    except OSError as error:
        raise BagError(f'cannot read {path}: {error.strerror or error}') from None
    if expanded > limit:
        raise BagError(f'{path} decompresses to more than {limit // MIB} MiB from '
                       f'{size_text(size)} (the ratio limit is {MAX_COMPRESSION_RATIO}, at least '
                       f'{MAX_COMPRESSION_RATIO} MiB): a decompression bomb, or decompress the '
                       'bag yourself (zstd -d) and fix metadata.yaml')


def _expanded_size(stream: Any, limit: int, path: Path) -> int:
    """Return the bytes the zstd frames of ``stream`` decompress to, or ``limit + 1`` if more."""
    reader = zstandard.ZstdDecompressor().stream_reader(stream, read_across_frames=True,
                                                        closefd=False)
    expanded = 0
    try:
        while expanded <= limit:
            piece = reader.read(_DECOMPRESSION_PIECE)
            if not piece:
                break
            expanded += len(piece)
    except zstandard.ZstdError as error:
        raise BagError(f'{path} is damaged: its zstd data cannot be decompressed ({error}); '
                       'the storage file cannot be read') from None
    return expanded


class BagReader:
    """
    Read recorded messages from a rosbag2 directory, a ``.db3``, ``.mcap`` or ROS 1 ``.bag`` file.

    Use as a context manager (or call :meth:`close`)::

        with BagReader('run1') as bag:
            for topic, log_time_ns, msg in bag.messages(['/plant/u', '/plant/y'], 10, 40):
                ...

    Parameters
    ----------
    path : str or os.PathLike
        A rosbag2 directory (sqlite3 or mcap storage), a directory holding a single ``.mcap`` or
        ``.db3`` file but no metadata.yaml, a single ``.mcap``/``.db3`` file, or a ROS 1 bag
        (format 2.0, named ``*.bag``), whose messages are yielded as their ROS 2 counterparts.

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
        return (self.end_time_ns - self.start_time_ns) / NANOSECONDS

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
        return (None if start is None else origin + round(start * NANOSECONDS),
                None if end is None else origin + round(end * NANOSECONDS))

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
            (arrays may be numpy arrays or lists). :meth:`records` gives the serialised bytes
            too.

        Raises
        ------
        BagError
            Immediately for unknown topics (the message lists the topics of the bag), an invalid
            window, or a topic whose type cannot be decoded; while iterating if the bag turns out
            to be damaged beyond what was found when it was opened.

        """
        records = self.records(topics, start, end, start_ns=start_ns, end_ns=end_ns)
        return (BagMessage(record.topic, record.log_time_ns, record.msg) for record in records)

    def records(self, topics: Union[str, Iterable[str], None] = None,
                start: Optional[float] = None, end: Optional[float] = None, *,
                start_ns: Optional[int] = None,
                end_ns: Optional[int] = None) -> Iterator[BagRecord]:
        """
        Stream messages as :meth:`messages` does, each with its serialised bytes as recorded.

        Returns
        -------
        iterator of BagRecord
            ``(topic, log_time_ns, msg, data)``: ``data`` is the message as stored (CDR), to
            copy it into another bag with its :meth:`topic_schema`.

        """
        selected = self._select(topics)
        return self._source.records(selected, *self._window_ns(start, end, start_ns, end_ns))

    def _window_ns(self, start: Optional[float], end: Optional[float], start_ns: Optional[int],
                   end_ns: Optional[int]) -> Tuple[int, int]:
        """Return the window in nanoseconds, from seconds or nanoseconds but not both."""
        if start is not None and start_ns is not None or end is not None and end_ns is not None:
            raise BagError('give the window either in seconds (start/end) or in nanoseconds '
                           '(start_ns/end_ns), not both')
        lo, hi = self.time_range_ns(start, end)
        return (start_ns if start_ns is not None else lo, end_ns if end_ns is not None else hi)

    def raw_streams(self, topics: Union[str, Iterable[str]]) -> Dict[int, RawStream]:
        """
        Return the streams (channels, connections) of ``topics``, for a columnar reader.

        Raises
        ------
        BagError
            As :meth:`records` does: unknown topics, a type that cannot be decoded.

        """
        return self._source.raw_streams(self._select(topics))

    def raw_blocks(self, streams: Mapping[int, RawStream], start: Optional[float] = None,
                   end: Optional[float] = None, *, start_ns: Optional[int] = None,
                   end_ns: Optional[int] = None) -> Iterator[RawBlock]:
        """
        Yield the serialised messages of ``streams`` (from :meth:`raw_streams`) by blocks.

        The messages and their order are those of :meth:`records` over the same window; each
        :class:`~ctid_ros.files.mcap_source.RawBlock` holds a chunk's worth (MCAP) or a fixed
        number of them, so memory stays bounded on long bags. A bag found damaged while reading
        raises :class:`~ctid_ros.errors.BagError` once the messages before the damage were
        yielded.
        """
        return self._source.raw_blocks(streams, *self._window_ns(start, end, start_ns, end_ns))

    def topic_schema(self, topic: str) -> TopicSchema:
        """
        Return how the messages of ``topic`` are encoded: type, definition and encodings.

        Raises
        ------
        BagError
            If the bag has no such topic (the message lists its topics).

        """
        (topic,) = self._select(topic)
        return self._source.schema(topic)

    def topic_name(self, topic: str) -> Optional[str]:
        """
        Return how the bag spells ``topic``, or None if it has no such topic.

        Bags written by tools that do not resolve names store topics without the leading
        slash (``AAA``); such a topic is found as ``/AAA`` too, and ``/AAA`` as ``AAA``.
        """
        available = self._source.topics
        if topic in available:
            return topic
        alike = [name for name in available if name.lstrip('/') == topic.lstrip('/')]
        return alike[0] if len(alike) == 1 else None

    def _select(self, topics: Union[str, Iterable[str], None]) -> List[str]:
        available = self._source.topics
        if topics is None:
            return list(available)
        requested = [topics] if isinstance(topics, str) else list(topics)
        if not requested:
            raise BagError('no topics selected')
        selected = [self.topic_name(topic) for topic in requested]
        missing = [topic for topic, name in zip(requested, selected) if name is None]
        if missing:
            listing = '; '.join(f'{topic} ({msgtype}, {self._source.counts[topic]} messages)'
                                for topic, msgtype in sorted(available.items())) or 'none'
            if self.truncated:
                readable = (f'its readable part has: {listing}' if available else 'nothing '
                            'is readable before the cut (cut before its first complete chunk)')
                raise BagError(f'topic(s) {", ".join(missing)} not in the readable part of '
                               f'{self.path}: the file is truncated or damaged, and '
                               f'{readable}')
            raise BagError(f'topic(s) {", ".join(missing)} not in {self.path}; it has: '
                           f'{listing}')
        return selected


_Item = TypeVar('_Item')


def readable_part(items: Iterable[_Item], warn: Callable[[str], None]) -> Iterator[_Item]:
    """
    Yield the records (or blocks) of a bag until one cannot be read, then warn and stop.

    A damaged chunk or message ends the readable part of a bag, not its use: the estimate is
    made on the messages before it, as from a truncated file, and ``warn`` gets the error with
    what was done about it.
    """
    iterator = iter(items)
    while True:
        try:
            item = next(iterator)
        except StopIteration:
            return
        except BagError as error:
            warn(f'{error}; estimating from the messages before it')
            return
        yield item


def open_bag(path: PathLike) -> BagReader:
    """Open a bag for reading; see :class:`BagReader`."""
    return BagReader(path)
