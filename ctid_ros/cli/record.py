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

Examples
--------
::

    ctid record run1.mcap /joint_states                     # until Ctrl-C
    ctid record run2.mcap /plant/u /plant/y --duration 30
    ctid replay run2.mcap --params-file my_node.yaml --sliding

"""

import argparse
from contextlib import contextmanager
import signal
import sys
import time
from typing import Any, Dict, Iterator, List, Optional, Tuple

from ctid_ros.errors import ConfigError
from ctid_ros.files.mcap_writer import RecordingWriter
from ctid_ros.ros.graph import matching_qos, wait_for_topics
from ctid_ros.ros.recorder import TopicRecorder
from ctid_ros.streaming.contract import resolve_topic

__all__ = ['run']

# Seconds between two looks at the clock while recording.
_TICK = 0.1


def _interrupt(signal_number: int, frame: Any) -> None:
    raise KeyboardInterrupt


@contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """Let SIGTERM stop the recording as Ctrl-C does, so the file is closed properly."""
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _record(recorder: TopicRecorder, duration: Optional[float]) -> float:
    """Record until ``duration`` has passed or Ctrl-C; return the seconds recorded."""
    started = time.monotonic()
    try:
        while duration is None or time.monotonic() - started < duration:
            time.sleep(_TICK if duration is None else
                       max(0.0, min(_TICK, duration - (time.monotonic() - started))))
    except KeyboardInterrupt:
        pass
    return time.monotonic() - started


def _session(writer: RecordingWriter, topics: List[str], arguments: argparse.Namespace
             ) -> Tuple[Dict[str, int], float]:
    """Discover the topics, record them; return the messages per topic and the seconds."""
    with TopicRecorder(writer, {}, node_name='ctid_record') as recorder:
        print(f'ctid record: waiting for publishers of {", ".join(topics)}', file=sys.stderr,
              flush=True)
        types = wait_for_topics(recorder.node, topics, arguments.wait)
        for topic, msgtype in types.items():
            recorder.add(topic, msgtype, matching_qos(recorder.node, topic, recorder.depth))
        recorder.start()
        until = 'Ctrl-C' if arguments.duration is None else f'{arguments.duration:g} s or Ctrl-C'
        listing = ', '.join(f'{topic} ({msgtype})' for topic, msgtype in types.items())
        print(f'ctid record: recording {listing} into {arguments.output} until {until}',
              file=sys.stderr, flush=True)
        seconds = _record(recorder, arguments.duration)
    return dict(recorder.counts), seconds


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid record``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    if arguments.output.exists() and not arguments.overwrite:
        raise ConfigError(f'{arguments.output} already exists; choose another file or pass '
                          '--overwrite to replace it')
    topics = [resolve_topic(topic) for topic in arguments.topics]
    with _terminate_as_interrupt():
        writer = RecordingWriter(arguments.output, overwrite=arguments.overwrite)
        try:
            counts, seconds = _session(writer, topics, arguments)
        except BaseException:
            # Nothing recorded (no publisher, interrupted while waiting): no file left behind.
            writer.close()
            arguments.output.unlink(missing_ok=True)
            raise
        writer.close()
    print(f'ctid record: wrote {sum(counts.values())} messages in {seconds:.1f} s to '
          f'{arguments.output} (' + ', '.join(f'{topic}: {count}'
                                              for topic, count in counts.items()) + ')',
          file=sys.stderr)
    return 0
