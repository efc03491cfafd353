"""
The noise behind an estimate: its colour, the covariance it implies, and the measured rate.

The output-error estimate stops where the residual ``e`` is orthogonal to the sensitivities
``Psi``, so to first order ``theta_hat - theta = (Psi^T Psi)^-1 Psi^T e``. Its covariance is
``(Psi^T Psi)^-1 Psi^T Sigma Psi (Psi^T Psi)^-1`` with ``Sigma`` the covariance of the noise.
``sigma^2 (Psi^T Psi)^-1`` is that for white noise only; real records (unmodelled dynamics,
drifting disturbances) and outputs interpolated onto a finer grid than they were measured on
have coloured residuals, and that formula then claims far too much. Here the residual's colour
is an autoregressive model ``A(q) e = w`` whose order is chosen by AICc (order 0 for a white
residual: then the formula above is recovered), and ``Psi^T Sigma Psi`` is computed exactly
for that model by filtering ``Psi`` backwards through ``1/A`` (``docs/algorithm.md``
section 15).

:func:`measured_every` recognises an output that was held or linearly interpolated onto the
sample grid from a slower measurement, so the estimate can say so.
"""

from dataclasses import dataclass
import math
import operator
from typing import Optional, Tuple

from ctid_ros.core.simulation import all_finite, all_pole, companion_roots
from ctid_ros.estimation.correlation import fft_size
from ctid_ros.estimation.linear_algebra import (gram_matrix, least_squares, symmetric_eigenvalues,
                                                thin_svd)
import numpy as np

__all__ = ['DEFAULT_CRITERION', 'NoiseModel', 'coloured_covariance', 'inverse_filtered',
           'measured_every', 'model_score', 'noise_memory', 'noise_model', 'noise_root',
           'rational_form', 'shaped_noise_model', 'unit_root']

# Largest autoregressive order tried, and the fraction of the record it may reach.
_MAX_ORDER = 30
_ORDER_FRACTION = 0.05
_PATIENCE = 10
# Interpolation is recognised when this share of an output's bends falls on one phase.
_PHASE_SHARE = 0.99
_MAX_FACTOR = 64
# Highest order of the rational form of a shaping filter that is looked for: a closed loop has
# degree at most 32 in s (core.expression.MAX_DEGREE) and its sampled form no higher order.
_MAX_RATIONAL_ORDER = 40
# A rational form stands for an impulse response it reproduces to this fraction of the peak:
# a hundred times the level at which the response itself was cut (consistency.loop_sensitivity).
_RATIONAL_TOLERANCE = 1e-10
# How the noise model's order is chosen (noise_model).
DEFAULT_CRITERION = 'aicc'
_PENALTIES = {
    'aicc': lambda order, count: 2.0 * order * count / max(count - order - 1, 1),
    'bic': lambda order, count: order * math.log(count),
}


@dataclass
class NoiseModel:
    """
    Autoregressive model ``A(q) e = w`` of a residual.

    Attributes
    ----------
    ar : ndarray
        ``[1, a_1, ..., a_p]`` (``[1]`` for a white residual).
    innovation_variance : float
        Variance of ``w``.
    variance : float
        Variance of the residual itself.
    shaping : ndarray or None
        Impulse response ``h`` (``h[0] = 1``) of a known filter the autoregressive noise passes
        through, ``e = H A^-1 w``: the loop's sensitivity ``1 - T`` when the measured output is
        fed back through a known controller (:func:`shaped_noise_model`); None: ``e = A^-1 w``.

    """

    ar: np.ndarray
    innovation_variance: float
    variance: float
    shaping: Optional[np.ndarray] = None

    @property
    def order(self) -> int:
        """Return the number of autoregressive coefficients (0: white)."""
        return self.ar.size - 1

    @property
    def variance_ratio(self) -> float:
        """Return the low-frequency noise power over that of white noise of equal variance."""
        if self.variance <= 0.0:
            return 1.0          # a residual of exact zeros: no noise to colour
        gain = 1.0 if self.shaping is None else float(self.shaping.sum()) ** 2
        return float(gain * self.innovation_variance / self.ar.sum() ** 2 / self.variance)


