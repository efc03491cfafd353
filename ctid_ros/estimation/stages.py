"""
The stages of :func:`~ctid_ros.estimation.estimate.estimate`, in the order it runs them.

Each stage takes what the previous ones produced and returns a new value: a :class:`Start`
(where the final iteration begins and what led there) or a :class:`Fit` (the latest result and
every accepted update so far); none extends a shared history. Every iteration a stage runs is
described by one :class:`~ctid_ros.estimation.iteration.IterationPolicy`. The pipeline
(``docs/algorithm.md`` section 1 lists it with the systems each stage is there for):

1. :func:`warm_start`: a complete guess, checked by a few full steps and a short local
   optimisation; kept if its model explains the data and (:func:`against_the_data_guess`)
   the data's own guess reaches no lower basin.
2. :func:`automatic_start`: otherwise the equation-error start, the dead-time search and the
   nested structures.
3. :func:`final_iteration`: the controlled iteration to convergence, then the best point seen.
4. :func:`symmetry_restarts`: a point where interchangeable parameters coincide is perturbed.
5. :func:`look_elsewhere` and :func:`other_side_of_the_sample`: for automatic searches only, other
   basins when the residual is not white, and the dead time's twin across a sample.

The one change these stages make to the :class:`~ctid_ros.estimation.problem.Problem` is
:func:`prepared` (the sign anchor of ``D``, the order-reduction bounds, the transient left
out), before the start is iterated; the problem also remembers the best point it evaluated
(:attr:`Problem.best`), which :func:`from_best_seen` reads.
"""

from dataclasses import dataclass, replace
from typing import Dict, List, Optional, Sequence, Tuple, Union

from ctid_ros.errors import EstimationError, ModelError
from ctid_ros.estimation.delay_search import (across_the_sample as mirrored_delay, delay_search,
                                              neighbouring_delays)
from ctid_ros.estimation.identifiability import (blind_combination, BlindCombination,
                                                 Sensitivities)
from ctid_ros.estimation.iteration import (iterate, Iteration, IterationPolicy, IterationResult,
                                           Opening, StopReason)
from ctid_ros.estimation.problem import DelayRange, Problem, State
from ctid_ros.estimation.residual_analysis import ResidualAnalysis
from ctid_ros.estimation.starts import (complete_guess, explains_data, Initial,
                                        initial_estimate, local_fit, random_starts,
                                        resembles_output)
import numpy as np
from scipy import special

__all__ = [
    'Fit', 'Start', 'against_the_data_basin', 'against_the_data_guess', 'automatic_start',
    'final_iteration',
    'from_best_seen', 'look_elsewhere', 'onto_the_sample', 'other_side_of_the_sample',
    'prepared', 'symmetry_restarts', 'warm_start',
]

_SYMMETRY_RESTARTS = 3
# Random perturbations tried at a point where symmetric parameters coincide.
_NUDGES = 14
# Full steps from a complete guess before its residual is tested. Fewer leave more good guesses
# unconverged, which then pay for the automatic start and search; more only delay the search
# for a guess that cannot explain the data.
_WARM_START_ITERATIONS = 6
# Updates of the local optimisation from a complete guess that the full steps left unconverged
# (least_squares LM needs 8-15 Jacobians from such starts).
_WARM_START_BUDGET = 15
# The local optimisation gives up when its cost fell by less than this share over two updates
# far from a minimum.
_WARM_START_PROGRESS = 0.01
# A warm start gives way to the data's guess when that reaches a cost lower by this share: below
# it the two are the same basin up to unfinished digits (the requirement is 0.5 %).
_SAME_BASIN = 1e-3
# A warm start whose guess the data cannot tell from its end at this significance (its cost
# rise in noise units against twice a chi-square with as many degrees of freedom as
# parameters) came from the same basin: the data's guess is not computed for it.
_SAME_PLACE = 1e-3
# A warm end whose dead time lies this close (in samples) to a sample instant sits on the
# cost's kink there (the 48 two-lag records: 0.0007 and 0.008 of a sample; ends elsewhere
# 0.06-0.49); its twin across the instant is tried.
_ON_THE_KINK = 0.05
# Iterations that fit a nested structure without a dead time to search.
_NESTED_ITERATIONS = 10
# Output-error updates from each random draw when the residual says the model misses dynamics.
_ELSEWHERE = IterationPolicy(max_iterations=20)


