"""
The change alarm of issue 17 on the demo's wheel drive: false alarms, delays, ramp, resonance.

Every scenario simulates the plant of ``make demo`` (``config/wheel_demo_plant.yaml``: the
wheel drive ``exp(-tau*s)/(J*s + b)``, J = 0.05, b = 0.2, tau = 37.3 ms, under its digital PI
at 100 Hz, PRBS speed reference, measurement noise 0.05 rad/s) exactly, sample by sample, and
feeds the samples to the node's own buffer, session and change detector with the node's
configuration ``config/wheel_demo.yaml`` (window 4 s every 2 s, baseline J 0.05, b 0.2,
tau 0.0373 from the data sheet, min_relative_change 0.02, false_alarm_per_hour 0.1) exactly as
``ctid_node`` runs them, but without DDS, so hours of plant time take minutes. Each run starts
at its own point of the PRBS and its own noise.

* **stationary**: ``--hours`` of the unchanged plant (10 in the full run), with detectors on
  the same windows (:func:`stationary`): the demo's (data-sheet baseline, 2 % dead zone); the
  purely statistical test (a baseline captured from 5 windows, no dead zone) at the default
  0.1 false alarms per hour; and, for the calibration of the threshold on the real estimator,
  the same against the run's own mean at 10 and 30 false alarms per hour.
  Also: the windows' standardised errors (their spread and lag-1 autocorrelation, against 1
  and 0.5 for calibrated covariances of half-overlapping windows), the robust scale, and
  windows whose model failed the residual check.
* **step**: J (and b, tau) up 10 % at a random instant after 120 s, ``--runs`` runs each; the
  delay from the step to the alarm in update periods (acceptance: within 3 in >= 95 %).
* **ramp**: J up 10 % linearly over 10 minutes after 120 s; the value of the ramp when the
  alarm comes (acceptance: before 10 %).
* **resonance**: after 120 s the drive gains a lightly damped mode at 60 rad/s (a
  ``(s^2 + 2 zeta_z w s + w^2)/(s^2 + 2 zeta_p w s + w^2)`` factor whose zeros stop cancelling
  its poles: a 14 dB peak); the parameters of the unchanged model move by more than their
  thresholds, and the acceptance is a model warning, not a parameter alarm.
* **coloured**: the unchanged drive with ARMA measurement noise (outside the loop) for at most
  an hour: windows failing the model check and model warnings per hour with the colour-aware
  check and with the fixed ``4/sqrt(N)`` bound on the same windows, then ``--runs``/3 steps of
  the gain ``1/b`` by +8 % and their delays with each check (acceptance: <= 1 WARN per hour,
  raised within 6 periods).
* ``--calibrate``: the Monte Carlo behind the overshoot table of
  :mod:`ctid_ros.streaming.alarm` (CUSUM on Gaussian estimates with the autocorrelation of
  overlapping windows).

``python -m bench.alarm`` is the full run of the README (10 h, 100 runs per step, 10 ramps, 10
resonances: about 15 minutes on the 2-core machine); ``--quick`` (1 h, 30 runs, 3, 3) takes
about 2 minutes. Results go to ``--json``.
"""

import argparse
from dataclasses import dataclass, replace
import json
import math
import time
from types import SimpleNamespace
from typing import Callable, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

from ctid_ros.core.plant import excitation, PlantSimulator
from ctid_ros.errors import CtidError
from ctid_ros.streaming.alarm import (AlarmSettings, brownian_barrier, ChangeDetector,
                                      long_run_variance, model_check)
from ctid_ros.streaming.baseline import Baseline
from ctid_ros.streaming.buffer import SampleBuffer
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import ERROR, NANOSECONDS, WARN
from ctid_ros.streaming.params_file import find_config, load_params_file
from ctid_ros.streaming.session import IdentificationSession, Update
import numpy as np
from scipy import signal
import yaml

__all__ = ['ArmaNoise', 'Plant', 'StepResult', 'coloured_noise', 'main', 'plant', 'run_windows',
           'step_delays']

T0_NS = 1_700_000_000 * NANOSECONDS
# The new mode of the resonance scenario: w = 60 rad/s, poles damped 0.05; zeros damped like
# the poles before (cancelling: no resonance) and 0.25 after (a 14 dB peak).
RESONANCE_MODEL = ('exp(-tau*s)/(J*s + b)*(s**2 + 2*zeta_z*60*s + 3600)/'
                   '(s**2 + 2*0.05*60*s + 3600)')
