"""The stable reformulation of integrating plants (docs/algorithm.md section 13)."""

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.integrating import default_cutoff, StabilizedModel
from ctid_ros.estimation.regressors import SignalBank
import numpy as np
import pytest


def test_denominator_trades_the_integrators_for_the_high_pass_poles():
    # K/(s (T s + 1)) becomes K/((T s + 1)(s + c)): same numerator, dead time and parameters.
    model = Model('K*exp(-tau*s)/(s*(T*s + 1))')
    stable = StabilizedModel(model, 2.0)
    theta = model.vector({'K': 3.0, 'tau': 0.1, 'T': 0.2})
    original, coefficients = model.coefficients(theta), stable.coefficients(theta)
    np.testing.assert_array_equal(coefficients.num, original.num)
    np.testing.assert_array_equal(coefficients.num_jacobian, original.num_jacobian)
    assert coefficients.delay == original.delay
    np.testing.assert_allclose(coefficients.den, np.polymul([0.2, 1.0], [1.0, 2.0]), rtol=1e-15)
    # dD'/dT = s, times (s + c); dD'/dK = dD'/dtau = 0.
    np.testing.assert_allclose(coefficients.den_jacobian,
                               [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, 0.0]], atol=0.0)
    assert model.integrators == 1 and stable.integrators == 0
    assert stable.parameters == model.parameters and stable.inputs == model.inputs
    assert stable.is_affine == model.is_affine


def test_double_integrator_gets_a_double_high_pass_pole():
    model = Model('1/(J*s**2)')
    coefficients = StabilizedModel(model, 3.0).coefficients({'J': 0.5})
    np.testing.assert_allclose(coefficients.den, [0.5, 3.0, 4.5], rtol=1e-15)


@pytest.mark.parametrize('text, truth', [
    ('K/(s*(T*s + 1))', {'K': 3.0, 'T': 0.2}),
    ('K/(s**2*(T*s + 1))', {'K': 3.0, 'T': 0.2}),
])
def test_high_passed_output_is_the_stable_model_response(text, truth):
    # (s/(s + c))^k N/(s^k D') u = N/(D' (s + c)^k) u exactly in continuous time; the measured
    # y is high-passed assuming it linear between samples, so the match is O(ts^2): four times
    # closer per halving of the sample time. The initial position drops out.
    model = Model(text)
    stable = StabilizedModel(model, 2.0)
    errors = []
    for ts in (0.01, 0.005):
        u = np.repeat(prbs(10, 10)[:3000], int(round(0.01 / ts)))
        u = u - np.mean(u)
        y = 5.0 + model.simulate(truth, u, ts)
        filtered = stable.filtered_output(y, ts)
        output = SignalBank(stable, u, filtered, ts).output(stable.coefficients(truth))
        errors.append(np.linalg.norm(output - filtered) / np.linalg.norm(filtered))
    assert errors[0] < 1e-4
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.05)


def test_default_cutoff_is_ten_periods_per_record():
    assert default_cutoff(60.0) == pytest.approx(2.0 * np.pi * 10.0 / 60.0, rel=1e-15)


@pytest.mark.parametrize('cutoff', [0.0, -1.0, np.nan, np.inf])
def test_cutoff_must_be_a_positive_frequency(cutoff):
    with pytest.raises(ValueError, match='positive frequency'):
        StabilizedModel(Model('K/(s*(T*s + 1))'), cutoff)
