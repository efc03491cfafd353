"""
Offline replay of recorded messages through the live node's identification pipeline.

:func:`replay_messages` turns every message of the configured input and output topics into
samples exactly as the live node does (:class:`~ctid_ros.streaming.sampler.MessageSampler`,
the same :class:`~ctid_ros.streaming.buffer.SampleBuffer` and windows) and estimates with the
node's :class:`~ctid_ros.streaming.session.IdentificationSession`. Two modes:

* default: one estimate over the whole span of the messages; the window is the span, *not* the
  configured ``window`` (which is the live node's memory, not a property of the data). If gaps
  split the span, the latest contiguous part of at least half the span is used and the
  estimate's warnings say how much was left out.
* ``sliding``: what the live node would have published. A timer fires every ``update_period``
  of log time, starting one period after the first message; each tick estimates on the last
  ``window`` seconds (warm-started from the previous tick). The buffer holds only that much
  history, so long recordings replay in bounded memory. Every estimate also goes through the
  node's change alarm (:class:`~ctid_ros.streaming.alarm.ChangeDetector`, against the
  configured baseline), so a recorded shift can be audited offline.

The messages are any iterable of ``(topic, log_time_ns, msg)``, so the same code path can be
checked against the live node fed the same messages. Reading bags, the ``ctid replay`` command,
its reports and figures are :mod:`ctid_ros.cli.replay`.
"""

from array import array
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, List, NamedTuple, Optional, Sequence, Tuple

from ctid_ros.errors import DataError, EstimationError
from ctid_ros.streaming.alarm import AlarmStatus, ChangeDetector
from ctid_ros.streaming.baseline import configured_baseline
from ctid_ros.streaming.buffer import BufferStats, INPUT, OUTPUT, resample
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import failure_status, NANOSECONDS, resolve_topic
from ctid_ros.streaming.sampler import FieldErrors, message_type, MessageSampler
from ctid_ros.streaming.session import buffer_capacity, IdentificationSession, Update
import numpy as np

__all__ = ['Replay', 'SampleColumns', 'SkippedTick', 'replay_columns', 'replay_messages']


class SkippedTick(NamedTuple):
    """
    A tick of the sliding replay that gave no estimate, as the live node reports it.

    Attributes
    ----------
    time_ns : int
        Log time of the tick.
    level : int
        Status level (:func:`~ctid_ros.streaming.contract.failure_status`): WARN while the data
        do not suffice, ERROR when the estimation failed.
    reason : str
        Why.

    """

    time_ns: int
    level: int
    reason: str


@dataclass(frozen=True)
class Replay:
    """
    The outcome of :func:`replay_messages`.

    Attributes
    ----------
    updates : list of Update
        One estimate (default mode), or one per successful tick (``sliding``), in time order.
    stats : BufferStats
        Admission counters of the input and output streams (non-finite, duplicates, late).
    messages : int
        Messages consumed on the two topics.
    skipped : list of SkippedTick
        Ticks (sliding mode) that gave no estimate and why: too little contiguous data yet, or
        an estimation failure. The live node reports those on ``/diagnostics``.
    alarms : list of AlarmStatus
        Sliding mode: the change alarm after each update (same length as ``updates``);
        empty in the default mode.
    warnings : list of str
        What the replay skipped: messages that lack the selected element, per stream
        (:meth:`~ctid_ros.streaming.sampler.FieldErrors.warnings`).

    """

    updates: List[Update]
    stats: BufferStats
    messages: int
    skipped: List[SkippedTick]
    alarms: List[AlarmStatus] = field(default_factory=list)
    warnings: List[str] = field(default_factory=list)


