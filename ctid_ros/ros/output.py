"""
The node's output: its publishers, the estimates, the change alarm and ``/diagnostics``.

The topics, types, layouts, QoS and status levels are those of
:mod:`ctid_ros.streaming.contract` (``~/estimate``, ``~/estimate_std``,
``~/estimate_covariance``, ``~/params/<name>``, ``~/alarm`` and ``~/tuning`` (with
``tune.controller``) transient-local,
``~/prediction`` if ``publish_prediction``, ``/diagnostics`` with the per-stream counters and
the alarm added), built there as plain data and converted here to rclpy messages;
``ctid replay --output`` writes the same. One INFO line per estimate, at most one a second
(:data:`INFO_PERIOD`).

:class:`Publishers` holds one lifecycle publisher per topic, created on first use and removed
when the configuration no longer has its topic (``~/params/J`` goes with a model without
``J``). :class:`Reporting` is the part of the identification node that publishes; it reads
the node's configuration, buffer and counters, and counts the internal errors it reports.
"""

import threading
import time
from typing import Any, Callable, Dict, Iterable, Optional, Tuple

from ctid_ros.ros.messages import import_message, to_message
from ctid_ros.streaming.alarm import AlarmStatus
from ctid_ros.streaming.buffer import INPUT, OUTPUT, StreamStats
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import (alarm_message, diagnostics_message, ERROR,
                                         estimate_line, estimate_messages, NodeTopics, OK,
                                         OutputMessage, PublisherQos, WARN)
from ctid_ros.streaming.session import Update
from rclpy.lifecycle import LifecycleNode
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['ERROR_LOG_PERIOD', 'INFO_PERIOD', 'Publishers', 'Reporting', 'output_topics']

# Seconds between two logs of the same error.
ERROR_LOG_PERIOD = 10.0
# One INFO line per estimate, at most this often (s).
INFO_PERIOD = 1.0
_RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE,
                'best_effort': ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {'transient_local': DurabilityPolicy.TRANSIENT_LOCAL,
               'volatile': DurabilityPolicy.VOLATILE}


def _qos_profile(qos: PublisherQos) -> QoSProfile:
    return QoSProfile(depth=qos.depth, reliability=_RELIABILITY[qos.reliability],
                      durability=_DURABILITY[qos.durability])


def output_topics(topics: NodeTopics, config: IdentificationConfig) -> Tuple[str, ...]:
    """Return every topic a node with ``config`` publishes on."""
    return (topics.estimate, topics.estimate_std, topics.estimate_covariance, topics.alarm,
            topics.diagnostics, *(topics.prediction for _ in range(config.publish_prediction)),
            *(topics.param(name) for name in config.names),
            *(topics.tuning for _ in range(bool(config.tune_controller))),
            *(topics.model_recommendation for _ in range(bool(config.candidate_models))))


class Publishers:
    """
    The lifecycle publishers of a node, one per topic, created when first needed.

    Parameters
    ----------
    node : LifecycleNode
        The node that publishes.
    usable : callable
        Returns (configured, active): nothing is created unconfigured, and a publisher
        created while active is activated at once.

    """

    def __init__(self, node: LifecycleNode, usable: Callable[[], Tuple[bool, bool]]) -> None:
        self._node = node
        self._usable = usable
        self._lock = threading.Lock()
        self._publishers: Dict[str, Tuple[Any, type]] = {}
        self._closed = False

    def ensure(self, message: OutputMessage) -> Optional[Tuple[Any, type]]:
        """Return the publisher of a message's topic and its class, None unconfigured."""
        with self._lock:
            return self._ensure(message)

    def _ensure(self, message: OutputMessage) -> Optional[Tuple[Any, type]]:
        if message.topic not in self._publishers:
            configured, active = self._usable()
            if not configured or self._closed:
                return None
            message_class = import_message(message.msgtype)
            publisher = self._node.create_lifecycle_publisher(
                message_class, message.topic, _qos_profile(message.qos))
            if active:
                publisher.on_activate(None)
            self._publishers[message.topic] = (publisher, message_class)
        return self._publishers[message.topic]

    def send(self, message: OutputMessage) -> None:
        """Publish ``message`` (nothing while unconfigured or once closed)."""
        with self._lock:
            found = None if self._closed else self._ensure(message)
            if found is not None:
                publisher, message_class = found
                publisher.publish(to_message(message_class, message.fields))

    def close(self) -> None:
        """
        Publish nothing more, also from a thread still running (before the node goes).

        Waits for a publication in progress; the publishers themselves go with the node.
        """
        with self._lock:
            self._closed = True

    def keep_only(self, topics: Iterable[str]) -> None:
        """Remove the publishers of every topic not in ``topics`` (all with none)."""
        keep = set(topics)
        with self._lock:
            gone = [publisher for topic, (publisher, _) in self._publishers.items()
                    if topic not in keep]
            self._publishers = {topic: entry for topic, entry in self._publishers.items()
                                if topic in keep}
        for publisher in gone:
            self._node.destroy_lifecycle_publisher(publisher)


class Reporting:
    """
    Publishing the estimates, the alarm and the status; logging them.

    A part of :class:`~ctid_ros.ros.node.IdentificationNode`, not usable alone.
    """

    def _publish(self, update: Update, config: IdentificationConfig) -> None:
        for message in estimate_messages(
                self._node_topics, update.names, update.values, update.stds,
                update.prediction if config.publish_prediction else None,
                covariance=update.covariance):
            self._outputs.send(message)

    def _publish_alarm(self, alarm: AlarmStatus) -> None:
        """Publish the change alarm on ``~/alarm`` (latched)."""
        config = self._config
        if config is None:
            return
        origin = self._origin()
        self._outputs.send(alarm_message(self._node_topics, alarm.level, alarm.text(origin),
                                         alarm.values(origin), hardware_id=config.hardware_id))

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
                      'skipped_ticks': self._worker.skipped_ticks,
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
            self._outputs.send(diagnostics_message(self._node_topics, now, level, text, values,
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
