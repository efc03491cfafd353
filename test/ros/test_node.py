"""
Launch-free tests of ctid_node against the simulated plant, on real DDS over loopback.

Each test has its own rclpy context, an executor thread per node and a namespace
(test/node_harness.py). Tolerances follow from the noise: the plant adds white noise of std
0.01 to outputs of amplitude ~1, so over windows of thousands of samples the standard
deviations of the estimates are a few 0.1 % (see the published ``estimate_std``); the bounds
below are several of those plus, for Float64 topics stamped on reception, the time resolution
of one sample time on the dead time.
"""

import math
import re
import subprocess
import sys
import threading
import time

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PointStamped
from node_harness import converge, keys, named, wait_for
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray
from std_srvs.srv import Trigger


def first_order(**extra):
    """ctid_node parameters for K*exp(-tau*s)/(T*s + 1) from Float64 topics u and y."""
    parameters = {
        'input_topic': 'u', 'output_topic': 'y', 'model': 'K*exp(-tau*s)/(T*s + 1)',
        'parameter_names': ['K', 'T', 'tau'], 'initial': [1.0, 1.0, math.nan],
        'lower': [0.001, 0.01, 0.0], 'upper': [100.0, 100.0, 1.0], 'sample_time': 0.005,
        'window': 6.0, 'update_period': 1.0, 'qos_reliability': 'reliable'}
    parameters.update(extra)
    return parameters


# Float64 has no header: samples are stamped when published, which on a loaded machine can be
# late by a few ms (more than a 5 ms sample at times), so these estimates are looser.
FLOAT64_TRUTH = ({'K': 2.0, 'T': 0.5}, {'K': 0.1, 'T': 0.05})


def test_open_loop_fractional_delay(ros):
    # tau = 27.4 samples of 5 ms, stamped in the headers: exact sampled data.
    truth = {'K': 2.0, 'T': 0.5, 'tau': 0.137}
    ros.plant(parameter_values=[2.0, 0.5, 0.137], sample_time=0.005,
              message_type='point_stamped')
    ros.identifier(**first_order(input_field='point.x', output_field='point.x'))
    estimate = converge(ros, truth, {'K': 0.02, 'T': 0.015, 'tau': 0.006}, timeout=60.0)
    assert estimate.keys() == truth.keys()
    # The diagnostics of an update follow its estimate.
    wait_for(lambda: 'fit_percent' in keys(ros.latest(ros.statuses)), 60.0, 'diagnostics')
    values = keys(ros.latest(ros.statuses))
    assert float(values['fit_percent']) > 95.0
    assert int(values['input_received']) > 500 and int(values['output_received']) > 500


def test_dead_time_from_stamps_at_a_phase_of_the_sample(ros):
    # Issue 13 live: header stamps 0.13 of a sample after the multiples of 10 ms, jittered by
    # up to 0.5 % of it, the output read 3 % of a sample after its command; published in real
    # time by a thread of this test. tau = 5.37 samples.
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    truth = {'K': 1.5, 'T': 0.08, 'tau': 0.0537}
    ts, count = 0.01, 1400
    rng = np.random.default_rng(13)
    u = np.resize(prbs(10, 4), count)
    y = model.simulate(truth, u, ts, output_skew=0.03 * ts)
    y = y + 0.02 * rng.standard_normal(count)
    node = ros.identifier(**first_order(
        input_field='point.x', output_field='point.x', sample_time=ts, window=8.0,
        update_period=2.0, lower=[0.001, 0.001, 0.0], upper=[100.0, 10.0, 0.5]))
    publishers = {topic: ros.observer.create_publisher(PointStamped, topic, 1000)
                  for topic in 'uy'}
    wait_for(lambda: all(p.get_subscription_count() for p in publishers.values()), 60.0,
             'ctid_node subscribed to u and y')
    start = (time.time_ns() // 10_000_000 + 20) * 10_000_000
    jitter = rng.uniform(-0.005, 0.005, (count, 2)) * ts
    stop = threading.Event()

    def publish():
        for k in range(count):
            for column, (topic, offset, value) in enumerate((('u', 0.13, u[k]),
                                                             ('y', 0.16, y[k]))):
                stamp = start + round(((k + offset) * ts + jitter[k, column]) * 1e9)
                delay = (stamp - time.time_ns()) / 1e9
                if delay > 0 and stop.wait(delay):
                    return
                message = PointStamped()
                message.point.x = float(value)
                message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 10 ** 9)
                publishers[topic].publish(message)

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        wait_for(lambda: node.last_update is not None and
                 node.last_update.window.data.y.size * ts > 8.0, 40.0, 'an 8 s window')
    finally:
        stop.set()
        thread.join(timeout=10)
    update = node.last_update
    assert update.window.plan.follows_input
    assert update.window.data.output_skew == pytest.approx(0.03 * ts, abs=5e-4 * ts)
    tau, std = (dict(zip(update.names, values))['tau']
                for values in (update.values, update.stds))
    assert abs(tau - truth['tau']) <= 0.03 * ts and abs(tau - truth['tau']) <= 3 * std, \
        (tau, std)


