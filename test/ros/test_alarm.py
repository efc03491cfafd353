"""
The change alarm of ctid_node live on real DDS: a plant whose inertia steps, ~/alarm, capture.

The plant is the demo's wheel drive (config/wheel_demo_plant.yaml) under its digital PI, header
stamped, in this process; the node has the demo's configuration with the data-sheet baseline
given as a params-file mapping. Windows of 4 s every 2 s, so the stationary part gives a few
windows and the step is seen within a few more.
"""

import math

from ctid_ros.streaming.params_file import find_config, load_params_file
from diagnostic_msgs.msg import DiagnosticStatus
from node_harness import keys, wait_for
import pytest
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger
import yaml

pytestmark = pytest.mark.ros

STEP_TIME = 14.0


def wheel_plant(ros, **changes):
    values = yaml.safe_load(find_config('wheel_demo_plant').read_text())['ctid_plant'][
        'ros__parameters']
    values.update(input_topic='r', output_topic='y', control_topic='u', **changes)
    return ros.plant(**values)


def wheel_node(ros, **changes):
    config = load_params_file(find_config('wheel_demo')).to_dict()
    parameters = {key: value for key, value in config.items()
                  if '.' not in key and value != [] and key != 'lifecycle'}
    parameters.update(input_topic='u', output_topic='y', initial=[math.nan] * 3,
                      baseline={'J': 0.05, 'b': 0.2, 'tau': 0.0373}, **changes)
    return ros.identifier(**parameters)


def listen(ros):
    """Subscribe to the node's ~/alarm as a late-joining tool would (transient local)."""
    received = []
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros.observer.create_subscription(DiagnosticStatus, f'{ros.namespace}/ctid_node/alarm',
                                     received.append, qos)
    return received


def test_a_step_of_the_plant_raises_the_alarm_and_a_capture_survives_a_restart(ros, tmp_path):
    baseline_file = tmp_path / 'wheel_baseline.yaml'
    node = wheel_node(ros, baseline_file=str(baseline_file))
    alarms = listen(ros)
    plant = wheel_plant(ros, drift_time=STEP_TIME, drift_values=[0.06, 0.2, 0.0373])
    start_ns = plant.start_ns

    def raised():
        return any(alarm.level == DiagnosticStatus.ERROR for alarm in alarms)

    wait_for(raised, 60.0, lambda: [(alarm.level, alarm.message) for alarm in alarms])
    first = next(alarm for alarm in alarms if alarm.level == DiagnosticStatus.ERROR)
    values = keys(first)
    assert first.name == f'{ros.namespace[1:]}/ctid_node: alarm'
    assert values['parameters'] == 'J' and first.message.startswith('changed: J +')
    assert float(values['J.relative_change']) == pytest.approx(0.2, abs=0.03)
    assert float(values['J.change_low']) < float(values['J.change']) < \
        float(values['J.change_high'])
    # Raised within three update periods of the step, dated just before it.
    window_end = float(values['window_end']) - start_ns / 1e9
    assert STEP_TIME < window_end <= STEP_TIME + 3 * 2.0 + 0.5
    assert STEP_TIME - 2.5 < float(values['since_stamp']) - start_ns / 1e9 <= STEP_TIME + 0.5
    # Before it every alarm status was OK, after estimates had come.
    before = alarms[:alarms.index(first)]
    assert before and all(alarm.level == DiagnosticStatus.OK for alarm in before)
    assert any(alarm.message.startswith('no change beyond the thresholds') for alarm in before)
    # The node's status on /diagnostics carries the alarm's level and message.
    wait_for(lambda: any(status.level == DiagnosticStatus.ERROR and
                         keys(status).get('alarm') == 'ERROR' for status in ros.statuses),
             20.0, 'the alarm in /diagnostics')

    # Accept the new payload: capture it as the baseline once five windows hold only data
    # from after the step; the file is a params file.
    settled = start_ns + round((STEP_TIME + 4.1) * 1e9)
    wait_for(lambda: sum(end > settled for end in node.detector.recent_ends()) >= 5, 60.0,
             'five windows after the step')
    answer = ros.call(Trigger, f'{ros.namespace}/ctid_node/capture_baseline', Trigger.Request())
    assert answer.success, answer.message
    assert f'saved to {baseline_file}' in answer.message and 'warning' not in answer.message
    saved = yaml.safe_load(baseline_file.read_text())[f'{ros.namespace}/ctid_node'][
        'ros__parameters']
    assert saved['baseline']['J'] == pytest.approx(0.06, rel=0.02)
    assert set(saved['baseline_std']) == {'J', 'b', 'tau'}
    wait_for(lambda: alarms[-1].level == DiagnosticStatus.OK, 60.0,
             lambda: alarms[-1].message)
    assert keys(alarms[-1])['baseline'].startswith('captured from 5 windows')

    # A runtime baseline (the old data sheet) raises the alarm again.
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter('baseline.J', value=0.05)])
    wait_for(future.done, 30.0, 'set_parameters')
    assert future.result().results[0].successful
    wait_for(lambda: alarms[-1].level == DiagnosticStatus.ERROR and
             keys(alarms[-1])['baseline'] == 'params file', 30.0, lambda: alarms[-1].message)
    future = client.set_parameters([Parameter('baseline.J', value=-1.0),
                                    Parameter('min_relative_change.J', value=-0.5)])
    wait_for(future.done, 30.0, 'set_parameters')
    refused = future.result().results[1]
    assert not refused.successful and 'min_relative_change.J must be between 0' in refused.reason

    # A restart reads the captured baseline from its file.
    node.destroy_node()
    restarted = wheel_node(ros, baseline_file=str(baseline_file))
    assert restarted.detector.baseline.source == f'baseline_file {baseline_file}'
    assert restarted.detector.baseline.value('J') == pytest.approx(0.06, rel=0.02)