def noise_model(residual: np.ndarray, max_order: int = _MAX_ORDER,
                autocorrelation: Optional[np.ndarray] = None,
                criterion: str = DEFAULT_CRITERION) -> NoiseModel:
    """
    Fit an autoregressive model to ``residual`` (Levinson-Durbin, order by AICc or BIC).

    The Yule-Walker estimate from the biased autocovariance, whose polynomial is always stable.
    Orders ``0..min(max_order, 5 % of the samples)`` are compared by
    ``N log(innovation variance) + penalty(p)``: ``'aicc'`` (default) ``2 p N / (N - p - 1)``,
    the corrected Akaike criterion, efficient for a spectrum that no finite order describes
    (noise fed back through a controller, ``docs/algorithm.md`` section 15); ``'bic'``
    ``p log N``, which stops at the first orders and misses a peak of such a spectrum. The
    search ends ten orders after the best. ``autocorrelation``: the residual's normalised
    autocorrelation at lags 0, 1, ... if the caller has it (the residual analysis does), so it
    is not computed again.
    """
    if criterion not in _PENALTIES:
        raise ValueError(f'criterion must be one of {", ".join(_PENALTIES)}, got {criterion!r}')
    penalty = _PENALTIES[criterion]
    residual = np.asarray(residual, dtype=float)
    count = residual.size
    centred = residual - residual.mean()
    variance = float(centred @ centred) / max(count, 1)
    top = int(min(max_order, _ORDER_FRACTION * count))
    if variance == 0.0 or top < 1:
        return NoiseModel(np.ones(1), variance, variance)
    if autocorrelation is not None and autocorrelation.size > top:
        autocovariance = variance * autocorrelation[:top + 1]
    else:
        autocovariance = _autocovariance(centred, top)
    best = (count * math.log(variance), 0, variance)
    # The recursion in Python floats: its vectors hold at most 31 values, where numpy's work
    # per call would cost more than the arithmetic. ar is a_0 .. a_order of the current order.
    # The products by map: the same sum as a generator's, without resuming one per term.
    lags = autocovariance.tolist()
    ar = kept = [1.0]
    error = lags[0]
    for order in range(1, top + 1):
        reflection = -(lags[order] + sum(map(operator.mul, ar[1:], lags[order - 1:0:-1]))
                       ) / error
        ar = [1.0] + [a + reflection * b for a, b in zip(ar[1:], ar[:0:-1])] + [reflection]
        error *= 1.0 - reflection ** 2
        if error <= 0.0:
            break
        score = count * math.log(error) + penalty(order, count)
        if score < best[0]:
            best = (score, order, error)
            kept = ar
        elif order - best[1] >= _PATIENCE:
            # Each further order costs at least 2; ten without a gain end the search.
            break
    return NoiseModel(np.array(kept), float(best[2]), variance)


def _autocovariance(centred: np.ndarray, top: int) -> np.ndarray:
    """
    Return ``sum_t x_t x_t+k / N`` for ``k = 0..top`` (``top < N``) of a centred series.

    Up to the default order's lags directly, one dot product per lag, where an FFT pair of
    the padded record costs several times that: the products over the first ``N - top``
    samples run as one correlation, and the last ``top`` samples add a triangle of their own
    products. More lags by FFT.
    """
    count = centred.size
    if top > _MAX_ORDER:
        size = fft_size(count + top + 1)
        spectrum = np.fft.rfft(centred, size)
        return np.fft.irfft(spectrum * np.conj(spectrum), size)[:top + 1] / count
    sums = np.correlate(centred, centred[:count - top])
    tail = centred[count - top:]
    sums[:top] += np.correlate(tail, tail, 'full')[top - 1:]
    return sums / count


