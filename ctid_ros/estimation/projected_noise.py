"""
The noise a fit removed: the residual's autocovariance restored before its noise model.

An output-error estimate stops where the residual is orthogonal to the sensitivities ``Psi``,
and the noise model is fitted to the residual with its mean removed: ``e = M v``,
``M = I - B B^T``, ``B`` an orthonormal basis of ``Psi``'s columns and the constant. ``e``
holds nothing of the noise ``v`` along ``B``. For white noise that costs ``n + 1`` of ``N``
degrees of freedom, which ``N / (N - n)`` restores. For coloured noise it costs far more where
it matters: the sensitivities have their energy at low frequency, where the noise has its
power, so the residual's low-frequency power, and with it the sandwich's
``Psi^T Sigma Psi``, falls short by about ``n r / N`` (``r`` the noise's low-frequency power
over white noise of equal variance): 10-25 % of the variance on 300 samples of noise coloured
to ``r = 20``, nothing on long records (``docs/algorithm.md`` section 15).

:func:`restored_noise_model` corrects the residual's autocovariance for the projection, a
method-of-moments analogue of restricted maximum likelihood: the lag-``k`` sum of ``e`` has the
expectation ``sum_t E[v_t v_t+k] - D_k`` with

    D_k = tr(L_k (B W^T + W B^T - B G B^T)),   W = Sigma B,   G = B^T Sigma B,

``L_k`` the lag-``k`` shift. ``D_k`` is computed for the current noise model (``W`` by filtering
``B`` backwards and forwards through it, the lag sums by FFT), added back, the autoregressive
model refitted to the restored autocovariance, and that repeated until the model settles.

:func:`noise_freedom` gives each standard deviation's effective degrees of freedom: how much
the noise model's own estimation error moves it. The autoregressive coefficients ``a`` of an
order-``p`` model fitted to ``N`` samples scatter with covariance ``sigma_w^2 R_p^-1 / N``
(``R_p`` the ``p x p`` autocovariance; by Gohberg-Semencul ``sigma_w^2 R_p^-1 = L_1 L_1^T -
L_2 L_2^T``, ``L_1``, ``L_2`` lower triangular Toeplitz of ``1, a_1 .. a_p-1`` and
``a_p .. a_1``), ``log sigma_w^2`` with variance ``2 / (N - n)``; the gradient ``g_i`` of
``log P_ii`` in ``a`` (exact, from two filter passes) gives ``var(log P_ii) = 2 / (N - n) +
g_i^T sigma_w^2 R_p^-1 g_i / N`` and ``nu_i = 2 / var(log P_ii)``, as for a variance
estimate distributed ``chi^2_nu / nu``. For white noise ``nu = N - n``; for a slow parameter
under noise of low-frequency power ``r`` times white, ``nu`` is about ``N / (2 r)``.
"""

from functools import lru_cache
from typing import Optional, Tuple

from ctid_ros.core.simulation import all_pole
from ctid_ros.estimation.linear_algebra import gram_matrix
from ctid_ros.estimation.noise import (DEFAULT_CRITERION, noise_model, noise_root, NoiseModel,
                                       unit_root)
import numpy as np

__all__ = ['RESTORE_PASSES', 'filtered_twice', 'low_frequency_level', 'noise_freedom',
           'restored_covariance', 'restored_noise_model']

# Most refits of the noise model to the restored autocovariance (each adds back what the
# previous model says the projection removed; the low-frequency level settles within a per
# cent by the third).
RESTORE_PASSES = 3
# A restoration that moves the low-frequency level by less than this share is not needed
# (on a long record), or has settled (between passes).
_NEGLIGIBLE = 0.005
# Longest lag the noise model may use (noise.noise_model's own limits are lower).
_MAX_LAG = 30
# filtered_twice takes one recursion of A^2 and A's FIR back from it for polynomials of at most
# this order (each FIR pass costs a fraction of a recursion's) whose coefficients after a_0 sum
# in magnitude to at most this share of a_0: A then keeps every root within that radius, and
# the squared recursion and the FIR stay within a few ulps of two recursions of A (roots near
# the unit circle would cost the squared recursion digits).
_FIR_ORDER = 8
_FIR_SUM = 0.9


def _lag_sums(first: np.ndarray, second: np.ndarray, lags: int, size: int) -> np.ndarray:
    """Return ``sum_i sum_t first[t, i] second[t + k, i]`` for ``k = 0..lags``."""
    spectrum = np.sum(np.conj(np.fft.rfft(first, size, axis=0)) *
                      np.fft.rfft(second, size, axis=0), axis=1)
    return np.fft.irfft(spectrum, size)[:lags + 1]


def _removed(basis: np.ndarray, model: NoiseModel, lags: int, size: int) -> np.ndarray:
    """Return ``D_k``, ``k = 0..lags``: the lag sums the projection on ``basis`` removes."""
    # W = Sigma B = sigma_w^2 H H^T B: backwards through 1/A (noise_root), then forwards.
    applied = np.sqrt(model.innovation_variance) * all_pole(model.ar,
                                                            noise_root(basis, model))
    gram = basis.T @ applied
    gram = 0.5 * (gram + gram.T)
    return (_lag_sums(basis, applied, lags, size) + _lag_sums(applied, basis, lags, size)
            - _lag_sums(basis @ gram, basis, lags, size))


