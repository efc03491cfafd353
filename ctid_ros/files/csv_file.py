"""Reading input/output data from CSV files with a header line."""

import csv
import gzip
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

from ctid_ros.core.data import Data
from ctid_ros.errors import DataError
from ctid_ros.streaming.buffer import resample
from ctid_ros.streaming.contract import NANOSECONDS
import numpy as np

__all__ = ['load_csv', 'timed_data', 'uniform_sample_time']

_RELATIVE_JITTER = 1e-3
# A time column step longer than this many sample times is a gap, not jitter or a lost row.
_GAP_STEPS = 10


def _steps(time: np.ndarray, what: str) -> np.ndarray:
    """Return the steps of increasing stamps, or say where they are not."""
    steps = np.diff(time)
    if steps.size == 0:
        raise DataError(f'{what} has a single sample: cannot infer the sample time')
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        raise DataError(f'{what} is not increasing at row {bad[0] + 1} '
                        f'({time[bad[0]]:g} -> {time[bad[0] + 1]:g}); sort or deduplicate it')
    return steps


def uniform_sample_time(time: np.ndarray, what: str = 'time column') -> float:
    """
    Return the sample time of uniformly spaced, increasing stamps.

    Raises
    ------
    DataError
        If the stamps decrease, repeat, or are not uniform to 0.1 % of the sample time.

    """
    steps = _steps(time, what)
    ts = float(np.median(steps))
    worst = int(np.argmax(np.abs(steps - ts)))
    if abs(steps[worst] - ts) > _RELATIVE_JITTER * ts:
        raise DataError(f'{what} is not uniformly sampled: step {steps[worst]:g} s at row '
                        f'{worst + 1} against a median of {ts:g} s; resample the data first '
                        '(gaps and jitter are handled by `ctid replay` and the live node)')
    return ts


def timed_data(time: np.ndarray, u: np.ndarray, y: np.ndarray, what: str = 'time column',
               ts: Optional[float] = None) -> Tuple[Data, Tuple[str, ...]]:
    """
    Return samples stamped by a time column as ``Data``, resampled as the live node does.

    Uniform stamps (to 0.1 % of the sample time) are taken as they are. Jittered ones go
    through the node's buffer (:func:`~ctid_ros.streaming.buffer.resample`): the grid is the
    input's own instants, its period and phase fitted to the stamps, every row its own sample
    (a lost row is held or interpolated and reported).

    Parameters
    ----------
    time : ndarray
        Stamps in seconds, one per row.
    u, y : ndarray
        Input (a column per input) and output, one row per stamp.
    what : str
        How the time column is called in messages.
    ts : float, optional
        The sample time the caller expects (``--ts``), checked against the stamps.

    Returns
    -------
    (Data, tuple of str)
        The data and what a user should know about their resampling.

    Raises
    ------
    DataError
        If the stamps are not increasing, have a gap longer than ten sample times, follow no
        period, or contradict ``ts``.

    """
    steps = _steps(time, what)
    median = float(np.median(steps))
    if np.all(np.abs(steps - median) <= _RELATIVE_JITTER * median):
        data, notes = Data(u, y, median, float(time[0])), ()
    else:
        data, notes = _resampled(time, u, y, steps, median, what)
    if ts is not None and abs(ts - data.ts) > _RELATIVE_JITTER * data.ts:
        raise DataError(f'--ts {ts:g} contradicts the time column ({what}, sample time '
                        f'{data.ts:g} s)')
    return data, notes


def _resampled(time: np.ndarray, u: np.ndarray, y: np.ndarray, steps: np.ndarray,
               median: float, what: str) -> Tuple[Data, Tuple[str, ...]]:
    """Resample jittered rows through the node's buffer; refuse gaps and aperiodic stamps."""
    gap = int(np.argmax(steps))
    if steps[gap] > _GAP_STEPS * median:
        raise DataError(f'{what} has a gap of {steps[gap]:g} s at row {gap + 1} (median step '
                        f'{median:g} s); split the file there')
    stamps = np.round((time - time[0]) * NANOSECONDS).astype(np.int64)
    window, _ = resample(stamps, u, stamps, y, median, max_gap=_GAP_STEPS * median,
                         reorder_horizon=0.0, names=('input', 'output'))
    plan = window.plan
    if not plan.follows_input:
        worst = int(np.argmax(np.abs(steps - median)))
        raise DataError(f'{what} is not uniformly sampled: step {steps[worst]:g} s at row '
                        f'{worst + 1} against a median of {median:g} s, and its stamps follow no '
                        'period (jittered stamps are resampled as the live node does); resample '
                        'the data first')
    data = window.data
    notes = (f'{what} jitters (robust std {plan.tolerance / 4 / NANOSECONDS:.3g} s, largest '
             f'step {steps.max():g} s): resampled on its own instants, every '
             f'{data.ts:.9g} s, as the live node does',) + window.warnings
    return Data(data.u, data.y, data.ts, float(time[0]) + data.t0), notes


def load_csv(path: Union[str, Path], *, input_column: Union[str, Sequence[str]] = 'u',
             output_column: str = 'y', time_column: str = 't', ts: Optional[float] = None,
             notes: Optional[List[str]] = None) -> Data:
    """
    Load sampled data from a CSV file whose first line names the columns.

    A time column whose stamps jitter is resampled as the live node does (:func:`timed_data`).

    Parameters
    ----------
    path : str or Path
        CSV file, optionally gzip-compressed (``.gz``).
    input_column : str or sequence of str
        Input column name(s); several make a multi-input ``Data`` (columns in that order).
    output_column : str
        Output column name.
    time_column : str
        Column of time stamps in seconds, used if present to infer and check the sample time.
    ts : float, optional
        Sample time; required if the file has no time column.
    notes : list, optional
        Gets what a user should know about the resampling of a jittered time column.

    Returns
    -------
    Data

    Raises
    ------
    DataError
        On a missing file or column, non-numeric cells, or non-uniform sampling.

    """
    path = Path(path)
    try:
        # A gzip-compressed file (name ending in .gz) is read transparently.
        opener = gzip.open if path.suffix == '.gz' else open
        with opener(path, 'rt', newline='') as handle:
            rows = list(csv.reader(handle))
    except OSError as error:
        raise DataError(f'cannot read {path}: {error.strerror}') from None
    if len(rows) < 2:
        raise DataError(f'{path} needs a header line and at least one row of data')
    header = [name.strip() for name in rows[0]]
    inputs = (input_column,) if isinstance(input_column, str) else tuple(input_column)
    columns = {}
    time = time_column
    for name in inputs + (output_column,) + ((time,) if time in header else ()):
        if name not in header:
            raise DataError(f'{path} has no column {name!r}; its columns are {", ".join(header)}')
        index = header.index(name)
        try:
            columns[name] = np.array([float(row[index]) for row in rows[1:] if row])
        except (ValueError, IndexError):
            raise DataError(f'{path}: column {name!r} has a missing or non-numeric cell') from None
    signals = [columns[name] for name in inputs]
    u = signals[0] if len(signals) == 1 else np.column_stack(signals)
    if time in columns:
        data, found = timed_data(columns[time], u, columns[output_column],
                                 f'{path} column {time!r}', ts)
        if notes is not None:
            notes.extend(found)
        return data
    if ts is None:
        raise DataError(f'{path} has no {time!r} column: give the sample time (--ts)')
    return Data(u, columns[output_column], ts, 0.0)
