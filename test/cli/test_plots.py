"""Figures: fit, parameters over time against the truth, Bode plot with its uncertainty band."""

from dataclasses import replace

from ctid_ros import Data, estimate, Model
from ctid_ros.cli.plots import (bode, bode_data, fit_figure, measured_response,
                                parameters_figure, residual_figure, transient_seconds)
from ctid_ros.core.excitation import prbs
import matplotlib
import numpy as np
import pytest

PNG = b'\x89PNG\r\n\x1a\n'
TRUTH = {'K': 2.0, 'T': 1.5, 'tau': 0.237}


@pytest.fixture(scope='module')
def result():
    """Return an estimate of a first order with dead time from 20 s of noisy data."""
    u = prbs(9, 20)[:2000]
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    y = model.simulate(TRUTH, u, 0.01)
    y = y + 0.02 * np.std(y) * np.random.default_rng(0).standard_normal(y.size)
    return estimate(model, Data(u, y, 0.01))


def written(path):
    data = path.read_bytes()
    return data[:8] == PNG and len(data) > 10_000


def test_fit_figure_with_the_residual_below(tmp_path, result):
    backend = matplotlib.get_backend()
    data = Data(prbs(9, 20)[:2000], np.zeros(2000), 0.01)
    figure = fit_figure(data.time, result.simulate(data) + 0.01, result.simulate(data),
                        fit=93.456, transient=1.5, unit='rad/s', verdict='white',
                        path=tmp_path / 'fit.png')
    assert written(tmp_path / 'fit.png')
    top, bottom = figure.axes
    assert top.get_ylabel() == 'output y (rad/s)' and bottom.get_ylabel() == 'residual (rad/s)'
    assert bottom.get_xlabel() == 'time (s)' and bottom.get_title() == 'residual: white'
    assert '93.5 %' in top.get_title()
    assert [text.get_text() for text in top.get_legend().get_texts()] == [
        'first 1.5 s simulated, not fitted', 'measured', 'simulated (fit 93.5 %)']
    # The residual (measured - simulated, 0.01 throughout) and its RMS where fitted.
    (residual,) = bottom.get_lines()[:1]
    np.testing.assert_allclose(residual.get_ydata(), 0.01)
    assert 'RMS 0.01 where fitted' in bottom.get_legend().get_texts()[-1].get_text()
    assert matplotlib.get_backend() == backend     # no global backend switch


def test_transient_seconds_of_an_estimate(result):
    assert transient_seconds(result, 2000, 0.01, 0.5) == pytest.approx(0.5)
    # Automatic: five time constants plus the dead time, in whole samples, at most half.
    assert transient_seconds(result, 2000, 0.01, -1.0) == pytest.approx(
        np.ceil((5 * result.params['T'] + result.params['tau']) / 0.01) * 0.01)
    assert transient_seconds(result, 600, 0.01, -1.0) == pytest.approx(3.0)


def test_parameters_figure_against_a_drifting_truth(tmp_path):
    times = np.arange(5.0, 60.0, 5.0)
    drift = np.where(times < 30.0, 1.5, 2.5)
    values = np.column_stack([np.full_like(times, 2.0), drift, np.full_like(times, 0.24)])
    stds = np.full_like(values, 0.05)
    stds[0, :] = np.nan       # an estimate without a known uncertainty draws no band

    def truth(time):
        return {'K': 2.0, 'T': np.where(time < 30.0, 1.5, 2.5)}

    figure = parameters_figure(times, ['K', 'T', 'tau'], values, stds, truth=truth,
                               units={'T': 's', 'tau': 's'}, path=tmp_path / 'params.png')
    assert written(tmp_path / 'params.png')
    assert [axes.get_ylabel() for axes in figure.axes] == ['K', 'T (s)', 'tau (s)']
    assert figure.axes[-1].get_xlabel().startswith('time (s)')
    labels = [[text.get_text() for text in axes.get_legend().get_texts()]
              for axes in figure.axes]
    assert set(labels[1]) == {'estimate', 'truth', '±2σ'}
    assert 'truth' not in labels[2]
    constant = parameters_figure(times, ['K', 'T', 'tau'], values, stds, truth=TRUTH)
    assert len(constant.axes[2].get_lines()) == 2


def test_bode_band_contains_the_estimate(tmp_path, result):
    data = bode_data(result, draws=100, seed=1)
    assert data.draws == 100
    assert data.omega[0] < 1 / TRUTH['T'] / 10 and data.omega[-1] > 1 / TRUTH['tau']
    assert np.all(data.magnitude_band[0] <= data.magnitude_db + 1e-9)
    assert np.all(data.magnitude_db <= data.magnitude_band[1] + 1e-9)
    assert np.all(data.phase_band[0] <= data.phase_deg + 1e-9)
    assert np.all(data.phase_deg <= data.phase_band[1] + 1e-9)
    # Low-frequency gain 20 log10(K) and a phase lag growing with the dead time.
    assert data.magnitude_db[0] == pytest.approx(20 * np.log10(TRUTH['K']), abs=0.1)
    assert data.phase_deg[-1] < -360.0
    again = bode_data(result, draws=100, seed=1)
    assert np.array_equal(again.magnitude_band, data.magnitude_band)   # seeded
    figure = bode(result, path=tmp_path / 'bode.png')
    assert written(tmp_path / 'bode.png')
    top, bottom = figure.axes
    assert top.get_ylabel() == 'magnitude (dB)' and bottom.get_ylabel() == 'phase (deg)'
    assert bottom.get_xlabel() == 'angular frequency (rad/s)'
    assert bottom.get_xscale() == 'log'


