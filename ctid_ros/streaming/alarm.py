"""
Change alarms: whether the plant has moved away from its baseline.

:class:`ChangeDetector` turns the estimates of successive windows, with their covariances, into
an alarm whose false-alarm rate is set by the user (``false_alarm_per_hour``) rather than by a
per-window threshold. It is shared by the live node and ``ctid replay --sliding``, like the
session: both feed it every :class:`~ctid_ros.streaming.session.Update` and publish or print
the :class:`AlarmStatus` it returns. The method (docs/algorithm.md, section 17):

* **Statistic.** For each watched parameter (those with a baseline, see
  :mod:`ctid_ros.streaming.baseline`) the change ``d = theta - theta_0`` of a window is
  compared with a dead zone ``m = delta + 2.576 sigma_0``: ``delta`` is the practical
  threshold ``min_relative_change * |theta_0|`` (a real but smaller change is no alarm) and
  ``sigma_0`` the baseline's own standard deviation. The baseline's error is the same in every
  window, so it cannot average out like the windows' noise: it widens the dead zone (to its
  99 % bound) instead of entering each window as noise. The excess, in the window's standard
  deviation ``sigma``, ``z+ = (d - m)/sigma`` for an increase and ``z- = (-d - m)/sigma`` for a
  decrease, is standard normal at the edge of the dead zone and smaller inside it.
* **Accumulation.** Two one-sided CUSUMs per parameter, ``S = max(0, S + (z - k)/sqrt(v))``
  with the reference ``k = 1`` (:data:`REFERENCE`), alarm at ``S >= h``.
* **Overlap.** Windows of ``W`` fitted seconds every ``U`` seconds share data: their estimates
  correlate as ``rho_j = max(0, 1 - j U/W)`` (:func:`~ctid_ros.streaming.baseline.overlap`).
  Dividing by the square root of the long-run variance ``v = 1 + 2 sum_j rho_j``
  (:func:`long_run_variance`) makes the sum behave like a Brownian motion with unit variance
  per window, whatever the overlap.
* **Threshold.** ``h`` solves Siegmund's average run length of a CUSUM on a Brownian motion,
  ``ARL = (exp(2 kappa b) - 2 kappa b - 1)/(2 kappa^2)`` with ``kappa = k/sqrt(v)`` and
  ``b = h + c`` (:func:`brownian_arl`, :func:`cusum_threshold`), for ``ARL`` = the windows of
  ``1/false_alarm_per_hour`` hours times the number of one-sided tests (a union bound over
  two per watched parameter). ``c`` is the overshoot of the discrete sum over the barriers:
  1.166 for independent windows (Siegmund), larger for overlapping ones, for which it was
  fitted by Monte Carlo (:func:`overshoot`; checked by test_alarm.py and bench/alarm.py).
* **Persistence.** An alarm needs the window before to lean the same way (its estimate beyond
  the dead zone on that side: a real change persists, and overlapping windows share its
  data), and a window adds at most ``0.55 h`` unless the one before leaned that way: a single
  window (an estimator outlier) can neither raise an alarm nor leave more than ``0.55 h``
  behind. A window whose model check failed (below) adds nothing but still leans: the windows
  that straddle a step fail the check (or carry inflated standard deviations), and the first
  clean window after them can then raise the alarm.
* **Robustness.** The windows' standard deviations are scaled by ``lambda``, at least 1: the
  robust spread of the standardised differences of non-overlapping windows over the last
  :data:`SCALE_HISTORY` (:func:`robust_scale`). A covariance that is optimistic by a constant
  factor is corrected once :data:`SCALE_MIN_WINDOWS` differences are in; a bias is not (it is
  what the dead zone and a captured baseline are for).
* **Model check.** A window whose residual is correlated with the input (a model that misses
  dynamics: a new resonance, a wrong dead time) does not feed the sums (:func:`model_check`;
  the estimator's ``Estimate.residuals`` verdict when it gives one). The windows that hold data
  from both sides of a parameter step fail it too, ``window/update_period`` of them at most;
  after one more such window in a row (:attr:`ChangeDetector.failures_to_warn`) the status is
  WARN ``model no longer explains the data``.

An alarm stays raised (ERROR) until its sum falls back to zero (the recent windows are inside
the dead zone again), or until a new baseline is set (``~/capture_baseline``); ``reset``
clears the sums and keeps the baseline.
"""

from collections import deque
from dataclasses import dataclass, field
import math
from typing import Any, Deque, Dict, List, Optional, Sequence, Tuple

from ctid_ros.errors import DataError
from ctid_ros.estimation.correlation import independent_of_input
from ctid_ros.estimation.problem import settling_time
from ctid_ros.streaming.baseline import average_windows, Baseline, overlap
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import ERROR, LEVELS, NANOSECONDS, OK, WARN
from ctid_ros.streaming.session import Update
import numpy as np

