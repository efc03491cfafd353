"""Equation-error starts and the warm-start check (docs/algorithm.md sections 10 and 11)."""

import gc
import threading
import weakref

from ctid_ros import Data, estimate, EstimationError, Model, ModelError
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.iteration import StopReason
from ctid_ros.estimation.problem import bound_vectors, Problem, State
from ctid_ros.estimation.starts import (best_candidate, complete_guess, default_filters,
                                        distinct, equation_error_fits, explains_data,
                                        filter_bandwidths,
                                        FILTER_COUNT, initial_estimate,
                                        local_fit, resembles_output, stabilized,
                                        StateVariableFilters)
import numpy as np
import pytest


def problem_for(model, data, bounds=None):
    lower, upper = bound_vectors(model, bounds)
    return Problem(model, data, lower, upper, 'zoh')


def state_at(problem, values):
    theta = problem.model.vector(values)
    coefficients = problem.admissible(theta)
    return State(theta, coefficients, problem.cost(coefficients))


def crlb(system):
    return np.array([system.crlb_std[name] for name in system.model.parameters])


@pytest.mark.parametrize('factory, tolerance', [
    (systems.mass_spring_damper, 1e-3), (systems.closed_loop_pid, 1e-3),
    (systems.second_order_nonaffine, 1e-3), (systems.rao_garnier, 5e-3),
])
def test_automatic_start_on_noise_free_data_is_next_to_the_truth(factory, tolerance):
    # The equation error D y - N u filtered by 1/E is linear in the coefficients and zero at
    # the truth; only the interpolation of y between samples (O(ts^2)) separates the fit from
    # it. The non-affine structure is fitted by its local solver from the default hint.
    system = factory()
    problem = problem_for(system.model, Data(system.u, system.noise_free(), system.ts),
                          system.bounds)
    start = initial_estimate(problem, 'auto', None)
    np.testing.assert_allclose(start.theta, system.model.vector(system.truth), rtol=tolerance)
    assert start.cost == problem.cost(start.coefficients)


def test_automatic_start_of_a_symmetric_non_affine_model():
    model = Model('K/((T1*s + 1)*(T2*s + 1))')
    u = prbs(9, 5)
    data = Data(u, model.simulate({'K': 1.5, 'T1': 0.3, 'T2': 2.0}, u, 0.02), 0.02)
    problem = problem_for(model, data, {'T1': (1e-3, None), 'T2': (1e-3, None)})
    theta = initial_estimate(problem, 'auto', None).theta
    assert theta[0] == pytest.approx(1.5, rel=1e-4)
    assert sorted(theta[1:]) == pytest.approx([0.3, 2.0], rel=1e-3)


def test_partial_initial_values_are_pinned_and_the_rest_fitted():
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, system.data(seed=2), system.bounds)
    start = initial_estimate(problem, {'m': 0.7}, None)
    assert start.theta[0] == 0.7
    assert np.all(np.isfinite(start.theta)) and start.cost < np.inf


@pytest.mark.parametrize('initial, fragment', [
    ({'mass': 1.0}, 'unknown parameter'), ({'m': 500.0}, 'outside its bounds'),
    ({'m': np.nan}, 'not finite'), ('best', "'auto'"),
])
def test_initial_values_are_checked(initial, fragment):
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, system.data(seed=2), system.bounds)
    with pytest.raises(ModelError, match=fragment):
        initial_estimate(problem, initial, None)


def test_no_stable_start_is_an_estimation_error():
    # d and k pinned negative: no positive m makes m s^2 + d s + k Hurwitz.
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, system.data(seed=2), {'m': (1e-3, 100.0)})
    with pytest.raises(EstimationError, match='no stable starting model'):
        initial_estimate(problem, {'d': -1.0, 'k': -5.0}, None)


def test_without_the_starts_as_given_the_best_equation_error_fit_is_returned():
    # On a noisy record the truth as a complete guess costs less than the equation-error fits
    # (the noise biases them): as given it wins. A caller that asks for the data's own guess
    # (a warm start's check) gets the best fit instead.
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, system.data(seed=0), system.bounds)
    truth = system.model.vector(system.truth)
    given = initial_estimate(problem, system.truth, None)
    fitted = initial_estimate(problem, system.truth, None, as_given=False)
    np.testing.assert_array_equal(given.theta, truth)
    assert not np.array_equal(fitted.theta, truth)
    assert fitted.cost > 3.0 * given.cost
    assert fitted.cost == problem.cost(fitted.coefficients)


