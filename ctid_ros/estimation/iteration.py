"""
The controlled projection iteration of the method.

At the current parameters the output error is projected onto the regressors ``phi``: the first
update by least squares, later ones by the instrumental-variable (oblique) projection with the
instruments ``psi``. Every update is controlled: the bounds truncate it, ``D`` must stay stable,
the output-error cost may not increase, and full steps are tried before halved ones and before
Gauss-Newton and Levenberg-Marquardt fallbacks. :func:`iterate` reports why it stopped as a
:class:`StopReason`. The equations are sections 5-8 of ``docs/algorithm.md``.
"""

from dataclasses import dataclass
import enum
from typing import Dict, List, Optional, Sequence, Tuple

from ctid_ros.estimation.problem import Problem, State
from ctid_ros.estimation.regressors import Linearization
import numpy as np

__all__ = [
    'Iteration', 'IterationResult', 'NEGLIGIBLE_STEP', 'OPTIMALITY_LIMIT', 'StopReason',
    'column_scales', 'free_parameters', 'iterate', 'on_bounds', 'optimality',
]

_HALVINGS = 14
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
# Updates over which min_progress measures the fall of the cost.
_PROGRESS_SPAN = 2
# After a full update shorter than this many standard deviations the IV iteration takes
# Gauss-Newton steps for as long as they are accepted in full. Chosen on the reference systems
# of bench/estimator.py: among 10, 30 and no limit, 30 needs the fewest simulations on most.
_NEAR_MINIMUM = 30.0


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


def _shrinking(lin: Linearization) -> Linearization:
    """Return the linearisation for a shrinking dead time (itself where both sides agree)."""
    if lin.delay_jump is None:
        return lin
    return Linearization(lin.output, None if lin.phi is None else lin.phi + lin.delay_jump,
                         lin.psi + lin.delay_jump, None, lin.delay_gradient)


def _delay_change(lin: Linearization, step: np.ndarray) -> float:
    """Change of the dead time along ``step``, to first order (0 without a jump)."""
    if lin.delay_jump is None:
        return 0.0
    return float(lin.delay_gradient @ step)


