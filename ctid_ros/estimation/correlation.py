"""
Residual analysis: does a model leave anything correlated with the input.

A model that captures the dynamics leaves a residual uncorrelated with past inputs, whatever the
colour of the noise (the test behind MATLAB's ``resid``). A wrong dead time or a missed mode
leaves correlation at the lags it gets wrong. The estimator uses this to accept a local fit of a
dead time without searching the whole delay range.
"""

import numpy as np

# Standard deviations of a correlation under independence: about 1 % false alarms over a
# hundred lags (two-sided normal tail 6e-5 per lag).
CONFIDENCE = 4.0


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
    size = 1 << int(np.ceil(np.log2(2 * residual.size)))
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
