"""One estimation problem: bounds, admissible set, cost, nuisance projection, dead-time bracket."""

from ctid_ros import Data, Model, ModelError
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.correlation import prewhitened_delay
from ctid_ros.estimation.problem import (bound_vectors, delay_parameter, nuisance_columns,
                                         orthonormal_basis, Problem, reduction_limits,
                                         settling_time, with_fitted_nuisance)
import numpy as np
import pytest

FOPDT = 'K*exp(-tau*s)/(T*s + 1)'


def problem_for(model, data, bounds=None, **options):
    lower, upper = bound_vectors(model, bounds)
    return Problem(model, data, lower, upper, 'zoh', **options)


def test_bound_vectors_follow_parameter_order_and_keep_a_dead_time_non_negative():
    model = Model(FOPDT)                                   # parameters K, tau, T
    lower, upper = bound_vectors(model, {'T': (1e-3, None), 'K': (None, 5.0)})
    np.testing.assert_array_equal(lower, [-np.inf, 0.0, 1e-3])
    np.testing.assert_array_equal(upper, [5.0, np.inf, np.inf])
    lower, _ = bound_vectors(model, {'tau': (-1.0, 2.0)})
    assert lower[1] == 0.0
    with pytest.raises(ModelError, match='unknown parameter'):
        bound_vectors(model, {'L': (0.0, 1.0)})
    with pytest.raises(ModelError, match='empty'):
        bound_vectors(model, {'T': (2.0, 1.0)})


def test_delay_parameter_is_only_a_parameter_that_is_the_dead_time_itself():
    assert delay_parameter(Model(FOPDT)) == 1
    assert delay_parameter(Model('K*exp(-0.5*s)/(T*s + 1)')) is None
    assert delay_parameter(Model('K*exp(-2*tau*s)/(T*s + 1)')) is None
    assert delay_parameter(Model('K/(T*s + 1)')) is None


def test_settling_time_is_five_slowest_time_constants_plus_the_dead_time():
    model = Model(FOPDT)
    assert settling_time(model.coefficients({'K': 2.0, 'tau': 1.234, 'T': 5.0})) == \
        pytest.approx(5.0 * 5.0 + 1.234, rel=1e-12)
    # Poles -1 and -4: the slower one sets it.
    second = Model('1/(s**2 + a*s + b)').coefficients({'a': 5.0, 'b': 4.0})
    assert settling_time(second) == pytest.approx(5.0, rel=1e-12)


def test_cost_is_half_the_squared_output_error():
    system = systems.mass_spring_damper()
    data = system.data(seed=1)
    problem = problem_for(system.model, data, system.bounds)
    theta = {'m': 0.6, 'd': 1.5, 'k': 40.0}
    error = data.y - system.model.simulate(theta, data.u, data.ts)
    assert problem.cost(system.model.coefficients(theta)) == \
        pytest.approx(0.5 * error @ error, rel=1e-12)
    clean = problem_for(system.model, Data(system.u, system.noise_free(), system.ts))
    assert clean.cost(system.model.coefficients(system.truth)) <= \
        1e-24 * system.noise_free() @ system.noise_free()


def test_admissible_set_is_the_box_with_a_stable_denominator_of_fixed_leading_sign():
    model = Model('K/(a*s + b)')
    u = prbs(7, 4)
    problem = problem_for(model, Data(u, model.simulate([1.0, 1.0, 2.0], u, 0.1), 0.1),
                          {'K': (0.0, 10.0)})
    assert problem.admissible(np.array([1.0, 1.0, 2.0])) is not None
    assert problem.admissible(np.array([11.0, 1.0, 2.0])) is None        # outside the box
    assert problem.admissible(np.array([1.0, 1.0, -2.0])) is None        # unstable
    flipped = np.array([1.0, -1.0, -2.0])                                # stable, D = -(s + 2)
    assert problem.admissible(flipped) is not None
    problem.anchor(model.coefficients([1.0, 1.0, 2.0]))
    assert problem.admissible(flipped) is None                           # the order would drop


def test_coefficients_whose_squares_underflow_are_not_admissible():
    # The two-mass drive's automatic start drifted to J2, c, k ~ 1e-160, where D ~ 1e-160 and
    # the filters of 1/D^2 underflow: building them raised ModelError out of estimate.
    model = Model('K/(a*s + b)')
    u = prbs(7, 4)
    problem = problem_for(model, Data(u, model.simulate([1.0, 1.0, 2.0], u, 0.1), 0.1))
    assert problem.admissible(np.array([1e-160, 1e-160, 2e-160])) is None
    assert problem.admissible(np.array([1e160, 1e160, 2e160])) is None
    assert problem.admissible(np.array([1e-40, 1e-40, 2e-40])) is not None