def test_complete_guess_is_a_state_only_if_complete_and_admissible():
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, system.data(seed=2), system.bounds)
    assert complete_guess(problem, 'auto') is None
    assert complete_guess(problem, {'m': 0.5, 'd': 1.0}) is None
    assert complete_guess(problem, {'m': 0.5, 'd': -1.0, 'k': 50.0}) is None   # unstable
    state = complete_guess(problem, {'m': 0.5, 'd': 1.0, 'k': 50.0})
    np.testing.assert_array_equal(state.theta, [0.5, 1.0, 50.0])
    assert state.cost == problem.cost(system.model.coefficients(state.theta))


def test_best_candidate_skips_inadmissible_ones_and_distinct_drops_repeats():
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, system.data(seed=2), system.bounds)
    candidates = [np.array([0.5, -1.0, 50.0]), np.array([0.8, 1.0, 40.0]),
                  np.array([0.5, 1.0, 50.0]), np.array([0.5, 1.0, 50.0 * (1 + 1e-9)])]
    best = best_candidate(problem, candidates)
    np.testing.assert_array_equal(best.theta, [0.5, 1.0, 50.0])
    assert best_candidate(problem, candidates[:1]) is None
    assert len(distinct(candidates)) == 3


def test_best_candidate_scores_a_model_seen_before_once():
    # Two lags swapped are one model: with the models seen so far, the twin is not simulated
    # again, and a model seen in an earlier call is not a candidate of this one.
    system = systems.two_lags_dead_time()
    problem = problem_for(system.model, system.data(seed=2), system.bounds)
    theta = system.model.vector(system.truth)
    twin = theta.copy()
    twin[2:] = theta[[3, 2]]
    assert not np.array_equal(twin, theta)
    seen = []
    best = best_candidate(problem, [twin, theta], seen)
    np.testing.assert_array_equal(best.theta, twin)
    assert len(seen) == 1
    assert best_candidate(problem, [theta], seen) is None
    assert best_candidate(problem, [theta]).cost == pytest.approx(best.cost, rel=1e-12)


def test_an_equation_error_fit_holds_a_collapsing_lag_on_its_bound():
    # A first-order plant fitted with two lags: one lag collapses to its lower bound. Held
    # there, the other parameters converge from any start to the one bounded minimum of each
    # filter (a projected step that moved the lag too crept along the bound instead).
    model = Model('K/((T1*s + 1)*(T2*s + 1))')
    u = prbs(9, 5)
    data = Data(u, Model('K/(T*s + 1)').simulate({'K': 1.5, 'T': 0.5}, u, 0.02), 0.02)
    problem = problem_for(model, data, {'T1': (1e-3, None), 'T2': (1e-3, None)})
    filters = default_filters(problem)
    free = np.ones(3, dtype=bool)
    fits = [equation_error_fits(problem, [np.array(start)], free, 0.0, filters)
            for start in ([1.0, 2.0, 0.05], [3.0, 0.1, 5.0])]
    for first, second in zip(*fits):
        assert min(first[1:]) == 1e-3 and min(second[1:]) == 1e-3
        np.testing.assert_allclose(sorted(first), sorted(second), rtol=1e-6)
        assert first[0] == pytest.approx(1.5, rel=0.02)
        assert max(first[1:]) == pytest.approx(0.5, rel=0.02)


def test_filters_span_ten_periods_per_record_to_three_tenths_of_nyquist():
    data = systems.first_order_dead_time().data(seed=1)              # 2550 samples of 0.1 s
    corners = filter_bandwidths(data, 3)
    np.testing.assert_allclose(corners[[0, -1]], [10.0 / 255.0, 0.3 * np.pi / 0.1],
                               rtol=1e-14)
    assert corners[1] == pytest.approx(np.sqrt(corners[0] * corners[2]), rel=1e-14)


def test_whole_sample_dead_time_shortcut_matches_direct_filtering():
    # On the sample lattice the filtered input is a shift of one undelayed filtering; just off
    # it the input is filtered with the fractional delay. Both give the same normal equations.
    system = systems.first_order_dead_time()
    problem = problem_for(system.model, system.data(seed=3), system.bounds)
    filters = StateVariableFilters(problem, filter_bandwidths(problem.data, 3))
    assert filters.count == 3 and filters.select(1).count == 1
    for on, off in zip(filters.factors(1.2), filters.factors(1.2 + 1e-8)):
        gram_on, gram_off = on.T @ on, off.T @ off
        assert np.max(np.abs(gram_on - gram_off)) < 1e-7 * np.max(np.abs(gram_on))


