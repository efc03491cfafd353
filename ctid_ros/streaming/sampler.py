"""
Messages to samples: the one rule the live node and the offline replay share.

A message on the input topic gives an input sample (one value per input field), a message on
the output topic an output sample, a message on a topic carrying both (``/joint_states``) one
of each with the same stamp. The stamp is ``header.stamp`` when ``stamp_source`` is ``header``
and the message has a non-zero one, else the receive time the caller passes: the DDS source
or reception time live, the recorder's log time in a bag
(:func:`~ctid_ros.streaming.message_fields.sample_stamp`). The streams are labelled the same
way in both, e.g. ``input /plant/u (data)``, in every message about them.
"""

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.buffer import INPUT, OUTPUT, SampleBuffer
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.message_fields import (extract_values, has_header_stamp, message_stamp,
                                               MissingElementError, parse_field_path,
                                               sample_stamp)
import numpy as np

__all__ = ['FieldErrors', 'MessageSampler', 'ROLES', 'Sample', 'WRONG_PATH_MESSAGES',
           'message_type', 'normalized_type', 'stream_names']

ROLES = (INPUT, OUTPUT)
# Messages of a stream that fail on a path their type cannot hold, none read, before a replay
# stops on a wrong path (a type that holds it may come later: it is read then).
WRONG_PATH_MESSAGES = 1000


def stream_names(config: IdentificationConfig, topics: Tuple[str, str]) -> Tuple[str, str]:
    """Return the labels of the input and output streams, e.g. ``input /plant/u (data)``."""
    return (f'{INPUT} {topics[0]} ({", ".join(config.input_fields)})',
            f'{OUTPUT} {topics[1]} ({config.output_field})')


@dataclass(frozen=True)
class Sample:
    """
    What one message carries.

    Attributes
    ----------
    stamp_ns : int
        Stamp of the samples.
    u : float or ndarray or None
        Input value (a row for several inputs); None if the message is not on the input topic
        or its input field could not be read.
    y : float or None
        Output value; None likewise.
    errors : tuple of (str, ConfigError)
        The role (``input``/``output``) and error of every field that could not be read.
    zero_stamp : bool
        True if ``stamp_source`` is ``header`` and the message has a header whose stamp is
        zero (unset): it was filed under the receive time instead.

    """

    stamp_ns: int
    u: Optional[Union[float, np.ndarray]]
    y: Optional[float]
    errors: Tuple[Tuple[str, ConfigError], ...] = ()
    zero_stamp: bool = False

    def add_to(self, buffer: SampleBuffer) -> None:
        """
        Append the samples to ``buffer``, input and output atomically when both are set.

        The first sample given to a buffer without a time origin becomes its origin
        (:attr:`SampleBuffer.origin_ns`), as it is the live node's: its messages then count
        seconds from the first sample, like the node's own.
        """
        if buffer.origin_ns is None and (self.u is not None or self.y is not None):
            buffer.origin_ns = self.stamp_ns
        if self.u is not None and self.y is not None:
            buffer.add_pair(self.stamp_ns, self.u, self.y)
        elif self.u is not None:
            buffer.add_input(self.stamp_ns, self.u)
        elif self.y is not None:
            buffer.add_output(self.stamp_ns, self.y)


class MessageSampler:
    """
    Turn messages of the configured input and output topics into :class:`Sample` objects.

    Parameters
    ----------
    config : IdentificationConfig
        Field paths and stamp source.
    topics : (str, str)
        Absolute input and output topics (the same topic for both is allowed).

    Raises
    ------
    ConfigError
        If a field path is malformed.

    """

    def __init__(self, config: IdentificationConfig, topics: Tuple[str, str]):
        self.topics = tuple(topics)
        self.names = stream_names(config, self.topics)
        self._paths = (tuple(parse_field_path(path) for path in config.input_fields),
                       (parse_field_path(config.output_field),))
        self._inputs = len(config.input_fields)
        self._stamp_source = config.stamp_source

    def roles(self, topic: str) -> Tuple[str, ...]:
        """Return which roles ``topic`` carries: ``input``, ``output``, both or none."""
        return tuple(role for role, wanted in zip(ROLES, self.topics) if topic == wanted)

    def buffer(self, capacity: int, config: IdentificationConfig,
               previous: Optional[SampleBuffer] = None) -> SampleBuffer:
        """
        Return a buffer for these streams, with the gap rules of ``config``.

        It is empty, or holds the samples of ``previous`` that still fit, for each stream
        whose topic and fields are unchanged (:meth:`SampleBuffer.carry_over`): a runtime
        change of the window keeps the data already received. Samples pushed out count as
        evicted only if a window of ``config`` would still have used them.
        """
        buffer = SampleBuffer(capacity, max_gap=config.max_gap,
                              reorder_horizon=config.reorder_horizon, names=self.names,
                              inputs=self._inputs,
                              history=config.history_span + config.max_gap +
                              config.reorder_horizon)
        if previous is not None:
            buffer.carry_over(previous)
        return buffer

    def __call__(self, topic: str, receive_ns: int, msg: Any) -> Sample:
        """
        Return the samples ``msg`` carries, received on ``topic`` at ``receive_ns``.

        A field that cannot be read is reported in :attr:`Sample.errors`, not raised: the
        live node counts it and goes on, the replay too unless the path is wrong
        (:class:`FieldErrors`).
        """
        values = [None, None]
        errors = []
        for index, (role, wanted, paths) in enumerate(zip(ROLES, self.topics, self._paths)):
            if topic != wanted:
                continue
            try:
                values[index] = extract_values(msg, paths)
            except ConfigError as error:
                errors.append((role, error))
        stamp = sample_stamp(msg, receive_ns, self._stamp_source)
        zero = (self._stamp_source == 'header' and stamp == int(receive_ns)
                and has_header_stamp(msg) and message_stamp(msg) is None)
        return Sample(stamp, *values, tuple(errors), zero_stamp=zero)


