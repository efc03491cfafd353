"""
Residual analysis of an estimate, as MATLAB's ``resid``, with a one-line verdict.

A model that captures the dynamics leaves a residual that is uncorrelated with past inputs; if
the noise is also white, the residual is white. The analysis computes

* the autocorrelation of the residual at lags ``0..M``;
* its cross-correlation with every input at lags ``-M..M`` (``r(k)`` correlates the residual
  at ``t`` with the input at ``t - k``: positive lags are the input's effect the model
  missed, negative lags mean the input reacts to past outputs, i.e. feedback);
* their 99 % bounds under independence: ``2.58 / sqrt(N)`` for the autocorrelation, and for a
  cross-correlation ``2.58 sqrt(sum_k rho_e(k) rho_u(k) / N)`` (Bartlett's formula: a
  coloured input and a coloured residual correlate more by chance than white ones);

and states a verdict. The verdict tests all lags at once at about 1 % false alarms
(Bonferroni over the lags tested), so the per-lag 99 % bounds that plots show are exceeded by
chance more often than the verdict says so (``docs/algorithm.md`` section 11).
"""

from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence, Tuple

from ctid_ros.estimation.correlation import (bartlett_span, bonferroni_quantile, chance_spread,
                                             fft_size)
import numpy as np
from scipy import special

__all__ = ['DEFAULT_LAGS', 'ResidualAnalysis', 'analyse_residual', 'cross_correlation']

DEFAULT_LAGS = 25
_PER_LAG = 0.99
_FAMILY = 0.99
# The per-lag bound's normal quantile.
_Z_LAG = float(special.ndtri(0.5 + _PER_LAG / 2.0))


def cross_correlation(first: np.ndarray, second: np.ndarray, lags: int) -> np.ndarray:
    """
    Return ``r(k) = sum_t a_t b_{t-k} / sqrt(sum a^2 sum b^2)`` for ``k = -lags..lags``.

    Means are removed first; computed by FFT. ``r(0)`` of a signal with itself is 1.
    """
    spectra, energies, size = _centred_spectra(np.array([first, second], dtype=float), lags)
    return _normalised(np.fft.irfft(spectra[0] * np.conj(spectra[1]), size), size, lags,
                       np.sqrt(energies[0] * energies[1]))


def _centred_spectra(rows: np.ndarray, lags: int) -> Tuple[np.ndarray, List[float], int]:
    """
    Return the centred rows' zero-padded FFTs, their energies and the FFT length.

    Padded to at least the length plus ``lags`` samples: enough for correlations up to that lag
    without wrapping around. Row by row as for each series alone (means and energies summed
    along the row, one transform per row), in one call each.
    """
    # np.mean's sum and division, without its wrappers.
    centred = rows - np.add.reduce(rows, axis=1, keepdims=True) / rows.shape[1]
    size = fft_size(rows.shape[1] + lags + 1)
    return np.fft.rfft(centred, size), [float(row @ row) for row in centred], size


def _normalised(full: np.ndarray, size: int, lags: int, scale: np.ndarray) -> np.ndarray:
    """
    Return the correlations at lags ``-lags..lags`` of the circular ones ``full`` over ``scale``.

    Along the last axis (one row per pair); 0 where ``scale`` is not positive.
    """
    values = np.concatenate([full[..., size - lags:], full[..., :lags + 1]], axis=-1)
    positive = scale > 0.0
    return np.where(positive, values / np.where(positive, scale, 1.0), 0.0)


