"""
The live identification node ``ctid_node``: ROS in, :class:`IdentificationSession` in the middle.

Inputs: the input and output topics of the configuration, one number per message read by a
field path; one subscription serves both when they share a topic. The message type is learnt
from the publishers on the graph and re-checked every :data:`TOPIC_CHECK_PERIOD`: among the
types published on a topic the node takes one whose fields hold the configured paths
(:func:`~ctid_ros.ros.messages.field_problem`), keeps it while it is published, and
resubscribes when only another fitting type is left, so a publisher of a wrong type (a
``std_msgs/String`` on the output topic) can neither capture the subscription nor hide the
right one; the conflict is reported on ``/diagnostics``. Each sample is stamped with
``header.stamp`` (``stamp_source: header`` and a non-zero stamp), else the DDS source timestamp
of the message, else its reception time; under ``use_sim_time`` the node's clock replaces the
DDS times, which are wall-clock.

Every ``update_period`` (node clock) a timer wakes a dedicated estimation thread, which takes
the latest window from the :class:`~ctid_ros.streaming.buffer.SampleBuffer` and calls
:meth:`IdentificationSession.update`, so samples keep being buffered while an estimate is
computed, whatever the executor. The thread keeps half a core free: after an estimate that took
``c`` seconds it skips the ticks of the next ``c`` seconds (counted as ``skipped_ticks``).
:func:`main` spins a single-threaded executor: with two 1 kHz Float64 streams
(``bench/node_throughput.py``), rclpy's ``MultiThreadedExecutor`` lost messages even without
estimating, the single-threaded one took all.

Robustness (issue #16): no exception leaves a callback (subscriptions, timers, services,
parameter and lifecycle callbacks, the estimation thread): each is caught, counted
(``internal_errors``), logged and reported on ``/diagnostics``. A parameter update is
validated by :class:`~ctid_ros.streaming.config.IdentificationConfig`, whose resource limits are
checked before anything is allocated, in a helper thread with a time bound
(:data:`VALIDATION_TIMEOUT`), so a model text that takes long to analyse cannot block the
executor; the parameter callback never waits for an estimate.

Managed (lifecycle) node with ``lifecycle: true``: it starts unconfigured with the standard
services (``~/change_state``, ``~/get_state``, ...); ``configure`` validates the parameters
and builds the buffer, publishers and services, ``activate`` subscribes and starts the timers,
``deactivate`` stops them, ``cleanup`` clears the buffer and removes the publishers, and
``shutdown`` finalises from any state. With ``lifecycle: false`` (default) the node configures
and activates itself at start-up and has no lifecycle services.

Outputs: the topics, types, layouts, QoS and status levels of
:mod:`ctid_ros.streaming.contract` (``~/estimate``, ``~/estimate_std``,
``~/estimate_covariance``, ``~/params/<name>`` and ``~/alarm`` transient-local,
``~/prediction`` if ``publish_prediction``, ``/diagnostics`` with the per-stream counters and
the alarm added), built there as plain data and converted here to rclpy messages;
``ctid replay --output`` writes the same. Services ``~/reset``, ``~/estimate_now`` and
``~/capture_baseline`` (``std_srvs/Trigger``). One INFO line per estimate, at most one a
second.

Change alarm: every estimate also goes to a :class:`~ctid_ros.streaming.alarm.ChangeDetector`
(the one ``ctid replay --sliding`` uses) against the baseline of
:func:`~ctid_ros.streaming.baseline.configured_baseline` (``baseline_file`` if it exists, else
``baseline.<name>``); the per-parameter parameters (``baseline.<name>``,
``baseline_std.<name>``, ``min_relative_change.<name>``) are declared once the model is known,
so a params file's ``baseline: {J: 0.05}`` reaches them. ``~/capture_baseline`` averages the
last ``baseline_windows`` windows into the baseline and writes ``baseline_file``; ``~/reset``
clears the alarm's sums and keeps its baseline; a runtime change keeps both unless it changes
the parameters' names (a new model) or the baseline.
"""

import functools
import math
import signal
import sys
import textwrap
import threading
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

from ctid_ros.errors import ConfigError, CtidError, DataError
from ctid_ros.ros.messages import field_problem, import_message, to_message
from ctid_ros.streaming.alarm import AlarmSettings, AlarmStatus, ChangeDetector
from ctid_ros.streaming.baseline import Baseline, configured_baseline, write_baseline_file
from ctid_ros.streaming.buffer import Gap, INPUT, OUTPUT, SampleBuffer, StreamStats
from ctid_ros.streaming.config import (IdentificationConfig, PARAMETER_NAMES, PARAMETERS,
                                       PER_PARAMETER, per_parameter_name, split_per_parameter)
from ctid_ros.streaming.contract import (alarm_message, DEFAULT_NODE_NAME, diagnostics_message,
                                         ERROR, estimate_line, estimate_messages,
                                         estimate_summary, failure_status, NANOSECONDS,
                                         NodeTopics, OK, OutputMessage, PublisherQos,
                                         update_status, warm_up_text, WARN)
from ctid_ros.streaming.message_fields import parse_field_path
from ctid_ros.streaming.sampler import MessageSampler, ROLES
from ctid_ros.streaming.session import IdentificationSession, Update
import numpy as np
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.node import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args
from std_srvs.srv import Trigger

__all__ = ['IdentificationNode', 'TOPIC_CHECK_PERIOD', 'VALIDATION_TIMEOUT', 'main',
           'node_usage', 'parameter_value', 'run_node', 'wrap_text']

