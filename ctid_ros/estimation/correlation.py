"""
Input-output correlation: does a model leave anything correlated with the input.

A model that captures the dynamics leaves a residual uncorrelated with past inputs, whatever the
colour of the noise (the test behind MATLAB's ``resid``). A wrong dead time or a missed mode
leaves correlation at the lags it gets wrong. The estimator uses this to accept a local fit
without the automatic start or the dead-time search (``docs/algorithm.md``, section 11).

The same correlation of the data themselves, after prewhitening the input, gives the data's own
dead-time guess (:func:`prewhitened_delay`, section 12).
"""

from bisect import bisect_left
from functools import lru_cache
from typing import List, Optional

from ctid_ros.core.data import Data
from ctid_ros.estimation.linear_algebra import gram_matrix, least_squares, normal_solution
import numpy as np
from scipy import special

__all__ = ['CONFIDENCE', 'autocorrelations', 'bartlett_span', 'bonferroni_quantile',
           'chance_spread', 'fft_size', 'independent_of_input', 'input_correlation',
           'prewhitened_delay', 'whitening_filter']

# Standard deviations of a correlation under independence: about 1 % false alarms over a
# hundred lags (two-sided normal tail 6e-5 per lag).
CONFIDENCE = 4.0
_PREWHITENING_ORDER = 10
# Order of the residual's whitening filter in the prewhitened test: enough for smooth noise
# spectra (what the filter leaves, Bartlett's bound counts); order 10 also whitens away much of
# a new resonance's ringing (on the demo drive its first windows read 3-5 sigma instead of 5-7).
_RESIDUAL_WHITENING_ORDER = 4
# Past values conditioned within this (columns of unit norm) are solved by normal equations.
_NORMAL_CONDITION = 1e3


# The sizes asked for are few (a record's length plus a few lag ranges): remembered.
@lru_cache(maxsize=256)
def fft_size(count: int) -> int:
    """
    Return the smallest ``2^a 3^b 5^c`` of at least ``count`` (1 for none): a fast FFT length.

    Zero padding to it rather than to the next power of two gives the same correlations to
    rounding; numpy's FFT runs these lengths at about the same speed per sample, and the power
    of two can be almost twice as long. Looked up among all such lengths up to ``2^32``; a
    longer ``count`` (32 GB a series) gets the next power of two.
    """
    sizes = _smooth_sizes()
    if count > sizes[-1]:
        return 1 << (count - 1).bit_length()
    return sizes[bisect_left(sizes, count)]


# Every length up to this is looked up (about 1 800 of them).
_LARGEST_SMOOTH = 1 << 32


@lru_cache(maxsize=1)
def _smooth_sizes() -> List[int]:
    """Return every ``2^a 3^b 5^c`` up to :data:`_LARGEST_SMOOTH`, ascending (built once)."""
    sizes = []
    fives = 1
    while fives <= _LARGEST_SMOOTH:
        odd = fives
        while odd <= _LARGEST_SMOOTH:
            size = odd
            while size <= _LARGEST_SMOOTH:
                sizes.append(size)
                size <<= 1
            odd *= 3
        fives *= 5
    return sorted(sizes)


# A few test counts recur (the lags of each estimate, the blocks of each record): remembered.
@lru_cache(maxsize=64)
def bonferroni_quantile(family: float, tests: int) -> float:
    """
    Return the two-sided normal quantile for ``tests`` tests together at ``family``.

    ``family`` is the probability of no alarm over all the tests (Bonferroni: each test's
    two-sided tail is ``(1 - family) / tests``), for the residual analysis's lags and the
    consistency check's blocks alike.
    """
    return float(special.ndtri(1.0 - (1.0 - family) / (2.0 * max(tests, 1))))


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
    first = _first_nonzero(residual)
    if first is None:
        return np.zeros((max_lag + 1, inputs.shape[1]))
    if first:
        error = np.zeros_like(residual)
        error[first:] = residual[first:] - residual[first:].mean()
    else:
        error = residual - residual.mean()
    centred = inputs - inputs.mean(axis=0)
    # Zero padding to N + max_lag keeps the circular correlation free of wrap-around.
    size = fft_size(residual.size + max_lag + 1)
    spectrum = np.fft.rfft(error, size)[:, None] * np.conj(np.fft.rfft(centred, size, axis=0))
    correlation = np.fft.irfft(spectrum, size, axis=0)[:max_lag + 1]
    scale = np.sqrt((error ** 2).sum() * (centred ** 2).sum(axis=0))
    return correlation / np.where(scale > 0.0, scale, 1.0)


