"""Offline replay and the live node give the same estimate when fed the same samples."""

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from ctid_ros.ros.node import IdentificationNode
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.replay import replay_messages
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

T0_NS = 1_700_000_000 * 10 ** 9
TS = 0.01
SETTINGS = {
    'input_topic': '/joint_states', 'output_topic': '/joint_states',
    'input_field': 'effort[0]', 'output_field': 'position[0]',
    'model': 'K/(T*s + 1)', 'sample_time': TS, 'window': 5.0, 'update_period': 11.0,
}


def joint_states(seconds: float = 12.0):
    """Header-stamped JointState messages of a first-order plant, logged 1 ms after stamping."""
    u = prbs(9, 10)[:int(seconds / TS)]
    y = Model('K/(T*s + 1)').simulate({'K': 2.0, 'T': 0.4}, u, TS)
    y = y + 0.01 * np.random.default_rng(3).standard_normal(y.size)
    messages = []
    for index, (effort, position) in enumerate(zip(u, y)):
        stamp = T0_NS + index * int(TS * 1e9)
        message = JointState(name=['joint'], effort=[float(effort)], position=[float(position)])
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 10 ** 9)
        messages.append(('/joint_states', stamp + 10 ** 6, message))
    return messages


@pytest.fixture
def node():
    context = Context()
    rclpy.init(context=context)
    overrides = [Parameter(name, value=value) for name, value in SETTINGS.items()]
    created = IdentificationNode(context=context, parameter_overrides=overrides,
                                 namespace='/agreement')
    yield created
    created.destroy_node()
    rclpy.shutdown(context=context)


def test_replay_matches_the_live_node_fed_the_same_messages(node):
    messages = joint_states()
    replayed = replay_messages(messages, IdentificationConfig(**SETTINGS), sliding=True)
    assert len(replayed.updates) == 1                     # one tick, 11 s after the first message
    tick = messages[0][1] + int(11.0 * 1e9)
    for topic, log_time, message in messages:
        if log_time <= tick:
            node.receive(topic, message)
    live, summary = node.estimate()
    assert live is not None, summary
    offline = replayed.updates[0]
    assert live.names == offline.names == ('K', 'T')
    assert live.end_ns == offline.end_ns
    np.testing.assert_array_equal(live.window.data.y, offline.window.data.y)
    np.testing.assert_allclose(live.values, offline.values, rtol=1e-12)
    np.testing.assert_allclose(live.stds, offline.stds, rtol=1e-12)
    assert live.values == pytest.approx([2.0, 0.4], rel=0.02)
