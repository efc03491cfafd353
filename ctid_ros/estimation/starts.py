"""
Starting points for the projection iteration, and the check that a start needs no search.

Automatic initialisation needs no user guess. For a few state-variable filters
``E(p) = (p + lam)^n`` it fits the equation error ``[D(p, theta) y - N(p, theta) u] / E`` by
least squares directly in the grey-box parameters (a small problem: the filtered signals are
computed once per filter and reduce to a triangular factor) and keeps the candidate with the
lowest output-error cost. For affine structures this is one linear solve, the exact one-step
regression of the method with a fixed filter, so any start works; a non-affine structure is
fitted from the hint with every filter, then from random starts with the filter that simulated
best.

The automatic start and the dead-time search (:mod:`ctid_ros.estimation.delay_search`) are
skipped when a few iterations from a start already give a model whose residual is independent
of the input (:func:`local_fit`, :func:`explains_data`): the estimator checks a complete user
guess (a warm start) this way first, the dead-time search its equation-error start.

The equations are sections 10 and 11 of ``docs/algorithm.md``.
"""

from functools import lru_cache
import math
import threading
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union
import weakref

from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.core.simulation import ContinuousFilter, DiscreteFilter, filter_responses
from ctid_ros.errors import EstimationError, ModelError
from ctid_ros.estimation.bvls import bounded_least_squares
from ctid_ros.estimation.correlation import independent_of_input
from ctid_ros.estimation.iteration import (iterate, IterationPolicy, IterationResult,
                                           Opening, Steps)
from ctid_ros.estimation.linear_algebra import gram_matrix, least_squares, solve_or_none
from ctid_ros.estimation.problem import (delay_parameter, DelayRange, FittedModel, Problem,
                                         settling_time, State)
import numpy as np
from scipy.linalg import lapack

__all__ = [
    'FILTER_COUNT', 'Initial', 'StateVariableFilters', 'best_candidate', 'complete_guess',
    'default_filters', 'distinct', 'equation_error_fits', 'explains_data', 'filter_bandwidths',
    'initial_estimate', 'local_fit', 'random_starts', 'resembles_output', 'stabilized',
]

# The smallest positive normal float: a zero diagonal's stand-in in the damped step.
_TINY = np.finfo(float).tiny
# Initial values by parameter name, or 'auto'/None for none.
Initial = Union[str, None, Mapping[str, float]]

FILTER_COUNT = 3
_START_TOLERANCE = 1e-6
_START_ITERATIONS = 100
_RANDOM_STARTS = 4
_LOCAL_ITERATIONS = 4
# A model explaining the data leaves a residual below this share of the output's spread.
_UNEXPLAINED = 0.9
# Share of the output's variance a start's output, scaled at best, must explain to be worth a
# local optimisation (a dead time far off leaves a squared correlation below 1e-3).
_RESEMBLANCE = 0.01
# Fractions of a sample whose filtered input is kept (the lattice, half samples, a hint).
_REMEMBERED_FRACTIONS = 4
# Dead times whose triangular factors are kept per filter: the warm start's look at the data's
# guess and the automatic start after it factor the same ones.
_REMEMBERED_FACTORS = 8
# Above this condition number (1-norm estimate) of the column-scaled filtered signals their
# triangular factor comes from a QR factorisation, not from the Gram matrix: the Gram route's
# error, about cond^2 rounding errors, stays below 1e-9 of the equation error's smallest
# singular direction (measured: the equation-error fits agree with QR's to 1e-12).
_GRAM_CONDITION = 1e3
# Discretised state-variable filters kept for every problem: the records of one length and
# sample time (a node's windows, a benchmark's records, a record's halves) use the same ones.
_SHARED_FILTERS = 64
# An equation-error fit whose coefficients all shrank by more than this from its start has
# slid towards the trivial zero of R [den; num] (fits found there: 1e-34 to 1e-162); one
# whose coefficients grew by more than its inverse has run off to a limit of the structure
# (a mass to infinity: fits found there at 1e147 to 1e153).
_COLLAPSE = 1e-12
# Per fitted model, per mask of free parameters: whether a coefficient no free parameter moves
# is nonzero (:meth:`_EquationError.anchored`): a property of the structure, asked once.
_ANCHORED: 'weakref.WeakKeyDictionary[FittedModel, Dict[bytes, bool]]' = \
    weakref.WeakKeyDictionary()


def _given_values(model: FittedModel, initial: Initial) -> Dict[str, float]:
    """Return the given initial values by name, checked against the model."""
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


