"""
The live identification node ``ctid_node``: ROS in, :class:`IdentificationSession` in the middle.

Inputs: the input and output topics of the configuration (any installed message type, learnt
from the ROS graph once a publisher appears), one number per message read by a field path; one
subscription serves both when they share a topic. Each sample is stamped with ``header.stamp``
(``stamp_source: header`` and a non-zero stamp), else the DDS source timestamp of the message,
else its reception time; under ``use_sim_time`` the node's clock replaces the DDS times, which
are wall-clock.

Every ``update_period`` (node clock) a timer takes the latest window from the
:class:`~ctid_ros.streaming.buffer.SampleBuffer` and calls
:meth:`IdentificationSession.update`. The timer only wakes a dedicated estimation thread, so
samples keep being buffered while an estimate is computed, whatever the executor.
:func:`main` spins a single-threaded executor: with two 1 kHz Float64 streams
(``bench/node_throughput.py``), rclpy's ``MultiThreadedExecutor`` lost messages even without
estimating, the single-threaded one took all. The services share a mutually exclusive
callback group and the subscriptions a reentrant one, so the node works in a multi-threaded
executor as well; under the single-threaded one ``~/estimate_now`` holds up the intake while
it computes.

Outputs: the topics, types, layouts and status levels of
:mod:`ctid_ros.streaming.contract` (``~/estimate``, ``~/estimate_std``, ``~/params/<name>``,
``~/prediction`` if ``publish_prediction``, ``/diagnostics`` with the per-stream sample counters
added), built there as plain data and converted here to rclpy messages; ``ctid replay
--output`` writes the same. Services ``~/reset`` and ``~/estimate_now`` (``std_srvs/Trigger``).
"""

import functools
import math
import signal
import sys
import threading
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

from ctid_ros.errors import ConfigError, CtidError, DataError
from ctid_ros.ros.messages import import_message, to_message
from ctid_ros.streaming.buffer import INPUT, OUTPUT, SampleBuffer, StreamStats
from ctid_ros.streaming.config import IdentificationConfig, PARAMETER_NAMES, PARAMETERS
from ctid_ros.streaming.contract import (DEFAULT_NODE_NAME, diagnostics_message, ERROR,
                                         estimate_messages, estimate_summary, failure_status,
                                         NANOSECONDS, NodeTopics, OutputMessage, update_status,
                                         WARN)
from ctid_ros.streaming.sampler import MessageSampler
from ctid_ros.streaming.session import buffer_capacity, IdentificationSession, Update
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

__all__ = ['IdentificationNode', 'main', 'parameter_value', 'run_node']

# Highest message rate the ring buffer is sized for when it exceeds 1/sample_time.
MAX_RATE = 1000.0
TOPIC_CHECK_PERIOD = 0.5
ERROR_LOG_PERIOD = 10.0
_INT64_MAX = 2 ** 63 - 1
# Changing one of these rebuilds the sample buffer (its gap rules or size depend on them).
_BUFFER_PARAMETERS = ('window', 'sample_time', 'max_gap', 'reorder_horizon')
_ARRAY_TYPES = {'string_array': Parameter.Type.STRING_ARRAY,
                'double_array': Parameter.Type.DOUBLE_ARRAY}


def _descriptor(spec) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(
        name=spec.name, type=getattr(ParameterType, spec.type_name),
        description=spec.description, additional_constraints=spec.constraints,
        read_only=spec.read_only)
    if spec.minimum is not None and spec.kind == 'double':
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(spec.minimum), to_value=math.inf, step=0.0)]
    elif spec.minimum is not None and spec.kind == 'integer':
        descriptor.integer_range = [IntegerRange(
            from_value=int(spec.minimum), to_value=_INT64_MAX, step=0)]
    return descriptor


def _initial_value(spec) -> Any:
    """Return the declaration default; arrays are declared by type (rclpy types [] as bytes)."""
    return _ARRAY_TYPES.get(spec.kind, spec.default)


def parameter_value(node: Node, name: str, default: Any = None) -> Any:
    """Return a declared parameter's value, or ``default`` if it was declared by type only."""
    try:
        return node.get_parameter(name).value
    except ParameterUninitializedException:
        return default