RESONANCE = {'zeta_z': (0.05, 0.25)}
# Seconds of plant time before anything changes: the first windows, a captured baseline, and
# the robust scale's first differences (it is used from 30 on).
SETTLE = 120.0
# Retune a drifting plant this often (s).
RETUNE = 0.1


@dataclass(frozen=True)
class Plant:
    """
    The demo's plant as its params file states it.

    Attributes
    ----------
    model : str
        Transfer function.
    params : dict
        True parameter values.
    sample_time : float
        Controller period (s).
    pi_gains : (float, float)
        Digital PI gains.
    noise_std : float
        Measurement noise.
    prbs : (int, int, float, float)
        Bits, clock, amplitude, offset of the reference.

    """

    model: str
    params: Dict[str, float]
    sample_time: float
    pi_gains: Tuple[float, float]
    noise_std: float
    prbs: Tuple[int, int, float, float]


def plant() -> Plant:
    """Return the plant of ``config/wheel_demo_plant.yaml``."""
    values = yaml.safe_load(find_config('wheel_demo_plant').read_text(encoding='utf-8'))[
        'ctid_plant']['ros__parameters']
    return Plant(values['model'], dict(zip(values['parameter_names'],
                                           values['parameter_values'])),
                 float(values['sample_time']), tuple(values['pi_gains']),
                 float(values['noise_std']),
                 (values['prbs_bits'], values['prbs_clock'], values['amplitude'],
                  values['offset']))


def node_config() -> IdentificationConfig:
    """Return the node configuration of the demo (``config/wheel_demo.yaml``)."""
    return load_params_file(find_config('wheel_demo'))


ParamsAt = Callable[[float], Mapping[str, float]]
# Colour of the coloured-noise scenario: (1 + 0.5 q^-1) / (1 - 0.9 q^-1), unit variance.
ARMA_NOISE = ((1.0, 0.5), (1.0, -0.9))
# The gain step of the coloured-noise scenario: the drive's gain 1/b up 8 %.
GAIN_STEP = 0.08


class ArmaNoise:
    """Endless ARMA noise :data:`ARMA_NOISE` of standard deviation ``std``, drawn in pieces."""

    def __init__(self, std: float, seed: int):
        numerator, denominator = (np.array(part) for part in ARMA_NOISE)
        # Power gain of the filter for unit white noise: sum of its impulse response squared.
        impulse = signal.lfilter(numerator, denominator, np.eye(1, 2000)[0])
        self._scale = std / math.sqrt(float(impulse @ impulse))
        self._filter = (numerator, denominator)
        self._rng = np.random.default_rng(seed)
        self._state = signal.lfilter_zi(numerator, denominator) * 0.0
        self.draw(2000)                  # start stationary

    def draw(self, count: int) -> np.ndarray:
        """Return the next ``count`` samples."""
        values, self._state = signal.lfilter(*self._filter, self._rng.standard_normal(count),
                                             zi=self._state)
        return self._scale * values


