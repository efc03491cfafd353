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
    'Iteration', 'IterationResult', 'NEGLIGIBLE_STEP', 'StopReason',
    'column_scales', 'iterate',
]

_HALVINGS = 14
_FULL_STEP = (1.0,)
_HALVED_STEPS = tuple(0.5 ** np.arange(1, _HALVINGS))
_ALL_STEPS = _FULL_STEP + _HALVED_STEPS
_IV_CONDITION_LIMIT = 1e10
_LM_DAMPINGS = (1e-2, 1.0, 1e2)
# An update smaller than this many standard deviations of the estimate changes nothing a user
# can see: the iteration stops instead of resolving noise to the last digit.
NEGLIGIBLE_STEP = 1e-3


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

    @property
    def converged(self) -> bool:
        """Return True for a convergence test, False for the limit or a check that gave up."""
        return self not in (StopReason.NO_FULL_STEP, StopReason.ITERATION_LIMIT)

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


def _direction(kind: str, lin: Linearization, error: np.ndarray, free: np.ndarray,
               damping: float = 0.0) -> Optional[np.ndarray]:
    """
    Update direction on the free parameters (zeros elsewhere), or None if singular.

    ``kind`` is ``'ls'``, ``'iv'``, ``'gn'`` or ``'lm'``: equations (5.1)-(5.4) of
    ``docs/algorithm.md``, on columns scaled by the instrument norms.

    """
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
        step = np.linalg.lstsq(psi_s, error, rcond=None)[0]
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


def _free_mask(theta: np.ndarray, lin: Linearization, error: np.ndarray,
               problem: Problem, frozen: np.ndarray) -> np.ndarray:
    """Active set: drop parameters that sit on a bound and whose gradient pushes outward."""
    gradient = lin.psi.T @ error                     # -dV/dtheta
    span = np.maximum(np.abs(theta), 1.0)
    at_lower = (theta - problem.lower <= 1e-9 * span) & (gradient < 0)
    at_upper = (problem.upper - theta <= 1e-9 * span) & (gradient > 0)
    return ~(frozen | at_lower | at_upper)


def _try_step(problem: Problem, state: State, step: np.ndarray, monotone: bool,
              scales: Sequence[float]) -> Optional[Tuple[State, float]]:
    """First admissible candidate ``theta + scale * step`` (box-limited) that does not raise V."""
    limit = _box_limit(state.theta, step, problem.lower, problem.upper)
    for scale in scales:
        candidate = state.theta + limit * scale * step
        coefficients = problem.admissible(candidate)
        if coefficients is not None:
            cost = problem.cost(coefficients)
            if not monotone or cost <= state.cost:
                return State(candidate, coefficients, cost), limit * scale
    return None


def _step_size(lin: Linearization, error: np.ndarray, step: np.ndarray) -> float:
    """Length of ``step`` in standard deviations of the estimate, ``|Psi step| / sigma`` (8.1)."""
    count, params = lin.psi.shape
    variance = float(error @ error) / max(count - params, 1)
    if variance == 0.0:
        return np.inf
    return float(np.linalg.norm(lin.psi @ step) / np.sqrt(variance))


def iterate(problem: Problem, state: State, *, method: str, frozen: np.ndarray,
            max_iterations: int, tolerance: float, first_ls: bool = True,
            trust_first_ls: bool = False, full_steps_only: bool = False) -> IterationResult:
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

    Returns
    -------
    IterationResult
        End state, accepted updates and the stopping rule that fired.

    Notes
    -----
    Each update tries the full primary step, then the full Gauss-Newton step, and only then
    halves them and falls back to Levenberg-Marquardt: a biased first least-squares step then
    costs one cost evaluation, not a whole halving sequence (``docs/algorithm.md`` section 6).

    """
    history: List[Iteration] = []

    def stop(reason: StopReason) -> IterationResult:
        return IterationResult(state, history, reason,
                               reason.describe(tolerance, max_iterations))

    for iteration in range(max_iterations):
        lin = problem.linearize(state.coefficients, regressors=method != 'gn')
        error = problem.measured - lin.output
        free = _free_mask(state.theta, lin, error, problem, frozen)
        if not np.any(free):
            return stop(StopReason.ALL_AT_BOUNDS)
        primary = 'gn' if method == 'gn' else ('ls' if method == 'ls' or (
            iteration == 0 and first_ls) else 'iv')
        directions: Dict[Tuple[str, float], Optional[np.ndarray]] = {}

        def direction(kind: str, damping: float) -> Optional[np.ndarray]:
            if (kind, damping) not in directions:
                directions[kind, damping] = _direction(kind, lin, error, free, damping)
            return directions[kind, damping]

        first = direction(primary, 0.0)
        if primary != 'ls' and first is not None and \
                _step_size(lin, error, first) < NEGLIGIBLE_STEP:
            return stop(StopReason.NEGLIGIBLE_UPDATE)
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
        if full_steps_only:
            attempts = [(kind, damping, _FULL_STEP, monotone)
                        for kind, damping, _, monotone in attempts if kind != 'lm']
        accepted = None
        tried = set()
        for kind, damping, scales, monotone in attempts:
            step = direction(kind, damping)
            if step is None or (kind, damping, scales) in tried:
                continue
            tried.add((kind, damping, scales))
            outcome = _try_step(problem, state, step, monotone, scales)
            if outcome is not None:
                accepted = (kind, step, outcome)
                break
        if accepted is None:
            return stop(StopReason.NO_FULL_STEP if full_steps_only else StopReason.NO_DECREASE)
        kind, step, (new_state, scale) = accepted
        change = np.max(np.abs(scale * step) / np.maximum(np.abs(state.theta), 1e-12))
        decrease = (state.cost - new_state.cost) / max(state.cost, np.finfo(float).tiny)
        state = new_state
        history.append(Iteration(state.theta.copy(), state.cost, scale, kind))
        if change < tolerance:
            return stop(StopReason.PARAMETER_CHANGE)
        if method != 'ls' and 0.0 <= decrease < tolerance ** 2 and kind != 'ls':
            return stop(StopReason.COST_DECREASE)
        if state.cost <= 1e-30 * max(float(problem.measured @ problem.measured), 1e-300):
            return stop(StopReason.EXACT_FIT)
    return stop(StopReason.ITERATION_LIMIT)
