"""The change alarm: threshold from the false-alarm rate, overlap, robustness, model check."""

import math
from types import SimpleNamespace

from bench.alarm import node_config, plant, RESONANCE_MODEL, run_windows
from ctid_ros import Data, Model
from ctid_ros.errors import DataError
from ctid_ros.streaming.alarm import (AlarmSettings, brownian_arl, ChangeDetector,
                                      cusum_threshold, long_run_variance, model_check, noise_only,
                                      overshoot, REFERENCE)
from ctid_ros.streaming.baseline import Baseline
from ctid_ros.streaming.contract import ERROR, NANOSECONDS, OK, WARN
import numpy as np
import pytest

NAMES = ('J', 'b', 'tau')
TRUTH = np.array([0.05, 0.2, 0.0373])
STD = np.array([0.00016, 0.00025, 0.0002])
T0 = 1_700_000_000 * NANOSECONDS
PERIOD_NS = 2 * NANOSECONDS


def settings(**changes):
    values = {'names': NAMES, 'window': 4.0, 'update_period': 2.0, 'false_alarm_per_hour': 0.1,
              'relative_changes': (0.02,) * 3, 'baseline_windows': 5}
    values.update(changes)
    return AlarmSettings(**values)


def exact_baseline():
    return Baseline(NAMES, TRUTH, np.zeros((3, 3)), 'params file')


WHEEL = Model('exp(-tau*s)/(J*s + b)')
# A window the model explains exactly (a zero residual): the verdict alone decides.
EXPLAINED = SimpleNamespace(data=Data(np.random.default_rng(0).standard_normal(400),
                                      np.linspace(0.0, 1.0, 400), 0.01))


def update(index, values, stds=STD, model_ok=True, converged=True):
    """Return a window's estimate as the detector sees it (the estimator's verdict given)."""
    end = T0 + index * PERIOD_NS
    verdict = 'white' if model_ok else 'correlated with input u: missing dynamics'
    return SimpleNamespace(
        names=NAMES, values=np.asarray(values, dtype=float), stds=np.asarray(stds, dtype=float),
        covariance=np.diag(np.asarray(stds, dtype=float) ** 2), end_ns=end,
        start_ns=end - 4 * NANOSECONDS, window=EXPLAINED, prediction=EXPLAINED.data.y,
        result=SimpleNamespace(converged=converged, model=WHEEL, intersample='zoh',
                               params=dict(zip(NAMES, np.asarray(values, dtype=float))),
                               residuals=SimpleNamespace(input_correlated=not model_ok,
                                                         verdict=verdict)))


def overlapping_errors(count, seed, ratio=2):
    """Return standard errors of windows overlapping by (ratio - 1)/ratio (moving sums)."""
    white = np.random.default_rng(seed).standard_normal((count + ratio, 3))
    return np.array([white[i:i + ratio].sum(axis=0) for i in range(count)]) / math.sqrt(ratio)


def test_threshold_follows_the_rate_and_the_overlap():
    assert long_run_variance(4.0, 2.0) == pytest.approx(2.0)
    assert long_run_variance(4.0, 4.0) == long_run_variance(4.0, 8.0) == pytest.approx(1.0)
    assert long_run_variance(10.0, 4.0) == pytest.approx(1.0 + 2.0 * (0.6 + 0.2))
    assert overshoot(1.0, 1.0) == pytest.approx(1.13) and overshoot(0.5, 1.0) == 1.13
    assert overshoot(2.0, 1.0) < overshoot(3.0, 1.0) < overshoot(12.0, 1.0) < overshoot(20, 1)
    # Siegmund at k = 1, independent windows: ARL 1e4 -> b = 4.95 (tables give h = 3.8).
    assert brownian_arl(1.0, cusum_threshold(1e4, 1.0, 1.0) + overshoot(1.0, 1.0)) == \
        pytest.approx(1e4)
    assert cusum_threshold(1e4, 1.0, 1.0) == pytest.approx(3.82, abs=0.05)
    low, high = settings().threshold(6), settings(false_alarm_per_hour=0.01).threshold(6)
    assert high > low > settings(false_alarm_per_hour=10.0).threshold(6)
    assert settings(window=8.0).threshold(6) > low       # more overlap, a higher threshold