def test_closed_loop_pi(ros):
    truth = {'m': 1.0, 'd': 2.0, 'k': 3.0}
    ros.plant(model='1/(m*s**2 + d*s + k)', parameter_names=['m', 'd', 'k'],
              parameter_values=[1.0, 2.0, 3.0], controller='20 + 10/s', sample_time=0.005,
              input_topic='r', prbs_clock=40, message_type='point_stamped')
    ros.identifier(input_topic='r', output_topic='y', input_field='point.x',
                   output_field='point.x', model='1/(m*s**2 + d*s + k)',
                   controller='20 + 10/s', parameter_names=['m', 'd', 'k'],
                   initial=[math.nan] * 3, lower=[0.001, 0.0, 0.0],
                   upper=[100.0, 100.0, 1000.0], sample_time=0.005, window=6.0,
                   update_period=1.0)
    converge(ros, truth, {'m': 0.05, 'd': 0.1, 'k': 0.15}, timeout=60.0)


def test_joint_state_single_topic_with_header_stamps(ros):
    truth = {'J': 0.2, 'b': 1.0, 'k': 4.0}
    plant = ros.plant(model='1/(J*s**2 + b*s + k)', parameter_names=['J', 'b', 'k'],
                      parameter_values=[0.2, 1.0, 4.0], sample_time=0.01,
                      message_type='joint_state', joint_state_topic='joint_states')
    node = ros.identifier(input_topic='joint_states', input_field='effort[0]',
                          output_topic='joint_states', output_field='position[0]',
                          model='1/(J*s**2 + b*s + k)', parameter_names=['J', 'b', 'k'],
                          sample_time=0.01, window=5.0, update_period=1.0, max_gap=0.1)
    # A message without an effort entry: the field path cannot be read, counted not fatal.
    broken = plant.create_publisher(JointState, 'joint_states', 10)
    wait_for(lambda: broken.get_subscription_count() > 0, 60.0, 'subscriber of joint_states')
    for _ in range(3):
        broken.publish(JointState(name=['joint'], position=[0.0]))
    converge(ros, truth, {'J': 0.004, 'b': 0.02, 'k': 0.04}, timeout=60.0)
    # Header stamps on the sample instants: input and output come in pairs, none refused.
    stats = node.buffer.stats()
    assert stats.u.duplicates == stats.u.late == stats.y.late == 0
    wait_for(lambda: keys(ros.latest(ros.statuses))['input_field_errors'] == '3', 10.0,
             lambda: f'3 field errors counted: {ros.latest(ros.statuses)}')
    assert keys(ros.latest(ros.statuses))['output_field_errors'] == '0'


