"""
Dead-time search: a local fit if it explains the data, else a profile over a grid of dead times.

The output-error cost is multimodal in the dead time ``tau``. A few joint iterations from the
start come first; if their residual is independent of the input the search ends there.
Otherwise, for each ``tau`` on a grid the other parameters get their equation-error fit with
``tau`` frozen (:mod:`ctid_ros.estimation.starts`) and the profile records its output-error
cost; the best local minima of that profile are then refined by projection iterations, first
with ``tau`` frozen, then jointly. The method is section 12 of ``docs/algorithm.md``.
"""

from dataclasses import dataclass, field
import math
from typing import Callable, Dict, List, Optional, Tuple

from ctid_ros.core.model import Coefficients
from ctid_ros.core.simulation import shifted
from ctid_ros.estimation.iteration import (iterate, Iteration, IterationPolicy, IterationResult,
                                           Opening)
from ctid_ros.estimation.linear_algebra import gram_matrix, least_squares, normal_solution
from ctid_ros.estimation.problem import DelayRange, Problem, reduction_limits, State
from ctid_ros.estimation.starts import (best_candidate, default_filters, distinct,
                                        equation_error_fits, explains_data, local_fit,
                                        StateVariableFilters)
import numpy as np

__all__ = ['DelaySearch', 'across_the_sample', 'delay_search', 'neighbouring_delays']

_GRID_POINTS = 30
_REFINED_MINIMA = 2
_REFINEMENT_MARGIN = 3.0
_COARSE_STRIDE = 3
_JOINT_ITERATIONS = 10
# A profile whose best fit leaves more than this share of the output's spread explains nothing.
_UNEXPLAINED = 0.9
# Dead times tried around the refined minimum, in samples.
_PROBE_OFFSETS = (-1.0, 1.0)
# A lag below this many times its order-reduction limit counts as collapsed.
_COLLAPSED = 10.0
# Shares of the dead time given to a lag that collapsed onto its limit.
_LAG_SHARES = (0.5, 0.25, 0.75)
# Lags below the sample time, in samples, tried for a lag that collapsed onto its limit.
_SUB_SAMPLE_LAGS = (0.05, 0.25)
# A lag shorter than this many sample times is tried below the sample time at whole samples.
_SHORT_LAG = 0.1
# Shifted sensitivities (columns of unit norm) conditioned within this are solved by normal
# equations.
_NORMAL_CONDITION = 1e3
# Joint refinement of every candidate: IV projections from a start refined already.
_JOINT = IterationPolicy(max_iterations=_JOINT_ITERATIONS, opening=Opening.PROJECTION)


@dataclass
class DelaySearch:
    """
    Outcome of :func:`delay_search`.

    Attributes
    ----------
    state : State
        The best state found.
    profile : list of (tau, cost)
        The profile over the grid (empty if the local fit was accepted).
    history : list of Iteration
        The joint iterations that led to ``state``.

    """

    state: State
    profile: List[Tuple[float, float]] = field(default_factory=list)
    history: List[Iteration] = field(default_factory=list)


def _local_minima(profile: List[Tuple[float, float, State]]) -> List[State]:
    """Return the states of the lowest local minima of the profile, best first."""
    costs = np.array([cost for _, cost, _ in profile])
    indices = [i for i in range(len(costs))
               if (i == 0 or costs[i] <= costs[i - 1])
               and (i == len(costs) - 1 or costs[i] <= costs[i + 1])]
    indices.sort(key=lambda i: costs[i])
    return [profile[i][2] for i in indices[:_REFINED_MINIMA]]


