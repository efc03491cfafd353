"""The node's output contract: names, status rule, message layouts."""

from ctid_ros.errors import ConfigError, DataError, EstimationError
from ctid_ros.streaming.contract import (diagnostics_message, ERROR, estimate_line,
                                         estimate_messages, failure_status, format_diagnostic,
                                         LATCHED, matrix_multiarray, multiarray, NodeTopics, OK,
                                         PublisherQos, resolve_topic, STREAM, update_status,
                                         warm_up_text, WARN)
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


def test_covariance_and_publisher_qos():
    node = NodeTopics.of('/lab/ctid_node')
    covariance = [[4.0, 0.5], [0.5, 1.0]]
    messages = estimate_messages(node, ['K', 'T'], [2.0, 0.5], [2.0, 1.0],
                                 covariance=covariance)
    assert [message.topic for message in messages] == [
        '/lab/ctid_node/estimate', '/lab/ctid_node/estimate_std',
        '/lab/ctid_node/estimate_covariance', '/lab/ctid_node/params/K',
        '/lab/ctid_node/params/T']
    assert messages[2].fields == matrix_multiarray('K,T', covariance) == {
        'layout': {'dim': [{'label': 'K,T', 'size': 2, 'stride': 4},
                           {'label': 'K,T', 'size': 2, 'stride': 2}], 'data_offset': 0},
        'data': [4.0, 0.5, 0.5, 1.0]}
    # Every estimate topic is latched (late subscribers get the last one); the rest streams.
    assert {message.qos for message in messages} == {LATCHED}
    assert LATCHED == PublisherQos('reliable', 'transient_local', 1)
    prediction = estimate_messages(node, ['K'], [1.0], prediction=[0.0, 1.0])[-1]
    assert prediction.qos == STREAM == PublisherQos('reliable', 'volatile', 10)
    assert diagnostics_message(node, 0, OK, '', {}).qos == STREAM
    with pytest.raises(DataError, match='2 covariance rows for 3 parameter names'):
        estimate_messages(node, ['K', 'T', 'tau'], [1.0] * 3, covariance=covariance)
    with pytest.raises(DataError, match='square'):
        matrix_multiarray('K', [1.0, 2.0])


def test_hardware_id_and_texts_for_people():
    node = NodeTopics.of()
    status = diagnostics_message(node, 0, OK, '', {}, hardware_id='left_wheel_drive')
    assert status.fields['status'][0]['hardware_id'] == 'left_wheel_drive'
    assert diagnostics_message(node, 0, OK, '', {}).fields['status'][0]['hardware_id'] == \
        'ctid_node'
    assert estimate_line(['K', 'T'], [2.00131, 0.49981], [0.0031, 0.00121], 12.5, 95.34,
                         'white') == ('t=12.50 s: K = 2.00131 +- 0.0031, T = 0.49981 +- '
                                      '0.0012; fit 95.3 %; residuals white')
    assert estimate_line(['K'], [2.0], [0.1], 3.0) == 't=3.00 s: K = 2 +- 0.1'
    assert warm_up_text(6.43, 10.0, 5.0) == \
        'warming up: 6.4 of 10 s of data (first estimate after 5 s)'
    assert warm_up_text(6.43, 10.0) == 'warming up: 6.4 of 10 s of data'
