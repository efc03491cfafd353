"""Text reports of estimates: the tables and JSON of ``ctid fit`` and ``ctid replay``."""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping, Optional, Sequence, TYPE_CHECKING

from ctid_ros.streaming.contract import NANOSECONDS, WARN
import numpy as np

if TYPE_CHECKING:  # annotations only: ctid fit need not import the streaming layer
    from ctid_ros.estimation.estimate import Estimate
    from ctid_ros.streaming.alarm import AlarmStatus
    from ctid_ros.streaming.buffer import BufferStats
    from ctid_ros.streaming.session import Update

__all__ = ['alarm_cell', 'format_estimate', 'format_series', 'format_stats', 'format_table',
           'format_update', 'json_default', 'series_header', 'series_row']


def format_table(result: Estimate, fixed: Optional[Mapping[str, float]] = None) -> str:
    """
    Human-readable table of estimates with standard deviations and 95 % intervals.

    ``fixed`` parameters (held at known values, ``ctid fit --fix``) follow the estimated ones,
    marked ``fixed`` instead of a standard deviation.
    """
    fixed = dict(fixed or {})
    width = max(len(name) for name in [*result.params, *fixed])
    lines = [f'{"parameter":<{max(width, 9)}}  {"estimate":>13}  {"std":>11}  '
             f'{"95% interval":>27}']
    for name, value in result.params.items():
        std = result.std[name]
        if np.isfinite(std):
            lines.append(f'{name:<{max(width, 9)}}  {value:>13.6g}  {std:>11.3g}  '
                         f'[{value - 1.96 * std:>12.6g}, {value + 1.96 * std:>12.6g}]')
        else:
            # Held at a bound: the value is the bound's, the data give no interval.
            lines.append(f'{name:<{max(width, 9)}}  {value:>13.6g}  {"at bound":>11}')
    lines.extend(f'{name:<{max(width, 9)}}  {value:>13.6g}  {"fixed":>11}'
                 for name, value in fixed.items())
    lines.append('')
    lines.append(f'fit {result.fit:.2f} %   iterations {result.iterations}   '
                 f'converged {"yes" if result.converged else "no"} ({result.stop_reason})')
    if result.residuals is not None:
        lines.append(f'residual: {result.residuals.verdict}')
    if result.consistency is not None:
        lines.append(f'consistency: {result.consistency.verdict}')
    lines.extend(f'warning: {note}' for note in result.warnings)
    return '\n'.join(lines)


def json_default(value):
    """Convert numpy scalars for :func:`json.dumps` (its ``default`` hook)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'not JSON serialisable: {type(value).__name__}')


def format_update(update: Update) -> str:
    """Return :func:`format_table` of an update, in publishing order."""
    result = update.result
    ordered = replace(result, params=dict(zip(update.names, update.values.tolist())),
                      std=dict(zip(update.names, update.stds.tolist())),
                      warnings=list(update.warnings))
    return format_table(ordered)


def format_series(updates: Sequence[Update], origin_ns: int,
                  alarms: Optional[Sequence[AlarmStatus]] = None) -> str:
    """
    Return one line per update: window end (s from ``origin_ns``), estimates +- std, fit.

    Parameters
    ----------
    updates : sequence of Update
        Sliding-window estimates, all with the same names.
    origin_ns : int
        Time shown as 0 (the bag start).
    alarms : sequence of AlarmStatus, optional
        The change alarm after each update: adds an ``alarm`` column (:func:`alarm_cell`).

    """
    names = updates[0].names
    cells = [[format_estimate(value, std) for value, std in zip(update.values, update.stds)]
             for update in updates]
    widths = [max(len(name), *(len(row[index]) for row in cells))
              for index, name in enumerate(names)]
    lines = [series_header(names, widths, alarms is not None)]
    for index, (update, row) in enumerate(zip(updates, cells)):
        lines.append(series_row((update.end_ns - origin_ns) / NANOSECONDS, row,
                                update.result.fit, widths,
                                None if alarms is None else alarm_cell(alarms[index])))
    return '\n'.join(lines)


def alarm_cell(status: AlarmStatus) -> str:
    """Return the alarm column of a series row: ``OK``, ``ERROR J,b``, ``WARN model``."""
    if status.parameters:
        return f'{status.level_name} {",".join(status.parameters)}'
    return 'WARN model' if status.level == WARN else status.level_name


def format_estimate(value: float, std: float) -> str:
    """Return the cell ``value ± std`` of a series table."""
    return f'{value:.5g} ± {std:.2g}'


def series_header(names: Sequence[str], widths: Sequence[int], alarm: bool = False) -> str:
    """Return the header of a series table with columns of the given widths (and alarm)."""
    return '  '.join([f'{"time s":>9}'] + [f'{name:>{width}}'
                                           for name, width in zip(names, widths)]
                     + [f'{"fit %":>7}'] + (['alarm'] if alarm else []))


def series_row(time_s: float, cells: Sequence[str], fit: float, widths: Sequence[int],
               alarm: Optional[str] = None) -> str:
    """Return one row of a series table: time (s), one cell per parameter, fit (%), alarm."""
    return '  '.join([f'{time_s:>9.2f}'] + [f'{cell:>{width}}'
                                            for cell, width in zip(cells, widths)]
                     + [f'{fit:>7.2f}'] + ([alarm] if alarm is not None else []))


def format_stats(stats: BufferStats, names: Sequence[str], messages: int) -> str:
    """Return how many messages were replayed and how many samples of each stream were used."""
    lines = [f'{messages} messages replayed']
    for name, stream in zip(names, (stats.u, stats.y)):
        lines.append(f'{name}: {stream.accepted} samples used of {stream.received} '
                     f'(non-finite {stream.non_finite}, duplicates {stream.duplicates}, '
                     f'late {stream.late}, out of clock {stream.out_of_clock})')
    return '\n'.join(lines)
