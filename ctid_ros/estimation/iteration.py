"""
The controlled projection iteration of the method.

At the current parameters the output error is projected onto the regressors ``phi``: the first
update by least squares, later ones by the instrumental-variable (oblique) projection with the
instruments ``psi``. Every update is controlled: the bounds truncate it, ``D`` must stay stable,
the output-error cost may not increase, and full steps are tried before halved ones and before
Gauss-Newton and Levenberg-Marquardt fallbacks. What a run does is one frozen
:class:`IterationPolicy`: the method, the limits, how the first update is taken
(:class:`Opening`), which steps an update may take (:class:`Steps`, from the named
:class:`Schedule`) and the optional tests. :func:`iterate` reports why it stopped as a
:class:`StopReason`. The equations are sections 5-8 of ``docs/algorithm.md``.
"""

from dataclasses import dataclass
import enum
from functools import lru_cache
import math
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

from ctid_ros.core.simulation import all_finite
from ctid_ros.estimation.linear_algebra import (condition, gram_matrix, solve_or_none,
                                                symmetric_eigen)
from ctid_ros.estimation.problem import Problem, State
from ctid_ros.estimation.regressors import Linearization
import numpy as np

__all__ = [
    'Attempt', 'Iteration', 'IterationPolicy', 'IterationResult', 'NEGLIGIBLE_STEP',
    'OPTIMALITY_LIMIT', 'Opening', 'Schedule', 'Steps', 'StopReason', 'column_scales',
    'free_parameters', 'iterate', 'on_bounds', 'optimality',
]

_HALVINGS = 14
# A step the box cuts stops this fraction of the way to the bound, strictly inside.
_INSIDE_BOX = 0.999
_FULL_STEP = (1.0,)
_HALVED_STEPS = tuple(0.5 ** np.arange(1, _HALVINGS))
_ALL_STEPS = _FULL_STEP + _HALVED_STEPS
# Steps tried on each side of a dead-time kink: enough to enter a basin, not to resolve it.
_KINK_STEPS = _ALL_STEPS[:4]
_IV_CONDITION_LIMIT = 1e10
_LM_DAMPINGS = (1e-2, 1.0, 1e2)
# An update smaller than this many standard deviations of the estimate changes nothing a user
# can see: the iteration stops instead of resolving noise to the last digit.
NEGLIGIBLE_STEP = 1e-3
# A point is a minimum for a user when the Gauss-Newton step from it (the projected gradient in
# the metric of the estimate's uncertainty) is below this many standard deviations.
OPTIMALITY_LIMIT = 0.1
# After a damped or halved update the statistical stop also measures the Gauss-Newton step
# without the directions the data barely see.
_STRUGGLING = 1
# Relative singular values of the scaled sensitivities below this carry no usable gradient
# information: the first-order model is swamped by second-order terms along such directions.
_OPTIMALITY_RCOND = 1e-6
# A scaled Gauss-Newton normal matrix whose eigenvalues lie within this ratio is solved
# directly (a relative error below 1e-8 in the step); a worse conditioned one by lstsq.
_NORMAL_CONDITION = 1e-8
# Updates over which min_progress measures the fall of the cost.
_PROGRESS_SPAN = 2
# After a full update shorter than this many standard deviations the IV iteration takes
# Gauss-Newton steps for as long as they are accepted in full. Chosen on the reference systems
# of bench/estimator.py: among 10, 30 and no limit, 30 needs the fewest simulations on most.
_NEAR_MINIMUM = 30.0
_TINY = np.finfo(float).tiny
_INF = math.inf
# After an IV update that the full Gauss-Newton step took with a fall of the cost by at least
# this share (far from a minimum), the next update tries that step first (_Run._rescued).
# Below it the IV step is tried first again: near a minimum or on a plateau Gauss-Newton
# predicts little and the IV step, which sees further, often goes on in full.
_RESCUE_DECREASE = 0.1


# A bound a step ran into: (parameter index, bound value).
_Bound = Tuple[int, float]
# What a tried step gives: the new state, the fraction of the step taken, the bound that cut it.
_Outcome = Tuple[State, float, Optional[_Bound]]


class StopReason(enum.Enum):
    """
    Why :func:`iterate` stopped (``docs/algorithm.md`` section 8).

    The value is the text users see (``Estimate.stop_reason``), with the iteration's
    ``tolerance`` and ``max_iterations`` filled in by :meth:`describe`.
    """

    ALL_AT_BOUNDS = 'all parameters fixed at bounds'
    NEGLIGIBLE_UPDATE = 'update below {negligible:g} standard deviations'
    NO_FULL_STEP = 'no full step decreases the cost'
    NO_DECREASE = 'no admissible step decreases the cost'
    PARAMETER_CHANGE = 'relative parameter change below {tolerance:g}'
    COST_DECREASE = 'relative cost decrease below resolution'
    EXACT_FIT = 'output reproduced exactly'
    ITERATION_LIMIT = 'iteration limit ({max_iterations}) reached'
    STALLED = 'stalled: the cost still decreases along its gradient'
    SLOW = 'the cost fell too slowly far from a minimum'

    @property
    def converged(self) -> bool:
        """Return True for a convergence test, False for the limit or a check that gave up."""
        return self not in (StopReason.NO_FULL_STEP, StopReason.ITERATION_LIMIT,
                            StopReason.STALLED, StopReason.SLOW)

    def describe(self, tolerance: float, max_iterations: int) -> str:
        """Return the text users see, with the iteration's settings filled in."""
        return self.value.format(negligible=NEGLIGIBLE_STEP, tolerance=tolerance,
                                 max_iterations=max_iterations)


@dataclass
class Iteration:
    """One accepted update: parameters after it, cost, step length and the direction used."""

    theta: np.ndarray
    cost: float
    step: float
    direction: str