@dataclass
class ResidualAnalysis:
    """
    Outcome of :func:`analyse_residual`.

    Attributes
    ----------
    verdict : str
        One line: white / correlated with an input (missing dynamics or a wrong dead time) /
        coloured (noise the model does not describe), and feedback if seen.
    white : bool
        No autocorrelation at lags ``1..M`` exceeds the all-lags bound.
    input_correlated : bool
        A cross-correlation at lags ``0..M`` exceeds the all-lags bound for some input.
    feedback : bool
        A cross-correlation at negative lags exceeds it while none at lags ``0..M`` does (the
        input depends on past outputs).
    lags : int
        ``M``.
    samples : int
        Residual samples analysed.
    autocorrelation : ndarray, shape (M + 1,)
        Lags ``0..M``.
    cross_correlation : ndarray, shape (2 M + 1, inputs)
        Lags ``-M..M``, one column per input.
    inputs : list of str
        Input names, in column order.
    auto_bound : float
        99 % bound of one autocorrelation value.
    cross_bounds : ndarray, shape (inputs,)
        99 % bound of one cross-correlation value, per input.
    correlated_inputs : list of str
        Inputs correlated with the residual at lags ``0..M``.
    worst_lags : list of (str, int, float)
        For each correlated input: name, lag and value of its largest correlation.
    noise_order : int
        Order of the residual's autoregressive model behind the covariance (0: white).
    noise_power_ratio : float
        The residual's low-frequency power over that of white noise of equal variance: how
        much the coloured noise widened the standard deviations, squared, for slow signals.
    measured_every : int
        How many samples apart the output was actually measured (1: every sample).

    """

    verdict: str
    white: bool
    input_correlated: bool
    feedback: bool
    lags: int
    samples: int
    autocorrelation: np.ndarray
    cross_correlation: np.ndarray
    inputs: List[str]
    auto_bound: float
    cross_bounds: np.ndarray
    correlated_inputs: List[str] = field(default_factory=list)
    worst_lags: List[Tuple[str, int, float]] = field(default_factory=list)
    noise_order: int = 0
    noise_power_ratio: float = 1.0
    measured_every: int = 1
    # True when the noise model behind the covariance passes through the loop's sensitivity.
    noise_shaped: bool = False
    # False when the parameters move across the record (``Estimate.consistency``).
    consistent: bool = True
    # The estimator's state the residual belongs to (not part of the summary).
    state: Optional[Any] = field(default=None, repr=False, compare=False)
    # The residual's autocorrelation over the longer range of Bartlett's sum (lags 0, 1, ...).
    long_autocorrelation: Optional[np.ndarray] = field(default=None, repr=False,
                                                       compare=False)

    def mark_inconsistent(self) -> None:
        """
        Say in the verdict that one parameter vector does not hold over the record.

        A coloured residual then no longer reads as noise the standard deviations account for:
        the model does not hold over the record (``docs/algorithm.md`` section 18).
        """
        self.consistent = False
        self.verdict = _verdict(self.white, self.correlated_inputs, self.worst_lags,
                                self.feedback, consistent=False)

    def to_dict(self) -> dict:
        """Return the summary as JSON-serialisable types (the ``--json`` ``residual`` object)."""
        return {
            'verdict': self.verdict,
            'white': bool(self.white),
            'input_correlated': bool(self.input_correlated),
            'feedback': bool(self.feedback),
            'correlated_inputs': list(self.correlated_inputs),
            'lags': int(self.lags),
            'samples': int(self.samples),
            'max_autocorrelation': float(np.max(np.abs(self.autocorrelation[1:]), initial=0.0)),
            'auto_bound': float(self.auto_bound),
            'max_cross_correlation': {
                name: float(np.abs(self.cross_correlation[self.lags:, j]).max())
                for j, name in enumerate(self.inputs)},
            'cross_bounds': {name: float(bound)
                             for name, bound in zip(self.inputs, self.cross_bounds)},
            'noise_order': int(self.noise_order),
            'noise_power_ratio': float(self.noise_power_ratio),
            'noise_shaped_by_loop': bool(self.noise_shaped),
            'measured_every': int(self.measured_every),
        }


