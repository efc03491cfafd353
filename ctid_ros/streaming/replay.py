"""
Offline replay of a recorded bag through the live node's identification pipeline.

``ctid replay PATH --params-file config/<file>.yaml`` reads the configured input and output
topics of a rosbag2 directory (sqlite3 or mcap storage) or a standalone ``.mcap`` file, turns
every message into samples exactly as the live node does (same stamp rule, same
:class:`~ctid_ros.streaming.buffer.SampleBuffer`, same windows) and estimates with the node's
:class:`~ctid_ros.streaming.session.IdentificationSession`. Two modes:

* default: one estimate over the whole selected span (``--start``/``--end``); the window is the
  span, *not* the configured ``window`` (which is the live node's memory, not a property of the
  data). If gaps split the span, the latest contiguous part of at least half the span is used
  and the estimate's warnings say how much was left out.
* ``--sliding``: what the live node would have published. A timer fires every
  ``update_period`` of bag time, starting one period after the first message; each tick
  estimates on the last ``window`` seconds (warm-started from the previous tick). The buffer
  holds only that much history, so long bags replay in bounded memory.

The core, :func:`replay_messages`, takes any iterable of ``(topic, log_time_ns, msg)`` so that
the same code path can be checked against the live node fed the same messages.

Examples
--------
::

    ctid replay run1/ --params-file config/open_loop_delay.yaml
    ctid replay run1.mcap --params-file config/closed_loop_pi.yaml --sliding --json
    ctid replay run1/ --params-file config/joint_states.yaml --start 10 --end 40
    ctid replay run1/ --params-file config/open_loop_delay.yaml --output est.mcap --plot fit.png

"""

import argparse
from array import array
from contextlib import contextmanager
from dataclasses import dataclass, replace
import json
from pathlib import Path
import sys
from typing import Any, Iterable, Iterator, List, Optional, Sequence, TextIO, Tuple

from ctid_ros.cli.report import format_table, json_default
from ctid_ros.errors import BagError, DataError, EstimationError
from ctid_ros.files.bag_reader import BagReader, open_bag
from ctid_ros.files.mcap_source import PathLike
from ctid_ros.files.mcap_writer import EstimateWriter
from ctid_ros.streaming.buffer import BufferStats, resample
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME, NANOSECONDS, resolve_topic
from ctid_ros.streaming.params_file import load_params_file
from ctid_ros.streaming.sampler import MessageSampler
from ctid_ros.streaming.session import buffer_capacity, IdentificationSession, Update
import numpy as np


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
    skipped : list of (int, str)
        Ticks (ns, sliding mode) that gave no estimate and why: too little contiguous data yet,
        or an estimation failure. The live node reports those on ``/diagnostics``.

    """

    updates: List[Update]
    stats: BufferStats
    messages: int
    skipped: List[Tuple[int, str]]


def replay_messages(messages: Iterable[Tuple[str, int, Any]], config: IdentificationConfig, *,
                    sliding: bool = False, topics: Optional[Tuple[str, str]] = None,
                    capacity: Optional[int] = None) -> Replay:
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

    Returns
    -------
    Replay
        The updates and the admission counters.

    Raises
    ------
    ConfigError
        On the first message whose field path does not exist (the message lists its fields).
    DataError
        If a stream has no sample, or no window could be estimated.
    EstimationError
        Default mode: if the estimate fails.

    """
    if topics is None:
        topics = (resolve_topic(config.input_topic), resolve_topic(config.output_topic))
    sampler = MessageSampler(config, topics)
    if sliding:
        capacity = capacity or buffer_capacity(config, 1.0 / config.sample_time)
        return _replay_sliding(messages, config, sampler, capacity)
    return _replay_span(messages, config, sampler)


def _relevant(messages: Iterable[Tuple[str, int, Any]], topics: Sequence[str]
              ) -> Iterator[Tuple[str, int, Any]]:
    return ((topic, log_time_ns, msg) for topic, log_time_ns, msg in messages if topic in topics)


