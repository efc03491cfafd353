"""The controlled projection iteration (docs/algorithm.md sections 5-8)."""

from ctid_ros import Data, Model
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.iteration import (iterate, IterationPolicy, IterationResult, Opening,
                                           optimality, OPTIMALITY_LIMIT, Steps, StopReason)
from ctid_ros.estimation.problem import bound_vectors, Problem, State
import numpy as np
import pytest


def problem_for(model, data, bounds=None):
    lower, upper = bound_vectors(model, bounds)
    return Problem(model, data, lower, upper, 'zoh')


def start_at(problem, values):
    """Return the state at ``values`` with D's leading sign anchored, as the estimator does."""
    theta = problem.model.vector(values)
    coefficients = problem.admissible(theta)
    problem.anchor(coefficients)
    return State(theta, coefficients, problem.cost(coefficients))


def run(problem, state, first_ls=True, full_steps_only=False, frozen=None, **options):
    """Iterate with the policy of ``options`` (and the two openings/steps by name)."""
    settings = {'method': 'iv', 'max_iterations': 100, 'tolerance': 1e-8,
                'opening': Opening.LEAST_SQUARES if first_ls else Opening.PROJECTION,
                'steps': Steps.FULL_ONLY if full_steps_only else Steps.CONTROLLED}
    settings.update(options)
    return iterate(problem, state, IterationPolicy(**settings), frozen)


def noise_free_mass_spring_damper():
    system = systems.mass_spring_damper()
    return system, problem_for(system.model, Data(system.u, system.noise_free(), system.ts),
                               system.bounds)


def test_stop_reasons_read_as_before_and_say_whether_they_converged():
    texts = {reason: reason.describe(1e-8, 100) for reason in StopReason}
    assert texts == {
        StopReason.ALL_AT_BOUNDS: 'all parameters fixed at bounds',
        StopReason.NEGLIGIBLE_UPDATE: 'update below 0.001 standard deviations',
        StopReason.NO_FULL_STEP: 'no full step decreases the cost',
        StopReason.NO_DECREASE: 'no admissible step decreases the cost',
        StopReason.PARAMETER_CHANGE: 'relative parameter change below 1e-08',
        StopReason.COST_DECREASE: 'relative cost decrease below resolution',
        StopReason.EXACT_FIT: 'output reproduced exactly',
        StopReason.ITERATION_LIMIT: 'iteration limit (100) reached',
        StopReason.STALLED: 'stalled: the cost still decreases along its gradient',
        StopReason.SLOW: 'the cost fell too slowly far from a minimum',
    }
    assert {reason for reason in StopReason if not reason.converged} == \
        {StopReason.NO_FULL_STEP, StopReason.ITERATION_LIMIT, StopReason.STALLED,
         StopReason.SLOW}


def test_slow_progress_far_from_a_minimum_gives_up_and_never_near_one():
    # The long dead time 6 s short: damped and fallback updates that hardly lower the cost.
    system = systems.second_order_dead_time()
    problem = problem_for(system.model, system.data(seed=3), system.bounds)
    options = {'max_iterations': 15, 'tolerance': 1e-6, 'check_optimality': True}
    far = start_at(problem, {**system.truth, 'tau': 2.0})
    result = run(problem, far, min_progress=0.01, **options)
    assert result.reason is StopReason.SLOW and not result.converged
    assert result.message == 'the cost fell too slowly far from a minimum'
    assert result.state.cost < far.cost
    for tau in (7.5, 8.0):
        near = start_at(problem, {**system.truth, 'tau': tau})
        given_up = run(problem, near, min_progress=0.01, **options)
        assert given_up.converged
        assert given_up.state.cost == run(problem, near, **options).state.cost


def test_first_least_squares_step_lands_next_to_the_truth_from_far_away():
    # One-step property on noise-free affine data: from a start 4x off in m and 10x in k the
    # least-squares projection is exact up to the O(ts^2) interpolation of y (1e-3 here).
    system, problem = noise_free_mass_spring_damper()
    result = run(problem, start_at(problem, {'m': 2.0, 'd': 0.1, 'k': 5.0}), max_iterations=1)
    assert result.reason is StopReason.ITERATION_LIMIT and not result.converged
    assert result.message == 'iteration limit (1) reached'
    assert [(entry.direction, entry.step) for entry in result.history] == [('ls', 1.0)]
    truth = system.model.vector(system.truth)
    np.testing.assert_allclose(result.state.theta, truth, rtol=1e-3)
    np.testing.assert_array_equal(result.history[0].theta, result.state.theta)


def test_instrumental_variable_iterations_then_reach_the_truth_to_rounding():
    system, problem = noise_free_mass_spring_damper()
    start = start_at(problem, {'m': 2.0, 'd': 0.1, 'k': 5.0})
    result = run(problem, start, tolerance=1e-10)
    assert isinstance(result, IterationResult)
    assert result.reason is StopReason.PARAMETER_CHANGE and result.converged
    assert result.message == 'relative parameter change below 1e-10'
    assert [entry.direction for entry in result.history][:2] == ['ls', 'iv']
    np.testing.assert_allclose(result.state.theta, system.model.vector(system.truth),
                               rtol=1e-12)
    costs = [start.cost] + [entry.cost for entry in result.history]
    assert all(later <= earlier for earlier, later in zip(costs, costs[1:]))
    assert result.state.cost == result.history[-1].cost


