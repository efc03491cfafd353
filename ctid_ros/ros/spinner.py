"""
An executor spun in a thread of its own, stopped without racing its shutdown.

``threading.Thread(target=executor.spin)`` stopped by ``executor.shutdown()`` can hang: when the
shutdown destroys its guard condition before the spinning thread has built its wait set, the
thread waits in ``rcl_wait`` with no timeout and nothing left to wake it (rclpy issues #968 and
#1666). A command that records or echoes until Ctrl-C then hangs on exit now and then.
:class:`Spinner` spins with a short timeout and checks a stop flag between waits, so
:meth:`Spinner.stop` returns within one period (plus a callback in progress); the executor is
shut down only after the thread has left it.

The commands that spin until stopped (``ctid record``, ``ctid echo``) take SIGINT and SIGTERM
as a request to stop (:func:`stop_on_signals`): an exception raised by the signal could land
anywhere, also inside the closing of a file or of an rclpy context (a second Ctrl-C from a
parent that forwards it, as launch does, once deleted a recording), and SIGTERM would end the
process without closing anything. Only while ``interrupting`` (waiting, before anything worth
keeping exists) does the first signal also raise :class:`KeyboardInterrupt`.
"""

from contextlib import contextmanager
import signal
import threading
from types import FrameType
from typing import Iterator, Optional

from rclpy.executors import Executor, ExternalShutdownException, ShutdownException

__all__ = ['Spinner', 'StopRequest', 'stop_on_signals']

# Longest wait of the thread between checks of its stop flag (seconds).
_PERIOD = 0.1


class Spinner:
    """
    Spin ``executor`` in a daemon thread named ``name`` from :meth:`start` until :meth:`stop`.

    The thread also ends when the executor's context is shut down from elsewhere.
    """

    def __init__(self, executor: Executor, name: str, period: float = _PERIOD) -> None:
        self._executor = executor
        self._name = name
        self._period = period
        self._stopping = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def start(self) -> None:
        """Start spinning."""
        self._thread = threading.Thread(target=self._spin, name=self._name, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            while not self._stopping.is_set() and self._executor.context.ok():
                self._executor.spin_once(timeout_sec=self._period)
        except (ExternalShutdownException, ShutdownException):
            pass

    def stop(self, timeout: float = 10.0) -> None:
        """Stop spinning and wait up to ``timeout`` seconds for the thread to leave."""
        self._stopping.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=timeout)


_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """
    The signal handler: sets :attr:`requested`, and raises once while :attr:`interrupting`.

    Attributes
    ----------
    requested : threading.Event
        Set by the first SIGINT or SIGTERM (later ones change nothing).
    interrupting : bool
        Whether the next signal also raises :class:`KeyboardInterrupt` (cleared by it).

    """

    def __init__(self, interrupting: bool = False) -> None:
        self.requested = threading.Event()
        self.interrupting = interrupting

    def __call__(self, number: int, frame: Optional[FrameType]) -> None:
        self.requested.set()
        if self.interrupting:
            self.interrupting = False
            raise KeyboardInterrupt


@contextmanager
def stop_on_signals(interrupting: bool = False) -> Iterator[StopRequest]:
    """
    Handle SIGINT and SIGTERM with a new :class:`StopRequest`.

    On leaving, the previous handlers come back unless a stop was requested: the process is
    then ending, and a signal that follows (a parent forwarding Ctrl-C again) must not
    interrupt its last messages or its exit status, so both signals are ignored from then on
    (also while the interpreter shuts down, when Python's own handlers are gone).
    """
    stop = StopRequest(interrupting)
    previous = {number: signal.signal(number, stop) for number in _SIGNALS}
    try:
        yield stop
    finally:
        for number, handler in previous.items():
            signal.signal(number, signal.SIG_IGN if stop.requested.is_set() else handler)