@dataclass(frozen=True)
class Start:
    """
    Where the final iteration begins, and what led there.

    Attributes
    ----------
    state : State
        The start of the final iteration.
    history : tuple of Iteration
        The updates that led to it.
    opening : Opening
        How the final iteration takes its first update: least squares from an unrefined
        automatic start, Gauss-Newton near a warm start that explained the data.
    from_initial : bool
        True if the user's complete guess explained the data (``Estimate.start ==
        'initial'``): no automatic start, search or look elsewhere.
    settled : bool
        The warm start already ended where the next update is below
        ``iteration.NEGLIGIBLE_STEP`` standard deviations: the final iteration's first test.
    profile : tuple of (tau, cost)
        The dead-time profile, if the search ran one.
    guess_cost : float
        The cost of the complete guess a warm start began from (infinite otherwise).
    from_afar : bool
        A warm start whose guess the data tell from its end (:func:`_came_from_far`): its
        final fit is checked again (:func:`against_the_data_basin`).
    data_guess : State or None
        The data's own guess a warm start from afar was compared with.

    """

    state: State
    history: Tuple[Iteration, ...] = ()
    opening: Opening = Opening.PROJECTION
    from_initial: bool = False
    settled: bool = False
    profile: Tuple[Tuple[float, float], ...] = ()
    guess_cost: float = np.inf
    from_afar: bool = False
    data_guess: Optional[State] = None


@dataclass(frozen=True)
class Fit:
    """The latest result of the pipeline and every accepted update that led to it."""

    result: IterationResult
    history: Tuple[Iteration, ...] = ()

    @property
    def state(self) -> State:
        """Return the state of the latest result."""
        return self.result.state

    def extended(self, updates: Sequence[Iteration],
                 result: Optional[IterationResult] = None) -> 'Fit':
        """Return the fit with ``updates`` appended and ``result`` (default the same) latest."""
        return Fit(self.result if result is None else result, self.history + tuple(updates))


def prepared(problem: Problem, start: State, transient: Union[float, str]) -> State:
    """
    Prepare the problem at ``start`` and return the start, moved into the box if need be.

    Anchors the sign of D's leading coefficient, bounds parameters whose zero would drop the
    order of D (:meth:`Problem.limit_reductions`) and leaves out the transient: the only
    stage that changes the problem (``docs/algorithm.md`` sections 7 and 9).
    """
    problem.anchor(start.coefficients)
    theta = problem.limit_reductions(start.theta)
    if (theta == start.theta).all() and not transient:
        return start
    coefficients = problem.admissible(theta)
    if coefficients is None:
        theta, coefficients = start.theta, start.coefficients
    if transient:
        problem.exclude_transient(transient, coefficients)
    return problem.state(theta, coefficients)


def warm_start(problem: Problem, initial: Initial, transient: Union[float, str], method: str,
               delay_index: Optional[int], delay_range: DelayRange) -> Optional[Start]:
    """
    Start from a complete guess if its model explains the data, else None (stage 1).

    At most :data:`_WARM_START_ITERATIONS` full steps first; if they do not reach a model that
    explains the data, the controlled iteration goes on from there (line search and fallbacks,
    at most :data:`_WARM_START_BUDGET` updates, given up when the cost stops falling far from a
    minimum). The guess is kept if a convergence test stopped it and its residual is
    independent of the input (:func:`~ctid_ros.estimation.starts.explains_data`); it is
    settled if the update from its end is below ``iteration.NEGLIGIBLE_STEP`` standard
    deviations (:attr:`StopReason.NEGLIGIBLE_UPDATE`, the test the final iteration would start
    with). A dead-time model whose output does not resemble the measured one
    (:func:`~ctid_ros.estimation.starts.resembles_output`: a dead time far off) is tried with
    the data's own dead-time guess instead (:attr:`Problem.delay_guess`); if that does not
    resemble it either, the automatic start takes over at once (``docs/algorithm.md``
    section 11).

    Evidence: the live node warm-starts every update from the previous estimate; from x10
    starts of ``bench/estimator.py`` 71 of 100 two-lags-plus-dead-time starts skip the search
    with it (median 31 -> 17-20 ms), 91 of the first order plus dead time, 89 of the
    non-affine second order.
    """
    guess = complete_guess(problem, initial)
    if guess is None:
        return None
    guess = prepared(problem, guess, transient)
    state, history, settled = _checked_guess(problem, guess, method, delay_index, delay_range)
    if history is None:
        return None
    return Start(state, tuple(history), Opening.NEAR_MINIMUM, from_initial=True, settled=settled,
                 guess_cost=guess.cost)


