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

The raw correlations and their bounds are what a plot shows (as ``resid`` does); the verdict's
test of the input is calibrated for open loop, where the input is independent of the noise. In
closed loop the noise fed back through the controller is in the input, so a coloured residual
correlates with the raw input at lag 0 (a controller's direct term) and at positive lags
although the model is right, and Bartlett's bound, which assumes the two independent, calls
that a model error. So the residual and every input are also filtered by the residual's own
autoregressive whitening filter (order :data:`_WHITENING_ORDER`, as for the amplitude test
below; Box-Jenkins prewhitening): the whitened residual approximates the innovation,
independent of ``u(t - k)`` for ``k >= 1`` even in closed loop, since the input then depends on
the noise up to ``t - k`` only, but not of ``u(t + k)``, ``k >= 0``, which react to it. Where
their correlation at lags ``-M..0`` exceeds the all-lags bound for Bartlett's standard
deviation of the filtered pair, the data show feedback (the input reacts to the noise within a
sample), and the correlations at lags ``1..M`` decide for that input (``prewhitened``);
elsewhere the raw test at lags ``0..M`` does, as before: it keeps its power on a model error
that rings (the whitening filter models much of a resonance's ringing) and its calibration at
an output-error optimum (``docs/algorithm.md`` section 11).

A static nonlinearity (actuator saturation, a dead zone, friction, a valve's curve) leaves a
residual uncorrelated with the input itself but not with its amplitude: the analysis also
tests the residual against the square and cube of every input and of the model's output, less
what the lower powers and the input's lags explain, prewhitened, at about 1 % false alarms of
its own (``amplitude_dependent``).
"""

from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence, Tuple

from ctid_ros.estimation.correlation import (bartlett_span, bonferroni_quantile, chance_spread,
                                             fft_size, whitening_filter)
import numpy as np
from scipy import linalg, special

__all__ = ['DEFAULT_LAGS', 'ResidualAnalysis', 'amplitude_dependence', 'amplitude_note',
           'analyse_residual', 'cross_correlation']

DEFAULT_LAGS = 25
_PER_LAG = 0.99
_FAMILY = 0.99
# A power of an input whose remainder keeps less than this share of its energy is not tested
# (a two-level input's square and cube: rounding).
_AMPLITUDE_ENERGY = 1e-6
# Nor one whose remainder lives on fewer effective samples than this ((sum g^2)^2 / sum g^4).
_AMPLITUDE_SAMPLES = 5.0
# Order of the residual's autoregressive whitening filter before the amplitude test.
_WHITENING_ORDER = 4
# The name of the model output's powers in the verdict.
_MODEL_OUTPUT = 'model output'
# Relative ridge on the inputs' lag-0 autocorrelation in the amplitude test's normal equations.
_RIDGE = 1e-6
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
        For some input, a correlation at lags ``0..M`` exceeds the all-lags bound: the raw one
        against Bartlett's standard deviation, or for an input in ``prewhitened`` the
        prewhitened one at lags ``1..M`` (the module's docstring).
    feedback : bool
        The input test (and the amplitude test) finds nothing, but the input depends on past
        outputs: a raw cross-correlation at negative lags, or a prewhitened one at lags
        ``-M..0``, exceeds the all-lags bound.
    lags : int
        ``M``.
    samples : int
        Residual samples analysed.
    autocorrelation : ndarray, shape (M + 1,)
        Lags ``0..M``.
    cross_correlation : ndarray, shape (2 M + 1, inputs)
        Lags ``-M..M``, one column per input: the raw correlations (what ``resid`` plots; in
        closed loop they are not a test of the model).
    inputs : list of str
        Input names, in column order.
    auto_bound : float
        99 % bound of one autocorrelation value.
    cross_bounds : ndarray, shape (inputs,)
        99 % bound of one raw cross-correlation value, per input, under independence of the
        residual and the input (Bartlett).
    correlated_inputs : list of str
        Inputs the residual correlates with (``input_correlated``).
    worst_lags : list of (str, int, float)
        For each correlated input: name, lag and value of its largest correlation (the
        prewhitened one for an input in ``prewhitened``).
    prewhitened : list of str
        Inputs the prewhitened residual correlates with at lags ``-M..0`` beyond the all-lags
        bound: feedback, so the prewhitened test at lags ``1..M`` decided for them.
    amplitude_dependent : bool
        The prewhitened residual correlates with the square or cube of an input or of the
        model output beyond the all-lags bound (:func:`amplitude_dependence`): a static
        nonlinearity the linear model cannot describe (``docs/algorithm.md`` section 11).
        Set by :meth:`test_amplitude` (``estimate`` runs it on the final residual).
    amplitude_terms : list of (str, int, int, float)
        For each power found: input name (``'model output'``), power, lag and value of its
        largest correlation.
    powers_tested : list of str
        The powers tested, as ``'u^2'``, ``'model output^3'`` (an input's none if it has two
        levels).
    amplitude_score : float
        The largest correlation with a power in standard deviations under independence.
    amplitude_bound : float
        The all-lags bound it is tested against (infinite where no power is tested).
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
    prewhitened: List[str] = field(default_factory=list)
    amplitude_dependent: bool = False
    amplitude_terms: List[Tuple[str, int, int, float]] = field(default_factory=list)
    powers_tested: List[str] = field(default_factory=list)
    amplitude_score: float = 0.0
    amplitude_bound: float = float('inf')
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
    # The model output the residual was taken from (not part of the summary).
    prediction: Optional[np.ndarray] = field(default=None, repr=False, compare=False)
    # The residual's whitening filter (None where it has no finite energy): the amplitude test
    # of the same residual filters by it too.
    whitening: Optional[np.ndarray] = field(default=None, repr=False, compare=False)

    def mark_inconsistent(self) -> None:
        """
        Say in the verdict that one parameter vector does not hold over the record.

        A coloured residual then no longer reads as noise the standard deviations account for:
        the model does not hold over the record (``docs/algorithm.md`` section 18).
        """
        self.consistent = False
        self.verdict = _verdict(self.white, self.correlated_inputs, self.worst_lags,
                                self.feedback, consistent=False,
                                amplitude=self.amplitude_terms)

    def test_amplitude(self, residual: np.ndarray, inputs: np.ndarray,
                       output: Optional[np.ndarray] = None) -> None:
        """
        Test whether the residual depends on the inputs' or the model output's amplitude.

        :func:`amplitude_dependence` on the residual this analysis is of (the inputs and the
        model's output on the same samples); sets the ``amplitude_*`` fields and says what it
        found in the verdict (and drops ``feedback`` where it finds something: the residual is
        then not one the inputs explain nothing of).
        """
        self.amplitude_terms, self.powers_tested, self.amplitude_score, \
            self.amplitude_bound = amplitude_dependence(residual, inputs, self.inputs,
                                                        self.lags, output, self.whitening)
        self.amplitude_dependent = bool(self.amplitude_terms)
        # A residual the inputs' amplitude explains is a model error, which correlates with a
        # coloured input at lags <= 0 too: not evidence of feedback (the cascaded tanks).
        self.feedback = self.feedback and not self.amplitude_dependent
        self.verdict = _verdict(self.white, self.correlated_inputs, self.worst_lags,
                                self.feedback, consistent=self.consistent,
                                amplitude=self.amplitude_terms)

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
            'prewhitened': list(self.prewhitened),
            'amplitude_dependent': bool(self.amplitude_dependent),
            'amplitude_terms': [{'input': name, 'power': int(power), 'lag': int(lag),
                                 'correlation': float(value)}
                                for name, power, lag, value in self.amplitude_terms],
            'powers_tested': list(self.powers_tested),
            'amplitude_score': float(self.amplitude_score),
            'amplitude_bound': float(self.amplitude_bound) if self.powers_tested else None,
            'noise_order': int(self.noise_order),
            'noise_power_ratio': float(self.noise_power_ratio),
            'noise_shaped_by_loop': bool(self.noise_shaped),
            'measured_every': int(self.measured_every),
        }


def analyse_residual(residual: np.ndarray, inputs: np.ndarray, names: Sequence[str],
                     lags: int = DEFAULT_LAGS) -> ResidualAnalysis:
    """
    Analyse ``residual`` against ``inputs`` (one column each, named ``names``).

    The raw correlations and their per-lag bounds are for plots; the verdict's
    ``input_correlated`` comes from the raw test where the data show no feedback and from the
    prewhitened test at lags ``1..M`` where they do (the module's docstring,
    ``docs/algorithm.md`` section 11).

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
    # m + 1..2m) back in one inverse transform. Padded for the prewhitened test's lags too
    # (the span covers them but in records of a few hundred samples).
    # Row-major whatever the inputs' layout: each row's mean is then summed as for that
    # series alone (a column-major stack sums in another order, a few ulps apart).
    spectra, energies, size = _centred_spectra(
        np.ascontiguousarray(np.concatenate([residual[None], inputs.T])),
        max(span, lags + _WHITENING_ORDER))
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
    # The prewhitened correlations (lags -M..M): where they show feedback, the raw test's null
    # does not hold and they decide (see the module's docstring).
    whitening = None
    if np.isfinite(energies[0]):
        whitening = whitening_filter(residual, _WHITENING_ORDER)
        whitened, whitened_spreads = _prewhitened_correlations(
            error[0], signals, _shaping(whitening, size), count, lags, size)
    else:
        whitened, whitened_spreads = np.zeros((inputs_count, 2 * lags + 1)), \
            np.zeros(inputs_count)
    correlated, worst, prewhitened = [], [], []
    feedback = False
    for j, name in enumerate(names):
        if whitened_spreads[j] > 0.0 and \
                np.abs(whitened[j, :lags + 1]).max() > z_all * whitened_spreads[j]:
            prewhitened.append(name)
            later = np.abs(whitened[j, lags + 1:])
            lag = int(later.argmax())
            if later[lag] > z_all * whitened_spreads[j]:
                correlated.append(name)
                worst.append((name, lag + 1, float(whitened[j, lags + 1 + lag])))
        else:
            positive = cross[lags:, j]
            if (np.abs(positive) > z_all * spreads[j]).any():
                lag = int(np.abs(positive).argmax())
                correlated.append(name)
                worst.append((name, lag, float(positive[lag])))
            if (np.abs(cross[:lags, j]) > z_all * spreads[j]).any():
                feedback = True
    # A model error driven by a coloured input correlates with it at negative lags too: only a
    # residual the inputs explain nothing of shows feedback there.
    feedback = (feedback or bool(prewhitened)) and not correlated
    verdict = _verdict(white, correlated, worst, feedback)
    return ResidualAnalysis(verdict, white, bool(correlated), feedback, lags, count, auto,
                            cross, list(names), float(auto_bound), cross_bounds, correlated,
                            worst, prewhitened=prewhitened, long_autocorrelation=rho_e[span:],
                            whitening=whitening)


def _shaping(whitening: np.ndarray, size: int) -> np.ndarray:
    """
    Return the power response, on ``size``-point FFT bins, of the residual's whitening filter.

    ``whitening``: the least-squares autoregressive filter of order :data:`_WHITENING_ORDER`
    (:func:`~ctid_ros.estimation.correlation.whitening_filter` of the residual): the residual
    and the series it is tested against are both filtered by it (Box-Jenkins prewhitening), by
    multiplying their cross-spectrum and power spectra by this.
    """
    return np.abs(np.fft.rfft(whitening, size)) ** 2


def amplitude_dependence(residual: np.ndarray, inputs: np.ndarray, names: Sequence[str],
                         lags: int = DEFAULT_LAGS, output: Optional[np.ndarray] = None,
                         whitening: Optional[np.ndarray] = None
                         ) -> Tuple[List[Tuple[str, int, int, float]], List[str], float, float]:
    """
    Test whether ``residual`` depends on the amplitude of the inputs or of the model output.

    Under a linear model the residual is independent of the inputs, so of any function of
    them; a static nonlinearity (actuator saturation, a dead zone, friction, a valve's curve)
    leaves a residual uncorrelated with the input itself (Bussgang) but correlated with its
    square or cube. Each input's and the model output's square and cube, less what the lower
    powers explain at lag 0 (:func:`_amplitude_terms`) and what the inputs explain at lags
    ``-K..K`` (``K = M + 5``: a linear model error, a missing lag or a wrong dead time, then
    correlates with none of them), and the residual are filtered by the residual's own
    autoregressive whitening filter (order :data:`_WHITENING_ORDER`, Box-Jenkins
    prewhitening: in closed loop the coloured noise fed back correlates with the input at
    positive lags too, its unpredictable part does not). Their cross-correlations at lags from
    1 (an input's: a controller acting on the latest output makes the input depend on the
    residual at lag 0) or 0 (the model output's, which past inputs make) to ``M`` are compared
    with Bartlett's standard deviation under independence, all together at about 1 % false
    alarms (Bonferroni). A power counts only where it correlates both before and after the
    inputs' lags are taken out of it (``docs/algorithm.md`` section 11).

    Parameters
    ----------
    residual : array_like, shape (N,)
        Output minus model output on the fitted samples.
    inputs : array_like, shape (N,) or (N, m)
        The inputs on the same samples.
    names : sequence of str
        Input names.
    lags : int
        ``M``, at most a quarter of the samples.
    output : array_like, shape (N,), optional
        The model's simulated output on the same samples (an output-side nonlinearity).
    whitening : array_like, optional
        The residual's whitening filter where it is known already
        (:attr:`ResidualAnalysis.whitening`); else fitted here.

    Returns
    -------
    found : list of (str, int, int, float)
        Each power the residual depends on: name (``'model output'`` for the model's
        output), power, lag and value of its largest correlation.
    tested : list of str
        The powers tested (``'u^3'``): none of a two-level input, whose square is constant
        and cube proportional to it (a saturation of it is a gain).
    score : float
        The largest correlation in standard deviations under independence.
    bound : float
        The all-lags bound it is tested against (infinite where nothing is tested).

    """
    residual = np.asarray(residual, dtype=float)
    count = residual.size
    inputs = np.asarray(inputs, dtype=float).reshape(count, -1)
    lags = int(max(1, min(lags, count // 4)))
    series = [(name, column, 1) for name, column in zip(names, inputs.T)]
    if output is not None:
        series.append((_MODEL_OUTPUT, np.asarray(output, dtype=float), 0))
    powers, terms = _amplitude_terms(series, count)
    tested = [f'{name}^{power}' for name, power, _ in terms]
    if not terms:
        return [], tested, 0.0, float('inf')
    window = int(min(lags + _WHITENING_ORDER + 1, count // 4))
    # Long enough that no correlation used wraps around: the powers less their fit by the
    # inputs reach ``window`` samples (plus the filter's order) beyond both ends of the record.
    size = fft_size(count + lags + 2 * window + _WHITENING_ORDER + 2)
    error = np.fft.rfft(residual - np.add.reduce(residual) / count, size)
    powers = np.fft.rfft(powers, size)
    # The whitening filter's power response: the residual and the powers both filtered by it.
    if whitening is None:
        whitening = whitening_filter(residual, _WHITENING_ORDER)
    shaping = _shaping(whitening, size)
    threshold = bonferroni_quantile(_FAMILY, sum(lags + 1 - start for _, _, start in terms))
    scores = _prewhitened_scores(error, powers, shaping, [start for _, _, start in terms],
                                 count, lags, size)
    # Only a power that correlates as it is is tested again less its fit by the inputs (in
    # open-loop records the more common alarm, a linear model error, correlates with the
    # inputs' lags and drops out there).
    suspects = [index for index, (score, _, _) in enumerate(scores) if score > threshold]
    if suspects:
        stripped = _less_input_lags(powers[suspects], inputs, size, window)
        if stripped is None:
            return [], [], 0.0, float('inf')
        again = _prewhitened_scores(error, stripped, shaping,
                                    [terms[index][2] for index in suspects], count, lags, size)
        for index, score in zip(suspects, again):
            if score[0] < scores[index][0]:
                scores[index] = score
    found = [(name, power, lag, value) for (name, power, _), (score, lag, value)
             in zip(terms, scores) if score > threshold]
    return found, tested, max(score for score, _, _ in scores), threshold


def _prewhitened_correlations(error: np.ndarray, series: np.ndarray, shaping: np.ndarray,
                              count: int, lags: int, size: int
                              ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return each series' correlations with the residual at lags ``-M..M`` and their spreads.

    ``error``, ``series``: the residual's and the series' spectra (zero-padded to ``size``),
    both filtered by the whitening filter of power response ``shaping`` (an input, or one of
    its powers). Energies and Bartlett's standard deviation under independence
    (:func:`~ctid_ros.estimation.correlation.chance_spread`, summed over all lags) from the
    spectra (Parseval: the one-sided spectrum counts every bin but the first and, for an even
    length, the last twice). Rows ``(p, 2 M + 1)`` and ``(p,)``; a spread of 0 where either
    filtered series has no energy.
    """
    counted = np.full(shaping.size, 2.0 / size)
    counted[0] = 1.0 / size
    if size % 2 == 0:
        counted[-1] = 1.0 / size
    correlations = np.fft.irfft(error * shaping * np.conj(series), size)
    error_power = shaping * (error.real ** 2 + error.imag ** 2)
    series_power = shaping * (series.real ** 2 + series.imag ** 2)
    error_energy = float(counted @ error_power)
    energies = series_power @ counted
    values = np.zeros((series.shape[0], 2 * lags + 1))
    spreads = np.zeros(series.shape[0])
    for row, energy in enumerate(energies):
        if not (energy > 0.0 and error_energy > 0.0):
            continue
        values[row] = _normalised(correlations[row], size, lags, np.sqrt(error_energy * energy))
        spreads[row] = chance_spread(counted * error_power / error_energy,
                                     series_power[row] / energy, count)
    return values, spreads


def _prewhitened_scores(error: np.ndarray, series: np.ndarray, shaping: np.ndarray,
                        starts: Sequence[int], count: int, lags: int,
                        size: int) -> List[Tuple[float, int, float]]:
    """
    Return each series' largest correlation with the residual: in standard deviations, lag, value.

    :func:`_prewhitened_correlations` at lags from each series' first (``starts``) to ``M``.
    """
    values, spreads = _prewhitened_correlations(error, series, shaping, count, lags, size)
    scores = []
    for row, start in enumerate(starts):
        if not spreads[row] > 0.0:
            scores.append((0.0, start, 0.0))
            continue
        tested = values[row, lags + start:]
        lag = int(np.abs(tested).argmax())
        scores.append((float(abs(tested[lag]) / spreads[row]), start + lag, float(tested[lag])))
    return scores


def _less_input_lags(powers: np.ndarray, inputs: np.ndarray, size: int, window: int
                     ) -> Optional[np.ndarray]:
    """
    Return the powers' spectra less their least-squares fit by every input at lags ``-K..K``.

    ``powers``: spectra zero-padded to ``size``; ``inputs``: ``(N, m)``; ``K = window``. One
    input at a time, by the Toeplitz normal equations of its autocorrelation (exact for
    inputs uncorrelated with each other); what is left is uncorrelated with the inputs at
    those lags, so a linear model error cannot correlate with it. None where the equations
    cannot be solved.
    """
    count = inputs.shape[0]
    signals = np.fft.rfft(inputs.T - np.add.reduce(inputs, axis=0)[:, None] / count, size)
    # Lag k at index k (negative lags at the end): each power's correlation with each input,
    # each input's autocorrelation.
    full = np.fft.irfft(np.concatenate([
        (powers[:, None] * np.conj(signals)).reshape(-1, signals.shape[1]),
        signals * np.conj(signals)]), size)
    products = full[:-signals.shape[0]].reshape(powers.shape[0], signals.shape[0], size)
    for index, autocorrelation in enumerate(full[-signals.shape[0]:]):
        column = autocorrelation[:2 * window + 1].copy()
        if not column[0] > 0.0:
            continue
        # A ridge for inputs (nearly) without the highest frequencies.
        column[0] *= 1.0 + _RIDGE
        sums = np.concatenate([products[:, index, size - window:],
                               products[:, index, :window + 1]], axis=1)
        try:
            weights = linalg.solve_toeplitz(column, sums.T).T
        except (linalg.LinAlgError, ValueError):
            return None
        if not np.isfinite(weights).all():
            return None
        placed = np.zeros((powers.shape[0], size))
        placed[:, :window + 1] = weights[:, window:]
        placed[:, size - window:] = weights[:, :window]
        powers = powers - np.fft.rfft(placed) * signals[index]
    return powers


def _amplitude_terms(series: Sequence[Tuple[str, np.ndarray, int]], count: int
                     ) -> Tuple[np.ndarray, List[Tuple[str, int, int]]]:
    """
    Return each series' square and cube less what its lower powers explain, and their labels.

    ``series``: ``(name, values, first lag tested)``. Every series is centred and scaled to
    unit mean square (``x``); ``x^2`` and ``x^3`` are orthogonalised at lag 0 against the
    constant, ``x`` and (for the cube) ``x^2``'s remainder, from the moments of ``x``
    (Hermite-like): a static nonlinearity leaves the odd (saturation, dead zone, friction) or
    even (a quadratic valve) remainder. A power left with (nearly) no energy is not tested: a
    two-level input makes ``x^2`` constant and ``x^3`` proportional to ``x`` (a saturation of
    a binary input is a gain, which the data cannot tell from a linear model), and neither is
    one carried by a few samples only (fewer than :data:`_AMPLITUDE_SAMPLES` effective ones: a
    spike is not an amplitude range). Returns rows ``(p, N)`` and ``(name, power, first
    lag)`` per row.
    """
    rows, terms = [], []
    for name, column, first in series:
        centred = column - column.mean()
        energy = float(centred @ centred)
        if not energy > 0.0 or not np.isfinite(energy):
            continue
        unit = centred * np.sqrt(count / energy)
        square = unit * unit
        cube = square * unit
        # Moments of the unit series: E[x^3], E[x^4], E[x^5], E[x^6].
        third, fourth = float(np.add.reduce(cube)) / count, float(square @ square) / count
        quadratic = square - 1.0 - third * unit
        energy = float(quadratic @ quadratic)
        cubic = cube - third - fourth * unit
        candidates = []
        if energy > _AMPLITUDE_ENERGY * fourth * count:
            candidates.append((2, quadratic, energy))
            cubic = cubic - (float(cubic @ quadratic) / energy) * quadratic
        candidates.append((3, cubic, float(cubic @ cubic)))
        for power, remainder, left in candidates:
            if power == 3 and not left > _AMPLITUDE_ENERGY * float(cube @ cube):
                continue
            squares = remainder * remainder
            if left * left < _AMPLITUDE_SAMPLES * float(squares @ squares):
                continue
            rows.append(remainder)
            terms.append((name, power, first))
    return np.array(rows).reshape(len(rows), count), terms


def amplitude_note(terms: Sequence[Tuple[str, int, int, float]]) -> str:
    """
    Return what a residual that depends on the input's amplitude means, in words.

    ``terms``: :attr:`ResidualAnalysis.amplitude_terms` (the model output's powers named
    ``'model output'``).
    """
    return f'the residual {_amplitude_clause(terms)}'


def _amplitude_clause(terms: Sequence[Tuple[str, int, int, float]]) -> str:
    """Return :func:`amplitude_note` without its subject: ``'depends on ...'``."""
    where = ', '.join(f'{name}^{power} at lag {lag}: {value:+.2f}'
                      for name, power, lag, value in terms)
    on_input = any(name != _MODEL_OUTPUT for name, _, _, _ in terms)
    on_output = any(name == _MODEL_OUTPUT for name, _, _, _ in terms)
    if on_input and on_output:
        source, examples = ("the amplitude of the input and of the model's output",
                            "actuator saturation, a dead zone, friction or a valve's curve")
    elif on_input:
        source, examples = ("the input's amplitude",
                            'actuator saturation, a dead zone or friction')
    else:
        source, examples = ("the model output's amplitude",
                            "friction, a valve's or sensor's curve or an outflow that grows "
                            'with the level')
    return (f'depends on {source} ({where}): a static nonlinearity such as {examples} that '
            'the linear model cannot describe; the standard deviations do not cover it')


def _verdict(white: bool, correlated: List[str], worst: List[Tuple[str, int, float]],
             feedback: bool, consistent: bool = True,
             amplitude: Sequence[Tuple[str, int, int, float]] = ()) -> str:
    """
    Return the verdict line (``consistent``: one parameter vector holds over the record).

    ``amplitude``: the powers the residual depends on (:func:`amplitude_dependence`).
    """
    if correlated:
        where = ', '.join(f'{name} (lag {lag}: {value:+.2f})' for name, lag, value in worst)
        text = (f'correlated with input {where}: missing dynamics or a wrong dead time; the '
                'standard deviations do not cover this model error')
        if amplitude:
            text += f'; also {amplitude_note(amplitude)}'
    elif amplitude:
        text = (f'{"white" if white else "coloured"} and uncorrelated with the input, but '
                f'{_amplitude_clause(amplitude)}')
        if not consistent:
            text += '; the parameters also move across the record'
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