def initial_estimate(problem: Problem, initial: Initial, delay_range: DelayRange,
                     pin: Optional[Mapping[str, float]] = None, as_given: bool = True
                     ) -> State:
    """
    Return the starting state of the iteration.

    The user's values compete with the equation-error multi-start described in the module
    docstring (missing values are fitted, given ones serve as hints, or stay fixed while others
    are missing); the candidate with the lowest output-error cost wins. A far or unstable guess
    therefore costs robustness nothing. ``pin`` holds further parameters at given values (a
    nested structure: a lag at its limit). Without ``as_given`` the starts themselves (the
    user's values; without them the all-ones vector and the random draws) compete only if no
    equation-error fit gives an admissible model: a caller that looks for the data's own
    guess, not for a start, need not simulate them.

    """
    model = problem.model
    given = _given_values(model, initial)
    pin = dict(pin or {})
    for name, value in given.items():
        index = model.parameters.index(name)
        if not problem.lower[index] <= value <= problem.upper[index]:
            raise ModelError(f'initial value {name}={value:g} lies outside its bounds '
                             f'[{problem.lower[index]:g}, {problem.upper[index]:g}]')
    # A complete guess is a hint for every parameter; a partial one pins the given values.
    pinned = dict({} if len(given) == len(model.parameters) else given, **pin)
    given = dict(given, **pin)
    delay_index = delay_parameter(model)
    filters = default_filters(problem)
    free = np.array([name not in pinned for name in model.parameters])
    if delay_index is not None:
        free[delay_index] = False
    taus = _initial_delays(problem, given, pinned, delay_index, delay_range)
    # The starts at a dead time are drawn once: the fits and the competition as given use them.
    points: Dict[float, List[np.ndarray]] = {}

    def starts_at(tau: float) -> List[np.ndarray]:
        if tau not in points:
            points[tau] = _start_points(problem, given, pinned, delay_index, tau)
        return points[tau]

    fit = None
    # The models the fits gave so far: a fit that is one of them again is not simulated again.
    seen: List[List[float]] = []
    for tau in taus:
        starts = starts_at(tau)
        # Every filter fits from the hint; the random starts of a non-affine structure then
        # look for other equation-error minima with the filter that simulated best.
        found, index = _best_filter_fit(problem, starts[:1], free, tau, filters, seen)
        if found is not None and len(starts) > 1:
            more, _ = _best_filter_fit(problem, starts[1:], free, tau, filters.select(index),
                                       seen)
            found = _lower_cost(found, more)
        fit = _lower_cost(fit, found)
    best = fit
    if as_given or best is None:
        # The user's values compete as given, their dead time not rounded to a sample.
        hinted_tau = taus[0] if delay_index is None else \
            given.get(model.parameters[delay_index], taus[0])
        best = _lower_cost(fit, best_candidate(problem, starts_at(hinted_tau)))
    if best is None and model.is_affine:
        # Every fit has an unstable D (a lightly damped plant, a biased equation error): its
        # unstable roots mirrored into the left half plane give a stable start nearby.
        for tau in taus:
            hint = starts_at(tau)[:1]
            for index in range(filters.count):
                fits = equation_error_fits(problem, hint, free, tau, filters.select(index))
                mirrored = (stabilized(problem, theta, free) for theta in fits)
                best = _lower_cost(best, best_candidate(
                    problem, [theta for theta in mirrored if theta is not None]))
    if best is None:
        raise EstimationError(
            'no stable starting model was found: the initial values give an unstable or '
            'out-of-bounds D(s), and the automatic initialisation found none either; give '
            'initial values that make the model stable, or check the bounds')
    return best


def stabilized(problem: Problem, theta: np.ndarray, free: np.ndarray) -> Optional[np.ndarray]:
    """
    Return ``theta`` with the unstable roots of ``D`` mirrored into the left half plane.

    For an affine structure ``D`` is linear in the parameters: the free ones are refitted by
    least squares to the mirrored polynomial (the others kept); None if that is impossible.
    """
    model = problem.model
    try:
        coefficients = model.coefficients(theta)
    except ModelError:
        return None
    den = coefficients.den
    if den.size < 2 or den[0] == 0.0:
        return None
    roots = np.roots(den)
    scale = max(float(np.abs(roots).max()), np.finfo(float).tiny)
    mirrored = np.where(roots.real >= 0.0, -np.abs(roots.real) - 1e-3 * scale + 1j * roots.imag,
                        roots)
    target = np.real(den[0] * np.poly(mirrored))
    jacobian = coefficients.den_jacobian[free].T            # d den / d theta_free
    if not jacobian.any():
        return None
    step = least_squares(jacobian, target - den)
    result = theta.copy()
    result[free] = theta[free] + step
    return np.clip(result, problem.lower, problem.upper)


def complete_guess(problem: Problem, initial: Initial) -> Optional[State]:
    """Return the state at the given values if they name every parameter and are admissible."""
    given = _given_values(problem.model, initial)
    if len(given) < len(problem.model.parameters):
        return None
    theta = problem.model.vector(given)
    coefficients = problem.admissible(theta)
    if coefficients is None:
        return None
    return problem.state(theta, coefficients)


def best_candidate(problem: Problem, candidates: Sequence[np.ndarray],
                   seen: Optional[List[List[float]]] = None) -> Optional[State]:
    """
    Return the admissible candidate with the lowest output-error cost (a state), or None.

    With ``seen`` (a list, extended here), a candidate whose model is one scored before (its
    coefficients equal to 1e-6 relative, :func:`_model_vector`) is skipped: it would simulate
    to the same cost up to rounding. Fits from different starts often reach the same model,
    by the same parameters or by a twin (two lags swapped).
    """
    best = None
    for theta in candidates:
        coefficients = problem.admissible(theta)
        if coefficients is None:
            continue
        if seen is not None:
            model = _model_vector(coefficients)
            if any(_equal_to_a_millionth(model, other) for other in seen):
                continue
            seen.append(model)
        state = problem.state(theta, coefficients)
        if best is None or state.cost < best.cost:
            best = state
    return best


def _model_vector(coefficients) -> List[float]:
    """Return the numerators, denominator and dead time of a model as one list."""
    return coefficients.num.ravel().tolist() + coefficients.den.tolist() + [coefficients.delay]


def _equal_to_a_millionth(first: Sequence[float], second: Sequence[float]) -> bool:
    """
    Return ``np.allclose(first, second, rtol=1e-6, atol=0)`` for finite values.

    The same test in Python floats: lists of a few numbers, compared many times, where numpy's
    per-call cost would be most of the work.
    """
    return all(abs(one - other) <= 1e-6 * abs(other) for one, other in zip(first, second))


def _lower_cost(first: Optional[State], second: Optional[State]) -> Optional[State]:
    """Return the state of lower cost; either may be None."""
    if first is None or (second is not None and second.cost < first.cost):
        return second
    return first


