"""Residual analysis as MATLAB's resid, and its verdict (docs/algorithm.md section 11)."""

import json

from ctid_ros import Data, estimate, Model
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.residual_analysis import analyse_residual, cross_correlation
import numpy as np
import pytest
from scipy import signal


def test_cross_correlation_matches_the_definition():
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal(300), rng.standard_normal(300)
    r = cross_correlation(a, b, 5)
    ac, bc = a - a.mean(), b - b.mean()
    scale = np.sqrt((ac @ ac) * (bc @ bc))
    for k in range(-5, 6):
        expected = sum(ac[t] * bc[t - k] for t in range(300) if 0 <= t - k < 300) / scale
        assert r[k + 5] == pytest.approx(expected, abs=1e-12)
    assert cross_correlation(a, a, 3)[3] == pytest.approx(1.0)


def test_white_noise_is_white_and_independent_in_nearly_every_record():
    u = prbs(9, 4)
    alarms = 0
    for seed in range(200):
        noise = np.random.default_rng(seed).standard_normal(u.size)
        analysis = analyse_residual(noise, u, ['u'], lags=25)
        alarms += analysis.input_correlated or not analysis.white
    # About 1 % false alarms per test, two tests.
    assert alarms <= 8
    assert analysis.verdict == 'white and independent of the input: nothing left to model'


def test_a_missed_input_effect_is_found_at_its_lag():
    rng = np.random.default_rng(1)
    u = prbs(9, 1)
    residual = 0.3 * np.roll(u, 3) + rng.standard_normal(u.size)
    analysis = analyse_residual(residual, u, ['u'])
    assert analysis.input_correlated and analysis.correlated_inputs == ['u']
    assert analysis.worst_lags[0][:2] == ('u', 3)
    assert analysis.verdict.startswith('correlated with input u (lag 3')
    assert 'missing dynamics or a wrong dead time' in analysis.verdict


def test_coloured_noise_is_coloured_but_not_input_correlated():
    # A strongly coloured input and coloured noise: Bartlett's bound keeps chance correlations
    # from reading as model errors.
    u = prbs(9, 20)
    alarms = 0
    for seed in range(50):
        white = np.random.default_rng(seed).standard_normal(u.size)
        analysis = analyse_residual(signal.lfilter([1.0], [1.0, -0.95], white), u, ['u'])
        assert not analysis.white
        alarms += analysis.input_correlated
    assert alarms <= 2
    assert analysis.verdict.startswith('coloured but independent of the input')


def test_feedback_shows_at_negative_lags():
    rng = np.random.default_rng(2)
    noise = rng.standard_normal(3000)
    u = 0.5 * np.roll(noise, 2) + rng.standard_normal(3000)     # the input reacts to e
    analysis = analyse_residual(noise, u, ['u'])
    assert analysis.feedback and not analysis.input_correlated
    assert 'feedback' in analysis.verdict


def test_estimate_carries_the_analysis_and_its_json():
    system = systems.first_order_dead_time()
    result = estimate(system.model, system.data(seed=2), 'auto', bounds=system.bounds)
    assert result.residuals.white and not result.residuals.input_correlated
    summary = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert summary['residual']['verdict'] == result.residuals.verdict
    assert summary['residual']['white'] is True
    assert summary['residual']['input_correlated'] is False
    assert summary['residual']['noise_order'] == 0


def test_a_wrong_dead_time_is_reported_in_the_warnings():
    # The dead time fixed 25 % too short: the fit stays high, the residual says what is wrong.
    system = systems.first_order_dead_time()
    data = system.data(seed=3)
    tau = 0.75 * system.truth['tau']
    result = estimate(system.model, data, dict(system.truth, tau=tau),
                      bounds={'tau': (tau, tau * (1 + 1e-12)), 'T': (1e-3, None)})
    assert result.fit > 60.0
    assert result.residuals.input_correlated
    assert any(note.startswith('residual correlated with input u') for note in result.warnings)


def test_two_inputs_are_analysed_separately():
    rng = np.random.default_rng(4)
    model = Model('s*y + y = a*u1 + b*u2', inputs=('u1', 'u2'))
    u = np.column_stack([prbs(8, 3), rng.standard_normal(765)])
    y = model.simulate({'a': 1.0, 'b': 0.5}, u, 0.1) + 0.05 * rng.standard_normal(765)
    result = estimate(model, Data(u, y, 0.1), 'auto')
    assert result.residuals.inputs == ['u1', 'u2']
    assert result.residuals.cross_correlation.shape == (2 * result.residuals.lags + 1, 2)
    assert not result.residuals.input_correlated
