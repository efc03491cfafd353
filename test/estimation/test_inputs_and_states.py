"""Several inputs, integrating plants, unknown initial states and output offsets (synthetic)."""

from ctid_ros import Data, DataError, estimate, Model
from ctid_ros.core.excitation import prbs
import numpy as np
import pytest

TS = 0.01


def relative_errors(result, truth):
    return {name: abs(result.params[name] / value - 1.0) for name, value in truth.items()}


def test_two_inputs_and_a_constant_share_one_denominator():
    model = Model('T*s*y + y = K1*u + K2*w + c', inputs=('u', 'w'))
    truth = {'T': 0.3, 'K1': 2.0, 'K2': -0.7, 'c': 0.4}
    rng = np.random.default_rng(7)
    u = np.column_stack([prbs(9, 6)[:3000], np.repeat(rng.standard_normal(300), 10)])
    clean = model.simulate(truth, u, TS)
    y = clean + 0.1 * np.std(clean) * rng.standard_normal(clean.size)
    result = estimate(model, Data(u, y, TS), {'T': 1.0, 'K1': 1.0, 'K2': 1.0, 'c': 0.0})
    assert max(relative_errors(result, truth).values()) < 0.03, result.params
    for name in truth:
        assert abs(result.params[name] - truth[name]) < 4.0 * result.std[name], name


def test_integrating_plant_is_recovered_from_noise_free_data():
    model = Model('M*s**2*y + F*s*y = u - off', inputs='u')
    truth = {'M': 2.0, 'F': 5.0, 'off': 0.3}
    u = prbs(10, 20)[:8000]
    y = model.simulate(truth, u, TS)
    result = estimate(model, Data(u, y, TS), {'M': 0.5, 'F': 20.0, 'off': 0.0})
    # Not to 1e-12: the high pass of the measured y assumes y linear between samples.
    assert max(relative_errors(result, truth).values()) < 1e-4, result.params
    assert result.compare(Data(u, y, TS)) > 99.999


def test_integrating_plant_from_a_nonzero_position_with_noise():
    model = Model('K/(s*(T*s + 1))')
    assert model.integrators == 1
    truth = {'K': 3.0, 'T': 0.2}
    u = prbs(10, 10)[:6000]
    rng = np.random.default_rng(11)
    clean = 5.0 + model.simulate(truth, u, TS)             # at rest at position 5
    y = clean + 0.02 * np.std(clean) * rng.standard_normal(clean.size)
    result = estimate(model, Data(u, y, TS), 'auto')
    assert max(relative_errors(result, truth).values()) < 0.03, result.params
    assert result.integrator_cutoff == pytest.approx(20 * np.pi / 60.0)


def first_order_with_initial_state(seed):
    model = Model('K/(T*s + 1)')
    truth = {'K': 1.5, 'T': 0.4}
    u = prbs(7, 8)[:400]
    rng = np.random.default_rng(seed)
    time = TS * np.arange(u.size)
    clean = model.simulate(truth, u, TS) + 2.0 * np.exp(-time / truth['T'])
    return model, truth, u, clean + 0.02 * rng.standard_normal(u.size)


def test_estimated_initial_state_removes_the_bias_of_a_start_away_from_rest():
    model, truth, u, y = first_order_with_initial_state(3)
    data = Data(u, y, TS)
    at_rest = estimate(model, data, 'auto')
    free = estimate(model, data, 'auto', initial_state='estimate')
    assert max(relative_errors(free, truth).values()) < 0.02, free.params
    assert max(relative_errors(at_rest, truth).values()) > 0.05, at_rest.params
    assert free.compare(data) == pytest.approx(free.fit, abs=1e-6)


def test_output_offset_is_estimated():
    model = Model('K/(T*s + 1)')
    truth = {'K': 1.5, 'T': 0.4}
    u = prbs(8, 8)[:2000]
    rng = np.random.default_rng(5)
    y = model.simulate(truth, u, TS) + 4.0 + 0.05 * rng.standard_normal(u.size)
    result = estimate(model, Data(u, y, TS), 'auto', output_offset=True,
                      initial_state='estimate')
    assert max(relative_errors(result, truth).values()) < 0.02, result.params
    assert result.compare(Data(u, y, TS)) == pytest.approx(result.fit, abs=1e-6)


def test_input_columns_must_match_the_model():
    model = Model('T*s*y + y = K1*u + K2*w', inputs=('u', 'w'))
    data = Data(prbs(6)[:60], np.ones(60), TS)
    with pytest.raises(DataError, match='2 input'):
        estimate(model, data, 'auto')
