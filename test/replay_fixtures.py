"""
Recordings of simulated plants with known parameters for the replay tests.

Written with independent writers: rosbags (rosbag2 directories, sqlite3 and mcap storage) and
mcap_ros2 (standalone .mcap), sampled at 100 Hz. The output noise is 1 % of the output's
standard deviation (40 dB SNR, seeded).
"""

from bag_fixtures import build_message, MSGDEFS, Record
from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as McapRos2Writer
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import yaml

T0_NS = 1_700_000_000_000_000_000
TS = 0.01
STEP_NS = 10_000_000
# The measurement is logged 1 ms after the command of the same instant, as a recorder sees it.
Y_LAG_NS = 1_000_000
FLOAT64 = 'std_msgs/msg/Float64'
JOINT_STATE = 'sensor_msgs/msg/JointState'

DELAY = {'model': 'K*exp(-tau*s)/(T*s + 1)', 'truth': {'K': 2.0, 'T': 1.5, 'tau': 0.237},
         'params': {'parameter_names': ['K', 'T', 'tau'], 'lower': [0.01, 0.01, 0.0],
                    'upper': [100.0, 100.0, 2.0], 'delay_min': 0.0, 'delay_max': 1.0}}
OPEN_LOOP = {'model': '1/(m*s**2 + d*s + k)', 'truth': {'m': 0.5, 'd': 1.0, 'k': 50.0},
             'params': {'parameter_names': ['m', 'd', 'k'], 'lower': [0.001, 0.0, 0.0],
                        'upper': [100.0, 100.0, 1000.0]}}
CLOSED_LOOP = {'model': '1/(m*s**2 + d*s + k)', 'controller': '20 + 10/s',
               'truth': {'m': 1.0, 'd': 2.0, 'k': 10.0},
               'params': {'parameter_names': ['m', 'd', 'k'], 'initial': [0.5, 1.0, 5.0],
                          'lower': [0.001, 0.0, 0.0], 'upper': [100.0, 100.0, 1000.0]}}


def simulate(case, seconds, seed=0):
    """Return the input (PRBS, bits of 0.2 s) and the noisy output (40 dB SNR) of a case."""
    u = prbs(10, 20)[:round(seconds / TS)]
    y = Model(case['model'], case.get('controller')).simulate(case['truth'], u, TS)
    noise = np.random.default_rng(seed).standard_normal(y.size)
    return u, y + 0.01 * np.std(y) * noise


def float_records(u, y, input_topic='/plant/u', output_topic='/plant/y'):
    """Return Float64 records in log-time order: input at t_k, output 1 ms later."""
    records = []
    for k, (u_k, y_k) in enumerate(zip(u, y)):
        records.append(Record(input_topic, T0_NS + k * STEP_NS, {'data': float(u_k)}))
        records.append(Record(output_topic, T0_NS + k * STEP_NS + Y_LAG_NS, {'data': float(y_k)}))
    return records


def joint_state_records(u, y, latency_ns):
    """Return JointStates stamped at t_k but logged ``latency_ns`` (plus jitter) later."""
    jitter = np.random.default_rng(1).integers(0, 3_000_000, size=len(u))
    records = []
    for k, (u_k, y_k) in enumerate(zip(u, y)):
        stamp_ns = T0_NS + k * STEP_NS
        records.append(Record('/joint_states', stamp_ns + latency_ns + int(jitter[k]), {
            'header': {'stamp': {'sec': stamp_ns // 10 ** 9, 'nanosec': stamp_ns % 10 ** 9},
                       'frame_id': 'base'},
            'name': ['joint'], 'position': [float(y_k)], 'velocity': [0.0],
            'effort': [float(u_k)]}))
    return sorted(records, key=lambda record: record.time_ns)


# Orders in which named JointStates list their joints, message after message.
JOINT_ORDERS = (['wheel_right', 'joint', 'arm'], ['joint', 'arm', 'wheel_right'],
                ['arm', 'wheel_right', 'joint'])
# Position, velocity and effort of the joints next to 'joint', which carries the recording.
_DECOYS = {'wheel_right': (5.0, 7.0, -5.0), 'arm': (-3.0, 2.0, 3.0)}


def name_joints(records, orders=JOINT_ORDERS):
    """
    Turn single-joint JointState records into three named joints, listed in changing orders.

    ``joint`` carries the record's position, velocity and effort; record ``k`` lists the joints
    as ``orders[k % len(orders)]``, which may leave ``joint`` out.
    """
    for k, record in enumerate(records):
        names = orders[k % len(orders)]
        values = {'joint': tuple(record.fields[field][0]
                                 for field in ('position', 'velocity', 'effort')), **_DECOYS}
        record.fields.update({'name': list(names), **{
            field: [values[name][column] for name in names]
            for column, field in enumerate(('position', 'velocity', 'effort'))}})
    return records


def types_of(records):
    return {record.topic: JOINT_STATE if 'header' in record.fields else FLOAT64
            for record in records}


def write_rosbag2(path, records, storage):
    """Write a rosbag2 directory with rosbags (sqlite3 or mcap storage)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.SQLITE3 if storage == 'sqlite3' else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        connections = {topic: (writer.add_connection(topic, msgtype, typestore=typestore),
                               msgtype) for topic, msgtype in types_of(records).items()}
        for record in records:
            connection, msgtype = connections[record.topic]
            msg = build_message(typestore, msgtype, record.fields)
            writer.write(connection, record.time_ns, typestore.serialize_cdr(msg, msgtype))
    return path


def write_mcap(path, records, chunk_size=16384, compression=CompressionType.ZSTD):
    """Write a standalone .mcap with mcap_ros2 (chunks compressed with ``compression``)."""
    with open(path, 'wb') as stream, McapRos2Writer(stream, chunk_size=chunk_size,
                                                    compression=compression) as writer:
        schemas = {msgtype: writer.register_msgdef(msgtype, MSGDEFS[msgtype])
                   for msgtype in set(types_of(records).values())}
        types = types_of(records)
        for record in records:
            writer.write_message(record.topic, schemas[types[record.topic]], record.fields,
                                 log_time=record.time_ns, publish_time=record.time_ns)
    return path


def damage_chunk(path, fraction):
    """Overwrite 64 bytes in the middle of the chunk at ``fraction`` of the file's chunks."""
    with open(path, 'rb') as stream:
        indexes = make_reader(stream).get_summary().chunk_indexes
    index = indexes[int(fraction * len(indexes))]
    data = bytearray(path.read_bytes())
    middle = index.chunk_start_offset + index.chunk_length // 2
    data[middle:middle + 64] = bytes(range(64))
    path.write_bytes(bytes(data))
    return index


def write_bag(tmp_path, records, kind):
    if kind == 'mcap-file':
        return write_mcap(tmp_path / 'run.mcap', records)
    return write_rosbag2(tmp_path / 'run', records, kind)


def params_file(tmp_path, case, node='ctid_node', **overrides):
    """Write a params YAML in the format of config/*.yaml and return its path."""
    values = {'input_topic': '/plant/u', 'input_field': 'data', 'output_topic': '/plant/y',
              'output_field': 'data', 'model': case['model'],
              'controller': case.get('controller', ''), 'sample_time': TS, 'window': 10.0,
              'update_period': 5.0, 'max_gap': 0.5, 'reorder_horizon': 0.05,
              **case['params'], **overrides}
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump({node: {'ros__parameters': values}}))
    return path