def run_windows(config: IdentificationConfig, seconds: float, seed: int,
                params_at: Optional[ParamsAt] = None, source: Optional[Plant] = None,
                model: Optional[str] = None, extra: Optional[Mapping[str, float]] = None,
                coloured: bool = False) -> Iterator[Tuple[float, Optional[Update]]]:
    """
    Yield ``(time s, update or None)`` every ``update_period`` of simulated plant time.

    The plant (``source``, default :func:`plant`; ``model`` overrides its transfer function,
    ``extra`` adds parameters) is stepped sample by sample with its PI loop; its samples go into
    the node's :class:`SampleBuffer` stamped at their instants, and each tick estimates on
    ``session.take_window`` as the node does (None where the window gave no estimate).
    ``params_at(t)`` gives the parameters from time ``t`` on (checked every :data:`RETUNE`).
    ``coloured``: the measurement noise (same variance) is ARMA (:data:`ARMA_NOISE`) and is
    added to the measured output outside the loop instead of white noise inside it.
    """
    source = source or plant()
    params = {**source.params, **(extra or {})}
    simulator = PlantSimulator(model or source.model, params, source.sample_time,
                               pi_gains=source.pi_gains,
                               noise_std=0.0 if coloured else source.noise_std, seed=seed)
    colour = ArmaNoise(source.noise_std, seed + 104729) if coloured else None
    bits, clock, amplitude, offset = source.prbs
    reference = excitation(bits, clock, amplitude, offset)
    # Each run at its own point of the PRBS.
    for _ in range(int(np.random.default_rng(seed + 7919).integers(0, (2 ** bits - 1) * clock))):
        next(reference)
    buffer = SampleBuffer(config.buffer_capacity(1.0 / source.sample_time),
                          max_gap=config.max_gap, reorder_horizon=config.reorder_horizon)
    session = IdentificationSession(config)
    step_ns = round(source.sample_time * NANOSECONDS)
    per_tick = round(config.update_period / source.sample_time)
    per_retune = max(1, round(RETUNE / source.sample_time))
    current = dict(params)
    done = 0
    total = round(seconds / source.sample_time)
    while done < total:
        u = np.empty(per_tick)
        y = np.empty(per_tick)
        for k in range(per_tick):
            sample = done + k
            if params_at is not None and sample % per_retune == 0:
                wanted = {**current, **params_at(sample * source.sample_time)}
                if wanted != current:
                    simulator.retune(wanted)
                    current = wanted
            u[k], y[k] = simulator.step(next(reference))
        if colour is not None:
            y = y + colour.draw(per_tick)
        stamps = T0_NS + (done + np.arange(per_tick)) * step_ns
        buffer.add_inputs(stamps, u)
        buffer.add_outputs(stamps, y)
        done += per_tick
        try:
            update = session.update(session.take_window(buffer))
        except CtidError:
            update = None
        yield done * source.sample_time, update


def detector(config: IdentificationConfig, baseline: Optional[Baseline] = None,
             **changes: float) -> ChangeDetector:
    """Return the node's detector for ``config`` with ``changes`` (e.g. a rate)."""
    settings = AlarmSettings.from_config(config)
    if 'min_relative_change' in changes:
        settings = replace(settings, relative_changes=(changes['min_relative_change'],)
                           * len(settings.names))
    if 'false_alarm_per_hour' in changes:
        settings = replace(settings, false_alarm_per_hour=changes['false_alarm_per_hour'])
    if baseline is None:
        baseline = Baseline.from_config(config)
    return ChangeDetector(settings, baseline)


def _raised(levels: Sequence[int], level: int = ERROR) -> int:
    """Count the windows at which ``level`` was entered."""
    count, previous = 0, 0
    for current in levels:
        count += current >= level and previous < level
        previous = current
    return count


def _light(update: Update, config: IdentificationConfig) -> SimpleNamespace:
    """Return what a detector reads of an update, the model check done, without the data."""
    result = update.result
    return SimpleNamespace(
        names=update.names, values=update.values, stds=update.stds,
        covariance=update.covariance, end_ns=update.end_ns, start_ns=update.start_ns,
        result=SimpleNamespace(converged=result.converged, std=result.std,
                               std_noise=result.std_noise, std_change=result.std_change,
                               consistency=result.consistency),
        check=model_check(update, config.window, config.transient))


def _count(watch: ChangeDetector, windows: Sequence[SimpleNamespace]) -> Tuple[int, int]:
    """Feed ``windows``; return the alarms (ERROR) and model warnings (WARN) raised."""
    levels = [watch.update(window, check=window.check).level for window in windows]
    return _raised(levels), _raised([WARN if level == WARN else 0 for level in levels], WARN)


