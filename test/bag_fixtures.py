"""
Bags written by independent writers (rosbags, mcap_ros2) for the bag I/O tests.

Every bag holds the same deterministic recording: ``std_msgs/msg/Float64`` on ``/plant/u`` and
``/plant/y``, ``sensor_msgs/msg/JointState`` on ``/joint_states`` and a custom type
``my_pkg/msg/Sample`` (not installed anywhere, known only from its .msg text) on
``/plant/sample``.
"""

from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from mcap.exceptions import McapError
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as McapRos2Writer
import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

T0_NS = 1_700_000_000_000_000_000
DURATION_S = 2.0
SAMPLE_TYPE = 'my_pkg/msg/Sample'
SAMPLE_MSG = 'std_msgs/Header header\nfloat64 u\nfloat64 y\n'
JOINT_NAMES = ['shoulder', 'elbow']

_SEP = '=' * 80 + '\n'
_HEADER_DEPS = (f'{_SEP}MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n'
                f'{_SEP}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n')
MSGDEFS = {
    'std_msgs/msg/Float64': 'float64 data\n',
    'sensor_msgs/msg/JointState': ('std_msgs/Header header\nstring[] name\nfloat64[] position\n'
                                   'float64[] velocity\nfloat64[] effort\n' + _HEADER_DEPS),
    SAMPLE_TYPE: SAMPLE_MSG + _HEADER_DEPS,
}
TOPICS = {
    '/plant/u': 'std_msgs/msg/Float64',
    '/plant/y': 'std_msgs/msg/Float64',
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/plant/sample': SAMPLE_TYPE,
}


@dataclass(frozen=True)
class Record:
    """One written message: its topic, log time and the field values it carries."""

    topic: str
    time_ns: int
    fields: Dict[str, object]


def make_records(seed: int = 0) -> List[Record]:
    """Return the recording in log-time order (ties cannot occur: every rate has its offset)."""
    rng = np.random.default_rng(seed)
    records = []
    for topic, rate_hz, offset_ns in (('/plant/u', 100, 0), ('/plant/y', 100, 2_000_000),
                                      ('/joint_states', 50, 5_000_000),
                                      ('/plant/sample', 10, 7_000_000)):
        for k in range(int(DURATION_S * rate_hz)):
            time_ns = T0_NS + offset_ns + k * 1_000_000_000 // rate_hz
            records.append(Record(topic, time_ns, _fields(topic, time_ns, rng)))
    return sorted(records, key=lambda record: record.time_ns)


def _fields(topic: str, time_ns: int, rng: np.random.Generator) -> Dict[str, object]:
    stamp = {'sec': time_ns // 1_000_000_000, 'nanosec': time_ns % 1_000_000_000}
    if topic == '/joint_states':
        return {'header': {'stamp': stamp, 'frame_id': 'base'}, 'name': JOINT_NAMES,
                'position': rng.normal(size=2).tolist(), 'velocity': rng.normal(size=2).tolist(),
                'effort': []}
    if topic == '/plant/sample':
        return {'header': {'stamp': stamp, 'frame_id': ''}, 'u': float(rng.normal()),
                'y': float(rng.normal())}
    return {'data': float(rng.normal())}


def assert_fields(msg: object, expected: Dict[str, object]) -> None:
    """Assert that a decoded message (any reader) carries the expected field values."""
    for name, value in expected.items():
        actual = getattr(msg, name)
        if isinstance(value, dict):
            assert_fields(actual, value)
        elif isinstance(value, list):
            assert list(actual) == value, name
        else:
            assert actual == value, name


def _typestore():
    typestore = get_typestore(Stores.ROS2_JAZZY)
    typestore.register(get_types_from_msg(SAMPLE_MSG, SAMPLE_TYPE))
    return typestore


def write_rosbag2(path: Path, records: Sequence[Record], storage: str,
                  compression: Optional[str] = None) -> None:
    """
    Write a rosbag2 directory with rosbags in ``sqlite3`` or ``mcap`` storage.

    ``compression`` ``'file'`` or ``'message'`` compresses with zstd as ``ros2 bag record
    --compression-mode`` does.
    """
    typestore = _typestore()
    plugin = StoragePlugin.SQLITE3 if storage == 'sqlite3' else StoragePlugin.MCAP
    writer = Writer(path, version=9, storage_plugin=plugin)
    if compression is not None:
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with writer:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=typestore)
                       for topic, msgtype in TOPICS.items()}
        for record in records:
            msg = build_message(typestore, TOPICS[record.topic], record.fields)
            writer.write(connections[record.topic], record.time_ns,
                         typestore.serialize_cdr(msg, TOPICS[record.topic]))


