"""
Listening to an identification node's outputs, for ``ctid echo``.

:class:`NodeListener` subscribes to a node's ``~/estimate`` and ``~/estimate_std`` (once they
have a publisher, with a QoS that matches it: the node latches its last estimate, so a listener
that starts late gets it at once) and to ``/diagnostics`` (the node's own status only), and hands
each message on as plain data (:class:`Estimates`, :class:`Status`) from the thread that spins
it. The layouts are those of :mod:`ctid_ros.streaming.contract`.
"""

from dataclasses import dataclass
import functools
from typing import Callable, Dict, Tuple, Union

from ctid_ros.ros.graph import matching_qos
from ctid_ros.ros.spinner import Spinner
from ctid_ros.streaming.contract import NANOSECONDS, NodeTopics
from diagnostic_msgs.msg import DiagnosticArray
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy
from std_msgs.msg import Float64MultiArray

__all__ = ['Estimates', 'NodeListener', 'Status']

# Seconds between two looks at the graph for the node's publishers.
_DISCOVERY_PERIOD = 0.1
_DEPTH = 10


@dataclass(frozen=True)
class Estimates:
    """
    One message of ``~/estimate`` (``kind='estimate'``) or ``~/estimate_std`` (``'std'``).

    Attributes
    ----------
    kind : str
        ``'estimate'`` or ``'std'``.
    names : tuple of str
        Parameter names, from ``layout.dim[0].label``.
    values : tuple of float
        One value per name.

    """

    kind: str
    names: Tuple[str, ...]
    values: Tuple[float, ...]


@dataclass(frozen=True)
class Status:
    """
    The node's status on ``/diagnostics``.

    Attributes
    ----------
    level : int
        ``contract.OK``, ``WARN`` or ``ERROR``.
    message : str
        The status message.
    values : dict of str to str
        Its key/value pairs (``fit_percent``, ``window_end``, ... after an estimate).
    stamp : float
        The header stamp of the message, seconds since the epoch (when it was published).

    """

    level: int
    message: str
    values: Dict[str, str]
    stamp: float


Event = Union[Estimates, Status]


class NodeListener:
    """
    Deliver the outputs of one identification node to ``callback`` until closed.

    Parameters
    ----------
    node : str
        Fully qualified node name, e.g. ``'/ctid_node'`` or ``'/plant1/ctid_node'``.
    callback : callable
        Called with each :class:`Estimates` or :class:`Status`, from the spinning thread.
    listener_name : str, optional
        Name of the listening node.

    Notes
    -----
    It runs in an rclpy context and executor thread of its own; use it as a context manager.

    """

    def __init__(self, node: str, callback: Callable[[Event], None], *,
                 listener_name: str = 'ctid_echo') -> None:
        self.topics = NodeTopics.of(node)
        self._callback = callback
        self._context = Context()
        rclpy.init(context=self._context)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._node = rclpy.create_node(listener_name, context=self._context)
        self._pending = {self.topics.estimate: ('estimate', Float64MultiArray),
                         self.topics.estimate_std: ('std', Float64MultiArray),
                         self.topics.diagnostics: ('status', DiagnosticArray)}
        self._timer = self._node.create_timer(_DISCOVERY_PERIOD, self._connect)
        self._executor.add_node(self._node)
        self._spinner = Spinner(self._executor, listener_name)
        self._spinner.start()

    def __enter__(self) -> 'NodeListener':
        """Return the listener; it is closed on leaving the block."""
        return self

    def __exit__(self, *exc_info: object) -> None:
        """Stop listening (see :meth:`close`)."""
        self.close()

    @property
    def connected(self) -> Tuple[str, ...]:
        """Return the topics subscribed so far (each once it had a publisher)."""
        return tuple(topic for topic in (self.topics.estimate, self.topics.estimate_std,
                                         self.topics.diagnostics)
                     if topic not in self._pending)

    def _connect(self) -> None:
        """Subscribe to each topic once it has a publisher, with a QoS matching it."""
        for topic, (kind, message_class) in list(self._pending.items()):
            if not self._node.count_publishers(topic):
                continue
            qos = matching_qos(self._node, topic, _DEPTH)
            if kind == 'status':
                # Shared by every node: never ask for a history another publisher lacks.
                qos.durability = DurabilityPolicy.VOLATILE
            callback = self._status if kind == 'status' else functools.partial(
                self._estimates, kind)
            self._node.create_subscription(message_class, topic, callback, qos)
            del self._pending[topic]
        if not self._pending:
            self._node.destroy_timer(self._timer)

    def _estimates(self, kind: str, message: Float64MultiArray) -> None:
        label = message.layout.dim[0].label if message.layout.dim else ''
        names = tuple(label.split(',')) if label else ()
        self._callback(Estimates(kind, names, tuple(float(value) for value in message.data)))

    def _status(self, message: DiagnosticArray) -> None:
        stamp = message.header.stamp.sec + message.header.stamp.nanosec / NANOSECONDS
        for status in message.status:
            if status.name == self.topics.status_name:
                # rclpy gives the byte field as bytes.
                level = status.level if isinstance(status.level, int) else ord(status.level)
                self._callback(Status(level, status.message,
                                      {pair.key: pair.value for pair in status.values}, stamp))

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        # The thread leaves the executor before it is shut down (see ctid_ros.ros.spinner).
        self._spinner.stop()
        self._executor.shutdown()
        if self._node is not None:
            self._node.destroy_node()
            self._node = None
        rclpy.try_shutdown(context=self._context)