def test_factors_of_problems_taking_turns_in_a_thread_are_those_of_a_fresh_thread():
    # Two records of one length share the thread's columns buffers (the same filters): each
    # problem's factors must be formed from its own output parts, however they take turns.
    system = systems.first_order_dead_time()
    problems = [problem_for(system.model, system.data(seed=seed), system.bounds)
                for seed in (3, 4)]
    turns = [(0, 1.2), (1, 1.2), (0, 0.7), (1, 2.35), (0, 2.35), (0, 0.0)]
    filters = [StateVariableFilters(problem, filter_bandwidths(problem.data, 3))
               for problem in problems]
    taking_turns = [filters[index].factors(tau) for index, tau in turns]
    alone = {}

    def fresh(index):
        # A new thread starts without buffers; each problem's filters are formed anew.
        own = StateVariableFilters(problems[index], filter_bandwidths(problems[index].data, 3))
        alone[index] = [own.factors(tau) for other, tau in turns if other == index]

    for index in (0, 1):
        thread = threading.Thread(target=fresh, args=(index,))
        thread.start()
        thread.join()
    expected = iter(alone[0]), iter(alone[1])
    for (index, _), factors in zip(turns, taking_turns):
        for got, want in zip(factors, next(expected[index])):
            np.testing.assert_array_equal(got, want)
    # The records differ, so the turns did not just repeat one problem's factors.
    assert not np.array_equal(taking_turns[0][0], taking_turns[1][0])


@pytest.mark.parametrize('seed', range(3, 8))
def test_residual_test_accepts_the_truth_and_rejects_a_dead_time_two_samples_off(seed):
    system = systems.first_order_dead_time()
    problem = problem_for(system.model, system.data(seed=seed), system.bounds)
    tau = system.model.parameters.index('tau')
    truth = dict(system.truth)
    assert explains_data(problem, state_at(problem, truth), tau, None)
    for wrong in (1.0, 1.5):
        assert not explains_data(problem, state_at(problem, {**truth, 'tau': wrong}), tau, None)


def test_local_fit_from_a_warm_start_converges_near_the_truth():
    system = systems.first_order_dead_time()
    problem = problem_for(system.model, system.data(seed=8), system.bounds)
    start = state_at(problem, {'K': 2.2, 'T': 4.5, 'tau': 1.3})
    problem.anchor(start.coefficients)
    result = local_fit(problem, start, 'iv', first_ls=True, full_steps_only=True, iterations=6)
    assert result.reason is not StopReason.NO_FULL_STEP and result.converged
    assert np.all(np.abs(result.state.theta - system.model.vector(system.truth))
                  < 4.0 * crlb(system))
    assert explains_data(problem, result.state, system.model.parameters.index('tau'), None)


def test_a_dead_time_far_off_leaves_an_output_that_does_not_resemble_the_measured_one():
    # The long dead time of 8 s: its output, uncorrelated with a model 6 s early, explains none
    # of the measured output at any scale; a tenfold gain or a 0.5 s error does not matter.
    system = systems.second_order_dead_time()
    problem = problem_for(system.model, system.data(seed=3), system.bounds)
    truth = dict(system.truth)
    assert resembles_output(problem, state_at(problem, truth))
    assert resembles_output(problem, state_at(problem, {**truth, 'b0': 120.0, 'tau': 7.5}))
    assert not resembles_output(problem, state_at(problem, {**truth, 'tau': 2.0}))


def test_an_unstable_fit_is_mirrored_into_a_stable_start():
    model = Model('(b1*s + b0)/(s**3 + a2*s**2 + a1*s + a0)')
    problem = problem_for(model, Data(prbs(7, 2), np.zeros(254), 0.1))
    # D = (s - 1)(s + 2)(s + 3): one root in the right half plane.
    theta = model.vector({'b1': 1.0, 'b0': 2.0, 'a2': 4.0, 'a1': 1.0, 'a0': -6.0})
    free = np.ones(theta.size, dtype=bool)
    mirrored = stabilized(problem, theta, free)
    roots = np.sort(np.roots(model.coefficients(mirrored).den).real)
    np.testing.assert_allclose(roots, [-3.0, -2.0, -1.0 - 3e-3], rtol=1e-9)
    assert problem.admissible(mirrored) is not None
    # The numerator is untouched.
    assert mirrored[0] == 1.0 and mirrored[1] == 2.0