def against_the_data_guess(problem: Problem, start: Start, delay_index: Optional[int],
                           delay_range: DelayRange) -> Optional[Start]:
    """
    Keep a warm start only if no cheap look elsewhere finds a lower basin (stage 1b).

    A complete guess that ends where its residual is independent of the input can still sit in
    a worse basin: with a short or noisy record the independence test cannot tell a basin a
    few per cent above the best one from it (a dead time traded for a lag, the twin of a
    minimum a sample away). Two cheap looks. For a dead-time model, the dead times one sample
    either side of the warm end, screened by one linearised update each and refitted only if
    the screen comes near (:func:`~ctid_ros.estimation.delay_search.neighbouring_delays`).
    Then, unless the guess and the warm end are the same place to the data
    (:func:`_came_from_far`: a node's warm start from the previous window's estimate), the
    guess the automatic start makes from the data alone
    (:func:`~ctid_ros.estimation.starts.initial_estimate` without hints), at its own cost: its
    best equation-error fit (the all-ones vector and the random draws it starts from compete
    as given only where no fit is admissible; as given they came nowhere near a warm end). If
    either is below the warm end's cost by more than :data:`_SAME_BASIN`, None: the automatic
    start and search run as if the warm start had not explained the data (every point seen,
    the screened neighbours too, stays a candidate, section 8). Otherwise the warm start
    stands. ``delay_index``: the dead time's parameter
    (:func:`~ctid_ros.estimation.problem.delay_parameter`), None for a model without one.

    Evidence: FOPDT fits of a two-lag plant with a dead time on 400 samples (AR(1) noise, SNR
    1, ``test_stages.py``): from ``K=1, tau=0, T=1`` the warm start ended 1.5 % above the
    automatic estimate, from 1.3 times that estimate 1.1 % above, both reported converged with
    no warning; the neighbour a sample away lies 1-1.5 % below both. Issue 24 saw the same on a
    drone's pitch loop (+2.4 %) and on the node's warm start (+3.8 %).
    """
    warm_cost = start.state.cost
    if delay_index is not None:
        neighbour = neighbouring_delays(problem, start.state, delay_index, delay_range)
        if neighbour is not None and neighbour.state.cost < (1.0 - _SAME_BASIN) * warm_cost:
            return None
    if not _came_from_far(problem, start):
        return start
    try:
        guess = initial_estimate(problem, 'auto', delay_range, as_given=False)
    except (EstimationError, ModelError):
        return start
    if guess.cost < (1.0 - _SAME_BASIN) * warm_cost:
        return None
    return replace(start, from_afar=True, data_guess=guess)


def against_the_data_basin(problem: Problem, fit: Fit, start: Start, policy: IterationPolicy,
                           delay_index: Optional[int], delay_range: DelayRange
                           ) -> Tuple[Fit, bool]:
    """
    Check a warm start's final fit from afar once more (stage 3b).

    Returns the fit and whether it is still the user's start's.

    :func:`against_the_data_guess` compares points before either is iterated. For a warm start
    from afar (:attr:`Start.from_afar`: not the node's warm start from the previous window,
    which :func:`_came_from_far` leaves out) two more looks after the final iteration:

    * the dead time's twin across the nearest sample instant
      (:func:`other_side_of_the_sample`, as after an automatic start) if the dead time ended
      within :data:`_ON_THE_KINK` of a sample from it: the cost has a kink there, the
      iteration sees one side at a time and parks on it, and the other side is a basin of
      its own. A smooth minimum between the instants passed the first-order test, and its
      neighbours a sample away were screened already (:func:`against_the_data_guess`);
    * the data's guess (:attr:`Start.data_guess`, already computed): if its cost is below the
      final fit's by more than :data:`_SAME_BASIN`, the final iteration goes on from it and
      the lower end wins (then the fit is no longer the user's start's: False). So the fit
      never ends above the guess, let alone in a basin 0.5 % above it.

    A start that did not come from afar is left as it is.

    Evidence: the 48 two-lag records of ``test_stages.py`` from ``K=1, tau=0, T=1`` and from
    1.3 times the automatic estimate: seed 13 from 1.3 times ended 0.60 % above the automatic
    estimate (dead time 0.200 against 0.190 s, the twin across a sample), reported converged;
    the data's guess itself (cost 25.2 against 20.8) could not tell.
    """
    if not start.from_afar:
        return fit, start.from_initial
    if delay_index is not None and _on_a_kink(problem, fit.state, delay_index):
        fit = other_side_of_the_sample(problem, fit, policy, delay_index, delay_range)
    guess = start.data_guess
    if guess is None or guess.cost >= (1.0 - _SAME_BASIN) * fit.state.cost:
        return fit, start.from_initial
    rival = final_iteration(problem, Start(guess, opening=Opening.LEAST_SQUARES), policy)
    rival = other_side_of_the_sample(problem, rival, policy, delay_index, delay_range)
    if rival.state.cost < fit.state.cost:
        return Fit(rival.result, fit.history + rival.history), False
    return fit, start.from_initial


