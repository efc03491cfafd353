"""
Writing new standalone MCAP files without ROS.

:class:`RecordingWriter` records serialised messages as they come off the wire (what ``ros2 bag
record`` does, for machines without the ros2 CLI); :class:`EstimateWriter` writes what the live
node publishes (:mod:`ctid_ros.streaming.contract`) and can hold copies of recorded topics
beside it. Messages are CDR with their definitions in the file, in the concatenated form
rosbag2 stores, so Foxglove, PlotJuggler, rosbags, mcap-ros2-support and
:class:`~ctid_ros.files.bag_reader.BagReader` read them without ROS. Times are integer
nanoseconds since the epoch.

A recording keeps what it recorded when the process dies: with ``flush_interval`` the messages
are written as a chunk at least that often, each followed by a provisional end of the file (a
data-end record and a footer without summary, overwritten by the next chunk), so that a file
cut off by SIGKILL or a power cut is a valid MCAP file up to its last flush, which the plain
``mcap`` reader reads too. A failed write (a full disk) raises :class:`~ctid_ros.errors.BagError`
naming the file and the cause, and the file keeps every chunk flushed before.
"""

from contextlib import contextmanager
import os
from pathlib import Path
import stat
import threading
import time
from typing import Any, Dict, Iterable, Iterator, Mapping, Optional, Sequence, TypeVar

from ctid_ros.core.limits import MIB
from ctid_ros.errors import BagError, DataError
from ctid_ros.files.mcap_source import MCAP_MAGIC, PathLike, TopicSchema
from ctid_ros.streaming.contract import (alarm_message, DEFAULT_NODE_NAME,
                                         diagnostics_message, estimate_messages, NodeTopics,
                                         OutputMessage, update_status)
from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import Writer as McapWriter
import numpy as np
from rosbags.typesys import get_typestore, Stores, TypesysError
from rosbags.typesys.base import Nodetype

__all__ = ['EstimateWriter', 'RecordingWriter', 'partial_path', 'special_file']

# numpy types of the primitive ROS types that rosbags wants as arrays inside sequences.
_ARRAY_TYPES = {
    'bool': np.bool_, 'byte': np.uint8, 'char': np.uint8, 'octet': np.uint8,
    'int8': np.int8, 'uint8': np.uint8, 'int16': np.int16, 'uint16': np.uint16,
    'int32': np.int32, 'uint32': np.uint32, 'int64': np.int64, 'uint64': np.uint64,
    'float32': np.float32, 'float64': np.float64,
}


# What a path that is no regular file is, by the file type bits of its mode.
_FILE_TYPES = ((stat.S_ISFIFO, 'a named pipe (FIFO)'), (stat.S_ISCHR, 'a character device'),
               (stat.S_ISBLK, 'a block device'), (stat.S_ISSOCK, 'a socket'))


def special_file(path: Path) -> Optional[str]:
    """
    Say what ``path`` is if it exists and is neither a regular file nor a directory.

    A named pipe would block the writer until someone reads it, a device (``/dev/full``,
    ``/dev/null``) would swallow or refuse the data: none is a file to write results into.
    Symbolic links are followed.
    """
    try:
        mode = path.stat().st_mode
    except OSError:
        return None
    kind = next((name for test, name in _FILE_TYPES if test(mode)), None)
    if kind is None:
        return None
    target = path.resolve()
    return kind + (f' ({target})' if target != path.absolute() else '')


def _check_output(path: Path, inputs: Iterable[PathLike], overwrite: bool) -> None:
    if path.suffix != '.mcap':
        raise BagError(f'cannot write {path}: the name must end in .mcap (an MCAP file is '
                       'written)')
    kind = special_file(path)
    if kind is not None:
        raise BagError(f'cannot write {path}: it is {kind}, not a regular file; give a file '
                       'path')
    target = path.resolve()
    for source in inputs:
        source = Path(source).resolve()
        if target == source or source in target.parents or (
                target.exists() and source.exists() and os.path.samefile(target, source)):
            raise BagError(f'refusing to write {path}: it is (inside) the input bag {source}; '
                           'choose another output file')
    if not target.parent.is_dir():
        raise BagError(f'cannot write {path}: directory {target.parent} does not exist')
    if target.is_dir():
        raise BagError(f'cannot write {path}: it is a directory')
    if target.exists() and not overwrite:
        raise BagError(f'{path} already exists; choose another output file or allow '
                       'overwriting it')