TOPIC_CHECK_PERIOD = 0.5
ERROR_LOG_PERIOD = 10.0
# One INFO line per estimate, at most this often (s).
INFO_PERIOD = 1.0
# Longest time a parameter update may take to validate (a model text is parsed and
# differentiated); beyond it the update is refused and the executor goes on.
VALIDATION_TIMEOUT = 5.0
_INT64_MAX = 2 ** 63 - 1
# A capture whose windows scatter more than this (in variance, against their covariance) is
# reported with a warning: the plant was probably changing.
_SCATTER_LIMIT = 9.0
# Changing one of these rebuilds the sample buffer (its gap rules or size depend on them).
_BUFFER_PARAMETERS = ('window', 'sample_time', 'max_gap', 'reorder_horizon', 'transient',
                      'max_message_rate')
_ARRAY_TYPES = {'string_array': Parameter.Type.STRING_ARRAY}
_SUCCESS = TransitionCallbackReturn.SUCCESS
_FAILURE = TransitionCallbackReturn.FAILURE
_RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE,
                'best_effort': ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {'transient_local': DurabilityPolicy.TRANSIENT_LOCAL,
               'volatile': DurabilityPolicy.VOLATILE}


def _descriptor(spec) -> ParameterDescriptor:
    # Doubles are dynamically typed so that an integer (YAML 5) is accepted and converted by
    # the configuration, as in ctid replay; everything else is typed by rclpy.
    dynamic = spec.kind in ('double', 'double_array')
    descriptor = ParameterDescriptor(
        name=spec.name, type=getattr(ParameterType, spec.type_name),
        description=spec.description, additional_constraints=spec.constraints,
        read_only=spec.read_only, dynamic_typing=dynamic)
    if spec.minimum is not None and spec.kind == 'double':
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(spec.minimum), to_value=math.inf, step=0.0)]
    elif spec.minimum is not None and spec.kind == 'integer':
        descriptor.integer_range = [IntegerRange(
            from_value=int(spec.minimum), to_value=_INT64_MAX, step=0)]
    return descriptor


def _initial_value(spec) -> Any:
    """Return the declaration default; string arrays are declared by type (rclpy types [])."""
    if spec.kind in _ARRAY_TYPES:
        return _ARRAY_TYPES[spec.kind]
    return list(spec.default) if isinstance(spec.default, tuple) else spec.default


def _per_parameter_descriptor(name: str) -> ParameterDescriptor:
    prefix, parameter = split_per_parameter(name)
    return ParameterDescriptor(
        name=name, type=ParameterType.PARAMETER_DOUBLE, dynamic_typing=True,
        description=f'Change alarm: {PER_PARAMETER[prefix]} {parameter} (NaN: not set).')


def parameter_value(node: Node, name: str, default: Any = None) -> Any:
    """Return a declared parameter's value, or ``default`` if it was declared by type only."""
    try:
        value = node.get_parameter(name).value
    except ParameterUninitializedException:
        return default
    return default if value is None else value


def _qos_profile(qos: PublisherQos) -> QoSProfile:
    return QoSProfile(depth=qos.depth, reliability=_RELIABILITY[qos.reliability],
                      durability=_DURABILITY[qos.durability])


def _bounded(function: Callable[[], Any], timeout: float, busy: List[threading.Thread]) -> Any:
    """
    Run ``function`` in a helper thread and wait at most ``timeout`` seconds for it.

    ``busy`` holds a helper still running from an earlier call: while it runs, further calls
    are refused at once, so at most one runaway validation exists.

    Raises
    ------
    ConfigError
        If the helper does not finish in time, or an earlier one is still running.

    """
    if busy and busy[0].is_alive():
        raise ConfigError('the previous parameter update is still being checked (its model '
                          'took longer than {:g} s to analyse); try again later'.format(timeout))
    busy.clear()
    outcome: Dict[str, Any] = {}

    def run() -> None:
        try:
            outcome['value'] = function()
        except BaseException as error:  # noqa: B902 - re-raised in the caller's thread
            outcome['error'] = error

    helper = threading.Thread(target=run, name='ctid_validate', daemon=True)
    helper.start()
    helper.join(timeout)
    if helper.is_alive():
        busy.append(helper)
        raise ConfigError(f'checking the new parameters took longer than {timeout:g} s: '
                          'refused, the node keeps its configuration')
    if 'error' in outcome:
        raise outcome['error']
    return outcome['value']


class _Counters:
    """What the node counts beyond the buffer's admission counters, per role."""

    def __init__(self):
        self.field_errors = dict.fromkeys(ROLES, 0)
        self.zero_stamps = dict.fromkeys(ROLES, 0)
        self.lost = dict.fromkeys(ROLES, 0)
        self.last_received: Dict[str, Optional[int]] = dict.fromkeys(ROLES)


