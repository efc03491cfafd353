"""Messages to samples, as the live node and the replay take them."""

from types import SimpleNamespace

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.sampler import (FieldErrors, message_type, MessageSampler, Sample,
                                        WRONG_PATH_MESSAGES)
import numpy as np
import pytest

T0_NS = 1_700_000_000_000_000_000


def joint_state(stamp_ns, effort, position):
    stamp = SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp), effort=effort,
                           position=position)


def test_one_topic_carrying_input_and_output():
    config = IdentificationConfig(
        model='T*s*q + q = K1*v + K2*w', input_names=('v', 'w'), output_name='q',
        input_topic='/joint_states', output_topic='/joint_states', input_field='effort[0]',
        extra_input_fields=('effort[1]',), output_field='position[0]')
    sampler = MessageSampler(config, ('/joint_states', '/joint_states'))
    assert sampler.names == ('input /joint_states (effort[0], effort[1])',
                             'output /joint_states (position[0])')
    assert sampler.roles('/joint_states') == ('input', 'output')
    assert sampler.roles('/other') == ()
    sample = sampler('/joint_states', T0_NS + 5, joint_state(T0_NS, [1.0, 2.0], [3.0]))
    assert sample.stamp_ns == T0_NS and sample.y == 3.0 and sample.errors == ()
    np.testing.assert_array_equal(sample.u, [1.0, 2.0])
    buffer = sampler.buffer(100, config)
    sample.add_to(buffer)
    stats = buffer.stats()
    assert (stats.u.accepted, stats.y.accepted) == (1, 1)
    # A missing entry: counted by the node and the replay; the output still comes.
    broken = sampler('/joint_states', T0_NS + 7, joint_state(0, [1.0], [4.0]))
    assert broken.stamp_ns == T0_NS + 7                 # unset header: the receive time
    assert broken.zero_stamp and not sample.zero_stamp  # ... counted as a zero stamp
    assert broken.u is None and broken.y == 4.0
    assert [role for role, _ in broken.errors] == ['input']
    errors = FieldErrors(sampler.names)
    errors.add(sample, sampler.roles('/joint_states'), 'sensor_msgs/msg/JointState')
    errors.add(broken, sampler.roles('/joint_states'), 'sensor_msgs/msg/JointState')
    errors.check()
    assert errors.warnings()[0] == ('input /joint_states (effort[0], effort[1]): 1 of 2 '
                                    'messages skipped, as the live node skips them: field '
                                    'effort[1]: index 1 out of range for effort, an array of '
                                    'length 1')
    # Its unset stamp is counted for both streams of the topic, as the node counts it.
    assert errors.unstamped == {'input': 1, 'output': 1}


JOINT_STATE = 'sensor_msgs/msg/JointState'


def test_field_errors_skip_missing_elements_and_raise_wrong_paths():
    """A message without the joint is skipped; a path no message can have stops the replay."""
    config = IdentificationConfig(model='K/(T*s + 1)', input_topic='/joint_states',
                                  output_topic='/joint_states', input_field='effort[wheel]',
                                  output_field='position[wheel]')
    sampler = MessageSampler(config, ('/joint_states', '/joint_states'))
    roles = sampler.roles('/joint_states')

    def named(names):
        message = joint_state(T0_NS, [1.0] * len(names), [2.0] * len(names))
        message.name = names
        return sampler('/joint_states', T0_NS, message)

    errors = FieldErrors(sampler.names)
    errors.add(named(['arm']), roles, JOINT_STATE)
    # No message had the joint yet: the first error is the reason.
    with pytest.raises(ConfigError, match="no joint 'wheel' in name; names seen: arm"):
        errors.check()
    errors.add(named(['arm', 'wheel']), roles, JOINT_STATE)
    errors.check()
    assert (errors.read, errors.failed) == ({'input': 1, 'output': 1},
                                            {'input': 1, 'output': 1})
    # A type without the field is ignored, by its name, while another type gives samples.
    string = sampler('/joint_states', T0_NS, SimpleNamespace(data='text'))
    errors.add(string, roles, 'std_msgs/msg/String')
    errors.check()
    assert errors.warnings()[-1] == (
        'output /joint_states (position[wheel]): 1 messages of std_msgs/msg/String ignored, as '
        'the live node ignores a type without the field: field position[wheel]: the message '
        "(SimpleNamespace) has no field 'position'; available fields: data")
    # A path no type has: raised once WRONG_PATH_MESSAGES messages gave nothing.
    wrong = FieldErrors(sampler.names)
    for _ in range(WRONG_PATH_MESSAGES - 1):
        wrong.add(string, roles, 'std_msgs/msg/String')
    with pytest.raises(ConfigError, match="has no field 'effort'"):
        wrong.add(string, roles, 'std_msgs/msg/String')


def test_separate_topics_and_receive_stamps():
    config = IdentificationConfig(model='K/(T*s + 1)', input_topic='u', output_topic='y',
                                  stamp_source='receive')
    sampler = MessageSampler(config, ('/u', '/y'))
    assert sampler.names == ('input /u (data)', 'output /y (data)')
    assert sampler('/u', 11, SimpleNamespace(data=2.0)) == Sample(11, 2.0, None)
    assert sampler('/y', 12, SimpleNamespace(data=3.0)) == Sample(12, None, 3.0)
    assert sampler('/z', 13, SimpleNamespace(data=3.0)) == Sample(13, None, None)


def test_message_type_is_the_full_name_for_both_decoders():
    class Decoded:      # as mcap_ros2 names its classes
        _type = 'std_msgs/Float64'

    assert message_type(Decoded()) == 'std_msgs/msg/Float64'
    assert message_type(SimpleNamespace(__msgtype__='geometry_msgs/msg/Twist')) == \
        'geometry_msgs/msg/Twist'