@dataclass
class IterationResult:
    """
    Outcome of :func:`iterate`.

    Attributes
    ----------
    state : State
        Where the iteration ended (the start if no update was accepted).
    history : list of Iteration
        Every accepted update, in order.
    reason : StopReason
        The stopping rule that fired.
    message : str
        ``reason`` as users read it (``Estimate.stop_reason``).

    """

    state: State
    history: List[Iteration]
    reason: StopReason
    message: str

    @property
    def converged(self) -> bool:
        """Return True if a convergence test, not the limit or a give-up, stopped it."""
        return self.reason.converged


def column_scales(psi: np.ndarray) -> np.ndarray:
    """Column norms of ``psi`` (1 for a zero column): the scaling of every solve."""
    scales = np.linalg.norm(psi, axis=0)
    return np.where(scales > 0.0, scales, 1.0)


# Masks over the parameters (a handful) are tested as lists: the builtin any/all of a few
# Python bools costs a fraction of the array methods' reduction machinery.

def _block(matrix: np.ndarray, free: np.ndarray, every: Optional[bool] = None) -> np.ndarray:
    """
    Return the rows and columns of the free parameters (the matrix if all are free).

    ``every``: whether every parameter is free, if the caller knows already.
    """
    if every is None:
        every = all(free.tolist())
    return matrix if every else matrix[np.ix_(free, free)]


class _Side:
    """
    The sensitivities of one side of a dead-time kink and their small products.

    ``psi^T psi``, ``psi^T e`` and ``psi^T phi`` are the only record-length work of an update:
    every direction, gradient and measure of it follows from these ``p x p`` products.
    """

    def __init__(self, psi: np.ndarray, phi: Optional[np.ndarray], error: np.ndarray,
                 gradient: np.ndarray):
        self.psi = psi
        self.phi = phi
        self.error = error
        self.gradient = gradient                             # psi^T e = -dV/dtheta
        self._gram: Optional[np.ndarray] = None
        self._cross: Optional[np.ndarray] = None

    @property
    def gram(self) -> np.ndarray:
        """``psi^T psi``."""
        if self._gram is None:
            self._gram = gram_matrix(self.psi)
        return self._gram

    @property
    def cross(self) -> np.ndarray:
        """``psi^T phi``: the instrumental-variable normal matrix."""
        if self._cross is None:
            self._cross = self.psi.T @ self.phi
        return self._cross

    def scales(self, free: np.ndarray) -> np.ndarray:
        """:func:`column_scales` of the free columns, from the diagonal of the gram matrix."""
        scales = np.sqrt(self.gram.diagonal()[free])
        scales[~(scales > 0.0)] = 1.0                    # np.where's choice, in place
        return scales


class _Linear:
    """
    A linearisation with its output error: the equations of every update from one point.

    The sides are built when first asked for: ``'up'`` (the sensitivities as given, for a
    growing dead time) and ``'down'`` (with the feedthrough's jump, for a shrinking one), the
    same where the dead time is off the sample lattice.
    """

    def __init__(self, lin: Linearization, error: np.ndarray):
        self.lin = lin
        self.error = error
        count, params = lin.psi.shape
        self.variance = float(error @ error) / max(count - params, 1)
        # Whether the dead time's two sides differ (on the sample lattice): every direction
        # and side asks.
        self.kinked = lin.delay_jump is not None
        self._sides: Dict[str, _Side] = {}

    def side(self, which: str = 'up') -> _Side:
        """Return the products of the ``'up'`` or ``'down'`` sensitivities."""
        if not self.kinked:
            which = 'up'
        if which not in self._sides:
            lin = self.lin
            if which == 'up':
                self._sides[which] = _Side(lin.psi, lin.phi, self.error, lin.psi.T @ self.error)
            else:
                up = self.side('up')
                self._sides[which] = _Side(
                    lin.psi + lin.delay_jump,
                    None if lin.phi is None else lin.phi + lin.delay_jump, self.error,
                    up.gradient + lin.delay_jump.T @ self.error)
        return self._sides[which]

    def descends(self, step: np.ndarray) -> bool:
        """Return True if the cost falls along ``step`` (to first order, on its side)."""
        side = self.side('up' if self.delay_change(step) >= 0.0 else 'down')
        return float(side.gradient @ step) > 0.0

    def delay_change(self, step: np.ndarray) -> float:
        """Change of the dead time along ``step``, to first order (0 without a jump)."""
        if not self.kinked:
            return 0.0
        return float(self.lin.delay_gradient @ step)


def _bounded_direction(kind: str, linear: _Linear, free: np.ndarray, at_lower: np.ndarray,
                       at_upper: np.ndarray, damping: float = 0.0,
                       rcond: Optional[float] = None, side: str = 'auto'
                       ) -> Optional[np.ndarray]:
    """
    :func:`_direction`, with parameters on a bound that it would push outward held.

    A parameter on a bound is free when the cost falls inward, but the joint direction may
    still move it outward (through its correlation with the others); the box would then cut
    the step to nothing. Such parameters are held and the direction solved again.
    """
    free = free.copy()
    while True:
        step = _direction(kind, linear, free, damping, rcond, side)
        if step is None:
            return None
        outward = free & ((at_lower & (step < 0.0)) | (at_upper & (step > 0.0)))
        if not any(outward.tolist()):
            return step
        free &= ~outward
        if not any(free.tolist()):
            return None