class IdentificationNode(LifecycleNode):
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
        for spec in PARAMETERS:
            self.declare_parameter(spec.name, _initial_value(spec), _descriptor(spec))
        self._lock = threading.RLock()                # references below, counters
        self._estimation_lock = threading.Lock()      # the session: one estimate at a time
        self._validating: List[threading.Thread] = []
        self._config: Optional[IdentificationConfig] = None
        self._session: Optional[IdentificationSession] = None
        self._detector: Optional[ChangeDetector] = None
        # A baseline set by a runtime parameter change, for the next estimate to take up.
        self._pending_baseline: Optional[Tuple[Optional[Baseline], str]] = None
        self._sampler: Optional[MessageSampler] = None
        self._buffer: Optional[SampleBuffer] = None
        self._counters = _Counters()
        self._node_topics = NodeTopics(self.get_fully_qualified_name())
        self._topic_publishers: Dict[str, Tuple[Any, type]] = {}
        self._topic_subscriptions: Dict[str, Tuple[Any, str]] = {}
        self._notes: Dict[str, str] = {}
        self._logged: Dict[str, str] = {}
        self._own_services: List[Any] = []
        self._own_timers: List[Any] = []
        self._active = False
        self._transition_error = ''
        self._internal_errors = 0
        self._last_internal_error = ''
        self._rejected_parameters = 0
        self._last_rejected_parameter = ''
        self._skipped_ticks = 0
        self._skipped_since_estimate = 0
        self._estimated_since_start = False
        self._origin_ns: Optional[int] = None
        self._last_info = -math.inf
        self._busy_until = 0.0
        self.last_update: Optional[Update] = None
        self._estimation_group = MutuallyExclusiveCallbackGroup()
        self._sample_group = ReentrantCallbackGroup()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._wakeup = threading.Event()
        self._stopping = False
        self._tick: Optional[float] = None
        self._worker = threading.Thread(target=self._work, name='ctid_estimator', daemon=True)
        self._worker.start()
        self._managed = bool(parameter_value(self, 'lifecycle', False))
        LifecycleNodeMixin.__init__(self, enable_communication_interface=self._managed,
                                    callback_group=MutuallyExclusiveCallbackGroup())
        if not self._managed:
            self._start()

    def _start(self) -> None:
        """Configure and activate at once (``lifecycle: false``); raise what went wrong."""
        for transition in (self.trigger_configure, self.trigger_activate):
            if transition() != _SUCCESS:
                self._stopping = True          # the node will not be spun: end the thread
                self._wakeup.set()
                raise ConfigError(self._transition_error or 'the node could not start')

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

    def _read_config(self) -> IdentificationConfig:
        values = {spec.name: parameter_value(self, spec.name, spec.default)
                  for spec in PARAMETERS}
        config = _bounded(lambda: IdentificationConfig.from_dict(values), VALIDATION_TIMEOUT,
                          self._validating)
        # The model's parameters are known now: baseline.J and the like can be declared (a
        # params file's values for them become theirs) and read.
        self._declare_per_parameter(config.names)
        values.update({name: parameter_value(self, name, math.nan)
                       for name in self._per_parameter_names(config.names)})
        return IdentificationConfig.from_dict(values)

    @staticmethod
    def _per_parameter_names(names: Tuple[str, ...]) -> List[str]:
        return [per_parameter_name(prefix, name) for prefix in PER_PARAMETER for name in names]

    def _declare_per_parameter(self, names: Tuple[str, ...]) -> None:
        for name in self._per_parameter_names(names):
            if not self.has_parameter(name):
                self.declare_parameter(name, math.nan, _per_parameter_descriptor(name))

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
                self._publisher(message)
            self._own_services = [
                self.create_service(Trigger, '~/reset', self._reset,
                                    callback_group=self._estimation_group),
                self.create_service(Trigger, '~/estimate_now', self._estimate_now,
                                    callback_group=self._estimation_group),
                self.create_service(Trigger, '~/capture_baseline', self._capture_baseline,
                                    callback_group=self._estimation_group)]
            self._publisher(alarm_message(self._node_topics, OK, '', {}))
        except Exception as error:  # noqa: B902 - a bug must not escape a transition
            self._internal_error('configure', error)
            self._teardown()
            return self._transition_failed('configure', error)
        self.get_logger().info(f'configured: model {config.model!r}, window {config.window:g} s '
                               f'on a {config.sample_time:g} s grid, an estimate every '
                               f'{config.update_period:g} s')
        self.get_logger().info(self._baseline_line(baseline, note))
        return _SUCCESS

    def _baseline_line(self, baseline: Optional[Baseline], note: str) -> str:
        if baseline is None:
            return f'change alarm: {note}; set baseline.<name> or call ~/capture_baseline'
        config = self._config
        return (f'change alarm: baseline {note}: {baseline.describe()}; '
                f'{config.false_alarm_per_hour:g} false alarms per hour')

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
        with self._lock:
            subscriptions = [subscription for subscription, _ in
                             self._topic_subscriptions.values()]
            self._topic_subscriptions = {}
            self._notes = {}
        for subscription in subscriptions:
            self.destroy_subscription(subscription)

    def _teardown(self) -> None:
        with self._estimation_lock, self._lock:
            publishers = [publisher for publisher, _ in self._topic_publishers.values()]
            self._topic_publishers = {}
            self._config = self._session = self._sampler = self._buffer = None
            self._detector = self._pending_baseline = None
            self.last_update = None
        for publisher in publishers:
            self.destroy_lifecycle_publisher(publisher)
        for service in self._own_services:
            self.destroy_service(service)
        self._own_services = []

    def _restart_counters(self) -> None:
        self._counters = _Counters()
        self._logged = {}
        self._origin_ns = None
        self._estimated_since_start = False
        self._skipped_since_estimate = 0

    def _new_sampler(self, config: IdentificationConfig) -> MessageSampler:
        return MessageSampler(config, (self.resolve_topic_name(config.input_topic),
                                       self.resolve_topic_name(config.output_topic)))

    @staticmethod
    def _new_buffer(config: IdentificationConfig, sampler: MessageSampler) -> SampleBuffer:
        # Sized and limited by the configuration (MAX_BUFFER_BYTES) before it is allocated.
        return sampler.buffer(config.buffer_capacity(), config)

    def _create_update_timer(self):
        return self.create_timer(self._config.update_period, self._on_timer,
                                 callback_group=self._estimation_group)

    # Input ---------------------------------------------------------------------------------

    def _paths(self, topic: str) -> List[Any]:
        config, sampler = self._config, self._sampler
        paths = []
        for role in sampler.roles(topic):
            fields = config.input_fields if role == INPUT else (config.output_field,)
            paths.extend(parse_field_path(path) for path in fields)
        return paths

    def _choose_type(self, topic: str, types: List[str], current: Optional[str]
                     ) -> Tuple[Optional[str], Optional[type], Dict[str, str]]:
        """Return the type to read ``topic`` as (None if none fits), its class, the misfits."""
        paths = self._paths(topic)
        fitting: Dict[str, type] = {}
        problems: Dict[str, str] = {}
        for name in types:
            try:
                message_class = import_message(name)
            except ConfigError as error:
                problems[name] = str(error)
                continue
            found = (field_problem(message_class, path) for path in paths)
            problem = next((text for text in found if text), None)
            if problem is None:
                fitting[name] = message_class
            else:
                problems[name] = problem
        if current in fitting:
            return current, fitting[current], problems
        for name, message_class in fitting.items():
            return name, message_class, problems
        return None, None, problems

    def _connect(self) -> None:
        """Subscribe to each topic with a published type that holds the configured fields."""
        try:
            self._check_topics()
        except Exception as error:  # noqa: B902 - a bug must not stop the node
            self._internal_error('topic check', error)

    def _check_topics(self) -> None:
        if not self._active or self._sampler is None:
            return
        for topic in dict.fromkeys(self._sampler.topics):
            roles = self._sampler.roles(topic)
            types = list(dict.fromkeys(info.topic_type for info in
                                       self.get_publishers_info_by_topic(topic)))
            subscribed = self._topic_subscriptions.get(topic)
            current = subscribed[1] if subscribed else None
            if not types:
                if current is None:
                    self._notes[topic] = (f'no publisher on {topic} yet: waiting to learn its '
                                          'message type')
                else:
                    self._notes.pop(topic, None)
                continue
            choice, message_class, problems = self._choose_type(topic, types, current)
            if choice is None:
                misfits = '; '.join(f'{name}: {problem}' for name, problem in problems.items())
                self._notes[topic] = (f'no publisher on {topic} has a type with the configured '
                                      f'field(s): {misfits}')
                self._log_once(topic, self._notes[topic], error=True)
                continue
            if choice != current:
                self._subscribe(topic, choice, message_class, roles, current)
            if problems:
                ignored = '; '.join(f'{name} ({problem})' for name, problem in problems.items())
                self._notes[topic] = (f'{topic} has publishers of {len(problems) + 1} types: '
                                      f'reading {choice}, ignoring {ignored}')
                self._log_once(topic, self._notes[topic], error=False)
            else:
                self._notes.pop(topic, None)
                self._logged.pop(topic, None)

    def _subscribe(self, topic: str, type_name: str, message_class: type,
                   roles: Tuple[str, ...], current: Optional[str]) -> None:
        callback = functools.partial(self.receive, topic)
        events = SubscriptionEventCallbacks(
            message_lost=functools.partial(self._lost, topic),
            incompatible_type=lambda event: None)
        qos = QoSProfile(depth=self._config.qos_depth,
                         reliability=_RELIABILITY[self._config.qos_reliability])
        try:
            subscription = self.create_subscription(
                message_class, topic, callback, qos, callback_group=self._sample_group,
                event_callbacks=events)
        except UnsupportedEventTypeError:
            subscription = self.create_subscription(
                message_class, topic, callback, qos, callback_group=self._sample_group,
                event_callbacks=SubscriptionEventCallbacks(incompatible_type=lambda event: None))
        with self._lock:
            old = self._topic_subscriptions.get(topic)
            self._topic_subscriptions[topic] = (subscription, type_name)
        if old is not None:
            self.destroy_subscription(old[0])
            self.get_logger().warning(f'{topic}: now reading {type_name} (was {current}, no '
                                      'longer published)')
        else:
            self.get_logger().info(f'subscribed to {topic} ({type_name}) for the '
                                   f'{" and ".join(roles)}')

    def _log_once(self, key: str, text: str, error: bool, again_if_changed: bool = True
                  ) -> None:
        if key not in self._logged or (again_if_changed and self._logged[key] != text):
            self._logged[key] = text
            # One severity per call site: rclpy refuses to mix them.
            if error:
                self.get_logger().error(text)
            else:
                self.get_logger().warning(text)

    def _lost(self, topic: str, info: Any) -> None:
        with self._lock:
            for role in self._sampler.roles(topic) if self._sampler else ():
                self._counters.lost[role] += int(getattr(info, 'total_count_change', 0))

    def _receive_stamp(self, info: Mapping[str, Any]) -> int:
        clock = self.get_clock()
        if clock.ros_time_is_active:
            return clock.now().nanoseconds
        return info.get('source_timestamp') or info.get('received_timestamp') or \
            clock.now().nanoseconds

    def receive(self, topic: str, message: Any, info: Optional[Mapping[str, Any]] = None
                ) -> None:
        """
        Take one message of ``topic`` into the buffer, as the subscriptions do.

        Parameters
        ----------
        topic : str
            Resolved topic the message came on.
        message : object
            The message.
        info : mapping, optional
            rclpy's message info (``source_timestamp``, ``received_timestamp``); without it the
            node's clock stamps a message that has no header stamp.

        """
        try:
            self._take(topic, message, info or {})
        except Exception as error:  # noqa: B902 - one bad message must not stop the intake
            self._internal_error(f'message on {topic}', error)

    def _take(self, topic: str, message: Any, info: Mapping[str, Any]) -> None:
        with self._lock:
            sampler, buffer, counters = self._sampler, self._buffer, self._counters
        if sampler is None:
            return
        roles = sampler.roles(topic)
        received = self.get_clock().now().nanoseconds
        sample = sampler(topic, self._receive_stamp(info), message)
        failed = dict(sample.errors)
        with self._lock:
            for role in roles:
                counters.last_received[role] = received
                counters.zero_stamps[role] += sample.zero_stamp
                if role in failed:
                    counters.field_errors[role] += 1
                    # Shown on /diagnostics until the field can be read again.
                    self._notes[f'field {role}'] = f'{role}: {failed[role]}'
                elif self._notes:
                    self._notes.pop(f'field {role}', None)
            if self._origin_ns is None and (sample.u is not None or sample.y is not None):
                self._origin_ns = sample.stamp_ns
        for role, error in failed.items():
            self._log_once(f'field {role}', f'{role}: {error}', error=True,
                           again_if_changed=False)
        sample.add_to(buffer)

    # Estimation ----------------------------------------------------------------------------

    def _on_timer(self) -> None:
        self._tick = time.perf_counter()
        self._wakeup.set()

    def _work(self) -> None:
        while True:
            self._wakeup.wait()
            self._wakeup.clear()
            if self._stopping:
                return
            try:
                if not self._active:
                    continue
                if time.perf_counter() < self._busy_until:
                    # The last estimate took longer than half the time since: keep half a
                    # core free for the controller this node runs next to.
                    self._skipped_ticks += 1
                    self._skipped_since_estimate += 1
                    continue
                self.estimate(self._tick)
            except Exception as error:  # noqa: B902 - a bug must not stop the estimates
                self._internal_error('estimation', error)

    def destroy_node(self) -> None:
        """Stop the estimation thread, then destroy the node and its lifecycle state machine."""
        self._stopping = True
        self._active = False
        self._wakeup.set()
        self._worker.join()
        super().destroy_node()
        # rclpy's LifecycleNode leaves its state machine to the garbage collector, whose
        # finaliser crashes a forked child (multiprocessing) that collects it: end it here.
        self._state_machine.destroy_when_not_in_use()

    def estimate(self, started: Optional[float] = None) -> Tuple[Optional[Update], str]:
        """
        Estimate on the latest window now and publish the result and diagnostics.

        Parameters
        ----------
        started : float, optional
            ``time.perf_counter()`` of the request (the timer tick), for ``publish_latency``.

        Returns
        -------
        (Update or None, str)
            The update (None if there was none) and a one-line summary or the reason.

        """
        started = time.perf_counter() if started is None else started
        with self._estimation_lock:
            with self._lock:
                config, buffer, session = self._config, self._buffer, self._session
                detector, pending = self._detector, self._pending_baseline
                self._pending_baseline = None
            if config is None:
                return None, 'not configured'
            if session.config is not config:
                session.reconfigure(config)
            self._follow_configuration(detector, config, pending)
            try:
                self._check_silence(config, buffer)
            except DataError as error:
                return None, self._failed(error)
            try:
                window = session.take_window(buffer)
            except DataError as error:
                return None, self._no_window(config, buffer, session, error)
            try:
                update = session.update(window)
            except CtidError as error:
                return None, self._failed(error)
            finally:
                self._busy_until = time.perf_counter() + (time.perf_counter() - started)
            previous = detector.status
            alarm = detector.update(update)
        self.last_update = update
        self._estimated_since_start = True
        self._publish(update, config)
        values = update.diagnostics()
        values['publish_latency'] = time.perf_counter() - started
        origin = self._origin_ns if self._origin_ns is not None else update.start_ns
        values['time'] = (update.end_ns - origin) / NANOSECONDS
        values['window'] = config.window
        values.update(alarm.diagnostics(origin))
        self._publish_alarm(alarm)
        self._log_alarm(previous, alarm)
        level, text = update_status(update.names, update.values, update.stds, values)
        available = self._available(buffer)
        if available is not None and available < config.window:
            text = f'{warm_up_text(available, config.window)}; {text}'
        if self._skipped_since_estimate:
            level = max(level, WARN)
            text = (f'{self._skipped_since_estimate} tick(s) skipped: an estimate takes '
                    f'{update.compute_time:.3g} s and the node keeps half a core free; {text}')
            self._skipped_since_estimate = 0
        self._publish_status(level, text, values)
        self._log_estimate(update, values['time'])
        return update, estimate_summary(update.names, update.values, update.stds)

    def _follow_configuration(self, detector: ChangeDetector, config: IdentificationConfig,
                              pending: Optional[Tuple[Optional[Baseline], str]]) -> None:
        """Bring the detector to ``config`` and a baseline set at runtime (estimation lock)."""
        settings = AlarmSettings.from_config(config)
        if settings != detector.settings:
            detector.reconfigure(settings, None if pending is None else pending[0])
        elif pending is not None:
            detector.set_baseline(pending[0])
        if pending is not None:
            self.get_logger().info(self._baseline_line(*pending))

    def _origin(self) -> int:
        return self._origin_ns if self._origin_ns is not None else 0

    def _publish_alarm(self, alarm: AlarmStatus) -> None:
        """Publish the change alarm on ``~/alarm`` (latched)."""
        config = self._config
        if config is None:
            return
        origin = self._origin()
        self._send(alarm_message(self._node_topics, alarm.level, alarm.text(origin),
                                 alarm.values(origin), hardware_id=config.hardware_id))

    def _log_alarm(self, previous: AlarmStatus, alarm: AlarmStatus) -> None:
        """Log when the alarm is raised, changes or clears."""
        if (alarm.level, alarm.parameters) == (previous.level, previous.parameters):
            return
        text = alarm.text(self._origin())
        if alarm.level == OK:
            self.get_logger().info(f'change alarm cleared: {text}')
        elif alarm.level == WARN:
            self.get_logger().warning(f'change alarm: {text}')
        else:
            self.get_logger().error(f'change alarm: {text}')

    def _log_estimate(self, update: Update, time_s: float) -> None:
        now = time.monotonic()
        if now - self._last_info >= INFO_PERIOD:
            self._last_info = now
            self.get_logger().info(estimate_line(update.names, update.values, update.stds,
                                                 time_s, update.result.fit, update.residuals))

    @staticmethod
    def _available(buffer: SampleBuffer) -> Optional[float]:
        """Return the seconds covered by both streams without a gap, or None if unknown."""
        stats = buffer.stats()
        if stats.u.gaps or stats.y.gaps:
            return None
        try:
            first, last = buffer.coverage()
        except DataError:
            return None
        return (last - first) / NANOSECONDS

    def _no_window(self, config: IdentificationConfig, buffer: SampleBuffer,
                   session: IdentificationSession, error: DataError) -> str:
        """
        Report why there is no window to estimate on.

        Collecting the first half window: OK, ``warming up: 1.2 of 4 s of data``, against the
        configured window. Collecting it again after a gap: WARN, the same with the gaps (in
        seconds since the first sample). Anything else (no samples): WARN with the error.
        """
        needed = 0.5 * config.window
        try:
            latest = buffer.window(session.window_length(), config.sample_time,
                                   min_length=2 * config.sample_time)
            available, gaps = len(latest.data) * config.sample_time, latest.gaps
        except DataError:
            # Not even two grid instants yet: the span both streams cover, if they have data.
            available, gaps = self._available(buffer), ()
        if available is None or available >= needed:
            return self._failed(error)
        text = warm_up_text(available, config.window, needed)
        values = {'window': config.window, 'data': available}
        if not gaps and not self._estimated_since_start:
            self._publish_status(OK, text, values)
            return text
        gaps = '; '.join(map(self._describe_gap, gaps)) or 'data missing before'
        text = f'{text}, again after a gap: {gaps}'
        self.get_logger().warning(f'no estimate: {text}', throttle_duration_sec=ERROR_LOG_PERIOD)
        self._publish_status(WARN, text, values)
        return text

    def _describe_gap(self, gap: Gap) -> str:
        origin = (self._origin_ns or 0) / NANOSECONDS
        if gap.end is None:
            return f'{gap.stream} silent since t={gap.start - origin:.2f} s'
        return (f'{gap.stream} missing for {gap.duration:.3g} s from t={gap.start - origin:.2f} '
                's')

    def _check_silence(self, config: IdentificationConfig, buffer: SampleBuffer) -> None:
        """
        Refuse to estimate again from stale data when a stream stopped.

        The buffer's windows end at its newest data, so without this check a dead publisher
        would go unnoticed: the same last window would be estimated over and over.
        """
        now = self.get_clock().now().nanoseconds
        limit = max(config.max_gap, config.update_period)
        for role, name in zip(ROLES, buffer.names):
            last = self._counters.last_received[role]
            if last is not None and now - last > limit * NANOSECONDS:
                silence = (now - last) / NANOSECONDS
                raise DataError(f'{name} silent: no message for {silence:.3g} s (more than '
                                f'{limit:g} s); check its publisher')

    def _failed(self, error: CtidError) -> str:
        level, text = failure_status(error)
        self.get_logger().warning(f'no estimate: {text}', throttle_duration_sec=ERROR_LOG_PERIOD)
        self._publish_status(level, text, {})
        return text

    # Output --------------------------------------------------------------------------------

    def _publisher(self, message: OutputMessage) -> Optional[Tuple[Any, type]]:
        """Return the publisher of a message's topic and its class, created on first use."""
        with self._lock:
            if message.topic not in self._topic_publishers:
                if self._config is None:
                    return None
                message_class = import_message(message.msgtype)
                publisher = self.create_lifecycle_publisher(
                    message_class, message.topic, _qos_profile(message.qos))
                if self._active:
                    publisher.on_activate(None)
                self._topic_publishers[message.topic] = (publisher, message_class)
            return self._topic_publishers[message.topic]

    def _send(self, message: OutputMessage) -> None:
        found = self._publisher(message)
        if found is not None:
            publisher, message_class = found
            publisher.publish(to_message(message_class, message.fields))

    def _publish(self, update: Update, config: IdentificationConfig) -> None:
        for message in estimate_messages(
                self._node_topics, update.names, update.values, update.stds,
                update.prediction if config.publish_prediction else None,
                covariance=update.covariance):
            self._send(message)

    def _stream_values(self, role: str, stats: StreamStats) -> Dict[str, Any]:
        counters = self._counters
        return {f'{role}_{key}': value for key, value in (
            ('received', stats.received), ('accepted', stats.accepted),
            ('duplicates', stats.duplicates), ('late', stats.late),
            ('non_finite', stats.non_finite), ('out_of_clock', stats.out_of_clock),
            ('pending', stats.pending), ('reanchors', stats.reanchors),
            ('evicted', stats.evicted), ('field_errors', counters.field_errors[role]),
            ('zero_stamps', counters.zero_stamps[role]), ('lost', counters.lost[role]))}

    def _publish_status(self, level: int, text: str, values: Dict[str, Any]) -> None:
        try:
            with self._lock:
                buffer, config, notes = self._buffer, self._config, list(self._notes.values())
            if buffer is None or config is None:
                return
            stats = buffer.stats()
            values = {**values, **self._stream_values(INPUT, stats.u),
                      **self._stream_values(OUTPUT, stats.y),
                      'skipped_ticks': self._skipped_ticks,
                      'rejected_parameters': self._rejected_parameters,
                      'internal_errors': self._internal_errors}
            if self._last_rejected_parameter:
                values['last_rejected_parameter'] = self._last_rejected_parameter
            if self._last_internal_error:
                values['last_internal_error'] = self._last_internal_error
            if notes:
                level = max(level, WARN)
                text = '; '.join([*notes, text])
            now = self.get_clock().now().nanoseconds
            self._send(diagnostics_message(self._node_topics, now, level, text, values,
                                           hardware_id=config.hardware_id))
        except Exception as error:  # noqa: B902 - reporting must not fail the caller
            self._count_internal_error('status', error)

    def _count_internal_error(self, what: str, error: BaseException) -> None:
        self._internal_errors += 1
        self._last_internal_error = f'{what}: {error!r}'[:500]
        self.get_logger().error(f'internal error in {what}: {error!r}',
                                throttle_duration_sec=ERROR_LOG_PERIOD)

    def _internal_error(self, what: str, error: BaseException) -> None:
        """Count, log and report an exception caught at the edge of a callback."""
        self._count_internal_error(what, error)
        self._publish_status(ERROR, f'internal error in {what}: {error!r}'[:500], {})

    # Services and parameters ---------------------------------------------------------------

    def reset(self) -> None:
        """Forget all samples, counters, the warm start and the alarm's sums (not its baseline)."""
        with self._estimation_lock, self._lock:
            if self._buffer is not None:
                self._buffer.clear()
                self._session.reset()
                self._detector.reset()
            self._restart_counters()
        if self._detector is not None:
            self._publish_alarm(self._detector.status)

    def capture_baseline(self) -> Tuple[bool, str]:
        """
        Average the last ``baseline_windows`` windows into the baseline; save it if configured.

        Returns
        -------
        (bool, str)
            Whether a baseline was captured, and what happened (the values, where they were
            written, or why not).

        """
        with self._estimation_lock:
            with self._lock:
                detector, config = self._detector, self._config
            if detector is None:
                return False, 'not configured'
            origin = self._origin()
            windows = list(detector.recent_ends())
            try:
                baseline = detector.capture()
            except DataError as error:
                return False, str(error)
            spread = detector.spread()
        first, last = ((windows[-config.baseline_windows] - origin) / NANOSECONDS,
                       (windows[-1] - origin) / NANOSECONDS)
        note = (f'captured by {self.get_fully_qualified_name()} from {config.baseline_windows} '
                f'windows ending t={first:.2f} to {last:.2f} s (stamps '
                f'{windows[-config.baseline_windows] / NANOSECONDS!r} to '
                f'{windows[-1] / NANOSECONDS!r})')
        text = f'baseline {baseline.describe()}, {note}'
        if spread > _SCATTER_LIMIT:
            text += (f'; warning: the windows scatter {math.sqrt(spread):.3g} times more than '
                     'their covariance says: was the plant changing?')
        if config.baseline_file:
            try:
                path = write_baseline_file(config.baseline_file, baseline,
                                           self.get_fully_qualified_name(), note)
                text += f'; saved to {path}'
            except ConfigError as error:
                text += f'; NOT saved: {error}'
                self.get_logger().error(f'~/capture_baseline: {error}')
        else:
            text += '; not saved (no baseline_file): a restart forgets it'
        self.get_logger().info(f'change alarm: {text}')
        self._publish_alarm(detector.status)
        return True, text

    def _capture_baseline(self, request: Trigger.Request,
                          response: Trigger.Response) -> Trigger.Response:
        try:
            response.success, response.message = self.capture_baseline()
        except Exception as error:  # noqa: B902 - a service must answer
            self._internal_error('capture_baseline', error)
            response.success, response.message = False, f'internal error: {error!r}'
        return response

    def _reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.reset()
            response.success, response.message = True, 'buffer cleared, warm start forgotten'
        except Exception as error:  # noqa: B902 - a service must answer
            self._internal_error('reset', error)
            response.success, response.message = False, f'internal error: {error!r}'
        return response

    def _estimate_now(self, request: Trigger.Request,
                      response: Trigger.Response) -> Trigger.Response:
        try:
            if not self._active:
                update, response.message = None, 'the node is not active'
            else:
                update, response.message = self.estimate()
            response.success = update is not None
        except Exception as error:  # noqa: B902 - a service must answer
            self._internal_error('estimate_now', error)
            response.success, response.message = False, f'internal error: {error!r}'
        return response

    def _on_set_parameters(self, parameters: List[Parameter]) -> SetParametersResult:
        try:
            changes = {parameter.name: parameter.value for parameter in parameters
                       if parameter.name in PARAMETER_NAMES
                       or split_per_parameter(parameter.name)}
            if not changes or self._config is None:
                # Unconfigured: the parameters are validated on configure, as nav2 does.
                return SetParametersResult(successful=True)
            defaults = {spec.name: spec.default for spec in PARAMETERS}
            changes = {name: defaults.get(name, math.nan) if value is None else value
                       for name, value in changes.items()}
            current = self._config
            config = _bounded(lambda: current.updated(changes), VALIDATION_TIMEOUT,
                              self._validating)
            baseline = self._changed_baseline(current, config, changes)
            self._apply(config)
            if baseline is not None:
                with self._lock:
                    self._pending_baseline = baseline
        except ConfigError as error:
            self._rejected_parameters += 1
            self._last_rejected_parameter = str(error)[:500]
            self.get_logger().warning(f'parameter update refused: {error}')
            return SetParametersResult(successful=False, reason=str(error))
        except Exception as error:  # noqa: B902 - MemoryError, bugs: refuse, keep running
            self._internal_error('parameter update', error)
            return SetParametersResult(successful=False, reason=f'internal error: {error!r}')
        return SetParametersResult(successful=True)

    def _changed_baseline(self, old: IdentificationConfig, new: IdentificationConfig,
                          changes: Mapping[str, Any]) -> Optional[Tuple[Optional[Baseline], str]]:
        """
        Return the baseline a runtime change sets, or None if it leaves the baseline alone.

        Setting any ``baseline.<name>``/``baseline_std.<name>`` uses the parameters' baseline
        (even over a captured one); a changed ``baseline_file`` (or model) gives
        :func:`configured_baseline`.

        Raises
        ------
        ConfigError
            If the new ``baseline_file`` exists and cannot be used.

        """
        if new.baseline_file != old.baseline_file or new.names != old.names:
            return configured_baseline(new, self.get_fully_qualified_name())
        if any((split_per_parameter(name) or ('',))[0] in ('baseline', 'baseline_std')
               for name in changes):
            return Baseline.from_config(new), 'from the parameters'
        return None

    def _apply(self, config: IdentificationConfig) -> None:
        """Switch to a validated configuration; the session follows at the next estimate."""
        old = self._config
        sampler = self._new_sampler(config)
        rebuild = any(getattr(config, name) != getattr(old, name) for name in _BUFFER_PARAMETERS)
        rebuild = rebuild or len(config.input_fields) != len(old.input_fields)
        buffer = self._new_buffer(config, sampler) if rebuild else self._buffer
        with self._lock:
            self._sampler, self._buffer, self._config = sampler, buffer, config
            if rebuild:
                self._estimated_since_start = False
            if config.input_fields != old.input_fields or config.output_field != old.output_field:
                self._logged = {}
                self._notes = {key: note for key, note in self._notes.items()
                               if not key.startswith('field ')}
                # Another field may fit another of the published types.
                for subscription, _ in self._topic_subscriptions.values():
                    self.destroy_subscription(subscription)
                self._topic_subscriptions = {}
        if config.update_period != old.update_period and self._active:
            self.destroy_timer(self._own_timers[0])
            self._own_timers[0] = self._create_update_timer()
        if self._active:
            self._connect()
        if config.names != old.names:
            # A new model: its parameters get their baseline.<name> and the like.
            self._declare_per_parameter(config.names)
        changed = ', '.join(sorted(_changed(old, config))) or 'the same values'
        self.get_logger().info(f'configuration updated: {changed}')


