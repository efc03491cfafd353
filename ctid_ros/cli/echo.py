"""
``ctid echo``: a running identification node's estimates as a live table.

What ``ros2 topic echo`` of the node's ``~/estimate``, ``~/estimate_std`` and ``/diagnostics``
would show, one row per estimate: the end of its window (local clock time), value ± standard
deviation of every parameter, the fit and the node's status; a status without an estimate
(warming up, not enough data) is a row of its own. Rows are printed as they come, so the output
also reads well in a log or through a pipe (a fixed-width text table, the format of ``ctid
replay --sliding``; no terminal control). ``--json`` prints one object per line instead (fields
in the README), ``--once`` the latest estimate only: the node keeps its last estimate for
subscribers that start later (transient local), so ``--once`` answers at once.

Examples
--------
::

    ctid echo                               # the node /ctid_node
    ctid echo --node /plant1/ctid_node --json
    ctid echo --once --timeout 10

"""

import argparse
from dataclasses import dataclass
from datetime import datetime
import json
import queue
import sys
import time
from typing import Any, List, Optional, Tuple

from ctid_ros.cli.report import format_estimate
from ctid_ros.errors import DataError
from ctid_ros.ros.echo import Estimates, NodeListener, Status
from ctid_ros.ros.spinner import stop_on_signals
from ctid_ros.streaming.contract import ERROR, OK, WARN

__all__ = ['LEVELS', 'Row', 'RowAssembler', 'format_row', 'header', 'row_json', 'run']

LEVELS = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR'}
# Seconds an estimate waits for the status the node publishes right after it; a late
# subscriber gets the latched estimate alone, and its row then shows no fit.
STATUS_WAIT = 0.5
_CELL_WIDTH = 19
_TIME_WIDTH = 12
# Characters of a WARN or ERROR message in the table (--json has all of it).
_MESSAGE_WIDTH = 80


@dataclass(frozen=True)
class Row:
    """
    One line of the table: an estimate with its status, or a status alone.

    Attributes
    ----------
    time : float or None
        End of the window, seconds since the epoch (from the status), if known; for a status
        alone, when it was published.
    names : tuple of str
        Parameter names (empty for a status alone).
    values, stds : tuple of float
        Estimates and standard deviations (NaN where not received).
    fit : float or None
        Fit of the window in percent.
    level : int or None
        Status level, if the status came.
    message : str
        Status message.

    """

    time: Optional[float]
    names: Tuple[str, ...]
    values: Tuple[float, ...]
    stds: Tuple[float, ...]
    fit: Optional[float]
    level: Optional[int]
    message: str


def _number(text: Optional[str]) -> Optional[float]:
    try:
        return float(text) if text is not None else None
    except ValueError:
        return None


class RowAssembler:
    """
    Put the node's messages of one update together into a :class:`Row`.

    The node publishes, per update, the estimates, the standard deviations and then its status
    (with ``fit_percent`` and ``window_end``). An estimate is held until its status comes;
    without one (a late subscriber's latched estimate) it is released by :meth:`expired` after
    :data:`STATUS_WAIT` seconds, or by the next estimate.
    """

    def __init__(self) -> None:
        self._estimate: Optional[Estimates] = None
        self._std: Optional[Estimates] = None
        self._since: Optional[float] = None

    def add(self, event: Any, now: float) -> List[Row]:
        """Take one :class:`Estimates` or :class:`Status`; return the rows it completes."""
        rows = []
        if isinstance(event, Estimates):
            if event.kind == 'estimate':
                if self._estimate is not None:
                    rows.extend(self._release(None))
                self._estimate, self._since = event, now
            else:
                self._std = event
            return rows
        if 'fit_percent' in event.values and self._estimate is not None:
            return self._release(event)
        if 'fit_percent' in event.values:
            return rows         # the status of an estimate this listener missed
        return [Row(event.stamp, (), (), (), None, event.level, event.message)]

    def expired(self, now: float) -> List[Row]:
        """Release an estimate whose status did not follow within :data:`STATUS_WAIT` s."""
        if self._estimate is not None and self._since is not None and \
                now - self._since >= STATUS_WAIT:
            return self._release(None)
        return []

    def _release(self, status: Optional[Status]) -> List[Row]:
        estimate, std = self._estimate, self._std
        self._estimate = self._std = self._since = None
        stds = std.values if std is not None and std.names == estimate.names else \
            (float('nan'),) * len(estimate.values)
        if status is None:
            return [Row(None, estimate.names, estimate.values, stds, None, None, '')]
        return [Row(_number(status.values.get('window_end')), estimate.names, estimate.values,
                    stds, _number(status.values.get('fit_percent')), status.level,
                    status.message)]