def test_reset_keeps_the_baseline_and_a_broken_baseline_file_is_refused(ros, tmp_path):
    node = wheel_node(ros)
    wheel_plant(ros)
    wait_for(lambda: node.detector is not None and node.detector.windows >= 2, 60.0,
             'two windows')
    answer = ros.call(Trigger, f'{ros.namespace}/ctid_node/capture_baseline', Trigger.Request())
    assert not answer.success and 'baseline_windows is 5' in answer.message
    answer = ros.call(Trigger, f'{ros.namespace}/ctid_node/reset', Trigger.Request())
    assert answer.success
    assert node.detector.windows == 0 and node.detector.baseline.source == 'params file'
    broken = tmp_path / 'broken.yaml'
    broken.write_text('ctid_node:\n  ros__parameters:\n    baseline: {J: .inf}\n')
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter('baseline_file', value=str(broken))])
    wait_for(future.done, 30.0, 'set_parameters')
    result = future.result().results[0]
    assert not result.successful and 'baseline.J must be a finite number' in result.reason
    assert node.config.baseline_file == ''


def test_a_new_model_gets_its_per_parameter_parameters(ros):
    node = ros.identifier(input_topic='u', output_topic='y', model='K/(T*s + 1)',
                          baseline={'K': 2.0, 'T': 0.5}, min_relative_change={'T': 0.1})
    assert node.get_parameter('baseline.K').value == 2.0
    assert math.isnan(node.get_parameter('baseline_std.T').value)
    assert node.detector.baseline.names == ('K', 'T')
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter('model', value='K/(T2*s + 1)')])
    wait_for(future.done, 30.0, 'set_parameters')
    assert future.result().results[0].successful, future.result().results[0].reason
    assert node.has_parameter('baseline.T2') and node.has_parameter('min_relative_change.T2')
    assert node.config.per_parameter == (('baseline.K', 2.0),)
    future = client.set_parameters([Parameter('baseline.T2', value=0.7)])
    wait_for(future.done, 30.0, 'set_parameters')
    assert future.result().results[0].successful, future.result().results[0].reason
    assert node.config.per_parameter_values('baseline') == {'K': 2.0, 'T2': 0.7}
    # The detector takes the new names and baseline at the next estimate.
    node.estimate()
    assert node.detector.settings.names == ('K', 'T2')
    assert node.detector.baseline.names == ('K', 'T2')