def stationary(config: IdentificationConfig, hours: float, seed: int) -> Dict[str, object]:
    """
    Run the unchanged plant for ``hours``; count the alarms of several detectors on its windows.

    * demo: the demo's configuration (data-sheet baseline, 2 % dead zone), all windows;
    * statistical: no dead zone, a baseline captured from 5 windows at :data:`SETTLE`, at the
      configured rate, on the windows after it;
    * calibration: no dead zone, the run's own mean as an exact baseline, at 10 and 30 false
      alarms per hour, on the windows after SETTLE: their counts against the allowed measure
      the threshold (with the robust scale and the overlap) on the real estimator.
    """
    started = time.perf_counter()
    windows = []
    unused = 0
    for time_s, update in run_windows(config, hours * 3600.0, seed):
        if update is None:
            unused += 1
        else:
            windows.append((time_s, _light(update, config)))
    simulated = time.perf_counter() - started
    times = np.array([time_s for time_s, _ in windows])
    light = [window for _, window in windows]
    settle = int(np.searchsorted(times, SETTLE))
    results: Dict[str, object] = {'hours': hours, 'windows': len(light),
                                  'windows_without_estimate': unused}
    alarms, warnings = _count(detector(config), light)
    results['demo'] = {'hours': hours, 'alarms': alarms,
                       'allowed': config.false_alarm_per_hour * hours,
                       'model_warnings': warnings}
    capturer = ChangeDetector(AlarmSettings.from_config(config))
    _count(capturer, light[:settle])
    statistical = detector(config, capturer.capture(), min_relative_change=0.0)
    monitored = (len(light) - settle) * config.update_period / 3600.0
    alarms, _ = _count(statistical, light[settle:])
    results['statistical'] = {'hours': monitored, 'alarms': alarms,
                              'allowed': config.false_alarm_per_hour * monitored,
                              'baseline_std_over_window_std': (
                                  statistical.baseline.stds / light[settle].stds).round(2)
                              .tolist()}
    # The plant's own long-run mean as an exact baseline: the estimator's small closed-loop bias
    # (about -0.3 std of b) does not count, nor does a baseline's uncertainty.
    mean = Baseline(config.names, np.mean([window.values for window in light[settle:]], axis=0),
                    np.zeros((len(config.names),) * 2), 'long-run mean')
    for rate in (10.0, 30.0):
        watch = detector(config, mean, min_relative_change=0.0, false_alarm_per_hour=rate)
        alarms, _ = _count(watch, light[settle:])
        results[f'calibration_{rate:g}_per_hour'] = {
            'hours': monitored, 'alarms': alarms, 'allowed': rate * monitored,
            'robust_scale': [round(change.scale, 3) for change in watch.status.changes]}
    truth = np.array([plant().params[name] for name in config.names])
    late = [window for time_s, window in windows if time_s > 10.0]
    errors = np.array([(window.values - truth) / window.stds for window in late])
    centred = errors - errors.mean(axis=0)
    lag1 = np.mean(centred[1:] * centred[:-1], axis=0) / np.var(errors, axis=0)
    failed = sum(not window.check[0] for window in light)
    results.update({
        'model_check_failed_windows': failed,
        'error_std': dict(zip(config.names, np.std(errors, axis=0).round(3).tolist())),
        'error_mean': dict(zip(config.names, np.mean(errors, axis=0).round(3).tolist())),
        'error_lag1_autocorrelation': dict(zip(config.names, lag1.round(3).tolist())),
        'simulation_seconds': simulated, 'seconds': time.perf_counter() - started})
    return results


@dataclass(frozen=True)
class StepResult:
    """
    One run with a change: when it began and when the alarm came.

    Attributes
    ----------
    change_s : float
        Time of the step (or start of the ramp), s.
    alarm_s : float or None
        End of the window at which the alarm was raised for the changed parameter.
    value : float or None
        The relative change of the truth at the alarm (ramp).
    other_alarms : int
        Alarms raised before the change or for another parameter.
    since_s : float or None
        The alarm's estimate of when the change began.

    """

    change_s: float
    alarm_s: Optional[float]
    value: Optional[float]
    other_alarms: int
    since_s: Optional[float]


def changed_run(config: IdentificationConfig, name: str, seed: int, size: float,
                ramp_s: float = 0.0, after_s: float = 30.0, coloured: bool = False,
                fixed_bound: bool = False) -> StepResult:
    """
    Run one step (``ramp_s`` 0) or ramp of ``size`` in ``name``; return when it alarmed.

    ``coloured``: ARMA measurement noise (:func:`run_windows`); ``fixed_bound``: the windows'
    model check with the white-series bound ``4/sqrt(N)`` instead of the colour-aware one.
    """
    rng = np.random.default_rng(seed)
    change = SETTLE + float(rng.uniform(0.0, config.update_period))
    base = plant().params[name]

    def fraction(t: float) -> float:
        if t < change:
            return 0.0
        return 1.0 if ramp_s <= 0.0 else min((t - change) / ramp_s, 1.0)

    watch = detector(config)
    alarm = since = value = None
    others = 0
    for time_s, update in run_windows(config, change + ramp_s + after_s, seed,
                                      lambda t: {name: base * (1.0 + size * fraction(t))},
                                      coloured=coloured):
        if update is None:
            continue
        status = watch.update(update, check=model_check(
            update, config.window, config.transient, coloured=not fixed_bound))
        if status.level == ERROR and name in status.parameters and alarm is None \
                and time_s >= change:
            alarm, value = time_s, size * fraction(time_s)
            since = None if status.since_ns is None else (status.since_ns - T0_NS) / NANOSECONDS
            if ramp_s <= 0.0:
                break
        elif status.level == ERROR and alarm is None:
            others += 1
        if alarm is not None and ramp_s > 0.0:
            break
    return StepResult(change, alarm, value, others, since)