def _on_a_kink(problem: Problem, state: State, delay_index: int) -> bool:
    """Return True if the dead time lies within :data:`_ON_THE_KINK` samples of the lattice."""
    tau = state.theta[delay_index]
    return bool(abs(tau - problem.on_delay_lattice(tau)) < _ON_THE_KINK * problem.data.ts)


def _came_from_far(problem: Problem, start: Start) -> bool:
    """
    Return True unless the data cannot tell the warm start's guess from its end.

    The cost the guess adds above the end, in units of the noise variance the end leaves
    (``2 (J_guess - J_end) / sigma^2``, ``sigma^2 = 2 J_end / (N - p)``), is about
    ``|Psi (theta_guess - theta_end)|^2 / sigma^2``: for the estimate of an independent
    record of the same plant (the node's previous window) twice a chi-square with ``p``
    degrees of freedom. Below the bound that exceeds with probability :data:`_SAME_PLACE`
    the guess was an estimate of the same basin already, and the data's own guess was
    checked when that one was made (the first window, or a start from afar). A coloured
    noise widens the true spread of the estimates beyond this white bound: the check then
    runs more often, never less.
    """
    count = start.state.theta.size
    samples = problem.measured.size
    if not np.isfinite(start.guess_cost) or samples <= count or start.state.cost <= 0.0:
        return True
    variance = 2.0 * start.state.cost / (samples - count)
    rise = 2.0 * (start.guess_cost - start.state.cost) / variance
    return bool(rise > 2.0 * special.chdtri(count, _SAME_PLACE))


def _checked_guess(problem: Problem, start: State, method: str, delay_index: Optional[int],
                   delay_range: DelayRange
                   ) -> Tuple[State, Optional[List[Iteration]], bool]:
    """
    Where a complete guess led, its updates (None if it did not explain the data), settled.

    :func:`warm_start` describes the check.
    """
    if delay_index is not None and not resembles_output(problem, start):
        moved = _with_data_delay(problem, start, delay_index)
        if moved is None:
            # The full steps, linear in the dead time, cannot move it that far either.
            return start, None, False
        start = moved
    warm = local_fit(problem, start, method, first_ls=False, full_steps_only=True,
                     iterations=_WARM_START_ITERATIONS)
    state, history = warm.state, warm.history
    if warm.reason is not StopReason.NO_FULL_STEP and \
            explains_data(problem, state, delay_index, delay_range):
        return state, history, warm.reason is StopReason.NEGLIGIBLE_UPDATE
    if not resembles_output(problem, state):
        return state, None, False
    policy = IterationPolicy(
        method=method, max_iterations=_WARM_START_BUDGET,
        opening=Opening.PROJECTION if history else Opening.LEAST_SQUARES,
        check_optimality=True, min_progress=_WARM_START_PROGRESS)
    local = iterate(problem, state, policy)
    if not (local.converged and explains_data(problem, local.state, delay_index, delay_range)):
        return local.state, None, False
    return local.state, history + local.history, local.reason is StopReason.NEGLIGIBLE_UPDATE


def _with_data_delay(problem: Problem, start: State, delay_index: int) -> Optional[State]:
    """
    Return ``start`` with the data's dead-time guess if its output then resembles the data.

    None if the guess leaves the bounds or an inadmissible model, or its output does not
    resemble the measured one either (:func:`resembles_output`).
    """
    theta = start.theta.copy()
    theta[delay_index] = np.clip(problem.delay_guess, problem.lower[delay_index],
                                 problem.upper[delay_index])
    coefficients = problem.admissible(theta)
    if coefficients is None:
        return None
    moved = problem.state(theta, coefficients)
    return moved if resembles_output(problem, moved) else None