def test_coefficients_whose_squares_overflow_are_not_admissible():
    # A two-mass drive's restart reached D = [5e149, 8e150, 3e153, ...]: its leading
    # coefficient within range, D^2's coefficients at 1e301, whose scaling overflowed and
    # raised ModelError out of estimate on noise-free data. No coefficient may pass 1e100.
    model = Model('K/(a*s + b)')
    u = prbs(7, 4)
    problem = problem_for(model, Data(u, model.simulate([1.0, 1.0, 2.0], u, 0.1), 0.1))
    assert problem.admissible(np.array([1e99, 1e99, 2e99])) is not None
    assert problem.admissible(np.array([1e99, 1e99, 2e101])) is None
    assert problem.admissible(np.array([1e99, 1e101, 2e101])) is None


def test_transient_exclusion_drops_the_settling_time_at_most_half_the_record():
    system = systems.first_order_dead_time()               # N = 2550, ts = 0.1
    problem = problem_for(system.model, system.data(seed=1), system.bounds)
    coefficients = system.model.coefficients(system.truth)
    problem.exclude_transient('auto', coefficients)
    assert problem.skip == int(np.ceil((25.0 + 1.234) / 0.1))
    assert problem.measured.size == 2550 - problem.skip
    problem.exclude_transient(1e6, coefficients)
    assert problem.skip == 2550 // 2
    with pytest.raises(ValueError, match='transient'):
        problem.exclude_transient(-1.0, coefficients)


def first_order_away_from_rest(offset):
    model = Model('K/(T*s + 1)')
    truth = {'K': 1.5, 'T': 0.4}
    u = prbs(7, 8)[:400]
    time = 0.01 * np.arange(u.size)
    y = model.simulate(truth, u, 0.01) + 2.0 * np.exp(-time / truth['T']) + offset
    return model, truth, Data(u, y, 0.01)


@pytest.mark.parametrize('offset', [0.0, 4.0])
def test_initial_state_and_offset_are_projected_out_exactly(offset):
    # y = G u + free response of 1/D (+ a constant): with those components fitted the truth
    # leaves no error; without them it does.
    model, truth, data = first_order_away_from_rest(offset)
    coefficients = model.coefficients(truth)
    fitted = problem_for(model, data, initial_state=True, output_offset=bool(offset))
    assert fitted.cost(coefficients) <= 1e-24 * data.y @ data.y
    assert problem_for(model, data).cost(coefficients) > 1e-3 * data.y @ data.y
    # The instruments and regressors are orthogonal to the fitted components.
    lin = fitted.linearize(coefficients)
    columns = nuisance_columns(coefficients.den, len(data), data.ts, True, bool(offset))
    assert columns.shape == (len(data), 1 + bool(offset))
    basis = orthonormal_basis(columns)
    for signals in (lin.psi, lin.phi):
        assert np.max(np.abs(basis.T @ signals)) <= 1e-12 * np.max(np.abs(signals))


def test_nuisance_helpers():
    assert nuisance_columns(np.array([1.0, 2.0]), 10, 0.1, False, False) is None
    assert orthonormal_basis(None) is None
    output = np.arange(5.0)
    assert with_fitted_nuisance(np.ones(5), output, None) is output
    columns = np.column_stack([np.ones(5), np.arange(5.0) * 1e6])
    basis = orthonormal_basis(columns)
    np.testing.assert_allclose(basis.T @ basis, np.eye(2), atol=1e-14)
    # A measured signal in the span is fitted exactly.
    measured = output + 3.0 - 2.0 * np.arange(5.0)
    np.testing.assert_allclose(with_fitted_nuisance(measured, output, basis), measured,
                               atol=1e-12)


def test_delay_bracket():
    system = systems.first_order_dead_time()               # tau in [0, 10]
    data = system.data(seed=1)
    problem = problem_for(system.model, data, system.bounds)
    assert problem.delay_bracket(1, None) == (0.0, 10.0)
    assert problem.delay_bracket(1, (2.0, 20.0)) == (2.0, 10.0)
    with pytest.raises(ModelError, match='delay range'):
        problem.delay_bracket(1, (3.0, 1.0))
    # No upper bound: three times the data's own guess, at least 20 samples beyond it, and at
    # least a twentieth of the record (255 s here).
    unbounded = problem_for(system.model, data)
    guess = prewhitened_delay(data)
    assert unbounded.delay_guess == guess
    assert unbounded.delay_bracket(1, None) == \
        (0.0, pytest.approx(max(3.0 * guess, guess + 2.0, 12.75), rel=1e-15))