def _clock(time_s: Optional[float]) -> str:
    """Return the local clock time of ``time_s`` (epoch seconds), or '-'."""
    if time_s is None:
        return '-'
    return datetime.fromtimestamp(time_s).strftime('%H:%M:%S.%f')[:-4]


def header(names: Tuple[str, ...]) -> str:
    """Return the column titles for the parameters ``names``."""
    cells = [f'{name:>{max(len(name), _CELL_WIDTH)}}' for name in names]
    return '  '.join([f'{"window end":>{_TIME_WIDTH}}', *cells, f'{"fit %":>7}', 'status'])


def format_row(row: Row, names: Tuple[str, ...]) -> str:
    """
    Return one line of the table (a status alone spans the parameter columns).

    The status is its level, and for WARN or ERROR the message, cut to 80 characters.
    """
    level = LEVELS.get(row.level, '-') if row.level is not None else '-'
    message = row.message if len(row.message) <= _MESSAGE_WIDTH else \
        row.message[:_MESSAGE_WIDTH - 3] + '...'
    status = level if row.level in (None, OK) else f'{level}: {message}'
    if not row.names:
        width = sum(max(len(name), _CELL_WIDTH) + 2 for name in names) or _CELL_WIDTH + 2
        return '  '.join([f'{_clock(row.time):>{_TIME_WIDTH}}',
                          f'{"(no estimate)":>{width - 2}}', f'{"-":>7}', status])
    cells = [f'{format_estimate(value, std):>{max(len(name), _CELL_WIDTH)}}'
             for name, value, std in zip(row.names, row.values, row.stds)]
    fit = '-' if row.fit is None else f'{row.fit:.2f}'
    return '  '.join([f'{_clock(row.time):>{_TIME_WIDTH}}', *cells, f'{fit:>7}', status])


def row_json(row: Row, node: str) -> str:
    """Return the ``--json`` line of a row (the README lists its fields)."""
    def finite(value: float) -> Optional[float]:
        return value if value == value else None

    estimate = bool(row.names)
    return json.dumps({
        'node': node,
        'time': row.time,
        'params': dict(zip(row.names, row.values)) if estimate else None,
        'std': {name: finite(std) for name, std in zip(row.names, row.stds)}
        if estimate else None,
        'fit': row.fit,
        'level': LEVELS.get(row.level) if row.level is not None else None,
        'status': row.message if row.level is not None else None,
    })


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid echo``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    events: 'queue.Queue[Any]' = queue.Queue()
    assembler = RowAssembler()
    started = time.monotonic()
    names: Tuple[str, ...] = ()
    estimated = False
    # Ctrl-C or SIGTERM end the table (exit status 0), the listener closed in order.
    with stop_on_signals() as stop, NodeListener(arguments.node, events.put) as listener:
        node = listener.topics.node
        if not arguments.json:
            print(f'ctid echo: estimates of {node} (window end, estimate ± std, fit of the '
                  'window, status); Ctrl-C to stop', file=sys.stderr, flush=True)
        while not stop.requested.is_set():
            try:
                rows = assembler.add(events.get(timeout=0.1), time.monotonic())
            except queue.Empty:
                rows = assembler.expired(time.monotonic())
            for row in rows:
                if arguments.once and not row.names:
                    continue        # --once: the estimate only, not the statuses before it
                estimated = estimated or bool(row.names)
                if arguments.json:
                    print(row_json(row, node), flush=True)
                else:
                    if row.names and row.names != names:
                        names = row.names
                        print(header(names), flush=True)
                    print(format_row(row, names), flush=True)
                if arguments.once and row.names:
                    return 0
            if arguments.timeout is not None and not estimated and \
                    time.monotonic() - started > arguments.timeout:
                raise DataError(_silence(listener, arguments.timeout))
    return 0


def _silence(listener: NodeListener, timeout: float) -> str:
    """Say why no estimate came: no publisher yet, or no estimate published."""
    waiting = [topic for topic in (listener.topics.estimate, listener.topics.estimate_std)
               if topic not in listener.connected]
    text = f'no estimate from {listener.topics.node} within {timeout:g} s'
    if waiting:
        text += (f' (no publisher of {", ".join(waiting)}: is the node running, with an '
                 'estimate yet, in this ROS_DOMAIN_ID?)')
    return text
