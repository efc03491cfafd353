"""
Reading input/output data from CSV files with a header line.

The file is read as a stream, a line at a time, and only the columns asked for are kept, so
what a file may cost is bounded (:mod:`ctid_ros.core.limits`): its size (also decompressed),
the length of a line, the number of rows (the record limit of one estimate) and of blank
lines. Broken files (not UTF-8, binary, a truncated or damaged gzip stream, another compression)
raise a :class:`~ctid_ros.errors.DataError` naming the file, the line and what to do.
"""

import array
import csv
import gzip
from numbers import Real
from pathlib import Path
from typing import BinaryIO, Dict, Iterator, List, Optional, Sequence, Tuple, Union
import zlib

from ctid_ros.core.data import Data
from ctid_ros.core.limits import (check_readable, MAX_BLANK_LINES, MAX_CSV_BYTES,
                                  MAX_LINE_BYTES, MAX_SAMPLES, size_text)
from ctid_ros.errors import bounded_repr, DataError
from ctid_ros.streaming.buffer import resample
from ctid_ros.streaming.contract import NANOSECONDS
import numpy as np

__all__ = ['TIME_COLUMNS', 'load_csv', 'read_columns', 'timed_data', 'uniform_sample_time']

_RELATIVE_JITTER = 1e-3
# A time column step longer than this many sample times is a gap, not jitter or a lost row.
_GAP_STEPS = 10
_GZIP_MAGIC = b'\x1f\x8b'
# Other containers a CSV may arrive in, recognised by their first bytes.
_OTHER_FORMATS = ((b'BZh', 'bzip2-compressed'), (b'\xfd7zXZ\x00', 'xz-compressed'),
                  (b'\x28\xb5\x2f\xfd', 'zstd-compressed'), (b'PK\x03\x04', 'a zip archive'),
                  (b'\x89MCAP', 'an MCAP file (use ctid replay)'),
                  (b'SQLite format 3\x00', 'an SQLite database (use ctid replay on its bag)'))


def _open_stream(path: Path) -> BinaryIO:
    """Open a CSV file (plain or gzip, recognised by its first bytes) for binary reading."""
    check_readable(path, MAX_CSV_BYTES, 'CSV file', DataError)
    try:
        stream = open(path, 'rb')
    except OSError as error:
        raise DataError(f'cannot read {path}: {error.strerror or error}') from None
    try:
        start = stream.peek(16)[:16]
    except OSError as error:
        stream.close()
        raise DataError(f'cannot read {path}: {error.strerror or error}') from None
    if start.startswith(_GZIP_MAGIC):
        return gzip.GzipFile(fileobj=stream, mode='rb')
    for magic, what in _OTHER_FORMATS:
        if start.startswith(magic):
            stream.close()
            raise DataError(f'{path} is {what}, not a CSV file: decompress or convert it first')
    if path.suffix == '.gz':
        stream.close()
        raise DataError(f'{path} is named .gz but is not gzip-compressed; rename or recompress it')
    return stream


def _text_lines(stream: BinaryIO, path: Path) -> Iterator[str]:
    """Yield the decoded lines of ``stream`` (a UTF-8 byte order mark dropped), bounded."""
    total = 0
    number = 0
    while True:
        raw = stream.readline(MAX_LINE_BYTES + 1)
        if not raw:
            return
        number += 1
        total += len(raw)
        if total > MAX_CSV_BYTES:
            raise DataError(f'{path} holds more than the limit of {size_text(MAX_CSV_BYTES)} '
                            '(decompressed)')
        if len(raw) > MAX_LINE_BYTES:
            raise DataError(f'{path} line {number} is longer than the limit of '
                            f'{size_text(MAX_LINE_BYTES)}: not a CSV of samples')
        if b'\0' in raw:
            raise DataError(f'{path} is binary, not CSV text (a NUL byte on line {number})')
        try:
            text = raw.decode('utf-8')
        except UnicodeDecodeError as error:
            raise DataError(f'{path} is not UTF-8 text: byte 0x{raw[error.start]:02x} on line '
                            f'{number}; save it as UTF-8 (e.g. iconv -f latin1 -t utf-8)'
                            ) from None
        yield text[1:] if number == 1 and text.startswith('\ufeff') else text