class _Output:
    """
    A writer's file: whole records held in memory until :meth:`commit` writes them.

    Every commit leaves the file a valid MCAP file, whatever moment the process dies at: the
    records and a new provisional end (:func:`_provisional_end`) are first written past the
    old provisional end's first bytes, which keep the file ending there (a reader stops at
    that footer); then those few bytes are overwritten with the records' first ones, one
    small write. After a failed write (a full disk) the file is cut back to its last end.
    """

    def __init__(self, path: Path, overwrite: bool) -> None:
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        self._fd = os.open(path, flags | getattr(os, 'O_CLOEXEC', 0), 0o666)
        self._pending = bytearray()
        self._committed = 0        # bytes of whole records on disk
        self._end = 0              # bytes of the provisional end after them

    def write(self, data: Any) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        return self._committed + len(self._pending)

    def flush(self) -> None:
        """Do nothing: :meth:`commit` writes (mcap's Writer.flush calls this)."""

    @property
    def pending(self) -> int:
        """Return the bytes held in memory."""
        return len(self._pending)

    def commit(self, end: bytes) -> None:
        """Write the records held and ``end`` after them (see the class)."""
        data = bytes(self._pending) + end
        keep = min(self._end, len(data))
        self._write_at(data[keep:], self._committed + keep)
        self._write_at(data[:keep], self._committed)
        self._committed += len(self._pending)
        self._end = len(end)
        self._pending.clear()

    def _write_at(self, data: bytes, offset: int) -> None:
        view = memoryview(data)
        while view:
            written = os.pwrite(self._fd, view, offset)
            view, offset = view[written:], offset + written

    def restore(self) -> None:
        """After a failed commit, cut the file back to its last valid end (frees space)."""
        self._pending.clear()
        os.ftruncate(self._fd, self._committed + self._end)

    def finish(self) -> None:
        """Write the records held (the file's real end) and nothing after them."""
        self.commit(b'')
        os.ftruncate(self._fd, self._committed)

    def close(self) -> None:
        os.close(self._fd)


def partial_path(path: Path) -> Path:
    """Return where an atomic writer writes ``path`` until it is complete."""
    return path.with_name(f'{path.stem}.partial{path.suffix}')


def _provisional_end() -> bytes:
    """Return a data-end record, a footer without summary and the magic: a file's valid end."""
    builder = RecordBuilder()
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return bytes(builder.end()) + MCAP_MAGIC


_PROVISIONAL_END = _provisional_end()
# Bytes of whole records held in memory before they are written whatever the flush interval
# (mcap writes a chunk of 1 MiB at a time).
_COMMIT_BYTES = 4 * MIB


