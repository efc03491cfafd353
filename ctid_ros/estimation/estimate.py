"""
Projection-based iterative estimation of grey-box continuous-time models.

Implements the method of Maruta & Sugie (see ``shared/docs/algorithm.md``): at the current
estimate ``theta_k`` the output error ``e = y - G(p, theta_k) u`` is projected onto regressors
``phi`` built by filtering ``u`` and ``y`` through ``1/D(p, theta_k)``:

* the first iteration is the least-squares projection (exact in one step for noise-free affine
  structures, from any stable start);
* later iterations use instruments ``psi`` built from the noise-free model output, an oblique
  projection whose fixed points are the output-error (maximum-likelihood) stationary points, so
  the estimate is consistent under coloured measurement noise;
* every step is controlled: the box bounds truncate it, ``D`` must stay Hurwitz and the
  output-error cost may never increase (step halving, then Gauss-Newton and Levenberg-Marquardt
  fallbacks).

A dead time ``exp(-tau s)`` is located first by a profile over a grid of frozen ``tau`` values,
then estimated jointly (fractional values are exact under a zero-order hold).

A complete initial guess is iterated first; if the model it reaches leaves a residual
independent of the input, the automatic start and the dead-time profile are not needed (see
:mod:`ctid_ros.estimation.starts`).
"""

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union
import warnings

from ctid_ros.core.data import Data
from ctid_ros.core.model import Coefficients, Model
from ctid_ros.core.simulation import ContinuousFilter
from ctid_ros.errors import DataError, EstimationError, ModelError
from ctid_ros.estimation.integrating import default_cutoff, StabilizedModel
from ctid_ros.estimation.regressors import is_stable, Linearization, SignalBank
import numpy as np
from scipy import linalg
from threadpoolctl import ThreadpoolController

METHODS = ('iv', 'ls', 'gn')
INITIAL_STATES = ('zero', 'estimate')
Bounds = Mapping[str, Tuple[Optional[float], Optional[float]]]
Initial = Union[str, None, Mapping[str, float]]

_HALVINGS = 14
_FULL_STEP = (1.0,)
_HALVED_STEPS = tuple(0.5 ** np.arange(1, _HALVINGS))
_ALL_STEPS = _FULL_STEP + _HALVED_STEPS
_IV_CONDITION_LIMIT = 1e10
_IDENTIFIABILITY_LIMIT = 1e10
_SYMMETRY_RESTARTS = 3
# An update smaller than this many standard deviations of the estimate changes nothing a user
# can see: the iteration stops instead of resolving noise to the last digit.
_NEGLIGIBLE_STEP = 1e-3
NO_FULL_STEP = 'no full step decreases the cost'
# Full steps from a complete guess before its residual is tested (FOPDT benchmark, 100 starts
# within x10: median 13.9 ms with six, 14.7 ms with four that left more of them unconverged).
_WARM_START_ITERATIONS = 6


@dataclass
class Iteration:
    """One accepted update: parameters after it, cost, step length and the direction used."""

    theta: np.ndarray
    cost: float
    step: float
    direction: str