@pytest.mark.parametrize('ratio', [1, 2, 3])
def test_run_length_of_the_threshold_by_monte_carlo(ratio):
    # The scaled CUSUM on Gaussian estimates of windows overlapping as the node's do, at the
    # threshold for 300 windows between false alarms: the measured run length is at least
    # that (the table errs on the safe side) and not far above it.
    target, paths, steps = 300.0, 1500, 2400
    threshold = cusum_threshold(target, float(ratio), 1.0)
    spread = math.sqrt(long_run_variance(float(ratio), 1.0))
    rng = np.random.default_rng(ratio)
    history = rng.standard_normal((ratio, paths))
    sums, first = np.zeros(paths), np.full(paths, np.nan)
    for step in range(steps):
        history = np.vstack([history[1:], rng.standard_normal(paths)])
        z = history.sum(axis=0) / math.sqrt(ratio)
        sums = np.maximum(0.0, sums + (z - REFERENCE) / spread)
        first[np.isnan(first) & (sums >= threshold)] = step + 1
    done = ~np.isnan(first)
    measured = np.where(done, first, steps).sum() / done.sum()
    assert target * 0.95 < measured < target * 1.6


def test_stationary_windows_raise_no_alarm_and_a_step_raises_one_within_three():
    detector = ChangeDetector(settings(), exact_baseline())
    errors = overlapping_errors(3000, seed=1)
    levels = [detector.update(update(i, TRUTH + errors[i] * STD)).level for i in range(2000)]
    assert max(levels) == OK
    # J up 10 % between windows 1999 and 2000: window 2000 holds a quarter of new data,
    # 2001 three quarters, 2002 only new data.
    statuses = []
    for i in range(2000, 2010):
        fraction = min(max((i - 2000) / 2 + 0.25, 0.0), 1.0)
        shifted = TRUTH * np.array([1.0 + 0.1 * fraction, 1.0, 1.0])
        statuses.append(detector.update(update(i, shifted + errors[i] * STD)))
    first = next(index for index, status in enumerate(statuses) if status.level == ERROR)
    assert first <= 2
    alarm = statuses[first]
    assert alarm.parameters == ('J',)
    # The change began after the end of the last window before the evidence grew: 1999, or
    # 2000 when that window's quarter of new data stayed within the dead zone.
    assert alarm.since_ns in (T0 + 1999 * PERIOD_NS, T0 + 2000 * PERIOD_NS)
    since = (alarm.since_ns - T0) / NANOSECONDS
    change = alarm.changes[0]
    low, high = change.interval
    # The interval holds the change the raising window saw (a share of it while it straddles).
    held = 0.1 * 0.05 * min(0.25 + first / 2, 1.0)
    assert low < held < high
    assert alarm.to_dict() == {'level': 'ERROR', 'parameters': ['J'],
                               'since': alarm.since_ns / NANOSECONDS}
    assert alarm.text(T0).startswith('changed: J +') and alarm.text(T0).endswith(
        f'since t={since:.2f} s')
    diagnostics = alarm.diagnostics(T0)
    assert diagnostics['alarm'] == 'ERROR' and diagnostics['alarm_parameters'] == ['J']
    assert diagnostics['alarm_since'] == pytest.approx(since)
    values = alarm.values(T0)
    assert values['parameters'] == ['J'] and values['J.relative_change'] > 0.05
    assert values['model_explains_data'] and 0 < values['J.evidence']
    # It stays raised while the change lasts, and clears once J is back.
    assert all(status.level == ERROR for status in statuses[first:])
    back = [detector.update(update(i, TRUTH + errors[i] * STD)) for i in range(2010, 2020)]
    assert back[-1].level == OK and back[-1].parameters == ()


def test_false_alarm_rate_without_a_dead_zone_is_at_most_the_configured_one():
    # The purely statistical test (no practical threshold, exact baseline) at 30 false alarms
    # per hour: 20 hours of overlapping windows may raise at most 600, and a calibrated
    # threshold raises a good part of that (it is not just conservative).
    detector = ChangeDetector(settings(false_alarm_per_hour=30.0, relative_changes=(0.0,) * 3),
                              exact_baseline())
    errors = overlapping_errors(36000, seed=2)
    raised, previous = 0, OK
    for i in range(36000):
        level = detector.update(update(i, TRUTH + errors[i] * STD)).level
        raised += level == ERROR and previous != ERROR
        previous = level
    assert 250 < raised <= 600


def test_one_outlier_window_is_no_alarm_but_two_are():
    detector = ChangeDetector(settings(), exact_baseline())
    errors = overlapping_errors(200, seed=3)
    for i in range(100):
        detector.update(update(i, TRUTH + errors[i] * STD))
    outlier = TRUTH * np.array([1.5, 1.0, 1.0])
    assert detector.update(update(100, outlier)).level == OK
    assert detector.update(update(101, TRUTH + errors[101] * STD)).level == OK
    assert detector.update(update(102, outlier)).level == OK
    assert detector.update(update(103, outlier)).level == ERROR


