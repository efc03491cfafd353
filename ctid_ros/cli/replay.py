"""
``ctid replay``: estimate from a recorded bag as the live node would have.

``ctid replay PATH --params-file config/<file>.yaml`` reads the configured input and output
topics of a rosbag2 directory (sqlite3 or mcap storage), a standalone ``.mcap`` file or a ROS 1
``.bag`` file (its messages converted to their ROS 2 counterparts) and replays them through
:func:`ctid_ros.streaming.replay.replay_messages`: one estimate over the selected span
(``--start``/``--end``), or ``--sliding`` one every ``update_period`` on the last ``window``
seconds. ``--output`` writes the node's topics (:mod:`ctid_ros.streaming.contract`)
into a new MCAP file together with the replayed input and output messages, copied as recorded
(it appears only complete: written as ``<stem>.partial.mcap``, renamed at the end; an existing
file is replaced only with ``--overwrite``);
``--plot`` draws the fit, the estimates over time and a Bode plot. Without ``--output`` the
messages are read as columns (:mod:`ctid_ros.files.columns`, the same numbers, faster).

With ``--sliding`` every window also goes through the node's change alarm against the baseline
of the params file (``baseline: {J: 0.05, ...}``, or its ``baseline_file``): the table gets an
``alarm`` column, ``--json`` an ``"alarm"`` object per window, the parameters figure red marks,
``--output`` the ``~/alarm`` topic, and the alarms raised are listed at the end. That is the
way to audit a recorded shift.

Examples
--------
::

    ctid replay run1/ --params-file config/open_loop_delay.yaml
    ctid replay run1.mcap --params-file config/closed_loop_pi.yaml --sliding --json
    ctid replay pitch.bag --params-file config/open_loop_delay.yaml
    ctid replay run1/ --params-file config/joint_states.yaml --start 10 --end 40
    ctid replay run1/ --params-file config/open_loop_delay.yaml --output est.mcap --plot fit.png

"""

import argparse
from contextlib import contextmanager
import json
import operator
from pathlib import Path
import sys
from typing import (Any, Callable, Iterable, Iterator, Mapping, Optional, Sequence, TextIO,
                    Tuple, TYPE_CHECKING)

from ctid_ros.cli.arguments import DEFAULT_PLOT
from ctid_ros.cli.report import format_series, format_stats, format_update, json_default
from ctid_ros.errors import BagError, ConfigError
from ctid_ros.files.bag_reader import BagReader, open_bag, readable_part
from ctid_ros.files.columns import sample_columns
from ctid_ros.files.mcap_source import BagRecord, PathLike
from ctid_ros.streaming.alarm import AlarmStatus, ChangeDetector
from ctid_ros.streaming.baseline import configured_baseline
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import ERROR, NANOSECONDS, resolve_topic
from ctid_ros.streaming.params_file import load_params_file, load_units
from ctid_ros.streaming.replay import (Replay, replay_columns, replay_messages, SampleColumns,
                                       SkippedTick)
from ctid_ros.streaming.sampler import message_type, normalized_type
from ctid_ros.streaming.session import buffer_capacity

if TYPE_CHECKING:   # for annotations only: the writer loads with --output (run time below)
    from ctid_ros.files.mcap_writer import EstimateWriter

__all__ = ['default_plot_path', 'progress', 'run']

Message = Tuple[str, int, Any]


def default_plot_path(bag: PathLike, directory: Optional[Path] = None) -> Path:
    """
    Return where ``--plot`` without a value writes: ``<bag name>_replay.png``.

    In ``directory`` (default: the current one), unless that is the bag directory or inside
    it: then next to the bag, so the figures never land in the recording.
    """
    bag = Path(bag).resolve()
    directory = (directory or Path.cwd()).resolve()
    if bag.is_dir() and (directory == bag or bag in directory.parents):
        directory = bag.parent
    name = bag.name[:-len('.mcap')] if bag.name.endswith('.mcap') else bag.name
    return directory / f'{name or "bag"}_replay.png'