__all__ = ['AlarmSettings', 'AlarmStatus', 'BASELINE_QUANTILE', 'CAP', 'ChangeDetector',
           'LEVEL_NAMES', 'MODEL_FAILURES', 'ParameterChange', 'REFERENCE', 'SCALE_HISTORY',
           'SCALE_MIN_WINDOWS', 'brownian_arl', 'brownian_barrier', 'cusum_threshold',
           'long_run_variance', 'model_check', 'noise_only', 'output_sensitivities', 'overshoot',
           'robust_scale']

LEVEL_NAMES = {level: name for name, level in LEVELS.items()}
# CUSUM reference, in window standard deviations beyond the dead zone: the sums grow while
# windows exceed it by more than one standard deviation (fastest for about two).
REFERENCE = 1.0
# Normal quantile of the baseline's uncertainty added to the dead zone (99 %, two-sided).
BASELINE_QUANTILE = 2.576
# A window adds at most this fraction of the threshold unless the one before it added too.
CAP = 0.55
# While alarmed, a sum is kept below this multiple of the threshold, so it can clear.
CEILING = 2.0
# Standardised differences of non-overlapping windows kept for the robust scale, and how many
# are needed before it is used.
SCALE_HISTORY = 500
SCALE_MIN_WINDOWS = 30
# Windows in a row whose model fails the residual check before the status says so, beyond
# those a single change can straddle (window/update_period of them: a step of a parameter
# also fails the check in the windows holding data from both sides of it).
MODEL_FAILURES = 1
# Lags of the fallback residual check (without the estimator's verdict).
_CHECK_LAGS = 100
_MAD_TO_STD = 1.4826
# Differences beyond this many robust standard deviations are left out of the scale (a normal
# one is that far once in 16 000).
_REJECT = 4.0
_Z95 = 1.959964
# Overshoot of the discrete sum over the barriers (in long-run standard deviations) against
# window length / update period: Siegmund's 1.166 for independent windows, Monte Carlo
# (bench/alarm.py --calibrate) for overlapping ones with the autocorrelation of overlap().
# The table is 0.05 below the measured values (fewer false alarms, not more).
_OVERSHOOT = ((1.0, 1.13), (1.25, 1.47), (1.5, 1.61), (2.0, 1.77), (2.5, 2.03), (3.0, 2.22),
              (4.0, 2.61), (6.0, 3.25), (8.0, 3.75), (12.0, 4.61))


def long_run_variance(window: float, period: float) -> float:
    """
    Return ``v = 1 + 2 sum_j rho_j`` of estimates of ``window``-second windows ``period`` apart.

    With ``rho_j = max(0, 1 - j period/window)``: 1 without overlap, about
    ``window/period`` with it (exactly that for a whole ratio).
    """
    lags = np.arange(1, int(math.ceil(window / period)) + 1)
    return float(1.0 + 2.0 * np.sum(np.maximum(0.0, 1.0 - lags * period / window)))


def overshoot(window: float, period: float) -> float:
    """
    Return the overshoot correction ``c`` of the threshold, in long-run standard deviations.

    Interpolated (linearly in the square root of ``window/period``) in a table fitted by Monte
    Carlo; beyond its end, extrapolated along its last segment.
    """
    ratio = max(window / period, 1.0)
    roots = np.sqrt([entry[0] for entry in _OVERSHOOT])
    values = np.array([entry[1] for entry in _OVERSHOOT])
    if ratio <= _OVERSHOOT[-1][0]:
        return float(np.interp(math.sqrt(ratio), roots, values))
    slope = (values[-1] - values[-2]) / (roots[-1] - roots[-2])
    return float(values[-1] + slope * (math.sqrt(ratio) - roots[-1]))


def brownian_arl(kappa: float, barrier: float) -> float:
    """
    Return the average run length of a CUSUM on a Brownian motion with drift ``-kappa``.

    Siegmund's formula ``(exp(2 kappa b) - 2 kappa b - 1)/(2 kappa^2)`` (unit variance per
    step, barrier ``b``).
    """
    x = 2.0 * kappa * barrier
    return (math.expm1(x) - x) / (2.0 * kappa * kappa)


def brownian_barrier(kappa: float, run_length: float) -> float:
    """Return the barrier ``b`` at which :func:`brownian_arl` reaches ``run_length``."""
    low, high = 0.0, 1.0
    while brownian_arl(kappa, high) < run_length:
        high *= 2.0
    for _ in range(100):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if brownian_arl(kappa, middle) < run_length else (low, middle)
    return high


def cusum_threshold(run_length: float, window: float, period: float,
                    reference: float = REFERENCE) -> float:
    """
    Return the threshold ``h`` of the scaled CUSUM for an in-control average run length.

    ``h = b - c``: the Brownian barrier (:func:`brownian_barrier`, drift
    ``kappa = reference/sqrt(v)``) less the overshoot (:func:`overshoot`), at least 0.5.

    Parameters
    ----------
    run_length : float
        Windows between false alarms of one one-sided CUSUM, on average.
    window, period : float
        Fitted seconds per window and seconds between windows (for the overlap).
    reference : float
        ``k`` in window standard deviations.

    """
    kappa = reference / math.sqrt(long_run_variance(window, period))
    return max(brownian_barrier(kappa, run_length) - overshoot(window, period), 0.5)


