"""
``tune.controller``: the node tunes a controller on every estimate and latches it on ~/tuning.

Launch-free, on real DDS over loopback (test/node_harness.py). The plant is first order with
dead time, ``K = 2, T = 0.5 s, tau = 0.137 s``, its samples stamped in the headers (exact
sampled data), so the estimate is within a few 0.1 % of the truth and the SIMC PI tuned on
it is that of the true plant (``kp = T / (K (tc + tau))``, ``ki = kp / min(T, 4 (tc + tau))``
with ``tc = tau``) to within a few %.
"""

import json
import math

from ctid_ros.design.tune import tune_from_settings
from diagnostic_msgs.msg import DiagnosticStatus
from node_harness import keys, wait_for
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

TRUTH = {'K': 2.0, 'T': 0.5, 'tau': 0.137}
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def parameters(model, names, tune, **extra):
    """ctid_node parameters for ``model`` on the plant's PointStamped topics u and y."""
    count = len(names)
    values = {'input_topic': 'u', 'output_topic': 'y', 'input_field': 'point.x',
              'output_field': 'point.x', 'model': model, 'parameter_names': names,
              'initial': [1.0, 1.0, math.nan][:count], 'lower': [0.001, 0.01, 0.0][:count],
              'upper': [100.0, 100.0, 1.0][:count], 'sample_time': 0.005, 'window': 6.0,
              'update_period': 1.0, 'qos_reliability': 'reliable'}
    if tune:
        values['tune'] = tune           # (rcl refuses an empty mapping)
    values.update(extra)
    return values


def late_subscriber(ros):
    """Subscribe to ~/tuning from a node started now; return the messages it receives."""
    late = ros.spin(rclpy.create_node('late_tool', namespace=ros.namespace,
                                      context=ros.context))
    received = []
    late.create_subscription(String, f'{ros.namespace}/ctid_node/tuning',
                             lambda message: received.append(json.loads(message.data)), LATCHED)
    return received


def test_a_late_subscriber_gets_the_pi_tuned_on_the_estimate(ros):
    ros.plant(parameter_values=list(TRUTH.values()), sample_time=0.005,
              message_type='point_stamped')
    node = ros.identifier(**parameters('K*exp(-tau*s)/(T*s + 1)', ['K', 'T', 'tau'],
                                       {'controller': 'PI', 'joint': 'wheel'},
                                       update_period=100.0))
    wait_for(lambda: node.buffer.stats().y.span > 6.5, 60.0, 'a window of data')
    response = ros.call(Trigger, f'{ros.namespace}/ctid_node/estimate_now', Trigger.Request())
    assert response.success, response.message
    update = node.last_update
    # Started after the estimate: the recommendation is latched.
    received = late_subscriber(ros)
    wait_for(lambda: received, 60.0, 'no latched message on ~/tuning')
    recommendation = received[-1]
    gains = recommendation['gains']
    assert set(gains) == {'kp', 'ki'}
    assert all(math.isfinite(value) for value in gains.values()) and gains['kp'] > 0
    # The same design as ctid tune's on this estimate, with the node's settings.
    expected = tune_from_settings(update.result, node.config.tune_settings())
    assert gains == pytest.approx(expected.gains.to_dict(), rel=1e-12)
    # SIMC on the true plant, tc = tau.
    K, T, tau = TRUTH.values()
    kp = T / (K * 2 * tau)
    assert gains['kp'] == pytest.approx(kp, rel=0.05)
    assert gains['ki'] == pytest.approx(kp / min(T, 8 * tau), rel=0.05)
    margins = recommendation['margins']
    assert margins['stable'] and 1.0 < margins['ms'] < 2.0
    assert margins['phase_deg'] > 30.0 and margins['gain_db'] > 3.0
    low, high = margins['band']['ms']
    assert low <= margins['ms'] <= high
    assert recommendation['draws'] == 50 and recommendation['unstable_draws'] == 0
    assert recommendation['model'] == 'K*exp(-tau*s)/(T*s + 1)'
    assert 'SIMC PI' in recommendation['method']
    assert 'gains:\n      wheel:\n        p: ' in recommendation['ros2_control']
    # /diagnostics carries the gains.
    wait_for(lambda: 'tuning' in keys(ros.latest(ros.statuses)), 60.0, 'tuning on diagnostics')
    assert keys(ros.latest(ros.statuses))['tuning'].startswith('kp ')


def test_a_design_error_is_reported_and_the_node_runs_on(ros):
    # SIMC's default speed is the dead time: a model without one cannot be tuned by default.
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[2.0, 0.5],
              message_type='point_stamped')
    node = ros.identifier(**parameters('K/(T*s + 1)', ['K', 'T'],
                                       {'controller': 'PI', 'method': 'simc'}, window=4.0))
    status = []

    def failed():
        latest = ros.latest(ros.statuses)
        status[:] = [latest]
        return latest is not None and 'tuning PI failed' in latest.message

    wait_for(failed, 60.0, lambda: f'no tuning error on /diagnostics: {status}')
    assert status[0].level == DiagnosticStatus.WARN
    assert 'no dead time' in status[0].message
    # The node estimates on.
    count = len(ros.estimates)
    wait_for(lambda: len(ros.estimates) > count + 1, 60.0, 'estimates after the error')
    # A target makes the design possible: set at runtime, the tuning follows.
    result = node.set_parameters([Parameter('tune.tc', value=0.2)])
    assert result[0].successful, result[0].reason
    received = late_subscriber(ros)
    wait_for(lambda: received, 60.0, 'no tuning after tune.tc was set')
    assert received[-1]['target'] == {'tc': 0.2} and received[-1]['gains']['kp'] > 0
    wait_for(lambda: 'tuning PI failed' not in ros.latest(ros.statuses).message, 60.0,
             'the tuning error stays on /diagnostics')


def test_candidate_models_are_compared_and_the_simplest_adequate_is_latched(ros):
    fopdt = 'K*exp(-tau*s)/(T*s + 1)'
    sopdt = 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'
    ros.plant(parameter_values=list(TRUTH.values()), sample_time=0.005,
              message_type='point_stamped')
    node = ros.identifier(**parameters(fopdt, ['K', 'T', 'tau'], {}, update_period=100.0,
                                       candidate_models=[fopdt, sopdt], compare_every=1))
    wait_for(lambda: node.buffer.stats().y.span > 6.5, 60.0, 'a window of data')
    response = ros.call(Trigger, f'{ros.namespace}/ctid_node/estimate_now', Trigger.Request(),
                        timeout=120.0)
    assert response.success, response.message
    late = ros.spin(rclpy.create_node('late_models', namespace=ros.namespace,
                                      context=ros.context))
    received = []
    late.create_subscription(String, f'{ros.namespace}/ctid_node/model_recommendation',
                             lambda message: received.append(json.loads(message.data)), LATCHED)
    wait_for(lambda: received, 60.0, 'no latched message on ~/model_recommendation')
    comparison = received[-1]
    # The plant is first order with dead time: the simpler structure is adequate.
    assert comparison['recommended'] == fopdt
    candidates = comparison['candidates']
    assert [item['model'] for item in candidates] == [fopdt, sopdt]
    assert [item['recommended'] for item in candidates] == [True, False]
    assert candidates[0]['params']['K'] == pytest.approx(TRUTH['K'], rel=0.02)
    assert candidates[0]['why']