def test_invalid_parameter_updates_rejected(ros):
    node = ros.identifier(**first_order())
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)

    def set_parameters(*parameters):
        future = client.set_parameters(list(parameters))
        wait_for(future.done, 30.0, 'set_parameters')
        return future.result().results[0]

    before = node.config
    for parameter, reason in (
            (Parameter('model', value="__import__('os')"), 'model'),
            (Parameter('lower', value=[0.001, 200.0, 0.0]), 'lower must be < upper'),
            (Parameter('upper', value=[1.0, 2.0]), 'upper has 2 values'),
            (Parameter('window', value=0.01), 'window'),
            (Parameter('method', value='magic'), 'method must be one of')):
        result = set_parameters(parameter)
        assert not result.successful
        assert reason in result.reason, result.reason
    assert node.config == before
    assert node.get_parameter('model').value == 'K*exp(-tau*s)/(T*s + 1)'
    # Read-only parameters are refused by rclpy itself.
    assert not set_parameters(Parameter('input_topic', value='other')).successful
    result = set_parameters(Parameter('upper', value=[50.0, 20.0, 0.5]))
    assert result.successful, result.reason
    assert node.config.upper == (50.0, 20.0, 0.5)
    assert node.config.bounds()['tau'] == (0.0, 0.5)


def test_garbage_silence_and_publisher_restart(ros):
    node = ros.identifier(**first_order(model='K/(T*s + 1)', parameter_names=['K', 'T'],
                                        initial=[1.0, 1.0], lower=[0.001, 0.01],
                                        upper=[100.0, 100.0], window=5.0))
    wait_for(lambda: ros.latest(ros.statuses) is not None, 60.0, 'diagnostics')
    silent = ros.latest(ros.statuses)
    assert silent.level == DiagnosticStatus.WARN
    assert f'no publisher on {ros.namespace}/u yet' in silent.message
    plant = {'model': 'K/(T*s + 1)', 'parameter_names': ['K', 'T'],
             'parameter_values': [2.0, 0.5]}
    process = ros.spawn_plant(**plant)
    converge(ros, *FLOAT64_TRUTH, timeout=60.0)
    # NaN on both topics from a second publisher: refused, counted, estimation goes on.
    garbage = {topic: ros.observer.create_publisher(Float64, topic, 10) for topic in 'uy'}
    wait_for(lambda: all(p.get_subscription_count() for p in garbage.values()), 60.0, 'match')
    for _ in range(5):
        for publisher in garbage.values():
            publisher.publish(Float64(data=math.nan))
    count = len(ros.estimates)
    wait_for(lambda: len(ros.estimates) > count + 1, 60.0, 'estimates after NaN')
    values = keys(ros.latest(ros.statuses))
    assert int(values['input_non_finite']) == 5 and int(values['output_non_finite']) == 5
    # Float64 is stamped on publication: under load an estimate may carry a warning.
    assert ros.latest(ros.statuses).level != DiagnosticStatus.ERROR, ros.latest(ros.statuses)
    # The plant's publishers go away: the node reports the silence and keeps running.
    process.terminate()
    process.wait(timeout=10)
    wait_for(lambda: 'silent: no message for' in ros.latest(ros.statuses).message, 60.0,
             'silence reported')
    assert ros.latest(ros.statuses).level == DiagnosticStatus.WARN
    received = node.buffer.stats().y.received
    ros.spawn_plant(**plant)
    count = len(ros.estimates)
    wait_for(lambda: len(ros.estimates) > count, 60.0, 'estimates after the restart')
    assert node.buffer.stats().y.received > received
    converge(ros, *FLOAT64_TRUTH, timeout=60.0)


