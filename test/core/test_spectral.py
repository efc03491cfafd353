"""The frequency response from data alone (Welch H1) against the exact one of the plant."""

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from ctid_ros.core.spectral import spectral_response
import numpy as np
import pytest

TS = 0.01


def record(noise: float, samples: int = 8192):
    """Return a first order with a dead time of 3.73 samples, driven by a PRBS held 2 samples."""
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    params = {'K': 2.0, 'T': 0.2, 'tau': 0.0373}
    u = prbs(12, 2)[:samples]
    y = model.simulate(params, u, TS)
    y = y + noise * np.random.default_rng(1).standard_normal(y.size)
    return model, params, u, y


def test_the_estimate_follows_the_plant_where_the_coherence_is_high():
    model, params, u, y = record(0.01)
    estimate = spectral_response(u, y, TS)
    assert estimate.segment == 1024 and estimate.omega[-1] < np.pi / TS
    # The exact response of the sampled plant under a held input: the transform of its
    # response to a one-sample pulse.
    pulse = model.simulate(params, np.eye(1, 4096)[0], TS)
    exact = np.exp(-1j * np.outer(estimate.omega * TS, np.arange(pulse.size))) @ pulse
    trusted = estimate.coherence > 0.9
    assert trusted.mean() > 0.5     # the PRBS held two samples has no power near Nyquist
    error = np.abs(estimate.response / exact - 1.0)[trusted]
    # The first bin sees the window's leakage from zero frequency: 8 % off, the others 4 %.
    assert np.median(error) < 0.02 and np.max(error[1:][estimate.omega[trusted][1:] < 50]) < 0.05


def test_the_phase_of_a_dead_time_falls_steadily_without_wrapping():
    model, params, u, y = record(0.01)
    estimate = spectral_response(u, y, TS)
    phase = estimate.phase_deg(start=0.0)
    first = estimate.omega[0]
    exact = -np.degrees(np.arctan(first * params['T']) + first * (params['tau'] + TS / 2))
    assert phase[0] == pytest.approx(exact, abs=5.0)
    # Near the Nyquist frequency -90 degrees of the lag and the dead time with half a sample,
    # about -850 degrees in all: two turns and more below the start, reached without a jump.
    last = estimate.omega[-1]
    expected = -np.degrees(np.arctan(last * params['T']) + last * (params['tau'] + TS / 2))
    assert expected < -800 and phase[-1] == pytest.approx(expected, abs=30.0)
    assert np.all(np.diff(phase[estimate.coherence > 0.5]) < 90.0)


def test_noise_lowers_the_coherence_and_bad_arguments_are_refused():
    _, _, u, y = record(5.0)
    assert np.median(spectral_response(u, y, TS).coherence) < 0.5
    with pytest.raises(ValueError, match='same length'):
        spectral_response(u, y[:-1], TS)
    with pytest.raises(ValueError, match='positive'):
        spectral_response(u, y, 0.0)