@dataclass
class Estimate:
    """
    Result of :func:`estimate`.

    Attributes
    ----------
    model : Model
        The identified structure.
    params, std : dict
        Estimated parameter values and their standard deviations, by name.
    covariance : ndarray
        Parameter covariance in ``model.parameters`` order.
    fit : float
        Normalised fit in percent, ``100 (1 - |y - yhat| / |y - mean(y)|)`` as MATLAB's compare,
        on the fitted samples (for an integrating model: of the high-passed output).
    converged : bool
        True if a convergence test (not the iteration limit or a failed step) stopped it.
    iterations : int
        Number of accepted updates (joint dead-time refinement included).
    cost : float
        Output-error cost ``0.5 |y - yhat|^2``.
    stop_reason : str
        Which stopping rule fired.
    history : list of Iteration
        Parameter vector and cost after every accepted update.
    noise_variance : float
        Residual variance ``|e|^2 / (N - n_theta)``.
    condition : float
        Condition number of the column-scaled sensitivity matrix at the estimate.
    warnings : list of str
        Conditions a user should know about (active bounds, weak excitation, ...).
    delay_profile : list of (tau, cost)
        Costs of the dead-time grid search, if one ran.
    start : {'initial', 'search'}
        ``'initial'``: the given values, iterated a few times, explained the data (their
        residual is independent of the input), so no automatic start was searched;
        ``'search'``: the automatic start (and, for a dead time, the delay search) was used.
    initial_state, output_offset, integrator_cutoff
        The options of :func:`estimate` that shaped the fit (:meth:`compare` uses the first
        two on validation data).

    """

    model: Model
    params: Dict[str, float]
    std: Dict[str, float]
    covariance: np.ndarray
    fit: float
    converged: bool
    iterations: int
    cost: float
    stop_reason: str
    history: List[Iteration]
    noise_variance: float
    condition: float
    intersample: str = 'zoh'
    warnings: List[str] = field(default_factory=list)
    delay_profile: List[Tuple[float, float]] = field(default_factory=list)
    start: str = 'search'
    initial_state: str = 'zero'
    output_offset: bool = False
    integrator_cutoff: Optional[float] = None

    @property
    def theta(self) -> np.ndarray:
        """Parameter vector in ``model.parameters`` order."""
        return self.model.vector(self.params)

    def simulate(self, data: Union[Data, Sequence[float]], ts: Optional[float] = None
                 ) -> np.ndarray:
        """Simulate the identified model on ``data`` (or on an input array with ``ts``)."""
        if isinstance(data, Data):
            return self.model.simulate(self.params, data.u, data.ts,
                                       intersample=self.intersample)
        if ts is None:
            raise ValueError('give the sample time ts when simulating an input array')
        return self.model.simulate(self.params, data, ts, intersample=self.intersample)

    def predict(self, data: Data) -> np.ndarray:
        """
        Return the simulated output on ``data`` as :meth:`compare` sees it.

        The model response to ``data.u``, plus an initial-state response and/or a constant
        output offset fitted to ``data.y`` by least squares if the estimation estimated them.
        An integrating model starts at rest at ``data.y[0]``.
        """
        output = self.simulate(data)
        if self.model.integrators:
            output = output + data.y[0]
        columns = nuisance_columns(self.model.coefficients(self.params).den, len(data), data.ts,
                                   self.initial_state == 'estimate', self.output_offset)
        return _fitted(data.y, output, _orthonormal(columns))

    def compare(self, data: Data) -> float:
        """Fit in percent of the identified model on (validation) ``data``, see :meth:`predict`."""
        return fit_percent(data.y, self.predict(data))

    def to_dict(self) -> dict:
        """Summary as plain JSON-serialisable types (the ``ctid fit --json`` object)."""
        return {
            'params': dict(self.params),
            'std': dict(self.std),
            'fit': float(self.fit),
            'converged': bool(self.converged),
            'iterations': int(self.iterations),
            'cost': float(self.cost),
            'stop_reason': self.stop_reason,
            'start': self.start,
            'warnings': list(self.warnings),
        }


def fit_percent(y: np.ndarray, yhat: np.ndarray) -> float:
    """Normalised root-mean-square fit in percent (100 is a perfect fit)."""
    spread = np.linalg.norm(y - np.mean(y))
    if spread == 0.0:
        return float('nan')
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / spread))


def nuisance_columns(den: np.ndarray, count: int, ts: float, initial_state: bool,
                     output_offset: bool) -> Optional[np.ndarray]:
    """
    Return the output components fitted besides ``G u`` as columns, or None.

    ``initial_state``: the free responses of ``1/D`` (a nonzero initial state, algorithm notes
    section 5.8); ``output_offset``: a constant. Their coefficients enter linearly, so they are
    projected out of every residual, regressor and instrument (variable projection).
    """
    columns = []
    if initial_state:
        columns.append(ContinuousFilter(den).discretize(ts).free_responses(count))
    if output_offset:
        columns.append(np.ones((count, 1)))
    return np.hstack(columns) if columns else None