def _check_figure_paths(arguments: argparse.Namespace) -> Optional[Path]:
    """Resolve ``--plot`` and check every figure can be written, before anything is estimated."""
    if arguments.plot is None:
        return None
    from ctid_ros.cli.plots import check_figure_paths, replay_figure_paths

    path = default_plot_path(arguments.path) if arguments.plot is DEFAULT_PLOT \
        else Path(arguments.plot)
    inputs = [Path(arguments.path), Path(arguments.params_file)] + (
        [Path(arguments.output)] if arguments.output is not None else [])
    check_figure_paths(path, [item for item in replay_figure_paths(path, arguments.sliding)
                              if item], inputs)
    return path


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid replay``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    plot = _check_figure_paths(arguments)
    config = load_params_file(arguments.params_file, arguments.node_name)
    topics = (resolve_topic(config.input_topic, arguments.node_name),
              resolve_topic(config.output_topic, arguments.node_name))
    if arguments.output is not None and arguments.output.exists() and not arguments.overwrite:
        raise ConfigError(f'--output {arguments.output} already exists; choose another file or '
                          'pass --overwrite to replace it')
    baseline, note = configured_baseline(config, arguments.node_name)
    detector = ChangeDetector.from_config(config, baseline)
    if arguments.sliding and baseline is not None:
        print(f'ctid replay: change alarm against the baseline {note}: {baseline.describe()} '
              f'({config.false_alarm_per_hour:g} false alarms per hour)', file=sys.stderr)
    with open_bag(arguments.path) as bag, \
            _estimate_output(arguments.output, arguments.path, arguments.node_name,
                             arguments.overwrite) as writer:
        for warning in bag.warnings:
            print(f'ctid replay: warning: {warning}', file=sys.stderr)
        _check_topics(bag, config, arguments.node_name, topics)
        # A bag may store a topic without its leading slash: use the bag's spelling.
        topics = tuple(bag.topic_name(topic) or topic for topic in topics)
        start_ns, end_ns = bag.time_range_ns(arguments.start, arguments.end)
        selected = sorted(set(topics))
        if writer is None:
            # A type that cannot be decoded is no damage: said at once, not as a cut bag.
            bag.raw_streams(selected)
            # The columnar path: the same numbers, without per-message Python.
            blocks = progress(_readable(sample_columns(bag, config, topics, start_ns, end_ns),
                                        sys.stderr), start_ns or bag.start_time_ns,
                              end_ns or bag.end_time_ns, sys.stderr, _last_time)
            replay = replay_columns(blocks, config, sliding=arguments.sliding, topics=topics,
                                    capacity=_capacity(bag, config, selected),
                                    detector=detector, origin_ns=bag.start_time_ns)
        else:
            records = _readable(bag.records(selected, start_ns=start_ns, end_ns=end_ns),
                                sys.stderr)
            schemas = {topic: bag.topic_schema(topic) for topic in selected}
            for topic, schema in schemas.items():
                writer.add_topic(topic, schema.msgtype, schema)
            declared = {topic: normalized_type(schema.msgtype)
                        for topic, schema in schemas.items()}
            messages = progress(_copied(records, writer, declared),
                                start_ns or bag.start_time_ns,
                                end_ns or bag.end_time_ns, sys.stderr)
            replay = replay_messages(messages, config, sliding=arguments.sliding,
                                     topics=topics, capacity=_capacity(bag, config, selected),
                                     detector=detector, origin_ns=bag.start_time_ns)
        origin_ns = bag.start_time_ns
        if writer is not None:
            _write_estimates(writer, replay, origin_ns)
    _report(arguments, replay, topics, origin_ns)
    if plot is not None:
        # matplotlib is needed (and loaded) only for figures.
        from ctid_ros.cli.plots import write_replay_figures

        try:
            written = write_replay_figures(
                plot, replay.updates, origin_ns, arguments.sliding,
                units=load_units(arguments.params_file, arguments.node_name),
                transient=config.transient, alarms=replay.alarms)
        except OSError as error:
            raise ConfigError(f'--plot {plot}: cannot write the figures: '
                              f'{error.strerror or error}') from None
        for path in written:
            print(f'ctid replay: wrote {path}', file=sys.stderr)
    return 0


