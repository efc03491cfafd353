"""
The live identification node ``ctid_node``: ROS in, :class:`IdentificationSession` in the middle.

The node is one class assembled from one part per concern, each in a file of its own:

* :mod:`ctid_ros.ros.topics`: which type to read each input topic as, the subscriptions and the
  samples they bring (:class:`~ctid_ros.ros.topics.TopicIntake`);
* :mod:`ctid_ros.ros.parameters`: the parameters declared from one table
  (:mod:`ctid_ros.ros.parameter_table`, importable without rclpy), read at configure and
  followed at runtime (:class:`~ctid_ros.ros.parameters.ParameterHandling`);
* :mod:`ctid_ros.ros.estimating` and :mod:`ctid_ros.ros.worker`: the estimates, computed in a
  thread of their own beside the executor, and the alarm's services;
* :mod:`ctid_ros.ros.output`: the publishers, estimates, alarm and ``/diagnostics``;
* this module: the node's state and its life (the lifecycle transitions), and :func:`main`;
  :mod:`ctid_ros.ros.runner` spins it as a process.

Robustness (issue #16): no exception leaves a callback (subscriptions, timers, services,
parameter and lifecycle callbacks, the estimation thread): each is caught, counted
(``internal_errors``), logged and reported on ``/diagnostics``.

Managed (lifecycle) node with ``lifecycle: true``: it starts unconfigured with the standard
services (``~/change_state``, ``~/get_state``, ...); ``configure`` validates the parameters
and builds the buffer, publishers and services, ``activate`` subscribes and starts the timers,
``deactivate`` stops them, ``cleanup`` clears the buffer and removes the publishers, and
``shutdown`` finalises from any state. With ``lifecycle: false`` (default) the node configures
and activates itself at start-up and has no lifecycle services.

Change alarm: the baseline comes from :func:`~ctid_ros.streaming.baseline.configured_baseline`
(``baseline_file`` if it exists, else ``baseline.<name>``); the per-parameter parameters
(``baseline.<name>``, ``baseline_std.<name>``, ``min_relative_change.<name>``) are declared once
the model is known, so a params file's ``baseline: {J: 0.05}`` reaches them. A runtime change
keeps the alarm's sums and baseline unless it changes the parameters' names (a new model) or
the baseline.
"""

import functools
import math
import sys
import threading
from typing import Any, Callable, Dict, List, Optional, Tuple

from ctid_ros.errors import ConfigError, DataError
from ctid_ros.ros.estimating import Estimating
from ctid_ros.ros.output import output_topics, Publishers, Reporting
from ctid_ros.ros.parameter_table import node_usage, wrap_text
from ctid_ros.ros.parameters import (declare_parameters, parameter_value, ParameterHandling,
                                     VALIDATION_TIMEOUT)
from ctid_ros.ros.runner import run_node
from ctid_ros.ros.topics import Counters, TOPIC_CHECK_PERIOD, TopicIntake
from ctid_ros.ros.worker import EstimationWorker
from ctid_ros.streaming.alarm import ChangeDetector
from ctid_ros.streaming.baseline import Baseline, configured_baseline
from ctid_ros.streaming.buffer import SampleBuffer
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import (alarm_message, DEFAULT_NODE_NAME, estimate_messages,
                                         NodeTopics, OK)
from ctid_ros.streaming.sampler import MessageSampler
from ctid_ros.streaming.session import IdentificationSession, Update
from lifecycle_msgs.srv import ChangeState
import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.node import LifecycleNodeMixin
from rclpy.node import Node
from std_srvs.srv import Trigger

__all__ = ['IdentificationNode', 'SHUTDOWN_GRACE', 'TOPIC_CHECK_PERIOD', 'VALIDATION_TIMEOUT',
           'main', 'node_usage', 'parameter_value', 'run_node', 'wrap_text']

# Seconds an estimate in progress at the exit may take to finish and be published.
SHUTDOWN_GRACE = 0.5
_SUCCESS = TransitionCallbackReturn.SUCCESS
_FAILURE = TransitionCallbackReturn.FAILURE


