"""
ctid_node follows what changes under it on real DDS: a topic's type, the model, the window.

Issue #25: a publisher switching Float64 -> Float32 left the node refused by Fast DDS (the new
subscription was created before the old one was destroyed); ``~/params/J`` stayed advertised
after the model lost J; the declarations of a new model's per-parameter values logged
"configuration updated: the same values" several times; a runtime ``window`` change threw the
buffered data away.
"""

import threading
import time

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from node_harness import converge, keys, named, wait_for
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float32, Float64

TRUTH = {'K': 2.0, 'T': 0.5}


def parameters(**extra):
    values = {'input_topic': 'u', 'output_topic': 'y', 'model': 'K/(T*s + 1)',
              'initial': [1.0, 1.0], 'lower': [0.001, 0.01],
              'upper': [100.0, 100.0], 'sample_time': 0.01, 'window': 4.0,
              'update_period': 0.5, 'qos_reliability': 'reliable'}
    values.update(extra)
    return values


class Publisher:
    """
    Publish a simulated first-order plant's u and y at 100 Hz from a thread of the test.

    The messages carry no header: the node stamps them with their DDS source timestamps,
    taken when they are published on the sample instants.
    """

    def __init__(self, ros, message_class, seed):
        # A context of its own, as another process: one DDS participant holds one type per
        # topic, also after its publishers of another type are gone.
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f'plant_{seed}', namespace=ros.namespace,
                                      context=self.context)
        self.publishers = {topic: self.node.create_publisher(message_class, topic, 1000)
                           for topic in 'uy'}
        self.message_class = message_class
        count, ts = 6000, 0.01
        self.ts = ts
        u = np.resize(prbs(10, 8), count)
        noise = 0.005 * np.random.default_rng(seed).standard_normal(count)
        self.samples = list(zip(u, Model('K/(T*s + 1)').simulate(TRUTH, u, ts) + noise))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self):
        self._thread.start()
        return self

    def _run(self):
        start = time.monotonic()
        for k, (u, y) in enumerate(self.samples):
            delay = start + k * self.ts - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            self.publishers['u'].publish(self.message_class(data=float(u)))
            self.publishers['y'].publish(self.message_class(data=float(y)))

    def stop(self):
        self._stop.set()
        self._thread.join(timeout=10)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def set_parameter(ros, name, value):
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter(name, value=value)])
    wait_for(future.done, 30.0, f'set {name}')
    result = future.result().results[0]
    assert result.successful, result.reason


def test_a_topic_that_changes_type_is_followed(ros):
    node = ros.identifier(**parameters())
    tolerance = {'K': 0.1, 'T': 0.05}
    first = Publisher(ros, Float64, seed=1).start()
    try:
        converge(ros, TRUTH, tolerance, timeout=60.0)
    finally:
        first.stop()
    reading = {topic: f'{ros.namespace}/{topic}' for topic in 'uy'}
    wait_for(lambda: not ros.observer.count_publishers(reading['y']), 30.0, 'Float64 gone')
    count = len(ros.estimates)
    second = Publisher(ros, Float32, seed=2).start()
    try:
        wait_for(lambda: all(node._topic_subscriptions.get(topic, (None, ''))[1] ==
                             'std_msgs/msg/Float32' for topic in reading.values()), 30.0,
                 lambda: f'subscriptions {node._topic_subscriptions}')
        # Estimates from the Float32 messages: a whole window of them after the switch.
        received = node.buffer.stats().y.received
        wait_for(lambda: node.buffer.stats().y.received > received + 450, 60.0,
                 'Float32 samples')
        count = len(ros.estimates)
        wait_for(lambda: len(ros.estimates) > count, 60.0, 'an estimate from Float32')
        converge(ros, TRUTH, tolerance, timeout=60.0)
    finally:
        second.stop()
    assert node._internal_errors == 0, node._last_internal_error