def _changed(old: IdentificationConfig, new: IdentificationConfig) -> List[str]:
    plain = [name for name in PARAMETER_NAMES if getattr(old, name) != getattr(new, name)]
    before, after = dict(old.per_parameter), dict(new.per_parameter)
    return plain + [name for name in set(before) | set(after)
                    if before.get(name) != after.get(name)]


def wrap_text(text: str, indent: str) -> str:
    """Wrap ``text`` for a --help page at 99 columns, every line indented by ``indent``."""
    return textwrap.fill(text, 99, initial_indent=indent, subsequent_indent=indent)


def node_usage() -> str:
    """Return the ``ctid_node --help`` text: how to run it and every parameter."""
    lines = [
        f'usage: {DEFAULT_NODE_NAME} [-h] [--ros-args [--params-file FILE] [-p NAME:=VALUE]... '
        '[-r __ns:=/NAMESPACE]]',
        '',
        wrap_text('Identify the physical parameters of a continuous-time transfer function '
                  'live from two ROS topics (input and output), and publish them with their '
                  'uncertainty on ~/estimate, ~/estimate_std, ~/estimate_covariance, '
                  '~/params/<name> and /diagnostics.', ''),
        '',
        'examples:',
        f'  {DEFAULT_NODE_NAME} --ros-args --params-file config/open_loop_delay.yaml',
        f"  {DEFAULT_NODE_NAME} --ros-args -p model:='K/(T*s + 1)' -p input_topic:=/u "
        '-p output_topic:=/y',
        f'  {DEFAULT_NODE_NAME} --ros-args --params-file p.yaml -p lifecycle:=true   '
        '# managed node',
        '',
        'parameters (-p NAME:=VALUE or a params file; integers are accepted for doubles):',
    ]
    for spec in PARAMETERS:
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        flags = ', read-only' if spec.read_only else ''
        lines.append(f'  {spec.name} ({spec.kind}{flags}, default {default!r})')
        lines.append(wrap_text(spec.description, '      '))
    lines.append('per model parameter <name> (a mapping in a params file, e.g. baseline: {J: '
                 '0.05, b: 0.2}):')
    for prefix, meaning in PER_PARAMETER.items():
        lines.append(f'  {prefix}.<name> (double, default unset)')
        lines.append(wrap_text(f"The change alarm's {meaning}.", '      '))
    return '\n'.join(lines)


