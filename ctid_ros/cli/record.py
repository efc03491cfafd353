"""
``ctid record``: record live topics into an MCAP file, as ``ros2 bag record`` does.

``ctid record OUT.mcap TOPIC...`` waits until every topic has a publisher, learns its type from
the graph, subscribes with a QoS matching the publishers (:mod:`ctid_ros.ros.graph`) and writes
every message as it came off the wire, at its reception time, with its type's definition
(:class:`~ctid_ros.ros.recorder.TopicRecorder` into a
:class:`~ctid_ros.files.mcap_writer.RecordingWriter`). It stops after ``--duration`` seconds,
or at Ctrl-C (or SIGTERM), and closes the file with its index either way, so ``ctid replay``,
Foxglove and PlotJuggler read it at once. An existing file is replaced only with
``--overwrite``.

What was recorded is kept: the messages are written to disk at least every second
(``--flush-interval``), each time followed by a valid end of the file, so a recorder killed
(SIGKILL, power cut) loses about the last second and leaves a file the plain ``mcap`` reader
reads; once recording, Ctrl-C and SIGTERM only ask it to stop (a second one, as a parent that
forwards Ctrl-C sends, changes nothing); a full disk stops the recording with a one-line error
and the file holds what was flushed before. Only a file without any message (no publisher
came, stopped while waiting) is removed. Stopped by a signal, it ends with status 0.

Examples
--------
::

    ctid record run1.mcap /joint_states                     # until Ctrl-C
    ctid record run2.mcap /plant/u /plant/y --duration 30
    ctid replay run2.mcap --params-file my_node.yaml --sliding

"""

import argparse
import sys
import time
from typing import Dict, List, Optional, Tuple

from ctid_ros.errors import BagError, ConfigError
from ctid_ros.files.mcap_writer import RecordingWriter
from ctid_ros.ros.graph import matching_qos, wait_for_topics
from ctid_ros.ros.recorder import TopicRecorder
from ctid_ros.ros.spinner import stop_on_signals, StopRequest
from ctid_ros.streaming.contract import resolve_topic

__all__ = ['run']
# Seconds between two looks at the clock while recording.
_TICK = 0.1


def _record(recorder: TopicRecorder, writer: RecordingWriter, stop: StopRequest,
            duration: Optional[float]) -> float:
    """Record until ``duration``, a signal or a failed write; return the seconds recorded."""
    started = time.monotonic()
    while not stop.requested.is_set() and recorder.failure is None:
        elapsed = time.monotonic() - started
        if duration is not None and elapsed >= duration:
            break
        stop.requested.wait(_TICK if duration is None else
                            max(0.0, min(_TICK, duration - elapsed)))
        try:
            writer.flush()      # what arrived in the last second, also when nothing comes
        except BagError as error:
            recorder.failure = recorder.failure or error
    return time.monotonic() - started


def _session(writer: RecordingWriter, topics: List[str], arguments: argparse.Namespace,
             stop: StopRequest) -> Tuple[Dict[str, int], float, Optional[BagError]]:
    """Discover the topics, record them; return the messages per topic, seconds, failure."""
    with TopicRecorder(writer, {}, node_name='ctid_record') as recorder:
        print(f'ctid record: waiting for publishers of {", ".join(topics)}', file=sys.stderr,
              flush=True)
        types = wait_for_topics(recorder.node, topics, arguments.wait)
        for topic, msgtype in types.items():
            recorder.add(topic, msgtype, matching_qos(recorder.node, topic, recorder.depth))
        stop.interrupting = False
        recorder.start()
        until = 'Ctrl-C' if arguments.duration is None else f'{arguments.duration:g} s or Ctrl-C'
        listing = ', '.join(f'{topic} ({msgtype})' for topic, msgtype in types.items())
        print(f'ctid record: recording {listing} into {arguments.output} until {until}',
              file=sys.stderr, flush=True)
        seconds = _record(recorder, writer, stop, arguments.duration)
    return dict(recorder.counts), seconds, recorder.failure


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid record``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    if arguments.output.exists() and not arguments.overwrite:
        raise ConfigError(f'{arguments.output} already exists; choose another file or pass '
                          '--overwrite to replace it')
    topics = [resolve_topic(topic) for topic in arguments.topics]
    # Waiting for publishers, a signal interrupts (nothing is recorded yet); once recording, it
    # only asks to stop, so that no exception can land in the middle of closing the file.
    with stop_on_signals(interrupting=True) as stop:
        writer = RecordingWriter(arguments.output, overwrite=arguments.overwrite,
                                 flush_interval=arguments.flush_interval)
        try:
            counts, seconds, failure = _session(writer, topics, arguments, stop)
        except KeyboardInterrupt:   # stopped while waiting for publishers, as asked
            _discard_if_empty(writer)
            print('ctid record: stopped while waiting for publishers; nothing recorded',
                  file=sys.stderr)
            return 0
        except BaseException:
            _discard_if_empty(writer)
            raise
        try:
            writer.close()
        except BagError as error:
            failure = failure or error
    written = (f'{sum(counts.values())} messages in {seconds:.1f} s (' +
               ', '.join(f'{topic}: {count}' for topic, count in counts.items()) + ')')
    if failure is not None:
        raise BagError(f'{failure}; recording stopped after {written}; {arguments.output} '
                       'keeps the messages written before (ctid replay reads it)')
    print(f'ctid record: wrote {written} to {arguments.output}', file=sys.stderr)
    return 0


def _discard_if_empty(writer: RecordingWriter) -> None:
    """Close the writer after a failure; remove its file if it holds no message."""
    try:
        writer.close()
    except BagError:
        pass
    if writer.message_count == 0:
        writer.path.unlink(missing_ok=True)