@dataclass(frozen=True)
class SampleColumns:
    """
    The samples of consecutive messages of the input and output topics, as arrays.

    What :class:`~ctid_ros.streaming.sampler.MessageSampler` makes of each message, for a
    block of messages at once (see :mod:`ctid_ros.files.columns`).

    Attributes
    ----------
    log_time_ns : ndarray of int64
        Log (arrival) time of each message of the block, in arrival order.
    input_index, output_index : ndarray of int64
        Index in the block of the message of each input (output) sample, increasing.
    input_stamps, output_stamps : ndarray of int64
        The samples' stamps (the sampler's stamp rule).
    input_values : ndarray
        Input values: one per sample, or a row per sample for several inputs.
    output_values : ndarray
        Output values.
    field_errors : FieldErrors, optional
        The block's messages read and skipped per stream; None: every message of the block
        on a stream's topic gave its sample.

    """

    log_time_ns: np.ndarray
    input_index: np.ndarray
    input_stamps: np.ndarray
    input_values: np.ndarray
    output_index: np.ndarray
    output_stamps: np.ndarray
    output_values: np.ndarray
    field_errors: Optional[FieldErrors] = None

    def count_into(self, errors: FieldErrors) -> None:
        """Add the block's messages read and skipped to ``errors``."""
        if self.field_errors is not None:
            errors.merge(self.field_errors)
        else:
            errors.read[INPUT] += self.input_index.size
            errors.read[OUTPUT] += self.output_index.size


def replay_columns(blocks: Iterable[SampleColumns], config: IdentificationConfig, *,
                   sliding: bool = False, topics: Optional[Tuple[str, str]] = None,
                   capacity: Optional[int] = None,
                   detector: Optional[ChangeDetector] = None,
                   origin_ns: Optional[int] = None) -> Replay:
    """
    Replay blocks of samples as :func:`replay_messages` replays the messages they came from.

    The samples are admitted to the same buffer (whole arrays at once, by
    :meth:`~ctid_ros.streaming.buffer.SampleBuffer.add_inputs`, which gives the buffer that
    appending them one by one gives) and estimated by the same session; the sliding ticks fire
    between the same messages. Same arguments, results and errors as :func:`replay_messages`.
    """
    return _dispatch(blocks, config, topics, sliding, capacity, detector, origin_ns,
                     _columns_span, _columns_sliding)


def _dispatch(source, config: IdentificationConfig, topics: Optional[Tuple[str, str]],
              sliding: bool, capacity: Optional[int], detector: Optional[ChangeDetector],
              origin_ns: Optional[int], span: Callable, slide: Callable) -> Replay:
    """Resolve the defaults of a replay and run ``slide`` (sliding) or ``span`` on ``source``."""
    if topics is None:
        topics = (resolve_topic(config.input_topic), resolve_topic(config.output_topic))
    sampler = MessageSampler(config, topics)
    if sliding:
        capacity = capacity or buffer_capacity(config, 1.0 / config.sample_time)
        return slide(source, config, sampler, capacity, detector or _detector(config), origin_ns)
    return span(source, config, sampler)


def _detector(config: IdentificationConfig) -> ChangeDetector:
    """Return the node's change detector with its configured baseline."""
    return ChangeDetector.from_config(config, configured_baseline(config)[0])


def _columns_span(blocks: Iterable[SampleColumns], config: IdentificationConfig,
                  sampler: MessageSampler) -> Replay:
    parts: List[SampleColumns] = []
    count = 0
    errors = FieldErrors(sampler.names)
    for block in blocks:
        count += block.log_time_ns.size
        block.count_into(errors)
        parts.append(block)
    errors.check()
    inputs = len(config.input_fields)
    u_stamps = np.concatenate([np.zeros(0, np.int64)] + [part.input_stamps for part in parts])
    y_stamps = np.concatenate([np.zeros(0, np.int64)] + [part.output_stamps for part in parts])
    empty = np.zeros((0, inputs)) if inputs > 1 else np.zeros(0)
    u = np.concatenate([empty] + [part.input_values for part in parts])
    y = np.concatenate([np.zeros(0)] + [part.output_values for part in parts])
    silent = [name for name, stamps in zip(sampler.names, (u_stamps, y_stamps)) if not stamps.size]
    if silent:
        raise DataError(f'no messages of the {" and the ".join(silent)} in the selected span')
    window, stats = resample(u_stamps, u, y_stamps, y, config.sample_time,
                             max_gap=config.max_gap, reorder_horizon=config.reorder_horizon,
                             names=sampler.names)
    update = IdentificationSession(config).update(window)
    return Replay([update], stats, count, [], warnings=errors.warnings())


