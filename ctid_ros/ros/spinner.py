"""
An executor spun in a thread of its own, stopped without racing its shutdown.

``threading.Thread(target=executor.spin)`` stopped by ``executor.shutdown()`` can hang: when the
shutdown destroys its guard condition before the spinning thread has built its wait set, the
thread waits in ``rcl_wait`` with no timeout and nothing left to wake it (rclpy issues #968 and
#1666). A command that records or echoes until Ctrl-C then hangs on exit now and then.
:class:`Spinner` spins with a short timeout and checks a stop flag between waits, so
:meth:`Spinner.stop` returns within one period (plus a callback in progress); the executor is
shut down only after the thread has left it.
"""

import threading
from typing import Optional

from rclpy.executors import Executor, ExternalShutdownException, ShutdownException

__all__ = ['Spinner']

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
