"""
Starting points for the projection iteration: automatic initialisation and dead-time search.

Automatic initialisation needs no user guess. For a few state-variable filters
``E(p) = (p + lam)^n`` it fits the equation error ``[D(p, theta) y - N(p, theta) u] / E`` by
least squares directly in the grey-box parameters (a small problem: the filtered signals are
computed once per filter and reduce to a triangular factor), from several starts, and keeps the
candidate with the lowest output-error cost. For affine structures this is the exact
one-step regression of the method with a fixed filter, so any start works.

The dead time is located by a profile: for each ``tau`` on a grid the other parameters get a
few projection iterations with ``tau`` frozen; the best local minima of that profile are then
refined jointly.
"""

from typing import List, Mapping, Optional, Tuple

from ctid_ros.errors import EstimationError, ModelError
from ctid_ros.simulation import ContinuousFilter
import numpy as np
from scipy import optimize

_FILTER_COUNT = 5
_GRID_FILTER_COUNT = 3
_RANDOM_STARTS = 4
_GRID_POINTS = 30
_REFINED_MINIMA = 2


def _given_values(model, initial) -> Mapping[str, float]:
    if initial is None or (isinstance(initial, str) and initial == 'auto'):
        return {}
    if isinstance(initial, str):
        raise ModelError(f"initial must be a dict of values or 'auto', got {initial!r}")
    unknown = sorted(set(initial) - set(model.parameters))
    if unknown:
        raise ModelError(f'initial values given for unknown parameter(s) {", ".join(unknown)}; '
                         f'the model has {", ".join(model.parameters)}')
    values = {name: float(value) for name, value in initial.items()}
    bad = [name for name, value in values.items() if not np.isfinite(value)]
    if bad:
        raise ModelError(f'initial value(s) of {", ".join(bad)} are not finite')
    return values


def initial_estimate(problem, initial, delay_range: Optional[Tuple[float, float]]):
    """
    Return the starting state of the iteration.

    The user's values compete with the equation-error multi-start described in the module
    docstring (missing values are fitted, given ones serve as hints, or stay fixed while others
    are missing); the candidate with the lowest output-error cost wins. A far or unstable guess
    therefore costs robustness nothing.

    """
    from ctid_ros.estimator import delay_parameter

    model = problem.model
    given = _given_values(model, initial)
    for name, value in given.items():
        index = model.parameters.index(name)
        if not problem.lower[index] <= value <= problem.upper[index]:
            raise ModelError(f'initial value {name}={value:g} lies outside its bounds '
                             f'[{problem.lower[index]:g}, {problem.upper[index]:g}]')
    # A complete guess is a hint for every parameter; a partial one pins the given values.
    pinned = {} if len(given) == len(model.parameters) else given
    delay_index = delay_parameter(model)
    tau = _initial_delay(problem, given, delay_index, delay_range)
    best = best_candidate(problem, _equation_error_candidates(
        problem, given, pinned, delay_index, tau))
    if best is None:
        raise EstimationError(
            'no stable starting model was found: the initial values give an unstable or '
            'out-of-bounds D(s), and the automatic initialisation found none either; give '
            'initial values that make the model stable, or check the bounds')
    return best


def best_candidate(problem, candidates: List[np.ndarray]):
    """Return the admissible candidate with the lowest output-error cost (a state), or None."""
    from ctid_ros.estimator import _State

    best = None
    for theta in candidates:
        structure = problem.admissible(theta)
        if structure is None:
            continue
        cost = problem.cost(structure)
        if best is None or cost < best.cost:
            best = _State(theta, structure, cost)
    return best


def _initial_delay(problem, given, delay_index, delay_range) -> float:
    if delay_index is None:
        return 0.0
    name = problem.model.parameters[delay_index]
    if name in given:
        return given[name]
    low, high = _delay_bracket(problem, delay_index, delay_range)
    return float(np.clip(impulse_delay(problem.data), low, high))