@pytest.mark.parametrize('offset,transient', [(False, 0.0), (True, 0.0), (True, 3.0)])
def test_projected_cost_gradient_is_exact_with_an_initial_state(offset, transient):
    # Variable projection: -Psi^T e must be the gradient of the projected cost itself, the
    # derivative of the fitted initial-state response included (docs/algorithm.md section 9).
    model = Model('K/((T1*s + 1)*(T2*s + 1))')
    u = prbs(8, 6)
    rng = np.random.default_rng(3)
    y = model.simulate({'K': 2.0, 'T1': 0.4, 'T2': 1.5}, u, 0.05)
    y = y + 0.7 * np.exp(-np.arange(u.size) * 0.05 / 1.5) + 0.05 * rng.standard_normal(u.size)
    problem = problem_for(model, Data(u, y + 0.3 * offset, 0.05), initial_state=True,
                          output_offset=offset)
    theta = np.array([1.7, 0.5, 1.2])
    coefficients = problem.admissible(theta)
    if transient:
        problem.exclude_transient(transient, coefficients)
    lin = problem.linearize(coefficients)
    gradient = -lin.psi.T @ (problem.measured - lin.output)
    for index in range(3):
        step = 1e-6 * theta[index]
        up, down = theta.copy(), theta.copy()
        up[index] += step
        down[index] -= step
        difference = (problem.cost(problem.admissible(up))
                      - problem.cost(problem.admissible(down))) / (2.0 * step)
        assert gradient[index] == pytest.approx(difference, rel=1e-5, abs=1e-9)


@pytest.mark.parametrize('factory,options', [
    (systems.first_order_dead_time, {}), (systems.rao_garnier, {}),
    (systems.two_lags_dead_time, {'initial_state': True, 'output_offset': True})])
def test_regressors_asked_after_the_instruments_are_those_of_a_whole_linearisation(
        factory, options):
    # The instruments are kept and only phi is added: the values a whole linearisation gives.
    system = factory()
    data = system.data(seed=2)
    theta = system.model.vector(system.truth) * 1.05
    whole = problem_for(system.model, data, **options)
    coefficients = whole.admissible(theta)
    expected = whole.linearize(coefficients)
    problem = problem_for(system.model, data, **options)
    first = problem.linearize(problem.admissible(theta), regressors=False)
    # Equal coefficients, another object: found by their values.
    lin = problem.linearize(problem.admissible(theta))
    assert first.phi is None
    np.testing.assert_array_equal(lin.psi, first.psi)
    assert problem.linearize(problem.admissible(theta), regressors=False) is lin
    np.testing.assert_allclose(lin.phi, expected.phi, rtol=0,
                               atol=1e-12 * np.max(np.abs(expected.phi)))
    np.testing.assert_allclose(lin.psi, expected.psi, rtol=0,
                               atol=1e-12 * np.max(np.abs(expected.psi)))
    # Mapped beside fewer rows (no phi), the output may differ in its last bits: the products
    # of complex modes in real form round per product.
    np.testing.assert_allclose(lin.output, expected.output, rtol=0,
                               atol=1e-12 * np.max(np.abs(expected.output)))


def test_best_state_is_remembered_and_forgotten_when_the_fitted_samples_change():
    system = systems.first_order_dead_time()
    problem = problem_for(system.model, system.data(seed=1))
    assert problem.best is None
    truth = system.model.vector(system.truth)
    far = truth * [1.5, 1.0, 2.0]
    first = problem.state(far, problem.admissible(far))
    assert problem.best is first
    best = problem.state(truth, problem.admissible(truth))
    problem.state(far, problem.admissible(far))
    assert problem.best is best and best.cost < first.cost
    problem.exclude_transient(2.0, best.coefficients)
    assert problem.best is None


def test_lags_and_masses_are_bounded_where_their_pole_leaves_the_sampled_band():
    ts = 0.1
    sopdt = Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))')          # K, tau, T1, T2
    limits = reduction_limits(sopdt, np.array([2.0, 0.3, 1.0, 5.0]), ts)
    assert sorted(limits) == [2, 3]
    assert limits[2] == pytest.approx(ts / (1000.0 * np.pi))
    assert limits[3] == pytest.approx(ts / (1000.0 * np.pi))
    msd = Model('1/(m*s**2 + d*s + k)')
    assert reduction_limits(msd, np.array([0.5, 2.0, 50.0]), ts) == \
        {0: pytest.approx(2.0 * ts / (1000.0 * np.pi))}
    # A monic denominator has no such parameter.
    assert reduction_limits(Model('K*w**2/(s**2 + 2*z*w*s + w**2)'),
                            np.array([1.0, 3.0, 0.2]), ts) == {}
    # The problem applies them unless a bound already keeps the parameter away from zero.
    data = Data(prbs(7, 2), np.linspace(0.0, 1.0, 254), ts)
    problem = problem_for(sopdt, data, {'T2': (0.5, None)})
    theta = problem.limit_reductions(np.array([2.0, 0.3, 1e-6, 5.0]))
    assert problem.reductions == {2: pytest.approx(ts / (1000.0 * np.pi))}
    assert problem.lower[2] == problem.reductions[2] and problem.lower[3] == 0.5
    assert theta[2] == problem.lower[2]