def test_output_reproduced_exactly_stops_the_iteration():
    # Numerator parameters only: the least-squares step is exact, the cost becomes zero.
    model = Model('(b1*s + b0)/(s**2 + 3*s + 2)')
    u = prbs(9, 4)
    problem = problem_for(model, Data(u, model.simulate([2.0, 1.0], u, 0.01), 0.01))
    result = run(problem, start_at(problem, [-1.0, 5.0]), tolerance=1e-20)
    assert result.reason is StopReason.EXACT_FIT
    np.testing.assert_allclose(result.state.theta, [2.0, 1.0], rtol=1e-13)


def test_frozen_parameters_keep_their_values():
    system, problem = noise_free_mass_spring_damper()
    frozen = np.array([False, True, False])
    result = run(problem, start_at(problem, {'m': 2.0, 'd': 0.1, 'k': 5.0}), frozen=frozen)
    assert result.converged
    assert all(entry.theta[1] == 0.1 for entry in result.history)
    assert result.state.theta[1] == 0.1


def test_instrumental_variables_and_gauss_newton_reach_the_same_output_error_minimum():
    # On noisy data the IV fixed points are the output-error stationary points: both end
    # where the other does, within the 0.001 standard deviations at which they stop.
    system = systems.mass_spring_damper()
    data = system.data(seed=3)
    ends = {}
    for method in ('iv', 'gn'):
        problem = problem_for(system.model, data, system.bounds)
        result = run(problem, start_at(problem, {'m': 1.0, 'd': 2.0, 'k': 30.0}), method=method)
        assert result.reason is StopReason.NEGLIGIBLE_UPDATE
        assert result.message == 'update below 0.001 standard deviations'
        ends[method] = result.state.theta
    crlb = np.array([system.crlb_std[name] for name in system.model.parameters])
    assert np.all(np.abs(ends['iv'] - ends['gn']) < 2e-3 * crlb)
    assert np.all(np.abs(ends['iv'] - system.model.vector(system.truth)) < 4.0 * crlb)


def test_instrumental_variables_converge_where_gauss_newton_drifts_away():
    # Initial resonance 3.3 rad/s against the true 10 rad/s: Gauss-Newton with the same step
    # control slides to a near-zero-gain plateau with m at its bound, IV reaches the truth.
    system = systems.mass_spring_damper()
    data = system.data(seed=2)
    ends = {}
    for method in ('iv', 'gn'):
        problem = problem_for(system.model, data, system.bounds)
        ends[method] = run(problem, start_at(problem, {'m': 1.47, 'd': 1.01, 'k': 16.0}),
                           method=method).state
    crlb = np.array([system.crlb_std[name] for name in system.model.parameters])
    assert np.all(np.abs(ends['iv'].theta - system.model.vector(system.truth)) < 4.0 * crlb)
    assert ends['gn'].theta[0] > 10.0 and ends['gn'].cost > 10.0 * ends['iv'].cost


def test_bounds_truncate_every_step():
    system = systems.mass_spring_damper()
    bounds = {'m': (0.1, 0.4), 'd': (0.0, 100.0), 'k': (0.0, 1e4)}
    problem = problem_for(system.model, system.data(seed=3), bounds)
    result = run(problem, start_at(problem, {'m': 0.3, 'd': 0.5, 'k': 30.0}))
    assert result.converged
    assert all(0.1 <= entry.theta[0] <= 0.4 for entry in result.history)
    assert result.state.theta[0] == pytest.approx(0.4, abs=1e-6)     # the truth is 0.5


def test_all_parameters_held_by_their_bounds_stop_at_once():
    model = Model('K/(s + 1)')
    u = prbs(8, 4)
    problem = problem_for(model, Data(u, model.simulate([2.0], u, 0.01), 0.01), {'K': (0, 1)})
    result = run(problem, start_at(problem, [1.0]))
    assert result.reason is StopReason.ALL_AT_BOUNDS and result.converged
    assert result.history == []


def test_full_steps_only_gives_up_where_the_iteration_needs_a_shorter_step():
    # From this start neither the full least-squares nor the full Gauss-Newton step is
    # accepted: the quick check gives up at once, the full iteration halves and converges.
    system = systems.mass_spring_damper()
    data = system.data(seed=1)
    start = {'m': 0.112, 'd': 5.325, 'k': 60.519}
    problem = problem_for(system.model, data, system.bounds)
    quick = run(problem, start_at(problem, start), max_iterations=6, full_steps_only=True)
    assert quick.reason is StopReason.NO_FULL_STEP and not quick.converged
    assert quick.history == []
    problem = problem_for(system.model, data, system.bounds)
    full = run(problem, start_at(problem, start))
    assert full.converged
    assert full.history[0].step < 1.0
    crlb = np.array([system.crlb_std[name] for name in system.model.parameters])
    assert np.all(np.abs(full.state.theta - system.model.vector(system.truth)) < 4.0 * crlb)