def distinct(thetas: Sequence[np.ndarray]) -> List[np.ndarray]:
    """
    Drop parameter vectors equal (to 1e-6 relative) to an earlier one.

    Fits from different starts often reach the same minimum, which need not be simulated twice.

    """
    kept: List[np.ndarray] = []
    values: List[List[float]] = []
    for theta in thetas:
        listed = theta.tolist()
        if not any(_equal_to_a_millionth(listed, other) for other in values):
            kept.append(theta)
            values.append(listed)
    return kept


def _best_filter_fit(problem: Problem, starts: Sequence[np.ndarray], free: np.ndarray,
                     tau: float, filters: 'StateVariableFilters', seen: List[List[float]]
                     ) -> Tuple[Optional[State], Optional[int]]:
    """
    Return the equation-error fit that simulates best over all filters, and its filter index.

    Returns ``(None, None)`` if no fit gives an admissible model not ``seen`` before
    (:func:`best_candidate`).

    """
    best, chosen = None, None
    # Every filter's fits first: their input parts in one pass, the fit's set-up done once.
    for index, fits in enumerate(_fits_by_filter(problem, starts, free, tau, filters)):
        state = best_candidate(problem, distinct(fits), seen)
        if state is not None and (best is None or state.cost < best.cost):
            best, chosen = state, index
    return best, chosen


def _initial_delays(problem: Problem, given: Mapping[str, float], pinned: Mapping[str, float],
                    delay_index: Optional[int], delay_range: DelayRange) -> List[float]:
    """
    Return the dead times the equation-error start is fitted at.

    The given one (alone if it is pinned), and the data's own guess from the impulse response
    unless a given dead time is pinned: a far guess then costs the start nothing. Unpinned
    values are rounded to whole samples (within the bounds), where the filtered input is a
    shift of one filtering; the iteration resolves the fraction.

    """
    if delay_index is None:
        return [0.0]
    name = problem.model.parameters[delay_index]
    if name in pinned:
        return [pinned[name]]
    low, high = problem.delay_bracket(delay_index, delay_range)
    taus = [given[name]] if name in given else []
    taus.append(float(np.clip(problem.delay_guess, low, high)))
    lower, upper = problem.lower[delay_index], problem.upper[delay_index]
    whole = [problem.on_delay_lattice(tau) for tau in taus]
    return list(dict.fromkeys(rounded if lower <= rounded <= upper else tau
                              for tau, rounded in zip(taus, whole)))


def random_starts(problem: Problem, theta: np.ndarray, delay_index: Optional[int]
                  ) -> List[np.ndarray]:
    """
    Return the random draws of the automatic start (none for an affine structure).

    The same seeded, log-uniform draws the equation-error multi-start uses, with the dead time
    of ``theta``: starts for output-error iterations elsewhere in the parameter space.
    """
    tau = 0.0 if delay_index is None else float(theta[delay_index])
    return _start_points(problem, {}, {}, delay_index, tau)[1:]


def _start_points(problem: Problem, hints: Mapping[str, float], pinned: Mapping[str, float],
                  delay_index: Optional[int], tau: float) -> List[np.ndarray]:
    """
    Return starting points: the user's hints first, then random draws.

    Draws are log-uniform over 1e-2..1e2, or over the box where it is finite (uniform when the
    box includes zero), seeded so a fit is reproducible. Pinned values and the dead time are the
    same in every start.

    """
    model = problem.model
    count = len(model.parameters)
    lower, upper = problem.lower, problem.upper
    boxed = np.isfinite(lower) & np.isfinite(upper)
    positive_box = boxed & (lower > 0)
    hinted = np.array([hints.get(name, np.nan) for name in model.parameters])
    fixed = np.array([pinned.get(name, np.nan) for name in model.parameters])
    guesses = [np.where(np.isnan(hinted), 1.0, hinted)]
    # The equation error of an affine structure is linear in theta: one start finds its optimum.
    if not model.is_affine:
        # low + (high - low) * draw, as Generator.uniform computes it from the same draws.
        draws = _uniform_draws(count)
        wide = -2.0 + 4.0 * draws[:, 0]
        log_lower = np.log(np.where(positive_box, lower, 1.0))
        log_upper = np.log(np.where(positive_box, upper, 1.0))
        in_log_box = np.exp(log_lower + (log_upper - log_lower) * draws[:, 1])
        box_lower, box_upper = np.where(boxed, lower, 0.0), np.where(boxed, upper, 1.0)
        in_box = box_lower + (box_upper - box_lower) * draws[:, 2]
        guesses.extend(np.where(boxed & ~positive_box, in_box,
                                np.where(positive_box, in_log_box, 10.0 ** wide)))
    # All starts at once: each row clipped and pinned as it would be alone.
    starts = np.where(np.isnan(fixed), np.clip(np.array(guesses), lower, upper), fixed)
    if delay_index is not None:
        starts[:, delay_index] = tau
    return list(starts)


@lru_cache(maxsize=16)
def _uniform_draws(count: int) -> np.ndarray:
    """
    Return the seeded uniform draws behind :func:`_start_points`'s random starts.

    Shape ``(_RANDOM_STARTS, 3, count)``: per start, the draws of the log-uniform value over
    1e-2..1e2, of the log-uniform value in a positive box and of the uniform value in a box,
    in the order one generator gave them. They depend on the number of parameters only, so a
    generator is seeded and drawn from once, not at every start.
    """
    draws = np.random.default_rng(20131).random((_RANDOM_STARTS, 3, count))
    draws.setflags(write=False)
    return draws


