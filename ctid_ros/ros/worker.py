"""
The estimation thread: estimates run beside the executor, never inside one of its callbacks.

Every ``update_period`` (node clock) a timer calls :meth:`EstimationWorker.tick`, which wakes
a dedicated thread that runs the node's estimate, so samples keep being buffered while an
estimate is computed, whatever the executor. The thread keeps half a core free: after an
estimate that took ``c`` seconds it skips the ticks of the next ``c`` seconds (counted in
:attr:`EstimationWorker.skipped_ticks`), for the controller the node runs next to.
"""

import threading
import time
from typing import Callable, Optional

__all__ = ['EstimationWorker']


class EstimationWorker:
    """
    Run ``estimate(tick)`` in a daemon thread at each :meth:`tick` while ``enabled()``.

    Parameters
    ----------
    estimate : callable
        Called with the ``time.perf_counter()`` of the tick; reports its time spent with
        :meth:`spent`.
    enabled : callable
        Returns whether a tick should estimate (the node is active).
    on_error : callable
        Called with a name and the exception an estimate raised; the thread goes on.

    """

    def __init__(self, estimate: Callable[[float], object], enabled: Callable[[], bool],
                 on_error: Callable[[str, BaseException], None]) -> None:
        self._estimate = estimate
        self._enabled = enabled
        self._on_error = on_error
        self._wakeup = threading.Event()
        self._stopping = False
        self._tick: Optional[float] = None
        self._busy_until = 0.0
        self.skipped_ticks = 0
        self.skipped_since_estimate = 0
        self._thread = threading.Thread(target=self._run, name='ctid_estimator', daemon=True)
        self._thread.start()

    def tick(self) -> None:
        """Ask for an estimate now (a timer callback: returns at once)."""
        self._tick = time.perf_counter()
        self._wakeup.set()

    def spent(self, started: float) -> None:
        """Note an estimate that began at ``started``: skip ticks for as long as it took."""
        now = time.perf_counter()
        self._busy_until = now + (now - started)

    def stop(self, timeout: Optional[float] = None) -> bool:
        """
        End the thread after the estimate in progress, if any.

        Returns
        -------
        bool
            True if the thread has ended within ``timeout`` seconds (None: wait for it).

        """
        self._stopping = True
        self._wakeup.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            self._wakeup.wait()
            self._wakeup.clear()
            if self._stopping:
                return
            try:
                if not self._enabled():
                    continue
                if time.perf_counter() < self._busy_until:
                    self.skipped_ticks += 1
                    self.skipped_since_estimate += 1
                    continue
                self._estimate(self._tick)
            except Exception as error:  # noqa: B902 - a bug must not stop the estimates
                self._on_error('estimation', error)