def progress(messages: Iterable[Any], start_ns: Optional[int], end_ns: Optional[int],
             stream: TextIO, time_of: Callable[[Any], int] = operator.itemgetter(1)
             ) -> Iterator[Any]:
    """
    Yield the messages unchanged while a bar shows how far through the span the replay is.

    The bar (tqdm) counts seconds of log time from ``start_ns`` to ``end_ns``; it is drawn on
    ``stream`` only if that is a terminal, and removed when the replay ends. ``time_of`` gives
    an item's log time (default the message's second element).
    """
    # tqdm would draw nothing unless the stream is a terminal (disable=None): then it is not
    # even imported (a tenth of the replay's imports of the bag extras).
    if None in (start_ns, end_ns) or end_ns <= start_ns or \
            not (hasattr(stream, 'isatty') and stream.isatty()):
        yield from messages
        return
    from tqdm import tqdm

    total = (end_ns - start_ns) / NANOSECONDS
    with tqdm(total=total, desc='replaying', file=stream, disable=None, leave=False,
              bar_format='{desc} {percentage:3.0f}%|{bar:25}| {n:.1f}/{total:.1f} s of bag time'
              ) as bar:
        shown = 0.0
        for message in messages:
            position = min(max((time_of(message) - start_ns) / NANOSECONDS, 0.0), total)
            if position > shown:
                bar.update(position - shown)
                shown = position
            yield message


def _last_time(block: SampleColumns) -> int:
    return int(block.log_time_ns[-1]) if block.log_time_ns.size else 0


def _readable(records: Iterable[Any], stream: TextIO) -> Iterator[Any]:
    """Yield records (or blocks) until the bag turns out damaged, then warn and stop."""
    return readable_part(records, lambda text: print(f'ctid replay: warning: {text}',
                                                     file=stream))


def _copied(records: Iterable[BagRecord], writer: Optional['EstimateWriter'],
            declared: Mapping[str, str]) -> Iterator[Message]:
    """
    Yield ``(topic, log_time_ns, msg)``, first copying each record into ``writer``.

    Only a record of the type its topic is declared with in ``writer`` is copied: a topic
    recorded with several types (a ``std_msgs/String`` publisher beside the ``Float64`` one)
    has one channel, whose schema the others' bytes do not fit; the replay ignores them too.
    """
    for record in records:
        if writer is not None and message_type(record.msg) == declared[record.topic]:
            writer.write(record.topic, record.log_time_ns, record.data)
        yield record.topic, record.log_time_ns, record.msg


def _check_topics(bag: BagReader, config: IdentificationConfig, node_name: str,
                  topics: Tuple[str, str]) -> None:
    """
    Refuse topics the bag does not have; for relative ones, name the ``--node-name`` they need.

    A relative ``input_topic: u`` follows the node's namespace: ``/u`` for the default
    ``--node-name ctid_node``, ``/plant1/u`` for ``/plant1/ctid_node``. When the bag has the
    topic in exactly one other namespace, the error says which ``--node-name`` selects it.
    """
    for name, configured, topic in zip(('input_topic', 'output_topic'),
                                       (config.input_topic, config.output_topic), topics):
        try:
            bag.topic_schema(topic)
        except BagError as error:
            if configured.startswith('/'):
                raise
            base = node_name.rpartition('/')[2]
            suffix = f'/{base}/{configured[2:]}' if configured.startswith('~/') \
                else f'/{configured}'
            namespaces = sorted({full[:-len(suffix)] for full in
                                 ('/' + candidate.lstrip('/') for candidate in bag.topics())
                                 if full.endswith(suffix) and len(full) > len(suffix)})
            hint = (f'; replay with --node-name {namespaces[0]}/{base} to read '
                    f'{namespaces[0]}{suffix}') if len(namespaces) == 1 else ''
            raise BagError(f'{error}. {name} {configured!r} is relative: {topic} for the node '
                           f'{node_name}{hint}') from None


