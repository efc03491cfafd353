"""
The columnar CDR decoder against rosbags' own deserialiser, on the same bytes.

Seeded random messages (empty arrays, frame_ids and names of every length modulo the
alignment, both byte orders), packed back to back in one buffer at random offsets as in a
chunk: every value the decoder returns equals what ``extract`` reads from rosbags' message, and
it hands to the per-message decoder exactly the messages whose path does not reach a number;
damaged bytes are always handed over. Elements selected by joint name are checked the same way,
with name lists in changing orders, lacking the joint, repeating a name, placed after the
array, or fixed-size.
"""

from ctid_ros.errors import ConfigError
from ctid_ros.files.cdr_columns import CdrColumns
from ctid_ros.streaming.message_fields import extract, message_stamp, parse_field_path
import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

STORE = get_typestore(Stores.ROS2_JAZZY)
CUSTOM = 'my_pkg/msg/Mixed'
CUSTOM_MSG = ('std_msgs/Header header\nbool flag\nint8 small\nuint16 medium\nstring label\n'
              'int64 big\nfloat32[3] triple\ngeometry_msgs/Point[] points\nuint8[] blob\n'
              'float64 last\n')
STORE.register(get_types_from_msg(CUSTOM_MSG, CUSTOM))
# Name lists after the arrays they name, fixed-size, and nested in a sequence of messages.
NAMES_AFTER = 'my_pkg/msg/NamesAfter'
FIXED_NAMES = 'my_pkg/msg/FixedNames'
NESTED_NAMES = 'my_pkg/msg/NestedNames'
STORE.register(get_types_from_msg('float32[] gains\nint16[2] limits\nstring[] joint_names\n',
                                  NAMES_AFTER))
STORE.register(get_types_from_msg('string frame\nstring[3] name\nfloat64[3] position\n',
                                  FIXED_NAMES))
STORE.register(get_types_from_msg(f'std_msgs/Header header\n{FIXED_NAMES}[] groups\n',
                                  NESTED_NAMES))
JOINTS = ['wheel_left', 'wheel_right', 'arm', 'j', 'arm/joint-2.a:b']
JOINT_STATE = 'sensor_msgs/msg/JointState'
POINT_STAMPED = 'geometry_msgs/msg/PointStamped'
FLOAT64 = 'std_msgs/msg/Float64'
TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'
IMU = 'sensor_msgs/msg/Imu'


def joint_names(rng, count):
    # Mostly a permutation of a few joints, sometimes a joint twice (the first one counts).
    names = list(rng.permutation(JOINTS)[:count])
    if count > 1 and rng.random() < 0.1:
        names[-1] = names[0]
    return names


def text(rng, longest=9):
    return ''.join(rng.choice(list('abcxyz_01'), size=int(rng.integers(0, longest + 1))))


def stamp(rng):
    # Zero stamps now and then: the sampler then takes the receive time.
    if rng.random() < 0.1:
        return STORE.types['builtin_interfaces/msg/Time'](0, 0)
    time_type = STORE.types['builtin_interfaces/msg/Time']
    return time_type(int(rng.integers(-2**31, 2**31)), int(rng.integers(0, 10**9)))


def header(rng):
    return STORE.types['std_msgs/msg/Header'](stamp(rng), text(rng))


def floats(rng, longest=4):
    return rng.normal(size=int(rng.integers(0, longest + 1))) * 10.0 ** rng.integers(-5, 5)


def point(rng):
    return STORE.types['geometry_msgs/msg/Point'](*rng.normal(size=3))


