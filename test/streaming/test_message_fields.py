"""Field paths read the same numbers from rclpy, rosbags-style and mcap_ros2 messages."""

from dataclasses import dataclass, field
import math
import tracemalloc
from typing import ClassVar, List

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.message_fields import (extract, extract_values, has_header_stamp, Key,
                                               message_fields, message_stamp, parse_field_path)
from geometry_msgs.msg import TwistStamped
import numpy as np
import pytest
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64, Float64MultiArray


@dataclass
class Time:
    sec: int = 0
    nanosec: int = 0
    __msgtype__: ClassVar[str] = 'builtin_interfaces/msg/Time'


@dataclass
class Header:
    stamp: Time = field(default_factory=Time)
    frame_id: str = ''
    __msgtype__: ClassVar[str] = 'std_msgs/msg/Header'


@dataclass
class BagJointState:
    """Shaped like a rosbags deserialised sensor_msgs/msg/JointState."""

    header: Header
    name: List[str]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    __msgtype__: ClassVar[str] = 'sensor_msgs/msg/JointState'


def joint_state(position, effort, sec=0, nanosec=0):
    message = JointState()
    message.header.stamp.sec = sec
    message.header.stamp.nanosec = nanosec
    message.name = [f'j{i}' for i in range(len(position))]
    message.position = list(position)
    message.effort = list(effort)
    return message


def bag_joint_state(position, effort, sec=0, nanosec=0):
    return BagJointState(Header(Time(sec, nanosec)), [f'j{i}' for i in range(len(position))],
                         np.asarray(position, dtype=float), np.zeros(0),
                         np.asarray(effort, dtype=float))


def test_grammar_compiles_names_and_indices():
    path = parse_field_path(' points[3].positions[1] ')
    assert path.steps == ('points', 3, 'positions', 1)
    assert str(path) == 'points[3].positions[1]'
    assert parse_field_path('pose.pose.position.z').steps == ('pose', 'pose', 'position', 'z')
    assert parse_field_path('data[0][12]').steps == ('data', 0, 12)
    # A selector with a letter is a joint name; digits alone an index.
    assert parse_field_path('position[wheel_left]').steps == ('position', Key('wheel_left'))
    assert parse_field_path('effort[arm/joint-2.a:b]').steps == ('effort', Key('arm/joint-2.a:b'))
    assert parse_field_path('position[2nd]').steps == ('position', Key('2nd'))


@pytest.mark.parametrize('text', [
    '', ' ', 'a..b', '.a', 'a.', '_data', 'a._b', 'a.__class__', '__class__', 'a[-1]',
    'a[0', 'a]', '0a', 'a b', 'a.b()', 'a[0]b', 'a;b', "a['b']", 'a[1.5]', 'a-b', 'a[]',
    'a[x y]', 'a[-]', 'a[x]]', 'a[[x]]', 'a[x)]', 'a[é]',
])
def test_invalid_paths_are_refused_with_the_grammar(text):
    with pytest.raises(ConfigError, match='names joined by dots'):
        parse_field_path(text)


def test_non_string_path_is_refused():
    with pytest.raises(ConfigError, match='must be a string'):
        parse_field_path(3)


def test_rclpy_messages():
    assert extract(Float64(data=2.5), 'data') == 2.5
    state = joint_state([0.1, 0.2, 0.3], [4.0, 5.0, 6.0])
    assert extract(state, 'effort[0]') == 4.0
    assert extract(state, parse_field_path('position[2]')) == pytest.approx(0.3)
    twist = TwistStamped()
    twist.twist.linear.x = -1.25
    twist.twist.angular.z = 3.0
    assert extract(twist, 'twist.linear.x') == -1.25
    assert extract(twist, 'twist.angular.z') == 3.0
    stamped = joint_state([0.0], [0.0], sec=7)
    value = extract(stamped, 'header.stamp.sec')
    assert value == 7.0 and isinstance(value, float)


def test_rosbags_style_dataclasses():
    state = bag_joint_state([0.5, -0.5], [1.5, 2.5], sec=3, nanosec=9)
    assert extract(state, 'position[1]') == -0.5
    assert extract(state, 'effort[1]') == 2.5
    assert message_fields(state) == ('header', 'name', 'position', 'velocity', 'effort')
    assert message_stamp(state) == 3_000_000_009