def two_driver_joint_states(tmp_path):
    """
    Write a JointState MCAP of OPEN_LOOP whose every third message lacks ``joint``.

    As ``/joint_states`` fed by two drivers (an arm's and a wheel's). Returns the bag, its
    params file (``effort[joint]`` to ``position[joint]``) and the records.
    """
    u, y = simulate(OPEN_LOOP, 10.0)
    records = name_joints(joint_state_records(u, y, latency_ns=1_000_000),
                          [['joint', 'arm'], ['arm', 'joint'], ['wheel_right']])
    bag = write_bag(tmp_path, records, 'mcap-file')
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[joint]',
                         output_field='position[joint]')
    return bag, params, records


# A ROS 1 command type of a package installed nowhere: known only from the bag's definitions.
COMMAND_TYPE = 'plant_msgs/msg/Command'
COMMAND_MSG = 'Header header\nfloat64 effort\nstring source\n'


def write_rosbag1(path, u, y, latency_ns=3_000_000):
    """
    Write a ROS 1 bag (rosbags' rosbag1 writer): ``/plant/cmd`` and ``/plant/y``.

    ``/plant/cmd`` carries the input in ``effort`` of the custom ``plant_msgs/Command``,
    stamped at t_k in its header and logged ``latency_ns`` later; ``/plant/y`` the output as a
    ``std_msgs/Float64`` logged 1 ms after t_k. Returns the path.
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.typesys import get_types_from_msg

    typestore = get_typestore(Stores.ROS1_NOETIC)
    typestore.register(get_types_from_msg(COMMAND_MSG, COMMAND_TYPE))
    command = typestore.types[COMMAND_TYPE]
    header = typestore.types['std_msgs/msg/Header']
    stamp = typestore.types['builtin_interfaces/msg/Time']
    value = typestore.types[FLOAT64]
    messages = []
    for k, (u_k, y_k) in enumerate(zip(u, y)):
        time_ns = T0_NS + k * STEP_NS
        msg = command(header=header(seq=k, stamp=stamp(sec=time_ns // 10 ** 9,
                                                       nanosec=time_ns % 10 ** 9),
                                    frame_id='base'), effort=float(u_k), source='prbs')
        messages.append(('/plant/cmd', time_ns + latency_ns,
                         typestore.serialize_ros1(msg, COMMAND_TYPE)))
        messages.append(('/plant/y', time_ns + Y_LAG_NS,
                         typestore.serialize_ros1(value(data=float(y_k)), FLOAT64)))
    with Writer1(path) as writer:
        connections = {'/plant/cmd': writer.add_connection('/plant/cmd', COMMAND_TYPE,
                                                           typestore=typestore),
                       '/plant/y': writer.add_connection('/plant/y', FLOAT64,
                                                         typestore=typestore)}
        for topic, time_ns, data in sorted(messages, key=lambda item: item[1]):
            writer.write(connections[topic], time_ns, data)
    return path


def convert_to_rosbag2(source, destination):
    """Convert a ROS 1 bag to a rosbag2 directory (mcap storage) with rosbags' converter."""
    from rosbags.convert import convert

    convert([source], destination, 'mcap', 9, None, 'none', None, None, [], [], [], [])
    return destination
