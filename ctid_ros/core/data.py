"""Uniformly sampled input/output data and their validation."""

from dataclasses import dataclass
import numbers
from typing import Optional

from ctid_ros.errors import bounded_repr, DataError
import numpy as np


def _check_nesting(values, name: str, depth: int) -> None:
    """
    Refuse lists nested deeper than ``depth`` before numpy expands them.

    numpy would materialise every element of a nested structure, and shared references (a
    YAML alias bomb) make a few kilobytes describe billions of them.
    """
    if not isinstance(values, (list, tuple)):
        return
    for item in values:
        if isinstance(item, (list, tuple)):
            if depth <= 1:
                raise DataError(f'{name} must be 1-D: it holds nested sequences, e.g. '
                                f'{bounded_repr(item, 40)}')
            _check_nesting(item, name, depth - 1)


def as_signal(values, name: str) -> np.ndarray:
    """Validate one sampled signal: a finite, 1-D float array (a copy, never a view)."""
    _check_nesting(values, name, 1)
    if isinstance(values, np.ma.MaskedArray) and np.ma.count_masked(values):
        # np.asarray would silently take the values under the mask.
        raise DataError(f'{name} has {np.ma.count_masked(values)} masked value(s); fill or '
                        'remove them before identification')
    try:
        raw = np.asarray(values)
        if raw.dtype.kind in 'cUSVmM':
            # Complex values would silently lose their imaginary part, text would be parsed.
            raise TypeError(f'got values of type {raw.dtype}')
        array = np.array(raw, dtype=float)
    except (TypeError, ValueError, OverflowError) as error:
        raise DataError(f'{name} must be numeric: {error}') from None
    if array.ndim != 1:
        raise DataError(f'{name} must be 1-D, got shape {array.shape}')
    if array.size == 0:
        raise DataError(f'{name} is empty')
    bad = np.flatnonzero(~np.isfinite(array))
    if bad.size:
        raise DataError(f'{name} has {bad.size} non-finite value(s) (NaN or inf), first at '
                        f'sample {bad[0]}; remove or interpolate them before identification')
    return array


def as_inputs(values, count: Optional[int] = None) -> np.ndarray:
    """
    Validate the input samples: an (N, count) float array (a copy).

    A 1-D array is one input; a 2-D array has one column per input. ``count=None`` accepts any
    number of columns.
    """
    _check_nesting(values, 'u', 2)
    if isinstance(values, np.ma.MaskedArray) and np.ma.count_masked(values):
        raise DataError(f'u has {np.ma.count_masked(values)} masked value(s); fill or remove '
                        'them before identification')
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError, OverflowError) as error:
        raise DataError(f'u must be numeric: {error}') from None
    if raw.ndim == 2:
        if raw.shape[1] == 0:
            raise DataError(f'u has no input columns (shape {raw.shape})')
        columns = [as_signal(raw[:, index], f'input column {index}')
                   for index in range(raw.shape[1])]
        matrix = np.column_stack(columns)
    else:
        matrix = as_signal(raw, 'u')[:, None]
    if count is not None and matrix.shape[1] != count:
        raise DataError(f'the model has {count} input(s), the data have {matrix.shape[1]} '
                        'input column(s)')
    return matrix