class IdentificationNode(Node):
    """Identify a grey-box model from two live topics; publish estimates and diagnostics."""

    def __init__(self, **kwargs):
        super().__init__(DEFAULT_NODE_NAME, **kwargs)
        for spec in PARAMETERS:
            self.declare_parameter(spec.name, _initial_value(spec), _descriptor(spec))
        self._config = IdentificationConfig.from_dict(
            {spec.name: parameter_value(self, spec.name, spec.default) for spec in PARAMETERS})
        self._session = IdentificationSession(self._config)
        # Guards the session and the buffer swap against the parameter callback.
        self._lock = threading.Lock()
        self._sampler = self._new_sampler(self._config)
        self._buffer = self._new_buffer(self._config)
        self._field_errors = {INPUT: 0, OUTPUT: 0}
        self._last_received: Dict[str, Optional[int]] = {INPUT: None, OUTPUT: None}
        # Roles whose unreadable field was logged: once per field configuration.
        self._logged_fields = set()
        self._topic_subscriptions: Dict[str, Any] = {}
        self._waiting: Dict[str, str] = {}
        self._estimation_group = MutuallyExclusiveCallbackGroup()
        self._sample_group = ReentrantCallbackGroup()
        self._qos = QoSProfile(depth=self._config.qos_depth, reliability=(
            ReliabilityPolicy.RELIABLE if self._config.qos_reliability == 'reliable'
            else ReliabilityPolicy.BEST_EFFORT))
        self._node_topics = NodeTopics(self.get_fully_qualified_name())
        # The fixed topics exist from the start, so subscribers can match before the first
        # update; a parameter's topic is created with its first value.
        self._topic_publishers: Dict[str, Any] = {}
        for message in (*estimate_messages(self._node_topics, (), (), (), ()),
                        diagnostics_message(self._node_topics, 0, WARN, '', {})):
            self._publisher(message)
        self.create_service(Trigger, '~/reset', self._reset,
                            callback_group=self._estimation_group)
        self.create_service(Trigger, '~/estimate_now', self._estimate_now,
                            callback_group=self._estimation_group)
        self._wakeup = threading.Event()
        self._stopping = False
        self._tick: Optional[float] = None
        # Estimation runs in its own thread, so even a single-threaded executor keeps taking
        # samples while an estimate is computed.
        self._worker = threading.Thread(target=self._work, name='ctid_estimator', daemon=True)
        self._worker.start()
        self._timer = self._create_update_timer()
        self._topic_timer = self.create_timer(TOPIC_CHECK_PERIOD, self._connect,
                                              callback_group=self._sample_group)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.last_update: Optional[Update] = None
        self._connect()

    @property
    def config(self) -> IdentificationConfig:
        """Return the configuration in use."""
        return self._config

    @property
    def buffer(self) -> SampleBuffer:
        """Return the sample buffer."""
        return self._buffer

    def _new_sampler(self, config: IdentificationConfig) -> MessageSampler:
        return MessageSampler(config, (self.resolve_topic_name(config.input_topic),
                                       self.resolve_topic_name(config.output_topic)))

    def _new_buffer(self, config: IdentificationConfig) -> SampleBuffer:
        rate = max(1.0 / config.sample_time, MAX_RATE)
        return self._sampler.buffer(buffer_capacity(config, rate), config)

    def _create_update_timer(self):
        return self.create_timer(self._config.update_period, self._on_timer,
                                 callback_group=self._estimation_group)

    # Input ---------------------------------------------------------------------------------

    def _connect(self) -> None:
        """Subscribe to every topic whose type the graph now knows; note the others."""
        sampler = self._sampler
        pending = {topic: sampler.roles(topic) for topic in sampler.topics
                   if topic not in self._topic_subscriptions}
        if not pending:
            self._topic_timer.cancel()
            return
        graph = dict(self.get_topic_names_and_types())
        for topic, roles in pending.items():
            types = graph.get(topic)
            if not types:
                self._waiting[topic] = (f'no publisher on {topic} yet: waiting to learn its '
                                        'message type')
                continue
            try:
                message_type = import_message(types[0])
            except ConfigError as error:
                self._waiting[topic] = str(error)
                continue
            callback = functools.partial(self.receive, topic)
            self._topic_subscriptions[topic] = self.create_subscription(
                message_type, topic, callback, self._qos, callback_group=self._sample_group)
            self._waiting.pop(topic, None)
            self.get_logger().info(f'subscribed to {topic} ({types[0]}) for the '
                                   f'{" and ".join(roles)}')

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
        sampler = self._sampler
        roles = sampler.roles(topic)
        received = self.get_clock().now().nanoseconds
        for role in roles:
            self._last_received[role] = received
        sample = sampler(topic, self._receive_stamp(info or {}), message)
        for role, error in sample.errors:
            self._field_errors[role] += 1
            if role not in self._logged_fields:
                self._logged_fields.add(role)
                self.get_logger().error(f'{role}: {error}')
        sample.add_to(self._buffer)

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
                self.estimate(self._tick)
            except Exception as error:  # noqa: B902 - a bug must not stop the estimates
                self.get_logger().error(f'estimation failed: {error!r}')
                self._publish_status(ERROR, f'internal error: {error!r}', {})

    def destroy_node(self) -> None:
        """Stop the estimation thread, then destroy the node."""
        self._stopping = True
        self._wakeup.set()
        self._worker.join()
        super().destroy_node()

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
            The update (None if it failed) and a one-line summary or the error.

        """
        started = time.perf_counter() if started is None else started
        with self._lock:
            config, buffer = self._config, self._buffer
            try:
                self._check_silence(config, buffer)
                window = self._session.take_window(buffer)
                update = self._session.update(window)
            except CtidError as error:
                return None, self._failed(error)
        self.last_update = update
        self._publish(update, config)
        diagnostics = update.diagnostics()
        diagnostics['publish_latency'] = time.perf_counter() - started
        self._publish_status(*update_status(update.names, update.values, update.stds,
                                            diagnostics), diagnostics)
        return update, estimate_summary(update.names, update.values, update.stds)

    def _check_silence(self, config: IdentificationConfig, buffer: SampleBuffer) -> None:
        """
        Refuse to estimate again from stale data when a stream stopped.

        The buffer's windows end at its newest data, so without this check a dead publisher
        would go unnoticed: the same last window would be estimated over and over.
        """
        now = self.get_clock().now().nanoseconds
        limit = max(config.max_gap, config.update_period)
        for role, name in zip((INPUT, OUTPUT), buffer.names):
            last = self._last_received[role]
            if last is not None and now - last > limit * NANOSECONDS:
                silence = (now - last) / NANOSECONDS
                raise DataError(f'{name} silent: no message for {silence:.3g} s (more than '
                                f'{limit:g} s); check its publisher')

    def _failed(self, error: CtidError) -> str:
        level, text = failure_status(error)
        self.get_logger().warning(f'no estimate: {text}', throttle_duration_sec=ERROR_LOG_PERIOD)
        self._publish_status(level, text, {})
        return text

    def _publisher(self, message: OutputMessage) -> Tuple[Any, type]:
        """Return the publisher of a message's topic and its class, created on first use."""
        if message.topic not in self._topic_publishers:
            message_class = import_message(message.msgtype)
            self._topic_publishers[message.topic] = (
                self.create_publisher(message_class, message.topic, 10), message_class)
        return self._topic_publishers[message.topic]

    def _send(self, message: OutputMessage) -> None:
        publisher, message_class = self._publisher(message)
        publisher.publish(to_message(message_class, message.fields))

    def _publish(self, update: Update, config: IdentificationConfig) -> None:
        for message in estimate_messages(
                self._node_topics, update.names, update.values, update.stds,
                update.prediction if config.publish_prediction else None):
            self._send(message)

    def _stream_values(self, role: str, stats: StreamStats) -> Dict[str, Any]:
        return {f'{role}_{key}': value for key, value in (
            ('received', stats.received), ('accepted', stats.accepted),
            ('duplicates', stats.duplicates), ('late', stats.late),
            ('non_finite', stats.non_finite), ('out_of_clock', stats.out_of_clock),
            ('pending', stats.pending), ('reanchors', stats.reanchors),
            ('evicted', stats.evicted), ('field_errors', self._field_errors[role]))}

    def _publish_status(self, level: int, text: str, values: Dict[str, Any]) -> None:
        stats = self._buffer.stats()
        values = {**values, **self._stream_values(INPUT, stats.u),
                  **self._stream_values(OUTPUT, stats.y)}
        if self._waiting:
            level = max(level, WARN)
            text = '; '.join([*self._waiting.values(), text])
        now = self.get_clock().now().nanoseconds
        self._send(diagnostics_message(self._node_topics, now, level, text, values))

    # Services and parameters ---------------------------------------------------------------

    def reset(self) -> None:
        """Forget all samples, counters and the warm start."""
        with self._lock:
            self._buffer.clear()
            self._session.reset()
            self._field_errors = {INPUT: 0, OUTPUT: 0}
            self._last_received = {INPUT: None, OUTPUT: None}

    def _reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.reset()
        response.success, response.message = True, 'buffer cleared, warm start forgotten'
        return response

    def _estimate_now(self, request: Trigger.Request,
                      response: Trigger.Response) -> Trigger.Response:
        update, response.message = self.estimate()
        response.success = update is not None
        return response

    def _on_set_parameters(self, parameters: List[Parameter]) -> SetParametersResult:
        spec_defaults = {spec.name: spec.default for spec in PARAMETERS}
        changes = {parameter.name: spec_defaults[parameter.name] if parameter.value is None
                   else parameter.value
                   for parameter in parameters if parameter.name in PARAMETER_NAMES}
        if not changes:
            return SetParametersResult(successful=True)
        try:
            config = self._config.updated(changes)
        except ConfigError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self._apply(config)
        return SetParametersResult(successful=True)

    def _apply(self, config: IdentificationConfig) -> None:
        old = self._config
        with self._lock:
            self._sampler = self._new_sampler(config)
            if config.input_fields != old.input_fields or config.output_field != old.output_field:
                self._logged_fields = set()
            if any(getattr(config, name) != getattr(old, name) for name in _BUFFER_PARAMETERS):
                self._buffer = self._new_buffer(config)
            self._session.reconfigure(config)
            self._config = config
        if config.update_period != old.update_period:
            self.destroy_timer(self._timer)
            self._timer = self._create_update_timer()
        self.get_logger().info('configuration updated')


def _interrupt(signal_number: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run_node(factory: Callable[[], Node], name: str, args: Optional[List[str]] = None) -> int:
    """
    Spin the node made by ``factory`` until Ctrl-C or SIGTERM.

    Both signals interrupt the spinning thread, which then destroys the node before the context
    goes, so no callback or publication meets an invalid context.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
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
    return run_node(IdentificationNode, DEFAULT_NODE_NAME, args)


if __name__ == '__main__':
    sys.exit(main())