def restored_noise_model(left: np.ndarray, residual: np.ndarray,
                         criterion: str = DEFAULT_CRITERION,
                         start: Optional[NoiseModel] = None) -> NoiseModel:
    """
    Return the autoregressive noise model of the residual before the fit's projection.

    Parameters
    ----------
    left : ndarray
        Orthonormal columns spanning the sensitivities (``U`` of their SVD), rows: samples.
    residual : ndarray
        The fit's residual, orthogonal to ``left``'s columns.
    criterion : str
        How the order is chosen (:func:`~ctid_ros.estimation.noise.noise_model`).
    start : NoiseModel, optional
        The model of the residual itself, if the caller has it.

    Returns
    -------
    NoiseModel
        Fitted to the residual's autocovariance plus what the projection on ``left``'s columns
        and the constant removed (module docstring); ``variance`` is the restored one. The
        model of the residual itself if it is white, or the record too short for a model.

    """
    residual = np.asarray(residual, dtype=float)
    count = residual.size
    model = noise_model(residual, criterion=criterion) if start is None else start
    if model.order == 0 or model.shaping is not None or model.variance <= 0.0:
        return model
    # The projection removes about (n + 1) r / N of the low-frequency level: nothing to
    # restore on a long record.
    if (left.shape[1] + 1) * max(model.variance_ratio, 1.0) < _NEGLIGIBLE * count:
        return model
    basis, _ = np.linalg.qr(np.column_stack([left, np.ones(count)]))
    lags = int(min(_MAX_LAG, count - 1))
    size = 1 << int(np.ceil(np.log2(count + lags + 1)))
    centred = residual - residual.mean()
    sums = _lag_sums(centred[:, None], centred[:, None], lags, size)
    level = low_frequency_level(model)
    for _ in range(RESTORE_PASSES):
        restored = sums + _removed(basis, model, lags, size)
        if restored[0] <= 0.0:
            break
        variance = float(restored[0]) / count
        fitted = noise_model(residual, autocorrelation=restored / restored[0],
                             criterion=criterion)
        # noise_model scaled the autocorrelation by the residual's own variance.
        scale = variance / fitted.variance
        model = NoiseModel(fitted.ar, fitted.innovation_variance * scale, variance)
        previous, level = level, low_frequency_level(model)
        if abs(level - previous) < _NEGLIGIBLE * previous:
            break
    return model


def low_frequency_level(model: NoiseModel) -> float:
    """Return the model's spectrum at frequency 0, ``sigma_w^2 / A(1)^2`` (unshaped)."""
    return model.innovation_variance / float(model.ar.sum()) ** 2


def restored_covariance(psi: np.ndarray, residual: np.ndarray,
                        svd: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None,
                        criterion: str = DEFAULT_CRITERION,
                        start: Optional[NoiseModel] = None
                        ) -> Optional[Tuple[np.ndarray, NoiseModel, np.ndarray]]:
    """
    Return the sandwich covariance with the restored noise model, that model and its root.

    ``psi``: the (column-scaled) sensitivities, ``svd`` their thin SVD if the caller has it;
    ``start``: the residual's own noise model. None if that model is white or shaped by a
    loop (the caller's covariance stands: ``N / (N - n)`` restores a white residual exactly).
    The restored variance already counts the removed degrees of freedom: no ``N / (N - n)``.
    The root is ``U`` filtered through the restored model for unit innovations
    (:func:`~ctid_ros.estimation.noise.unit_root`), for the checks after the covariance.
    """
    left, singular, right_t = np.linalg.svd(psi, full_matrices=False) if svd is None else svd
    if singular.size == 0 or singular[-1] <= 0.0:
        return None
    model = restored_noise_model(left, residual, criterion, start)
    if model is start or model.order == 0:
        return None
    mapping = right_t.T / singular
    root = unit_root(left, model)
    # noise_root(left, model) to the last bit (unit_root): one filter pass for both.
    filtered = np.sqrt(model.innovation_variance) * root
    return mapping @ gram_matrix(filtered) @ mapping.T, model, root