def _columns_sliding(blocks: Iterable[SampleColumns], config: IdentificationConfig,
                     sampler: MessageSampler, capacity: int, detector: ChangeDetector,
                     origin_ns: Optional[int]) -> Replay:
    buffer = sampler.buffer(capacity, config)
    ticks = _Ticks(config, buffer, detector)
    period_ns = round(config.update_period * NANOSECONDS)
    tick: Optional[int] = None
    newest: Optional[int] = None
    last: Optional[int] = None
    count = 0
    errors = FieldErrors(sampler.names)

    def add(block: SampleColumns, first: int, stop: int) -> None:
        """Admit the samples of messages ``first`` to ``stop - 1`` of the block."""
        low, high = np.searchsorted(block.input_index, (first, stop))
        buffer.add_inputs(block.input_stamps[low:high], block.input_values[low:high])
        low, high = np.searchsorted(block.output_index, (first, stop))
        buffer.add_outputs(block.output_stamps[low:high], block.output_values[low:high])

    for block in blocks:
        times = block.log_time_ns
        block.count_into(errors)
        if not times.size:
            continue
        count += times.size
        if tick is None:
            tick = int(times[0]) + period_ns
            newest = int(times[0])
            buffer.origin_ns = int(times[0]) if origin_ns is None else origin_ns
        # A tick fires before the first message logged after it (replay_messages' rule): the
        # messages up to there are those whose running newest log time is not after it.
        reached = np.maximum.accumulate(np.maximum(times, newest))
        position = 0
        while tick < reached[-1]:
            stop = int(np.searchsorted(reached, tick, side='right'))
            add(block, position, stop)
            position = stop
            ticks.fire(tick)
            tick += period_ns
        add(block, position, times.size)
        newest, last = int(reached[-1]), int(times[-1])
    if tick is not None and tick <= last:
        ticks.fire(tick)
    errors.check()
    return ticks.result(count, errors.warnings())


class _Ticks:
    """The sliding replay's ticks: an estimate on the buffer's window, its alarm or its failure."""

    def __init__(self, config: IdentificationConfig, buffer: Any, detector: ChangeDetector):
        self.config, self.buffer, self.detector = config, buffer, detector
        self.session = IdentificationSession(config)
        self.updates: List[Update] = []
        self.alarms: List[AlarmStatus] = []
        self.skipped: List[SkippedTick] = []

    def fire(self, time_ns: int) -> None:
        """Estimate at the tick ``time_ns``; a failed window is recorded as a skipped tick."""
        try:
            self.updates.append(self.session.update(self.session.take_window(self.buffer)))
        except (DataError, EstimationError) as error:
            self.skipped.append(SkippedTick(time_ns, *failure_status(error)))
            return
        self.alarms.append(self.detector.update(self.updates[-1]))

    def result(self, count: int, warnings: List[str]) -> Replay:
        """Return the replay of ``count`` messages; no estimate at all is an error."""
        if not self.updates:
            reason = self.skipped[-1].reason if self.skipped else (
                f'the span is shorter than update_period ({self.config.update_period:g} s)')
            raise DataError(f'no estimate in the whole replay: {reason}')
        return Replay(self.updates, self.buffer.stats(), count, self.skipped, self.alarms,
                      warnings)


def replay_messages(messages: Iterable[Tuple[str, int, Any]], config: IdentificationConfig, *,
                    sliding: bool = False, topics: Optional[Tuple[str, str]] = None,
                    capacity: Optional[int] = None,
                    detector: Optional[ChangeDetector] = None,
                    origin_ns: Optional[int] = None) -> Replay:
    """
    Feed recorded messages through the live node's buffer and estimation session.

    Parameters
    ----------
    messages : iterable of (str, int, msg)
        ``(topic, log_time_ns, msg)`` in log-time (arrival) order; ``msg`` exposes its fields as
        attributes (rosbags, mcap_ros2 or rclpy messages). Other topics are ignored.
    config : IdentificationConfig
        The node's configuration.
    sliding : bool
        False: one estimate over everything received (the window is the whole span).
        True: tick every ``update_period`` of log time, the first one period after the first
        message; a tick at ``T`` sees the messages logged at or before ``T`` and estimates on
        ``session.take_window(buffer)`` (the settled end): the window plus the transient that
        settles the model's state, exactly as the live node does.
    topics : (str, str), optional
        Absolute input and output topics; default the configured ones resolved for a node
        ``ctid_node`` in the root namespace.
    capacity : int, optional
        Sliding mode: samples kept per stream; default
        :func:`~ctid_ros.streaming.session.buffer_capacity` at one message per ``sample_time``.
        Ignored in the default mode, which keeps the whole span.
    detector : ChangeDetector, optional
        Sliding mode: the change alarm fed every update (:attr:`Replay.alarms`); default one
        for ``config`` with its configured baseline
        (:func:`~ctid_ros.streaming.baseline.configured_baseline`).
    origin_ns : int, optional
        Sliding mode: the time origin of the skipped ticks' reasons (``t=`` seconds from it),
        e.g. the bag's start, as the caller's own messages use; default the log time of the
        first message on the two topics.

    Returns
    -------
    Replay
        The updates and the admission counters.

    Raises
    ------
    ConfigError
        On the first message whose field path does not exist (the message lists its fields),
        at the end if no message of a stream has the selected element (a joint, an index;
        messages without it are otherwise skipped and counted in :attr:`Replay.warnings`),
        or a ``baseline_file`` that exists but cannot be read.
    DataError
        If a stream has no sample, or no window could be estimated.
    EstimationError
        Default mode: if the estimate fails.

    """
    return _dispatch(messages, config, topics, sliding, capacity, detector, origin_ns,
                     _replay_span, _replay_sliding)