def automatic_start(problem: Problem, initial: Initial, transient: Union[float, str],
                    delay_index: Optional[int], delay_range: DelayRange) -> Start:
    """
    Start from the data: equation-error start, dead-time search, nested structures (stage 2).

    The automatic start (:func:`~ctid_ros.estimation.starts.initial_estimate`, the user's
    partial values as hints), then for a dead-time parameter the search of
    :func:`~ctid_ros.estimation.delay_search.delay_search`, then :func:`_nested_start`. A start
    refined by iterations opens the final iteration with IV projections, an unrefined one with
    the least-squares projection (``docs/algorithm.md`` sections 10 and 12).

    Evidence: every system of ``bench/estimator.py`` from 'auto'; the dead-time search for the
    second order plus long dead time (without it the iteration ends at ``tau -> 0``), the
    nested structures for the heating system of ``bench/real_records.py`` (its second order
    ended above its first-order special case, 10192-11011 against 9235).
    """
    state = prepared(problem, initial_estimate(problem, initial, delay_range), transient)
    history: Tuple[Iteration, ...] = ()
    profile: Tuple[Tuple[float, float], ...] = ()
    if delay_index is not None:
        search = delay_search(problem, state, delay_index, delay_range)
        state, profile, history = search.state, tuple(search.profile), tuple(search.history)
    nested = _nested_start(problem, initial, delay_range, delay_index, state)
    if nested is not None:
        state, history = nested[0], tuple(nested[1])
    refined = delay_index is not None or nested is not None
    return Start(state, history, Opening.PROJECTION if refined else Opening.LEAST_SQUARES,
                 profile=profile)


def _nested_start(problem: Problem, initial: Initial, delay_range: DelayRange,
                  delay_index: Optional[int], start: State
                  ) -> Optional[Tuple[State, List[Iteration]]]:
    """
    Return the best nested structure's optimum if it is better than ``start``, else None.

    Each structure a parameter's limit leaves (:func:`_reductions`: a lag dropped, the dead
    time removed) is fitted by the same automatic start and dead-time search with that
    parameter held at its limit; the final iteration then releases it. So a structure is never
    left worse than one it contains (``docs/algorithm.md`` section 12).
    """
    names = problem.model.parameters
    hints = {name: float(np.clip(value, problem.lower[names.index(name)],
                                 problem.upper[names.index(name)]))
             for name, value in _given_hints(initial).items()}
    best = None
    for index, value in _reductions(problem, start.theta).items():
        fixed = np.zeros(len(names), dtype=bool)
        fixed[index] = True
        try:
            nested = initial_estimate(problem, hints or 'auto', delay_range,
                                      pin={names[index]: value})
        except (EstimationError, ModelError):
            continue
        if delay_index is not None:
            found = delay_search(problem, nested, delay_index, delay_range, fixed=fixed)
        else:
            found = local_fit(problem, nested, 'iv', first_ls=True, frozen=fixed,
                              iterations=_NESTED_ITERATIONS)
        if found.state.cost < (start.cost if best is None else best[0].cost):
            best = (found.state, found.history)
    if best is not None:
        # The search's own result may be a few iterations short of its minimum: it competes
        # refined, or a nested structure wins on an unfinished comparison.
        own = local_fit(problem, start, 'iv', first_ls=False, iterations=_NESTED_ITERATIONS)
        if own.state.cost <= best[0].cost:
            return own.state, own.history
    return best


def _given_hints(initial: Initial) -> Dict[str, float]:
    """Return the user's initial values as a dict (none for 'auto')."""
    if initial is None or isinstance(initial, str):
        return {}
    return {name: float(value) for name, value in initial.items()}


def _reductions(problem: Problem, theta: np.ndarray) -> Dict[int, float]:
    """
    Parameters whose limit gives a simpler structure, and that limit; one per distinct one.

    A lag or mass at its order-reduction limit (:attr:`Problem.reductions`) unless that leaves
    a static model. Of two parameters that play the same role (the model is unchanged when
    they are swapped, as ``T1`` and ``T2`` in ``(T1 s + 1)(T2 s + 1)``) only the first counts:
    both give the same nested structure. The dead time's own nested structure (no dead time) is
    the first point of the dead-time profile, refined if it is among its best minima, and a
    dead time on its lower bound is released when the cost falls inward (section 7).
    """
    # The structure one order lower still has dynamics only if D had degree 2 or more.
    limits = dict(problem.reductions) if problem.model.den_degree >= 2 else {}
    model = problem.model
    probe = theta * np.random.default_rng(0).uniform(1.1, 1.9, theta.size)
    distinct: Dict[int, float] = {}
    for index, value in sorted(limits.items()):
        if any(_interchangeable(model, probe, index, other) for other in distinct):
            continue
        distinct[index] = value
    return distinct


