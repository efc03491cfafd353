"""Model output, regressors phi and instruments psi (docs/algorithm.md sections 3 and 4)."""

from ctid_ros import EstimationError, Model
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.core.simulation import responses
from ctid_ros.estimation.regressors import is_stable, SignalBank
import numpy as np
import pytest


def two_input_equation():
    model = Model('T*s*y + y = K1*u + K2*w + c', inputs=('u', 'w'))
    rng = np.random.default_rng(7)
    u = np.column_stack([prbs(9, 6)[:3000], np.repeat(rng.standard_normal(300), 10)])
    return model, {'T': 0.3, 'K1': 2.0, 'K2': -0.7, 'c': 0.4}, u, 0.01


def reference(factory):
    system = factory()
    return system.model, system.truth, system.u, system.ts


# Fractional dead times only: at a dead time of whole samples the output has a kink in tau
# (the input switches exactly at a sample), where central differences lose their second order.
CASES = {
    'mass-spring-damper': lambda: reference(systems.mass_spring_damper),
    'rao-garnier': lambda: reference(systems.rao_garnier),
    'closed loop': lambda: reference(systems.closed_loop_pid),
    'fractional dead time': lambda: reference(systems.first_order_dead_time),
    'non-affine': lambda: reference(systems.second_order_nonaffine),
    'two inputs and a constant': two_input_equation,
}


@pytest.mark.parametrize('case', sorted(CASES))
def test_instruments_are_the_output_sensitivities(case):
    # psi_i = d yhat / d theta_i, against central differences of the simulated output
    # (step 1e-5 relative: truncation and rounding both stay near 1e-8 here).
    model, truth, u, ts = CASES[case]()
    theta = model.vector(truth)
    bank = SignalBank(model, u, model.simulate(truth, u, ts), ts)
    psi = bank.linearize(model.coefficients(theta), regressors=False).psi
    assert psi.shape == (len(u), theta.size)
    for index, name in enumerate(model.parameters):
        step = 1e-5 * max(abs(theta[index]), 1.0)
        up, down = theta.copy(), theta.copy()
        up[index] += step
        down[index] -= step
        difference = (bank.output(model.coefficients(up))
                      - bank.output(model.coefficients(down))) / (2.0 * step)
        error = np.linalg.norm(difference - psi[:, index]) / np.linalg.norm(psi[:, index])
        assert error < 1e-7, (name, error)


def decomposition_error(model, truth, start, u, ts):
    """Return |e - Phi (theta0 - theta)| / |e| at ``start`` on noise-free data from ``truth``."""
    y = model.simulate(truth, u, ts)
    lin = SignalBank(model, u, y, ts).linearize(model.coefficients(start))
    error = y - lin.output
    predicted = lin.phi @ (model.vector(truth) - model.vector(start))
    return np.linalg.norm(error - predicted) / np.linalg.norm(error)


def test_error_decomposition_is_exact_for_numerator_parameters():
    # With D independent of theta, phi = N_i/D u holds no filtered output: e = Phi (theta0 -
    # theta) to rounding, from any start.
    model = Model('(b1*s + b0)/(s**2 + 3*s + 2)')
    error = decomposition_error(model, {'b1': 2.0, 'b0': 1.0}, {'b1': -1.0, 'b0': 5.0},
                                prbs(9, 4), 0.01)
    assert error < 1e-12


def test_error_decomposition_for_denominator_parameters_is_second_order_in_ts():
    # The identity is exact in continuous time; D_i/D y is computed from the samples of y
    # assumed linear between them (first-order hold), so it holds to O(ts^2): the mismatch
    # falls four times per halving of the sample time.
    system = systems.mass_spring_damper()
    start = {'m': 1.0, 'd': 3.0, 'k': 20.0}
    errors = []
    for ts in (0.01, 0.005, 0.0025):
        u = np.repeat(system.u, int(round(0.01 / ts)))
        errors.append(decomposition_error(system.model, system.truth, start, u, ts))
    assert errors[0] < 1e-3
    for coarse, fine in zip(errors, errors[1:]):
        assert coarse / fine == pytest.approx(4.0, rel=0.05)


