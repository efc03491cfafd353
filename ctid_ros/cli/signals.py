"""
SIGINT and SIGTERM as a request to stop, for the commands that run until Ctrl-C.

``ctid record`` and ``ctid echo`` loop until the user stops them. A Python exception raised by
the signal could land anywhere, also inside the closing of a file or of an rclpy context (a
second Ctrl-C from a parent that forwards it, as launch does, once deleted a recording), and
SIGTERM would end the process without closing anything. :class:`StopRequest` turns both into a
flag that the loop looks at; only while ``interrupting`` (waiting, before anything worth
keeping exists) does the first signal also raise :class:`KeyboardInterrupt`.
"""

from contextlib import contextmanager
import signal
import threading
from types import FrameType
from typing import Iterator, Optional

__all__ = ['StopRequest', 'stop_on_signals']

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