def _interchangeable(model, theta: np.ndarray, first: int, second: int) -> bool:
    """Return True if swapping two parameters leaves the model's coefficients unchanged."""
    swapped = theta.copy()
    swapped[[first, second]] = theta[[second, first]]
    try:
        one, other = model.coefficients(theta), model.coefficients(swapped)
    except ModelError:
        return False
    return bool(np.allclose(one.num, other.num) and np.allclose(one.den, other.den)
                and np.isclose(one.delay, other.delay))


def final_iteration(problem: Problem, start: Start, policy: IterationPolicy) -> Fit:
    """
    Iterate from the start to convergence, then from the best point seen (stage 3).

    ``policy`` is the final iteration's (the user's method, limits and tolerance, first-order
    optimality checked); the start says how it opens. A settled warm start is the result
    itself, with no update. :func:`from_best_seen` follows.

    Evidence: every estimate; the convergence tests are sections 5-8 of
    ``docs/algorithm.md``.
    """
    if start.settled:
        reason = StopReason.NEGLIGIBLE_UPDATE
        result = IterationResult(start.state, [], reason,
                                 reason.describe(policy.tolerance, policy.max_iterations))
    else:
        result = iterate(problem, start.state, replace(policy, opening=start.opening))
    return from_best_seen(problem, Fit(result, start.history + tuple(result.history)), policy)


def from_best_seen(problem: Problem, fit: Fit, policy: IterationPolicy) -> Fit:
    """
    Continue from the best point evaluated if the iteration ended above it.

    Every start, profile point and line-search candidate is a point of the same cost
    (:attr:`Problem.best`); the estimate may not be worse than any of them, nor than its start
    (``docs/algorithm.md`` section 8). Least-squares projections (``method='ls'``) follow their
    own fixed point and are left where they end. At most two continuations.

    Evidence: the heating system of ``bench/real_records.py``, where a warm start at cost
    3556 used to return 4893; ``test_estimate.py`` asserts the guarantee from every start.
    """
    for _ in range(2):
        best = problem.best
        if policy.method == 'ls' or best is None or best.cost >= fit.state.cost:
            return fit
        again = iterate(problem, best, policy)
        fit = fit.extended(again.history,
                           again if again.state.cost <= fit.state.cost else fit.result)
    return fit


def symmetry_restarts(problem: Problem, fit: Fit, policy: IterationPolicy,
                      sensitivities: Sensitivities, rng: np.random.Generator
                      ) -> Tuple[Fit, Optional[BlindCombination]]:
    """
    Perturb a point where interchangeable parameters coincide; return it and what is blind.

    Where :func:`~ctid_ros.estimation.identifiability.blind_combination` finds a combination
    the output ignores, the point is perturbed (:func:`_nudged`) and iterated again, at most
    :data:`_SYMMETRY_RESTARTS` times; a restart that ends no lower than the point it left ends
    them: the data put the minimum at the coincidence (``docs/algorithm.md`` section 14).

    Evidence: the two-lags-plus-dead-time system of ``bench/estimator.py`` (``T1``, ``T2``
    interchangeable) and the thermic wall of ``bench/real_records.py`` (both time constants
    1.925 s: the restarts return there and the estimate says so).
    """
    blind = blind_combination(problem, fit.state, sensitivities)
    for _ in range(_SYMMETRY_RESTARTS):
        if blind is None:
            break
        nudged = _nudged(problem, fit.state, rng)
        if nudged is None:
            break
        restarted = iterate(problem, nudged, policy)
        if restarted.state.cost >= fit.state.cost:
            # Back where it started, or worse: the data put the minimum at the coincidence.
            return fit.extended(restarted.history), blind
        fit = from_best_seen(problem, fit.extended(restarted.history, restarted), policy)
        blind = blind_combination(problem, fit.state, sensitivities)
    return fit, blind