def filtered_twice(columns: np.ndarray, model: NoiseModel) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return ``Z = H^T X`` and ``Y = H^T Z``: the columns through ``1/A`` backwards once and twice.

    ``Z`` is :func:`~ctid_ros.estimation.noise.unit_root` of the columns ``X`` for the unshaped
    ``model`` and ``Y`` that of ``Z``. ``H^T`` is ``1/A`` backwards in time, so ``Y`` is ``X``
    through ``1/A^2`` and ``Z = A(S^T) Y`` (``S`` the lower shift, ``Y`` zero past the record):
    one recursion of twice the order and ``order`` FIR passes, where two recursions of ``A``
    would run. Two recursions where ``A`` is long or near the unit circle
    (:data:`_FIR_ORDER`, :data:`_FIR_SUM`).
    """
    ar = model.ar
    order = ar.size - 1
    unit = NoiseModel(ar, 1.0, model.variance)
    if order > _FIR_ORDER or float(np.abs(ar[1:]).sum()) > _FIR_SUM * abs(float(ar[0])):
        once = unit_root(columns, unit)
        return once, unit_root(once, unit)
    twice = unit_root(columns, NoiseModel(np.convolve(ar, ar), 1.0, model.variance))
    once = ar[0] * twice
    for lag in range(1, order + 1):
        once[:-lag] += ar[lag] * twice[lag:]
    return once, twice


def _log_diagonal(mapping: np.ndarray, left: np.ndarray, model: NoiseModel,
                  root: Optional[np.ndarray] = None, again: Optional[np.ndarray] = None
                  ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return ``log d`` and its gradient in ``a_1 .. a_p``, ``d`` the diagonal of ``M Z^T Z M^T``.

    ``Z = H^T U`` with ``H = A(S)^-1`` the causal impulse-response matrix of ``1/A`` for unit
    innovations (``S`` the lower shift). ``dH/da_k = -S^k H^2``: lower triangular Toeplitz
    matrices commute, so ``dZ/da_k = -(S^T)^k Y`` with ``Y = H^T Z``, the root filtered once
    more, moved ``k`` samples earlier. Two filter passes give the exact gradient, where
    differences would take one pass per coefficient. ``root``: ``Z``, and ``again``: ``Y``
    (:func:`filtered_twice`), if the caller has them.
    """
    unit = NoiseModel(model.ar, 1.0, model.variance)
    root = noise_root(left, unit) if root is None else root
    again = noise_root(root, unit) if again is None else again
    # Through p x p Gram matrices: numpy's product of the long, reversed root with the
    # mapping does not reach BLAS speed.
    diagonal = np.einsum('ij,jk,ik->i', mapping, gram_matrix(root), mapping)
    order = model.order
    crosses = np.zeros((order,) + (root.shape[1],) * 2)
    for lag in range(1, min(order, root.shape[0] - 1) + 1):
        crosses[lag - 1] = root[:-lag].T @ again[lag:]
    # Every lag's quadratic forms in one call.
    gradient = -np.einsum('ij,ljk,ik->il', mapping, crosses + crosses.transpose(0, 2, 1),
                          mapping) / diagonal[:, None]
    return np.log(diagonal), gradient


# One noise order per estimate, and a few orders overall: remembered.
@lru_cache(maxsize=64)
def _toeplitz_steps(order: int) -> np.ndarray:
    """Return ``i - j`` below the diagonal of an ``order`` square matrix, ``order`` above it."""
    steps = np.subtract.outer(np.arange(order), np.arange(order))
    steps[steps < 0] = order
    steps.flags.writeable = False
    return steps


def noise_freedom(left: np.ndarray, mapping: np.ndarray, model: NoiseModel, count: int,
                  parameters: int, removed_share: float = 0.0,
                  root: Optional[np.ndarray] = None,
                  again: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return each standard deviation's effective degrees of freedom (module docstring).

    Parameters
    ----------
    left : ndarray
        ``U`` of the scaled sensitivities' thin SVD (rows: samples).
    mapping : ndarray
        ``V S^-1`` of that SVD: the covariance is ``mapping U^T Sigma U mapping^T``.
    model : NoiseModel
        The noise model behind the covariance.
    count, parameters : int
        Fitted samples and free parameters.
    removed_share : float
        Share of the noise's low-frequency level the fit's projection took out of the
        residual: the coefficients are determined by that share fewer samples' worth of
        residual (``count (1 - removed_share)``).
    root : ndarray, optional
        ``left`` filtered through ``1/A`` backwards in time for unit innovations
        (:func:`~ctid_ros.estimation.noise.noise_root`), if the caller has it.
    again : ndarray, optional
        ``root`` filtered so once more (:func:`filtered_twice`), if the caller has it.

    Returns
    -------
    ndarray
        ``nu_i`` per row of ``mapping``, at least 1. A model shaped by a loop gets
        ``N / r - n`` for all (``r`` its low-frequency power ratio, at least 1).

    """
    rows = mapping.shape[0]
    if model.shaping is not None:
        ratio = max(float(model.variance_ratio), 1.0)
        return np.full(rows, max(count / ratio - parameters, 1.0))
    residual_freedom = max(count - parameters, 1)
    variance = np.full(rows, 2.0 / residual_freedom)
    order = model.order
    if order:
        _, gradient = _log_diagonal(mapping, left, model, root, again)
        # Lower triangular Toeplitz matrices of a_0 .. a_p-1 and a_p .. a_1, by indexing
        # (past the last coefficient: the zero appended above the diagonal).
        steps = _toeplitz_steps(order)
        first = np.concatenate([model.ar[:order], [0.0]])[steps]
        second = np.concatenate([model.ar[:0:-1], [0.0]])[steps]
        inverse = first @ first.T - second @ second.T
        informative = count * (1.0 - min(max(removed_share, 0.0), 0.9))
        variance += np.einsum('ij,jk,ik->i', gradient, inverse, gradient) / informative
    return np.maximum(2.0 / variance, 1.0)