def _orthonormal(columns: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """Orthonormal basis of the span of ``columns`` (None stays None)."""
    if columns is None:
        return None
    norms = np.linalg.norm(columns, axis=0)
    return linalg.orth(columns / np.where(norms > 0.0, norms, 1.0))


def _fitted(measured: np.ndarray, output: np.ndarray, basis: Optional[np.ndarray]
            ) -> np.ndarray:
    """Model output plus its least-squares fitted nuisance part."""
    if basis is None:
        return output
    return output + basis @ (basis.T @ (measured - output))


class _Problem:
    """Data, model and constraints of one estimation; evaluates costs and directions."""

    def __init__(self, model: Model, data: Data, lower: np.ndarray, upper: np.ndarray,
                 intersample: str, initial_state: bool = False, output_offset: bool = False):
        self.model = model
        self.data = data
        self.lower = lower
        self.upper = upper
        self.bank = SignalBank(model, data.u, data.y, data.ts, intersample)
        self.initial_state = initial_state
        self.output_offset = output_offset
        self.evaluations = 0
        self.skip = 0
        self._leading_sign = None
        self._latest: Optional[Tuple[bytes, Linearization]] = None

    @cached_property
    def delay_guess(self) -> float:
        """Return the data's own dead-time guess (initialization.impulse_delay), once."""
        from ctid_ros.estimation.starts import impulse_delay

        # The start, the delay bracket, the residual checks and the grid all ask for it.
        return impulse_delay(self.data)

    @property
    def measured(self) -> np.ndarray:
        """Output samples that are fitted (after the excluded transient)."""
        return self.data.y[self.skip:]

    def _basis(self, coefficients: Coefficients) -> Optional[np.ndarray]:
        columns = nuisance_columns(coefficients.den, len(self.data), self.data.ts,
                                   self.initial_state, self.output_offset)
        return None if columns is None else _orthonormal(columns[self.skip:])

    def prediction(self, coefficients: Coefficients) -> np.ndarray:
        """Model output on the fitted samples, with the fitted initial state and offset."""
        return _fitted(self.measured, self.bank.output(coefficients)[self.skip:],
                       self._basis(coefficients))

    def linearize(self, coefficients: Coefficients, regressors: bool = True) -> Linearization:
        """
        Output, regressors and instruments on the fitted samples (nuisance projected out).

        The latest result is kept: the final estimate is linearised once for the stopping
        rule, the identifiability check and the covariance.

        """
        key = b''.join(np.ascontiguousarray(part).tobytes() for part in (
            coefficients.den, coefficients.num, coefficients.delay, coefficients.den_jacobian,
            coefficients.num_jacobian, coefficients.delay_gradient, self.skip))
        if self._latest is not None and self._latest[0] == key and (
                self._latest[1].phi is not None or not regressors):
            return self._latest[1]
        lin = self._linearized(coefficients, regressors)
        self._latest = (key, lin)
        return lin

    def _linearized(self, coefficients: Coefficients, regressors: bool) -> Linearization:
        lin = self.bank.linearize(coefficients, regressors)
        output, phi, psi = (lin.output[self.skip:],
                            None if lin.phi is None else lin.phi[self.skip:],
                            lin.psi[self.skip:])
        basis = self._basis(coefficients)
        if basis is not None:
            output = _fitted(self.measured, output, basis)
            psi = psi - basis @ (basis.T @ psi)
            if phi is not None:
                phi = phi - basis @ (basis.T @ phi)
        return Linearization(output, phi, psi)

    def exclude_transient(self, seconds: Union[float, str], coefficients: Coefficients) -> None:
        """
        Leave the first samples out of every sum, so data that do not start at rest fit.

        ``'auto'`` takes five times the slowest time constant of ``coefficients`` plus its dead
        time, at most half of the record.

        """
        if seconds == 'auto':
            seconds = settling_time(coefficients)
        seconds = float(seconds)
        if not (np.isfinite(seconds) and seconds >= 0.0):
            raise ValueError(f"transient must be 'auto' or a non-negative time, got {seconds}")
        self.skip = int(min(np.ceil(seconds / self.data.ts), len(self.data) // 2))

    def admissible(self, theta: np.ndarray) -> Optional[Coefficients]:
        """Coefficients at theta if theta is inside the bounds and ``D`` is stable, else None."""
        if np.any(theta < self.lower) or np.any(theta > self.upper):
            return None
        try:
            coefficients = self.model.coefficients(theta)
        except ModelError:
            return None
        if coefficients.delay < 0.0 or not is_stable(coefficients.den):
            return None
        sign = np.sign(coefficients.den[0])
        if self._leading_sign is not None and sign != self._leading_sign:
            return None
        return coefficients

    def anchor(self, coefficients: Coefficients) -> None:
        """Fix the sign of D's leading coefficient: crossing zero would change the order."""
        self._leading_sign = np.sign(coefficients.den[0])

    def cost(self, coefficients: Coefficients) -> float:
        self.evaluations += 1
        error = self.measured - self.prediction(coefficients)
        return 0.5 * float(error @ error)


@dataclass
class _State:
    theta: np.ndarray
    coefficients: Coefficients
    cost: float


@lru_cache(maxsize=1)
def _thread_pools() -> ThreadpoolController:
    # Finding the loaded BLAS libraries takes milliseconds: once per process, not per estimate.
    return ThreadpoolController()


def settling_time(coefficients: Coefficients) -> float:
    """Return five times the slowest time constant of ``D`` plus the dead time (seconds)."""
    roots = np.roots(coefficients.den) if coefficients.den.size > 1 else np.zeros(0)
    slowest = float(np.max(-1.0 / roots.real, initial=0.0)) if roots.size else 0.0
    return 5.0 * slowest + max(coefficients.delay, 0.0)


def _column_scales(psi: np.ndarray) -> np.ndarray:
    scales = np.linalg.norm(psi, axis=0)
    return np.where(scales > 0.0, scales, 1.0)


def _direction(kind: str, lin: Linearization, error: np.ndarray, free: np.ndarray,
               damping: float = 0.0) -> Optional[np.ndarray]:
    """Update direction on the free parameters (zeros elsewhere), or None if singular."""
    psi = lin.psi[:, free]
    scales = _column_scales(psi)
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
               problem: _Problem, frozen: np.ndarray) -> np.ndarray:
    """Active set: drop parameters that sit on a bound and whose gradient pushes outward."""
    gradient = lin.psi.T @ error                     # -dV/dtheta
    span = np.maximum(np.abs(theta), 1.0)
    at_lower = (theta - problem.lower <= 1e-9 * span) & (gradient < 0)
    at_upper = (problem.upper - theta <= 1e-9 * span) & (gradient > 0)
    return ~(frozen | at_lower | at_upper)


def _try_step(problem: _Problem, state: _State, step: np.ndarray, monotone: bool,
              scales: Sequence[float]) -> Optional[Tuple[_State, float]]:
    """First admissible candidate ``theta + scale * step`` (box-limited) that does not raise V."""
    limit = _box_limit(state.theta, step, problem.lower, problem.upper)
    for scale in scales:
        candidate = state.theta + limit * scale * step
        coefficients = problem.admissible(candidate)
        if coefficients is not None:
            cost = problem.cost(coefficients)
            if not monotone or cost <= state.cost:
                return _State(candidate, coefficients, cost), limit * scale
    return None


def _step_size(lin: Linearization, error: np.ndarray, step: np.ndarray) -> float:
    """Length of ``step`` in standard deviations of the estimate, ``|Psi step| / sigma``."""
    count, params = lin.psi.shape
    variance = float(error @ error) / max(count - params, 1)
    if variance == 0.0:
        return np.inf
    return float(np.linalg.norm(lin.psi @ step) / np.sqrt(variance))


def _iterate(problem: _Problem, state: _State, *, method: str, frozen: np.ndarray,
             max_iterations: int, tolerance: float, first_ls: bool = True,
             trust_first_ls: bool = False, full_steps_only: bool = False
             ) -> Tuple[_State, List[Iteration], str, bool]:
    """
    Run the controlled projection iteration from ``state``.

    Each update tries the full primary step, then the full Gauss-Newton step, and only then
    halves them and falls back to Levenberg-Marquardt: a biased first least-squares step then
    costs one cost evaluation, not a whole halving sequence.

    ``trust_first_ls`` accepts the first (least-squares) step even if it raises the cost, as
    long as the model stays stable and inside the bounds: for an affine structure that step is
    the exact regression from any start, which is what a profile over frozen parameters needs.

    ``full_steps_only`` gives up (not converged) at the first update that needs a shorter or
    damped step: a quick check of a start that is either close to a minimum or not worth the
    halving.

    """
    history: List[Iteration] = []
    for iteration in range(max_iterations):
        lin = problem.linearize(state.coefficients, regressors=method != 'gn')
        error = problem.measured - lin.output
        free = _free_mask(state.theta, lin, error, problem, frozen)
        if not np.any(free):
            return state, history, 'all parameters fixed at bounds', True
        primary = 'gn' if method == 'gn' else ('ls' if method == 'ls' or (
            iteration == 0 and first_ls) else 'iv')
        directions = {}

        def direction(kind: str, damping: float) -> Optional[np.ndarray]:
            if (kind, damping) not in directions:
                directions[kind, damping] = _direction(kind, lin, error, free, damping)
            return directions[kind, damping]

        first = direction(primary, 0.0)
        if primary != 'ls' and first is not None and \
                _step_size(lin, error, first) < _NEGLIGIBLE_STEP:
            return state, history, \
                f'update below {_NEGLIGIBLE_STEP:g} standard deviations', True
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
            attempts += [('lm', damping, _ALL_STEPS, True) for damping in (1e-2, 1.0, 1e2)]
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
        if accepted is None and full_steps_only:
            return state, history, NO_FULL_STEP, False
        if accepted is None:
            return state, history, 'no admissible step decreases the cost', True
        kind, step, (new_state, scale) = accepted
        change = np.max(np.abs(scale * step) / np.maximum(np.abs(state.theta), 1e-12))
        decrease = (state.cost - new_state.cost) / max(state.cost, np.finfo(float).tiny)
        state = new_state
        history.append(Iteration(state.theta.copy(), state.cost, scale, kind))
        if change < tolerance:
            return state, history, f'relative parameter change below {tolerance:g}', True
        if method != 'ls' and 0.0 <= decrease < tolerance ** 2 and kind != 'ls':
            return state, history, 'relative cost decrease below resolution', True
        if state.cost <= 1e-30 * max(float(problem.measured @ problem.measured), 1e-300):
            return state, history, 'output reproduced exactly', True
    return state, history, f'iteration limit ({max_iterations}) reached', False


def bound_vectors(model: Model, bounds: Optional[Bounds]) -> Tuple[np.ndarray, np.ndarray]:
    """Return lower and upper bound vectors in parameter order (a dead time >= 0)."""
    lower = np.full(len(model.parameters), -np.inf)
    upper = np.full(len(model.parameters), np.inf)
    for name, pair in (bounds or {}).items():
        if name not in model.parameters:
            raise ModelError(f'bounds given for unknown parameter {name!r}; the model has '
                             f'{", ".join(model.parameters)}')
        index = model.parameters.index(name)
        low, high = pair
        lower[index] = -np.inf if low is None else float(low)
        upper[index] = np.inf if high is None else float(high)
        if not lower[index] < upper[index]:
            raise ModelError(f'bounds for {name} are empty: {low} >= {high}')
    delay_index = delay_parameter(model)
    if delay_index is not None:
        lower[delay_index] = max(lower[delay_index], 0.0)
    return lower, upper


def delay_parameter(model: Model) -> Optional[int]:
    """Index of the parameter that is the dead time itself (``exp(-tau*s)``), if any."""
    if not model.delay_is_estimated:
        return None
    probe = model.coefficients(np.ones(len(model.parameters)))
    gradient = probe.delay_gradient
    nonzero = np.flatnonzero(gradient)
    if nonzero.size == 1 and gradient[nonzero[0]] == 1.0:
        return int(nonzero[0])
    return None


def _check_excitation(model: Model, data: Data) -> None:
    if data.input_count != len(model.inputs):
        raise DataError(f'the model has {len(model.inputs)} input(s) '
                        f'({", ".join(model.inputs)}), the data have {data.input_count}')
    spans = np.ptp(data.u.reshape(len(data), -1), axis=0)
    for name, span in zip(model.inputs, spans):
        if span == 0.0:
            raise EstimationError(f'the input {name} is constant: it does not excite the '
                                  'system, so no dynamic parameter can be identified')
    if np.ptp(data.y) == 0.0:
        raise EstimationError('the output is constant: the data carry no information about '
                              'the dynamics (is the output topic/column the right one?)')
    if len(data) < 10:
        raise EstimationError(f'only {len(data)} samples: too few to identify a model')


def _blind_combination(problem: _Problem, state: _State) -> Optional[str]:
    """Explain why the output is (almost) blind to a parameter combination, or None."""
    lin = problem.linearize(state.coefficients, regressors=False)
    norms = np.linalg.norm(lin.psi, axis=0)
    if np.any(norms == 0.0):
        dead = ', '.join(problem.model.parameters[i] for i in np.flatnonzero(norms == 0.0))
        return f'the output does not depend on {dead} on these data: the input does not excite it'
    singular, vectors = np.linalg.svd(lin.psi / norms, full_matrices=False)[1:]
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else np.inf
    if condition <= _IDENTIFIABILITY_LIMIT:
        return None
    names = [f'{weight:+.2f}*{name}' for weight, name in
             zip(vectors[-1], problem.model.parameters) if abs(weight) > 0.1]
    return ('the parameters are not identifiable from these data: the combination '
            f'{" ".join(names)} has (almost) no effect on the output (condition number '
            f'{condition:.1e}); fix one of them, reparameterise the model or use a richer input')


def _nudged(problem: _Problem, state: _State, rng: np.random.Generator) -> Optional[_State]:
    """Perturb a point where symmetric parameters coincide (e.g. T1 = T2) so they can split."""
    for _ in range(_HALVINGS):
        theta = state.theta * (1.0 + 0.05 * rng.standard_normal(state.theta.size))
        theta = np.clip(theta, problem.lower, problem.upper)
        coefficients = problem.admissible(theta)
        if coefficients is not None:
            return _State(theta, coefficients, problem.cost(coefficients))
    return None


def _covariance(problem: _Problem, state: _State) -> Tuple[np.ndarray, float, float]:
    lin = problem.linearize(state.coefficients, regressors=False)
    error = problem.measured - lin.output
    count, params = lin.psi.shape
    variance = float(error @ error) / max(count - params, 1)
    scales = _column_scales(lin.psi)
    _, singular, vt = np.linalg.svd(lin.psi / scales, full_matrices=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else np.inf
    inverse = (vt.T / singular ** 2) @ vt
    covariance = variance * inverse / np.outer(scales, scales)
    return covariance, variance, condition


def estimate(model: Model, data: Data, initial: Initial = 'auto', *,
             bounds: Optional[Bounds] = None, method: str = 'iv', intersample: str = 'zoh',
             max_iterations: int = 100, tolerance: float = 1e-8,
             delay_range: Optional[Tuple[float, float]] = None,
             transient: Union[float, str] = 0.0, initial_state: str = 'zero',
             output_offset: bool = False, integrator_cutoff: Optional[float] = None
             ) -> Estimate:
    """
    Estimate the parameters of a grey-box continuous-time model from sampled data.

    Parameters
    ----------
    model : Model
        Model structure (open loop, or closed loop with a known controller; then ``data.u`` is
        the reference ``r``). Integrators (``D = s^k D'``) are fitted through the exact stable
        reformulation of :mod:`ctid_ros.estimation.integrating`.
    data : Data
        Uniformly sampled input/output data (one column of ``u`` per model input), starting at
        rest unless ``initial_state``/``transient`` say otherwise. Offsets are not removed: use
        :meth:`Data.detrend`, ``output_offset`` or a constant term of a model equation.
    initial : dict, 'auto' or None
        Initial values by parameter name. Missing names (or ``'auto'``/None) are initialised
        automatically from a state-variable-filter least-squares fit with multi-start. A
        complete set is iterated first and kept if its residual is independent of the input
        (``Estimate.start == 'initial'``); otherwise it competes with the automatic start.
    bounds : dict, optional
        ``{name: (lower, upper)}``, either side may be None. A dead-time parameter is kept
        non-negative in any case.
    method : {'iv', 'ls', 'gn'}
        ``'iv'``: least-squares projection first, then instrumental-variable projections
        (consistent, default). ``'ls'``: least-squares projection at every iteration (biased
        under noise; for comparison). ``'gn'``: Gauss-Newton on the output error.
    intersample : {'zoh', 'foh'}
        Behaviour of the input between samples.
    max_iterations : int
        Limit on the number of updates of the final iteration.
    tolerance : float
        Stop when the largest relative parameter change falls below it. The iteration also
        stops when the next update is below 0.001 standard deviations of the estimate.
    delay_range : (float, float), optional
        Search range in seconds for a dead-time parameter; default from its bounds, else
        automatic.
    transient : float or 'auto'
        Seconds at the start of the record that are simulated but not fitted, for data that do
        not start at rest (e.g. a window cut from a running plant). ``'auto'``: five times the
        slowest time constant of the starting model plus its dead time (at most half of the
        record). Default 0: the data start at rest.
    initial_state : {'zero', 'estimate'}
        ``'estimate'``: fit the response of an unknown initial state (the free responses of
        ``1/D``) along with the parameters, for records that do not start at rest.
    output_offset : bool
        Fit a constant added to the output (an unknown operating point of ``y``).
    integrator_cutoff : float, optional
        Corner in rad/s of the high pass applied to the output of an integrating model; default
        ``20 pi / T`` for a record of ``T`` seconds (ten periods per record).

    Returns
    -------
    Estimate
        Estimates, standard deviations, covariance, fit and iteration record.

    Raises
    ------
    EstimationError
        If the data cannot identify the parameters or no stable starting point is found.
    ModelError
        If initial values or bounds do not match the model.

    """
    from ctid_ros.estimation.starts import (complete_guess, delay_search, explains_data,
                                            initial_estimate, local_fit)

    if method not in METHODS:
        raise ValueError(f'method must be one of {METHODS}, got {method!r}')
    if max_iterations < 1:
        raise ValueError('max_iterations must be at least 1')
    if initial_state not in INITIAL_STATES:
        raise ValueError(f'initial_state must be one of {INITIAL_STATES}, got {initial_state!r}')
    _check_excitation(model, data)
    lower, upper = bound_vectors(model, bounds)
    fitted_model, fitted_data, cutoff = model, data, None
    if model.integrators:
        cutoff = default_cutoff(len(data) * data.ts) if integrator_cutoff is None \
            else float(integrator_cutoff)
        fitted_model = StabilizedModel(model, cutoff)
        fitted_data = Data(data.u, fitted_model.filtered_output(data.y, data.ts), data.ts,
                           data.t0)
    problem = _Problem(fitted_model, fitted_data, lower, upper, intersample,
                       initial_state == 'estimate', output_offset)
    # The matrices are tiny: threaded BLAS only adds spin-waiting (about 6x slower under load).
    with warnings.catch_warnings(), _thread_pools().limit(limits=1, user_api='blas'):
        warnings.simplefilter('ignore', RuntimeWarning)
        delay_index = delay_parameter(model)
        profile: List[Tuple[float, float]] = []
        history: List[Iteration] = []
        # A complete guess (a warm start) is iterated first; if that model leaves nothing
        # correlated with the input there is nothing for the global start and search to find.
        start = complete_guess(problem, initial)
        from_initial = False
        if start is not None:
            start = _started(problem, start, transient)
            start, history, held = local_fit(problem, start, method, first_ls=True,
                                             full_steps_only=True,
                                             iterations=_WARM_START_ITERATIONS)
            from_initial = held and explains_data(problem, start, delay_index, delay_range)
        refined = from_initial
        if not from_initial:
            history = []
            start = _started(problem, initial_estimate(problem, initial, delay_range), transient)
            if delay_index is not None:
                start, profile, history = delay_search(problem, start, delay_index,
                                                       delay_range)
            refined = delay_index is not None
        frozen = np.zeros(len(model.parameters), dtype=bool)
        # A start refined by iterations needs no least-squares step.
        final, more, reason, converged = _iterate(
            problem, start, method=method, frozen=frozen, max_iterations=max_iterations,
            tolerance=tolerance, first_ls=not refined)
        history.extend(more)
        rng = np.random.default_rng(0)
        for _ in range(_SYMMETRY_RESTARTS):
            if _blind_combination(problem, final) is None:
                break
            nudged = _nudged(problem, final, rng)
            if nudged is None:
                break
            final, more, reason, converged = _iterate(
                problem, nudged, method=method, frozen=frozen,
                max_iterations=max_iterations, tolerance=tolerance, first_ls=False)
            history.extend(more)
        blind = _blind_combination(problem, final)
        if blind is not None:
            raise EstimationError(blind)
        covariance, variance, condition = _covariance(problem, final)
    std = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    notes = _warnings(problem, final, converged, reason)
    fit = fit_percent(problem.measured, problem.prediction(final.coefficients))
    return Estimate(
        model=model, params=model.as_dict(final.theta), std=model.as_dict(std),
        covariance=covariance, fit=fit, converged=converged, iterations=len(history),
        cost=final.cost, stop_reason=reason, history=history, noise_variance=variance,
        condition=condition, intersample=intersample, warnings=notes, delay_profile=profile,
        start='initial' if from_initial else 'search', initial_state=initial_state,
        output_offset=output_offset, integrator_cutoff=cutoff)


def _started(problem: _Problem, start: _State, transient: Union[float, str]) -> _State:
    """Anchor the sign of D's leading coefficient and leave out the transient, from ``start``."""
    problem.anchor(start.coefficients)
    if not transient:
        return start
    problem.exclude_transient(transient, start.coefficients)
    return _State(start.theta, start.coefficients, problem.cost(start.coefficients))


def _warnings(problem: _Problem, state: _State, converged: bool, reason: str) -> List[str]:
    notes = []
    span = np.maximum(np.abs(state.theta), 1.0)
    for index, name in enumerate(problem.model.parameters):
        if state.theta[index] - problem.lower[index] <= 1e-6 * span[index]:
            notes.append(f'{name} is at its lower bound {problem.lower[index]:g}')
        elif problem.upper[index] - state.theta[index] <= 1e-6 * span[index]:
            notes.append(f'{name} is at its upper bound {problem.upper[index]:g}')
    if not converged:
        notes.append(f'not converged: {reason}')
    return notes