def _nudged(problem: Problem, state: State, rng: np.random.Generator) -> Optional[State]:
    """Perturb a point where symmetric parameters coincide (e.g. T1 = T2) so they can split."""
    for _ in range(_NUDGES):
        theta = state.theta * (1.0 + 0.05 * rng.standard_normal(state.theta.size))
        theta = np.clip(theta, problem.lower, problem.upper)
        coefficients = problem.admissible(theta)
        if coefficients is not None:
            return problem.state(theta, coefficients)
    return None


def look_elsewhere(problem: Problem, fit: Fit, policy: IterationPolicy,
                   delay_index: Optional[int], verdict: ResidualAnalysis) -> Fit:
    """
    Look for another basin when the residual is not white (stage 5, automatic searches).

    A residual that is correlated with the input, or coloured (section 11; a coloured input
    makes the two hard to tell apart), can mean the model misses something: a structure that
    cannot do better, or a local minimum. For a non-affine structure, whose equation-error
    start can miss the output-error basin altogether, the random draws of the automatic start
    are then iterated on the output error directly (twenty updates each); a better end is
    iterated to convergence and kept (``docs/algorithm.md`` section 12).

    Evidence: the CD player arm of ``bench/real_records.py``: every equation-error fit of the
    non-affine second order lands in an overdamped basin (cost 13.28), the resonance is at
    11.42.
    """
    if problem.model.is_affine or policy.method == 'ls' or \
            verdict.white and not verdict.input_correlated:
        return fit
    best = None
    for theta in random_starts(problem, fit.state.theta, delay_index):
        coefficients = problem.admissible(theta)
        if coefficients is None:
            continue
        trial = iterate(problem, problem.state(theta, coefficients), _ELSEWHERE)
        if trial.state.cost < (fit.state.cost if best is None else best.state.cost):
            best = trial
    if best is None:
        return fit
    again = iterate(problem, best.state, policy)
    return from_best_seen(problem, fit.extended(best.history + again.history,
                                                _lower(fit.result, again)), policy)


def other_side_of_the_sample(problem: Problem, fit: Fit, policy: IterationPolicy,
                             delay_index: Optional[int], delay_range: DelayRange) -> Fit:
    """
    Try the dead time's twin across the nearest sample instant (stage 5, automatic searches).

    :func:`~ctid_ros.estimation.delay_search.across_the_sample`; a lower end is iterated to
    convergence and :func:`from_best_seen` follows (``docs/algorithm.md`` section 12).

    Evidence: the winding record of ``bench/real_records.py``: tau = 3.024 s at cost 1053.79
    against its twin 2.952 s at 1053.52.
    """
    if delay_index is None:
        return fit
    across = mirrored_delay(problem, fit.state, delay_index, delay_range)
    if across is None:
        return fit
    again = iterate(problem, across.state, policy)
    return from_best_seen(problem, fit.extended(across.history + again.history,
                                                _lower(fit.result, again)), policy)


def onto_the_sample(problem: Problem, fit: Fit, policy: IterationPolicy,
                    delay_index: Optional[int]) -> Fit:
    """
    Finish a fit that stalled with its dead time just off a sample instant (stage 6).

    On the sample lattice the cost has a kink along the dead time: from just above it (or
    below) the gradient points at the lattice, but every step that crosses it rises, so the
    iteration creeps up to the kink and stops as stalled, not converged, although the point is
    a minimum. The dead time is put on the lattice point within :data:`_ON_THE_KINK` samples,
    where the iteration sees both sides; its result is kept if it is no worse.

    Evidence: a first order with a dead time of exactly five samples (ts 60 s, T 3600 s, tau
    300 s, SNR 20 dB): 4 of 40 seeds stalled 1e-9 samples above 300 s, where refits from
    nearby lowered the cost by less than 1e-5 of the noise variance.
    """
    if delay_index is None or fit.result.reason is not StopReason.STALLED or \
            not _on_a_kink(problem, fit.state, delay_index):
        return fit
    theta = fit.state.theta.copy()
    theta[delay_index] = problem.on_delay_lattice(theta[delay_index])
    coefficients = problem.admissible(theta)
    if coefficients is None:
        return fit
    snapped = problem.state(theta, coefficients)
    if snapped.cost > fit.state.cost:
        return fit
    again = iterate(problem, snapped, policy)
    if again.state.cost > fit.state.cost:
        return fit
    return fit.extended(again.history, again)


def _lower(first: IterationResult, second: IterationResult) -> IterationResult:
    """Return the result of lower cost (the first on a tie)."""
    return second if second.state.cost < first.state.cost else first