def model_score(model: NoiseModel, count: int, criterion: str = DEFAULT_CRITERION) -> float:
    """
    Return ``N log(innovation variance) + penalty(order)`` of a noise model (lower: better).

    A shaping filter with ``h[0] = 1`` has a unit determinant: it adds nothing to the
    likelihood's normalisation, so shaped and plain models compare on this score directly.
    """
    if model.innovation_variance <= 0.0 or not math.isfinite(model.innovation_variance):
        return math.inf
    penalty = _PENALTIES[criterion](model.order, count)
    return count * math.log(model.innovation_variance) + penalty


def rational_form(impulse: np.ndarray, max_order: int = _MAX_RATIONAL_ORDER,
                  order_hint: int = 1) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """
    Return ``(num, den)`` of the lowest order whose impulse response is ``impulse``, or None.

    A sampled rational filter of order ``m`` satisfies ``(den * h)[k] = 0`` for ``k > m``
    (``den[0] = 1``), so ``den`` is the least-squares solution of that recurrence over the
    response (Prony's method with the order found, not chosen) and ``num = (den * h)[:m + 1]``.
    An order is accepted only if the filter ``num/den`` reproduces ``impulse`` over its whole
    length to 1e-10 of its peak; None if no order up to ``max_order`` does (then the response
    is not that of a low-order filter, or too short to tell).

    ``order_hint``: an order the caller expects (a loop's degree). The search starts there
    only where :func:`_lower_orders_fail` proves that every lower order fails the test above;
    so the result is the same with any hint, only found sooner with a good one.
    """
    impulse = np.asarray(impulse, dtype=float)
    # np.max and np.sum are these reductions behind numpy's dispatch.
    peak = float(np.maximum.reduce(np.abs(impulse), axis=None, initial=0.0))
    if peak == 0.0 or not all_finite(impulse):
        return None
    first = 1
    if 1 < order_hint <= max_order and impulse.size >= 3 * order_hint + 2 and \
            _lower_orders_fail(impulse, order_hint, peak):
        first = order_hint
    for order in range(first, max_order + 1):
        if impulse.size < 3 * order + 2:
            return None
        # Row j: h[j + order] = -(tail . (h[j + order - 1], ..., h[j])); the recurrence holds
        # from k = order + 1 on, i.e. for j >= 1. Column c of the matrix is h shifted by
        # order - c, copied in the column-major order LAPACK takes (no index arrays).
        count = impulse.size - order - 1
        matrix = np.empty((count, order), order='F')
        for column in range(order):
            matrix[:, column] = impulse[order - column:order - column + count]
        tail = least_squares(matrix, -impulse[order + 1:])
        den = np.concatenate([[1.0], tail])
        num = np.convolve(den, impulse[:order + 1])[:order + 1]
        if not (all_finite(den) and num[0] != 0.0):
            continue
        # den * (impulse - response) is den * impulse after the first order + 1 samples: where
        # that exceeds |den|_1 times the tolerance, so does the error itself (no filtering).
        recurrence = np.convolve(den, impulse)[order + 1:impulse.size]
        if np.maximum.reduce(np.abs(recurrence), axis=None, initial=0.0) > \
                2.0 * np.add.reduce(np.abs(den), axis=None) * _RATIONAL_TOLERANCE * peak:
            continue
        pulse = np.zeros(impulse.size)
        pulse[:order + 1] = num
        with np.errstate(all='ignore'):
            error = np.abs(all_pole(den, pulse) - impulse).max()
        if error <= _RATIONAL_TOLERANCE * peak:
            return num, den
    return None