def test_an_optimistic_covariance_is_corrected_by_the_robust_scale():
    # The estimates scatter three times more than their reported standard deviations say.
    errors = overlapping_errors(6000, seed=4)
    plain = settings(relative_changes=(0.0,) * 3, false_alarm_per_hour=1.0)
    detector = ChangeDetector(plain, exact_baseline())
    levels = [detector.update(update(i, TRUTH + 3.0 * errors[i] * STD)).level
              for i in range(6000)]
    scales = [change.scale for change in detector.status.changes]
    assert scales == pytest.approx([3.0] * 3, rel=0.2)
    # Before the scale is learnt (30 non-overlapping differences) the windows alarm; after,
    # 3.3 hours raise at most a few (1 per hour allowed).
    assert max(levels[:100]) == ERROR
    later = np.array(levels[200:])
    assert np.sum((later[1:] == ERROR) & (later[:-1] != ERROR)) <= 4


def test_the_change_test_takes_the_estimate_s_change_covariance():
    window = update(0, TRUTH)
    covariance = np.array(window.covariance)
    window.result.consistency, window.result.std = None, dict(zip(NAMES, STD))
    assert noise_only(window, covariance) == pytest.approx(covariance)
    # Without the t factors and the restored noise (Estimate.std_change), correlations kept.
    covariance[0, 1] = covariance[1, 0] = 0.5 * STD[0] * STD[1]
    window.result.std_change = dict(zip(NAMES, STD * np.array([0.9, 0.95, 1.0])))
    narrowed = noise_only(window, covariance)
    assert np.sqrt(np.diag(narrowed)) == pytest.approx(STD * np.array([0.9, 0.95, 1.0]))
    assert narrowed[0, 1] == pytest.approx(0.5 * 0.9 * 0.95 * STD[0] * STD[1])


def test_the_baseline_uncertainty_widens_the_dead_zone():
    # A captured baseline off by 2 of its standard deviations: no alarm without a practical
    # threshold, as the offset is within its 99 % bound.
    baseline = Baseline(NAMES, TRUTH + 2.0 * STD, np.diag(STD ** 2), 'captured')
    detector = ChangeDetector(settings(relative_changes=(0.0,) * 3), baseline)
    errors = overlapping_errors(3000, seed=5)
    levels = [detector.update(update(i, TRUTH + errors[i] * STD)).level for i in range(3000)]
    assert max(levels) == OK
    # Treated as exact, the same offset raises alarms.
    exact = Baseline(NAMES, TRUTH + 2.0 * STD, np.zeros((3, 3)), 'exact')
    detector = ChangeDetector(settings(relative_changes=(0.0,) * 3), exact)
    levels = [detector.update(update(i, TRUTH + errors[i] * STD)).level for i in range(3000)]
    assert max(levels) == ERROR


def test_a_model_that_fails_the_residual_check_warns_and_does_not_feed_the_sums():
    detector = ChangeDetector(settings(), exact_baseline())
    for i in range(10):
        detector.update(update(i, TRUTH))
    shifted = TRUTH * np.array([0.88, 1.0, 0.72])        # what a new resonance does to them
    # Two windows (4 s every 2 s) may straddle a step of a parameter and fail for that: the
    # third failure in a row is a warning.
    assert detector.failures_to_warn == 3
    for index in (10, 11):
        first = detector.update(update(index, shifted, model_ok=False))
        assert first.level == OK and not first.model_ok and not first.used
        assert first.summary.startswith('window not used: correlated with input')
    third = detector.update(update(12, shifted, model_ok=False))
    assert third.level == WARN and third.parameters == ()
    assert third.since_ns == T0 + 9 * PERIOD_NS
    assert 'model no longer explains the data (3 windows in a row)' in third.summary
    assert third.to_dict() == {'level': 'WARN', 'parameters': [],
                               'since': (T0 + 9 * PERIOD_NS) / NANOSECONDS}
    statuses = [detector.update(update(i, shifted, model_ok=False)) for i in range(13, 40)]
    assert {status.level for status in statuses} == {WARN}
    # The same shift with a model that explains the data is a parameter alarm.
    explained = ChangeDetector(settings(), exact_baseline())
    levels = [explained.update(update(i, shifted)).level for i in range(3)]
    assert levels[-1] == ERROR


def test_unconverged_windows_are_not_used():
    detector = ChangeDetector(settings(), exact_baseline())
    status = detector.update(update(0, TRUTH * 1.5, converged=False))
    assert status.level == OK and not status.used
    assert 'did not converge' in status.summary