def _rows(path: Path, stream: BinaryIO) -> Iterator[Tuple[int, list]]:
    """Yield ``(line number, cells)`` of every non-blank row, header first."""
    reader = csv.reader(_text_lines(stream, path))
    blank = 0
    try:
        for row in reader:
            if not row or (len(row) == 1 and not row[0].strip()):
                blank += 1
                if blank > MAX_BLANK_LINES:
                    raise DataError(f'{path} has more than {MAX_BLANK_LINES} blank lines: not a '
                                    'CSV of samples')
                continue
            yield reader.line_num, row
    except csv.Error as error:
        raise DataError(f'{path} line {reader.line_num}: {error}; not a CSV of samples'
                        ) from None
    except (EOFError, zlib.error, gzip.BadGzipFile) as error:
        raise DataError(f'{path} is a truncated or damaged gzip file ({error}) after line '
                        f'{reader.line_num}; recompress it, or decompress what is readable '
                        '(zcat) and check its end') from None
    except OSError as error:
        raise DataError(f'cannot read {path}: {error.strerror or error}') from None


def read_columns(path: Union[str, Path], names: Sequence[str], optional: Sequence[str] = (),
                 *, skipped: Optional[List[int]] = None) -> Dict[str, np.ndarray]:
    """
    Read the named columns of a CSV file with a header line as float arrays.

    Parameters
    ----------
    path : str or Path
        CSV file, plain or gzip-compressed (recognised by its content).
    names : sequence of str
        Columns that must exist; header names are compared without surrounding spaces.
    optional : sequence of str
        Columns read only if the header has them.
    skipped : list, optional
        If given, a row whose cells of ``names`` are all empty is skipped and its line number
        appended here: in a PlotJuggler export, rows at the instants of the other series.
        A row with some of them empty is an error either way (the columns were sampled at
        different instants).

    Returns
    -------
    dict
        ``{name: values}`` for ``names`` and the ``optional`` names present.

    Raises
    ------
    DataError
        On a missing, unreadable or broken file, a missing column, a missing or non-numeric
        cell (the message names the line), or a file beyond the limits of
        :mod:`ctid_ros.core.limits`.

    """
    path = Path(path)
    with _open_stream(path) as stream:
        rows = _rows(path, stream)
        first = next(rows, None)
        if first is None:
            raise DataError(f'{path} needs a header line and at least one row of data')
        header = [name.strip() for name in first[1]]
        for name in names:
            if name not in header:
                listed = ', '.join(header)
                listed = listed if len(listed) <= 200 else listed[:197] + '...'
                raise DataError(f'{path} has no column {bounded_repr(name, 40)}; its columns '
                                f'are {listed}')
        wanted = [name for name in dict.fromkeys([*names, *optional]) if name in header]
        indices = [header.index(name) for name in wanted]
        required = [header.index(name) for name in names]
        values = [array.array('d') for _ in wanted]
        count = 0
        for line, row in rows:
            count += 1
            if count > MAX_SAMPLES:
                raise DataError(f'{path} has more than {MAX_SAMPLES} rows, the record limit of '
                                'one estimate; decimate it or split it')
            if skipped is not None:
                empty = [name for name, index in zip(names, required) if _blank(row, index)]
                if len(empty) == len(names):
                    skipped.append(line)
                    continue
                if empty:
                    filled = next(name for name in names if name not in empty)
                    raise DataError(
                        f'{path} line {line}: column {empty[0]!r} is empty where {filled!r} '
                        'has a value: the columns were sampled at different instants (a '
                        'PlotJuggler export of separate topics?); export them from one message, '
                        'or replay the recording with ctid replay, which resamples them as the '
                        'node does')
            for name, index, column in zip(wanted, indices, values):
                try:
                    column.append(float(row[index]))
                except (ValueError, IndexError):
                    cell = bounded_repr(row[index], 40) if index < len(row) else 'nothing'
                    raise DataError(f'{path} line {line}: column {name!r} has a missing or '
                                    f'non-numeric cell ({cell})') from None
    if count == len(skipped or ()):
        raise DataError(f'{path} needs a header line and at least one row of data')
    return {name: np.frombuffer(column, dtype=float).copy()
            for name, column in zip(wanted, values)}


