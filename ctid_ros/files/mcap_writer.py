"""
Writing new standalone MCAP files without ROS.

:class:`EstimateWriter` holds the topics the live node publishes; :class:`RecordingWriter`
records serialised messages as they come off the wire (what ``ros2 bag record`` does, for
machines without the ros2 CLI). Both files are readable by Foxglove, PlotJuggler, rosbags,
mcap-ros2-support and :class:`~ctid_ros.files.bag_reader.BagReader`. Times are integer
nanoseconds since the epoch.
"""

import os
from pathlib import Path
import re
from typing import Any, Dict, Iterable, Mapping, Optional, Sequence, Tuple, TypeVar

from ctid_ros.errors import BagError, ConfigError, DataError
from ctid_ros.files.mcap_source import PathLike
from ctid_ros.streaming.session import format_diagnostic
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as McapRos2Writer
import numpy as np
from rosbags.typesys import get_typestore, Stores, TypesysError

__all__ = ['EstimateWriter', 'RecordingWriter']

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
