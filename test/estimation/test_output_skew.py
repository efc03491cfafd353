"""Outputs measured a fixed time after the input instants (``Data.output_skew``)."""

from ctid_ros import Data, estimate, Model
from ctid_ros.core import reference_systems as systems
import numpy as np
import pytest

SKEW = 0.037        # seconds after each input instant; the sample time is 0.1 s


def skewed_data(system, seed, skew=SKEW):
    """Return the system's data with the output read ``skew`` after every input instant."""
    clean = system.model.simulate(system.truth, system.u, system.ts, output_skew=skew)
    sigma = np.std(clean) / 10.0 ** (system.snr_db / 20.0)
    noise = sigma * np.random.default_rng(seed).standard_normal(clean.size)
    return Data(system.u, clean + noise, system.ts, output_skew=skew)


@pytest.mark.parametrize('seed', [1, 2])
def test_dead_time_is_unbiased_under_an_output_skew(seed):
    system = systems.first_order_dead_time()
    data = skewed_data(system, seed)
    result = estimate(system.model, data, 'auto', bounds=system.bounds)
    for name, true_value in system.truth.items():
        assert abs(result.params[name] - true_value) < 4.0 * system.crlb_std[name], name
    # Ignoring the skew moves the dead time by the skew, about 3.5 of its standard deviations.
    ignored = estimate(system.model, Data(data.u, data.y, data.ts), 'auto',
                       bounds=system.bounds)
    assert ignored.params['tau'] == pytest.approx(result.params['tau'] - SKEW, abs=0.01)
    # The identified model reproduces the data at the output instants.
    assert result.compare(data) == pytest.approx(result.fit, abs=1e-9)
    np.testing.assert_allclose(result.predict(data), system.model.simulate(
        result.params, data.u, data.ts, output_skew=SKEW), rtol=0.0, atol=1e-12)


def test_skew_without_a_dead_time_parameter_and_with_an_initial_state():
    system = systems.second_order_nonaffine()
    data = skewed_data(system, 3, skew=0.015)
    result = estimate(system.model, data, 'auto', bounds=system.bounds,
                      initial_state='estimate')
    for name, true_value in system.truth.items():
        assert abs(result.params[name] - true_value) < 4.0 * system.crlb_std[name], name


def test_zero_skew_keeps_every_number():
    system = systems.first_order_dead_time()
    data = system.data(seed=4)
    plain = estimate(system.model, data, 'auto', bounds=system.bounds)
    zero = estimate(system.model, Data(data.u, data.y, data.ts, output_skew=0.0), 'auto',
                    bounds=system.bounds)
    assert plain.params == zero.params and plain.std == zero.std and plain.cost == zero.cost


def test_skewed_second_order_plus_dead_time_with_a_known_answer():
    model = Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))')
    truth = {'K': 1.0, 'T1': 0.5, 'T2': 2.0, 'tau': 0.25}
    system = systems.first_order_dead_time()
    u, ts = system.u, system.ts
    clean = model.simulate(truth, u, ts, output_skew=0.06)
    y = clean + 0.02 * np.random.default_rng(1).standard_normal(u.size)
    result = estimate(model, Data(u, y, ts, output_skew=0.06), 'auto',
                      bounds={'T1': (1e-3, None), 'T2': (1e-3, None)})
    lags = sorted((result.params[name], result.std[name]) for name in ('T1', 'T2'))
    for (value, std), true_value in zip(lags, (0.5, 2.0)):
        assert value == pytest.approx(true_value, abs=4.0 * std)
    assert result.params['tau'] == pytest.approx(0.25, abs=4.0 * result.std['tau'])
    assert result.params['K'] == pytest.approx(1.0, abs=4.0 * result.std['K'])