def _real(value, what: str) -> float:
    """Return a real scalar (not text, not a bool) as float."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise DataError(f'{what} must be a number, got {bounded_repr(value)}')
    try:
        return float(value)
    except (OverflowError, ValueError, TypeError):
        raise DataError(f'{what} must be a finite number, got {bounded_repr(value)}') from None


@dataclass(frozen=True)
class Data:
    """
    Input ``u`` (the reference ``r`` in closed loop) and output ``y`` sampled every ``ts``.

    Parameters
    ----------
    u : array_like
        Input samples, shape (N,), or (N, m) for a model with m inputs (columns in the order of
        ``Model.inputs``).
    y : array_like
        Output samples, shape (N,). All samples are finite and at ``t_k = t0 + k*ts``.
    ts : float
        Sample time in seconds (> 0).
    t0 : float, optional
        Time of the first sample, only used for reporting.
    output_skew : float, optional
        Seconds by which every output sample lags its input sample, ``0 <= output_skew < ts``:
        ``u[k]`` is applied at ``t_k = t0 + k*ts`` (and held, or interpolated, until
        ``t_{k+1}``), ``y[k]`` is measured at ``t_k + output_skew``. Estimation, simulation and
        prediction evaluate the model output at those instants exactly (``docs/algorithm.md``
        section 2). Default 0: both are sampled at ``t_k``.

    Raises
    ------
    DataError
        On unequal lengths, non-finite values, a non-positive sample time or an output skew
        outside ``[0, ts)``.

    """

    u: np.ndarray
    y: np.ndarray
    ts: float
    t0: float = 0.0
    output_skew: float = 0.0

    def __post_init__(self):
        u = as_inputs(self.u)
        u = u[:, 0] if np.ndim(self.u) != 2 else u
        y = as_signal(self.y, 'y')
        if u.shape[0] != y.size:
            raise DataError(f'u and y must have the same length, got {u.shape[0]} and {y.size}')
        ts = _real(self.ts, 'sample time')
        if not (np.isfinite(ts) and ts > 0):
            raise DataError(
                f'sample time must be positive and finite, got {bounded_repr(self.ts)}')
        t0 = _real(self.t0, 'start time t0')
        if not np.isfinite(t0):
            raise DataError(f'start time t0 must be finite, got {bounded_repr(self.t0)}')
        if not np.isfinite(t0 + ts * y.size):
            raise DataError(f'the sample times overflow: t0 {t0:g} s plus {y.size} samples of '
                            f'{ts:g} s is not a finite time')
        skew = _real(self.output_skew, 'output skew')
        if not (np.isfinite(skew) and 0.0 <= skew < ts):
            raise DataError(f'output skew must lie in [0, ts) = [0, {ts:g}) seconds, got '
                            f'{bounded_repr(self.output_skew)}')
        object.__setattr__(self, 'u', u)
        object.__setattr__(self, 'y', y)
        object.__setattr__(self, 'ts', ts)
        object.__setattr__(self, 't0', t0)
        object.__setattr__(self, 'output_skew', skew)

    def __len__(self) -> int:
        return self.y.size

    @property
    def time(self) -> np.ndarray:
        """Return the input sample instants in seconds (outputs: plus :attr:`output_skew`)."""
        return self.t0 + self.ts * np.arange(self.y.size)

    @property
    def input_count(self) -> int:
        """Return the number of input signals (columns of ``u``)."""
        return 1 if self.u.ndim == 1 else self.u.shape[1]

    def detrend(self, kind: str = 'mean') -> 'Data':
        """
        Return the data with the operating point removed from ``u`` and ``y``.

        Parameters
        ----------
        kind : {'mean', 'initial'}
            Subtract the means (as MATLAB's ``detrend(data, 0)``), or the first samples (for a
            record that starts in equilibrium).

        """
        # Values near the float limit overflow: the result is then refused as non-finite.
        with np.errstate(over='ignore', invalid='ignore'):
            if kind == 'mean':
                return Data(self.u - self.u.mean(axis=0), self.y - self.y.mean(), self.ts,
                            self.t0, self.output_skew)
            if kind == 'initial':
                return Data(self.u - self.u[0], self.y - self.y[0], self.ts, self.t0,
                            self.output_skew)
        raise DataError(f"detrend kind must be 'mean' or 'initial', got {bounded_repr(kind)}")

    def segment(self, start: int, stop: Optional[int] = None) -> 'Data':
        """Return samples ``start:stop`` (Python slice rules) as new data, times kept."""
        for name, value in (('start', start), ('stop', stop)):
            if value is not None and (isinstance(value, (bool, np.bool_))
                                      or not isinstance(value, numbers.Integral)):
                raise DataError(f'segment {name} must be an integer sample index, got '
                                f'{bounded_repr(value)}')
        start, stop, _ = slice(start, stop).indices(len(self))
        return Data(self.u[start:stop], self.y[start:stop], self.ts,
                    self.t0 + start * self.ts, self.output_skew)
