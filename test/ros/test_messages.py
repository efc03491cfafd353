"""The live node's messages and those ``ctid replay --output`` writes are the same messages."""

from ctid_ros.errors import ConfigError
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.mcap_writer import EstimateWriter
from ctid_ros.ros.messages import field_problem, import_message, to_message
from ctid_ros.streaming.contract import (diagnostics_message, estimate_messages, NodeTopics,
                                         update_status)
from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rclpy.serialization import deserialize_message
from std_msgs.msg import Float64MultiArray

T0_NS = 1_700_000_000_123_456_789
NAMES = ('J', 'b', 'tau')
VALUES, STDS = (0.05, 0.2, 0.0373), (1e-4, 2e-4, 3e-4)
PREDICTION = [0.0, 0.5, 0.75, 0.875]
DIAGNOSTICS = {'fit_percent': 95.25, 'converged': True, 'window_end': T0_NS * 1e-9,
               'warnings': []}


def test_replay_output_decodes_in_ros_to_the_messages_the_node_publishes(tmp_path):
    path = tmp_path / 'estimates.mcap'
    with EstimateWriter(path, node_name='/lab/ctid_node') as writer:
        writer.write_estimate(T0_NS, NAMES, VALUES, STDS, DIAGNOSTICS, PREDICTION)
    node = NodeTopics('/lab/ctid_node')
    # What IdentificationNode publishes for the same update (it stamps the status itself).
    expected = [*estimate_messages(node, NAMES, VALUES, STDS, PREDICTION),
                diagnostics_message(node, T0_NS, *update_status(NAMES, VALUES, STDS, DIAGNOSTICS),
                                    DIAGNOSTICS)]
    with BagReader(path) as bag:
        types = bag.topics()
        records = list(bag.records())
    assert [record.topic for record in records] == [message.topic for message in expected]
    for record, message in zip(records, expected):
        assert types[record.topic] == message.msgtype
        message_class = import_message(message.msgtype)
        assert deserialize_message(record.data, message_class) == \
            to_message(message_class, message.fields), record.topic


def test_to_message_nests_and_converts_bytes():
    status = to_message(DiagnosticStatus, {'level': 2, 'name': 'n', 'values': [
        {'key': 'a', 'value': '1'}]})
    assert status.level == DiagnosticStatus.ERROR and status.values[0].key == 'a'
    layout = {'dim': [{'label': 'x', 'size': 1, 'stride': 1}]}
    array = to_message(Float64MultiArray, {'layout': layout, 'data': [1.0]})
    assert array.layout.dim[0].label == 'x' and list(array.data) == [1.0]
    with pytest.raises(ConfigError, match='no field'):
        to_message(Float64MultiArray, {'values': []})


def test_import_message_names():
    assert import_message('sensor_msgs/msg/JointState').__name__ == 'JointState'
    assert import_message('std_msgs/Header').__name__ == 'Header'
    with pytest.raises(ConfigError, match='not installed'):
        import_message('my_pkg/msg/Missing')


def test_field_problem_checks_a_path_against_a_message_type():
    from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64, String

    for message_class, path in ((Float64, 'data'), (PointStamped, 'point.x'),
                                (JointState, 'position[0]'), (JointState, 'effort[wheel_left]'),
                                (PoseWithCovarianceStamped, 'pose.covariance[35]'),
                                (PointStamped, 'header.stamp.sec')):
        assert field_problem(message_class, path) is None, (message_class, path)
    assert field_problem(String, 'data') == 'data is a string, not a number'
    assert field_problem(Float64, 'point.x') == "Float64 has no field 'point'; its fields: data"
    assert field_problem(PointStamped, 'point.w') == \
        "Point has no field 'w'; its fields: x, y, z"
    assert field_problem(Float64, 'data[0]') == 'double is not an array, cannot take [0]'
    assert field_problem(JointState, 'position') == 'position is a sequence<double>, not a number'
    assert field_problem(JointState, 'name[0]') == 'name[0] is a string, not a number'
    assert 'needs a list of names' in field_problem(Float64MultiArray, 'data[x]')
    assert field_problem(Float64, 'data.x') == "double has no field 'x'"