def test_real_rosbags_types():
    typestore = pytest.importorskip('rosbags.typesys').get_typestore
    from rosbags.typesys import Stores
    types = typestore(Stores.ROS2_JAZZY).types
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=2, nanosec=500), frame_id='')
    state = types['sensor_msgs/msg/JointState'](
        header=header, name=['a'], position=np.array([1.25]), velocity=np.array([]),
        effort=np.array([-3.0]))
    assert extract(state, 'position[0]') == 1.25
    assert extract(state, 'effort[0]') == -3.0
    assert '__msgtype__' not in message_fields(state)
    assert message_stamp(state) == 2_000_000_500


def test_mcap_ros2_decoded_objects(tmp_path):
    writer_module = pytest.importorskip('mcap_ros2.writer')
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    definition = '\n'.join([
        'std_msgs/Header header', 'geometry_msgs/Twist twist', '=' * 80, 'MSG: std_msgs/Header',
        'builtin_interfaces/Time stamp', 'string frame_id', '=' * 80,
        'MSG: builtin_interfaces/Time', 'int32 sec', 'uint32 nanosec', '=' * 80,
        'MSG: geometry_msgs/Twist', 'Vector3 linear', 'Vector3 angular', '=' * 80,
        'MSG: geometry_msgs/Vector3', 'float64 x', 'float64 y', 'float64 z'])
    path = tmp_path / 'twist.mcap'
    with open(path, 'wb') as stream:
        writer = writer_module.Writer(stream)
        schema = writer.register_msgdef('geometry_msgs/msg/TwistStamped', definition)
        writer.write_message('/cmd', schema, {
            'header': {'stamp': {'sec': 4, 'nanosec': 25}, 'frame_id': 'base'},
            'twist': {'linear': {'x': 0.75, 'y': 0.0, 'z': 0.0},
                      'angular': {'x': 0.0, 'y': 0.0, 'z': -0.5}}},
            log_time=1, publish_time=1)
        writer.finish()
    with open(path, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        message = next(iter(reader.iter_decoded_messages()))[3]
    assert extract(message, 'twist.linear.x') == 0.75
    assert extract(message, 'twist.angular.z') == -0.5
    assert message_fields(message) == ('header', 'twist')
    assert message_stamp(message) == 4_000_000_025
    with pytest.raises(ConfigError, match='available fields: x, y, z'):
        extract(message, 'twist.linear.w')


def test_unknown_field_lists_the_fields_at_that_level():
    with pytest.raises(ConfigError, match=r"twist\.linear .* no field 'q'; available fields: "
                                          r'x, y, z'):
        extract(TwistStamped(), 'twist.linear.q')
    with pytest.raises(ConfigError, match='available fields: header, twist'):
        extract(TwistStamped(), 'speed')
    with pytest.raises(ConfigError, match='available fields: header, name, position, velocity'):
        extract(bag_joint_state([1.0], [1.0]), 'positions[0]')


def test_index_errors_give_the_array_length():
    with pytest.raises(ConfigError, match='index 3 out of range for position, an array of '
                                          'length 2'):
        extract(joint_state([1.0, 2.0], [0.0, 0.0]), 'position[3]')
    with pytest.raises(ConfigError, match='length 0'):
        extract(bag_joint_state([1.0], [1.0]), 'velocity[0]')
    with pytest.raises(ConfigError, match=r'data is not an array, cannot take \[0\]'):
        extract(Float64(data=1.0), 'data[0]')


def test_non_numeric_values_are_refused():
    with pytest.raises(ConfigError, match='not a number: it is a str'):
        extract(joint_state([1.0], [1.0]), 'header.frame_id')
    with pytest.raises(ConfigError, match='not a number: .*available fields: x, y, z'):
        extract(TwistStamped(), 'twist.linear')
    with pytest.raises(ConfigError, match='not a number: .*array of length 2'):
        extract(joint_state([1.0, 2.0], [0.0, 0.0]), 'position')
    with pytest.raises(ConfigError, match='not a number: it is a str'):
        extract(joint_state([1.0], [1.0]), 'name[0]')


@dataclass
class BagSwitches:
    """Shaped like a rosbags deserialised message with a bool[] field (a numpy bool array)."""

    closed: np.ndarray
    __msgtype__: ClassVar[str] = 'test_msgs/msg/Switches'


def test_booleans_are_numbers_in_every_message_source():
    # A relay or valve input: rosbags gives a bool[] as a numpy bool array, whose elements
    # are np.bool_ (not numbers.Real); mcap_ros2 and the columnar decoder give 0/1.
    message = BagSwitches(np.array([True, False]))
    assert extract(message, 'closed[0]') == 1.0
    assert extract(message, 'closed[1]') == 0.0
    assert extract(Bool(data=True), 'data') == 1.0


def test_only_declared_fields_are_followed():
    # Python would resolve these attributes, but they are not message fields.
    with pytest.raises(ConfigError, match="no field 'get_fields_and_field_types'"):
        extract(Float64(data=1.0), 'get_fields_and_field_types')
    with pytest.raises(ConfigError, match="no field 'real'; it is a float"):
        extract(Float64(data=1.0), 'data.real')
    with pytest.raises(ConfigError, match="no field 'copy'"):
        extract(bag_joint_state([1.0], [1.0]), 'position.copy')


def test_non_finite_values_are_returned_for_the_buffer_to_count():
    assert math.isnan(extract(Float64(data=math.nan), 'data'))
    assert extract(bag_joint_state([math.inf], [0.0]), 'position[0]') == math.inf


def test_message_stamp():
    assert message_stamp(joint_state([0.0], [0.0], sec=12, nanosec=345)) == 12_000_000_345
    assert message_stamp(Float64(data=1.0)) is None
    # An all-zero stamp means an unset header: the caller falls back to the receive time.
    assert message_stamp(joint_state([0.0], [0.0])) is None
    assert message_stamp(TwistStamped()) is None


def named_joint_state(names, position, effort=()):
    message = JointState()
    message.name = list(names)
    message.position = list(position)
    message.effort = list(effort)
    return message


def test_joint_names_select_by_name_in_every_message_source():
    names = ['arm', 'wheel_left', 'wheel_right']
    rclpy_message = named_joint_state(names, [0.1, 0.2, 0.3], [1.0, 2.0, 3.0])
    bag_message = BagJointState(Header(), names, np.array([0.1, 0.2, 0.3]), np.zeros(0),
                                np.array([1.0, 2.0, 3.0]))
    for message in (rclpy_message, bag_message):
        assert extract(message, 'position[wheel_left]') == 0.2
        assert extract(message, 'effort[wheel_right]') == 3.0
        # An integer still indexes.
        assert extract(message, 'position[0]') == 0.1
        assert list(extract_values(message, ['effort[arm]', 'position[wheel_right]'])) == [
            1.0, 0.3]
    # The order may change from one message to the next: the name is looked up every time.
    reordered = named_joint_state(['wheel_right', 'wheel_left', 'arm'], [3.0, 2.0, 1.0])
    assert extract(reordered, 'position[wheel_left]') == 2.0
    assert extract(reordered, 'position[arm]') == 1.0


def test_joint_name_errors_list_the_names_seen():
    message = named_joint_state(['arm', 'wheel_right'], [0.1, 0.2], [1.0])
    with pytest.raises(ConfigError, match=r"field position\[wheel_left\]: no joint 'wheel_left' "
                                          r'in name; names seen: arm, wheel_right'):
        extract(message, 'position[wheel_left]')
    with pytest.raises(ConfigError, match=r"index 1 \(of 'wheel_right'\) out of range for "
                                          r'effort, an array of length 1'):
        extract(message, 'effort[wheel_right]')
    with pytest.raises(ConfigError, match=r'names seen: none \(empty\)'):
        extract(JointState(), 'position[arm]')
    many = named_joint_state([f'j{i}' for i in range(30)], [0.0] * 30)
    with pytest.raises(ConfigError, match=r'names seen: j0, j1, .*, j19 and 10 more'):
        extract(many, 'position[k]')
    # No list of names next to the array: said so, with the fields there are.
    with pytest.raises(ConfigError, match=r'selecting \[x\] by name needs a list of names '
                                          r'\(name or joint_names\) next to data; available '
                                          r'fields: layout, data'):
        extract(Float64MultiArray(data=[1.0]), 'data[x]')


def test_has_header_stamp():
    assert has_header_stamp(joint_state([0.0], [0.0]))
    assert has_header_stamp(bag_joint_state([0.0], [0.0]))
    assert not has_header_stamp(Float64(data=1.0))


def test_a_huge_message_is_read_without_copying_its_arrays():
    # A JointState of a million joints: the named element is found in place (issue 25: one
    # 1e7-element message raised the node's memory for good).
    count = 1_000_000
    names = [f'j{index}' for index in range(count)]
    message = JointState(name=names, position=np.arange(count, dtype=float))
    tracemalloc.start()
    try:
        value = extract(message, 'position[j999998]')
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert value == 999_998.0
    # A copy of the name list alone would take 8 MB.
    assert peak < 1_000_000, peak