def _time_ns(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise DataError(f'times must be non-negative integer nanoseconds, got {value!r}')
    return int(value)


_Writer = TypeVar('_Writer', bound='RecordingWriter')


class RecordingWriter:
    """
    Record serialised ROS 2 messages into a new standalone MCAP file, as ``ros2 bag record``.

    The messages are written as received, in CDR (e.g. from an rclpy subscription created with
    ``raw=True``, or copied from another bag), with the definition of their type: from rosbags'
    ROS 2 Jazzy type store, or as recorded for a copied topic.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file to create.
    inputs : iterable of str or os.PathLike, optional
        Bags the data come from: writing to (or into) any of them is refused, even with
        ``overwrite``.
    overwrite : bool, optional
        Replace an existing file at ``path`` instead of refusing.
    flush_interval : float, optional
        Seconds: write the messages received so far as a chunk, followed by a provisional
        end of the file, when this long has passed since the last such flush (checked at every
        message and by :meth:`flush`); a killed process then loses at most about that long.
        None (the default) writes chunks by size only, and the file is valid only once closed.
    atomic : bool, optional
        Write into ``<stem>.partial.mcap`` beside ``path`` and rename it to ``path`` when
        :meth:`close` completes it, so that ``path`` is complete or absent (an existing one
        untouched) whatever happens; :meth:`discard` removes the partial file. A process
        killed meanwhile leaves only the ``.partial.mcap`` file, which the next one replaces.

    Attributes
    ----------
    message_count : int
        Messages written so far.

    Raises
    ------
    BagError
        If ``path`` is not a new ``.mcap`` file outside the inputs, or cannot be created.

    Notes
    -----
    The methods may be called from several threads (a recorder's executor writes, the main
    thread flushes and closes).

    """

    def __init__(self, path: PathLike, *, inputs: Iterable[PathLike] = (),
                 overwrite: bool = False, flush_interval: Optional[float] = None,
                 atomic: bool = False) -> None:
        self.path = Path(path)
        _check_output(self.path, inputs, overwrite)
        self._file = partial_path(self.path) if atomic else self.path
        if atomic:
            _check_output(self._file, inputs, True)
        try:
            self._stream = _Output(self._file, overwrite or atomic)
        except OSError as error:
            raise BagError(f'cannot create {self._file}: {error.strerror or error}') from None
        self._closed = False
        self._failure: Optional[BagError] = None
        self._lock = threading.RLock()
        self._flush_interval = flush_interval
        self._flushed_at = time.monotonic()
        self._pending = False
        self.message_count = 0
        self._writer = McapWriter(self._stream)
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._schemas: Dict[TopicSchema, int] = {}
        self._channels: Dict[str, int] = {}
        self._types: Dict[str, str] = {}
        with self._lock, self._writing():
            self._writer.start(profile='ros2', library='ctid_ros')
            self._stream.commit(_PROVISIONAL_END)

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """Turn a failed write into a BagError that every later write raises too."""
        if self._failure is not None:
            raise self._failure
        try:
            yield
        except BagError:
            raise
        except OSError as error:
            self._failure = BagError(f'cannot write {self.path}: {error.strerror or error}')
            try:
                self._stream.restore()
            except OSError:     # the file keeps its cut: BagReader reads up to it
                pass
            raise self._failure from None

    def __enter__(self: _Writer) -> _Writer:
        """Return the writer; :meth:`close` it on leaving."""
        return self

    def __exit__(self, *exc_info: object) -> None:
        """Close the file, also after an error: the messages so far stay readable."""
        self.close()

    def close(self) -> None:
        """
        Write the MCAP index and close the file (also after an error: messages so far stay).

        Raises
        ------
        BagError
            If the index cannot be written (a full disk): the file is closed, and holds every
            message flushed before.

        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                if self._failure is None:
                    with self._writing():
                        self._writer.finish()
                        self._stream.finish()
            finally:
                self._stream.close()
                if self._file != self.path and self._failure is not None:
                    self._file.unlink(missing_ok=True)
            if self._file != self.path and self._failure is None:
                try:
                    os.replace(self._file, self.path)
                except OSError as error:
                    raise BagError(f'cannot replace {self.path} with the finished '
                                   f'{self._file.name}: {error.strerror or error}') from None

    def discard(self) -> None:
        """
        Close the file without finishing it, after a failure.

        An ``atomic`` writer removes its partial file (``path`` is left as it was); any other
        keeps the file, readable up to its last flush.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stream.close()
            if self._file != self.path:
                self._file.unlink(missing_ok=True)

    def flush(self, force: bool = False) -> None:
        """
        Write the messages received so far as a chunk if ``flush_interval`` has passed.

        With ``force``, whatever the interval. The chunk is followed by a provisional end of
        the file, so that the file as it is on disk is a valid MCAP file.

        Raises
        ------
        BagError
            If the writing fails (a full disk).

        """
        with self._lock:
            if self._closed or not self._pending:
                return
            if not force and (self._flush_interval is None or time.monotonic() <
                              self._flushed_at + self._flush_interval):
                return
            with self._writing():
                self._writer.flush()
                self._stream.commit(_PROVISIONAL_END)
            self._flushed_at = time.monotonic()
            self._pending = False

    def _check_open(self) -> None:
        if self._closed:
            raise BagError(f'{self.path} is already closed')

    def topics(self) -> Dict[str, str]:
        """Return the message type of each declared topic."""
        return dict(self._types)

    def add_topic(self, topic: str, msgtype: str, schema: Optional[TopicSchema] = None) -> None:
        """
        Declare a topic and its message type, e.g. ``'geometry_msgs/msg/PointStamped'``.

        Parameters
        ----------
        topic : str
            Absolute topic name.
        msgtype : str
            Message type.
        schema : TopicSchema, optional
            The definition the messages were recorded with (a copied topic, possibly of a
            custom type); default the standard ROS 2 Jazzy definition of ``msgtype``.

        Raises
        ------
        BagError
            If the topic was declared already, or it has no ``schema`` and its type is not a
            standard ROS 2 Jazzy type.

        """
        with self._lock:
            self._check_open()
            with self._writing():
                self._declare(topic, msgtype, schema)

    def _declare(self, topic: str, msgtype: str, schema: Optional[TopicSchema]) -> None:
        if topic in self._channels:
            raise BagError(f'topic {topic} is already recorded in {self.path}')
        if schema is None:
            try:
                text, _ = self._typestore.generate_msgdef(msgtype, ros_version=2)
            except TypesysError:
                raise BagError(f'cannot record {topic}: {msgtype} is not a standard ROS 2 '
                               'Jazzy message type') from None
            schema = TopicSchema(msgtype, 'ros2msg', text.encode())
        if schema not in self._schemas:
            self._schemas[schema] = self._writer.register_schema(schema.msgtype, schema.encoding,
                                                                 schema.definition)
        self._channels[topic] = self._writer.register_channel(topic, schema.message_encoding,
                                                              self._schemas[schema])
        self._types[topic] = msgtype

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Write one serialised message of a declared topic at its log (reception) time."""
        time_ns = _time_ns(log_time_ns)
        with self._lock:
            self._check_open()
            if topic not in self._channels:
                raise BagError(f'topic {topic} was not declared with add_topic')
            with self._writing():
                self._writer.add_message(self._channels[topic], time_ns, bytes(data), time_ns)
                if self._stream.pending > _COMMIT_BYTES:
                    self._stream.commit(_PROVISIONAL_END)
            self.message_count += 1
            self._pending = True
        if self._flush_interval is not None:
            self.flush()

    def write_message(self, message: OutputMessage, log_time_ns: int) -> None:
        """
        Serialise and write a message given as plain data, declaring its topic on first use.

        Raises
        ------
        BagError
            If the topic was declared with another type.
        DataError
            If a field is missing or has a value its type cannot take.

        """
        time_ns = _time_ns(log_time_ns)
        if message.topic not in self._channels:
            self.add_topic(message.topic, message.msgtype)
        elif self._types[message.topic] != message.msgtype:
            raise BagError(f'topic {message.topic} holds {self._types[message.topic]} in '
                           f'{self.path}, not {message.msgtype}')
        msg = self._build(message.msgtype, message.fields)
        self.write(message.topic, time_ns, self._typestore.serialize_cdr(msg, message.msgtype))

    def _build(self, msgtype: str, fields: Mapping[str, Any]) -> Any:
        """Return the rosbags message of ``msgtype`` holding ``fields`` (nested plain data)."""
        _, definitions = self._typestore.fielddefs[msgtype]
        missing = [name for name, _ in definitions if name not in fields]
        if missing:
            raise DataError(f'{msgtype} needs the field(s) {", ".join(missing)}')
        return self._typestore.types[msgtype](**{
            name: self._field(kind, fields[name]) for name, kind in definitions})

    def _field(self, kind: Any, value: Any) -> Any:
        nodetype, details = kind
        if nodetype == Nodetype.NAME:
            return self._build(details, value)
        if nodetype in (Nodetype.SEQUENCE, Nodetype.ARRAY):
            element = details[0]
            if element[0] == Nodetype.BASE and element[1][0] in _ARRAY_TYPES:
                return np.asarray(value, dtype=_ARRAY_TYPES[element[1][0]])
            return [self._field(element, item) for item in value]
        return value


class EstimateWriter(RecordingWriter):
    """
    Write what the live node publishes into a new standalone MCAP file.

    Topics, types and layouts are those of :mod:`ctid_ros.streaming.contract`: with the default
    node name and no namespace ``/ctid_node/estimate``, ``/ctid_node/estimate_std``,
    ``/ctid_node/params/<name>``, ``/ctid_node/prediction`` and ``/diagnostics``. Recorded
    topics can be copied beside them with :meth:`add_topic` and :meth:`write`.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file to create.
    inputs : iterable of str or os.PathLike, optional
        The bag(s) being replayed: writing to (or into) any of them is refused, even with
        ``overwrite``.
    node_name : str, optional
        Name of the node whose topics are written, optionally with its namespace
        (``'/plant1/ctid_node'``).
    namespace : str, optional
        ROS namespace of the node, e.g. ``'/plant1'``.
    overwrite : bool, optional
        Replace an existing file at ``path`` instead of refusing.
    atomic : bool, optional
        Write into a ``.partial.mcap`` file renamed to ``path`` when complete (see
        :class:`RecordingWriter`).

    Attributes
    ----------
    node : NodeTopics
        The node whose topics are written.

    Raises
    ------
    BagError
        If ``path`` is not a new ``.mcap`` file outside the inputs, or cannot be created.
    ConfigError
        If the namespace or node name is not a valid ROS name.

    """

    def __init__(self, path: PathLike, *, inputs: Iterable[PathLike] = (),
                 node_name: str = DEFAULT_NODE_NAME, namespace: str = '',
                 overwrite: bool = False, atomic: bool = False) -> None:
        self.node = NodeTopics.of(node_name, namespace)
        super().__init__(path, inputs=inputs, overwrite=overwrite, atomic=atomic)

    def write_estimate(self, time_ns: int, names: Sequence[str], values: Sequence[float],
                       stds: Optional[Sequence[float]] = None,
                       diagnostics: Optional[Mapping[str, Any]] = None,
                       prediction: Optional[Sequence[float]] = None,
                       covariance: Optional[Any] = None) -> None:
        """
        Write one update, as the live node publishes it after a window is identified.

        Parameters
        ----------
        time_ns : int
            Log time and header stamp (ns since the epoch), e.g. the window's last sample.
        names : sequence of str
            Parameter names in publishing order.
        values, stds : sequence of float
            Estimates and their standard deviations (NaN where unknown), in ``names`` order;
            without ``stds`` nothing is written on the ``estimate_std`` topic.
        diagnostics : mapping, optional
            Key/value pairs for ``/diagnostics`` (e.g. ``fit_percent``, ``iterations``,
            ``converged``, ``warnings``), written in the given order with the status of
            :func:`~ctid_ros.streaming.contract.update_status`.
        prediction : sequence of float, optional
            The model output over the window, one value per grid instant.
        covariance : array_like, optional
            Parameter covariance in ``names`` order (n x n), for ``estimate_covariance``.

        Raises
        ------
        DataError
            If names are not valid, unique ROS name tokens, lengths differ, or the time is not
            a non-negative integer.

        """
        time_ns = _time_ns(time_ns)
        for message in estimate_messages(self.node, names, values, stds, prediction,
                                         covariance=covariance):
            self.write_message(message, time_ns)
        if diagnostics is not None:
            level, text = update_status(names, values, stds, diagnostics)
            self.write_status(time_ns, level, text, diagnostics)

    def write_status(self, time_ns: int, level: int, message: str,
                     values: Optional[Mapping[str, Any]] = None) -> None:
        """
        Write the node's status on ``/diagnostics``, e.g. for an update that gave no estimate.

        Parameters
        ----------
        time_ns : int
            Log time and header stamp.
        level : int
            ``contract.OK``, ``WARN`` or ``ERROR``.
        message : str
            Status message.
        values : mapping, optional
            Key/value pairs of the status.

        """
        time_ns = _time_ns(time_ns)
        self.write_message(diagnostics_message(self.node, time_ns, level, message,
                                               values or {}), time_ns)

    def write_alarm(self, time_ns: int, level: int, message: str,
                    values: Optional[Mapping[str, Any]] = None) -> None:
        """
        Write the change alarm on ``~/alarm`` (a ``DiagnosticStatus``), as the node does.

        Parameters are those of :meth:`write_status`; ``values`` those of
        :meth:`ctid_ros.streaming.alarm.AlarmStatus.values`.
        """
        self.write_message(alarm_message(self.node, level, message, values or {}),
                           _time_ns(time_ns))