def first_order_dead_time_on_coarse_samples(tau, seed=0, noise=0.01):
    """Return data of K exp(-tau s)/(T s + 1) sampled every second, T = 0.75 s (coarse)."""
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    truth = {'K': 1.5, 'tau': tau, 'T': 0.75}
    u = prbs(7, 2, 2)
    y = model.simulate(truth, u, 1.0)
    y = y + noise * np.random.default_rng(seed).standard_normal(u.size)
    return model, truth, problem_for(model, Data(u, y, 1.0))


def test_dead_time_leaves_its_lower_bound_when_the_cost_falls_inward():
    # At tau = 0 (a lattice point and the bound) the cost falls for a growing dead time; the
    # derivative for a shrinking one says the opposite and used to hold it there.
    model, truth, problem = first_order_dead_time_on_coarse_samples(0.3)
    start = start_at(problem, {'K': 1.5, 'tau': 0.0, 'T': 0.75})
    result = run(problem, start, first_ls=False, check_optimality=True)
    assert result.converged, result.message
    assert result.state.theta[1] == pytest.approx(0.3, abs=0.01)
    assert optimality(problem, result.state, np.zeros(3, dtype=bool)) < OPTIMALITY_LIMIT


def test_a_kink_between_two_basins_is_left_to_the_lower_one():
    # The true dead time is just below two samples; from exactly two samples the cost falls
    # both ways (a concave kink), much more steeply towards the truth.
    model, truth, problem = first_order_dead_time_on_coarse_samples(1.99)
    start = start_at(problem, {'K': 1.4, 'tau': 2.0, 'T': 0.7})
    result = run(problem, start, first_ls=False, check_optimality=True)
    assert result.state.theta[1] == pytest.approx(1.99, abs=0.005)
    assert result.converged


def test_a_point_the_iteration_cannot_leave_but_that_is_no_minimum_is_stalled():
    # Data from an unstable oscillator: the cost keeps falling towards a1 < 0, beyond the
    # stable models the estimator admits. That boundary is no minimum: not converged.
    model = Model('b/(s**2 + a1*s + a0)')
    u = prbs(6, 5)[:200]
    data = Data(u, model.simulate({'b': 1.0, 'a1': -0.1, 'a0': 4.0}, u, 0.05), 0.05)
    problem = problem_for(model, data)
    result = run(problem, start_at(problem, {'b': 1.0, 'a1': 1.0, 'a0': 4.0}),
                 check_optimality=True)
    assert result.reason is StopReason.STALLED and not result.converged
    assert 0.0 < result.state.theta[1] < 1e-3
    assert optimality(problem, result.state, np.zeros(3, dtype=bool)) > OPTIMALITY_LIMIT
    # Without the test the same point passed as converged.
    unchecked = run(problem, start_at(problem, {'b': 1.0, 'a1': 1.0, 'a0': 4.0}))
    assert unchecked.converged


def test_after_a_gauss_newton_rescue_its_step_goes_first_without_the_regressors():
    # The long dead time from 0.3-17 times its true values: far from the minimum the IV step
    # is refused and the full Gauss-Newton step taken, the cost falling by a tenth or more;
    # the next update then linearises without the regressors (no filtering of y through 1/D)
    # and takes that step again first. The run still ends at the minimum a run from the truth
    # reaches.
    system = systems.second_order_dead_time()
    problem = problem_for(system.model, system.data(seed=1001), system.bounds)
    start = start_at(problem, {'b0': 5.0448, 'tau': 5.6201, 'a1': 18.0911, 'a0': 2.633})
    first_asked = {}
    linearize = problem.linearize

    def recorded(coefficients, regressors=True):
        first_asked.setdefault(coefficients.den.tobytes(), regressors)
        return linearize(coefficients, regressors)

    problem.linearize = recorded
    result = run(problem, start, first_ls=False, tolerance=1e-6, check_optimality=True)
    history = result.history
    costs = [start.cost] + [update.cost for update in history]
    # Two full Gauss-Newton updates in a row, each lowering the cost by a tenth or more: the
    # point between them was linearised without the regressors first.
    between = [history[index].theta for index in range(len(history) - 1)
               if all(history[later].direction == 'gn' and history[later].step == 1.0 and
                      costs[later + 1] <= 0.9 * costs[later] for later in (index, index + 1))]
    assert between
    for theta in between:
        den = problem.model.coefficients(theta).den.tobytes()
        assert first_asked[den] is False
    assert result.converged
    assert optimality(problem, result.state, np.zeros(4, dtype=bool)) < OPTIMALITY_LIMIT
    near = problem_for(system.model, system.data(seed=1001), system.bounds)
    reference = run(near, start_at(near, system.truth), first_ls=False, tolerance=1e-6,
                    check_optimality=True)
    assert result.state.cost == pytest.approx(reference.state.cost, rel=1e-9)
    assert np.allclose(result.state.theta, reference.state.theta, rtol=1e-4)