def delay_search(problem: Problem, start: State, delay_index: int, delay_range: DelayRange,
                 fixed: Optional[np.ndarray] = None) -> DelaySearch:
    """
    Locate the dead time: a local fit if it explains the data, else a profile over a grid.

    A few joint iterations from the start come first. If they reach a model whose residual is
    independent of the input over the lags of the delay range plus the settling time
    (:func:`~ctid_ros.estimation.starts.explains_data`), the data show no dynamics the model
    misses and the search ends there (a warm start in the live node takes this path).

    Otherwise the search profiles the whole range and refines its best minima jointly.
    At each grid ``tau`` (on whole samples where the search bracket allows, so the filtered
    input is a shift) the other parameters get their equation-error fit and the profile
    records the output-error cost of that fit. Every third grid point tries every
    state-variable filter; the filter that gave the lowest cost there serves the whole profile
    (one filter throughout, so the profile's minima are not artefacts of switching filters).
    The best local minima of the profile get a few projection iterations with ``tau`` frozen,
    then joint ones. A profile whose lowest point is the end of an automatic bracket, or whose
    best fit explains less than a tenth of the output's spread, goes on over a bracket twice as
    long (at most half the record). On coarse data, where the bracket
    spans fewer samples than the grid has points, the grid adds the half-sample points: for a
    model of relative degree one the cost has a kink on every sample, and its minima lie
    between them.

    ``fixed`` parameters (default none) keep their start values throughout (the search for a
    nested structure).

    """
    data = problem.data
    fixed = np.zeros(start.theta.size, dtype=bool) if fixed is None else fixed
    low, high = problem.delay_bracket(delay_index, delay_range)
    local = local_fit(problem, start, 'iv', first_ls=True, frozen=fixed)
    if explains_data(problem, local.state, delay_index, delay_range):
        state, history = _lag_for_delay(problem, local.state, local.history, delay_index, low,
                                        fixed)
        return DelaySearch(state, [], history)
    grid = np.union1d(np.linspace(low, high, _GRID_POINTS),
                      [start.theta[delay_index], problem.delay_guess])
    grid = np.unique(np.clip([problem.on_delay_lattice(tau) for tau in grid], low, high))
    lattice = problem.on_delay_lattice(low)
    if (high - lattice) / data.ts < _GRID_POINTS:
        halves = np.arange(lattice + 0.5 * data.ts, high, data.ts)
        grid = np.union1d(grid, halves[halves > low])
    delay_mask = np.zeros(start.theta.size, dtype=bool)
    delay_mask[delay_index] = True
    frozen = fixed | delay_mask
    filters = default_filters(problem)
    coarse = np.zeros(grid.size, dtype=bool)
    coarse[::_COARSE_STRIDE] = True

    lowest = [start]

    def fitted(tau: float, chosen: StateVariableFilters) -> Optional[State]:
        # A non-affine fit starts from the hint and from the best fit so far (moved to this
        # tau), not from random draws: the start's multi-start has been done at its own tau.
        sources = [start] if problem.model.is_affine else [start, lowest[0]]
        starts = distinct([np.where(delay_mask, tau, state.theta) for state in sources])
        state = best_candidate(problem, distinct(equation_error_fits(
            problem, starts, ~frozen, tau, chosen)))
        if state is not None and state.cost < lowest[0].cost:
            lowest[0] = state
        return state

    def by_every_filter(tau: float) -> List[Optional[State]]:
        filters.factors(tau)        # every filter's factor at tau, their input parts in one pass
        return [fitted(tau, filters.select(index)) for index in range(filters.count)]

    trials = {tau: by_every_filter(tau) for tau in grid[coarse]}
    costs = np.array([[np.inf if state is None else state.cost for state in row]
                      for row in trials.values()]).reshape(-1, filters.count)
    index = int(np.argmin(np.min(costs, axis=0))) if np.isfinite(costs).any() \
        else filters.count // 2
    states = {tau: row[index] for tau, row in trials.items()}
    chosen = filters.select(index)
    states.update({tau: fitted(tau, chosen) for tau in grid[~coarse]})
    # A grid point without an admissible fit (an unstable D, as often past the true dead time,
    # where the fit would have to anticipate the input) drops out of the profile.
    profile = [(float(tau), states[tau].cost, states[tau]) for tau in grid
               if states[tau] is not None]
    # An automatic bracket rests on the data's guess; a profile still falling at its end, or
    # whose best fit explains nothing (a tenth of the output's spread), says the dead time lies
    # beyond: the bracket is doubled (at most to half the record) until neither holds.
    automatic = delay_range is None and not np.isfinite(problem.upper[delay_index])
    ceiling = 0.5 * data.ts * len(data)
    spread = problem.measured - problem.measured.mean()
    # np.linalg.norm's arithmetic for a vector, without its dispatch.
    nothing = 0.5 * (_UNEXPLAINED * math.sqrt(spread.dot(spread))) ** 2

    def beyond() -> bool:
        lowest = min(profile, key=lambda point: point[1])
        return lowest is profile[-1] or lowest[1] > nothing

    while automatic and profile and high < ceiling and beyond():
        extended = min(2.0 * high, ceiling)
        more = np.unique([problem.on_delay_lattice(tau) for tau in
                          np.linspace(high, extended, _GRID_POINTS)])
        more = more[(more > high) & (more <= extended)]
        profile += [(float(tau), state.cost, state) for tau, state in
                    ((tau, fitted(tau, chosen)) for tau in more) if state is not None]
        high = extended
    if not profile:
        return DelaySearch(start)
    # With tau frozen an affine structure is nearly solved by the first (LS) projection step.
    frozen_iterations = 2 if problem.model.is_affine else 3
    profiled_policy = IterationPolicy(max_iterations=frozen_iterations,
                                      opening=Opening.TRUSTED_LEAST_SQUARES)
    best, history, margin = None, [], np.inf
    for state in _local_minima(profile):
        # Refinement lowered the best minimum's cost by some amount; a minimum whose profile
        # cost exceeds the best refined cost by three times that amount cannot compete.
        if best is not None and state.cost - _REFINEMENT_MARGIN * margin > best.cost:
            continue
        profiled = state.cost
        state = iterate(problem, state, profiled_policy, frozen).state
        joint = iterate(problem, state, _JOINT, fixed)
        if best is None or joint.state.cost < best.cost:
            best, history, margin = joint.state, joint.history, profiled - joint.state.cost
    best, history = _probe_neighbours(problem, best, history, delay_index, profile, frozen,
                                      fixed, profiled_policy, lambda tau: fitted(tau, chosen))
    best, history = _lag_for_delay(problem, best, history, delay_index, low, fixed)
    return DelaySearch(best, [(tau, cost) for tau, cost, _ in profile], history)


