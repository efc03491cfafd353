"""Residual analysis as MATLAB's resid, and its verdict (docs/algorithm.md section 11)."""

import json

from ctid_ros import Data, estimate, Model
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.residual_analysis import (amplitude_dependence, analyse_residual,
                                                   cross_correlation)
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


FOPDT = Model('K*exp(-tau*s)/(T*s + 1)')
FOPDT_TRUTH = {'K': 2.0, 'T': 1.5, 'tau': 0.33}
FOPDT_BOUNDS = {'T': (1e-3, None), 'tau': (0.0, 3.0)}


def multilevel(seed, size=3066, hold=6):
    """Return random steps uniform in -1..1, each held ``hold`` samples."""
    levels = np.random.default_rng(seed).uniform(-1.0, 1.0, size // hold + 1)
    return np.repeat(levels, hold)[:size]


def fopdt_record(commanded, applied, seed, level=0.05):
    """Return the commanded input and the output the applied one drives, in white noise."""
    clean = FOPDT.simulate(FOPDT_TRUTH, applied, 0.05)
    noise = np.random.default_rng(1000 + seed).standard_normal(clean.size)
    return Data(commanded, clean + level * clean.std() * noise, 0.05)


def test_a_saturated_actuator_is_found_in_the_inputs_amplitude():
    # The commanded input recorded, the actuator clipping at +-0.5 (half the samples): the fit
    # is good and its residual uncorrelated with the input, but K comes out a third low.
    u = multilevel(1)
    result = estimate(FOPDT, fopdt_record(u, np.clip(u, -0.5, 0.5), 1), 'auto',
                      bounds=FOPDT_BOUNDS)
    assert result.params['K'] < 0.8 * FOPDT_TRUTH['K']
    assert not result.residuals.input_correlated
    assert result.residuals.amplitude_dependent
    assert ('u', 3) in [term[:2] for term in result.residuals.amplitude_terms]
    assert "depends on the input's amplitude (u^3 at lag" in result.residuals.verdict
    assert 'the standard deviations account for it' not in result.residuals.verdict
    note = [text for text in result.warnings if 'amplitude' in text]
    assert len(note) == 1 and 'actuator saturation' in note[0]
    assert 'the standard deviations do not cover it' in note[0]
    summary = json.loads(json.dumps(result.to_dict(), allow_nan=False))['residual']
    assert summary['amplitude_dependent'] is True
    assert summary['powers_tested'] == ['u^2', 'u^3', 'model output^2', 'model output^3']
    assert summary['amplitude_score'] > summary['amplitude_bound']
    assert any(term['input'] == 'u' and term['power'] == 3
               for term in summary['amplitude_terms'])


def test_a_linear_multilevel_record_does_not_warn():
    # The same input and plant without the saturation, in white and in AR(0.9) noise.
    alarms = 0
    for seed in range(12):
        u = multilevel(seed)
        data = fopdt_record(u, u, seed)
        if seed % 2:
            clean = FOPDT.simulate(FOPDT_TRUTH, u, 0.05)
            noise = signal.lfilter([1.0], [1.0, -0.9],
                                   np.random.default_rng(seed).standard_normal(u.size))
            data = Data(u, clean + 0.05 * clean.std() * noise / noise.std(), 0.05)
        result = estimate(FOPDT, data, 'auto', bounds=FOPDT_BOUNDS)
        assert result.residuals.powers_tested[:2] == ['u^2', 'u^3']
        alarms += result.residuals.amplitude_dependent
        assert not any('amplitude' in text for text in result.warnings)
    assert alarms == 0


def test_a_saturated_binary_input_is_only_a_gain():
    # A PRBS clipped at half its level is a linear record of half the gain: its square and
    # cube are not tested (nothing distinguishes the two), and nothing is found.
    u = prbs(9, 6)
    result = estimate(FOPDT, fopdt_record(u, np.clip(u, -0.5, 0.5), 2), 'auto',
                      bounds=FOPDT_BOUNDS)
    assert result.params['K'] == pytest.approx(1.0, rel=0.01)
    assert 'u^2' not in result.residuals.powers_tested
    assert 'u^3' not in result.residuals.powers_tested
    assert not result.residuals.amplitude_dependent


def test_an_output_nonlinearity_is_found_in_the_model_outputs_amplitude():
    # y = z + 0.1 z^2 with z the linear output: the model output's square carries it.
    u = multilevel(3)
    clean = FOPDT.simulate(FOPDT_TRUTH, u, 0.05)
    noise = np.random.default_rng(3).standard_normal(u.size)
    data = Data(u, clean + 0.1 * clean ** 2 + 0.05 * clean.std() * noise, 0.05)
    result = estimate(FOPDT, data, 'auto', bounds=FOPDT_BOUNDS)
    assert ('model output', 2) in [term[:2] for term in result.residuals.amplitude_terms]
    assert any(text.startswith("the residual depends on the model output's amplitude")
               for text in result.warnings)


def test_a_linear_model_error_is_not_blamed_on_a_nonlinearity():
    # A second-order plant fitted by a first order: the residual correlates with the input,
    # and with its powers through the input's lags, which the test takes out first.
    model = Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))')
    u = multilevel(4)
    clean = model.simulate({'K': 2.0, 'T1': 1.5, 'T2': 0.4, 'tau': 0.33}, u, 0.05)
    noise = np.random.default_rng(4).standard_normal(u.size)
    result = estimate(FOPDT, Data(u, clean + 0.05 * clean.std() * noise, 0.05), 'auto',
                      bounds=FOPDT_BOUNDS)
    assert result.residuals.input_correlated
    assert not result.residuals.amplitude_dependent