def _bounded_direction(kind: str, lin: Linearization, error: np.ndarray, free: np.ndarray,
                       at_lower: np.ndarray, at_upper: np.ndarray, damping: float = 0.0,
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
        step = _direction(kind, lin, error, free, damping, rcond, side)
        if step is None:
            return None
        outward = free & ((at_lower & (step < 0.0)) | (at_upper & (step > 0.0)))
        if not np.any(outward):
            return step
        free &= ~outward
        if not np.any(free):
            return None


def _direction(kind: str, lin: Linearization, error: np.ndarray, free: np.ndarray,
               damping: float = 0.0, rcond: Optional[float] = None, side: str = 'auto'
               ) -> Optional[np.ndarray]:
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
    if lin.delay_jump is None:
        return _one_sided_direction(kind, lin, error, free, damping, rcond)
    held = free & (lin.delay_gradient == 0.0)
    if side == 'auto':
        # The side where the cost falls faster first, then the other.
        rising, falling = _one_sided_gradients(lin, error)
        delays = free & (lin.delay_gradient != 0.0)
        down_first = np.max(falling[delays], initial=0.0) > np.max(rising[delays], initial=0.0)
        sides = ('down', 'up') if down_first else ('up', 'down')
    else:
        sides = (side,)
    for which in sides:
        sided = lin if which == 'up' else _shrinking(lin)
        step = _one_sided_direction(kind, sided, error, free, damping, rcond)
        change = 0.0 if step is None else _delay_change(lin, step)
        if step is None or (change >= 0.0 if which == 'up' else change <= 0.0):
            return step
    if not np.any(held):
        return None
    return _one_sided_direction(kind, lin, error, held, damping, rcond)


def _one_sided_direction(kind: str, lin: Linearization, error: np.ndarray, free: np.ndarray,
                         damping: float, rcond: Optional[float] = None) -> Optional[np.ndarray]:
    """Direction of :func:`_direction` with the sensitivities as given."""
    psi = lin.psi[:, free]
    scales = column_scales(psi)
    psi_s = psi / scales
    if kind == 'ls':
        phi_s = lin.phi[:, free] / scales
        step = np.linalg.lstsq(phi_s, error, rcond=None)[0]
    elif kind == 'iv':
        phi_s = lin.phi[:, free] / scales
        matrix = psi_s.T @ phi_s
        if np.linalg.cond(matrix) > _IV_CONDITION_LIMIT:
            return None
        step = np.linalg.solve(matrix, psi_s.T @ error)
    elif kind == 'gn':
        step = np.linalg.lstsq(psi_s, error, rcond=rcond)[0]
    else:
        gram = psi_s.T @ psi_s
        try:
            step = np.linalg.solve(gram + damping * np.diag(np.diag(gram)), psi_s.T @ error)
        except np.linalg.LinAlgError:
            return None
    if not np.all(np.isfinite(step)):
        return None
    full = np.zeros(free.size)
    full[free] = step / scales
    return full


def _box_limit(theta: np.ndarray, step: np.ndarray, lower: np.ndarray,
               upper: np.ndarray) -> float:
    """Largest fraction (<= 1) of ``step`` that keeps theta inside the box."""
    limit = 1.0
    with np.errstate(divide='ignore', invalid='ignore'):
        up = np.where(step > 0, (upper - theta) / step, np.inf)
        down = np.where(step < 0, (lower - theta) / step, np.inf)
    limit = min(limit, float(np.min(up, initial=np.inf)), float(np.min(down, initial=np.inf)))
    return limit if limit >= 1.0 else 0.999 * limit


def _one_sided_gradients(lin: Linearization, error: np.ndarray
                         ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Rates at which the cost falls when each parameter rises, and when it falls.

    ``-dV/dtheta_i`` from the right, and ``+dV/dtheta_i`` from the left: with a dead time on the
    sample lattice the two sides have different sensitivities (the side a parameter moves the
    dead time to decides). Elsewhere the second is minus the first.
    """
    up = lin.psi.T @ error                                   # -dV/dtheta, growing dead time
    if lin.delay_jump is None:
        return up, -up
    down = up + lin.delay_jump.T @ error                     # the same, shrinking dead time
    # A parameter that shrinks the dead time when it rises takes the other side's derivative.
    raises = lin.delay_gradient >= 0.0
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
    lower, upper = problem.lower, problem.upper
    near_lower = np.isfinite(lower) & (theta - lower <= tolerance * np.maximum(np.abs(theta),
                                                                               np.abs(lower)))
    near_upper = np.isfinite(upper) & (upper - theta <= tolerance * np.maximum(np.abs(theta),
                                                                               np.abs(upper)))
    return near_lower, near_upper


def _free_mask(theta: np.ndarray, lin: Linearization, error: np.ndarray,
               problem: Problem, frozen: np.ndarray) -> np.ndarray:
    """
    Active set: hold parameters that can only move where the cost rises.

    A parameter on a bound is held if the cost rises inward (the one-sided derivative into the
    box), and a dead time on the sample lattice is held where the cost rises on both sides.
    """
    rising, falling = _one_sided_gradients(lin, error)
    at_lower, at_upper = on_bounds(theta, problem)
    kink = (rising < 0) & (falling < 0)
    return ~(frozen | (at_lower & (rising < 0)) | (at_upper & (falling < 0)) | kink)


def free_parameters(problem: Problem, state: State, frozen: np.ndarray) -> np.ndarray:
    """
    Parameters the data determine at ``state``: not frozen, not held at a bound.

    A parameter on a bound whose cost rises inward is held there by the bound, not by the
    data (:func:`_free_mask`); identifiability and covariance concern the others. A dead time
    at a kink of the cost on the sample lattice is a minimum the data chose: it stays free.
    """
    lin = problem.linearize(state.coefficients, regressors=False)
    error = problem.measured - lin.output
    rising, falling = _one_sided_gradients(lin, error)
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
    lin = problem.linearize(state.coefficients, regressors=False)
    error = problem.measured - lin.output
    free = _free_mask(state.theta, lin, error, problem, frozen)
    if not np.any(free):
        return 0.0
    # Combinations the data barely determine (their sensitivities nearly dependent, as where
    # two time constants coincide) have no first-order information: the measure leaves them
    # out rather than reading rounding as a gradient.
    step = _bounded_direction('gn', lin, error, free, *on_bounds(state.theta, problem),
                              rcond=_OPTIMALITY_RCOND)
    if step is None:
        return np.inf
    return _step_size(lin, error, step)


def _try_step(problem: Problem, state: State, step: np.ndarray, monotone: bool,
              scales: Sequence[float]) -> Optional[Tuple[State, float]]:
    """First admissible candidate ``theta + scale * step`` (box-limited) that does not raise V."""
    limit = _box_limit(state.theta, step, problem.lower, problem.upper)
    if not limit > 0.0:
        return None
    for scale in scales:
        candidate = state.theta + limit * scale * step
        coefficients = problem.admissible(candidate)
        if coefficients is not None:
            new_state = problem.state(candidate, coefficients)
            if not monotone or new_state.cost <= state.cost:
                return new_state, limit * scale
    return None


def _truncated_step_size(lin: Linearization, error: np.ndarray, free: np.ndarray) -> float:
    """
    Length in standard deviations of the Gauss-Newton step of the free parameters, truncated.

    ``sqrt(sum_i (v_i^T g)^2 / lambda_i) / sigma`` over the eigenpairs of the scaled ``Psi^T
    Psi`` whose singular values ``sqrt(lambda_i)`` exceed ``_OPTIMALITY_RCOND`` of the largest:
    the measure of (8.1) without the directions the data barely see, from the small normal
    matrix (a measure, not a solve: the squared condition number does no harm above 1e-12).
    """
    count, params = lin.psi.shape
    variance = float(error @ error) / max(count - params, 1)
    if variance == 0.0:
        return np.inf
    psi = lin.psi[:, free]
    scaled = psi / column_scales(psi)
    values, vectors = np.linalg.eigh(scaled.T @ scaled)
    kept = values > _OPTIMALITY_RCOND ** 2 * max(values[-1], np.finfo(float).tiny)
    projected = vectors[:, kept].T @ (scaled.T @ error)
    return float(np.sqrt(np.sum(projected ** 2 / values[kept]) / variance))


def _across_kink(problem: Problem, state: State, lin: Linearization, error: np.ndarray,
                 free: np.ndarray, bounded: Tuple[np.ndarray, np.ndarray], kind: str
                 ) -> Optional[Tuple[str, np.ndarray, Tuple[State, float]]]:
    """
    At a dead time on the lattice where the cost falls to both sides, take the better side.

    Such a kink separates two basins; both one-sided directions are tried (full step, then
    halved at most three times until the cost falls) and the lower cost wins (None if neither
    lowers it: the usual attempts follow).
    """
    rising, falling = _one_sided_gradients(lin, error)
    delays = free & (lin.delay_gradient != 0.0)
    if not np.any(delays & (rising > 0.0) & (falling > 0.0)):
        return None
    best = None
    for side in ('up', 'down'):
        step = _bounded_direction(kind, lin, error, free, *bounded, side=side)
        if step is None or _delay_change(lin, step) == 0.0:
            continue
        outcome = _try_step(problem, state, step, True, _KINK_STEPS)
        if outcome is not None and (best is None or outcome[0].cost < best[2][0].cost):
            best = (kind, step, outcome)
    return best


def _step_size(lin: Linearization, error: np.ndarray, step: np.ndarray) -> float:
    """Length of ``step`` in standard deviations of the estimate, ``|Psi step| / sigma`` (8.1)."""
    count, params = lin.psi.shape
    variance = float(error @ error) / max(count - params, 1)
    if variance == 0.0:
        return np.inf
    psi = lin.psi if _delay_change(lin, step) >= 0.0 else _shrinking(lin).psi
    return float(np.linalg.norm(psi @ step) / np.sqrt(variance))


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


def iterate(problem: Problem, state: State, *, method: str, frozen: np.ndarray,
            max_iterations: int, tolerance: float, first_ls: bool = True,
            trust_first_ls: bool = False, full_steps_only: bool = False,
            check_optimality: bool = False, min_progress: float = 0.0,
            near_start: bool = False) -> IterationResult:
    """
    Run the controlled projection iteration from ``state``.

    Parameters
    ----------
    problem : Problem
        Data, model and bounds.
    state : State
        Admissible start.
    method : {'iv', 'ls', 'gn'}
        ``'iv'``: instrumental-variable projections (after a least-squares first update if
        ``first_ls``); ``'ls'``: least-squares projections throughout; ``'gn'``: Gauss-Newton.
    frozen : ndarray of bool
        Parameters kept at their start values.
    max_iterations : int
        Limit on the number of updates.
    tolerance : float
        Stop when the largest relative parameter change falls below it.
    first_ls : bool
        Start the ``'iv'`` schedule with a least-squares update.
    trust_first_ls : bool
        Accept the first (least-squares) step even if it raises the cost, as long as the model
        stays stable and inside the bounds: for an affine structure that step is the exact
        regression from any start, which is what a profile over frozen parameters needs.
    full_steps_only : bool
        Give up (:attr:`StopReason.NO_FULL_STEP`, not converged) at the first update that needs
        a shorter or damped step: a quick check of a start that is either close to a minimum or
        not worth the halving.
    min_progress : float
        Give up (:attr:`StopReason.SLOW`, not converged) when the cost fell by less than this
        share over the last two updates and both needed another direction or a shorter step
        (far from a minimum): a local optimisation a search does better. 0: never.
    check_optimality : bool
        Before a rule that claims convergence stops the iteration, test first-order optimality
        (:func:`optimality` below :data:`OPTIMALITY_LIMIT`): a small step or a small decrease
        away from a minimum does not stop it, and where no admissible step decreases the cost
        away from a minimum it stops as :attr:`StopReason.STALLED` (not converged).
    near_start : bool
        The start is a converged local fit: ``'iv'`` begins with the Gauss-Newton steps it
        otherwise takes after a full update below :data:`_NEAR_MINIMUM` standard deviations.

    Returns
    -------
    IterationResult
        End state, accepted updates and the stopping rule that fired.

    Notes
    -----
    Each update tries the full primary step, then the full Gauss-Newton step, and only then
    halves them and falls back to Levenberg-Marquardt: a biased first least-squares step then
    costs one cost evaluation, not a whole halving sequence (``docs/algorithm.md`` section 6).
    For ``'iv'``, once a full update was shorter than :data:`_NEAR_MINIMUM` standard deviations
    the primary step is Gauss-Newton, full steps only, until one needs another direction or
    a shorter step; where no full Gauss-Newton step decreases the cost the same point is
    updated by the IV schedule. The stopping rules are the same for both (section 5).

    """
    history: List[Iteration] = []

    def stop(reason: StopReason) -> IterationResult:
        return IterationResult(state, history, reason,
                               reason.describe(tolerance, max_iterations))

    def optimal() -> bool:
        # LS follows its own fixed point, not the minimum of V.
        return not check_optimality or method == 'ls' or \
            optimality(problem, state, frozen) <= OPTIMALITY_LIMIT

    # Updates so far that needed another direction or a shorter step.
    struggling = 0
    # Costs after every update (the start's first) and whether each update struggled.
    costs = [state.cost]
    struggled: List[bool] = []
    # Near a minimum the IV and Gauss-Newton updates agree (both vanish where Psi^T e = 0) and
    # Gauss-Newton needs no filtered output: one simulation fewer per update.
    near = method == 'iv' and near_start
    while len(history) < max_iterations:
        iteration = len(history)
        lin = problem.linearize(state.coefficients, regressors=method != 'gn' and not near)
        error = problem.measured - lin.output
        free = _free_mask(state.theta, lin, error, problem, frozen)
        bounded = on_bounds(state.theta, problem)
        if not np.any(free):
            return stop(StopReason.ALL_AT_BOUNDS)
        primary = 'gn' if method == 'gn' or near else ('ls' if method == 'ls' or (
            iteration == 0 and first_ls) else 'iv')
        directions: Dict[Tuple[str, float], Optional[np.ndarray]] = {}

        def direction(kind: str, damping: float) -> Optional[np.ndarray]:
            if (kind, damping) not in directions:
                directions[kind, damping] = _bounded_direction(kind, lin, error, free,
                                                               *bounded, damping)
            return directions[kind, damping]

        first = direction(primary, 0.0)
        size = np.inf
        if primary != 'ls':
            size = np.inf if first is None else _step_size(lin, error, first)
            if size >= NEGLIGIBLE_STEP and (first is None or struggling >= _STRUGGLING):
                # Where two parameters act alike (coinciding time constants) the IV step is
                # singular or large along what the data cannot see, and the updates that pass
                # are damped or halved; the Gauss-Newton step without those directions
                # measures the update then.
                size = _truncated_step_size(lin, error, free)
            if size < NEGLIGIBLE_STEP:
                return stop(StopReason.NEGLIGIBLE_UPDATE)
            if near and size >= _NEAR_MINIMUM:
                # Gauss-Newton disagrees with the IV step that judged this point near a
                # minimum (a far, flat or large-residual region): the IV schedule goes on.
                near = False
                continue
            if _slow(costs, struggled, min_progress):
                return stop(StopReason.SLOW)
        # Pure P-LS follows its own fixed point, not the output-error descent.
        trusted = method == 'ls' or (trust_first_ls and iteration == 0 and primary == 'ls')
        if trusted:
            attempts = [(primary, 0.0, _ALL_STEPS, False), ('gn', 0.0, _ALL_STEPS, True)]
        else:
            attempts = [(primary, 0.0, _FULL_STEP, True), ('gn', 0.0, _FULL_STEP, True),
                        (primary, 0.0, _HALVED_STEPS, True), ('gn', 0.0, _HALVED_STEPS, True)]
        if method == 'ls':
            attempts = attempts[:1]
        else:
            attempts += [('lm', damping, _ALL_STEPS, True) for damping in _LM_DAMPINGS]
        if full_steps_only or near:
            attempts = [(kind, damping, _FULL_STEP, monotone)
                        for kind, damping, _, monotone in attempts if kind != 'lm']
        accepted = None
        if not trusted and lin.delay_jump is not None:
            accepted = _across_kink(problem, state, lin, error, free, bounded, primary)
        tried = set()
        for kind, damping, scales, monotone in attempts:
            if accepted is not None:
                break
            step = direction(kind, damping)
            if step is None or (kind, damping, scales) in tried:
                continue
            tried.add((kind, damping, scales))
            outcome = _try_step(problem, state, step, monotone, scales)
            if outcome is not None:
                accepted = (kind, step, outcome)
                break
        if accepted is None and near:
            # Where the residual is large (a model that does not explain everything) the
            # Gauss-Newton step can fail where the IV step, which carries part of the curvature
            # it leaves out, succeeds: the same point again, with the IV schedule.
            near = False
            continue
        if accepted is None:
            if full_steps_only:
                return stop(StopReason.NO_FULL_STEP)
            return stop(StopReason.NO_DECREASE if optimal() else StopReason.STALLED)
        kind, step, (new_state, scale) = accepted
        struggled.append(kind != primary or scale < 1.0)
        near = method == 'iv' and not struggled[-1] and (near or size < _NEAR_MINIMUM)
        struggling += struggled[-1]
        change = np.max(np.abs(scale * step) / np.maximum(np.abs(state.theta), 1e-12))
        previous = max(state.cost, np.finfo(float).tiny)
        decrease = (state.cost - new_state.cost) / previous
        state = new_state
        history.append(Iteration(state.theta.copy(), state.cost, scale, kind))
        costs.append(state.cost)
        if change < tolerance and optimal():
            return stop(StopReason.PARAMETER_CHANGE)
        if method != 'ls' and 0.0 <= decrease < tolerance ** 2 and kind != 'ls' and optimal():
            return stop(StopReason.COST_DECREASE)
        # A decrease smaller than a step of NEGLIGIBLE_STEP standard deviations would give,
        # (8.1) squared: progress along directions the data barely see (coinciding time
        # constants) that no user could tell from here.
        count, params = lin.psi.shape
        variance = 2.0 * state.cost / max(count - params, 1)
        if check_optimality and method != 'ls' and kind != 'ls' and \
                decrease * previous < 0.5 * NEGLIGIBLE_STEP ** 2 * variance and optimal():
            return stop(StopReason.NEGLIGIBLE_UPDATE)
        if state.cost <= 1e-30 * max(float(problem.measured @ problem.measured), 1e-300):
            return stop(StopReason.EXACT_FIT)
    return stop(StopReason.ITERATION_LIMIT)