def across_the_sample(problem: Problem, best: State, delay_index: int,
                      delay_range: DelayRange) -> Optional[IterationResult]:
    """
    Try the other side of the sample instant nearest the dead time, for a kinked cost.

    For a model of relative degree one the cost has a kink at every whole sample of dead time
    (section 3 of ``docs/algorithm.md``); a minimum just past one has a twin just before it
    that the iteration, which sees one side at a time, cannot reach. The dead time mirrored
    across the nearest lattice point is iterated jointly (ten updates); the result if it ends
    lower than ``best``, else None.
    """
    low, high = problem.delay_bracket(delay_index, delay_range)
    fixed = np.zeros(best.theta.size, dtype=bool)
    num = best.coefficients.num
    order = best.coefficients.den.size - 1
    # Relative degree one: some numerator reaches s^(n-1).
    if order < 1 or num.shape[1] < order or not num[:, num.shape[1] - order].any():
        return None
    tau = best.theta[delay_index]
    knot = problem.on_delay_lattice(tau)
    mirrored = 2.0 * knot - tau
    if abs(tau - knot) < 1e-9 * problem.data.ts or not low <= mirrored <= high:
        return None
    theta = best.theta.copy()
    theta[delay_index] = mirrored
    admissible = problem.admissible(theta)
    if admissible is None:
        return None
    joint = iterate(problem, problem.state(theta, admissible), _JOINT, fixed)
    return joint if joint.state.cost < best.cost else None


def _lag_for_delay(problem: Problem, best: State, history: List[Iteration], delay_index: int,
                   low: float, fixed: np.ndarray) -> Tuple[State, List[Iteration]]:
    """
    Trade dead time for a lag that collapsed onto its order-reduction limit.

    A lag ``T`` and a dead time delay low frequencies alike (``1/(T s + 1) ~ exp(-T s)``), so
    a fit can end with the lag at its limit and the dead time doing its work: a boundary
    minimum next to the basin where both share it. From there a part of the dead time,
    ``delta`` = a quarter, half and three quarters of it, is given to the lag
    (``T = delta``, ``tau - delta``) and iterated jointly; the better end is kept. A lag
    below the sample time is tried too (a twentieth and a quarter of a sample, at the whole
    sample dead times around ``tau``): on a record sampled every 0.1 s with a best lag of
    0.004-0.03 s the lag otherwise stayed on its limit 1-4 % above the optimum, where the
    output no longer depends on the dead time between samples.
    """
    tau = best.theta[delay_index]
    ts = problem.data.ts
    limits = _order_limits(problem, best.theta)
    # Within ten times its limit a lag's pole is a hundred times the Nyquist frequency: gone.
    collapsed = [index for index, limit in limits.items()
                 if not fixed[index] and abs(best.theta[index]) <= _COLLAPSED * abs(limit)]
    # Lags below the sample time at the whole-sample dead times either side of tau: with the
    # lag on its limit the output is a shifted input, blind to the dead time between samples.
    lattice = problem.on_delay_lattice(tau)
    knots = [knot for knot in (lattice - ts, lattice, lattice + ts) if knot >= low]
    # A lag below a tenth of the sample time leaves the output within exp(-10) of a shifted
    # input.
    short = [index for index, limit in limits.items()
             if not fixed[index] and abs(best.theta[index]) < _SHORT_LAG * ts]
    for index in sorted(set(collapsed) | set(short)):
        trials = [] if index not in collapsed else \
            [(share * (tau - low), tau - share * (tau - low)) for share in _LAG_SHARES]
        if index in short:
            trials += [(share * ts, knot) for share in _SUB_SAMPLE_LAGS for knot in knots]
        for delta, delay in trials:
            if delta <= abs(limits[index]):
                continue
            theta = best.theta.copy()
            theta[index] = np.sign(limits[index]) * delta
            theta[delay_index] = delay
            coefficients = problem.admissible(theta)
            if coefficients is None:
                continue
            joint = iterate(problem, problem.state(theta, coefficients), _JOINT, fixed)
            if joint.state.cost < best.cost:
                best, history = joint.state, joint.history
    return best, history