def robust_scale(differences: Sequence[float]) -> float:
    """
    Return how much wider than reported the estimates scatter: at least 1.

    ``differences`` are the standardised differences of non-overlapping windows (standard
    normal for a calibrated covariance). Their spread is estimated robustly: differences
    further than four median absolute deviations (in standard deviations) from the median are
    left out (the few that straddle a change), the rest give a root mean square, which is then
    raised by its standard error (a relative ``1/sqrt(2 n_eff)`` with ``n_eff = n/2``:
    neighbouring differences share windows) so that a spread estimated too small does not raise
    the false-alarm rate. 1 until :data:`SCALE_MIN_WINDOWS` differences are in.
    """
    count = len(differences)
    if count < SCALE_MIN_WINDOWS:
        return 1.0
    data = np.fromiter(differences, dtype=float, count=count)
    centre = float(np.median(data))
    spread = _MAD_TO_STD * float(np.median(np.abs(data - centre)))
    if spread <= 0.0:
        return 1.0
    kept = data[np.abs(data - centre) <= _REJECT * spread] - centre
    spread = math.sqrt(float(np.mean(kept ** 2)))
    return max(1.0, spread * (1.0 + 1.0 / math.sqrt(kept.size)))


def model_check(update: Update, window: float, transient: float = -1.0,
                coloured: bool = True) -> Tuple[bool, str]:
    """
    Return whether the window's model explains its data, and the verdict in words.

    Fails when the estimator's verdict (``Estimate.residuals``) finds the residual correlated
    with the input, or else when the residual test of docs/algorithm.md section 11 does, on the
    fitted samples (after ``transient`` seconds, or for an automatic one after the settling time
    of the estimate, and at most the last ``window`` seconds, as the session fits them): their
    correlation with the input at lags 1 to :data:`_CHECK_LAGS` (and a quarter of them; not
    at lag 0, where a controller's direct term puts the noise into the input),
    prewhitened by the residual's own AR model, the estimate's sensitivities
    (:func:`output_sensitivities`) projected out, within four of Bartlett's standard
    deviations for the colour of both (``4/sqrt(N)`` for white ones; ``coloured=False`` keeps
    that fixed bound on the raw series, for comparison: a held input with coloured noise fails
    it in most windows). The second test looks further back than the verdict's lags: a new
    lightly damped mode rings longer than they reach, and in closed loop the verdict may call
    it coloured noise. Integrating models (fitted on a high-passed output) get the verdict only.
    A residual that depends on the input's amplitude (a static nonlinearity, the verdict's
    ``amplitude_dependent``) does not fail it: friction or saturation present from the start is
    no change, and one that appears moves the parameters, which the detector watches.
    """
    residuals = update.result.residuals
    if residuals is not None and residuals.input_correlated:
        return False, residuals.verdict
    result, data = update.result, update.window.data
    if getattr(result.model, 'integrators', 0):
        return True, ''
    record = len(data) * data.ts
    if transient >= 0.0:
        fitted = record - transient
    else:
        fitted = min(window, record - settling_time(result.model.coefficients(result.params)))
    count = min(len(data), int(round(fitted / data.ts)))
    if count < 16:
        return True, ''
    residual = np.asarray(data.y, dtype=float)[-count:] - update.prediction[-count:]
    inputs = np.asarray(data.u, dtype=float).reshape(len(data), -1)[-count:]
    if not np.all(np.isfinite(residual)):
        return False, 'the model output is not finite'
    if not np.any(residual):
        return True, 'residual independent of the input'
    sensitivities = output_sensitivities(result, data)[-count:] if coloured else None
    if independent_of_input(residual, inputs, min(_CHECK_LAGS, count // 4),
                            bound='prewhitened' if coloured else 'white',
                            sensitivities=sensitivities):
        return True, 'residual independent of the input'
    return False, ('residual correlated with the input: missing dynamics (e.g. a new resonance) '
                   'or a wrong dead time')


def output_sensitivities(result: Any, data: Any) -> np.ndarray:
    """
    Return the derivatives of the estimate's simulated output on ``data`` by its parameters.

    Central differences of :meth:`Estimate.simulate` (steps of 1e-5 of each value, at least
    1e-9), one column per parameter in ``result.model.parameters`` order.
    """
    names = result.model.parameters
    columns = []
    for name in names:
        step = max(1e-5 * abs(result.params[name]), 1e-9)
        shifted = []
        for sign in (1.0, -1.0):
            params = dict(result.params)
            params[name] = params[name] + sign * step
            shifted.append(result.model.simulate(params, data.u, data.ts,
                                                 intersample=result.intersample,
                                                 output_skew=data.output_skew))
        columns.append((shifted[0] - shifted[1]) / (2.0 * step))
    return np.column_stack(columns)


def noise_only(update: Update, covariance: np.ndarray) -> np.ndarray:
    """
    Return the window's covariance as a change test needs it: the noise's alone.

    Where the window's parameters move across it (its consistency check flagged it, section
    18) the estimate reports standard deviations that cover the scatter of its quarters: the
    honest spread of the answer, but for the change test a window that straddles a change
    would then hide the change behind it. Nor does the test take the small-sample t factors (a
    quantile correction of a single window's interval, not a variance) or the restored
    projected noise (it grows where a model that does not hold across the window colours the
    residual): the estimate's ``std_change`` (section 17). The test compares each window with
    the baseline on that covariance (the correlations kept); that an adequate model's windows
    agree with it is what :func:`robust_scale` learns anyway. An estimate without
    ``std_change`` gets the noise-only covariance where it was flagged.
    """
    result = update.result
    std = getattr(result, 'std_change', None)
    if not std:
        consistency = getattr(result, 'consistency', None)
        if consistency is None or consistency.consistent or not result.std_noise:
            return covariance
        std = result.std_noise
    ratio = np.array([std.get(name, math.nan) / result.std[name]
                      if result.std.get(name) else 1.0 for name in update.names])
    ratio = np.where(np.isfinite(ratio) & (ratio > 0.0) & (ratio < 1.0), ratio, 1.0)
    return covariance * np.outer(ratio, ratio)


@dataclass(frozen=True)
class AlarmSettings:
    """
    What the detector needs of the configuration.

    Attributes
    ----------
    names : tuple of str
        Parameters in publishing order.
    window, update_period : float
        Fitted seconds per window and seconds between windows.
    false_alarm_per_hour : float
        Target false-alarm rate of a stationary plant.
    relative_changes : tuple of float
        Practical threshold per name (fraction of the baseline).
    baseline_windows : int
        Windows a capture averages.
    transient : float
        Seconds of each window simulated but not fitted (negative: automatic), for the
        fallback model check.

    """

    names: Tuple[str, ...]
    window: float
    update_period: float
    false_alarm_per_hour: float
    relative_changes: Tuple[float, ...]
    baseline_windows: int
    transient: float = -1.0

    @classmethod
    def from_config(cls, config: IdentificationConfig) -> 'AlarmSettings':
        """Return the settings of ``config``."""
        changes = config.relative_changes()
        return cls(tuple(config.names), config.window, config.update_period,
                   config.false_alarm_per_hour, tuple(changes[name] for name in config.names),
                   config.baseline_windows, config.transient)

    @property
    def windows_per_hour(self) -> float:
        """Return the windows estimated in an hour."""
        return 3600.0 / self.update_period

    def threshold(self, tests: int) -> float:
        """Return ``h`` for ``tests`` one-sided CUSUMs sharing the false-alarm rate."""
        run_length = max(tests, 1) * self.windows_per_hour / self.false_alarm_per_hour
        return cusum_threshold(run_length, self.window, self.update_period)


@dataclass(frozen=True)
class ParameterChange:
    """
    One watched parameter in one window.

    Attributes
    ----------
    name : str
        The parameter.
    baseline, value : float
        Its baseline and its estimate in the window.
    change : float
        ``value - baseline``.
    std : float
        Standard deviation of the change (window and baseline, with the robust scale).
    threshold : float
        The practical threshold ``min_relative_change * |baseline|``.
    evidence : float
        The larger of its two sums over the alarm threshold (1 = alarm).
    scale : float
        The robust scale applied to the window's standard deviation (1 = as reported).
    alarmed : bool
        True while its alarm is raised.
    since_ns : int or None
        Estimated start of the change (end of the last window before the evidence grew).

    """

    name: str
    baseline: float
    value: float
    change: float
    std: float
    threshold: float
    evidence: float
    scale: float
    alarmed: bool
    since_ns: Optional[int]

    @property
    def relative(self) -> float:
        """Return the change as a fraction of the baseline (NaN for a zero baseline)."""
        return self.change / abs(self.baseline) if self.baseline else math.nan

    @property
    def interval(self) -> Tuple[float, float]:
        """Return the 95 % interval of the change."""
        return self.change - _Z95 * self.std, self.change + _Z95 * self.std

    def describe(self) -> str:
        """Return e.g. ``'J +60.2 % (95 %: +59.5 to +60.9 %)'``."""
        low, high = self.interval
        if self.baseline:
            scale = 100.0 / abs(self.baseline)
            return (f'{self.name} {scale * self.change:+.3g} % (95 %: {scale * low:+.3g} to '
                    f'{scale * high:+.3g} %)')
        return f'{self.name} {self.change:+.3g} (95 %: {low:+.3g} to {high:+.3g})'


@dataclass(frozen=True)
class AlarmStatus:
    """
    The alarm after one window: what ``~/alarm`` publishes and ``ctid replay`` reports.

    Attributes
    ----------
    level : int
        OK, WARN (the model no longer explains the data) or ERROR (a parameter changed).
    parameters : tuple of str
        Parameters whose alarm is raised, in publishing order.
    since_ns : int or None
        When the change (or the model failure) began, estimated: the end of the last window
        before it showed; None when OK.
    time_ns : int or None
        End of the window (None before any).
    summary : str
        What happened, for people (no times: :meth:`text` adds them).
    changes : tuple of ParameterChange
        Every watched parameter in this window (empty without a baseline or an unused window).
    used : bool
        True if the window fed the sums.
    model_ok : bool
        The model check of the window.
    verdict : str
        The residual verdict in words.
    threshold : float
        ``h`` (scaled sums).
    distance : float
        Mahalanobis distance of the watched estimates from the baseline (both covariances);
        NaN when not computed.
    baseline : str
        Where the baseline came from ('' without one).

    """

    level: int
    parameters: Tuple[str, ...] = ()
    since_ns: Optional[int] = None
    time_ns: Optional[int] = None
    summary: str = 'no estimate yet'
    changes: Tuple[ParameterChange, ...] = ()
    used: bool = False
    model_ok: bool = True
    verdict: str = ''
    threshold: float = math.nan
    distance: float = math.nan
    baseline: str = ''

    @property
    def level_name(self) -> str:
        """Return ``'OK'``, ``'WARN'`` or ``'ERROR'``."""
        return LEVEL_NAMES[self.level]

    def to_dict(self) -> Dict[str, Any]:
        """
        Return the ``--json`` object of a window.

        ``{"level": "OK"|"WARN"|"ERROR", "parameters": [names], "since": seconds}``, ``since``
        in the time base of the window's ``time`` (stamps in seconds), null when OK.
        """
        return {'level': self.level_name, 'parameters': list(self.parameters),
                'since': None if self.since_ns is None else self.since_ns / NANOSECONDS}

    def text(self, origin_ns: int = 0) -> str:
        """Return the status message, with ``since`` in seconds after ``origin_ns``."""
        if self.since_ns is None:
            return self.summary
        return f'{self.summary} since t={(self.since_ns - origin_ns) / NANOSECONDS:.2f} s'

    def diagnostics(self, origin_ns: int = 0) -> Dict[str, Any]:
        """Return the key/value pairs merged into the node's ``/diagnostics`` status."""
        values: Dict[str, Any] = {'alarm': self.level_name, 'alarm_message': self.text(origin_ns)}
        if self.parameters:
            values['alarm_parameters'] = list(self.parameters)
        if self.since_ns is not None:
            values['alarm_since'] = (self.since_ns - origin_ns) / NANOSECONDS
        return values

    def values(self, origin_ns: int = 0) -> Dict[str, Any]:
        """Return the key/value pairs of the ``~/alarm`` status (times after ``origin_ns``)."""
        values: Dict[str, Any] = {'parameters': list(self.parameters)}
        if self.since_ns is not None:
            values['since'] = (self.since_ns - origin_ns) / NANOSECONDS
            values['since_stamp'] = self.since_ns / NANOSECONDS
        if self.time_ns is not None:
            values['window_end'] = self.time_ns / NANOSECONDS
        values.update({'baseline': self.baseline or 'none', 'window_used': self.used,
                       'model_explains_data': self.model_ok})
        if self.verdict:
            values['residual'] = self.verdict
        if math.isfinite(self.distance):
            values['distance'] = self.distance
        for change in self.changes:
            low, high = change.interval
            values.update({f'{change.name}.baseline': change.baseline,
                           f'{change.name}.change': change.change,
                           f'{change.name}.relative_change': change.relative,
                           f'{change.name}.change_low': low, f'{change.name}.change_high': high,
                           f'{change.name}.threshold': change.threshold,
                           f'{change.name}.evidence': change.evidence,
                           f'{change.name}.scale': change.scale})
        return values


@dataclass
class _Sums:
    """The two one-sided CUSUMs of one parameter (see :meth:`add`)."""

    up: float = 0.0
    down: float = 0.0
    start: List[Optional[int]] = field(default_factory=lambda: [None, None])
    alarmed: List[bool] = field(default_factory=lambda: [False, False])
    since: List[Optional[int]] = field(default_factory=lambda: [None, None])
    added: List[bool] = field(default_factory=lambda: [False, False])

    def add(self, increments: Sequence[float], threshold: float, previous_ns: int,
            leaning: Sequence[bool]) -> None:
        """
        Add one window's increments (up, down) to the sums.

        An increment is capped at :data:`CAP` of the threshold unless the previous window
        leaned the same way (its estimate beyond the dead zone on that side, ``leaning``), and
        an alarm is raised only when the sum reaches the threshold with this window adding and
        the previous one leaning: one window alone (an estimator outlier) can neither raise an
        alarm nor leave more than ``CAP`` behind.
        """
        sums = [self.up, self.down]
        for side, increment in enumerate(increments):
            limit = threshold if self.added[side] else CAP * threshold
            grown = max(0.0, sums[side] + min(increment, limit))
            if sums[side] == 0.0 and grown > 0.0:
                self.start[side] = previous_ns
            confirmed = self.added[side] and increment > 0.0
            if grown >= threshold and confirmed and not self.alarmed[side]:
                self.alarmed[side], self.since[side] = True, self.start[side]
            if self.alarmed[side]:
                grown = min(grown, CEILING * threshold)
                if grown == 0.0:
                    self.alarmed[side], self.since[side] = False, None
            sums[side] = grown
        self.corroborate(leaning)
        self.up, self.down = sums

    def corroborate(self, leaning: Sequence[bool]) -> None:
        """
        Note on which sides a window's estimate lies beyond the dead zone, for the next window.

        Also for a window that is not added (its model check failed): such a window straddles
        a parameter step (or the model misses dynamics), so its estimate must not feed the
        sums, but whether it lies beyond the dead zone tells whether the next window's excess
        persists, as :meth:`add` asks of the previous window.
        """
        self.added = [bool(side) for side in leaning]

    @property
    def raised(self) -> bool:
        return any(self.alarmed)

    @property
    def raised_since(self) -> Optional[int]:
        times = [since for since, raised in zip(self.since, self.alarmed)
                 if raised and since is not None]
        return min(times) if times else None


class ChangeDetector:
    """
    The sequential change test on the estimates of successive windows (see the module).

    Parameters
    ----------
    settings : AlarmSettings
        Names, window, update period, false-alarm rate, practical thresholds.
    baseline : Baseline, optional
        What to compare with; without one only the model check runs (and windows are kept
        for :meth:`capture`).

    """

    def __init__(self, settings: AlarmSettings, baseline: Optional[Baseline] = None):
        self._settings = settings
        self._baseline: Optional[Baseline] = None
        self._watched: Tuple[int, ...] = ()
        self._threshold = math.nan
        # (end_ns, values, covariance) of the latest usable windows: for a capture and for the
        # robust scale's non-overlapping partner.
        self._recent: Deque[Tuple[int, np.ndarray, np.ndarray]] = deque(
            maxlen=_history_length(settings))
        self._differences: List[Deque[float]] = []
        self._sums: List[_Sums] = []
        self._status = AlarmStatus(OK)
        self._failures = 0
        self._failing_since: Optional[int] = None
        self._last_end: Optional[int] = None
        self._last_changes: Tuple[ParameterChange, ...] = ()
        self.set_baseline(baseline)

    @classmethod
    def from_config(cls, config: IdentificationConfig, baseline: Optional[Baseline] = None
                    ) -> 'ChangeDetector':
        """Return a detector for ``config`` (see :func:`configured_baseline` for a baseline)."""
        return cls(AlarmSettings.from_config(config), baseline)

    @property
    def settings(self) -> AlarmSettings:
        """Return the settings in use."""
        return self._settings

    @property
    def baseline(self) -> Optional[Baseline]:
        """Return the baseline in use, if any."""
        return self._baseline

    @property
    def status(self) -> AlarmStatus:
        """Return the status after the last window."""
        return self._status

    @property
    def threshold(self) -> float:
        """Return the alarm threshold ``h`` of the scaled sums (NaN without a baseline)."""
        return self._threshold

    @property
    def failures_to_warn(self) -> int:
        """Return how many failing windows in a row make the status WARN."""
        settings = self._settings
        return int(math.ceil(settings.window / settings.update_period)) + MODEL_FAILURES

    @property
    def windows(self) -> int:
        """Return how many usable windows a capture could average now."""
        return len(self._recent)

    def recent_ends(self) -> List[int]:
        """Return the ends (ns) of the usable windows kept for a capture, oldest first."""
        return [item[0] for item in self._recent]

    def set_baseline(self, baseline: Optional[Baseline]) -> None:
        """Compare with ``baseline`` from now on (None: none); the sums start afresh."""
        names = self._settings.names
        if baseline is not None:
            unknown = [name for name in baseline.names if name not in names]
            if unknown:
                raise DataError(f'the baseline has parameters the model has not: '
                                f'{", ".join(unknown)} (model: {", ".join(names)})')
        self._baseline = baseline
        self._watched = () if baseline is None else tuple(
            names.index(name) for name in baseline.names)
        self._threshold = self._settings.threshold(2 * len(self._watched)) \
            if self._watched else math.nan
        self._sums = [_Sums() for _ in self._watched]
        self._last_changes = ()
        self._status = self._idle(self._status)

    def reconfigure(self, settings: AlarmSettings, baseline: Optional[Baseline] = None) -> None:
        """
        Switch settings; the sums start afresh (their threshold may have changed).

        With the same parameter names the windows, the robust scale and the baseline are kept
        (``baseline`` replaces it if given); with other names (a new model) everything is
        forgotten and ``baseline`` is used.
        """
        same_names = settings.names == self._settings.names
        kept = self._baseline if same_names and baseline is None else baseline
        self._settings = settings
        recent = self._recent if same_names else ()
        self._recent = deque(recent, maxlen=_history_length(settings))
        if not same_names:
            self._forget()
        self.set_baseline(kept)

    def reset(self) -> None:
        """Forget the sums, the windows and the robust scale; keep the baseline."""
        self._recent.clear()
        self._forget()
        self.set_baseline(self._baseline)

    def _forget(self) -> None:
        self._differences = []
        self._failures, self._failing_since, self._last_end = 0, None, None
        self._last_changes: Tuple[ParameterChange, ...] = ()
        self._status = AlarmStatus(OK)

    def capture(self, source: str = '') -> Baseline:
        """
        Average the last ``baseline_windows`` usable windows into the new baseline, and use it.

        Every parameter is covered; the covariance is that of the average of overlapping
        windows (:func:`~ctid_ros.streaming.baseline.average_windows`) scaled by the robust
        scale. Windows whose model failed the check are not used.

        Raises
        ------
        DataError
            If fewer usable windows than ``baseline_windows`` came since the start or the last
            reset (the message says how long to wait).

        """
        settings = self._settings
        count = settings.baseline_windows
        if len(self._recent) < count:
            wait = (count - len(self._recent)) * settings.update_period
            raise DataError(f'only {len(self._recent)} usable window(s) so far and '
                            f'baseline_windows is {count}: try again in about {wait:g} s')
        chosen = list(self._recent)[-count:]
        scale = self._scales(range(len(settings.names)))
        baseline = average_windows(
            settings.names, [item[0] for item in chosen], np.array([item[1] for item in chosen]),
            np.array([item[2] * np.outer(scale, scale) for item in chosen]), settings.window,
            source or f'captured from {count} windows')
        self.set_baseline(baseline)
        return baseline

    def spread(self) -> float:
        """
        Return how far the windows a capture would average scatter, against their covariance.

        The largest over the parameters of the windows' variance about their mean divided by
        what overlapping windows of the reported covariance give: about 1 for a stationary
        plant, large when the windows straddle a change. NaN with fewer than two windows.
        """
        chosen = list(self._recent)[-self._settings.baseline_windows:]
        count = len(chosen)
        if count < 2:
            return math.nan
        values = np.array([item[1] for item in chosen])
        root = np.sqrt(np.array([np.diag(item[2]) for item in chosen]))
        correlation = np.array([[overlap((a[0] - b[0]) / NANOSECONDS, self._settings.window)
                                 for b in chosen] for a in chosen])
        # E sum_i (x_i - mean)^2 = sum_i var_i - (1/n) sum_ij rho_ij sigma_i sigma_j
        expected = np.sum(root ** 2, axis=0) - np.einsum(
            'ij,ip,jp->p', correlation, root, root) / count
        observed = np.sum((values - values.mean(axis=0)) ** 2, axis=0)
        return float(np.max(observed / np.where(expected > 0.0, expected, np.inf)))

    def update(self, update: Update, check: Optional[Tuple[bool, str]] = None) -> AlarmStatus:
        """
        Take one window; return the alarm status after it.

        ``check``: the result of :func:`model_check` on this window when it was done before
        (a benchmark that keeps hours of windows without their samples); else it is done here.
        """
        settings = self._settings
        if tuple(update.names) != settings.names:
            raise DataError(f'an update of {", ".join(update.names)} for a detector of '
                            f'{", ".join(settings.names)}')
        model_ok, verdict = check if check is not None else \
            model_check(update, settings.window, settings.transient)
        values = np.asarray(update.values, dtype=float)
        covariance = noise_only(update, np.diag(np.asarray(update.stds, dtype=float) ** 2)
                                if update.covariance is None else
                                np.asarray(update.covariance, dtype=float))
        usable = bool(update.result.converged) and bool(np.all(np.isfinite(values)))
        if not model_ok:
            if self._failures == 0:
                self._failing_since = self._last_end
            self._failures += 1
        else:
            self._failures, self._failing_since = 0, None
        changes: Tuple[ParameterChange, ...] = ()
        distance = math.nan
        if usable and model_ok:
            self._learn_scale(update.end_ns, values, np.diag(covariance))
            if self._baseline is not None:
                changes, distance = self._test(update, values, covariance)
            self._recent.append((update.end_ns, values, covariance))
            self._last_end = update.end_ns
        elif usable and self._baseline is not None:
            scale = self._scales(self._watched)
            for position, index in enumerate(self._watched):
                excess = self._excess(position, index, values, covariance, scale[position])[0]
                if excess is not None:
                    self._sums[position].corroborate(excess > 0.0)
        self._status = self._compose(update.end_ns, changes, model_ok, verdict, distance, usable)
        return self._status

    # Internals ------------------------------------------------------------------------------

    def _scales(self, indices: Sequence[int]) -> np.ndarray:
        return np.array([robust_scale(self._differences[index])
                         if index < len(self._differences) else 1.0 for index in indices])

    def _learn_scale(self, end_ns: int, values: np.ndarray, variances: np.ndarray) -> None:
        """Add the standardised difference from the latest window this one does not overlap."""
        if not self._differences:
            self._differences = [deque(maxlen=SCALE_HISTORY) for _ in values]
        limit = end_ns - self._settings.window * NANOSECONDS * (1.0 - 1e-9)
        partner = next((item for item in reversed(self._recent) if item[0] <= limit), None)
        if partner is None:
            return
        total = variances + np.diag(partner[2])
        valid = np.isfinite(total) & (total > 0.0)
        differences = (values - partner[1]) / np.sqrt(np.where(valid, total, 1.0))
        for history, difference, ok in zip(self._differences, differences, valid):
            if ok and math.isfinite(difference):
                history.append(float(difference))

    def _test(self, update: Update, values: np.ndarray, covariance: np.ndarray
              ) -> Tuple[Tuple[ParameterChange, ...], float]:
        baseline, settings, threshold = self._baseline, self._settings, self._threshold
        watched = list(self._watched)
        scale = self._scales(watched)
        spread = math.sqrt(long_run_variance(settings.window, settings.update_period))
        previous = self._last_end if self._last_end is not None else update.start_ns
        changes = []
        for position, index in enumerate(watched):
            excess, sigma = self._excess(position, index, values, covariance, scale[position])
            reference = float(baseline.values[position])
            sigma0 = float(baseline.stds[position])
            sums = self._sums[position]
            if excess is not None:
                sums.add((excess - REFERENCE) / spread, threshold, previous, excess > 0.0)
            changes.append(ParameterChange(
                settings.names[index], reference, float(values[index]),
                float(values[index]) - reference, math.hypot(sigma, sigma0),
                settings.relative_changes[index] * abs(reference),
                max(sums.up, sums.down) / threshold, float(scale[position]), sums.raised,
                sums.raised_since))
        difference = values[watched] - baseline.values
        total = (covariance[np.ix_(watched, watched)] * np.outer(scale, scale)
                 + baseline.covariance)
        try:
            distance = math.sqrt(max(float(difference @ np.linalg.pinv(total) @ difference), 0.0))
        except (np.linalg.LinAlgError, ValueError):
            distance = math.nan
        return tuple(changes), distance

    def _excess(self, position: int, index: int, values: np.ndarray, covariance: np.ndarray,
                scale: float) -> Tuple[Optional[np.ndarray], float]:
        """
        Return a watched parameter's excess (up, down) in scaled stds, and the scaled std.

        The excess is the change beyond the dead zone and the baseline's bound, (17.1) of
        docs/algorithm.md, with the window's std times the robust ``scale``; None where the
        window gives no finite, positive std.
        """
        settings, baseline = self._settings, self._baseline
        reference = float(baseline.values[position])
        sigma = float(scale) * math.sqrt(max(covariance[index, index], 0.0))
        if not (math.isfinite(sigma) and sigma > 0.0):
            return None, sigma
        margin = (settings.relative_changes[index] * abs(reference)
                  + BASELINE_QUANTILE * float(baseline.stds[position]))
        change = float(values[index]) - reference
        return np.array([change - margin, -change - margin]) / sigma, sigma

    def _idle(self, previous: AlarmStatus) -> AlarmStatus:
        """Return the status right after the baseline changed (no window tested yet)."""
        if self._baseline is None:
            summary = 'no baseline: set baseline.<name> or call ~/capture_baseline'
        else:
            summary = f'baseline set ({self._baseline.source}): no window tested yet'
        return AlarmStatus(OK, time_ns=previous.time_ns, summary=summary,
                           threshold=self._threshold, baseline=self._baseline_text())

    def _baseline_text(self) -> str:
        return '' if self._baseline is None else self._baseline.source

    def _compose(self, end_ns: int, changes: Tuple[ParameterChange, ...], model_ok: bool,
                 verdict: str, distance: float, usable: bool) -> AlarmStatus:
        if changes:
            self._last_changes = changes
        shown = {change.name: change for change in self._last_changes}
        names = self._settings.names
        raised = [names[index] for index, sums in zip(self._watched, self._sums) if sums.raised]
        starts = [sums.raised_since for sums in self._sums
                  if sums.raised and sums.raised_since is not None]
        parts, level, since = [], OK, None
        if raised:
            level, since = ERROR, (min(starts) if starts else None)
            parts.append('changed: ' + ', '.join(shown[name].describe() for name in raised
                                                 if name in shown))
        if self._failures >= self.failures_to_warn:
            level = max(level, WARN)
            parts.append(f'model no longer explains the data ({self._failures} windows in a '
                         f'row): {verdict}')
            since = self._failing_since if since is None else since
        elif not model_ok:
            parts.append(f'window not used: {verdict}')
        elif not usable:
            parts.append('window not used: the estimate is not finite or did not converge')
        elif not raised and self._baseline is None:
            parts.append('no baseline: set baseline.<name> or call ~/capture_baseline')
        elif not raised:
            parts.append('no change beyond the thresholds: ' + ', '.join(
                change.describe() for change in changes))
        return AlarmStatus(level, tuple(raised), since, end_ns, '; '.join(parts), changes,
                           bool(changes), model_ok, verdict, self._threshold, distance,
                           self._baseline_text())


def _history_length(settings: AlarmSettings) -> int:
    """Return how many recent windows a detector keeps: a capture's and a partner's worth."""
    return max(settings.baseline_windows,
               int(math.ceil(settings.window / settings.update_period)) + 2)
