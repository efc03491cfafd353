"""
Recording live topics into an MCAP file, as ``ros2 bag record`` does (which PyPI lacks).

:class:`TopicRecorder` subscribes with ``raw=True``, so every message is written exactly as it
came off the wire, at its reception time, by a
:class:`~ctid_ros.files.mcap_writer.RecordingWriter`. It runs in an rclpy context and executor
thread of its own, beside whatever else the process does.
"""

import functools
from typing import Any, Callable, Dict, Mapping, Optional, TypeVar

from ctid_ros.errors import BagError
from ctid_ros.files.mcap_writer import RecordingWriter
from ctid_ros.ros.messages import import_message
from ctid_ros.ros.spinner import Spinner
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

__all__ = ['TopicRecorder']

_Recorder = TypeVar('_Recorder', bound='TopicRecorder')


class TopicRecorder:
    """
    Record topics into a :class:`RecordingWriter` until closed.

    Parameters
    ----------
    writer : RecordingWriter
        Where the messages go; the topics are declared on it here.
    topics : mapping of str to str
        Absolute topic names and their message types, e.g.
        ``{'/wheel/y': 'geometry_msgs/msg/PointStamped'}``.
    node_name : str, optional
        Name of the recording node.
    depth : int, optional
        Depth of the reliable subscription queues: deep, so a burst is not lost.

    Attributes
    ----------
    counts : dict of str to int
        Messages written per topic so far.
    depth : int
        The queue depth of its subscriptions.
    failure : BagError or None
        Why writing failed (a full disk): from then on messages are dropped, not written; the
        owner stops the recording and reports it.

    Notes
    -----
    Use as a context manager: subscriptions are made in the constructor (add typed ones for
    display with :meth:`subscribe`), spinning starts with :meth:`start`, and leaving the block
    stops it and shuts the context down, before the writer is closed.

    """

    def __init__(self, writer: RecordingWriter, topics: Mapping[str, str], *,
                 node_name: str = 'ctid_recorder', depth: int = 1000) -> None:
        self._writer = writer
        self.depth = depth
        self.counts: Dict[str, int] = {}
        self.failure: Optional[BagError] = None
        self._context = Context()
        rclpy.init(context=self._context)
        self._executor: Optional[SingleThreadedExecutor] = None
        self._spinner: Optional[Spinner] = None
        try:
            self._executor = SingleThreadedExecutor(context=self._context)
            self._node = rclpy.create_node(node_name, context=self._context)
            self._qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
            for topic, msgtype in topics.items():
                self.add(topic, msgtype)
        except BaseException:
            self.close()
            raise

    @property
    def node(self) -> Node:
        """Return the recording node, e.g. to look at the graph (:mod:`ctid_ros.ros.graph`)."""
        return self._node

    def add(self, topic: str, msgtype: str, qos: Optional[QoSProfile] = None) -> None:
        """
        Record one more topic, also while recording.

        ``qos`` defaults to reliable with the recorder's depth; a best-effort or latched
        publisher needs a matching one (:func:`~ctid_ros.ros.graph.matching_qos`).
        """
        self._writer.add_topic(topic, msgtype)
        self.counts[topic] = 0
        self._node.create_subscription(import_message(msgtype), topic,
                                       functools.partial(self._record, topic),
                                       qos or self._qos, raw=True)

    def __enter__(self: _Recorder) -> _Recorder:
        """Return the recorder; it is closed on leaving the block."""
        return self

    def __exit__(self, *exc_info: object) -> None:
        """Stop recording (see :meth:`close`)."""
        self.close()

    def _record(self, topic: str, data: bytes, info: Mapping[str, Any]) -> None:
        if self.failure is not None:
            return
        try:
            self._writer.write(topic, info['received_timestamp'], data)
        except BagError as error:   # raised in the executor's thread: kept for the owner
            self.failure = error
            return
        self.counts[topic] += 1

    def subscribe(self, topic: str, msgtype: str, callback: Callable[[Any], None]) -> None:
        """Also deliver the decoded messages of ``topic`` to ``callback`` (not recorded)."""
        self._node.create_subscription(import_message(msgtype), topic, callback, self._qos)

    def start(self) -> None:
        """Start spinning in a thread of its own."""
        self._executor.add_node(self._node)
        self._spinner = Spinner(self._executor, 'ctid_recorder')
        self._spinner.start()

    def close(self) -> None:
        """Stop spinning and shut the context down; the writer stays open."""
        # The thread leaves the executor before it is shut down (see ctid_ros.ros.spinner).
        if self._spinner is not None:
            self._spinner.stop()
        if self._executor is not None:
            self._executor.shutdown()
        if getattr(self, '_node', None) is not None:
            self._node.destroy_node()
            self._node = None
        rclpy.try_shutdown(context=self._context)