def _order_limits(problem: Problem, theta: np.ndarray) -> Dict[int, float]:
    """
    Return the order-reduction limits, with a user's bound where it stops a lag first.

    :attr:`Problem.reductions` holds the lags (and masses) bounded at the value where their
    pole leaves the sampled band; a tighter bound of the user's (``T >= 0.001``) keeps them
    out of it. A lag on such a bound below a tenth of a sample has collapsed all the same.
    """
    limits = dict(problem.reductions)
    short = _SHORT_LAG * problem.data.ts
    # Only a parameter already below a tenth of a sample can be such a lag: usually none.
    if all(value >= short or value <= -short for index, value in enumerate(theta.tolist())
           if index not in limits):
        return limits
    for index, value in reduction_limits(problem.model, theta, problem.data.ts).items():
        bound = problem.lower[index] if value > 0.0 else problem.upper[index]
        if index not in limits and 0.0 < bound / value and abs(bound) < short:
            limits[index] = float(bound)
    return limits


def _probe_neighbours(problem: Problem, best: State, history: List[Iteration], delay_index: int,
                      profile: List[Tuple[float, float, State]], frozen: np.ndarray,
                      fixed: np.ndarray, profiled_policy: IterationPolicy,
                      fitted: Callable[[float], Optional[State]]
                      ) -> Tuple[State, List[Iteration]]:
    """
    Refine the profile's fits one sample either side of the best dead time too.

    The equation-error profile is only a proxy of the output-error one: its minimum can sit a
    sample off, next to the basin of another structure (a lag traded for dead time, a
    lag collapsed onto its limit). Each neighbour's own fit is iterated with the dead time
    frozen; one that beats ``best`` is refined jointly, and the better end kept. The
    neighbours are those of the refined dead time and of the profile's lowest point; where
    the grid has no point there (its points several samples apart), ``fitted`` gives the
    equation-error fit at that sample.
    """
    ts = problem.data.ts
    taus = np.array([tau for tau, _, _ in profile])
    lowest = taus[int(np.argmin([cost for _, cost, _ in profile]))]
    tried = set()
    for centre, offset in [(centre, offset) for centre in (best.theta[delay_index], lowest)
                           for offset in _PROBE_OFFSETS]:
        tau = problem.on_delay_lattice(centre + offset * ts)
        index = int(np.argmin(np.abs(taus - tau)))
        if abs(taus[index] - tau) <= 0.5 * ts:
            tau, state = taus[index], profile[index][2]
        elif tau >= taus[0] and tau <= taus[-1]:
            state = fitted(tau)
        else:
            continue
        if tau in tried or state is None:
            continue
        tried.add(tau)
        probe = iterate(problem, state, profiled_policy, frozen).state
        if probe.cost >= best.cost:
            continue
        joint = iterate(problem, probe, _JOINT, fixed)
        if joint.state.cost < best.cost:
            best, history = joint.state, joint.history
    return best, history