def _relevant(messages: Iterable[Tuple[str, int, Any]], topics: Sequence[str]
              ) -> Iterator[Tuple[str, int, Any]]:
    return ((topic, log_time_ns, msg) for topic, log_time_ns, msg in messages if topic in topics)


def _replay_span(messages: Iterable[Tuple[str, int, Any]], config: IdentificationConfig,
                 sampler: MessageSampler) -> Replay:
    # Compact typed arrays: the span is kept whole, the messages are not.
    streams = ((array('q'), array('d')), (array('q'), array('d')))
    count = 0
    errors = FieldErrors(sampler.names)
    for topic, log_time_ns, msg in _relevant(messages, sampler.topics):
        count += 1
        sample = sampler(topic, log_time_ns, msg)
        errors.add(sample, sampler.roles(topic), message_type(msg))
        for (stamps, samples), value in zip(streams, (sample.u, sample.y)):
            if value is not None:
                stamps.append(sample.stamp_ns)
                samples.extend(np.atleast_1d(value))
    names = sampler.names
    errors.check()
    _require_samples(streams, names)
    (u_stamps, u), (y_stamps, y) = streams
    inputs = len(config.input_fields)
    u = np.frombuffer(u, dtype=float) if inputs == 1 else \
        np.frombuffer(u, dtype=float).reshape(-1, inputs)
    window, stats = resample(np.frombuffer(u_stamps, dtype=np.int64), u,
                             np.frombuffer(y_stamps, dtype=np.int64), y, config.sample_time,
                             max_gap=config.max_gap, reorder_horizon=config.reorder_horizon,
                             names=names)
    update = IdentificationSession(config).update(window)
    return Replay([update], stats, count, [], warnings=errors.warnings())


def _require_samples(streams: Sequence[Tuple[array, array]], names: Sequence[str]) -> None:
    silent = [name for name, (stamps, _) in zip(names, streams) if not stamps]
    if silent:
        raise DataError(f'no messages of the {" and the ".join(silent)} in the selected span')


def _replay_sliding(messages: Iterable[Tuple[str, int, Any]], config: IdentificationConfig,
                    sampler: MessageSampler, capacity: int, detector: ChangeDetector,
                    origin_ns: Optional[int]) -> Replay:
    buffer = sampler.buffer(capacity, config)
    ticks = _Ticks(config, buffer, detector)
    period_ns = round(config.update_period * NANOSECONDS)
    tick: Optional[int] = None
    count = 0
    errors = FieldErrors(sampler.names)
    for topic, log_time_ns, msg in _relevant(messages, sampler.topics):
        if tick is None:
            tick = log_time_ns + period_ns
            buffer.origin_ns = log_time_ns if origin_ns is None else origin_ns
        while tick < log_time_ns:
            ticks.fire(tick)
            tick += period_ns
        count += 1
        sample = sampler(topic, log_time_ns, msg)
        errors.add(sample, sampler.roles(topic), message_type(msg))
        sample.add_to(buffer)
    if tick is not None and tick <= log_time_ns:
        ticks.fire(tick)
    errors.check()
    return ticks.result(count, errors.warnings())