@pytest.mark.parametrize('text,theta', [
    # k moves N and D, m and d only D: the filtered output is taken from the input's rows.
    ('k/(m*s**2 + d*s + k)', {'m': 1.0, 'd': 3.0, 'k': 20.0}),
    # Every parameter moves D alone: the input gives no rows.
    ('1/(m*s**2 + d*s + k)', {'m': 1.0, 'd': 3.0, 'k': 20.0}),
    # T moves D alone, K and b only N: the filtered output goes to some rows only.
    ('K*(b*s + 1)/(T*s**2 + 2*s + 1)', {'K': 2.0, 'b': 0.5, 'T': 0.4}),
])
def test_regressors_are_their_definition(text, theta):
    # phi_i = dN_i/D u - dD_i/D y (u held, y first-order hold), against core's own responses.
    model = Model(text)
    ts = 0.01
    u = prbs(9, 4)[:2000]
    y = np.sin(0.01 * np.arange(u.size)) + 0.1 * u
    coefficients = model.coefficients(model.vector(theta))
    phi = SignalBank(model, u, y, ts).linearize(coefficients).phi
    den = coefficients.den
    for index in range(len(theta)):
        expected = responses([coefficients.num_jacobian[index, 0]], den, u, ts)[0] - \
            responses([coefficients.den_jacobian[index]], den, y, ts, intersample='foh')[0]
        np.testing.assert_allclose(phi[:, index], expected, rtol=0,
                                   atol=1e-10 * np.max(np.abs(expected)))


def test_output_is_the_model_simulation_and_regressors_are_optional():
    system = systems.first_order_dead_time()
    bank = SignalBank(system.model, system.u, system.noise_free(), system.ts)
    coefficients = system.model.coefficients(system.truth)
    np.testing.assert_allclose(bank.output(coefficients), system.noise_free(), rtol=0,
                               atol=1e-12 * np.max(np.abs(system.noise_free())))
    lin = bank.linearize(coefficients, regressors=False)
    assert lin.phi is None
    np.testing.assert_array_equal(lin.output, bank.output(coefficients))
    assert bank.linearize(coefficients).phi.shape == lin.psi.shape


def test_dead_time_of_a_biproper_model_is_refused():
    model = Model('(a*s + 1)*exp(-tau*s)/(s + 1)')
    u = prbs(6, 4)
    bank = SignalBank(model, u, np.zeros(u.size), 0.1)
    with pytest.raises(EstimationError, match='biproper'):
        bank.linearize(model.coefficients({'a': 2.0, 'tau': 0.25}))


@pytest.mark.parametrize('den, stable', [
    ([1.0, 3.0, 2.0], True), ([1.0, -1.0], False), ([1.0, 0.0, 1.0], False),
    ([1.0, 0.0], False), ([0.0, 1.0], False), ([-2.0, -1.0], True), ([2.0], True),
    ([np.nan, 1.0], False),
])
def test_hurwitz_test(den, stable):
    assert bool(is_stable(np.array(den))) == stable


@pytest.mark.parametrize('samples', [0, 3])
def test_dead_time_sensitivity_on_the_lattice_is_one_sided(samples):
    # With a held input and a dead time of whole samples the output has a kink in tau: psi is
    # the derivative for a growing dead time, psi + delay_jump for a shrinking one.
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    u = prbs(7, 3)
    theta = np.array([2.0, samples * 0.1, 0.4])
    bank = SignalBank(model, u, np.zeros(u.size), 0.1)
    lin = bank.linearize(model.coefficients(theta), regressors=False)
    assert lin.delay_jump is not None and np.any(lin.delay_jump[:, 1])
    assert not np.any(lin.delay_jump[:, [0, 2]])
    step = 1e-7
    here = bank.output(model.coefficients(theta))
    later = theta + [0.0, step, 0.0]
    right = (bank.output(model.coefficients(later)) - here) / step
    scale = np.linalg.norm(right)
    assert np.linalg.norm(lin.psi[:, 1] - right) < 1e-5 * scale
    if samples:
        earlier = theta - [0.0, step, 0.0]
        left = (here - bank.output(model.coefficients(earlier))) / step
        shrinking = lin.psi[:, 1] + lin.delay_jump[:, 1]
        assert np.linalg.norm(shrinking - left) < 1e-5 * scale
        assert np.linalg.norm(lin.psi[:, 1] - left) > 0.1 * scale
    # Off the lattice both sides agree.
    off = bank.linearize(model.coefficients(theta + [0.0, 0.037, 0.0]), regressors=False)
    assert off.delay_jump is None


@pytest.mark.parametrize('intersample', ['zoh', 'foh'])
def test_pulse_response_is_the_models_simulated_pulse(intersample):
    model = Model('K/((T*s + 1)*(0.05*s + 1))', controller='2 + 1/s')
    params = {'K': 1.5, 'T': 0.4}
    u = prbs(9, 4)[:1500]
    bank = SignalBank(model, u, model.simulate(params, u, 0.01), 0.01, intersample)
    pulse = np.zeros(700)
    pulse[0] = 1.0
    # The bank's kept discretisation gives Model.simulate's zero-order-hold pulse response
    # to the bit, whatever the bank's own intersample behaviour.
    np.testing.assert_array_equal(bank.pulse_response(model.coefficients(params), 700),
                                  model.simulate(params, pulse, 0.01))
