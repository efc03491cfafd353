"""
ctid_node as a managed (lifecycle) node, driven through its lifecycle services on real DDS.

``lifecycle: true``: the node starts unconfigured; the transitions are requested as a lifecycle
manager (nav2's) requests them, through ``~/change_state`` from another node, and the state is
read back through ``~/get_state``. What each state may do is checked on the graph: publishers
only from configure, subscriptions only while active, the buffer gone after cleanup.
"""

import math
import signal

from ctid_ros.errors import ConfigError
from ctid_ros.ros.node import IdentificationNode
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from node_harness import converge, keys, NodeProcess, wait_for
import pytest
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_srvs.srv import Trigger

TRUTH = {'K': 2.0, 'T': 0.5}
TOLERANCE = {'K': 0.02, 'T': 0.01}


def parameters(**extra):
    values = {'input_topic': 'u', 'output_topic': 'y', 'input_field': 'point.x',
              'output_field': 'point.x', 'model': 'K/(T*s + 1)', 'parameter_names': ['K', 'T'],
              'initial': [1.0, 1.0], 'lower': [0.001, 0.01], 'upper': [100.0, 100.0],
              'sample_time': 0.005, 'window': 4.0, 'update_period': 1.0,
              'qos_reliability': 'reliable', 'lifecycle': True}
    values.update(extra)
    return values


class Manager:
    """Request transitions and read the state, as a lifecycle manager does."""

    def __init__(self, ros):
        self.ros = ros
        self.node = f'{ros.namespace}/ctid_node'

    def change(self, transition_id):
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return self.ros.call(ChangeState, f'{self.node}/change_state', request).success

    def state(self):
        return self.ros.call(GetState, f'{self.node}/get_state', GetState.Request(),
                             repeatable=True).current_state.label

    def subscribers(self, topic):
        return self.ros.observer.count_subscribers(f'{self.ros.namespace}/{topic}')

    def publishers(self, topic):
        return self.ros.observer.count_publishers(f'{self.node}/{topic}')


def test_transitions(ros):
    plant = ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'],
                      parameter_values=[2.0, 0.5], message_type='point_stamped')
    # Invalid in the file: a managed node starts anyway and refuses to configure.
    node = ros.identifier(**parameters(window=0.01))
    manager = Manager(ros)
    assert manager.state() == 'unconfigured'
    assert node.buffer is None and node.config is None
    assert manager.subscribers('u') == manager.subscribers('y') == 0
    assert manager.publishers('estimate') == 0
    # Parameters are validated on configure, not before.
    assert not manager.change(Transition.TRANSITION_CONFIGURE)
    assert manager.state() == 'unconfigured'
    client = AsyncParameterClient(ros.observer, manager.node)
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter('window', value=4)])     # an integer: 4.0
    wait_for(future.done, 30.0, 'set window')
    assert future.result().results[0].successful

    assert manager.change(Transition.TRANSITION_CONFIGURE)
    assert manager.state() == 'inactive'
    assert node.config.window == 4.0 and node.buffer.stats().u.received == 0
    assert manager.publishers('estimate') == manager.publishers('estimate_covariance') == 1
    assert manager.subscribers('u') == manager.subscribers('y') == 0

    assert manager.change(Transition.TRANSITION_ACTIVATE)
    assert manager.state() == 'active'
    wait_for(lambda: manager.subscribers('u') == manager.subscribers('y') == 1, 60.0,
             'subscriptions while active')
    converge(ros, TRUTH, TOLERANCE, timeout=60.0)

    assert manager.change(Transition.TRANSITION_DEACTIVATE)
    assert manager.state() == 'inactive'
    wait_for(lambda: manager.subscribers('u') == manager.subscribers('y') == 0, 60.0,
             'no subscriptions while inactive')
    status = ros.latest(ros.statuses)
    assert status.message == 'inactive: deactivated', status.message
    kept = node.buffer.stats().y.received
    assert kept > 500                             # the buffer survives a deactivation
    count = len(ros.estimates)
    estimate_now = ros.call(Trigger, f'{manager.node}/estimate_now', Trigger.Request())
    assert not estimate_now.success and estimate_now.message == 'the node is not active'

    assert manager.change(Transition.TRANSITION_CLEANUP)
    assert manager.state() == 'unconfigured'
    assert node.buffer is None                    # cleared with everything it held
    wait_for(lambda: manager.publishers('estimate') == 0, 60.0, 'publishers removed')
    assert len(ros.estimates) == count

    # Configure and activate again: a fresh buffer, estimates again.
    published = plant.published
    assert manager.change(Transition.TRANSITION_CONFIGURE)
    assert node.buffer.stats().y.received == 0
    assert manager.change(Transition.TRANSITION_ACTIVATE)
    wait_for(lambda: len(ros.estimates) > count, 30.0, 'estimates after re-activation')
    converge(ros, TRUTH, TOLERANCE, timeout=60.0)
    # Only samples published since the new configuration are counted: the old ones are gone.
    received = int(keys(ros.latest(ros.statuses))['output_received'])
    assert 0 < received <= plant.published - published

    assert manager.change(Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert manager.state() == 'finalized'
    wait_for(lambda: manager.subscribers('y') == 0, 60.0, 'no subscription after shutdown')
    assert node.buffer is None
    assert plant.published > 0


def test_unmanaged_node_has_no_lifecycle_services_and_starts_active(ros):
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[2.0, 0.5],
              message_type='point_stamped')
    node = ros.identifier(**parameters(lifecycle=False, initial=[math.nan, math.nan]))
    assert node.active and node.buffer is not None
    converge(ros, TRUTH, TOLERANCE, timeout=60.0)
    services = dict(ros.observer.get_service_names_and_types())
    assert f'{ros.namespace}/ctid_node/estimate_now' in services
    assert f'{ros.namespace}/ctid_node/change_state' not in services
    # lifecycle is read-only: a running node does not change its kind.
    client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
    assert client.wait_for_services(timeout_sec=30.0)
    future = client.set_parameters([Parameter('lifecycle', value=True)])
    wait_for(future.done, 30.0, 'set lifecycle')
    assert not future.result().results[0].successful