def test_capture_averages_overlapping_windows_and_reset_keeps_it():
    detector = ChangeDetector(settings())
    assert detector.status.summary.startswith('no baseline')
    errors = overlapping_errors(10, seed=6)
    for i in range(3):
        assert detector.update(update(i, TRUTH + errors[i] * STD)).level == OK
    with pytest.raises(DataError, match='only 3 usable window.s. so far and baseline_windows '
                                        'is 5: try again in about 4 s'):
        detector.capture()
    for i in range(3, 6):
        detector.update(update(i, TRUTH + errors[i] * STD))
    baseline = detector.capture()
    assert detector.baseline is baseline and baseline.names == NAMES
    expected = np.mean([TRUTH + errors[i] * STD for i in range(1, 6)], axis=0)
    assert baseline.values == pytest.approx(expected)
    # Five windows half overlapping: variance (5 + 2 * 4 * 0.5)/25 = 9/25 of one window's.
    assert baseline.stds == pytest.approx(STD * 0.6)
    assert 0.0 < detector.spread() < 10.0
    detector.reset()
    assert detector.baseline is baseline and detector.windows == 0
    detector.reconfigure(settings(false_alarm_per_hour=1.0))
    assert detector.baseline is baseline
    detector.reconfigure(settings(names=('K', 'T', 'tau')))
    assert detector.baseline is None
    with pytest.raises(DataError, match='parameters the model has not: J, b'):
        detector.set_baseline(Baseline(('J', 'b'), TRUTH[:2], np.zeros((2, 2)), 'x'))


def test_a_new_resonance_is_a_model_warning_not_a_parameter_alarm():
    # The demo's wheel drive through the node's session: a lightly damped mode at 60 rad/s
    # appears after 30 s. The unchanged model's J and tau then move by more than 10 %, which
    # alone would be a parameter alarm; the residual check sees the missing dynamics.
    config = node_config()
    truth = plant().params
    detector = ChangeDetector.from_config(config, Baseline.from_config(config))
    statuses, moved = [], []
    for time_s, window in run_windows(config, 50.0, seed=21,
                                      params_at=lambda t: {'zeta_z': 0.25 if t >= 30 else 0.05},
                                      model=RESONANCE_MODEL, extra={'zeta_z': 0.05}):
        if window is None:
            continue
        statuses.append((time_s, detector.update(window)))
        if time_s >= 36.0:
            moved.append(abs(window.values[0] - truth['J']) / truth['J'])
    assert all(status.level == OK for time_s, status in statuses if time_s < 30.0)
    after = [status for time_s, status in statuses if time_s >= 36.0]
    assert min(moved) > 0.05
    assert all(status.level == WARN and not status.parameters for status in after)
    assert 'model no longer explains the data' in after[-1].summary


def test_a_real_step_of_the_demo_drive_is_alarmed_within_three_periods():
    config = node_config()
    detector = ChangeDetector.from_config(config, Baseline.from_config(config))
    change = 31.0
    for time_s, window in run_windows(config, 44.0, seed=22,
                                      params_at=lambda t: {'J': 0.055 if t >= change else 0.05}):
        if window is None:
            continue
        status = detector.update(window)
        if time_s < change:
            assert status.level == OK, status.summary
        elif status.level == ERROR:
            break
    assert status.parameters == ('J',)
    assert time_s - change <= 3 * config.update_period
    assert status.changes[0].relative == pytest.approx(0.1, abs=0.01)


def test_coloured_noise_passes_the_model_check_and_a_gain_step_is_raised_within_six():
    # The demo drive with ARMA measurement noise (pole 0.9, zero -0.5) and its held PRBS: the
    # perfect model fails the fixed 4/sqrt(N) bound in about half of the windows (54 % in
    # bench/alarm.py), never the colour-aware one; a +8 % step of the gain 1/b is raised within
    # six update periods.
    config = node_config()
    detector = ChangeDetector.from_config(config, Baseline.from_config(config))
    change = 61.0
    fixed_failures = aware_failures = healthy = 0
    raised = None
    for time_s, window in run_windows(config, 80.0, seed=31, coloured=True,
                                      params_at=lambda t: {'b': 0.2 / 1.08 if t >= change
                                                           else 0.2}):
        if window is None:
            continue
        check = model_check(window, config.window, config.transient)
        status = detector.update(window, check=check)
        if time_s < change:
            healthy += 1
            aware_failures += not check[0]
            fixed_failures += not model_check(window, config.window, config.transient,
                                              coloured=False)[0]
            assert status.level == OK, status.summary
        elif status.level == ERROR:
            raised = time_s
            break
    assert healthy >= 28
    assert aware_failures <= 1
    assert fixed_failures >= 0.25 * healthy
    assert raised is not None and raised - change <= 6 * config.update_period
    assert status.parameters == ('b',)