def _lower_orders_fail(impulse: np.ndarray, order: int, peak: float) -> bool:
    """
    Return True if it is proven that no order below ``order`` passes :func:`rational_form`.

    Order ``m``'s recurrence ``r = (den * h)[m + 1:]`` is ``H_m den`` for the matrix ``H_m`` of
    ``h`` shifted by ``0..m``; over rows ``k > order - 1`` it is ``H den`` (``den`` padded
    with zeros) for ``H = H_(order - 1)``, so, ``n`` the number of those rows (below the
    response's length, which the test uses for it: a stricter test), ``max|r| >= |r|_2 / sqrt(n) >=
    sigma_min(H) |den|_2 / sqrt(n) >= sigma_min(H) |den|_1 / sqrt(order n)`` for every
    ``den`` with ``den[0] = 1``. Where that exceeds twice the test's bound
    ``2 |den|_1 1e-10 peak`` (room for the rounding of the convolution), every lower order
    fails. ``sigma_min(H)^2`` is the Gram matrix's least eigenvalue, less a bound on the
    rounding of its sums and of the eigenvalue. False where that is not shown.
    """
    size, top = impulse.size, order - 1
    rows = size - top - 1
    shifted = np.empty((rows, order), order='F')
    for column in range(order):
        shifted[:, column] = impulse[top + 1 - column:top + 1 - column + rows]
    gram = gram_matrix(shifted)
    if not all_finite(gram):
        return False
    rounding = 4.0 * (size + order) * np.finfo(float).eps * float(np.trace(gram))
    bound = 4.0 * _RATIONAL_TOLERANCE * peak
    least = float(symmetric_eigenvalues(gram)[0]) - rounding
    return least > bound * bound * order * size


def inverse_filtered(shaping: np.ndarray, values: np.ndarray,
                     order_hint: int = 1) -> np.ndarray:
    """
    Return ``H^-1 values`` for the filter ``H`` of impulse response ``shaping`` (``h[0] != 0``).

    This is ``lfilter([1], shaping, values)``, the forward substitution, which with a response
    thousands of samples long is a recursion of that order. Where the response is that of a
    low-order rational filter ``num/den`` (:func:`rational_form`; the loop sensitivity of a
    closed-loop model is one, of the loop's order) the same inverse is ``den/num``: an FIR pass
    and an all-pole recursion of that low order, equal to the long form to the rounding of
    the response's own cut. A response without such a form takes the long recursion.
    ``order_hint``: the order of that form the caller expects (:func:`rational_form`).
    """
    values = np.asarray(values, dtype=float)
    form = rational_form(shaping, order_hint=order_hint)
    if form is None:
        # Imported here: only a shaping without a low-order form needs it, and scipy.signal is
        # slow to import (all_pole's banded solve with a band this long is far slower).
        from scipy.signal import lfilter
        return lfilter([1.0], shaping, values)
    num, den = form
    return all_pole(num, np.convolve(den, values)[:values.size])


def shaped_noise_model(residual: np.ndarray, shaping: np.ndarray,
                       criterion: str = DEFAULT_CRITERION, order_hint: int = 1) -> NoiseModel:
    """
    Fit ``e = H A^-1 w``: an autoregressive model of ``H^-1 e`` for a known filter ``H``.

    ``shaping`` is the impulse response of ``H`` (``h[0] = 1``, negligible beyond its length);
    ``H^-1 e`` is computed by :func:`inverse_filtered` (``order_hint``: ``H``'s expected
    order, which only speeds the search for its rational form).
    Where ``H`` has zeros on the unit circle (the sensitivity of a loop with integrators) the
    substitution is marginally stable: a residual it does not fit blows up, and
    :func:`model_score` then prefers the plain model.
    """
    residual = np.asarray(residual, dtype=float)
    with np.errstate(all='ignore'):
        prewhitened = inverse_filtered(shaping, residual - residual.mean(), order_hint)
    if not all_finite(prewhitened):
        return NoiseModel(np.ones(1), math.inf, float(np.var(residual)), np.asarray(shaping))
    inner = noise_model(prewhitened, criterion=criterion)
    return NoiseModel(inner.ar, inner.innovation_variance, float(np.var(residual)),
                      np.asarray(shaping, dtype=float))