class StateVariableFilters:
    """
    Signals ``p^j/E`` of the data for the state-variable filters ``E = (p + lam)^n``.

    The output, initial-state and offset parts do not depend on the dead time and are filtered
    once. The input parts of a dead time ``(d + f) ts`` are the input parts of ``f ts`` shifted
    by ``d`` samples (exact: the filters start at rest), so a delay grid on the sample lattice
    (or on half samples) filters the input once per filter and fraction.

    It keeps the problem's signal bank and sample time, not the problem itself, so that the
    cache of :func:`default_filters` (keyed weakly by the problem) lets the problem go.

    """

    def __init__(self, problem: Problem, lams: np.ndarray):
        model, data = problem.model, problem.data
        n, m = model.den_degree, model.num_degree
        # Row j of the identity is the numerator p^(n - j): the output parts p^n/E .. 1/E
        # and the input parts p^m/E .. 1/E, as 2-D arrays (mapped in one pass).
        powers = np.eye(n + 1)
        self._u_powers = powers[n - m:]
        self._bank, self._ts = problem.bank, data.ts
        self._filters = []
        filters_of = [(n, float(lam), data.ts) for lam in lams]
        # Every filter's y in one pass (filter_responses).
        y_responses = filter_responses([_filter_discretized(*filter_of, 0.0, 'foh')
                                        for filter_of in filters_of], data.y)
        for filter_of, y_response in zip(filters_of, y_responses):
            y_parts = y_response.outputs(powers)
            nuisance = []
            if problem.initial_state or problem.output_offset:
                # Both act on y from t_0, so they are filtered without the input's dead time.
                undelayed = _filter_discretized(*filter_of, 0.0, 'zoh')
                if problem.initial_state:
                    nuisance.append(undelayed.free_responses(len(data)).T)
                if problem.output_offset:
                    nuisance.append(undelayed.outputs(np.ones(len(data)), [np.ones(1)]))
            self._filters.append(_FilterSignals(filter_of, nuisance, y_parts))

    def factors(self, tau: float) -> List[np.ndarray]:
        """
        Triangular factors ``R`` of ``[p^j/E y, -p^j/E u_c]`` ordered like ``(den, num)``.

        Initial-state and offset components of the equation error (if the problem estimates
        them) are projected out first. A filter's factor depends on the dead time's whole
        samples and fraction only: the latest are kept.

        """
        bank, ts = self._bank, self._ts
        delay = tau + bank.extra_delay
        whole = int(np.floor(delay / ts + 1e-9))
        fraction = round(max(delay / ts - whole, 0.0), 9)
        # The input parts of every filter that needs them, in one pass (filter_responses).
        key = (whole, fraction)
        missing = [signals for signals in self._filters
                   if key not in signals.by_shift and fraction not in signals.by_fraction]
        if missing:
            parts = self._input_parts([signals.filter_of for signals in missing], fraction * ts)
            for signals, part in zip(missing, parts):
                by_fraction = signals.by_fraction
                if len(by_fraction) >= _REMEMBERED_FRACTIONS:
                    del by_fraction[next(iter(by_fraction))]
                by_fraction[fraction] = part
        factors = []
        for signals in self._filters:
            by_shift = signals.by_shift
            factor = by_shift.get(key)
            if factor is None:
                factor = signals.factor(whole - bank.trim, fraction)
                if len(by_shift) >= _REMEMBERED_FACTORS:
                    del by_shift[next(iter(by_shift))]
                by_shift[key] = factor
            factors.append(factor)
        return factors

    @property
    def count(self) -> int:
        """Return the number of filters."""
        return len(self._filters)

    def select(self, index: int) -> 'StateVariableFilters':
        """Return the same signals for filter ``index`` only."""
        chosen = object.__new__(StateVariableFilters)
        chosen.__dict__.update(self.__dict__)
        chosen._filters = self._filters[index:index + 1]
        return chosen

    def _input_parts(self, filters_of: List[Tuple[int, float, float]], delay: float
                     ) -> List[np.ndarray]:
        """
        Return ``p^j/E e^{-delay p} u_c`` for every channel, as rows, for every filter.

        ``filters_of`` are the filters' ``(order, lam, ts)``. The input is the one the
        simulations run on (extended by a sample under an output skew, whose extra dead time
        ``delay`` includes): the caller drops the first sample then.
        """
        discretes = [_filter_discretized(*filter_of, delay, self._bank.intersample)
                     for filter_of in filters_of]
        channels = [[response.outputs(self._u_powers)
                     for response in filter_responses(discretes, channel)]
                    for channel in self._bank.driving.T]
        if len(channels) == 1:
            # One channel's parts as they are: concatenating one array would copy it.
            return channels[0]
        return [np.concatenate([outputs[index] for outputs in channels])
                for index in range(len(discretes))]