def _direction(kind: str, linear: _Linear, free: np.ndarray, damping: float = 0.0,
               rcond: Optional[float] = None, side: str = 'auto') -> Optional[np.ndarray]:
    """
    Update direction on the free parameters (zeros elsewhere), or None if singular.

    ``kind`` is ``'ls'``, ``'iv'``, ``'gn'`` or ``'lm'``: equations (5.1)-(5.4) of
    ``docs/algorithm.md``, on columns scaled by the instrument norms. Where the dead time sits
    on the sample lattice and the sensitivities differ on its two sides, the direction is
    solved with the side it moves the dead time to; if neither side's solution moves it to
    its own side (a kink that is a minimum along the dead time), the dead time is held.
    ``rcond`` truncates the singular values of a Gauss-Newton solve (default: rounding).
    ``side`` ``'up'`` or ``'down'`` asks for a direction that grows (shrinks) the dead time or
    holds it.

    """
    if not linear.kinked:
        return _one_sided_direction(kind, linear.side(), free, damping, rcond)
    gradient = linear.lin.delay_gradient
    held = free & (gradient == 0.0)
    if side == 'auto':
        # The side where the cost falls faster first, then the other.
        rising, falling = _one_sided_gradients(linear)
        delays = free & (gradient != 0.0)
        # np.max is np.maximum.reduce behind Python wrappers: called directly.
        down_first = np.maximum.reduce(falling[delays], initial=0.0) > \
            np.maximum.reduce(rising[delays], initial=0.0)
        sides = ('down', 'up') if down_first else ('up', 'down')
    else:
        sides = (side,)
    for which in sides:
        step = _one_sided_direction(kind, linear.side(which), free, damping, rcond)
        change = 0.0 if step is None else linear.delay_change(step)
        if step is None or (change >= 0.0 if which == 'up' else change <= 0.0):
            return step
    if not any(held.tolist()):
        return None
    return _one_sided_direction(kind, linear.side(), held, damping, rcond)


def _one_sided_direction(kind: str, side: _Side, free: np.ndarray, damping: float,
                         rcond: Optional[float] = None) -> Optional[np.ndarray]:
    """Direction of :func:`_direction` with the sensitivities of one side."""
    every = all(free.tolist())              # every parameter free (as a rule): nothing to pick
    scales = side.scales(free)
    outer = scales[:, None] * scales                          # np.outer's own product
    rhs = side.gradient[free] / scales
    if kind == 'ls':
        phi_s = side.phi[:, free] / scales
        step = np.linalg.lstsq(phi_s, side.error, rcond=None)[0] / scales
    elif kind == 'iv':
        matrix = _block(side.cross, free, every) / outer
        if not all_finite(matrix) or condition(matrix) > _IV_CONDITION_LIMIT:
            return None
        step = solve_or_none(matrix, rhs)
        if step is None:
            return None
        step /= scales
    else:
        gram = _block(side.gram, free, every) / outer
        if not all_finite(gram):
            return None
        if kind == 'gn':
            step = _gauss_newton(side, free, scales, gram, rhs, rcond)
        else:
            step = solve_or_none(gram + damping * np.diag(np.diag(gram)), rhs)
            if step is None:
                return None
            step /= scales
    if not all(map(math.isfinite, step.tolist())):
        return None
    if every:
        return step
    full = np.zeros(free.size)
    full[free] = step
    return full


def _gauss_newton(side: _Side, free: np.ndarray, scales: np.ndarray, gram: np.ndarray,
                  rhs: np.ndarray, rcond: Optional[float]) -> np.ndarray:
    """
    Least-squares solution of ``psi step = e`` on the free columns (unscaled step).

    From the eigenpairs of the scaled normal matrix ``gram`` (right-hand side ``rhs``),
    dropping those whose singular value is below ``rcond`` of the largest; without ``rcond``
    where the matrix is well conditioned (the squared condition number costs nothing then),
    else by ``lstsq`` on the scaled sensitivities themselves, which resolves singular values
    down to rounding.
    """
    values, vectors = symmetric_eigen(gram)
    largest = max(values[-1], _TINY)
    if rcond is not None:
        kept = values > rcond ** 2 * largest
    elif values[0] > _NORMAL_CONDITION * largest:
        kept = np.ones(values.size, dtype=bool)
    else:
        # Scaled by the columns' own norms, as every solve was before the products: where the
        # rank is in doubt, which combination lstsq drops follows the rounding of its input.
        psi = side.psi[:, free]
        norms = column_scales(psi)
        return np.linalg.lstsq(psi / norms, side.error, rcond=None)[0] / norms
    return vectors[:, kept] @ ((vectors[:, kept].T @ rhs) / values[kept]) / scales


def _box_limit(theta: np.ndarray, step: np.ndarray, lower: np.ndarray, upper: np.ndarray
               ) -> Tuple[float, Optional[_Bound]]:
    """
    Largest fraction (<= 1) of ``step`` that keeps theta inside the box, and what limits it.

    A step the box cuts stops 0.999 of the way to the bound, and the bound is returned as
    ``(index, value)`` (None for a whole step).
    """
    # A handful of parameters: Python floats, not numpy's dispatch (the same IEEE quotients).
    nearest, index = math.inf, 0
    for i, (value, change, low, high) in enumerate(zip(theta.tolist(), step.tolist(),
                                                       lower.tolist(), upper.tolist())):
        if change != 0.0:
            reach = ((high if change > 0.0 else low) - value) / change
            if reach < nearest:                              # the first of equal reaches
                nearest, index = reach, i
    if not nearest < 1.0:
        return 1.0, None
    bound = float(upper[index] if step[index] > 0 else lower[index])
    return _INSIDE_BOX * nearest, (index, bound)


def _one_sided_gradients(linear: _Linear) -> Tuple[np.ndarray, np.ndarray]:
    """
    Rates at which the cost falls when each parameter rises, and when it falls.

    ``-dV/dtheta_i`` from the right, and ``+dV/dtheta_i`` from the left: with a dead time on the
    sample lattice the two sides have different sensitivities (the side a parameter moves the
    dead time to decides). Elsewhere the second is minus the first.
    """
    up = linear.side('up').gradient                          # -dV/dtheta, growing dead time
    if not linear.kinked:
        return up, -up
    down = linear.side('down').gradient                      # the same, shrinking dead time
    # A parameter that shrinks the dead time when it rises takes the other side's derivative.
    raises = linear.lin.delay_gradient >= 0.0
    rising = np.where(raises, up, down)
    falling = -np.where(raises, down, up)
    return rising, falling