def coloured_covariance(psi: np.ndarray, residual: np.ndarray, parameters: int,
                        svd: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None,
                        autocorrelation: Optional[np.ndarray] = None,
                        criterion: str = DEFAULT_CRITERION,
                        model: Optional[NoiseModel] = None,
                        root: Optional[np.ndarray] = None) -> Tuple[np.ndarray, NoiseModel]:
    """
    Return ``(Psi^T Psi)^-1 Psi^T Sigma Psi (Psi^T Psi)^-1`` and the noise model behind it.

    ``Sigma`` is the covariance of the autoregressive model of the residual
    (:func:`noise_model`), scaled by ``N / (N - parameters)`` like ``|e|^2 / (N - n)``, so a
    white residual gives exactly ``sigma^2 (Psi^T Psi)^-1``. With ``Psi = U S V^T``,
    ``(Psi^T Psi)^-1 Psi^T = V S^-1 U^T`` and ``U^T Sigma U = sigma_w^2 Z^T Z``, ``Z = H^T U``
    with ``H`` the (causal) impulse-response matrix of ``1/A``: ``Z`` is ``U`` filtered through
    ``1/A`` backwards in time. Scale ``Psi``'s columns first: the SVD keeps the precision the
    normal equations would square away. ``svd``: ``np.linalg.svd(psi, full_matrices=False)``,
    ``autocorrelation``: that of the residual, if the caller has them; ``criterion``: how the
    noise model's order is chosen (:func:`noise_model`); ``model``: the noise model to use, if
    the caller has chosen it (a plain or a loop-shaped one, :func:`shaped_noise_model`; then
    ``autocorrelation`` and ``criterion`` are not used), and ``root``: ``unit_root(U, model)``,
    if the caller has it.
    """
    count = residual.size
    if model is None:
        model = noise_model(residual, autocorrelation=autocorrelation, criterion=criterion)
    left, singular, right_t = thin_svd(psi) if svd is None else svd
    if singular.size == 0 or singular[-1] <= 0.0:
        return np.full((psi.shape[1],) * 2, np.inf), model
    mapping = right_t.T / singular                       # V S^-1
    if model.order == 0 and model.shaping is None:
        variance = float(residual @ residual) / max(count - parameters, 1)
        return variance * (mapping @ mapping.T), model
    scale = count / max(count - parameters, 1)
    if root is None:
        filtered = noise_root(left, model, scale)
        return mapping @ gram_matrix(filtered) @ mapping.T, model
    # The unit root's p x p products scaled, rather than a scaled copy of the N x p root.
    gram = (scale * model.innovation_variance) * gram_matrix(root)
    return mapping @ gram @ mapping.T, model


def noise_root(columns: np.ndarray, model: NoiseModel, scale: float = 1.0) -> np.ndarray:
    """
    Return ``Z`` with ``Z^T Z = X^T Sigma X`` for the columns ``X`` (rows: samples).

    ``Sigma = scale sigma_w^2 H H^T`` is the covariance of ``model`` (``H`` the causal
    impulse-response matrix of ``1/A``), so ``Z = sqrt(scale) sigma_w H^T X``: ``X`` filtered
    through ``1/A`` backwards in time. ``scale`` is ``N / (N - n)`` for the covariance of an
    estimate (:func:`coloured_covariance`).
    """
    return np.sqrt(scale * model.innovation_variance) * _backward_filtered(columns, model)


def unit_root(columns: np.ndarray, model: NoiseModel) -> np.ndarray:
    """
    Return :func:`noise_root` of ``columns`` for unit innovations: the filtering alone.

    ``noise_root(columns, model, scale)`` is ``sqrt(scale sigma_w^2)`` times it, to the last
    bit: one filter pass serves every scale and every use of the same model's filter. A new
    array in C order, as the scaled one is: its products read it as such.
    """
    return np.array(_backward_filtered(columns, model), order='C')