def step_delays(results: Sequence[StepResult], period: float) -> np.ndarray:
    """Return the delays from change to alarm in update periods (inf where none came)."""
    return np.array([math.inf if result.alarm_s is None else
                     (result.alarm_s - result.change_s) / period for result in results])


def steps(config: IdentificationConfig, runs: int, names: Sequence[str], size: float = 0.10
          ) -> Dict[str, object]:
    """Run ``runs`` steps of ``size`` per parameter; summarise the delays."""
    summary: Dict[str, object] = {}
    for offset, name in enumerate(names):
        started = time.perf_counter()
        results = [changed_run(config, name, 1000 * (offset + 1) + run, size)
                   for run in range(runs)]
        delays = step_delays(results, config.update_period)
        found = delays[np.isfinite(delays)]
        since_error = [result.since_s - result.change_s for result in results
                       if result.since_s is not None]
        summary[name] = {
            'runs': runs, 'detected': int(found.size),
            'within_3_periods': float(np.mean(delays <= 3.0)),
            'delay_periods': {'min': float(found.min()), 'median': float(np.median(found)),
                              'p95': float(np.percentile(found, 95)),
                              'max': float(found.max())} if found.size else {},
            'histogram_periods': np.histogram(found, bins=np.arange(0.0, 5.5, 0.5))[0].tolist(),
            'since_error_s': {'median': float(np.median(since_error)),
                              'min': float(np.min(since_error)),
                              'max': float(np.max(since_error))} if since_error else {},
            'false_alarms_before': int(sum(result.other_alarms for result in results)),
            'seconds': time.perf_counter() - started}
    return summary


def coloured_noise(config: IdentificationConfig, hours: float, runs: int, seed: int = 23
                   ) -> Dict[str, object]:
    """
    Healthy drive with ARMA measurement noise: model checks, WARNs per hour, a gain step.

    The windows' model check with the colour-aware bound against the fixed ``4/sqrt(N)`` one on
    the same windows: how many windows fail it and how many model warnings (WARN) the demo's
    detector raises per hour; then ``runs`` steps of the drive's gain ``1/b`` by +8 %
    (:data:`GAIN_STEP`) and the delay to the alarm in update periods with each check
    (acceptance: <= 1 WARN per hour, the step raised within 6 periods).
    """
    started = time.perf_counter()
    windows = [update for _, update in run_windows(config, hours * 3600.0, seed, coloured=True)
               if update is not None]
    results: Dict[str, object] = {'hours': hours, 'windows': len(windows)}
    for label, fixed in (('colour_aware', False), ('fixed_bound', True)):
        checks = [model_check(update, config.window, config.transient, coloured=not fixed)
                  for update in windows]
        watch = detector(config)
        levels = [watch.update(update, check=check).level
                  for update, check in zip(windows, checks)]
        results[label] = {
            'model_check_failed_windows': int(sum(not ok for ok, _ in checks)),
            'failed_share': float(np.mean([not ok for ok, _ in checks])),
            'warn_per_hour': _raised([WARN if level == WARN else 0 for level in levels],
                                     WARN) / hours,
            'alarms': _raised(levels)}
    size = 1.0 / (1.0 + GAIN_STEP) - 1.0
    for label, fixed in (('colour_aware', False), ('fixed_bound', True)):
        outcome = [changed_run(config, 'b', 7000 + run, size, coloured=True, fixed_bound=fixed)
                   for run in range(runs)]
        delays = step_delays(outcome, config.update_period)
        found = delays[np.isfinite(delays)]
        results[label]['gain_step'] = {
            'runs': runs, 'detected': int(found.size),
            'within_6_periods': float(np.mean(delays <= 6.0)),
            'delay_periods': {'median': float(np.median(found)),
                              'max': float(found.max())} if found.size else {}}
    results['seconds'] = time.perf_counter() - started
    return results