def random_message(rng, msgtype, named=False):
    types = STORE.types
    if msgtype == JOINT_STATE and named:
        return named_joint_state(rng)
    if msgtype == JOINT_STATE:
        return types[msgtype](header(rng), [text(rng) for _ in range(rng.integers(0, 4))],
                              floats(rng), floats(rng), floats(rng))
    if msgtype == NAMES_AFTER:
        return types[msgtype](rng.normal(size=int(rng.integers(0, 4))).astype(np.float32),
                              rng.integers(-999, 999, size=2).astype(np.int16),
                              joint_names(rng, int(rng.integers(0, 4))))
    if msgtype == FIXED_NAMES:
        return types[msgtype](text(rng), joint_names(rng, 3), rng.normal(size=3))
    if msgtype == NESTED_NAMES:
        return types[msgtype](header(rng), [random_message(rng, FIXED_NAMES)
                                            for _ in range(rng.integers(0, 3))])
    if msgtype == POINT_STAMPED:
        return types[msgtype](header(rng), point(rng))
    if msgtype == FLOAT64:
        return types[msgtype](float(rng.normal()))
    if msgtype == IMU:
        vector = types['geometry_msgs/msg/Vector3']
        return types[msgtype](header(rng), types['geometry_msgs/msg/Quaternion'](
            *rng.normal(size=4)), rng.normal(size=9), vector(*rng.normal(size=3)),
            rng.normal(size=9), vector(*rng.normal(size=3)), rng.normal(size=9))
    if msgtype == TRAJECTORY:
        point_type = types['trajectory_msgs/msg/JointTrajectoryPoint']
        duration = types['builtin_interfaces/msg/Duration']
        points = [point_type(floats(rng), floats(rng), floats(rng), floats(rng),
                             duration(int(rng.integers(0, 9)), 5))
                  for _ in range(rng.integers(0, 4))]
        return types[msgtype](header(rng), [text(rng) for _ in range(rng.integers(0, 3))],
                              points)
    return types[msgtype](header(rng), bool(rng.random() < 0.5), int(rng.integers(-128, 128)),
                          int(rng.integers(0, 65536)), text(rng), int(rng.integers(-2**62, 2**62)),
                          rng.normal(size=3).astype(np.float32),
                          [point(rng) for _ in range(rng.integers(0, 3))],
                          rng.integers(0, 256, size=int(rng.integers(0, 6))).astype(np.uint8),
                          float(rng.normal()))


PATHS = {
    JOINT_STATE: ['position[0]', 'velocity[1]', 'effort[0]', 'effort[2]', 'header.stamp.sec'],
    POINT_STAMPED: ['point.x', 'point.z', 'header.stamp.nanosec'],
    FLOAT64: ['data'],
    IMU: ['angular_velocity.z', 'orientation_covariance[8]', 'orientation.w'],
    TRAJECTORY: ['points[0].positions[1]', 'points[2].time_from_start.sec',
                 'points[1].effort[0]'],
    CUSTOM: ['flag', 'small', 'medium', 'big', 'triple[2]', 'points[1].y', 'blob[3]', 'last'],
}


NAMED_PATHS = {
    JOINT_STATE: ['position[wheel_left]', 'effort[arm]', 'velocity[0]', 'velocity[arm]'],
    NAMES_AFTER: ['gains[wheel_right]', 'limits[arm]', 'limits[j]'],
    FIXED_NAMES: ['position[wheel_left]', 'position[arm/joint-2.a:b]'],
    NESTED_NAMES: ['groups[1].position[arm]', 'groups[0].position[wheel_left]',
                   ],
}


def named_joint_state(rng):
    """Return a JointState of 0 to 5 named joints (fewer values now and then)."""
    count = int(rng.integers(0, len(JOINTS) + 1))
    values = [rng.normal(size=count - int(rng.random() < 0.1) if count else 0)
              for _ in range(3)]
    return STORE.types[JOINT_STATE](header(rng), joint_names(rng, count), *values)


def pack(rng, blobs):
    """Put serialised messages back to back at random (unaligned) offsets in one buffer."""
    data, starts = bytearray(), []
    for blob in blobs:
        data += bytes(rng.integers(0, 256, size=int(rng.integers(0, 8))).astype(np.uint8))
        starts.append(len(data))
        data += bytes(blob)
    return (np.frombuffer(bytes(data), dtype=np.uint8), np.array(starts),
            np.array([len(blob) for blob in blobs]))