def on_bounds(theta: np.ndarray, problem: Problem, tolerance: float = 1e-9
              ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Parameters on their lower and on their upper bound, within ``tolerance`` relative.

    Relative to the larger of the value and the bound, never to an absolute unit: a time
    constant of 5e-10 s identified at a sample time of 1e-12 s is not on its bound at 0 (the
    iteration clips to a bound exactly, so a parameter held there equals it).
    """
    # Every update asks, for a handful of parameters: Python floats, not numpy's dispatch,
    # and operators, not calls: a finite bound is one between the infinities, and a gap
    # within tolerance times the larger magnitude is within it times either magnitude
    # (rounding keeps the order of the products, and negation is exact).
    values = theta.tolist()
    near_lower = [-_INF < low < _INF and (
        (gap := value - low) <= tolerance * value or gap <= -(tolerance * value) or
        gap <= tolerance * low or gap <= -(tolerance * low))
        for value, low in zip(values, problem.lower.tolist())]
    near_upper = [-_INF < high < _INF and (
        (gap := high - value) <= tolerance * value or gap <= -(tolerance * value) or
        gap <= tolerance * high or gap <= -(tolerance * high))
        for value, high in zip(values, problem.upper.tolist())]
    return np.array(near_lower, dtype=bool), np.array(near_upper, dtype=bool)


def _free_mask(linear: _Linear, bounded: Tuple[np.ndarray, np.ndarray], frozen: np.ndarray
               ) -> np.ndarray:
    """
    Active set: hold parameters that can only move where the cost rises.

    A parameter on a bound (``bounded``: :func:`on_bounds` of the point) is held if the cost
    rises inward (the one-sided derivative into the box), and a dead time on the sample
    lattice is held where the cost rises on both sides.
    """
    at_lower, at_upper = bounded
    held = frozen | at_lower | at_upper
    if not (linear.kinked or any(held.tolist())):
        return ~held                            # no bound, no kink: every one is free (True)
    rising, falling = _one_sided_gradients(linear)
    kink = (rising < 0) & (falling < 0)
    return ~(frozen | (at_lower & (rising < 0)) | (at_upper & (falling < 0)) | kink)


def _linear_at(problem: Problem, state: State) -> _Linear:
    """Return the linearisation at ``state`` (no regressors) with its output error."""
    lin = problem.linearize(state.coefficients, regressors=False)
    return _Linear(lin, problem.measured - lin.output)


def free_parameters(problem: Problem, state: State, frozen: np.ndarray) -> np.ndarray:
    """
    Parameters the data determine at ``state``: not frozen, not held at a bound.

    A parameter on a bound whose cost rises inward is held there by the bound, not by the
    data (:func:`_free_mask`); identifiability and covariance concern the others. A dead time
    at a kink of the cost on the sample lattice is a minimum the data chose: it stays free.
    """
    rising, falling = _one_sided_gradients(_linear_at(problem, state))
    at_lower, at_upper = on_bounds(state.theta, problem)
    return ~(frozen | (at_lower & (rising < 0)) | (at_upper & (falling < 0)))


def optimality(problem: Problem, state: State, frozen: np.ndarray) -> float:
    """
    First-order optimality of ``state``, in standard deviations of the estimate.

    The Gauss-Newton step of the free parameters (those not held by :func:`_free_mask`: at an
    active bound only an inward decrease counts, at a dead-time kink the side that decreases)
    measured as ``|Psi step| / sigma``, i.e. ``sqrt(g^T (Psi^T Psi)^-1 g) / sigma`` with ``g``
    the projected gradient. Zero at a stationary point; ``docs/algorithm.md`` section 8.
    """
    return _optimality(_linear_at(problem, state), on_bounds(state.theta, problem), frozen)


def _optimality(linear: _Linear, bounded: Tuple[np.ndarray, np.ndarray], frozen: np.ndarray
                ) -> float:
    """:func:`optimality` of a point linearised as ``linear`` with ``bounded`` its bounds."""
    free = _free_mask(linear, bounded, frozen)
    if not any(free.tolist()):
        return 0.0
    # Combinations the data barely determine (their sensitivities nearly dependent, as where
    # two time constants coincide) have no first-order information: the measure leaves them
    # out rather than reading rounding as a gradient.
    step = _bounded_direction('gn', linear, free, *bounded, rcond=_OPTIMALITY_RCOND)
    if step is None:
        return np.inf
    return _step_size(linear, step)


def _try_step(problem: Problem, state: State, step: np.ndarray, monotone: bool,
              scales: Sequence[float], land: Optional[_Bound] = None) -> Optional[_Outcome]:
    """
    First admissible candidate ``theta + scale * step`` (box-limited) that does not raise V.

    Returns the new state, the fraction of ``step`` taken and the bound that cut a whole step
    (:func:`_box_limit`; None if it was not cut or a shorter one was taken). A whole step cut
    by ``land``, the bound that cut the previous update too, lands on it: stopping 0.999 of
    the way again would only creep towards the bound, 1000 times closer per update.
    """
    limit, bound = _box_limit(state.theta, step, problem.lower, problem.upper)
    if not limit > 0.0:
        return None
    for scale in scales:
        candidate = state.theta + limit * scale * step
        if scale == 1.0 and bound is not None and bound == land:
            candidate = state.theta + (limit / _INSIDE_BOX) * step
            candidate[bound[0]] = bound[1]
        coefficients = problem.admissible(candidate)
        if coefficients is not None:
            new_state = problem.state(candidate, coefficients)
            if not monotone or new_state.cost <= state.cost:
                return new_state, limit * scale, bound if scale == 1.0 else None
    return None


def _truncated_step_size(linear: _Linear, free: np.ndarray) -> float:
    """
    Length in standard deviations of the Gauss-Newton step of the free parameters, truncated.

    ``sqrt(sum_i (v_i^T g)^2 / lambda_i) / sigma`` over the eigenpairs of the scaled ``Psi^T
    Psi`` whose singular values ``sqrt(lambda_i)`` exceed ``_OPTIMALITY_RCOND`` of the largest:
    the measure of (8.1) without the directions the data barely see, from the small normal
    matrix (a measure, not a solve: the squared condition number does no harm above 1e-12).
    """
    if linear.variance == 0.0:
        return np.inf
    side = linear.side()
    scales = side.scales(free)
    outer = scales[:, None] * scales                          # np.outer's own product
    values, vectors = symmetric_eigen(_block(side.gram, free) / outer)
    kept = values > _OPTIMALITY_RCOND ** 2 * max(values[-1], _TINY)
    projected = vectors[:, kept].T @ (side.gradient[free] / scales)
    # np.sum of a vector is its add.reduce; the square root of a float, math's (both IEEE).
    return math.sqrt(np.add.reduce(projected ** 2 / values[kept]) / linear.variance)


def _across_kink(problem: Problem, state: State, linear: _Linear, free: np.ndarray,
                 bounded: Tuple[np.ndarray, np.ndarray], kind: str
                 ) -> Optional[Tuple[str, np.ndarray, _Outcome]]:
    """
    At a dead time on the lattice where the cost falls to both sides, take the better side.

    Such a kink separates two basins; both one-sided directions are tried (full step, then
    halved at most three times until the cost falls) and the lower cost wins (None if neither
    lowers it: the usual attempts follow).
    """
    rising, falling = _one_sided_gradients(linear)
    delays = free & (linear.lin.delay_gradient != 0.0)
    if not any((delays & (rising > 0.0) & (falling > 0.0)).tolist()):
        return None
    best = None
    for side in ('up', 'down'):
        step = _bounded_direction(kind, linear, free, *bounded, side=side)
        if step is None or linear.delay_change(step) == 0.0:
            continue
        outcome = _try_step(problem, state, step, True, _KINK_STEPS)
        if outcome is not None and (best is None or outcome[0].cost < best[2][0].cost):
            best = (kind, step, outcome)
    return best


def _step_size(linear: _Linear, step: np.ndarray) -> float:
    """Length of ``step`` in standard deviations of the estimate, ``|Psi step| / sigma`` (8.1)."""
    if linear.variance == 0.0:
        return np.inf
    side = linear.side('up' if linear.delay_change(step) >= 0.0 else 'down')
    change = side.psi @ step
    return math.sqrt(change.dot(change)) / math.sqrt(linear.variance)       # np.linalg.norm


def _slow(costs: List[float], struggled: List[bool], min_progress: float) -> bool:
    """
    Return True if the last updates lowered the cost by less than ``min_progress`` far away.

    Over the last :data:`_PROGRESS_SPAN` updates, each of which ``struggled`` (needed another
    direction or a shorter step): far from a minimum. Near one the cost falls little at every
    full step, and the convergence tests stop the iteration there.
    """
    if not min_progress or len(costs) <= _PROGRESS_SPAN:
        return False
    return costs[-1] > (1.0 - min_progress) * costs[-1 - _PROGRESS_SPAN] and \
        all(struggled[-_PROGRESS_SPAN:])


class Opening(enum.Enum):
    """
    How an iteration takes its first update (:attr:`IterationPolicy.opening`).

    Attributes
    ----------
    LEAST_SQUARES
        ``'iv'`` starts with a least-squares projection, controlled like every update: exact in
        one step for a noise-free affine structure from any stable start, so the automatic
        start's equation-error fit is refined without its bias.
    TRUSTED_LEAST_SQUARES
        As ``LEAST_SQUARES``, and that first step is accepted even if it raises the cost, as
        long as the model stays stable and inside the bounds: for an affine structure it is the
        exact regression from any start, which a profile over frozen parameters needs.
    PROJECTION
        Instrumental-variable projections from the first update: a start refined already.
    NEAR_MINIMUM
        The start is a converged local fit: ``'iv'`` begins with the Gauss-Newton steps it
        otherwise takes after a full update below :data:`_NEAR_MINIMUM` standard deviations.

    """

    LEAST_SQUARES = 'least squares'
    TRUSTED_LEAST_SQUARES = 'trusted least squares'
    PROJECTION = 'projection'
    NEAR_MINIMUM = 'near a minimum'


_LEAST_SQUARES_OPENINGS = (Opening.LEAST_SQUARES, Opening.TRUSTED_LEAST_SQUARES)


class Steps(enum.Enum):
    """
    Which steps an update may take (:attr:`IterationPolicy.steps`).

    Attributes
    ----------
    CONTROLLED
        The whole :class:`Schedule`: full steps, halved ones, Levenberg-Marquardt.
    FULL_ONLY
        Full steps only; the iteration gives up (:attr:`StopReason.NO_FULL_STEP`, not
        converged) at the first update that needs a shorter or damped one: a quick check of a
        start that is either close to a minimum or not worth the halving.

    """

    CONTROLLED = 'controlled'
    FULL_ONLY = 'full steps only'


class Attempt(NamedTuple):
    """One attempt of an update: a direction, its damping, the step fractions, monotone."""

    kind: str
    damping: float
    scales: Tuple[float, ...]
    monotone: bool


# The update's own direction (least squares, IV or Gauss-Newton) in a schedule.
_PRIMARY = 'primary'
_LEVENBERG_MARQUARDT = tuple(Attempt('lm', damping, _ALL_STEPS, True)
                             for damping in _LM_DAMPINGS)


class Schedule(enum.Enum):
    """
    The attempts of one update, in order (``docs/algorithm.md`` section 6).

    Attributes
    ----------
    CONTROLLED
        The full primary step, then the full Gauss-Newton step, and only then halved ones and
        the Levenberg-Marquardt fallbacks, each kept only if the cost does not rise: a biased
        first least-squares step costs one cost evaluation, not a whole halving sequence.
    TRUSTED
        The primary step (halved only until admissible, the cost may rise), then Gauss-Newton
        and Levenberg-Marquardt: the opening :attr:`Opening.TRUSTED_LEAST_SQUARES`.
    PROJECTION
        The primary step alone, halved only until admissible: ``method='ls'`` follows its own
        fixed point, not the descent of the output-error cost.

    """

    CONTROLLED = (Attempt(_PRIMARY, 0.0, _FULL_STEP, True), Attempt('gn', 0.0, _FULL_STEP, True),
                  Attempt(_PRIMARY, 0.0, _HALVED_STEPS, True),
                  Attempt('gn', 0.0, _HALVED_STEPS, True)) + _LEVENBERG_MARQUARDT
    TRUSTED = (Attempt(_PRIMARY, 0.0, _ALL_STEPS, False),
               Attempt('gn', 0.0, _ALL_STEPS, True)) + _LEVENBERG_MARQUARDT
    PROJECTION = (Attempt(_PRIMARY, 0.0, _ALL_STEPS, False),)

    def attempts(self, primary: str, full_only: bool) -> Tuple[Attempt, ...]:
        """Return the attempts with ``primary`` as the primary direction, full steps only."""
        return _attempts(self, primary, full_only)


# Every update asks for one of a few schedules: each is formed once.
@lru_cache(maxsize=None)
def _attempts(schedule: Schedule, primary: str, full_only: bool) -> Tuple[Attempt, ...]:
    """:meth:`Schedule.attempts`, formed once per schedule, primary direction and choice."""
    attempts = [attempt._replace(kind=primary) if attempt.kind == _PRIMARY else attempt
                for attempt in schedule.value]
    if full_only:
        attempts = [attempt._replace(scales=_FULL_STEP) for attempt in attempts
                    if attempt.kind != 'lm']
    return tuple(attempts)


@dataclass(frozen=True)
class IterationPolicy:
    """
    The settings of one :func:`iterate` run.

    Attributes
    ----------
    method : {'iv', 'ls', 'gn'}
        ``'iv'``: instrumental-variable projections (after the opening); ``'ls'``:
        least-squares projections throughout; ``'gn'``: Gauss-Newton.
    max_iterations : int
        Limit on the number of updates.
    tolerance : float
        Stop when the largest relative parameter change falls below it.
    opening : Opening
        How the first update is taken.
    steps : Steps
        Which steps an update may take.
    check_optimality : bool
        Before a rule that claims convergence stops the iteration, test first-order optimality
        (:func:`optimality` below :data:`OPTIMALITY_LIMIT`): a small step or a small decrease
        away from a minimum does not stop it, and where no admissible step decreases the cost
        away from a minimum it stops as :attr:`StopReason.STALLED` (not converged).
    min_progress : float
        Give up (:attr:`StopReason.SLOW`, not converged) when the cost fell by less than this
        share over the last two updates and both needed another direction or a shorter step
        (far from a minimum): a local optimisation a search does better. 0: never.

    """

    method: str = 'iv'
    max_iterations: int = 100
    tolerance: float = 1e-6
    opening: Opening = Opening.LEAST_SQUARES
    steps: Steps = Steps.CONTROLLED
    check_optimality: bool = False
    min_progress: float = 0.0


class _Point:
    """The linearisation of the current point, its active set and its directions (cached)."""

    def __init__(self, linear: _Linear, free: np.ndarray,
                 bounded: Tuple[np.ndarray, np.ndarray]):
        self.linear = linear
        self.free = free
        self.bounded = bounded
        self._directions: Dict[Tuple[str, float], Optional[np.ndarray]] = {}

    def direction(self, kind: str, damping: float) -> Optional[np.ndarray]:
        """:func:`_bounded_direction` of ``kind`` with ``damping``, solved once per point."""
        if (kind, damping) not in self._directions:
            self._directions[kind, damping] = _bounded_direction(
                kind, self.linear, self.free, *self.bounded, damping)
        return self._directions[kind, damping]


# What an update accepted: the direction's kind, the direction, the outcome of the step.
_Accepted = Tuple[str, np.ndarray, _Outcome]


class _Run:
    """One run of :func:`iterate`: where it is, what it recorded, whether it is near a minimum."""

    def __init__(self, problem: Problem, state: State, policy: IterationPolicy,
                 frozen: np.ndarray):
        self.problem = problem
        self.policy = policy
        self.frozen = frozen
        self.state = state
        self.history: List[Iteration] = []
        # The latest linearisation with its products: the optimality test at a new point and
        # the next update from it share one.
        self.latest: Optional[_Linear] = None
        # Costs after every update (the start's first) and whether each update struggled
        # (needed another direction or a shorter step); how many did.
        self.costs = [state.cost]
        self.struggled: List[bool] = []
        self.struggling = 0
        # Near a minimum the IV and Gauss-Newton updates agree (both vanish where Psi^T e = 0)
        # and Gauss-Newton needs no filtered output: one simulation fewer per update.
        self.near = policy.method == 'iv' and policy.opening is Opening.NEAR_MINIMUM
        # The bound that cut the latest update (None if it was whole or shorter).
        self.creeping: Optional[_Bound] = None
        # The latest IV update was taken by the full Gauss-Newton step (the IV step was not),
        # the cost falling by _RESCUE_DECREASE at least: the next one tries it first.
        self.rescued = False
        # An attempt refused at the current point (the full Gauss-Newton step of a rescue or
        # near a minimum), not tried again when the IV schedule takes the point over.
        self.refused: Optional[Tuple[str, float, Tuple[float, ...]]] = None

    def result(self) -> IterationResult:
        """Iterate until a stopping rule fires and return the outcome."""
        reason = None
        while reason is None and len(self.history) < self.policy.max_iterations:
            reason = self._update()
        reason = reason or StopReason.ITERATION_LIMIT
        return IterationResult(self.state, self.history, reason, reason.describe(
            self.policy.tolerance, self.policy.max_iterations))

    def _linearized(self, regressors: bool) -> _Linear:
        lin = self.problem.linearize(self.state.coefficients, regressors=regressors)
        if self.latest is None or self.latest.lin is not lin:
            self.latest = _Linear(lin, self.problem.measured - lin.output)
        return self.latest

    def _optimal(self) -> bool:
        # LS follows its own fixed point, not the minimum of V.
        policy = self.policy
        return not policy.check_optimality or policy.method == 'ls' or _optimality(
            self._linearized(False), on_bounds(self.state.theta, self.problem),
            self.frozen) <= OPTIMALITY_LIMIT

    def _primary(self) -> str:
        """Return the direction of this update: least squares, IV or Gauss-Newton."""
        method = self.policy.method
        if method == 'gn' or self.near:
            return 'gn'
        if method == 'ls' or (not self.history and self.policy.opening in _LEAST_SQUARES_OPENINGS):
            return 'ls'
        return 'iv'

    def _update(self) -> Optional[StopReason]:
        """Take one update; return why to stop, or None to go on (maybe from the same point)."""
        policy = self.policy
        if self.rescued and not self.near:
            return self._rescued()
        linear = self._linearized(policy.method != 'gn' and not self.near)
        point = self._point(linear)
        if point is None:
            return StopReason.ALL_AT_BOUNDS
        primary = self._primary()
        size = np.inf
        if primary != 'ls':
            size = self._size(point, primary)
            if size < NEGLIGIBLE_STEP:
                return StopReason.NEGLIGIBLE_UPDATE
            if self.near and size >= _NEAR_MINIMUM:
                # Gauss-Newton disagrees with the IV step that judged this point near a
                # minimum (a far, flat or large-residual region): the IV schedule goes on.
                self.near = False
                return None
            if _slow(self.costs, self.struggled, policy.min_progress):
                return StopReason.SLOW
        accepted = self._accepted(point, primary)
        if accepted is None and self.near:
            # Where the residual is large (a model that does not explain everything) the
            # Gauss-Newton step can fail where the IV step, which carries part of the curvature
            # it leaves out, succeeds: the same point again, with the IV schedule.
            self.near = False
            self.refused = ('gn', 0.0, _FULL_STEP)
            return None
        if accepted is None:
            if policy.steps is Steps.FULL_ONLY:
                return StopReason.NO_FULL_STEP
            return StopReason.NO_DECREASE if self._optimal() else StopReason.STALLED
        return self._record(accepted, primary, size, linear)

    def _rescued(self) -> Optional[StopReason]:
        """
        Take the full Gauss-Newton step first after it rescued the previous IV update.

        Far from a minimum, or where the residual is large, the IV step can be refused update
        after update while the Gauss-Newton step is taken in full each time: its linearisation
        then needs no filtered output, and the refused IV step no simulation. The update
        counts as struggling, as the rescued one did: its size is the struggling update's
        measure (the truncated Gauss-Newton step of (8.1), after the whole Gauss-Newton step
        in place of the IV one), and the stopping rules, the slow-progress give-up and the
        hand-over to the near-minimum mode are the IV schedule's. Where the Gauss-Newton step
        is not taken in full (or the dead time sits on a kink) the IV schedule takes the same
        point over.
        """
        self.rescued = False
        linear = self._linearized(False)
        if linear.kinked:
            return None
        point = self._point(linear)
        if point is None:
            return StopReason.ALL_AT_BOUNDS
        size = self._size(point, 'gn')
        if size < NEGLIGIBLE_STEP:
            return StopReason.NEGLIGIBLE_UPDATE
        if _slow(self.costs, self.struggled, self.policy.min_progress):
            return StopReason.SLOW
        step = point.direction('gn', 0.0)
        if step is None:
            return None
        outcome = _try_step(self.problem, self.state, step, True, _FULL_STEP,
                            land=self.creeping)
        if outcome is None:
            self.refused = ('gn', 0.0, _FULL_STEP)
            return None
        return self._record(('gn', step, outcome), 'iv', size, linear)

    def _point(self, linear: _Linear) -> Optional[_Point]:
        """Return the update's point at the current state, None if every parameter is held."""
        bounded = on_bounds(self.state.theta, self.problem)
        free = _free_mask(linear, bounded, self.frozen)
        if not any(free.tolist()):
            return None
        return _Point(linear, free, bounded)

    def _size(self, point: _Point, primary: str) -> float:
        """Return the primary update's length in standard deviations of the estimate (8.1)."""
        first = point.direction(primary, 0.0)
        size = np.inf if first is None else _step_size(point.linear, first)
        if size >= NEGLIGIBLE_STEP and (first is None or self.struggling >= _STRUGGLING):
            # Where two parameters act alike (coinciding time constants) the IV step is
            # singular or large along what the data cannot see, and the updates that pass are
            # damped or halved; the Gauss-Newton step without those directions measures the
            # update then.
            size = _truncated_step_size(point.linear, point.free)
        return size

    def _schedule(self, primary: str) -> Tuple[Schedule, bool]:
        """Return the schedule of this update and whether it is trusted (the cost may rise)."""
        policy = self.policy
        if policy.method == 'ls':
            # Pure P-LS follows its own fixed point, not the output-error descent.
            return Schedule.PROJECTION, True
        if policy.opening is Opening.TRUSTED_LEAST_SQUARES and not self.history and \
                primary == 'ls':
            return Schedule.TRUSTED, True
        return Schedule.CONTROLLED, False

    def _accepted(self, point: _Point, primary: str) -> Optional[_Accepted]:
        """Return the first attempt of the update's schedule that is accepted, or None."""
        problem, state, linear = self.problem, self.state, point.linear
        schedule, trusted = self._schedule(primary)
        if not trusted and linear.kinked:
            across = _across_kink(problem, state, linear, point.free, point.bounded, primary)
            if across is not None:
                return across
        full_only = self.policy.steps is Steps.FULL_ONLY or self.near
        # Its outcome here is known: the same candidate, refused.
        tried = set() if self.refused is None else {self.refused}
        self.refused = None
        for kind, damping, scales, monotone in schedule.attempts(primary, full_only):
            step = point.direction(kind, damping)
            if step is None or (kind, damping, scales) in tried:
                continue
            tried.add((kind, damping, scales))
            if monotone and len(scales) > 1 and not linear.descends(step):
                # Shorter steps along a direction the cost rises on cannot lower it: only the
                # whole step, which may reach past the rise, is worth its simulation.
                scales = scales[:1] if scales[0] == 1.0 else ()
            outcome = _try_step(problem, state, step, monotone, scales, land=self.creeping)
            if outcome is not None:
                return kind, step, outcome
        return None

    def _record(self, accepted: _Accepted, primary: str, size: float, linear: _Linear
                ) -> Optional[StopReason]:
        """Move to the accepted point, record it and apply the convergence tests."""
        kind, step, (new_state, scale, self.creeping) = accepted
        struggled = kind != primary or scale < 1.0
        self.rescued = primary == 'iv' and kind == 'gn' and scale == 1.0 and \
            new_state.cost <= (1.0 - _RESCUE_DECREASE) * self.state.cost
        self.struggled.append(struggled)
        self.near = self.policy.method == 'iv' and not struggled and \
            (self.near or size < _NEAR_MINIMUM)
        self.struggling += struggled
        state = self.state
        # The largest relative change |scale move| / max(|value|, 1e-12), in Python floats and
        # operators (magnitudes by negation, exact): no builtin call per parameter.
        change = 0.0
        for move, value in zip(step.tolist(), state.theta.tolist()):
            moved = scale * move
            magnitude = value if value >= 0.0 else -value
            relative = (moved if moved >= 0.0 else -moved) / \
                (magnitude if magnitude > 1e-12 else 1e-12)
            if relative > change:
                change = relative
        previous = max(state.cost, _TINY)
        decrease = (state.cost - new_state.cost) / previous
        self.state = new_state
        self.history.append(Iteration(new_state.theta.copy(), new_state.cost, scale, kind))
        self.costs.append(new_state.cost)
        return self._converged(kind, change, decrease * previous, decrease, linear)

    def _converged(self, kind: str, change: float, fall: float, decrease: float,
                   linear: _Linear) -> Optional[StopReason]:
        """Return the convergence test that fires after an update of ``kind``, or None."""
        policy, state = self.policy, self.state
        if change < policy.tolerance and self._optimal():
            return StopReason.PARAMETER_CHANGE
        projection = policy.method == 'ls' or kind == 'ls'
        if not projection and 0.0 <= decrease < policy.tolerance ** 2 and self._optimal():
            return StopReason.COST_DECREASE
        # A decrease smaller than a step of NEGLIGIBLE_STEP standard deviations would give,
        # (8.1) squared: progress along directions the data barely see (coinciding time
        # constants) that no user could tell from here.
        count, params = linear.lin.psi.shape
        variance = 2.0 * state.cost / max(count - params, 1)
        if policy.check_optimality and not projection and \
                fall < 0.5 * NEGLIGIBLE_STEP ** 2 * variance and self._optimal():
            return StopReason.NEGLIGIBLE_UPDATE
        measured = self.problem.measured
        if state.cost <= 1e-30 * max(float(measured @ measured), 1e-300):
            return StopReason.EXACT_FIT
        return None


def iterate(problem: Problem, state: State, policy: IterationPolicy,
            frozen: Optional[np.ndarray] = None) -> IterationResult:
    """
    Run the controlled projection iteration from ``state``.

    Parameters
    ----------
    problem : Problem
        Data, model and bounds.
    state : State
        Admissible start.
    policy : IterationPolicy
        Method, limits, opening, steps and the optional tests.
    frozen : ndarray of bool, optional
        Parameters kept at their start values (default none).

    Returns
    -------
    IterationResult
        End state, accepted updates and the stopping rule that fired.

    Notes
    -----
    Each update tries the attempts of its :class:`Schedule` in order: the full primary step,
    then the full Gauss-Newton step, and only then halves them and falls back to
    Levenberg-Marquardt (``docs/algorithm.md`` section 6). For ``'iv'``, once a full update was
    shorter than :data:`_NEAR_MINIMUM` standard deviations the primary step is Gauss-Newton,
    full steps only, until one needs another direction or a shorter step; where no full
    Gauss-Newton step decreases the cost the same point is updated by the IV schedule. After
    an IV update that the full Gauss-Newton step took with the cost falling by
    :data:`_RESCUE_DECREASE` or more, the next update tries that step first (section 5). The
    stopping rules are the same for all (section 8).

    """
    if frozen is None:
        frozen = np.zeros(state.theta.size, dtype=bool)
    return _Run(problem, state, policy, frozen).result()