def _first_nonzero(values: np.ndarray) -> Optional[int]:
    """Return the index of the first nonzero (or NaN, or True) of ``values``, None if none."""
    if not values.size:
        return None
    nonzero = values != 0
    # argmax of booleans stops at the first True: no index array of every nonzero.
    first = int(nonzero.argmax())
    return first if nonzero[first] else None


def bartlett_span(count: int, max_lag: int) -> int:
    """Return the lags ``|k| <= span`` over which Bartlett's sum runs: ``max(4 L, 50)``, <= N/4."""
    return int(min(count // 4, max(4 * max_lag, 50)))


def autocorrelations(columns: np.ndarray, span: int) -> np.ndarray:
    """
    Return the normalised autocorrelation of each column at lags ``-span..span``.

    Means removed, computed by FFT (zero-padded: no wrap-around); shape ``(2 span + 1, m)``.
    """
    columns = np.asarray(columns, dtype=float)
    columns = columns.reshape(columns.shape[0], -1)
    centred = columns - columns.mean(axis=0)
    size = fft_size(centred.shape[0] + span + 1)
    spectrum = np.fft.rfft(centred, size, axis=0)
    full = np.fft.irfft(spectrum * np.conj(spectrum), size, axis=0)
    values = np.concatenate([full[size - span:], full[:span + 1]]) if span else full[:1]
    energy = (centred ** 2).sum(axis=0)
    return values / np.where(energy > 0.0, energy, 1.0)


def chance_spread(residual_autocorrelation: np.ndarray, input_autocorrelation: np.ndarray,
                  count: int) -> float:
    """
    Return the standard deviation of a cross-correlation of two independent series.

    Bartlett's formula ``sqrt(sum_k rho_e(k) rho_u(k) / N)`` over the lags both are given at
    (the same ``-span..span``): a coloured input and a coloured residual correlate by chance
    far more than white ones. Never below the white value ``1/sqrt(N)``.
    """
    total = float(np.asarray(residual_autocorrelation) @ np.asarray(input_autocorrelation))
    return float(np.sqrt(max(total, 1.0) / max(count, 1)))


def _white_spread(count: int) -> float:
    """
    Return :func:`chance_spread`'s floor ``1/sqrt(N)``, rounded as it rounds it.

    No spread is below it, so a correlation within ``confidence`` times it passes every bound
    without the autocorrelations behind the spread.
    """
    return float(np.sqrt(1.0 / max(count, 1)))


def independent_of_input(residual: np.ndarray, inputs: np.ndarray, max_lag: int,
                         confidence: float = CONFIDENCE, bound: str = 'prewhitened',
                         sensitivities: Optional[np.ndarray] = None) -> bool:
    """
    Return True if the residual shows no correlation with past inputs beyond chance.

    ``bound='bartlett'``: the correlations of the raw series within ``confidence`` of
    Bartlett's standard deviations for them (:func:`chance_spread`), as the residual analysis
    tests: calibrated at an output-error optimum under any colour of input and noise, blind to
    a model error whose ringing the input shares (a resonance in closed loop).
    ``bound='prewhitened'`` (default): the residual is prewhitened by its own autoregressive
    model (least squares, order 4: :func:`whitening_filter`) and every input filtered by the
    same polynomial, as a noise model's innovations are tested; the correlations of the filtered
    series (:func:`input_correlation`) must stay within ``confidence`` of Bartlett's standard
    deviations for them (:func:`chance_spread`: the input's colour, and what the filter left of
    the residual's, counted; ``1/sqrt(N)`` for white series). A held input and coloured noise
    then correlate no more than white ones by chance, while a model error that rings in the
    residual and in a closed-loop input alike (a new resonance) still shows: Bartlett's bound on
    the raw series would call that chance. The filtered residual approximates the innovation,
    independent of the inputs before it even in closed loop, but not of the input at the same
    sample, which a controller's direct term makes react to it: lags from 1 are tested (the
    residual analysis's verdict covers lag 0 where the data show no feedback). Filtering the
    residual, not the input, also keeps that lag-0 correlation from spreading to later lags.
    ``sensitivities``: the model output's derivatives by its parameters (rows as the
    residual's), filtered alike and projected out of the filtered residual: an output-error
    estimate is the optimum of the unfiltered residual, and its (noise-sized) parameter error
    would otherwise show against the whitened input as a model error (a dead time a fraction of
    its standard deviation off correlates at its lag). The test then asks whether any
    parameters of the structure explain the data (at a point that is not an optimum, a small
    error of any parameter is explained too). ``bound='white'``: the white-series bound
    ``confidence/sqrt(N)`` on the raw series (for comparison: it calls a perfect model with
    coloured noise and a held input a model error in most records). ``N`` counts the residual
    samples from its first nonzero one.

    """
    residual = np.asarray(residual, dtype=float)
    first = _first_nonzero(residual)
    if first is None:
        return True
    count = residual.size - first
    inputs = np.asarray(inputs, dtype=float).reshape(residual.size, -1)
    if bound not in ('prewhitened', 'bartlett', 'white'):
        raise ValueError(f"bound must be 'prewhitened', 'bartlett' or 'white', got {bound!r}")
    if bound == 'bartlett' and first == 0 and max_lag <= bartlett_span(count, max_lag):
        return _within_spread(residual, inputs, max_lag, bartlett_span(count, max_lag),
                              confidence)
    if bound != 'prewhitened':
        correlation = input_correlation(residual, inputs, max_lag)
        if bound == 'white':
            return bool(np.abs(correlation).max() <= confidence / np.sqrt(count))
        largest = np.abs(correlation).max(axis=0)
        if (largest <= confidence * _white_spread(count)).all():
            return True
        span = bartlett_span(count, max_lag)
        rho_e = autocorrelations(residual[first:], span)[:, 0]
        rho_u = autocorrelations(inputs[first:], span)
        spreads = np.array([chance_spread(rho_e, rho_u[:, j], count)
                            for j in range(inputs.shape[1])])
        return bool((largest <= confidence * spreads).all())
    polynomial = whitening_filter(residual[first:], _RESIDUAL_WHITENING_ORDER)
    start = polynomial.size - 1
    filtered = np.convolve(residual[first:] - residual[first:].mean(), polynomial)[start:count]
    if sensitivities is not None:
        columns = np.asarray(sensitivities, dtype=float).reshape(residual.size, -1)[first:]
        columns = np.apply_along_axis(np.convolve, 0, columns - columns.mean(axis=0),
                                      polynomial)[start:count]
        if columns.shape[0] > 2 * columns.shape[1]:
            filtered = filtered - columns @ np.linalg.lstsq(columns, filtered, rcond=None)[0]
    lags = min(max_lag, filtered.size // 4)
    if lags < 1 or not filtered.any():
        return True
    span = bartlett_span(filtered.size, lags)
    whitened = np.column_stack([np.convolve(column - column.mean(), polynomial)[start:count]
                                for column in inputs[first:].T])
    if filtered[0] != 0.0:
        return _within_spread(filtered, whitened, lags, span, confidence, first_lag=1)
    # Leading zeros, which input_correlation leaves out of the residual's mean.
    rho_e = None
    for column in whitened.T:
        largest = np.abs(input_correlation(filtered, column, lags)[1:, 0]).max()
        if largest <= confidence * _white_spread(filtered.size):
            continue
        if rho_e is None:
            rho_e = autocorrelations(filtered, span)[:, 0]
        spread = chance_spread(rho_e, autocorrelations(column, span)[:, 0], filtered.size)
        if largest > confidence * spread:
            return False
    return True


def _within_spread(residual: np.ndarray, inputs: np.ndarray, lags: int, span: int,
                   confidence: float, first_lag: int = 0) -> bool:
    """
    Return True if every input's correlation with ``residual`` stays within Bartlett's bound.

    The correlations of :func:`input_correlation` at lags ``first_lag..lags`` within
    ``confidence`` times :func:`chance_spread` of the autocorrelations at ``-span..span``
    (:func:`autocorrelations`), for a residual without leading zeros (``inputs``: shape
    ``(N, m)``). The three come from one zero-padded FFT of each series: ``span >= lags``.
    Correlations within the white bound ``confidence/sqrt(N)``, which no spread goes below,
    pass without the autocorrelations.
    """
    count = residual.size
    error = residual - residual.mean()
    centred = inputs - inputs.mean(axis=0)
    size = fft_size(count + span + 1)
    spectrum = np.fft.rfft(error, size)
    spectra = np.fft.rfft(centred, size, axis=0)
    energy = (error ** 2).sum()
    energies = (centred ** 2).sum(axis=0)
    scale = np.sqrt(energy * energies)
    correlation = np.fft.irfft(spectrum[:, None] * np.conj(spectra), size,
                               axis=0)[first_lag:lags + 1] / np.where(scale > 0.0, scale, 1.0)
    largest = np.abs(correlation).max(axis=0)
    # A model that explains the data passes here.
    if (largest <= confidence * _white_spread(count)).all():
        return True
    full = np.fft.irfft(spectrum * np.conj(spectrum), size)
    rho_e = np.concatenate([full[size - span:], full[:span + 1]]) / \
        (energy if energy > 0.0 else 1.0)
    full = np.fft.irfft(spectra * np.conj(spectra), size, axis=0)
    rho_u = np.concatenate([full[size - span:], full[:span + 1]]) / \
        np.where(energies > 0.0, energies, 1.0)
    spreads = np.array([chance_spread(rho_e, rho_u[:, j], count)
                        for j in range(inputs.shape[1])])
    return bool((largest <= confidence * spreads).all())


def whitening_filter(values: np.ndarray, order: int = _PREWHITENING_ORDER) -> np.ndarray:
    """
    Return ``[1, a_1, ..., a_p]``: the least-squares autoregressive whitening filter of a series.

    ``values - mean`` filtered by it (``a`` applied to past values) leaves the part of each
    sample its past does not predict. Order ``min(order, N/10)``; ``[1]`` for a constant series.
    """
    values = np.asarray(values, dtype=float)
    values = values - values.mean()
    count = values.size
    order = min(order, count // 10)
    if order < 1 or not values.any():
        return np.ones(1)
    # Column 0 the predicted samples, column k their k-th past values.
    lagged = np.empty((count - order, order + 1))
    for k in range(order + 1):
        lagged[:, k] = values[order - k:count - k]
    # The normal equations where the past values are well conditioned (a cond^2 eps relative
    # error), least squares otherwise.
    products = gram_matrix(lagged)
    coefficients = normal_solution(products[1:, 1:], products[1:, 0], _NORMAL_CONDITION)
    if coefficients is None:
        coefficients = least_squares(lagged[:, 1:], lagged[:, 0])
    return np.concatenate([[1.0], -coefficients])


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
    u, y = u - u.mean(), y - y.mean()
    polynomial = whitening_filter(u, order)
    start = polynomial.size - 1
    whitened_u = np.convolve(u, polynomial)[start:count]
    whitened_y = np.convolve(y, polynomial)[start:count]
    correlation = np.abs(input_correlation(whitened_y, whitened_u, count // 2)[:, 0])
    first = _first_nonzero(correlation > CONFIDENCE / np.sqrt(count))
    if first is None:
        return 0.0
    # An output measured output_skew after its input instant shows the response that much
    # earlier in lags.
    return max((first - 0.5) * data.ts - data.output_skew, 0.0)