class _FilterSignals:
    """
    One state-variable filter's signals of the data, and the factors formed from them.

    The signals are rows (one per column of the equation error's regressors): ``fixed``, the
    ones that do not depend on the dead time (the initial-state and offset parts, then the
    output parts); ``by_fraction``, the input parts (unshifted, as long as the simulations'
    input) by the dead time's fraction of a sample; ``by_shift``, the factors by the dead
    time's whole samples and fraction. A factor's signals ``[fixed; -u_parts]`` are written
    into a buffer of the thread's (:func:`_signals_buffer`): the fixed ones when the buffer
    last held another filter's, the delayed input parts every time (no shifted copy, negated
    copy and joined columns per dead time), each a contiguous copy of whole rows.
    """

    __slots__ = ('filter_of', 'fixed', 'leading', 'by_fraction', 'by_shift', 'own_signals',
                 '__weakref__')

    def __init__(self, filter_of: Tuple[int, float, float], nuisance: List[np.ndarray],
                 y_parts: np.ndarray):
        self.filter_of = filter_of
        self.fixed = np.concatenate(nuisance + [y_parts]) if nuisance else y_parts
        self.leading = sum(part.shape[0] for part in nuisance)
        self.by_fraction: Dict[float, np.ndarray] = {}
        self.by_shift: Dict[Tuple[int, float], np.ndarray] = {}
        # Signals too long for the thread's buffers (:data:`_KEPT_SIGNALS_SIZE`), kept here.
        self.own_signals: Optional[np.ndarray] = None

    def factor(self, offset: int, fraction: float) -> np.ndarray:
        """Return the factor of the columns, ``u_parts[k]`` the input parts' ``k - offset``."""
        parts, fixed = self.by_fraction[fraction], self.fixed
        size, count = fixed.shape
        signals = _signals_buffer(self, (size + parts.shape[0], count))
        inputs = signals[size:]
        # -shifted(parts.T, -offset)[:count].T, written in place (its zeros negated too).
        if offset >= 0:
            samples = count - offset if offset < count else 0
            inputs[:, :count - samples] = -0.0
            np.negative(parts[:, :samples], out=inputs[:, count - samples:])
        else:
            # A negative dead time (a caller of StateVariableFilters' own): the tail is zeros.
            samples = max(min(count, parts.shape[1] + offset), 0)
            np.negative(parts[:, -offset:samples - offset], out=inputs[:, :samples])
            inputs[:, samples:] = -0.0
        leading = self.leading
        # The columns are the buffer's transpose, a view: numpy's Gram matrix of them
        # (signals @ signals.T) is the one of the same columns laid out row by row, to the bit.
        factor = _triangular_factor(signals.T)[leading:, leading:]
        factor.setflags(write=False)
        return factor


# Per thread, the signals buffers of the latest filters: a factor's signals go into memory the
# thread has written before, where a new array of a record's length would map fresh pages
# (each first write a page fault: on a 10 000-sample record more time than the filling).
# At most _KEPT_SIGNALS buffers of at most _KEPT_SIGNALS_SIZE numbers (2 MiB) each stay with a
# thread; longer signals stay with their filter, as long as the problem.
_SIGNALS = threading.local()
_KEPT_SIGNALS = 6
_KEPT_SIGNALS_SIZE = 1 << 18


def _signals_buffer(signals: _FilterSignals, shape: Tuple[int, int]) -> np.ndarray:
    """Return a buffer for the rows of ``signals``' factors, its fixed rows filled."""
    if shape[0] * shape[1] > _KEPT_SIGNALS_SIZE:
        buffer = signals.own_signals
        if buffer is None or buffer.shape != shape:
            buffer = signals.own_signals = np.empty(shape)
            buffer[:signals.fixed.shape[0]] = signals.fixed
        return buffer
    kept = getattr(_SIGNALS, 'buffers', None)
    if kept is None:
        kept = _SIGNALS.buffers = {}
    key = signals.filter_of, shape
    buffer, filler = kept.pop(key, (None, None))
    if buffer is None:
        buffer = np.empty(shape)
    if filler is None or filler() is not signals:
        buffer[:signals.fixed.shape[0]] = signals.fixed
    kept[key] = buffer, weakref.ref(signals)
    if len(kept) > _KEPT_SIGNALS:
        del kept[next(iter(kept))]
    return buffer


@lru_cache(maxsize=_SHARED_FILTERS)
def _filter_discretized(order: int, lam: float, ts: float, delay: float, hold: str
                        ) -> DiscreteFilter:
    """
    Return ``1/(p + lam)^order`` discretised with sample time ``ts``, dead time and hold.

    It depends on these numbers only, not on the data: every problem of the same sample time
    and length (:func:`filter_bandwidths`) shares it. Kept here although
    :meth:`ContinuousFilter.discretize` keeps its discretisations too: a hit here is one call,
    where reaching that cache builds the realisation first (``np.poly``, its roots and
    balancing) and then forms the cache's key under its lock: 67 to 96 profiled calls (orders
    1 to 4) for each of the six filters of a problem.
    """
    realization = ContinuousFilter(np.poly(np.full(order, -lam)) if order else np.ones(1))
    return realization.discretize(ts, delay, hold)


def _triangular_factor(columns: np.ndarray) -> np.ndarray:
    """
    Return a triangular ``R`` with ``|columns c| = |R c|`` for every ``c`` (``R^T R`` = Gram).

    The columns scaled to unit norm (``columns / scales = Q R_s``, so ``R = R_s * scales``)
    are factored by the Cholesky factor of their Gram matrix: one pass over the record
    instead of a QR factorisation's several. Its quadratic form is exact to about
    ``cond(R_s)^2`` rounding errors, so it serves only where the scaled columns are well
    conditioned (:data:`_GRAM_CONDITION`; the state-variable filters of the reference systems
    give 1-170); otherwise LAPACK's QR factorisation (geqrf, as ``np.linalg.qr(mode='r')``
    calls it) of the scaled columns. ``columns`` is left as it is.
    """
    gram = gram_matrix(columns)
    scales = np.sqrt(gram.diagonal())
    scales[scales == 0.0] = 1.0
    cholesky, info = lapack.dpotrf(gram / (scales[:, None] * scales))      # np.outer's
    if info == 0 and lapack.dtrcon(cholesky)[0] > 1.0 / _GRAM_CONDITION:
        return cholesky * scales
    # The columns laid out row by row: numpy's norms sum a strided axis in another order.
    columns = np.ascontiguousarray(columns)
    scales = np.linalg.norm(columns, axis=0)
    scales[scales == 0.0] = 1.0
    factored, _, _, info = lapack.dgeqrf(np.asfortranarray(columns / scales), overwrite_a=True)
    if info != 0:
        raise np.linalg.LinAlgError(f'QR factorisation failed (LAPACK info {info})')
    return np.triu(factored[:min(columns.shape)]) * scales


# The filtered signals of each problem's default filters: the automatic start, the dead-time
# search and every nested structure filter the same data with the same filters. The values
# must not refer to their problem, or no entry would ever be dropped.
_DEFAULT_FILTERS: 'weakref.WeakKeyDictionary[Problem, StateVariableFilters]' = \
    weakref.WeakKeyDictionary()