def _interrupt(signal_number: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run_node(factory: Callable[[], Node], name: str, args: Optional[List[str]] = None,
             usage: Optional[Callable[[], str]] = None) -> int:
    """
    Spin the node made by ``factory`` until Ctrl-C or SIGTERM.

    ``-h``/``--help`` before ``--ros-args`` prints ``usage()`` and returns 0 without starting;
    any other argument outside ``--ros-args`` is an error (status 2). Both signals interrupt
    the spinning thread, which then destroys the node before the context goes, so no callback
    or publication meets an invalid context.
    """
    arguments = list(sys.argv if args is None else args)
    own = remove_ros_args(arguments)[1:]
    if '-h' in own or '--help' in own:
        print(usage() if usage else f'usage: {name} [--ros-args ...]')
        return 0
    if own:
        print(f'{name}: error: unrecognised argument(s) {" ".join(own)}: ROS arguments go after '
              f'--ros-args (see {name} --help)', file=sys.stderr)
        return 2
    rclpy.init(args=arguments, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    executor = SingleThreadedExecutor()
    try:
        executor.add_node(factory())
        executor.spin()
    except (ConfigError, ParameterException) as error:
        print(f'{name}: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    finally:
        executor.shutdown()
        for node in executor.get_nodes():
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(args: Optional[List[str]] = None) -> int:
    """Run ``ctid_node`` until Ctrl-C or SIGTERM; return the exit status."""
    return run_node(IdentificationNode, DEFAULT_NODE_NAME, args, node_usage)


if __name__ == '__main__':
    sys.exit(main())