def neighbouring_delays(problem: Problem, best: State, delay_index: int,
                        delay_range: DelayRange) -> Optional[IterationResult]:
    """
    Refit the model one sample either side of the dead time of ``best``; a lower end, or None.

    The cost's basins in the dead time are often a sample apart (a kink on every sample for a
    model of relative degree one, section 3; a lag traded for dead time): a local fit ends in
    one of them, and the neighbour can be lower. Each neighbour ``tau -+ ts`` (within the
    bounds and the given delay range) is screened first by one Gauss-Newton update of the
    other parameters, from the output and sensitivities of ``best`` shifted by that sample
    (:func:`_linearised_refit`: one simulation, no new sensitivities). Only a neighbour whose
    screened cost, less the update's own linearisation error, is below the cost of ``best``
    is iterated jointly (:data:`_JOINT`); the lowest end is returned if it is below ``best``.
    """
    # The automatic bracket would compute the data's dead-time guess, only to cap the search.
    low, high = (problem.lower[delay_index], problem.upper[delay_index]) \
        if delay_range is None else problem.delay_bracket(delay_index, delay_range)
    others = np.ones(best.theta.size, dtype=bool)
    others[delay_index] = False
    # The warm start's last update linearised at best already: usually no new simulation.
    linearised = problem.linearize(best.coefficients, regressors=False)
    sensitivities = linearised.psi[:, others]
    # Both neighbours' normal matrices are this one less the row their shift drops.
    gram = gram_matrix(sensitivities)
    lowest = None
    for offset in _PROBE_OFFSETS:
        theta = best.theta.copy()
        theta[delay_index] = best.theta[delay_index] + offset * problem.data.ts
        if not low <= theta[delay_index] <= high:
            continue
        coefficients = problem.admissible(theta)
        if coefficients is None:
            continue
        screened, error = _linearised_refit(problem, theta, coefficients, others,
                                            linearised.output, sensitivities, gram, int(offset))
        if screened.cost - error >= best.cost:
            continue
        joint = iterate(problem, screened, _JOINT)
        if joint.state.cost < (best.cost if lowest is None else lowest.state.cost):
            lowest = joint
    return lowest


def _linearised_refit(problem: Problem, theta: np.ndarray, coefficients: Coefficients,
                      others: np.ndarray, output: np.ndarray, sensitivities: np.ndarray,
                      gram: np.ndarray, samples: int) -> Tuple[State, float]:
    """
    Screen ``theta`` by one Gauss-Newton update of its ``others`` parameters.

    ``output`` and ``sensitivities`` (the model output of a dead time ``samples`` samples
    shorter and its derivatives by the ``others`` on the fitted samples, ``gram`` the
    sensitivities' normal matrix), delayed by ``samples`` (advanced if negative) with zeros
    shifted in, approximate those at ``theta``: exact for a model at rest before the record, a
    screen otherwise. The update solves the shifted least-squares problem by its normal
    equations where the shifted sensitivities (columns of unit norm) are conditioned within
    :data:`_NORMAL_CONDITION` (a ``cond^2 eps`` relative error), by ``lstsq`` otherwise.
    Returns the updated point (clipped into the bounds), a candidate (:attr:`Problem.best`),
    and its linearisation error: the difference between its cost and the cost
    ``0.5 |e - S d|^2`` the linearised output promised. If the update leaves an inadmissible
    model, ``theta`` itself with no error.
    """
    count = output.size
    # The rows the shift keeps (kept) and where they land (moved); the other rows of the
    # shifted sensitivities are zeros.
    kept = slice(0, count - samples) if samples >= 0 else slice(-samples, count)
    moved = slice(samples, count) if samples >= 0 else slice(0, count + samples)
    dropped = slice(count - samples, count) if samples >= 0 else slice(0, -samples)
    error = problem.measured.copy()
    error[moved] -= output[kept]
    columns = sensitivities[kept]
    step = normal_solution(gram - sensitivities[dropped].T @ sensitivities[dropped],
                           columns.T @ error[moved], _NORMAL_CONDITION)
    if step is None:
        step = least_squares(shifted(sensitivities, -samples), error)
    remaining = error.copy()
    remaining[moved] -= columns @ step
    updated = theta.copy()
    updated[others] += step
    updated = np.clip(updated, problem.lower, problem.upper)
    admissible = problem.admissible(updated) if np.isfinite(updated).all() else None
    if admissible is None:
        return problem.state(theta, coefficients), 0.0
    refit = problem.state(updated, admissible)
    return refit, abs(refit.cost - 0.5 * float(remaining @ remaining))