def default_filters(problem: Problem) -> StateVariableFilters:
    """Return the :data:`FILTER_COUNT` filters of :func:`filter_bandwidths`, once per problem."""
    filters = _DEFAULT_FILTERS.get(problem)
    if filters is None:
        filters = StateVariableFilters(problem, filter_bandwidths(problem.data, FILTER_COUNT))
        _DEFAULT_FILTERS[problem] = filters
    return filters


def filter_bandwidths(data: Data, count: int) -> np.ndarray:
    """Return ``count`` filter corners from ten per record to 0.3 of the Nyquist frequency."""
    return _bandwidths(data.ts, len(data), count)


@lru_cache(maxsize=_SHARED_FILTERS)
def _bandwidths(ts: float, samples: int, count: int) -> np.ndarray:
    """Return :func:`filter_bandwidths` (read-only) for records of this sample time and length."""
    # Kept like the filters they define: geomspace alone costs tens of Python-level calls.
    corners = np.geomspace(10.0 / (ts * samples), 0.3 * np.pi / ts, count)
    corners.setflags(write=False)
    return corners


def equation_error_fits(problem: Problem, starts: Sequence[np.ndarray], free: np.ndarray,
                        tau: float, filters: StateVariableFilters) -> List[np.ndarray]:
    """
    Return the equation-error fits of every filter from every start.

    Only the ``free`` parameters are fitted; the others (the dead time ``tau`` among them) keep
    their start values.

    """
    return [theta for fits in _fits_by_filter(problem, starts, free, tau, filters)
            for theta in fits]


def _fits_by_filter(problem: Problem, starts: Sequence[np.ndarray], free: np.ndarray,
                    tau: float, filters: StateVariableFilters) -> List[List[np.ndarray]]:
    """Return :func:`equation_error_fits`, filter by filter (none for nothing free)."""
    model = problem.model
    if not free.any():
        return [[] for _ in range(filters.count)]
    lower, upper = problem.lower[free], problem.upper[free]
    by_filter = []
    equation = _EquationError(model, free)
    solution = equation.linear_solution if model.is_affine else equation.local_solution
    # A non-affine structure with no fixed coefficient is fitted scale-free; only its fits can
    # collapse or run off (:meth:`_EquationError.collapsed`): the others skip the check. An
    # affine one keeps its exact solve: with no fixed coefficient its coefficients are (but
    # for contrived structures) linear and homogeneous in the parameters, c = G theta, every
    # multiple of theta is the same model, and the estimate says the parameters are not
    # identifiable whatever the start.
    anchored = model.is_affine or not starts or equation.anchored(starts[0])
    if not anchored:
        solution = equation.scale_free_solution
    for factor in filters.factors(tau):
        fits = []
        for start in starts:
            theta = start.copy()
            try:
                theta[free] = solution(factor, start, lower, upper)
                if not anchored and equation.collapsed(start, theta):
                    continue
            except (ValueError, ModelError, np.linalg.LinAlgError):
                continue
            fits.append(theta)
        by_filter.append(fits)
    return by_filter


