"""Reading input/output data from CSV files with a header line."""

import csv
import gzip
from pathlib import Path
from typing import Optional, Sequence, Union

from ctid_ros.core.data import Data
from ctid_ros.errors import DataError
import numpy as np

__all__ = ['load_csv', 'uniform_sample_time']

_RELATIVE_JITTER = 1e-3


def uniform_sample_time(time: np.ndarray, what: str = 'time column') -> float:
    """
    Return the sample time of uniformly spaced, increasing stamps.

    Raises
    ------
    DataError
        If the stamps decrease, repeat, or are not uniform to 0.1 % of the sample time.

    """
    steps = np.diff(time)
    if steps.size == 0:
        raise DataError(f'{what} has a single sample: cannot infer the sample time')
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        raise DataError(f'{what} is not increasing at row {bad[0] + 1} '
                        f'({time[bad[0]]:g} -> {time[bad[0] + 1]:g}); sort or deduplicate it')
    ts = float(np.median(steps))
    worst = int(np.argmax(np.abs(steps - ts)))
    if abs(steps[worst] - ts) > _RELATIVE_JITTER * ts:
        raise DataError(f'{what} is not uniformly sampled: step {steps[worst]:g} s at row '
                        f'{worst + 1} against a median of {ts:g} s; resample the data first '
                        '(gaps and jitter are handled by `ctid replay` and the live node)')
    return ts


def load_csv(path: Union[str, Path], *, input_column: Union[str, Sequence[str]] = 'u',
             output_column: str = 'y', time_column: str = 't', ts: Optional[float] = None
             ) -> Data:
    """
    Load uniformly sampled data from a CSV file whose first line names the columns.

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
    if time in columns:
        inferred = uniform_sample_time(columns[time], f'{path} column {time!r}')
        if ts is not None and abs(ts - inferred) > _RELATIVE_JITTER * inferred:
            raise DataError(f'--ts {ts:g} contradicts the time column of {path} '
                            f'(sample time {inferred:g} s)')
    else:
        if ts is None:
            raise DataError(f'{path} has no {time!r} column: give the sample time (--ts)')
        inferred = ts
    signals = [columns[name] for name in inputs]
    u = signals[0] if len(signals) == 1 else np.column_stack(signals)
    return Data(u, columns[output_column], inferred, columns[time][0] if time in columns else 0.0)
