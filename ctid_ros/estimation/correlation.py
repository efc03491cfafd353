"""
Input-output correlation: does a model leave anything correlated with the input.

A model that captures the dynamics leaves a residual uncorrelated with past inputs, whatever the
colour of the noise (the test behind MATLAB's ``resid``). A wrong dead time or a missed mode
leaves correlation at the lags it gets wrong. The estimator uses this to accept a local fit
without the automatic start or the dead-time search (``docs/algorithm.md``, section 11).

The same correlation of the data themselves, after prewhitening the input, gives the data's own
dead-time guess (:func:`prewhitened_delay`, section 12).
"""

from ctid_ros.core.data import Data
import numpy as np

__all__ = ['CONFIDENCE', 'independent_of_input', 'input_correlation', 'prewhitened_delay']

# Standard deviations of a correlation under independence: about 1 % false alarms over a
# hundred lags (two-sided normal tail 6e-5 per lag).
CONFIDENCE = 4.0
_PREWHITENING_ORDER = 10


def input_correlation(residual: np.ndarray, inputs: np.ndarray, max_lag: int) -> np.ndarray:
    """
    Normalised cross-correlation of a residual with past inputs.

    Parameters
    ----------
    residual : array_like, shape (N,)
        Output minus model output. Leading zeros (samples left out of a fit) are allowed.
    inputs : array_like, shape (N,) or (N, m)
        The inputs on the same sample grid.
    max_lag : int
        Largest lag in samples (>= 0).

    Returns
    -------
    ndarray, shape (max_lag + 1, m)
        ``r[k, j] = sum_t e[t] u_j[t - k] / sqrt(sum e^2 * sum u_j^2)`` with the means of ``e``
        and ``u_j`` removed. Under independence each value has standard deviation about
        ``1/sqrt(N)``.

    """
    residual = np.asarray(residual, dtype=float)
    inputs = np.asarray(inputs, dtype=float).reshape(residual.size, -1)
    used = np.flatnonzero(residual)
    if used.size == 0:
        return np.zeros((max_lag + 1, inputs.shape[1]))
    first = used[0]
    error = np.zeros_like(residual)
    error[first:] = residual[first:] - np.mean(residual[first:])
    centred = inputs - np.mean(inputs, axis=0)
    # Zero padding to N + max_lag keeps the circular correlation free of wrap-around.
    size = 1 << int(np.ceil(np.log2(residual.size + max_lag + 1)))
    spectrum = np.fft.rfft(error, size)[:, None] * np.conj(np.fft.rfft(centred, size, axis=0))
    correlation = np.fft.irfft(spectrum, size, axis=0)[:max_lag + 1]
    scale = np.sqrt(np.sum(error ** 2) * np.sum(centred ** 2, axis=0))
    return correlation / np.where(scale > 0.0, scale, 1.0)


def independent_of_input(residual: np.ndarray, inputs: np.ndarray, max_lag: int,
                         confidence: float = CONFIDENCE) -> bool:
    """
    Return True if no correlation of :func:`input_correlation` exceeds ``confidence/sqrt(N)``.

    ``N`` counts the residual samples from its first nonzero one.

    """
    residual = np.asarray(residual, dtype=float)
    used = np.flatnonzero(residual)
    if used.size == 0:
        return True
    count = residual.size - used[0]
    correlation = input_correlation(residual, inputs, max_lag)
    return bool(np.max(np.abs(correlation)) <= confidence / np.sqrt(count))


def prewhitened_delay(data: Data) -> float:
    """
    Dead-time guess: first lag of significant prewhitened input-output correlation.

    An autoregressive model of the (first) input (least squares, order 10) whitens it; the same
    filter applied to the output leaves a cross-correlation proportional to the impulse response
    (Box-Jenkins prewhitening), whose first lag above ``CONFIDENCE/sqrt(N)``, less half a
    sample for the hold, is the guess. A slowly held input that the filter cannot whiten
    gives an early guess: it only orders the search, it does not bound it from below.

    """
    u = np.asarray(data.u, dtype=float).reshape(len(data), -1)[:, 0]
    y = np.asarray(data.y, dtype=float)
    count = u.size
    order = min(_PREWHITENING_ORDER, count // 10)
    if order < 1 or not np.ptp(u):
        return 0.0
    u, y = u - np.mean(u), y - np.mean(y)

    def lagged(values: np.ndarray) -> np.ndarray:
        return np.column_stack([values[order - k - 1:count - k - 1] for k in range(order)])

    inputs = lagged(u)
    coefficients = np.linalg.lstsq(inputs, u[order:], rcond=None)[0]
    whitened_u = u[order:] - inputs @ coefficients
    whitened_y = y[order:] - lagged(y) @ coefficients
    correlation = np.abs(input_correlation(whitened_y, whitened_u, count // 2)[:, 0])
    significant = np.flatnonzero(correlation > CONFIDENCE / np.sqrt(count))
    if significant.size == 0:
        return 0.0
    # An output measured output_skew after its input instant shows the response that much
    # earlier in lags.
    return max((significant[0] - 0.5) * data.ts - data.output_skew, 0.0)