def ramps(config: IdentificationConfig, runs: int, name: str = 'J', size: float = 0.10,
          minutes: float = 10.0) -> Dict[str, object]:
    """Ramp ``name`` by ``size`` over ``minutes``; report the ramp's value at the alarm."""
    started = time.perf_counter()
    results = [changed_run(config, name, 5000 + run, size, ramp_s=60.0 * minutes)
               for run in range(runs)]
    values = np.array([math.inf if result.value is None else 100.0 * result.value
                       for result in results])
    return {'parameter': name, 'runs': runs, 'size_percent': 100.0 * size, 'minutes': minutes,
            'detected_before_full': int(np.sum(values < 100.0 * size)),
            'detected_at_percent': {'min': float(values.min()),
                                    'median': float(np.median(values)),
                                    'max': float(values.max())},
            'detected_after_s': float(np.median([result.alarm_s - result.change_s
                                                 for result in results
                                                 if result.alarm_s is not None])),
            'false_alarms_before': int(sum(result.other_alarms for result in results)),
            'seconds': time.perf_counter() - started}


def resonances(config: IdentificationConfig, runs: int, after_s: float = 60.0
               ) -> Dict[str, object]:
    """Let a lightly damped mode appear after :data:`SETTLE`; count alarms and warnings."""
    started = time.perf_counter()
    before, after = RESONANCE['zeta_z']
    alarms = warned = failing = windows = 0
    first_warning = []
    moved = []
    truth = plant().params
    for run in range(runs):
        seed = 9000 + run
        watch = detector(config)
        first = None
        for time_s, update in run_windows(
                config, SETTLE + after_s, seed,
                lambda t: {'zeta_z': after if t >= SETTLE else before},
                model=RESONANCE_MODEL, extra={'zeta_z': before}):
            if update is None:
                continue
            status = watch.update(update)
            if time_s < SETTLE:
                continue
            windows += 1
            alarms += status.level == ERROR
            warned += status.level == WARN
            failing += not status.model_ok
            if status.level == WARN and first is None:
                first = (time_s - SETTLE) / config.update_period
            if time_s >= SETTLE + config.window + config.update_period:
                moved.append([100.0 * (value - truth[name]) / truth[name]
                              for name, value in zip(update.names, update.values)])
        first_warning.append(math.inf if first is None else first)
    moved = np.array(moved)
    return {'runs': runs, 'windows_after': windows, 'parameter_alarm_windows': alarms,
            'model_warning_windows': warned, 'model_check_failed_windows': failing,
            'first_warning_periods': {'median': float(np.median(first_warning)),
                                      'max': float(np.max(first_warning))},
            'parameters_moved_percent': dict(zip(config.names,
                                                 np.median(moved, axis=0).round(1).tolist())),
            'seconds': time.perf_counter() - started}


def calibrate(ratios: Sequence[float] = (1.0, 1.5, 2.0, 3.0, 4.0), target: float = 1000.0,
              paths: int = 3000, seed: int = 0) -> Dict[str, float]:
    """
    Fit the overshoot correction ``c`` for each window/period ratio by Monte Carlo.

    Gaussian estimates with the autocorrelation of overlapping windows (moving sums of white
    noise on a grid of ``q`` steps per update period), the scaled CUSUM with ``k = 1``; ``c``
    is found by bisection so that the measured run length equals ``target``.
    """
    results = {}
    for ratio in ratios:
        kappa = 1.0 / math.sqrt(long_run_variance(ratio, 1.0))
        barrier = brownian_barrier(kappa, target)
        low, high = 0.0, 8.0
        for iteration in range(10):
            guess = 0.5 * (low + high)
            measured = _run_length(ratio, barrier - guess, kappa, paths, int(8 * target),
                                   seed + iteration)
            low, high = (guess, high) if measured > target else (low, guess)
        results[str(ratio)] = round(0.5 * (low + high), 3)
    return results