def expected(msg, paths):
    """Return the values extract reads, or None if a path does not reach a number."""
    try:
        return [extract(msg, path) for path in paths]
    except ConfigError:
        return None


@pytest.mark.parametrize('msgtype', list(PATHS))
@pytest.mark.parametrize('little_endian', [True, False])
def test_random_messages_decode_as_rosbags_does(msgtype, little_endian):
    rng = np.random.default_rng(len(msgtype) + 7 * little_endian)
    messages = [random_message(rng, msgtype) for _ in range(300)]
    blobs = [STORE.serialize_cdr(msg, msgtype, little_endian=little_endian) for msg in messages]
    data, starts, lengths = pack(rng, blobs)
    paths = [parse_field_path(path) for path in PATHS[msgtype]]
    decoder = CdrColumns(STORE.fielddefs, msgtype, paths)
    assert decoder.supported
    decoded = decoder.decode(data, starts, lengths)
    reachable = 0
    for index, blob in enumerate(blobs):
        msg = STORE.deserialize_cdr(blob, msgtype)
        want = expected(msg, paths)
        assert decoded.fallback[index] == (want is None), index
        if want is not None:
            reachable += 1
            assert decoded.values[index].tolist() == want, index
        if decoded.stamp_ns is not None:
            assert (message_stamp(msg) or 0) == decoded.stamp_ns[index]
    assert (decoded.stamp_ns is None) == (msgtype == FLOAT64)
    assert reachable >= 20


@pytest.mark.parametrize('msgtype', list(NAMED_PATHS))
@pytest.mark.parametrize('little_endian', [True, False])
def test_elements_selected_by_name_decode_as_rosbags_does(msgtype, little_endian):
    rng = np.random.default_rng(len(msgtype) + 11 * little_endian)
    messages = [random_message(rng, msgtype, named=True) for _ in range(600)]
    blobs = [STORE.serialize_cdr(msg, msgtype, little_endian=little_endian) for msg in messages]
    for text in NAMED_PATHS[msgtype]:
        paths = [parse_field_path(text)]
        decoded = CdrColumns(STORE.fielddefs, msgtype, paths).decode(*pack(rng, blobs))
        reachable = 0
        for index, blob in enumerate(blobs):
            want = expected(STORE.deserialize_cdr(blob, msgtype), paths)
            assert decoded.fallback[index] == (want is None), (text, index)
            if want is not None:
                reachable += 1
                assert decoded.values[index].tolist() == want, (text, index)
        assert 20 <= reachable < len(blobs), text