def test_coloured_noise_fed_back_is_not_an_amplitude_dependence():
    # A PI loop around a first order with a dead time, AR(0.9) noise fed back: the input
    # depends on past noise, whose colour correlates it with the residual at positive lags.
    # The whitened residual is independent of the past: no alarm in 20 loops.
    ts, count = 0.05, 4000
    a, b = np.exp(-ts / 1.5), 2.0 * (1.0 - np.exp(-ts / 1.5))
    alarms = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        reference = np.repeat(rng.uniform(-1.0, 1.0, count // 40 + 1), 40)[:count]
        noise = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(count))
        noise *= 0.2 / noise.std()
        state, integral = 0.0, 0.0
        u, y = np.zeros(count), np.zeros(count)
        for k in range(count):
            y[k] = state + noise[k]
            integral += 1.5 * ts * (reference[k] - y[k])
            u[k] = 0.4 * (reference[k] - y[k]) + integral
            state = a * state + b * (u[k - 7] if k >= 7 else 0.0)
        result = estimate(FOPDT, Data(u, y, ts), 'auto', bounds=FOPDT_BOUNDS)
        alarms += result.residuals.amplitude_dependent
    assert alarms == 0


def test_amplitude_dependence_on_a_residual_alone():
    # The residual a cubic function of a Gaussian input at lag 3, which is uncorrelated with
    # the input itself; white noise alone is not flagged.
    rng = np.random.default_rng(5)
    u = rng.standard_normal(2000)
    cubic = u ** 3 - 3.0 * u
    residual = 0.1 * np.roll(cubic, 3) + rng.standard_normal(2000)
    found, tested, score, bound = amplitude_dependence(residual, u, ['u'], 25)
    assert tested == ['u^2', 'u^3']
    assert [term[:3] for term in found] == [('u', 3, 3)] and score > bound
    found, _, score, bound = amplitude_dependence(rng.standard_normal(2000), u, ['u'], 25)
    assert not found and score < bound


def test_noise_fed_back_through_a_controller_is_feedback_not_a_model_error():
    # A right model in closed loop: the input carries the coloured noise through a controller's
    # direct term, so the raw residual correlates with it at lag 0 and at positive lags
    # (Bartlett's bound, which assumes them independent, calls it a model error); the
    # prewhitened residual, the innovation, does not correlate with past inputs.
    alarms = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        noise = signal.lfilter([1.0], [1.0, -0.8], rng.standard_normal(4000))
        reference = np.repeat(rng.uniform(-1.0, 1.0, 100), 40)
        u = reference - 0.6 * noise - 0.3 * signal.lfilter([0.0, 1.0], [1.0, -0.9], noise)
        analysis = analyse_residual(noise, u, ['u'], lags=50)
        alarms += analysis.input_correlated
        assert analysis.prewhitened == ['u']
    assert alarms <= 1
    assert analysis.feedback and 'feedback' in analysis.verdict
    # The raw correlation the plot shows is far beyond its bound at lag 0.
    assert abs(analysis.cross_correlation[50, 0]) > 3 * analysis.cross_bounds[0]


def pi_loop(reference, noise, plant, ts, kp, ki, delay):
    """Return the input and output of a PI loop around the ZOH plant ``(num, den)``."""
    a, b, c, _, _ = signal.cont2discrete(signal.tf2ss(*plant), ts, method='zoh')
    state, integral = np.zeros(a.shape[0]), 0.0
    u, y = np.zeros(noise.size), np.zeros(noise.size)
    for k in range(noise.size):
        y[k] = c[0] @ state + noise[k]
        integral += ki * ts * (reference[k] - y[k])
        u[k] = kp * (reference[k] - y[k]) + integral
        state = a @ state + b[:, 0] * (u[k - delay] if k >= delay else 0.0)
    return u, y


@pytest.mark.parametrize('seed', [4, 5])
def test_a_right_model_identified_in_closed_loop_does_not_warn(seed):
    # A PI loop around two lags and a dead time, multilevel reference, AR(0.8) output noise of
    # 20 %, identified from the plant's own u and y: the estimate is right, and the residual's
    # raw correlation with u at lag 0 (the noise through the proportional term) is feedback,
    # not missing dynamics.
    model = Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))')
    truth = {'K': 2.0, 'T1': 1.5, 'T2': 0.4, 'tau': 0.35}
    rng = np.random.default_rng([25, 0, 20, seed])
    reference = np.repeat(rng.uniform(-1.0, 1.0, 101), 40)[:4000]
    noise = signal.lfilter([1.0], [1.0, -0.8], rng.standard_normal(4000))
    u, y = pi_loop(reference, 0.2 * noise / noise.std(), ([2.0], [0.6, 1.9, 1.0]), 0.05, 0.3,
                   0.4, 7)
    result = estimate(model, Data(u, y, 0.05), 'auto',
                      bounds={'T1': (1e-3, None), 'T2': (1e-3, None), 'tau': (0.0, 3.0)})
    params, std = dict(result.params), dict(result.std)
    if params['T1'] < params['T2']:
        params['T1'], params['T2'] = params['T2'], params['T1']
        std['T1'], std['T2'] = std['T2'], std['T1']
    for name, value in truth.items():
        assert abs(params[name] - value) < 3.0 * std[name], name
    assert not result.residuals.input_correlated
    assert result.residuals.prewhitened == ['u'] and result.residuals.feedback
    assert not any('residual correlated with input' in note for note in result.warnings)


def test_a_wrong_dead_time_in_open_loop_still_warns():
    # Open loop, AR(0.9) noise, a held input: a dead time fixed two samples short is a model
    # error, whichever of the two tests decides.
    rng = np.random.default_rng(7)
    u = multilevel(7)
    clean = FOPDT.simulate(FOPDT_TRUTH, u, 0.05)
    noise = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(u.size))
    data = Data(u, clean + 0.2 * clean.std() * noise / noise.std(), 0.05)
    short = Model('K*exp(-0.23*s)/(T*s + 1)')
    result = estimate(short, data, 'auto', bounds={'T': (1e-3, None)})
    assert result.residuals.input_correlated
    assert any(note.startswith('residual correlated with input u') for note in result.warnings)