def _replay_span(messages: Iterable[Tuple[str, int, Any]], config: IdentificationConfig,
                 sampler: MessageSampler) -> Replay:
    # Compact typed arrays: the span is kept whole, the messages are not.
    streams = ((array('q'), array('d')), (array('q'), array('d')))
    count = 0
    for topic, log_time_ns, msg in _relevant(messages, sampler.topics):
        count += 1
        sample = sampler(topic, log_time_ns, msg)
        sample.check()
        for (stamps, samples), value in zip(streams, (sample.u, sample.y)):
            if value is not None:
                stamps.append(sample.stamp_ns)
                samples.extend(np.atleast_1d(value))
    names = sampler.names
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
    return Replay([update], stats, count, [])


def _require_samples(streams: Sequence[Tuple[array, array]], names: Sequence[str]) -> None:
    silent = [name for name, (stamps, _) in zip(names, streams) if not stamps]
    if silent:
        raise DataError(f'no messages of the {" and the ".join(silent)} in the selected span')


def _replay_sliding(messages: Iterable[Tuple[str, int, Any]], config: IdentificationConfig,
                    sampler: MessageSampler, capacity: int) -> Replay:
    buffer = sampler.buffer(capacity, config)
    session = IdentificationSession(config)
    period_ns = round(config.update_period * NANOSECONDS)
    updates: List[Update] = []
    skipped: List[Tuple[int, str]] = []
    tick: Optional[int] = None
    count = 0

    def fire(time_ns: int) -> None:
        try:
            updates.append(session.update(session.take_window(buffer)))
        except (DataError, EstimationError) as error:
            skipped.append((time_ns, str(error)))

    for topic, log_time_ns, msg in _relevant(messages, sampler.topics):
        if tick is None:
            tick = log_time_ns + period_ns
        while tick < log_time_ns:
            fire(tick)
            tick += period_ns
        count += 1
        sample = sampler(topic, log_time_ns, msg)
        sample.check()
        sample.add_to(buffer)
    if tick is not None and tick <= log_time_ns:
        fire(tick)
    stats = buffer.stats()
    if not updates:
        reason = skipped[-1][1] if skipped else (
            f'the span is shorter than update_period ({config.update_period:g} s)')
        raise DataError(f'no estimate in the whole replay: {reason}')
    return Replay(updates, stats, count, skipped)