def test_reset_and_estimate_now(ros):
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[2.0, 0.5],
              message_type='point_stamped')
    node = ros.identifier(**first_order(model='K/(T*s + 1)', parameter_names=['K', 'T'],
                                        initial=[1.0, 1.0], lower=[0.001, 0.01],
                                        upper=[100.0, 100.0], window=5.0,
                                        update_period=100.0, input_field='point.x',
                                        output_field='point.x', publish_prediction=True))
    estimate_now = f'{ros.namespace}/ctid_node/estimate_now'
    wait_for(lambda: node.buffer.stats().y.span > 5.5, 60.0, 'a window of data')
    response = ros.call(Trigger, estimate_now, Trigger.Request())
    assert response.success, response.message
    found = dict(re.findall(r'(\w+)=([-0-9.e]+)', response.message))
    assert abs(float(found['K']) - 2.0) < 0.02 and abs(float(found['T']) - 0.5) < 0.01, \
        response.message
    wait_for(lambda: ros.estimates, 60.0, 'estimate published by estimate_now')
    # The contract's prediction: one array per update over the window's grid instants.
    wait_for(lambda: ros.predictions and ros.statuses, 60.0, 'prediction and diagnostics')
    prediction, status = ros.latest(ros.predictions), ros.latest(ros.statuses)
    assert prediction.layout.dim[0].label == 'prediction'
    assert len(prediction.data) == prediction.layout.dim[0].size == int(keys(status)['samples'])
    assert len(ros.predictions) == 1
    response = ros.call(Trigger, f'{ros.namespace}/ctid_node/reset', Trigger.Request())
    assert response.success
    assert node.buffer.stats().y.received < 50
    response = ros.call(Trigger, estimate_now, Trigger.Request())
    assert not response.success
    # The buffer fills again: the node says how far, against the configured 5 s window.
    assert re.fullmatch(r'warming up: \d\.\d of 5 s of data \(first estimate after 2.5 s\)',
                        response.message) or 'no samples' in response.message, response.message


def test_late_subscriber_gets_the_last_estimate(ros):
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[2.0, 0.5],
              message_type='point_stamped')
    node = ros.identifier(**first_order(model='K/(T*s + 1)', parameter_names=['K', 'T'],
                                        initial=[1.0, 1.0], lower=[0.001, 0.01],
                                        upper=[100.0, 100.0], window=4.0,
                                        update_period=100.0, input_field='point.x',
                                        output_field='point.x'))
    wait_for(lambda: node.buffer.stats().y.span > 4.5, 60.0, 'a window of data')
    response = ros.call(Trigger, f'{ros.namespace}/ctid_node/estimate_now', Trigger.Request())
    assert response.success, response.message
    published = node.last_update
    # A tool started after the estimate, asking for the last one (transient local).
    late = rclpy.create_node('late_tool', namespace=ros.namespace, context=ros.context)
    ros.spin(late)
    received = {}
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    for topic in ('estimate', 'estimate_std', 'estimate_covariance'):
        late.create_subscription(
            Float64MultiArray, f'{ros.namespace}/ctid_node/{topic}',
            lambda message, topic=topic: received.setdefault(topic, message), latched)
    late.create_subscription(Float64, f'{ros.namespace}/ctid_node/params/K',
                             lambda message: received.setdefault('K', message), latched)
    wait_for(lambda: len(received) == 4, 60.0, lambda: f'latched messages: {sorted(received)}')
    assert named(received['estimate']) == dict(zip(published.names, published.values))
    assert named(received['estimate_std']) == dict(zip(published.names, published.stds))
    assert received['K'].data == published.values[0]
    covariance = received['estimate_covariance']
    assert [(dim.label, dim.size, dim.stride) for dim in covariance.layout.dim] == [
        ('K,T', 2, 4), ('K,T', 2, 2)]
    matrix = np.reshape(covariance.data, (2, 2))
    np.testing.assert_allclose(np.sqrt(np.diag(matrix)), published.stds, rtol=1e-12)
    assert matrix[0, 1] == pytest.approx(matrix[1, 0], rel=1e-9)