def _run_length(ratio: float, threshold: float, kappa: float, paths: int, steps: int,
                seed: int, per_period: int = 12) -> float:
    rng = np.random.default_rng(seed)
    length = int(round(ratio * per_period))
    history = rng.standard_normal((length, paths))
    total = history.sum(axis=0)
    spread = 1.0 / kappa
    sums = np.zeros(paths)
    alarm = np.full(paths, np.nan)
    alive = np.ones(paths, dtype=bool)
    position = 0
    for step in range(steps):
        for _ in range(per_period):
            new = rng.standard_normal(paths)
            total += new - history[position]
            history[position] = new
            position = (position + 1) % length
        sums = np.maximum(0.0, sums + (total / math.sqrt(length) - 1.0) / spread)
        hit = alive & (sums >= threshold)
        alarm[hit] = step + 1
        alive &= ~hit
    done = ~np.isnan(alarm)
    return float(np.where(done, alarm, steps).sum() / max(done.sum(), 1))


def main(argv: Optional[List[str]] = None) -> Dict[str, object]:
    """Run the scenarios; print a summary and optionally write JSON."""
    parser = argparse.ArgumentParser(prog='python -m bench.alarm', description=__doc__.split(
        '\n\n')[0])
    parser.add_argument('--quick', action='store_true',
                        help='1 h stationary, 30 runs per step, 3 ramps, 3 resonances')
    parser.add_argument('--hours', type=float, default=None, help='stationary hours (10)')
    parser.add_argument('--runs', type=int, default=None, help='runs per step (100)')
    parser.add_argument('--ramps', type=int, default=None, help='ramp runs (10)')
    parser.add_argument('--resonances', type=int, default=None, help='resonance runs (10)')
    parser.add_argument('--only', nargs='*', default=None,
                        choices=('stationary', 'step', 'ramp', 'resonance', 'coloured'),
                        help='run only these scenarios')
    parser.add_argument('--calibrate', action='store_true',
                        help='only the Monte Carlo of the overshoot table')
    parser.add_argument('--json', default=None, help='write the results here')
    arguments = parser.parse_args(argv)
    if arguments.calibrate:
        results: Dict[str, object] = {'overshoot': calibrate()}
        print(json.dumps(results, indent=2))
        return results
    quick = arguments.quick
    hours = arguments.hours if arguments.hours is not None else (1.0 if quick else 10.0)
    runs = arguments.runs if arguments.runs is not None else (30 if quick else 100)
    ramp_runs = arguments.ramps if arguments.ramps is not None else (3 if quick else 10)
    resonance_runs = arguments.resonances if arguments.resonances is not None else (
        3 if quick else 10)
    only = set(arguments.only or ('stationary', 'step', 'ramp', 'resonance', 'coloured'))
    config = node_config()
    settings = AlarmSettings.from_config(config)
    results = {'mode': 'quick' if quick else 'full',
               'threshold': settings.threshold(2 * len(config.names)),
               'long_run_variance': long_run_variance(config.window, config.update_period)}
    print(f'change alarm on the demo wheel drive: window {config.window:g} s every '
          f'{config.update_period:g} s, {config.false_alarm_per_hour:g} false alarms per hour, '
          f'min_relative_change {config.min_relative_change:g}, threshold '
          f'{results["threshold"]:.3f}', flush=True)
    if 'stationary' in only:
        results['stationary'] = stationary(config, hours, seed=17)
        _show('stationary', results['stationary'])
    if 'step' in only:
        results['step'] = steps(config, runs, config.names)
        _show('10 % step', results['step'])
    if 'ramp' in only:
        results['ramp'] = ramps(config, ramp_runs)
        _show('10 % ramp over 10 min', results['ramp'])
    if 'resonance' in only:
        results['resonance'] = resonances(config, resonance_runs)
        _show('new resonance', results['resonance'])
    if 'coloured' in only:
        # An hour at most: the model checks of its windows are the figure, not rare alarms.
        results['coloured'] = coloured_noise(config, min(hours, 1.0), max(runs // 3, 5))
        _show('ARMA noise: model check and +8 % gain step', results['coloured'])
    if arguments.json:
        with open(arguments.json, 'w', encoding='utf-8') as stream:
            json.dump(results, stream, indent=2)
    return results


def _show(title: str, values: object) -> None:
    print(f'{title}: {json.dumps(values)}', flush=True)


if __name__ == '__main__':
    main()