class Progress:
    """
    Show how far through the bag (in bag time) a replay is, on one rewritten terminal line.

    Parameters
    ----------
    stream : text stream
        Where to draw (stderr); nothing is drawn unless it is a terminal.
    start_ns, end_ns : int or None
        Log-time span being replayed.

    """

    def __init__(self, stream: TextIO, start_ns: Optional[int], end_ns: Optional[int]):
        self._stream = stream
        self._start = start_ns
        self._length = (end_ns - start_ns) if None not in (start_ns, end_ns) else 0
        self._shown = -1
        self.enabled = bool(self._length > 0 and stream.isatty())

    def track(self, messages: Iterable[Tuple[str, int, Any]]
              ) -> Iterator[Tuple[str, int, Any]]:
        """Yield the messages unchanged, redrawing the bar whenever a whole percent passes."""
        for item in messages:
            if self.enabled:
                self._draw(min(100, max(0, (item[1] - self._start) * 100 // self._length)))
            yield item
        self.finish()

    def _draw(self, percent: int) -> None:
        if percent != self._shown:
            self._shown = percent
            bar = '#' * (percent // 4)
            self._stream.write(f'\rreplaying [{bar:<25}] {percent:3d} %')
            self._stream.flush()

    def finish(self) -> None:
        """Clear the bar's line."""
        if self.enabled and self._shown >= 0:
            self._stream.write('\r' + ' ' * 40 + '\r')
            self._stream.flush()
            self._shown = -1


def _readable(messages: Iterable[Tuple[str, int, Any]], warn: TextIO
              ) -> Iterator[Tuple[str, int, Any]]:
    """Yield messages until the bag turns out damaged, then warn and stop (keep what was read)."""
    iterator = iter(messages)
    while True:
        try:
            item = next(iterator)
        except StopIteration:
            return
        except BagError as error:
            print(f'ctid replay: warning: {error}; estimating from the messages before it',
                  file=warn)
            return
        yield item


def format_update(update: Update) -> str:
    """Return :func:`ctid_ros.cli.format_table` of an update, in publishing order."""
    result = update.result
    ordered = replace(result, params=dict(zip(update.names, update.values.tolist())),
                      std=dict(zip(update.names, update.stds.tolist())),
                      warnings=list(update.warnings))
    return format_table(ordered)


def format_series(updates: Sequence[Update], origin_ns: int) -> str:
    """
    Return one line per update: window end (s from ``origin_ns``), estimates +- std, fit.

    Parameters
    ----------
    updates : sequence of Update
        Sliding-window estimates, all with the same names.
    origin_ns : int
        Time shown as 0 (the bag start).

    """
    names = updates[0].names
    cells = [[format_estimate(value, std) for value, std in zip(update.values, update.stds)]
             for update in updates]
    widths = [max(len(name), *(len(row[index]) for row in cells))
              for index, name in enumerate(names)]
    lines = [series_header(names, widths)]
    for update, row in zip(updates, cells):
        lines.append(series_row((update.end_ns - origin_ns) / NANOSECONDS, row,
                                update.result.fit, widths))
    return '\n'.join(lines)


def format_estimate(value: float, std: float) -> str:
    """Return the cell ``value ± std`` of a series table."""
    return f'{value:.5g} ± {std:.2g}'


def series_header(names: Sequence[str], widths: Sequence[int]) -> str:
    """Return the header of a series table with columns of the given widths."""
    return '  '.join([f'{"time s":>9}'] + [f'{name:>{width}}'
                                           for name, width in zip(names, widths)]
                     + [f'{"fit %":>7}'])


def series_row(time_s: float, cells: Sequence[str], fit: float, widths: Sequence[int]) -> str:
    """Return one row of a series table: time (s), one cell per parameter, fit (%)."""
    return '  '.join([f'{time_s:>9.2f}'] + [f'{cell:>{width}}'
                                            for cell, width in zip(cells, widths)]
                     + [f'{fit:>7.2f}'])


def _format_stats(stats: BufferStats, names: Sequence[str], messages: int) -> str:
    lines = [f'{messages} messages replayed']
    for name, stream in zip(names, (stats.u, stats.y)):
        lines.append(f'{name}: {stream.accepted} samples used of {stream.received} '
                     f'(non-finite {stream.non_finite}, duplicates {stream.duplicates}, '
                     f'late {stream.late})')
    return '\n'.join(lines)


def plot_paths(path: Path, sliding: bool) -> Tuple[Path, Optional[Path], Path]:
    """Return the measured-vs-simulated, parameters (sliding only) and Bode figure paths."""
    def sibling(suffix: str) -> Path:
        return path.with_name(f'{path.stem}_{suffix}{path.suffix or ".png"}')

    return path, sibling('params') if sliding else None, sibling('bode')


def write_plots(path: Path, updates: Sequence[Update], origin_ns: int, sliding: bool,
                truth: Optional[dict] = None) -> List[Path]:
    """
    Write the replay's figures as PNG files and return their paths.

    ``path`` gets measured vs. simulated output of the last window; ``<stem>_bode.png`` the Bode
    plot of the last estimate up to the Nyquist frequency of the data; with ``sliding`` also
    ``<stem>_params.png``, the estimates over time with their ±2σ bands (against ``truth`` if
    given).
    """
    from ctid_ros.cli import plots

    fit_path, params_path, bode_path = plot_paths(path, sliding)
    last = updates[-1]
    times = (last.prediction_times_ns - origin_ns) / NANOSECONDS
    plots.fit_figure(times, last.window.data.y, last.prediction, fit=last.result.fit,
                     path=fit_path)
    written = [fit_path]
    if params_path is not None:
        plots.parameters_figure(
            np.array([(update.end_ns - origin_ns) / NANOSECONDS for update in updates]),
            last.names, np.array([update.values for update in updates]),
            np.array([update.stds for update in updates]), truth=truth, path=params_path)
        written.append(params_path)
    plots.bode(last.result, max_omega=np.pi / last.window.data.ts, path=bode_path)
    written.append(bode_path)
    return written


def _write_estimates(writer: EstimateWriter, updates: Sequence[Update]) -> None:
    """Write every update as the live node publishes it, prediction included."""
    for update in updates:
        writer.write_estimate(update.end_ns, update.names, update.values, update.stds,
                              update.diagnostics(), prediction=update.prediction)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid replay`` arguments to ``parser``."""
    parser.description = ('Estimate from a rosbag2 directory (sqlite3 or mcap storage) or a '
                          'standalone .mcap file with the params file of the live node: one '
                          'estimate over the selected span, or --sliding as the node would.')
    parser.add_argument('path', help='rosbag2 directory or .mcap file (never modified)')
    parser.add_argument('--params-file', required=True,
                        help='ROS 2 params YAML of the node (e.g. config/open_loop_delay.yaml)')
    parser.add_argument('--node-name', default=DEFAULT_NODE_NAME,
                        help='node section of the params file, optionally with namespace '
                        '(/plant1/ctid_node); also names the --output topics')
    parser.add_argument('--start', type=float, default=None,
                        help='start of the span, seconds from the first message of the bag')
    parser.add_argument('--end', type=float, default=None,
                        help='end of the span, seconds from the first message of the bag')
    parser.add_argument('--sliding', action='store_true',
                        help='estimate every update_period on the last window seconds, as the '
                        'live node does (default: once over the whole span)')
    parser.add_argument('--output', type=Path, default=None,
                        help='new .mcap file for the estimates, on the topics of the live node')
    parser.add_argument('--plot', type=Path, default=None,
                        help='PNG of measured vs simulated output; also writes <stem>_bode.png '
                        'and, with --sliding, <stem>_params.png')
    parser.add_argument('--json', action='store_true',
                        help='print the ctid fit --json object (a list of them with --sliding)')


@contextmanager
def _estimate_output(path: Optional[Path], bag: PathLike, node_name: str
                     ) -> Iterator[Optional[EstimateWriter]]:
    """Create the ``--output`` file before replaying (to fail fast); remove it on failure."""
    if path is None:
        yield None
        return
    writer = EstimateWriter(path, inputs=[bag], node_name=node_name)
    try:
        yield writer
    except BaseException:
        writer.close()
        path.unlink(missing_ok=True)
        raise
    writer.close()


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid replay``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    config = load_params_file(arguments.params_file, arguments.node_name)
    topics = (resolve_topic(config.input_topic, arguments.node_name),
              resolve_topic(config.output_topic, arguments.node_name))
    with open_bag(arguments.path) as bag, \
            _estimate_output(arguments.output, arguments.path, arguments.node_name) as writer:
        for warning in bag.warnings:
            print(f'ctid replay: warning: {warning}', file=sys.stderr)
        start_ns, end_ns = bag.time_range_ns(arguments.start, arguments.end)
        selected = sorted(set(topics))
        messages = bag.messages(selected, start_ns=start_ns, end_ns=end_ns)
        progress = Progress(sys.stderr, start_ns or bag.start_time_ns,
                            end_ns or bag.end_time_ns)
        try:
            replay = replay_messages(progress.track(_readable(messages, sys.stderr)), config,
                                     sliding=arguments.sliding, topics=topics,
                                     capacity=_capacity(bag, config, selected))
        finally:
            progress.finish()
        if writer is not None:
            _write_estimates(writer, replay.updates)
        origin_ns = bag.start_time_ns
    _report(arguments, replay, topics, origin_ns)
    if arguments.plot is not None:
        for path in write_plots(arguments.plot, replay.updates, origin_ns, arguments.sliding):
            print(f'ctid replay: wrote {path}', file=sys.stderr)
    return 0


def _capacity(bag: BagReader, config: IdentificationConfig, topics: Sequence[str]
              ) -> Optional[int]:
    """Size the sliding buffer from the highest message rate of the bag's topics."""
    counts = [bag.message_count(topic) for topic in topics]
    if None in counts or bag.duration_s <= 0:
        return None
    rate = max(max(counts) / bag.duration_s, 1.0 / config.sample_time)
    return buffer_capacity(config, rate)


def _report(arguments: argparse.Namespace, replay: Replay, topics: Tuple[str, str],
            origin_ns: int) -> None:
    for time_ns, reason in replay.skipped:
        print(f'ctid replay: no estimate at t={(time_ns - origin_ns) / NANOSECONDS:.2f} s: '
              f'{reason}', file=sys.stderr)
    if arguments.json:
        objects = [update.to_dict() for update in replay.updates]
        print(json.dumps(objects if arguments.sliding else objects[0], indent=2,
                         default=json_default))
        return
    if arguments.sliding:
        print(format_series(replay.updates, origin_ns))
        print(f'\nlast window ({replay.updates[-1].window.data.y.size} samples):')
    print(format_update(replay.updates[-1]))
    print(_format_stats(replay.stats, topics, replay.messages))