def analyse_residual(residual: np.ndarray, inputs: np.ndarray, names: Sequence[str],
                     lags: int = DEFAULT_LAGS) -> ResidualAnalysis:
    """
    Analyse ``residual`` against ``inputs`` (one column each, named ``names``).

    Parameters
    ----------
    residual : array_like, shape (N,)
        Output minus model output on the fitted samples.
    inputs : array_like, shape (N,) or (N, m)
        The inputs on the same samples.
    names : sequence of str
        Input names for the verdict.
    lags : int
        ``M``, at most a quarter of the samples.

    """
    residual = np.asarray(residual, dtype=float)
    count = residual.size
    inputs = np.asarray(inputs, dtype=float).reshape(count, -1)
    lags = int(max(1, min(lags, count // 4)))
    span = bartlett_span(count, lags)
    # The residual and every input transformed together; the residual's autocorrelation, its
    # cross-correlation with each input and each input's autocorrelation (rows 0, 1..m and
    # m + 1..2m) back in one inverse transform.
    # Row-major whatever the inputs' layout: each row's mean is then summed as for that
    # series alone (a column-major stack sums in another order, a few ulps apart).
    spectra, energies, size = _centred_spectra(
        np.ascontiguousarray(np.concatenate([residual[None], inputs.T])), span)
    error, signals = spectra[:1], spectra[1:]
    scales = np.sqrt([energies[0] * energy for energy in energies] +
                     [energy * energy for energy in energies[1:]])[:, None]
    correlations = _normalised(np.fft.irfft(np.concatenate([
        error * np.conj(spectra), signals * np.conj(signals)]), size), size, span, scales)
    rho_e = correlations[0]
    auto = rho_e[span:span + lags + 1]
    auto_bound = _Z_LAG / np.sqrt(count)
    # Bartlett: var r_eu(k) = sum_j rho_e(j) rho_u(j) / N, summed where both are correlated.
    inputs_count = inputs.shape[1]
    cross = correlations[1:inputs_count + 1, span - lags:span + lags + 1].T
    spreads = np.array([chance_spread(rho_e, rho_u, count)
                        for rho_u in correlations[inputs_count + 1:]])
    cross_bounds = _Z_LAG * spreads
    z_all = bonferroni_quantile(_FAMILY, lags * (1 + 2 * inputs.shape[1]) + inputs.shape[1])
    # No lag above the bound (a NaN is not white): the largest against it, in one reduction.
    white = bool(np.maximum.reduce(np.abs(auto[1:]), initial=0.0) <= z_all / np.sqrt(count))
    correlated, worst = [], []
    feedback = False
    for j, name in enumerate(names):
        positive = cross[lags:, j]
        if (np.abs(positive) > z_all * spreads[j]).any():
            lag = int(np.abs(positive).argmax())
            correlated.append(name)
            worst.append((name, lag, float(positive[lag])))
        if (np.abs(cross[:lags, j]) > z_all * spreads[j]).any():
            feedback = True
    # A model error driven by a coloured input correlates with it at negative lags too: only a
    # residual the inputs explain nothing of shows feedback there.
    feedback = feedback and not correlated
    verdict = _verdict(white, correlated, worst, feedback)
    return ResidualAnalysis(verdict, white, bool(correlated), feedback, lags, count, auto,
                            cross, list(names), float(auto_bound), cross_bounds, correlated,
                            worst, long_autocorrelation=rho_e[span:])


def _verdict(white: bool, correlated: List[str], worst: List[Tuple[str, int, float]],
             feedback: bool, consistent: bool = True) -> str:
    """Return the verdict line (``consistent``: one parameter vector holds over the record)."""
    if correlated:
        where = ', '.join(f'{name} (lag {lag}: {value:+.2f})' for name, lag, value in worst)
        text = (f'correlated with input {where}: missing dynamics or a wrong dead time; the '
                'standard deviations do not cover this model error')
    elif not white and not consistent:
        text = ('coloured but independent of the input, and the parameters move across the '
                'record: the model does not hold over it (time-varying, nonlinear, or a '
                'missing lag / different structure); the noise alone does not account for it')
    elif not white:
        text = ('coloured but independent of the input: noise or disturbances the model does '
                'not describe; the standard deviations account for it')
    elif not consistent:
        text = ('white and independent of the input, but the parameters move across the '
                'record: the model does not hold over it (time-varying, nonlinear, or a '
                'missing lag / different structure)')
    else:
        text = 'white and independent of the input: nothing left to model'
    if feedback:
        text += ('; correlated with the input at negative lags: the input reacts to the output '
                 '(feedback)')
    return text