@contextmanager
def _estimate_output(path: Optional[Path], bag: PathLike, node_name: str, overwrite: bool
                     ) -> Iterator[Optional['EstimateWriter']]:
    """
    Create the ``--output`` file before replaying (to fail fast), complete or not at all.

    It is written as ``<stem>.partial.mcap`` and renamed when complete: a failure removes it
    and leaves an existing ``path`` as it was; a killed replay leaves only the partial file.
    """
    if path is None:
        yield None
        return
    # Imported here: only --output writes a bag (the mcap writer costs a replay 15 ms).
    from ctid_ros.files.mcap_writer import EstimateWriter

    writer = EstimateWriter(path, inputs=[bag], node_name=node_name, overwrite=overwrite,
                            atomic=True)
    try:
        yield writer
    except BaseException:
        writer.discard()
        raise
    writer.close()


def _write_estimates(writer: 'EstimateWriter', replay: Replay, origin_ns: int) -> None:
    """
    Write every update as the live node publishes it, and the status of every skipped tick.

    With the sliding replay's alarms, each update's diagnostics carry its alarm (as the node's
    do) and the alarm goes to ``~/alarm`` too; times in them count from ``origin_ns``.
    """
    alarms = replay.alarms or [None] * len(replay.updates)
    events = [(update.end_ns, (update, alarm)) for update, alarm in zip(replay.updates, alarms)]
    events += [(skipped.time_ns, skipped) for skipped in replay.skipped]
    for time_ns, event in sorted(events, key=lambda pair: pair[0]):
        if isinstance(event, SkippedTick):
            writer.write_status(time_ns, event.level, event.reason)
            continue
        update, alarm = event
        diagnostics = update.diagnostics()
        if alarm is not None:
            diagnostics.update(alarm.diagnostics(origin_ns))
        writer.write_estimate(time_ns, update.names, update.values, update.stds, diagnostics,
                              prediction=update.prediction, covariance=update.covariance)
        if alarm is not None:
            writer.write_alarm(time_ns, alarm.level, alarm.text(origin_ns),
                               alarm.values(origin_ns))


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
    for warning in replay.warnings:
        print(f'ctid replay: warning: {warning}', file=sys.stderr)
    for skipped in replay.skipped:
        print(f'ctid replay: no estimate at t={(skipped.time_ns - origin_ns) / NANOSECONDS:.2f} '
              f's: {skipped.reason}', file=sys.stderr)
    if arguments.json:
        objects = [update.to_dict() for update in replay.updates]
        for item, alarm in zip(objects, replay.alarms):
            item['alarm'] = alarm.to_dict()
        print(json.dumps(objects if arguments.sliding else objects[0], indent=2,
                         default=json_default))
        return
    if arguments.sliding:
        print(format_series(replay.updates, origin_ns, replay.alarms or None))
        for line in _alarm_lines(replay.alarms, origin_ns):
            print(line)
        print(f'\nlast window ({replay.updates[-1].window.data.y.size} samples):')
    print(format_update(replay.updates[-1]))
    print(format_stats(replay.stats, topics, replay.messages))


def _alarm_lines(alarms: Sequence[AlarmStatus], origin_ns: int) -> Iterator[str]:
    """Yield one line per alarm raised (ERROR or WARN), when it was raised and what it said."""
    previous = None
    for alarm in alarms:
        key = (alarm.level, alarm.parameters)
        if alarm.level and key != previous:
            kind = 'alarm' if alarm.level == ERROR else 'warning'
            raised = ((alarm.time_ns or 0) - origin_ns) / NANOSECONDS
            yield f'{kind} at t={raised:.2f} s: {alarm.text(origin_ns)}'
        previous = key if alarm.level else None