def test_the_cached_default_filters_let_their_problem_be_collected():
    # The cache is keyed weakly by the problem; a value that referred to its problem kept
    # every window's problem (and its data) alive in a live run (issue 25).
    system = systems.mass_spring_damper()
    problem = problem_for(system.model, Data(system.u, system.noise_free(), system.ts))
    filters = default_filters(problem)
    assert default_filters(problem) is filters and filters.count == FILTER_COUNT
    factors = filters.factors(0.0)
    alive = weakref.ref(problem)
    del problem
    gc.collect()
    assert alive() is None
    # The filters taken out still work without the problem.
    np.testing.assert_array_equal(filters.factors(0.0)[0], factors[0])


def test_a_negative_dead_time_factor_is_that_of_zero_filled_inputs():
    # StateVariableFilters is public: a dead time below zero shifts the inputs the other way,
    # their tail zeros (as the shifted copy did), rather than failing to broadcast.
    system = systems.first_order_dead_time()
    problem = problem_for(system.model, system.data(seed=3), system.bounds)
    filters = StateVariableFilters(problem, filter_bandwidths(problem.data, 3))
    ahead = filters.factors(-0.02)
    assert len(ahead) == filters.count
    assert all(np.isfinite(factor).all() for factor in ahead)


def test_an_equation_error_fit_that_shrinks_every_coefficient_to_zero_is_no_start():
    # A two-mass drive has no coefficient that no parameter moves: the equation error
    # R [den; num] vanishes as J2, c, k -> 0, and the automatic start slid there (J2, c, k
    # ~ -1e-34, a pure inertia 1/(J1 s) with a negative leading coefficient), which then
    # anchored the sign of D and bounded J2 below zero: the estimate ended at a fit of 5 %.
    model = Model('(J2*s**2 + c*s + k)/(J1*J2*s**3 + (J1 + J2)*c*s**2 + (J1 + J2)*k*s)')
    truth = {'J1': 0.01, 'J2': 0.02, 'c': 0.02, 'k': 20.0}
    u = np.random.default_rng(0).choice([-1.0, 1.0], 2001).repeat(2)[:4000]
    clean = model.simulate(truth, u, 0.002)
    noise = np.std(clean) / 10 ** 1.5 * np.random.default_rng(100).standard_normal(u.size)
    result = estimate(model, Data(u, clean + noise, 0.002))
    assert result.converged
    for name, value in truth.items():
        assert abs(result.params[name] - value) < 3 * result.std[name]


def _two_mass_drive():
    """Return the two-mass drive's motor speed model and its true values."""
    model = Model('(J2*s**2 + c*s + k)/(J1*J2*s**3 + (J1 + J2)*c*s**2 + (J1 + J2)*k*s)')
    return model, {'J1': 0.01, 'J2': 0.02, 'c': 0.02, 'k': 20.0}


def test_a_positive_bound_does_not_stop_a_two_mass_drives_start_in_a_wrong_basin():
    # With every parameter bounded below by 1e-6 the slide of |R [den; num]| towards its
    # trivial zero stopped at the bound (J1 = 4.6e-6, c 5, k 3.9: a fit of 5 %), where no fit
    # collapses. The scale-free |R c| / |c| of a structure with no fixed coefficient cannot
    # gain by shrinking c, bounds or not.
    model, truth = _two_mass_drive()
    u = prbs(11, 2)[:4000]
    clean = model.simulate(truth, u, 0.002)
    noise = np.std(clean) / 10 ** 1.25 * np.random.default_rng(1000).standard_normal(u.size)
    result = estimate(model, Data(u, clean + noise, 0.002),
                      bounds={name: (1e-6, None) for name in truth})
    assert result.converged
    for name, value in truth.items():
        assert abs(result.params[name] - value) < 0.05 * value


def test_a_scale_free_start_that_runs_off_to_a_limit_of_the_structure_is_no_start():
    # |R c| / |c| can fall towards a limit of the structure instead (J2 -> 1e148, the load's
    # inertia infinite): such a fit made a restart's linearisation raise ModelError ('roots
    # too many decades apart') on valid, noise-free data.
    model, truth = _two_mass_drive()
    u = np.random.default_rng(0).choice([-1.0, 1.0], 4001).repeat(2)[:8000]
    result = estimate(model, Data(u, model.simulate(truth, u, 0.002), 0.002))
    assert result.converged
    for name, value in truth.items():
        assert abs(result.params[name] - value) < 1e-3 * value
