"""
The node's input: which message type to read each topic as, the subscriptions, the samples.

Inputs are the input and output topics of the configuration, one number per message read by a
field path; one subscription serves both when they share a topic. The message type is learnt
from the publishers on the graph and re-checked every :data:`TOPIC_CHECK_PERIOD`: among the
types published on a topic the node takes one whose fields hold the configured paths
(:func:`~ctid_ros.ros.messages.field_problem`), keeps it while it is published, and
resubscribes when only another fitting type is left (the old subscription is destroyed before
the new one is created: Fast DDS refuses a second type on a topic in one participant), so a
publisher of a wrong type (a ``std_msgs/String`` on the output topic) can neither capture the
subscription nor hide the right one; the conflict is reported on ``/diagnostics``.

Each sample is stamped with ``header.stamp`` (``stamp_source: header`` and a non-zero stamp),
else the DDS source timestamp of the message, else its reception time; under ``use_sim_time``
the node's clock replaces the DDS times, which are wall-clock.

:class:`TopicIntake` is the part of the identification node that does this; it owns
``_topic_subscriptions`` and ``_counters``, reads ``_config``, ``_sampler`` and ``_buffer``
(under ``_lock``), and writes the notes shown on ``/diagnostics`` (``_notes``).
"""

import functools
from typing import Any, Dict, List, Mapping, Optional, Tuple

from ctid_ros.errors import ConfigError
from ctid_ros.ros.messages import field_problem, import_message
from ctid_ros.streaming.buffer import INPUT
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import count_change
from ctid_ros.streaming.message_fields import parse_field_path
from ctid_ros.streaming.sampler import ROLES
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.qos import QoSProfile, ReliabilityPolicy

__all__ = ['Counters', 'RELIABILITY', 'TOPIC_CHECK_PERIOD', 'TopicIntake']

# Seconds between two looks at the publishers of the input topics.
TOPIC_CHECK_PERIOD = 0.5
RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE,
               'best_effort': ReliabilityPolicy.BEST_EFFORT}


def _importable(type_name: str) -> bool:
    try:
        import_message(type_name)
    except ConfigError:
        return False
    return True


class Counters:
    """What the node counts beyond the buffer's admission counters, per role."""

    def __init__(self):
        self.field_errors = dict.fromkeys(ROLES, 0)
        self.zero_stamps = dict.fromkeys(ROLES, 0)
        self.lost = dict.fromkeys(ROLES, 0)
        self.last_received: Dict[str, Optional[int]] = dict.fromkeys(ROLES)


class TopicIntake:
    """
    Subscribing to the input topics with a fitting type and taking their messages.

    A part of :class:`~ctid_ros.ros.node.IdentificationNode`, not usable alone.
    """

    def _paths(self, topic: str, config: Optional[IdentificationConfig] = None) -> List[Any]:
        """Return the parsed field paths of ``topic`` (of ``config``, default the node's)."""
        config = config or self._config
        paths = []
        for role in self._sampler.roles(topic):
            fields = config.input_fields if role == INPUT else (config.output_field,)
            paths.extend(parse_field_path(path) for path in fields)
        return paths

    def _published_types(self, topic: str) -> List[str]:
        return list(dict.fromkeys(info.topic_type for info in
                                  self.get_publishers_info_by_topic(topic)))

    def _unreadable_fields(self, config: IdentificationConfig) -> Optional[str]:
        """
        Say why no type published on one of the topics holds the fields of ``config``.

        None if every topic has a fitting type, or has no publisher yet, or a type this
        process cannot import: those are learnt, and the fields checked, when they are read.
        A runtime change to fields that no publisher's type has would stop the estimates
        while the publishers go on; it is refused instead.
        """
        for topic in dict.fromkeys(self._sampler.topics):
            types = self._published_types(topic)
            if not types or not all(map(_importable, types)):
                continue
            choice, _, problems = self._choose_type(topic, types, None, config)
            if choice is None:
                misfits = '; '.join(f'{name}: {problem}' for name, problem in problems.items())
                return (f'no type published on {topic} has the field(s) '
                        f'{", ".join(map(str, self._paths(topic, config)))}: {misfits}')
        return None

    def _choose_type(self, topic: str, types: List[str], current: Optional[str],
                     config: Optional[IdentificationConfig] = None
                     ) -> Tuple[Optional[str], Optional[type], Dict[str, str]]:
        """Return the type to read ``topic`` as (None if none fits), its class, the misfits."""
        paths = self._paths(topic, config)
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
            types = self._published_types(topic)
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
        """Read ``topic`` as ``type_name`` from now on, instead of ``current``."""
        with self._lock:
            old = self._topic_subscriptions.pop(topic, None)
        if old is not None:
            # First: a participant holds one type per topic, the new subscription would fail.
            self.destroy_subscription(old[0])
        callback = functools.partial(self.receive, topic)
        qos = QoSProfile(depth=self._config.qos_depth,
                         reliability=RELIABILITY[self._config.qos_reliability])
        try:
            subscription = self.create_subscription(
                message_class, topic, callback, qos, callback_group=self._sample_group,
                event_callbacks=SubscriptionEventCallbacks(
                    message_lost=functools.partial(self._lost, topic),
                    incompatible_type=lambda event: None))
        except UnsupportedEventTypeError:
            subscription = self.create_subscription(
                message_class, topic, callback, qos, callback_group=self._sample_group,
                event_callbacks=SubscriptionEventCallbacks(incompatible_type=lambda event: None))
        with self._lock:
            self._topic_subscriptions[topic] = (subscription, type_name)
        if old is not None:
            self.get_logger().warning(f'{topic}: now reading {type_name} (was {current}, no '
                                      'longer published)')
        else:
            self.get_logger().info(f'subscribed to {topic} ({type_name}) for the '
                                   f'{" and ".join(roles)}')

    def _unsubscribe_all(self) -> None:
        """Destroy every input subscription (the next topic check subscribes again)."""
        with self._lock:
            subscriptions = [subscription for subscription, _ in
                             self._topic_subscriptions.values()]
            self._topic_subscriptions = {}
        for subscription in subscriptions:
            self.destroy_subscription(subscription)

    def _follow_topics(self) -> None:
        """Forget the types chosen for the old fields: another field may fit another type."""
        with self._lock:
            self._logged = {}
            self._notes = {key: note for key, note in self._notes.items()
                           if not key.startswith('field ')}
        self._unsubscribe_all()

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
                self._counters.lost[role] += count_change(getattr(info, 'total_count_change', 0))

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
