"""The node's output contract: names, status rule, message layouts."""

from ctid_ros.errors import ConfigError, DataError, EstimationError
from ctid_ros.streaming.contract import (diagnostics_message, ERROR, estimate_messages,
                                         failure_status, format_diagnostic, multiarray,
                                         NodeTopics, OK, resolve_topic, update_status, WARN)
import numpy as np
import pytest


def test_node_topics():
    for node in (NodeTopics.of(), NodeTopics.of('ctid_node'), NodeTopics('/ctid_node')):
        assert (node.estimate, node.estimate_std, node.prediction, node.param('K')) == (
            '/ctid_node/estimate', '/ctid_node/estimate_std', '/ctid_node/prediction',
            '/ctid_node/params/K')
        assert (node.diagnostics, node.status_name, node.name) == (
            '/diagnostics', 'ctid_node: estimate', 'ctid_node')
    assert NodeTopics.of('/lab/ident').node == NodeTopics.of('ident', '/lab/').node == \
        '/lab/ident'
    assert NodeTopics.of('/lab/ident').status_name == 'lab/ident: estimate'
    for bad in ('plant-1', '1st'):
        with pytest.raises(ConfigError, match='invalid ROS name'):
            NodeTopics.of('ctid_node', bad)
    with pytest.raises(ConfigError, match='fully qualified'):
        NodeTopics('ctid_node')


def test_topic_resolution():
    assert resolve_topic('/plant/u', '/lab/ctid_node') == '/plant/u'
    assert resolve_topic('u', 'ctid_node') == '/u'
    assert resolve_topic('u', '/lab/ctid_node') == '/lab/u'
    assert resolve_topic('~/u', '/lab/ctid_node') == '/lab/ctid_node/u'


def test_status_rule():
    names, values, stds = ('K', 'T'), (2.0, 0.5), (0.01, 0.002)
    assert update_status(names, values, stds, {'converged': True, 'warnings': []}) == (
        OK, 'K=2 (std 0.01), T=0.5 (std 0.002)')
    assert update_status(names, values, stds, {'converged': False, 'warnings': []}) == (
        WARN, 'not converged')
    assert update_status(names, values, stds, {'converged': False, 'warnings': ['a', 'b']}) == (
        WARN, 'a; b')
    assert failure_status(DataError('no samples')) == (WARN, 'no samples')
    assert failure_status(EstimationError('unstable')) == (ERROR, 'unstable')


def test_messages_of_an_update():
    node = NodeTopics.of()
    messages = estimate_messages(node, ['K', 'T'], [2.0, 0.5], [0.1, 0.2], np.arange(3.0))
    assert [(message.topic, message.msgtype) for message in messages] == [
        ('/ctid_node/estimate', 'std_msgs/msg/Float64MultiArray'),
        ('/ctid_node/estimate_std', 'std_msgs/msg/Float64MultiArray'),
        ('/ctid_node/params/K', 'std_msgs/msg/Float64'),
        ('/ctid_node/params/T', 'std_msgs/msg/Float64'),
        ('/ctid_node/prediction', 'std_msgs/msg/Float64MultiArray')]
    assert messages[0].fields == multiarray('K,T', [2.0, 0.5]) == {
        'layout': {'dim': [{'label': 'K,T', 'size': 2, 'stride': 2}], 'data_offset': 0},
        'data': [2.0, 0.5]}
    assert messages[-1].fields['layout']['dim'][0]['label'] == 'prediction'
    assert len(estimate_messages(node, ['K'], [1.0])) == 2     # no stds, no prediction
    with pytest.raises(DataError):
        estimate_messages(node, ['K', 'T'], [1.0])
    status = diagnostics_message(node, 1_700_000_000_250_000_000, WARN, 'late',
                                 {'fit_percent': 95.5, 'converged': np.bool_(True),
                                  'window_end': 1_700_000_000.25, 'warnings': ['a', 'b']})
    assert status.topic == '/diagnostics'
    assert status.fields['header']['stamp'] == {'sec': 1_700_000_000, 'nanosec': 250_000_000}
    (entry,) = status.fields['status']
    assert (entry['level'], entry['name'], entry['message'], entry['hardware_id']) == (
        WARN, 'ctid_node: estimate', 'late', 'ctid_node')
    assert entry['values'] == [{'key': 'fit_percent', 'value': '95.5'},
                               {'key': 'converged', 'value': 'true'},
                               {'key': 'window_end', 'value': '1700000000.25'},
                               {'key': 'warnings', 'value': 'a; b'}]


def test_diagnostic_values_keep_every_digit():
    assert format_diagnostic(1_700_000_000.123456789) == repr(1_700_000_000.123456789)
    assert format_diagnostic(np.int64(3)) == '3' and format_diagnostic(False) == 'false'