class FieldErrors:
    """
    The messages of a replay whose configured field could not be read, per role.

    The live node counts such a message (``field_errors`` on ``/diagnostics``), takes what
    else it carries and goes on, and reads a topic only as a type whose fields hold the paths
    (a ``std_msgs/String`` publisher beside the ``Float64`` one is ignored); so does the
    replay, which then gives the node's estimates on the same messages. A message that lacks
    the selected element (:class:`~ctid_ros.streaming.message_fields.MissingElementError`: a
    joint another driver publishes on the same ``/joint_states``, an ``effort`` array left
    empty at times) is skipped and counted; a message of a type that cannot hold the path (no
    such field, not a number) is ignored and counted by its type. A stream of which no
    message could be read raises its first error (a wrong path): at the end of the replay
    (:meth:`check`), or at once after :data:`WRONG_PATH_MESSAGES` messages of types without
    the path. It also counts the messages whose ``header.stamp`` is unset (zero), filed
    under their log time, as the node counts ``zero_stamps``: their dead time then includes
    the delay to the recorder.

    Parameters
    ----------
    names : (str, str)
        Labels of the input and output streams (:func:`stream_names`).

    """

    def __init__(self, names: Sequence[str]):
        self.names = dict(zip(ROLES, names))
        self.read = dict.fromkeys(ROLES, 0)
        self.failed = dict.fromkeys(ROLES, 0)
        self.first: Dict[str, ConfigError] = {}
        self.unstamped = dict.fromkeys(ROLES, 0)
        # Messages of a type without the path, and its error, by role and type.
        self.misfits: Dict[Tuple[str, str], Tuple[int, ConfigError]] = {}

    def add(self, sample: Sample, roles: Sequence[str], kind: str) -> None:
        """Count one message of type ``kind`` carrying ``roles``."""
        failed = dict(sample.errors)
        for role in roles:
            self.unstamped[role] += sample.zero_stamp
            if role in failed:
                self.fail(role, failed[role], kind)
            else:
                self.read[role] += 1

    def fail(self, role: str, error: ConfigError, kind: str, count: int = 1) -> None:
        """
        Count ``count`` messages of type ``kind`` whose ``role`` field failed with ``error``.

        Raises
        ------
        ConfigError
            The stream's first error, if no message of it was read and
            :data:`WRONG_PATH_MESSAGES` of types without the path failed.

        """
        if isinstance(error, MissingElementError):
            self.failed[role] += count
            self.first.setdefault(role, error)
            return
        before, first = self.misfits.get((role, kind), (0, error))
        self.misfits[role, kind] = (before + count, first)
        if not self.read[role] and sum(number for (which, _), (number, _) in
                                       self.misfits.items() if which == role) \
                >= WRONG_PATH_MESSAGES:
            raise self._errors(role)[0]

    def merge(self, other: 'FieldErrors') -> None:
        """Add the counts of ``other`` (the errors of a later block of messages)."""
        for role in ROLES:
            self.read[role] += other.read[role]
            self.unstamped[role] += other.unstamped[role]
            if other.failed[role]:
                self.fail(role, other.first[role], '', other.failed[role])
        for (role, kind), (count, error) in other.misfits.items():
            self.fail(role, error, kind, count)

    def _errors(self, role: str) -> List[ConfigError]:
        return [error for (which, _), (_, error) in self.misfits.items() if which == role] + \
            ([self.first[role]] if role in self.first else [])

    def check(self) -> None:
        """Raise the first error of a stream whose every message failed (a wrong path)."""
        for role in ROLES:
            errors = self._errors(role)
            if errors and not self.read[role]:
                raise errors[0]

    def warnings(self) -> List[str]:
        """Say for each stream how many messages were skipped, ignored or unstamped, and why."""
        notes = [f'{self.names[role]}: {self.failed[role]} of '
                 f'{self.failed[role] + self.read[role]} messages skipped, as the live node skips '
                 f'them: {self.first[role]}' for role in ROLES if self.failed[role]]
        notes += [f'{self.names[role]}: {count} messages of {kind} ignored, as the live node '
                  f'ignores a type without the field: {error}'
                  for (role, kind), (count, error) in self.misfits.items()]
        notes += [f'{self.names[role]}: header.stamp unset (zero) in {self.unstamped[role]} '
                  'messages, filed under their log time (when the recorder received them), as '
                  'the live node files them under the receive time; a dead time then includes '
                  'the delay to the recorder' for role in ROLES if self.unstamped[role]]
        return notes


def message_type(msg: Any) -> str:
    """Return the type name of a decoded message (rosbags or mcap_ros2), as in a bag."""
    return normalized_type(str(getattr(msg, '__msgtype__', None)
                               or getattr(type(msg), '_type', None) or type(msg).__name__))


def normalized_type(name: str) -> str:
    """Return a type name in its full form: ``std_msgs/Float64`` is ``std_msgs/msg/Float64``."""
    package, _, base = name.partition('/')
    return f'{package}/msg/{base}' if base and '/' not in base else name