def test_bode_stops_at_max_omega_and_gives_the_band_width(result):
    assert bode_data(result, draws=0).omega[-1] == pytest.approx(100.0)  # 1/tau: 4.2 rad/s
    data = bode_data(result, draws=20, max_omega=20.0)
    assert data.omega[-1] == pytest.approx(20.0) and data.omega[0] < 1 / TRUTH['T'] / 10
    legend = bode(result, draws=20, max_omega=20.0).axes[0].get_legend()
    width = np.max(data.magnitude_band[1] - data.magnitude_band[0])
    assert f'at most {width:.2g} dB wide' in legend.get_texts()[0].get_text()


def test_bode_of_a_closed_loop_estimate_shows_the_plant():
    model = Model('1/(m*s**2 + d*s + k)', controller='20 + 10/s')
    u = prbs(9, 20)[:2000]
    y = model.simulate({'m': 1.0, 'd': 2.0, 'k': 10.0}, u, 0.01)
    closed = estimate(model, Data(u, y + 1e-3 * np.sin(np.arange(y.size)), 0.01),
                      {'m': 0.5, 'd': 1.0, 'k': 5.0})
    plant = bode_data(closed, np.array([1e-3]), draws=0)
    assert plant.magnitude_db[0] == pytest.approx(20 * np.log10(1 / 10.0), abs=0.05)
    loop = bode_data(closed, np.array([1e-3]), draws=0, closed_loop=True)
    assert loop.magnitude_db[0] == pytest.approx(0.0, abs=0.05)     # integral action
    assert 'plant' in bode(closed, draws=10).axes[0].get_title()


def test_residual_figure(tmp_path, result):
    figure = residual_figure(result, path=tmp_path / 'residual.png')
    assert written(tmp_path / 'residual.png')
    autocorrelation, cross = figure.axes
    assert autocorrelation.get_title() == 'autocorrelation of the residual'
    assert cross.get_title() == 'cross-correlation of the residual with u'
    assert cross.get_xlabel() == 'lag (samples)'
    lags = result.residuals.lags
    # Cross-correlation over negative and positive lags, autocorrelation from lag 0.
    assert cross.get_xlim()[0] < -0.9 * lags and autocorrelation.get_xlim()[0] > -0.1 * lags
    assert figure.texts[0].get_text().startswith('Residual: white')
    with pytest.raises(ValueError, match='no residual analysis'):
        residual_figure(replace(result, residuals=None))


def test_bode_over_the_response_seen_in_the_data(tmp_path, result):
    u = prbs(11, 2)[:4000]      # power up to the Nyquist frequency
    y = result.model.simulate(TRUTH, u, 0.01)
    measured = measured_response(result, Data(u, y, 0.01))
    # The hold taken out, the data's response is the plant's where the input has power: the
    # hold's half sample alone would be 29 degrees at 100 rad/s.
    exact = result.model.frequency_response(TRUTH, measured.omega)
    coherent = (measured.coherence > 0.9) & (measured.omega < 150)
    ratio = measured.response[coherent] / exact[coherent]
    assert np.count_nonzero(coherent) > 20
    assert np.median(np.abs(np.abs(ratio) - 1)) < 0.05
    assert np.median(np.abs(np.degrees(np.angle(ratio)))) < 3.0
    figure = bode(result, measured=measured, max_omega=np.pi / 0.01,
                  units={'u': 'V', 'y': 'm'}, path=tmp_path / 'bode.png')
    top, bottom = figure.axes
    assert top.get_ylabel() == 'magnitude (dB of y/u in m per V)'
    assert any('data (Welch' in text.get_text() for text in top.get_legend().get_texts())
    # The data's phase is drawn on the model's branch and falls with the dead time.
    dots = [line for line in bottom.get_lines() if line.get_marker() == '.']
    phases = np.concatenate([line.get_ydata() for line in dots])
    assert phases.min() < -360 and phases.max() < 10


@pytest.mark.parametrize('text, params, low', [
    ('K/(s*(T*s + 1))', {'K': 1.0, 'T': 0.5}, -90.0),               # an integrator
    ('K/(s**3 + a*s**2 + b*s)', {'K': 1.0, 'a': 3.0, 'b': 2.0}, -90.0),
    ('K/(T*s + 1)', {'K': -2.0, 'T': 0.5}, -180.0),                 # a negative gain
    ('K*exp(-tau*s)/(T*s + 1)', {'K': 1.0, 'T': 0.5, 'tau': 2.0}, 0.0),
])
def test_phase_starts_on_its_low_frequency_branch_and_never_wraps(text, params, low):
    model = Model(text)
    u = prbs(8, 5)[:1000]
    fitted = estimate(model, Data(u, model.simulate(params, u, 0.05), 0.05), params,
                      max_iterations=1)
    data = bode_data(fitted, np.logspace(-3, 2, 60), draws=0)
    assert data.phase_deg[0] == pytest.approx(low, abs=1.0)
    # A long dead time (2 s) over a coarse grid: a steadily falling phase, no jump back up.
    assert np.all(np.diff(data.phase_deg) < 1.0)