def _backward_filtered(columns: np.ndarray, model: NoiseModel) -> np.ndarray:
    """Return ``H^T X``: the columns filtered through ``model``'s filter backwards in time."""
    columns = np.asarray(columns, dtype=float)
    if model.shaping is not None:
        # H^T X: the columns filtered through the shaping backwards in time.
        count = columns.shape[0]
        size = fft_size(count + model.shaping.size)
        spectrum = np.fft.rfft(columns[::-1].reshape(count, -1), size, axis=0)
        filtered = np.fft.irfft(spectrum * np.fft.rfft(model.shaping, size)[:, None], size,
                                axis=0)[:count]
        columns = filtered[::-1].reshape(columns.shape)
    if model.order:
        columns = all_pole(model.ar, columns[::-1])[::-1]
    return columns


def noise_memory(model: NoiseModel, limit: int) -> int:
    """
    Return how many samples :func:`noise_root`'s filter takes to forget a state (<= ``limit``).

    Past that many samples the response of ``1/A`` (and the shaping) to any state it holds is
    below :data:`_FORGOTTEN` of that state's own size: a block's filtered map is exact to
    rounding when only those samples before the block are filtered. From ``A``'s largest root
    ``r``: ``ln(1/_FORGOTTEN) / ln(1/r)`` samples plus the order, doubled until the impulse
    response over the last ``2 order`` of them is that small (roots near each other decay
    more slowly at first); ``limit`` for an ``A`` with a root on or outside the unit circle.
    """
    shaping = 0 if model.shaping is None else model.shaping.size
    order = model.order
    if order == 0:
        return min(shaping, limit)
    radius = float(np.abs(companion_roots(model.ar)).max())
    if not radius < 1.0:
        return limit
    span = order + (1 if radius == 0.0 else
                    int(np.ceil(math.log(_FORGOTTEN) / math.log(radius))))
    while span + shaping < limit:
        impulse = np.zeros(span + order)
        impulse[0] = 1.0
        response = np.abs(all_pole(model.ar, impulse))
        if response[span - order:].max() <= _FORGOTTEN * response.max():
            return span + shaping
        span *= 2
    return limit


# What a filtered state may keep of its size once noise_memory's samples have passed.
_FORGOTTEN = 1e-20


def measured_every(y: np.ndarray) -> int:
    """
    Return how many samples apart the output was actually measured (1: every sample).

    An output held (zero-order) or linearly interpolated onto the grid from a measurement every
    ``m`` samples changes slope (or value) only on one phase of ``m``: at least 99 % of its
    nonzero second (or first) differences fall on samples ``k = r mod m``, for the largest such
    ``m`` up to 64, and the output bends at half of those samples or more.
    """
    y = np.asarray(y, dtype=float)
    scale = float(np.abs(y).max()) if y.size else 0.0
    best = 1
    differences = y
    for order in (1, 2):
        # np.diff(y, 2) is the difference of np.diff(y): the first order's, differenced again
        # (by np.diff's own subtraction).
        differences = differences[1:] - differences[:-1]
        changing = np.abs(differences) > 1e-9 * scale
        count = int(np.count_nonzero(changing))
        if count < 4 or -(-differences.size // 2) < _PHASE_SHARE * count:
            # Too few changes, or none of the factors below has room for them (measured
            # data, which move on nearly every sample).
            continue
        moving = np.flatnonzero(changing)
        # One phase of m holds at most a 1/m share of the samples: measured data, which move
        # on (nearly) every sample, rule out every factor at once.
        largest = int(min(_MAX_FACTOR, differences.size / (_PHASE_SHARE * moving.size) + 1))
        for factor in range(2, largest + 1):
            if -(-differences.size // factor) < _PHASE_SHARE * moving.size:
                # No phase of this or a larger factor has room for the share.
                break
            phases = np.bincount(moving % factor, minlength=factor)
            if phases.max() >= _PHASE_SHARE * moving.size and \
                    phases.max() >= 0.5 * differences.size / factor:
                best = max(best, factor)
    return best