def test_unmanaged_node_refuses_to_start_on_an_invalid_configuration(ros):
    overrides = [Parameter(name, value=value) for name, value in
                 parameters(lifecycle=False, window=5e8).items()]
    with pytest.raises(ConfigError, match='samples per estimate, more than the limit'):
        IdentificationNode(context=ros.context, namespace=ros.namespace,
                           parameter_overrides=overrides)


def test_a_transition_invalid_in_the_state_is_refused_and_the_node_runs_on(ros):
    """Issue #25: rclpy's RCLError for such an id ended the process with status 1."""
    node = NodeProcess(ros, parameters())
    try:
        assert node.state() == 'unconfigured'
        assert not node.change(Transition.TRANSITION_ACTIVATE)
        assert node.change(Transition.TRANSITION_CONFIGURE)
        assert not node.change(Transition.TRANSITION_DEACTIVATE)    # id 4 while inactive
        assert not node.change(99)
        assert not node.change(0, label='no_such_transition')
        assert node.state() == 'inactive'
        assert node.change(Transition.TRANSITION_ACTIVATE)
        assert not node.change(Transition.TRANSITION_ACTIVATE)      # id 3 while active
        assert node.state() == 'active'
        running = node.process.poll() is None
    finally:
        _, status, log = node.stop(signal.SIGTERM)
    assert running and status == 0, log
    assert 'Traceback' not in log and 'RCLError' not in log, log
    assert log.count('is not available in state') == 4, log


@pytest.mark.ros
def test_cleanup_then_configure_reads_new_topics(ros):
    """
    A lifecycle manager moves the node to other topics: cleanup, set them, configure.

    The topics were read-only, so rclpy refused them in every state and only a restart with
    another params file could move the node; now they change while unconfigured, and a
    configured node refuses them with the way to do it.
    """
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[2.0, 0.5],
              message_type='point_stamped')
    ros.plant(model='K/(T*s + 1)', parameter_names=['K', 'T'], parameter_values=[3.0, 0.25],
              message_type='point_stamped', input_topic='u2', output_topic='y2')
    node = ros.identifier(**parameters())
    manager = Manager(ros)
    client = AsyncParameterClient(ros.observer, manager.node)
    assert client.wait_for_services(timeout_sec=30.0)

    def set_topics(input_topic, output_topic):
        future = client.set_parameters([Parameter('input_topic', value=input_topic),
                                        Parameter('output_topic', value=output_topic)])
        wait_for(future.done, 30.0, 'set topics')
        return future.result().results

    assert manager.change(Transition.TRANSITION_CONFIGURE)
    assert manager.change(Transition.TRANSITION_ACTIVATE)
    converge(ros, TRUTH, TOLERANCE, timeout=60.0)
    refused = set_topics('u2', 'y2')[0]
    assert not refused.successful
    assert refused.reason == ('input_topic: read-only while the node is configured; a managed '
                              'node (lifecycle: true) takes a new value between cleanup and '
                              'configure, a plain node at start-up'), refused.reason
    assert node.config.input_topic == 'u'

    assert manager.change(Transition.TRANSITION_DEACTIVATE)
    assert manager.change(Transition.TRANSITION_CLEANUP)
    assert all(result.successful for result in set_topics('u2', 'y2'))
    assert manager.change(Transition.TRANSITION_CONFIGURE)
    assert (node.config.input_topic, node.config.output_topic) == ('u2', 'y2')
    assert manager.change(Transition.TRANSITION_ACTIVATE)
    wait_for(lambda: manager.subscribers('u2') == manager.subscribers('y2') == 1
             and manager.subscribers('u') == manager.subscribers('y') == 0, 60.0,
             'subscribed to the new topics only')
    converge(ros, {'K': 3.0, 'T': 0.25}, {'K': 0.03, 'T': 0.005}, timeout=60.0)