def build_message(typestore, msgtype: str, fields: Dict[str, object]):
    """Build a rosbags message object (nested dicts become nested messages)."""
    fielddefs = dict(typestore.fielddefs[msgtype][1])
    values = {}
    for name, value in fields.items():
        if isinstance(value, dict):
            values[name] = build_message(typestore, fielddefs[name][1], value)
        elif isinstance(value, list) and name != 'name':
            values[name] = np.asarray(value, dtype=np.float64)
        else:
            values[name] = value
    return typestore.types[msgtype](**values)


def write_mcap(path: Path, records: Sequence[Record], chunk_size: int = 4096) -> None:
    """
    Write a standalone MCAP file with mcap_ros2 in small chunks.

    Neighbouring messages are swapped every few records, as a recorder with several
    subscriptions does, so a reader must sort by log time across chunk boundaries.

    """
    order = list(range(len(records)))
    for i in range(0, len(order) - 1, 7):
        order[i], order[i + 1] = order[i + 1], order[i]
    with open(path, 'wb') as stream, McapRos2Writer(stream, chunk_size=chunk_size) as writer:
        schemas = {msgtype: writer.register_msgdef(msgtype, text)
                   for msgtype, text in MSGDEFS.items()}
        for i in order:
            record = records[i]
            writer.write_message(record.topic, schemas[TOPICS[record.topic]], record.fields,
                                 log_time=record.time_ns, publish_time=record.time_ns)


def write_unchunked_mcap(path: Path, records: Sequence[Record]) -> None:
    """
    Write an MCAP file without chunks, in reverse log-time order, with the plain mcap writer.

    Messages are CDR-encoded by rosbags; the file has a summary but no chunk index.

    """
    typestore = _typestore()
    with open(path, 'wb') as stream:
        writer = McapWriter(stream, use_chunking=False)
        writer.start(profile='ros2', library='test')
        schemas = {msgtype: writer.register_schema(msgtype, 'ros2msg', text.encode())
                   for msgtype, text in MSGDEFS.items()}
        channels = {topic: writer.register_channel(topic, 'cdr', schemas[msgtype])
                    for topic, msgtype in TOPICS.items()}
        for record in reversed(records):
            msgtype = TOPICS[record.topic]
            msg = build_message(typestore, msgtype, record.fields)
            data = typestore.serialize_cdr(msg, msgtype)
            writer.add_message(channels[record.topic], record.time_ns, bytes(data),
                               record.time_ns)
        writer.finish()


def readable_prefix(path: Path, records: Sequence[Record]) -> List[Record]:
    """Return the records of the messages mcap's own streaming reader recovers from a file."""
    by_time = {r.time_ns: r for r in records}
    recovered = []
    try:
        for record in StreamReader(BytesIO(path.read_bytes())).records:
            if isinstance(record, Message):
                recovered.append(by_time[record.log_time])
    except McapError:
        pass
    return sorted(recovered, key=lambda r: r.time_ns)


def truncate(path: Path, fraction: float) -> None:
    """Cut a file to a fraction of its bytes, as a crash during recording does."""
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * fraction)])