def _blank(row: Sequence[str], index: int) -> bool:
    """Return True if ``row`` has a cell at ``index`` and it is blank (a short row has none)."""
    return index < len(row) and not row[index].strip()


def _column_names(input_column: Union[str, Sequence[str]]) -> Tuple[str, ...]:
    inputs = (input_column,) if isinstance(input_column, str) else tuple(input_column)
    if not inputs or not all(isinstance(name, str) for name in inputs):
        raise DataError(f'input columns must be one or more names, got {bounded_repr(inputs)}')
    return inputs


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


# Names of a time column, in the order they are looked for: t, and PlotJuggler's __time.
TIME_COLUMNS = ('t', '__time')


def load_csv(path: Union[str, Path], *, input_column: Union[str, Sequence[str]] = 'u',
             output_column: str = 'y', time_column: Union[str, Sequence[str]] = TIME_COLUMNS,
             ts: Optional[float] = None, notes: Optional[List[str]] = None) -> Data:
    """
    Load sampled data from a CSV file whose first line names the columns.

    A time column whose stamps jitter is resampled as the live node does (:func:`timed_data`).

    Parameters
    ----------
    path : str or Path
        CSV file, optionally gzip-compressed (``.gz``; recognised by its content).
    input_column : str or sequence of str
        Input column name(s); several make a multi-input ``Data`` (columns in that order).
    output_column : str
        Output column name.
    time_column : str or sequence of str
        Column of time stamps in seconds, used if present to infer and check the sample time;
        of several names the first the file has (default ``t``, else PlotJuggler's
        ``__time``). With a time column, rows whose input and output cells are all empty
        (a PlotJuggler export's rows of other series) are skipped.
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
        On a missing file or column, non-numeric cells, or stamps that follow no period; on a
        file that is broken or beyond the limits of :mod:`ctid_ros.core.limits` (see
        :func:`read_columns`).

    """
    path = Path(path)
    inputs = _column_names(input_column)
    if ts is not None and (isinstance(ts, bool) or not isinstance(ts, Real)
                           or not 0 < ts < float('inf')):
        raise DataError(f'the sample time must be a positive number, got {bounded_repr(ts)}')
    times = (time_column,) if isinstance(time_column, str) else tuple(time_column)
    skipped: List[int] = []
    columns = read_columns(path, inputs + (output_column,), optional=times, skipped=skipped)
    signals = [columns[name] for name in inputs]
    u = signals[0] if len(signals) == 1 else np.column_stack(signals)
    time = next((name for name in times if name in columns), None)
    if time is not None:
        data, found = timed_data(columns[time], u, columns[output_column],
                                 f'{path} column {time!r}', ts)
        if notes is not None:
            if skipped:
                notes.append(f'{len(skipped)} rows without a value in '
                             f'{", ".join(inputs + (output_column,))} skipped (first on line '
                             f'{skipped[0]}): rows of other series')
            notes.extend(found)
        return data
    if skipped:
        raise DataError(f'{path} line {skipped[0]}: no value in '
                        f'{", ".join(inputs + (output_column,))}; without a time column the '
                        'samples after it would shift: remove such rows or add the time column')
    if ts is None:
        names = ' or '.join(repr(name) for name in times)
        raise DataError(f'{path} has no {names} column: give the sample time (--ts)')
    return Data(u, columns[output_column], ts, 0.0)