class IdentificationNode(TopicIntake, ParameterHandling, Estimating, Reporting, LifecycleNode):
    """
    Identify a grey-box model from two live topics; publish estimates and diagnostics.

    A managed node with ``lifecycle: true`` (see the module docstring); otherwise it is
    configured and active as soon as it is constructed.

    Raises
    ------
    ConfigError
        With ``lifecycle: false``, if the parameters are invalid.

    """

    def __init__(self, **kwargs):
        Node.__init__(self, DEFAULT_NODE_NAME, **kwargs)
        declare_parameters(self)
        self._lock = threading.RLock()                # references below, counters
        self._estimation_lock = threading.Lock()      # the session: one estimate at a time
        self._validating: List[threading.Thread] = []
        # What a configuration builds (None while unconfigured).
        self._config: Optional[IdentificationConfig] = None
        self._session: Optional[IdentificationSession] = None
        self._detector: Optional[ChangeDetector] = None
        self._sampler: Optional[MessageSampler] = None
        self._buffer: Optional[SampleBuffer] = None
        # A baseline set by a runtime parameter change, for the next estimate to take up.
        self._pending_baseline: Optional[Tuple[Optional[Baseline], str]] = None
        # Input (ctid_ros.ros.topics).
        self._counters = Counters()
        self._topic_subscriptions: Dict[str, Tuple[Any, str]] = {}
        self._sample_group = ReentrantCallbackGroup()
        self._origin_ns: Optional[int] = None
        # Output (ctid_ros.ros.output): notes shown on /diagnostics, what was logged once.
        self._node_topics = NodeTopics(self.get_fully_qualified_name())
        self._outputs = Publishers(self, lambda: (self._config is not None, self._active))
        self._notes: Dict[str, str] = {}
        self._logged: Dict[str, str] = {}
        self._last_info = -math.inf
        self._internal_errors = 0
        self._last_internal_error = ''
        self._rejected_parameters = 0
        self._last_rejected_parameter = ''
        # Life: services and timers of a configuration, the state.
        self._own_services: List[Any] = []
        self._own_timers: List[Any] = []
        self._active = False
        self._transition_error = ''
        self._estimated_since_start = False
        self._estimates_since_comparison = 0
        self.last_update: Optional[Update] = None
        self._estimation_group = MutuallyExclusiveCallbackGroup()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._worker = EstimationWorker(self.estimate, lambda: self._active,
                                        self._internal_error)
        self._managed = bool(parameter_value(self, 'lifecycle', False))
        LifecycleNodeMixin.__init__(self, enable_communication_interface=self._managed,
                                    callback_group=MutuallyExclusiveCallbackGroup())
        if self._managed:
            service = self._service_change_state
            service.callback = functools.partial(self._change_state, service.callback)
        else:
            self._start()

    def _start(self) -> None:
        """Configure and activate at once (``lifecycle: false``); raise what went wrong."""
        for transition in (self.trigger_configure, self.trigger_activate):
            if transition() != _SUCCESS:
                error = self._transition_error or 'the node could not start'
                # Never spun nor returned: its thread and handles end here, so the context
                # (and its DDS participant) can end before the process exits.
                self.destroy_node()
                raise ConfigError(error)

    @property
    def config(self) -> Optional[IdentificationConfig]:
        """Return the configuration in use, None while unconfigured."""
        return self._config

    @property
    def detector(self) -> Optional[ChangeDetector]:
        """Return the change alarm's detector with its baseline and status; None unconfigured."""
        return self._detector

    @property
    def buffer(self) -> Optional[SampleBuffer]:
        """Return the sample buffer, None while unconfigured."""
        return self._buffer

    @property
    def active(self) -> bool:
        """Return True while the node subscribes and estimates."""
        return self._active

    # Lifecycle -----------------------------------------------------------------------------

    def _change_state(self, change_state: Callable[[Any, Any], Any],
                      request: ChangeState.Request, response: ChangeState.Response
                      ) -> ChangeState.Response:
        """
        Answer ``~/change_state`` through rclpy's ``change_state``, refusing what it cannot take.

        rclpy (the Jazzy wheel) raises ``RCLError: Transition is not registered`` out of the
        service for a transition id that is invalid in the current state (``4`` while
        inactive), which ends the node; a label is checked. Here an id is checked against the
        available transitions first, and any exception is answered with ``success=False``.
        """
        try:
            transition = request.transition
            available = {description[0]: description[1]
                         for description in self._state_machine.available_transitions}
            if transition.label or transition.id in available:
                return change_state(request, response)
            state = self._state_machine.current_state[1]
            self.get_logger().warning(
                f'~/change_state: transition id {transition.id} is not available in state '
                f'{state!r} (available: ' + ', '.join(
                    f'{number} {label}' for number, label in sorted(available.items()))
                + '); refused')
        except Exception as error:  # noqa: B902 - a service must answer, the node run on
            self._internal_error('change_state', error)
        response.success = False
        return response

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Validate the parameters; build the buffer, session, publishers and services."""
        try:
            config = self._read_config()
            sampler = self._new_sampler(config)
            buffer = self._new_buffer(config, sampler)
            baseline, note = configured_baseline(config, self.get_fully_qualified_name())
        except (ConfigError, DataError, MemoryError, ParameterException) as error:
            return self._transition_failed('configure', error)
        except Exception as error:  # noqa: B902 - a bug must not escape a transition
            self._internal_error('configure', error)
            return self._transition_failed('configure', error)
        with self._lock:
            self._config, self._sampler, self._buffer = config, sampler, buffer
            self._session = IdentificationSession(config)
            self._detector = ChangeDetector.from_config(config, baseline)
            self._pending_baseline = None
            self._restart_counters()
        try:
            # The fixed topics exist from configure on, so subscribers can match early.
            for message in estimate_messages(self._node_topics, (), (), (), (),
                                             covariance=np.empty((0, 0))):
                self._outputs.ensure(message)
            self._own_services = [
                self.create_service(Trigger, '~/reset', self._reset,
                                    callback_group=self._estimation_group),
                self.create_service(Trigger, '~/estimate_now', self._estimate_now,
                                    callback_group=self._estimation_group),
                self.create_service(Trigger, '~/capture_baseline', self._capture_baseline,
                                    callback_group=self._estimation_group)]
            self._outputs.ensure(alarm_message(self._node_topics, OK, '', {}))
        except Exception as error:  # noqa: B902 - a bug must not escape a transition
            self._internal_error('configure', error)
            self._teardown()
            return self._transition_failed('configure', error)
        self.get_logger().info(f'configured: model {config.model!r}, window {config.window:g} s '
                               f'on a {config.sample_time:g} s grid, an estimate every '
                               f'{config.update_period:g} s')
        self.get_logger().info(self._baseline_line(baseline, note))
        return _SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Enable the publishers, subscribe and start the timers."""
        try:
            super().on_activate(state)
            self._active = True
            self._own_timers = [self._create_update_timer(), self.create_timer(
                TOPIC_CHECK_PERIOD, self._connect, callback_group=self._sample_group)]
            self._connect()
        except Exception as error:  # noqa: B902 - a bug must not escape a transition
            self._internal_error('activate', error)
            self._stop_activity()
            return self._transition_failed('activate', error)
        self._publish_status(OK, 'active: waiting for data', {})
        self._publish_alarm(self._detector.status)
        return _SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the subscriptions and timers; the buffer and the warm start are kept."""
        self._publish_status(OK, 'inactive: deactivated', {})
        self._stop_activity()
        super().on_deactivate(state)
        return _SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Clear the buffer and the warm start; remove publishers and services."""
        self._teardown()
        return _SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop everything, from whatever state."""
        self._stop_activity()
        self._teardown()
        return _SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Recover to unconfigured after a failed transition."""
        self._stop_activity()
        self._teardown()
        return _SUCCESS

    def _transition_failed(self, transition: str, error: BaseException
                           ) -> TransitionCallbackReturn:
        self._transition_error = str(error)
        self.get_logger().error(f'{transition} failed: {error}')
        return _FAILURE

    def _stop_activity(self) -> None:
        self._active = False
        for timer in self._own_timers:
            self.destroy_timer(timer)
        self._own_timers = []
        self._unsubscribe_all()
        with self._lock:
            self._notes = {}

    def _teardown(self) -> None:
        with self._estimation_lock, self._lock:
            self._config = self._session = self._sampler = self._buffer = None
            self._detector = self._pending_baseline = None
            self.last_update = None
        self._outputs.keep_only(())
        for service in self._own_services:
            self.destroy_service(service)
        self._own_services = []

    def _restart_counters(self) -> None:
        self._counters = Counters()
        self._logged = {}
        self._origin_ns = None
        self._estimated_since_start = False
        self._worker.skipped_since_estimate = 0

    def _new_sampler(self, config: IdentificationConfig) -> MessageSampler:
        return MessageSampler(config, (self.resolve_topic_name(config.input_topic),
                                       self.resolve_topic_name(config.output_topic)))

    @staticmethod
    def _new_buffer(config: IdentificationConfig, sampler: MessageSampler,
                    previous: Optional[SampleBuffer] = None) -> SampleBuffer:
        # Sized and limited by the configuration (MAX_BUFFER_BYTES) before it is allocated.
        return sampler.buffer(config.buffer_capacity(), config, previous=previous)

    def _create_update_timer(self):
        return self.create_timer(self._config.update_period, self._worker.tick,
                                 callback_group=self._estimation_group)

    def _restart_update_timer(self) -> None:
        """Follow a new ``update_period`` (while active)."""
        self.destroy_timer(self._own_timers[0])
        self._own_timers[0] = self._create_update_timer()

    def _follow_outputs(self, config: IdentificationConfig) -> None:
        """Remove the publishers of topics ``config`` has no more (``~/params/<old name>``)."""
        self._outputs.keep_only(output_topics(self._node_topics, config))

    def destroy_node(self) -> None:
        """
        Stop the estimation thread, then destroy the node and its lifecycle state machine.

        An estimate in progress gets :data:`SHUTDOWN_GRACE` seconds to finish and be
        published; after that it is abandoned (it publishes nothing more), so that a signal
        ends the process at once whatever the estimate costs.
        """
        self._active = False
        if not self._worker.stop(SHUTDOWN_GRACE):
            self.get_logger().warning('exiting during an estimate: its result is not published')
        self._outputs.close()
        super().destroy_node()
        # rclpy's LifecycleNode leaves its state machine to the garbage collector, whose
        # finaliser crashes a forked child (multiprocessing) that collects it: end it here.
        self._state_machine.destroy_when_not_in_use()


def main(args: Optional[List[str]] = None) -> int:
    """Run ``ctid_node`` until Ctrl-C or SIGTERM; return the exit status."""
    return run_node(IdentificationNode, DEFAULT_NODE_NAME, args, node_usage)


if __name__ == '__main__':
    sys.exit(main())