def test_joint_names_live_integer_doubles_and_hardware_id(ros):
    truth = {'J': 0.2, 'b': 1.0, 'k': 4.0}
    ros.plant(model='1/(J*s**2 + b*s + k)', parameter_names=['J', 'b', 'k'],
              parameter_values=[0.2, 1.0, 4.0], sample_time=0.01, message_type='joint_state',
              joint_state_topic='joint_states', joint_names=['wheel_right', 'arm', 'wheel_left'])
    # Integers for doubles (window: 5, sample_time given as 0.01), as a hand-written file has.
    node = ros.identifier(input_topic='joint_states', input_field='effort[wheel_left]',
                          output_topic='joint_states', output_field='position[wheel_left]',
                          model='1/(J*s**2 + b*s + k)', parameter_names=['J', 'b', 'k'],
                          sample_time=0.01, window=5, update_period=1, max_gap=0.1,
                          hardware_id='left_wheel_drive')
    assert (node.config.window, node.config.update_period) == (5.0, 1.0)
    converge(ros, truth, {'J': 0.004, 'b': 0.02, 'k': 0.04}, timeout=60.0)
    status = ros.latest(ros.statuses)
    assert status.hardware_id == 'left_wheel_drive'
    assert keys(status)['output_field_errors'] == '0'
    # A joint that is not in the messages: the names seen are on /diagnostics.
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter('output_field', value='position[wheel_lft]'),
                                    Parameter('update_period', value=2)])
    wait_for(future.done, 30.0, 'set_parameters')
    assert all(result.successful for result in future.result().results)
    assert node.config.update_period == 2.0
    wait_for(lambda: "output: field position[wheel_lft]: no joint 'wheel_lft' in name; names "
             'seen: wheel_right, arm, wheel_left' in ros.latest(ros.statuses).message, 20.0,
             lambda: ros.latest(ros.statuses).message)
    assert ros.latest(ros.statuses).level == DiagnosticStatus.WARN
    assert int(keys(ros.latest(ros.statuses))['output_field_errors']) > 0


def test_help_prints_usage_instead_of_starting():
    for module, expected in (('ctid_ros.ros.node', 'lifecycle (bool, read-only, default False)'),
                             ('ctid_ros.ros.plant_node', 'joint_names (default')):
        done = subprocess.run([sys.executable, '-m', module, '--help'], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        assert done.stdout.startswith('usage: ctid_') and expected in done.stdout
    done = subprocess.run([sys.executable, '-m', 'ctid_ros.ros.node', '--params-file', 'x.yaml'],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert 'ROS arguments go after --ros-args' in done.stderr


@pytest.mark.ros
def test_a_field_no_published_type_has_is_refused_and_the_estimates_go_on(ros):
    """
    ``output_field: point.w`` at run time, with PointStamped published: refused, kept.

    Accepted, it left the node subscribed to nothing (no type fits) and estimating nothing,
    while the publishers went on; a path the type has (``point.y``) is still accepted.
    """
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[2.0, 0.5],
              message_type='point_stamped')
    node = ros.identifier(input_topic='u', output_topic='y', input_field='point.x',
                          output_field='point.x', model='K/(T*s + 1)', parameter_names=['K', 'T'],
                          sample_time=0.005, window=4.0, update_period=1.0,
                          qos_reliability='reliable')
    wait_for(lambda: len(ros.estimates) >= 1, 60.0, 'a first estimate')
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)

    def set_parameter(name, value):
        future = client.set_parameters([Parameter(name, value=value)])
        wait_for(future.done, 30.0, 'set_parameters')
        return future.result().results[0]

    result = set_parameter('output_field', 'point.w')
    assert not result.successful
    assert result.reason == (
        f'no type published on {ros.namespace}/y has the field(s) point.w: '
        "geometry_msgs/msg/PointStamped: Point has no field 'w'; its fields: x, y, z; the node "
        'keeps reading point.x and point.x'), result.reason
    assert node.config.output_field == 'point.x'
    count = len(ros.estimates)
    wait_for(lambda: len(ros.estimates) >= count + 2, 60.0, 'estimates after the refusal')
    assert keys(ros.latest(ros.statuses))['rejected_parameters'] == '1'
    assert set_parameter('output_field', 'point.y').successful
    assert node.config.output_field == 'point.y'