def test_a_name_list_that_is_no_list_of_strings_hands_the_messages_over():
    """A ``name`` string (extract would index its characters) is left to extract."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('string name\nfloat64[] values\n', 'my_pkg/msg/OneName'))
    blob = store.serialize_cdr(store.types['my_pkg/msg/OneName']('abc', np.array([1.0, 2.0])),
                               'my_pkg/msg/OneName')
    data = np.frombuffer(blob, dtype=np.uint8)
    for path in ('values[b]', 'values[x]'):
        decoder = CdrColumns(store.fielddefs, 'my_pkg/msg/OneName', [parse_field_path(path)])
        assert decoder.decode(data, np.array([0]), np.array([data.size])).fallback.all(), path
    assert extract(store.deserialize_cdr(blob, 'my_pkg/msg/OneName'), 'values[b]') == 2.0


def test_a_path_that_exists_nowhere_hands_every_message_over():
    rng = np.random.default_rng(3)
    blobs = [STORE.serialize_cdr(random_message(rng, JOINT_STATE), JOINT_STATE)
             for _ in range(5)]
    for path in ('positions[0]', 'name[0]', 'position', 'header', 'header.frame_id',
                 'position[0].x', 'name[wheel_left]', 'header.stamp[wheel_left]',
                 'position[nobody]'):
        decoder = CdrColumns(STORE.fielddefs, JOINT_STATE, [parse_field_path(path)])
        assert decoder.decode(*pack(rng, blobs)).fallback.all(), path


@pytest.mark.parametrize('msgtype, named, texts', [
    (JOINT_STATE, False, PATHS[JOINT_STATE]), (CUSTOM, False, PATHS[CUSTOM]),
    (TRAJECTORY, False, PATHS[TRAJECTORY]), (JOINT_STATE, True, NAMED_PATHS[JOINT_STATE]),
    (NAMES_AFTER, True, NAMED_PATHS[NAMES_AFTER][:1]),
    (FIXED_NAMES, True, NAMED_PATHS[FIXED_NAMES])])
def test_damaged_bytes_are_handed_to_the_per_message_decoder(msgtype, named, texts):
    """Truncated, padded, flipped and re-encapsulated messages: never a wrong value."""
    rng = np.random.default_rng(5)
    paths = [parse_field_path(path) for path in texts]
    decoder = CdrColumns(STORE.fielddefs, msgtype, paths)
    blobs = []
    for _ in range(400):
        blob = bytearray(STORE.serialize_cdr(random_message(rng, msgtype, named), msgtype))
        damage = rng.integers(0, 5)
        if damage == 0 and len(blob) > 4:
            del blob[int(rng.integers(4, len(blob))):]
        elif damage == 1:
            blob += bytes(int(rng.integers(1, 9)))
        elif damage == 2:
            blob[int(rng.integers(4, len(blob)))] = int(rng.integers(0, 256))
        elif damage == 3:
            blob[1] = int(rng.integers(2, 4))
        blobs.append(bytes(blob))
    decoded = decoder.decode(*pack(rng, blobs))
    assert np.count_nonzero(~decoded.fallback) >= 20
    for index, blob in enumerate(blobs):
        if decoded.fallback[index]:
            continue
        # Not handed over: rosbags reads the same values from it.
        msg = STORE.deserialize_cdr(blob, msgtype)
        assert decoded.values[index].tolist() == expected(msg, paths), index


def test_a_message_cut_inside_its_last_element_is_handed_over():
    """
    Cut after the element read: the message is still short for rosbags.

    The effort count ends 4 bytes before an 8-byte boundary, so the bytes left after it hold
    the two elements but not their alignment padding as well.
    """
    types = STORE.types
    msg = types[JOINT_STATE](types['std_msgs/msg/Header'](
        types['builtin_interfaces/msg/Time'](1, 2), 'ab'), ['a'], np.zeros(1), np.zeros(1),
        np.array([1.0, 2.0]))
    blob = STORE.serialize_cdr(msg, JOINT_STATE)[:-2]
    with pytest.raises(Exception, match='buffer is smaller'):
        STORE.deserialize_cdr(blob, JOINT_STATE)
    decoder = CdrColumns(STORE.fielddefs, JOINT_STATE, [parse_field_path('effort[0]')])
    data = np.frombuffer(blob, dtype=np.uint8)
    assert decoder.decode(data, np.array([0]), np.array([data.size])).fallback.all()


def test_types_outside_the_layouts_are_declined():
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('wstring text\nfloat64 x\n', 'my_pkg/msg/Wide'))
    store.register(get_types_from_msg('float64[<=3] few\n', 'my_pkg/msg/Bounded'))
    path = [parse_field_path('x')]
    assert not CdrColumns(store.fielddefs, 'my_pkg/msg/Wide', path).supported
    assert not CdrColumns(store.fielddefs, 'my_pkg/msg/Bounded', path).supported
    assert not CdrColumns(store.fielddefs, 'my_pkg/msg/Unknown', path).supported
    assert CdrColumns(store.fielddefs, JOINT_STATE, path).supported