def _starts(problem, hints, pinned, delay_index, tau, rng) -> List[np.ndarray]:
    """
    Return starting points: the user's hints first, then random draws.

    Draws are log-uniform over 1e-2..1e2, or over the box where it is finite (uniform when the
    box includes zero). Pinned values and the dead time are the same in every start.

    """
    model = problem.model
    count = len(model.parameters)
    lower, upper = problem.lower, problem.upper
    boxed = np.isfinite(lower) & np.isfinite(upper)
    positive_box = boxed & (lower > 0)
    hinted = np.array([hints.get(name, np.nan) for name in model.parameters])
    fixed = np.array([pinned.get(name, np.nan) for name in model.parameters])
    starts = []
    # The equation error of an affine structure is linear in theta: one start finds its optimum.
    for draw in range(1 if model.is_affine else _RANDOM_STARTS + 1):
        if draw == 0:
            guess = np.where(np.isnan(hinted), 1.0, hinted)
        else:
            guess = 10.0 ** rng.uniform(-2.0, 2.0, count)
            in_log_box = np.exp(rng.uniform(np.log(np.where(positive_box, lower, 1.0)),
                                            np.log(np.where(positive_box, upper, 1.0))))
            guess = np.where(positive_box, in_log_box, guess)
            guess = np.where(boxed & ~positive_box, rng.uniform(np.where(boxed, lower, 0.0),
                                                                np.where(boxed, upper, 1.0)),
                             guess)
        guess = np.clip(guess, lower, upper)
        guess = np.where(np.isnan(fixed), guess, fixed)
        if delay_index is not None:
            guess[delay_index] = tau
        starts.append(guess)
    return starts


def _filtered_regressors(problem, lam: float, tau: float) -> np.ndarray:
    """
    Triangular factor ``R`` of ``[p^j/E y, -p^j/E u_c]`` ordered like ``(den, num)``.

    Initial-state and offset components of the equation error (if the problem estimates them)
    are projected out first.
    """
    model = problem.model
    data = problem.data
    n, m = model.den_degree, model.num_degree
    filter_den = np.poly(np.full(n, -lam)) if n else np.ones(1)
    powers = [np.eye(n + 1)[n - j] for j in range(n + 1)]             # p^j, degree <= n
    realization = ContinuousFilter(filter_den)
    y_parts = realization.discretize(data.ts, 0.0, 'foh').outputs(data.y, powers[::-1])
    bank_u = realization.discretize(data.ts, tau, problem.bank.intersample)
    u_parts = [bank_u.outputs(channel, powers[m::-1]) for channel in problem.bank.channels.T]
    columns = np.vstack([y_parts] + [-part for part in u_parts]).T
    # Both act on y from t_0, so they are filtered without the input's dead time.
    undelayed = realization.discretize(data.ts)
    nuisance = []
    if problem.initial_state:
        nuisance.append(undelayed.free_responses(len(data)))
    if problem.output_offset:
        nuisance.append(undelayed.outputs(np.ones(len(data)), [np.ones(1)]).T)
    columns = np.hstack(nuisance + [columns])
    scales = np.linalg.norm(columns, axis=0)
    scales[scales == 0.0] = 1.0
    triangular = np.linalg.qr(columns / scales, mode='r')
    leading = columns.shape[1] - (n + 1) - len(u_parts) * (m + 1)
    return (triangular * scales)[leading:, leading:]


def _equation_error_candidates(problem, hints, pinned, delay_index, tau,
                               filters: int = _FILTER_COUNT) -> List[np.ndarray]:
    model = problem.model
    data = problem.data
    record = data.ts * len(data)
    rng = np.random.default_rng(20131)
    lams = np.geomspace(10.0 / record, 0.3 * np.pi / data.ts, filters)
    free = np.array([name not in pinned for name in model.parameters])
    if delay_index is not None:
        free[delay_index] = False
    starts = _starts(problem, hints, pinned, delay_index, tau, rng)
    if not np.any(free):
        return starts
    candidates = []
    for lam in lams:
        factor = _filtered_regressors(problem, lam, tau)

        def residual(values, start):
            theta = start.copy()
            theta[free] = values
            structure = model.structure(theta)
            return factor @ np.concatenate([structure.den, structure.num.ravel()])

        def jacobian(values, start):
            theta = start.copy()
            theta[free] = values
            structure = model.structure(theta)
            grad = np.hstack([structure.den_jacobian,
                              structure.num_jacobian.reshape(theta.size, -1)])[free]
            return factor @ grad.T

        for start in starts:
            try:
                result = optimize.least_squares(
                    residual, start[free], jac=jacobian, args=(start,),
                    bounds=(problem.lower[free], problem.upper[free]), method='trf',
                    max_nfev=200)
            except (ValueError, ModelError, np.linalg.LinAlgError):
                continue
            theta = start.copy()
            theta[free] = result.x
            candidates.append(theta)
    return candidates + starts