def test_advertised_topics_follow_the_model_and_same_values_are_not_logged(ros, capfd):
    node = ros.identifier(**parameters(model='K/(J*s + 1)'))
    publisher = Publisher(ros, Float64, seed=3).start()
    params = f'{ros.namespace}/ctid_node/params'
    try:
        wait_for(lambda: ros.observer.count_publishers(f'{params}/J') == 1, 60.0,
                 'params/J advertised after an estimate')
        capfd.readouterr()
        set_parameter(ros, 'model', 'K/(T*s + 1)')
        wait_for(lambda: ros.observer.count_publishers(f'{params}/J') == 0, 30.0,
                 'params/J removed')
        wait_for(lambda: ros.observer.count_publishers(f'{params}/T') == 1, 60.0,
                 'params/T advertised')
        wait_for(lambda: 'T' in named(ros.latest(ros.estimates)), 60.0, 'estimates of T')
        converge(ros, TRUTH, {'K': 0.1, 'T': 0.05}, timeout=60.0)
    finally:
        publisher.stop()
    log = capfd.readouterr().err
    assert log.count('configuration updated: ') == 1, log
    assert 'configuration updated: model' in log and 'the same values' not in log
    assert node.has_parameter('baseline.T')


def test_a_window_change_keeps_the_data_that_fit(ros):
    # Stamped at the sample instants by a plant process: exact data, tight tolerances.
    ros.spawn_plant(model='K/(T*s + 1)', parameter_names=['K', 'T'],
                    parameter_values=[2.0, 0.5], message_type='point_stamped')
    node = ros.identifier(**parameters(window=4.0, sample_time=0.005, input_field='point.x',
                                       output_field='point.x'))
    tolerance = {'K': 0.02, 'T': 0.01}
    converge(ros, TRUTH, tolerance, timeout=60.0)
    wait_for(lambda: span(node) > 4.0, 30.0, 'a full window buffered')
    set_parameter(ros, 'window', 3.0)
    # The new buffer holds the newest data at once: a whole window of the new size.
    assert node.config.window == 3.0
    assert span(node) >= 3.0, span(node)
    # The first estimate after the change has its whole window.
    wait_for(lambda: keys(ros.latest(ros.statuses)).get('window') == '3.0', 30.0,
             lambda: f'an estimate on 3 s windows: {ros.latest(ros.statuses)}')
    status = ros.latest(ros.statuses)
    assert 'warming up' not in status.message, status.message
    converge(ros, TRUTH, tolerance, timeout=30.0)


def span(node):
    first, last = node.buffer.coverage()
    return (last - first) / 1e9


def test_a_model_with_other_parameters_changes_in_one_atomic_update(ros):
    """
    A single ``model`` set fails against the old parameter_names and says how; atomic works.

    ``ros2 param set`` changes one parameter at a time: with parameter_names, initial, lower
    and upper given per parameter (as every shipped params file does), a new model's names
    fail against the old ones.
    """
    ros.identifier(**parameters(model='K/(J*s + 1)', parameter_names=['K', 'J']))
    publisher = Publisher(ros, Float64, seed=5).start()
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    try:
        assert client.wait_for_services(timeout_sec=30.0)
        future = client.set_parameters([Parameter('model', value='K/(T*s + 1)')])
        wait_for(future.done, 30.0, 'set model alone')
        alone = future.result().results[0]
        assert not alone.successful
        assert alone.reason.startswith('parameter_names must be a permutation')
        assert 'set model with parameter_names, initial, lower, upper in one atomic update' in \
            alone.reason, alone.reason
        future = client.set_parameters_atomically(
            [Parameter('model', value='K/(T*s + 1)'),
             Parameter('parameter_names', value=['T', 'K']),
             Parameter('initial', value=[1.0, 1.0]),
             Parameter('lower', value=[0.01, 0.001]),
             Parameter('upper', value=[100.0, 100.0])])
        wait_for(future.done, 30.0, 'set model atomically')
        together = future.result().result
        assert together.successful, together.reason
        wait_for(lambda: ros.latest(ros.estimates) is not None and
                 list(named(ros.latest(ros.estimates))) == ['T', 'K'], 60.0,
                 'estimates of T, K in the new order')
        converge(ros, TRUTH, {'K': 0.1, 'T': 0.05}, timeout=60.0)
    finally:
        publisher.stop()