class _EquationError:
    """Residual ``R [den; num]`` of a filter's factor ``R`` by the free parameters."""

    def __init__(self, model: FittedModel, free: np.ndarray):
        self._model = model
        self._free = free
        # Integer positions: a trial's values go into its parameter vector by one indexing.
        self._positions = free.nonzero()[0]
        # The coefficients as one flat array, [den; num] and their gradients read from it by
        # one indexing each: a Model's own coefficient array (thousands of evaluations per
        # fit); a StabilizedModel changes D, so its coefficients are laid out the same way.
        nums = (len(model.inputs) + int(model.constant_input)) * (model.num_degree + 1)
        if isinstance(model, Model):
            self._evaluate = model.coefficient_array
            self._order = np.concatenate([np.arange(nums, nums + model.den_degree + 1),
                                          np.arange(nums)])
            rows = nums + model.den_degree + 2          # ... and the dead time
        else:
            self._evaluate = self._stabilized_array
            rows = model.den_degree + 1 + nums
            self._order = np.arange(rows)
        # After the coefficients, one row per coefficient of its derivatives by the
        # parameters: the free ones' gradients of [den; num].
        self._gradient = rows + self._order[None, :] * free.size + self._positions[:, None]
        # The latest start evaluated, and its [den; num] and their gradients: every filter
        # fits from the same starts.
        self._latest: Tuple[Optional[bytes], Optional[Tuple[np.ndarray, ...]]] = (None, None)

    def _at(self, point: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the evaluation at ``point``, its ``[den; num]`` and their gradients' rows."""
        key = point.tobytes()
        if key != self._latest[0]:
            evaluated = self._evaluate(point)
            self._latest = key, (evaluated, evaluated[self._order], evaluated[self._gradient].T)
        return self._latest[1]

    def anchored(self, point: np.ndarray) -> bool:
        """
        Return True if a coefficient no free parameter moves is nonzero (judged at ``point``).

        ``R [den; num]`` vanishes at ``den = num = 0``. Such a coefficient (the 1 of ``T s +
        1``, a known numerator) keeps every fit away from there; see :meth:`collapsed`.
        """
        known = _ANCHORED.setdefault(self._model, {})
        key = self._free.tobytes()
        if key not in known:
            _, coefficients, gradients = self._at(point)
            moved = np.abs(gradients).sum(axis=1) > 0.0
            known[key] = bool(((coefficients != 0.0) & ~moved).any())
        return known[key]

    def collapsed(self, start: np.ndarray, fit: np.ndarray) -> bool:
        """
        Return True if the fit from ``start`` shrank or grew its coefficients without bound.

        Where no coefficient is fixed (:meth:`anchored`: a two-mass drive, ``(J2 s^2 + c s +
        k)/(J1 J2 s^3 + (J1 + J2) c s^2 + ...)``) a fit of ``|R [den; num]|`` could slide
        towards its trivial zero instead of fitting the data: ``J2, c, k -> 0`` with every
        coefficient below 1e-34 of its start's, a model that is no model. The scale-free fit
        (:meth:`scale_free_solution`) cannot, but it can run off to a limit of the structure
        (``J2 -> 1e148``: the load's inertia infinite), a model no simulation can use.
        """
        if self.anchored(start):
            return False
        coefficients = self._at(start)[1]
        fitted = self._at(fit)[1]
        size, start_size = float(fitted @ fitted), float(coefficients @ coefficients)
        return not _COLLAPSE ** 2 * start_size <= size <= start_size / _COLLAPSE ** 2

    def _stabilized_array(self, theta: np.ndarray) -> np.ndarray:
        """Return ``[den; num]`` and then each one's derivatives by the parameters, flat."""
        coefficients = self._model.coefficients(theta)
        gradients = np.hstack([coefficients.den_jacobian,
                               coefficients.num_jacobian.reshape(self._free.size, -1)])
        return np.concatenate([coefficients.den, coefficients.num.ravel(), gradients.T.ravel()])

    def scale_free_solution(self, factor: np.ndarray, start: np.ndarray, lower: np.ndarray,
                            upper: np.ndarray) -> np.ndarray:
        """
        Return a local minimiser of ``|R c| / |c|`` from ``start``, ``c = [den; num]``.

        The fit of a structure with no fixed coefficient (:meth:`anchored`): the ratio is the
        same at every scale of ``c``, so it cannot reward sliding towards ``c = 0``, the
        trivial zero of ``|R c|``, whatever the bounds (the bounds stopped that slide with a
        parameter on its bound, a wrong basin, not the trivial zero :meth:`collapsed` drops).
        """
        return self.local_solution(factor, start, lower, upper, scale_free=True)

    def local_solution(self, factor: np.ndarray, start: np.ndarray, lower: np.ndarray,
                       upper: np.ndarray, scale_free: bool = False) -> np.ndarray:
        """
        Return a local minimiser from ``start``: Levenberg-Marquardt projected onto the box.

        It minimises ``|R c|`` of the coefficients ``c = [den; num]``, or with ``scale_free``
        ``|R c| / |c|`` (:meth:`scale_free_solution`): residual ``R c / |c|``, Jacobian
        ``(R G - (R c / |c|) (c^T G / |c|)) / |c|`` with ``G = dc/dtheta``.

        The problem has a handful of rows and parameters, so scipy's general solvers would spend
        most of their time on their own bookkeeping; a start needs no more digits than the
        projection iteration corrects (relative change of parameters or cost below
        ``_START_TOLERANCE``).

        Its bookkeeping on the handful of free values mixes numpy's ufuncs (the step, held on
        the bounds the gradient pushes against and clipped into the box) with Python floats
        (whether a value is on a bound at all, whether a step is finite, the relative change):
        the same arithmetic either way, at the fewest calls and operations.
        """
        evaluate, order, rows = self._evaluate, self._order, self._gradient
        positions = self._positions
        # np.clip's arithmetic.
        values = np.minimum(np.maximum(start[self._free], lower), upper)
        # The whole parameter vector, its free values written in for each point evaluated
        # (the evaluation returns a new array and keeps nothing of it).
        point = start.copy()
        point[positions] = values
        evaluated = self._at(point)[0]
        coefficients = evaluated[order]
        residual = factor @ coefficients
        if scale_free:
            size = math.sqrt(coefficients.dot(coefficients))
            if not size > 0.0:
                return values               # no model at the start: nothing to scale by
            residual = residual / size
        # The products of the fit's own arrays (the Gram matrix, gradient and cost) by
        # ndarray.dot: the same numbers as the matmul operator's, without its ufunc machinery's
        # per-call work. The filter's factor keeps the operator: it may come in any memory
        # layout, for which the two can round differently.
        cost = residual.dot(residual)
        damping = 1e-3
        current, low, high = values.tolist(), lower.tolist(), upper.tolist()
        # Every (size + 1)-th entry of a flattened Gram matrix is on its diagonal: its damped
        # values are written over it for each damping, the rest stays.
        every_diagonal = slice(None, None, values.size + 1)
        for _ in range(_START_ITERATIONS):
            gradients = evaluated[rows].T
            jacobian = factor @ gradients
            if scale_free:
                jacobian = (jacobian - np.outer(residual, coefficients.dot(gradients) / size)
                            ) / size
            transposed = jacobian.T
            gram = transposed.dot(jacobian)
            gradient = transposed.dot(residual)
            # A parameter on a bound that the cost's gradient pushes outward is held there.
            # Moving it would be clipped back, and the other parameters' part of that step,
            # solved as if it moved, then creeps along the bound by damped steps (a lag
            # collapsing to its lower bound took up to the iteration limit instead of a few
            # steps). The values lie in the box: only one on a bound can be held.
            holding = False
            for value, bottom, top in zip(current, low, high):
                if value <= bottom or value >= top:
                    held = ((values <= lower) & (gradient > 0.0)) | \
                        ((values >= upper) & (gradient < 0.0))
                    holding = held.any()
                    break
            if holding:
                moving = ~held
                if not moving.any():
                    return values           # no descent direction inside the box
                # C-ordered for the flat view below (a column selection is not; a product is).
                gram = np.ascontiguousarray(gram[moving][:, moving])
                gradient = gradient[moving]
                diagonal = slice(None, None, gradient.size + 1)
            else:
                diagonal = every_diagonal
            flat = gram.ravel()
            original = flat[diagonal].copy()
            scaling = np.maximum(original, _TINY)
            while True:
                # gram + damping * diag(scaling), without forming the diagonal matrix.
                flat[diagonal] = original + damping * scaling
                # gesv leaves gram as it is; a singular one damps more.
                solution = solve_or_none(gram, gradient)
                # Finite solution: tested on its few Python floats, without numpy's per-call
                # work on a ufunc and its reduction.
                if solution is not None and all(map(math.isfinite, solution.tolist())):
                    if holding:
                        step = np.zeros(values.size)
                        step[moving] = -solution
                        trial = values + step
                    else:
                        trial = values - solution           # values + (-solution)
                    trial = np.minimum(np.maximum(trial, lower), upper)
                    point[positions] = trial
                    try:
                        trial_evaluated = evaluate(point)
                        trial_coefficients = trial_evaluated[order]
                        trial_residual = factor @ trial_coefficients
                    except ModelError:
                        trial_residual = None
                    if scale_free and trial_residual is not None:
                        trial_size = math.sqrt(trial_coefficients.dot(trial_coefficients))
                        trial_residual = trial_residual / trial_size if trial_size > 0.0 \
                            else None
                    if trial_residual is not None:
                        trial_cost = trial_residual.dot(trial_residual)
                        if trial_cost < cost:
                            break
                damping *= 4.0
                if damping > 1e12:
                    return values
            # The largest relative change below the tolerance: every one below it (abs and
            # max written out, the same values).
            moved = trial.tolist()
            settled = True
            for new, old in zip(moved, current):
                change = new - old if new >= old else old - new
                size = old if old >= 0.0 else -old
                if not change / (size if size >= 1e-12 else 1e-12) < _START_TOLERANCE:
                    settled = False
                    break
            decrease = 1.0 - trial_cost / cost
            values, current, residual, evaluated = trial, moved, trial_residual, trial_evaluated
            coefficients, cost = trial_coefficients, trial_cost
            if scale_free:
                size = trial_size
            damping /= 3.0
            if damping < 1e-9:          # max(damping, 1e-9) without the call
                damping = 1e-9
            if settled or decrease < _START_TOLERANCE:
                break
        return values

    def linear_solution(self, factor: np.ndarray, start: np.ndarray, lower: np.ndarray,
                        upper: np.ndarray) -> np.ndarray:
        """Exact minimiser for an affine structure (the residual is linear), within bounds."""
        values = start[self._free]
        _, coefficients, gradients = self._at(start)
        jacobian = factor @ gradients
        residual = factor @ coefficients
        step = least_squares(jacobian, -residual)
        moved = values + step
        if np.logical_and.reduce((moved >= lower) & (moved <= upper)):
            return moved
        return values + bounded_least_squares(jacobian, -residual, lower - values,
                                              upper - values)


def local_fit(problem: Problem, start: State, method: str, first_ls: bool,
              full_steps_only: bool = False, iterations: int = _LOCAL_ITERATIONS,
              frozen: Optional[np.ndarray] = None) -> IterationResult:
    """
    Return the outcome of a few iterations from ``start`` to a loose tolerance.

    ``frozen`` parameters (default none) keep their start values.

    With ``full_steps_only`` its reason is :attr:`StopReason.NO_FULL_STEP` if it gave up;
    otherwise (converged or not) the residual test of :func:`explains_data` judges the result.

    """
    policy = IterationPolicy(
        method=method, max_iterations=iterations,
        opening=Opening.LEAST_SQUARES if first_ls else Opening.PROJECTION,
        steps=Steps.FULL_ONLY if full_steps_only else Steps.CONTROLLED)
    return iterate(problem, start, policy, frozen)


def explains_data(problem: Problem, state: State, delay_index: Optional[int],
                  delay_range: DelayRange) -> bool:
    """
    Return True if the model at ``state`` leaves a residual independent of the input.

    The lags tested cover the model's settling time (its dead time included) plus, for a
    dead-time parameter, the upper end of its search range: a wrong dead time or a missed mode
    shows there (:mod:`ctid_ros.estimation.correlation`, ``docs/algorithm.md`` section 11).
    A model must also explain a tenth of the output's spread (a fit above 10 %): a model that
    explains nothing (a gain near zero) leaves the output itself as residual, which passes the
    test when its dynamics lie beyond the lags tested.

    """
    data = problem.data
    residual = np.zeros(len(data))
    residual[problem.skip:] = problem.measured - problem.prediction(state.coefficients)
    spread = problem.measured - problem.measured.mean()
    # np.linalg.norm's arithmetic for a vector, without its dispatch.
    if math.sqrt(residual.dot(residual)) > _UNEXPLAINED * math.sqrt(spread.dot(spread)):
        return False
    horizon = settling_time(state.coefficients)
    if delay_index is not None:
        horizon += problem.delay_bracket(delay_index, delay_range)[1]
    lags = int(np.ceil(horizon / data.ts))
    # Bartlett's bound counts the colour of residual and input (a held input with coloured
    # noise is no model error), and is calibrated at the local fit's optimum.
    return independent_of_input(residual, problem.bank.channels, min(lags, len(data) // 4),
                                bound='bartlett')


def resembles_output(problem: Problem, state: State) -> bool:
    """
    Return True if the model output at ``state`` is correlated with the measured output.

    The squared correlation of the two (both less their means) is the share of the output's
    variance the model output explains at its best scale; a start with a dead time far off
    explains almost none (below :data:`_RESEMBLANCE`), however close its other parameters.
    """
    measured = problem.measured - problem.measured.mean()
    output = problem.prediction(state.coefficients)
    output = output - output.mean()
    power = float((measured @ measured) * (output @ output))
    return power > 0.0 and float(measured @ output) ** 2 >= _RESEMBLANCE * power