def impulse_delay(data) -> float:
    """
    Dead-time guess from the cross-correlation of the differenced input and output.

    Differencing whitens a held (e.g. PRBS) input, so the correlation approximates the impulse
    response; the first lag at which it reaches a quarter of its peak, less half a sample (the
    hold), is a robust bracket centre.

    """
    du = np.diff(data.u)
    dy = np.diff(data.y)
    count = du.size
    if count < 4 or not np.any(du):
        return 0.0
    size = 1 << int(np.ceil(np.log2(2 * count)))
    spectrum = np.fft.rfft(dy, size) * np.conj(np.fft.rfft(du, size))
    correlation = np.abs(np.fft.irfft(spectrum, size)[:count // 2])
    peak = np.max(correlation)
    if peak == 0.0:
        return 0.0
    first = int(np.argmax(correlation >= 0.25 * peak))
    return max(first - 0.5, 0.0) * data.ts


def _delay_bracket(problem, delay_index, delay_range) -> Tuple[float, float]:
    data = problem.data
    if delay_range is not None:
        low, high = float(delay_range[0]), float(delay_range[1])
        if not (0.0 <= low < high):
            raise ModelError(f'delay range must satisfy 0 <= min < max, got {delay_range}')
        return max(low, problem.lower[delay_index]), min(high, problem.upper[delay_index])
    low = problem.lower[delay_index]
    high = problem.upper[delay_index]
    if not np.isfinite(high):
        guess = impulse_delay(data)
        high = min(max(3.0 * guess, guess + 20.0 * data.ts), 0.5 * data.ts * len(data))
    return low, max(high, low + data.ts)


def _local_minima(profile: List[Tuple[float, float, object]]) -> List[object]:
    costs = np.array([cost for _, cost, _ in profile])
    indices = [i for i in range(len(costs))
               if (i == 0 or costs[i] <= costs[i - 1])
               and (i == len(costs) - 1 or costs[i] <= costs[i + 1])]
    indices.sort(key=lambda i: costs[i])
    return [profile[i][2] for i in indices[:_REFINED_MINIMA]]


def delay_search(problem, start, delay_index: int, delay_range):
    """
    Locate the dead time by a frozen-delay profile, then refine the best minima jointly.

    Returns the best state, the profile as ``[(tau, cost), ...]`` and the joint iterations
    that refined the best minimum.

    """
    from ctid_ros.estimator import _iterate

    low, high = _delay_bracket(problem, delay_index, delay_range)
    grid = np.union1d(np.linspace(low, high, _GRID_POINTS),
                      np.clip([start.theta[delay_index], impulse_delay(problem.data)],
                              low, high))
    frozen = np.zeros(start.theta.size, dtype=bool)
    frozen[delay_index] = True
    # With tau frozen an affine structure is nearly solved by the first (LS) projection step.
    grid_iterations = 2 if problem.model.is_affine else 3
    hints = problem.model.as_dict(start.theta)
    profile = []
    for tau in grid:
        theta = start.theta.copy()
        theta[delay_index] = tau
        # A start fitted at another tau can be far off here: refit by equation error too.
        state = best_candidate(problem, [theta] + _equation_error_candidates(
            problem, hints, {}, delay_index, tau, filters=_GRID_FILTER_COUNT))
        if state is None:
            continue
        state = _iterate(problem, state, method='iv', frozen=frozen,
                         max_iterations=grid_iterations, tolerance=1e-6,
                         trust_first_ls=True)[0]
        profile.append((float(tau), state.cost, state))
    if not profile:
        return start, [], []
    refined = [
        _iterate(problem, state, method='iv', frozen=np.zeros_like(frozen),
                 max_iterations=10, tolerance=1e-6, first_ls=False)[:2]
        for state in _local_minima(profile)]
    best, history = min(refined, key=lambda outcome: outcome[0].cost)
    return best, [(tau, cost) for tau, cost, _ in profile], history
