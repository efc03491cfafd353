"""
Grey-box continuous-time estimation: :func:`estimate` and its result :class:`Estimate`.

Implements the method of Maruta & Sugie as described in ``docs/algorithm.md``: at the current
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
independent of the input, the automatic start and the dead-time profile are not needed.

The layers below: :mod:`~ctid_ros.estimation.problem` (data, bounds, cost),
:mod:`~ctid_ros.estimation.iteration` (the controlled iteration),
:mod:`~ctid_ros.estimation.starts` (automatic start, warm-start check) and
:mod:`~ctid_ros.estimation.delay_search`. This module adds the orchestration, the
identifiability check and the covariance (``docs/algorithm.md`` sections 1, 14 and 15).
"""

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Dict, List, Optional, Sequence, Tuple, Union
import warnings

from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import DataError, EstimationError, ModelError
from ctid_ros.estimation.consistency import Consistency, with_consistency
from ctid_ros.estimation.delay_search import across_the_sample, delay_search
from ctid_ros.estimation.integrating import default_cutoff, StabilizedModel
from ctid_ros.estimation.iteration import (column_scales, free_parameters, iterate, Iteration,
                                           IterationResult, on_bounds, StopReason)
from ctid_ros.estimation.noise import coloured_covariance, measured_every, NoiseModel
from ctid_ros.estimation.options import check_options
from ctid_ros.estimation.problem import (bound_vectors, Bounds, delay_parameter, DelayRange,
                                         nuisance_columns, orthonormal_basis, Problem,
                                         settling_time, State, with_fitted_nuisance)
from ctid_ros.estimation.residual_analysis import (analyse_residual, DEFAULT_LAGS,
                                                   ResidualAnalysis)
from ctid_ros.estimation.starts import (complete_guess, explains_data, Initial,
                                        initial_estimate, local_fit, random_starts,
                                        resembles_output)
import numpy as np
from threadpoolctl import ThreadpoolController

__all__ = [
    'Estimate', 'ILL_CONDITIONED', 'LOW_FIT', 'Uncertainty', 'build_problem',
    'covariance', 'estimate', 'fit_percent',
]

_IDENTIFIABILITY_LIMIT = 1e10
# Above this condition number of the scaled sensitivities a combination is reported as weak.
ILL_CONDITIONED = 1e3
# Below this fit (%) the estimate carries a warning that the model explains almost nothing.
LOW_FIT = 10.0
_MAX_RESIDUAL_LAGS = 200
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
# Iterations that fit a nested structure without a dead time to search.
_NESTED_ITERATIONS = 10
# Output-error updates from each random draw when the residual says the model misses dynamics.
_ELSEWHERE_ITERATIONS = 20


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
        Which stopping rule of the final iteration fired: the text of a
        :class:`~ctid_ros.estimation.iteration.StopReason`.
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
        ``'initial'``: the given values, iterated a few times (full steps, then a short local
        optimisation to convergence), explained the data (their residual is independent of
        the input), so no automatic start was searched;
        ``'search'``: the automatic start (and, for a dead time, the delay search) was used.
    initial_state, output_offset, integrator_cutoff
        The options of :func:`estimate` that shaped the fit (:meth:`compare` uses the first
        two on validation data).
    residuals : ResidualAnalysis or None
        Autocorrelation of the residual and its cross-correlation with every input, their 99 %
        bounds and a one-line ``verdict`` (``white`` / ``input_correlated`` / ``feedback``), as
        MATLAB's ``resid``; also the order of the residual's noise model behind the
        covariance and how many samples apart the output was measured.
    consistency : Consistency or None
        Whether one parameter vector holds over the whole record (the halves' and quarters'
        estimates against the whole, :mod:`~ctid_ros.estimation.consistency`). If not, ``std``
        covers the scatter of the quarter estimates and ``covariance`` is scaled to match.
    std_noise : dict
        The standard deviations the noise alone implies (equal to ``std`` when consistent).

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
    residuals: Optional[ResidualAnalysis] = None
    consistency: Optional[Consistency] = None
    std_noise: Dict[str, float] = field(default_factory=dict)

    @property
    def theta(self) -> np.ndarray:
        """Parameter vector in ``model.parameters`` order."""
        return self.model.vector(self.params)

    def simulate(self, data: Union[Data, Sequence[float]], ts: Optional[float] = None
                 ) -> np.ndarray:
        """
        Simulate the identified model on ``data`` (or on an input array with ``ts``).

        The output is evaluated at the output instants of ``data`` (its ``output_skew``).
        """
        if isinstance(data, Data):
            return self.model.simulate(self.params, data.u, data.ts,
                                       intersample=self.intersample,
                                       output_skew=data.output_skew)
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
        return with_fitted_nuisance(data.y, output, orthonormal_basis(columns))

    def compare(self, data: Data) -> float:
        """Fit in percent of the identified model on (validation) ``data``, see :meth:`predict`."""
        return fit_percent(data.y, self.predict(data))

    def to_dict(self) -> dict:
        """Summary as plain JSON-serialisable types (the ``ctid fit --json`` object)."""
        summary = {
            'params': dict(self.params),
            # A parameter held at a bound has no standard deviation: null, not NaN.
            'std': {name: float(value) if np.isfinite(value) else None
                    for name, value in self.std.items()},
            'fit': float(self.fit),
            'converged': bool(self.converged),
            'iterations': int(self.iterations),
            'cost': float(self.cost),
            'stop_reason': self.stop_reason,
            'start': self.start,
            'condition': float(self.condition),
            'warnings': list(self.warnings),
        }
        if self.residuals is not None:
            summary['residual'] = self.residuals.to_dict()
        if self.consistency is not None:
            summary['consistency'] = self.consistency.to_dict()
            summary['std_noise'] = {name: float(value) if np.isfinite(value) else None
                                    for name, value in self.std_noise.items()}
        return summary


def fit_percent(y: np.ndarray, yhat: np.ndarray) -> float:
    """Normalised root-mean-square fit in percent (100 is a perfect fit)."""
    spread = np.linalg.norm(y - np.mean(y))
    if spread == 0.0:
        return float('nan')
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / spread))


@lru_cache(maxsize=1)
def _thread_pools() -> ThreadpoolController:
    # Finding the loaded BLAS libraries is slow: once per process, not per estimate.
    return ThreadpoolController()


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


class _Sensitivities:
    """
    The sensitivities of the free parameters at the latest state asked for, and their SVD.

    The identifiability check and the covariance of one estimate use the same column-scaled
    sensitivities: one decomposition serves both.
    """

    def __init__(self, problem: Problem):
        self._problem = problem
        self._latest: Optional[Tuple[State, tuple]] = None

    def at(self, state: State) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Optional[tuple]]:
        """
        Return ``free``, ``psi[:, free]``, its column norms and the SVD of ``psi / norms``.

        ``free`` are the parameters not held at a bound (:func:`free_parameters`); the SVD is
        None if a column is zero.
        """
        if self._latest is None or self._latest[0] is not state:
            problem = self._problem
            free = free_parameters(problem, state, np.zeros(state.theta.size, dtype=bool))
            psi = problem.linearize(state.coefficients, regressors=False).psi[:, free]
            norms = np.linalg.norm(psi, axis=0)
            svd = None if np.any(norms == 0.0) else \
                np.linalg.svd(psi / norms, full_matrices=False)
            self._latest = (state, (free, psi, norms, svd))
        return self._latest[1]


def _blind_combination(problem: Problem, state: State,
                       sensitivities: Optional[_Sensitivities] = None) -> Optional[str]:
    """
    Explain why the output is (almost) blind to a parameter combination, or None.

    Parameters held at a bound are left out.
    """
    free, psi, norms, svd = (sensitivities or _Sensitivities(problem)).at(state)
    if not np.any(free):
        return None
    names = [name for name, keep in zip(problem.model.parameters, free) if keep]
    if svd is None:
        dead = ', '.join(names[i] for i in np.flatnonzero(norms == 0.0))
        delay_index = delay_parameter(problem.model)
        record = problem.data.ts * len(problem.data)
        if np.all(norms == 0.0) and delay_index is not None and \
                state.theta[delay_index] >= 0.5 * record:
            return (f'the output does not depend on {dead} on these data: the dead time went '
                    f'to {state.theta[delay_index]:.4g} s, where the model output is zero over '
                    f'the {record:.4g} s record (the fit never found the input in the output). '
                    'A dead time beyond half the record is not searched: record longer, check '
                    'that input and output are the right signals, or bound the dead time')
        return f'the output does not depend on {dead} on these data: the input does not excite it'
    singular, vectors = svd[1:]
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else np.inf
    if condition <= _IDENTIFIABILITY_LIMIT:
        return None
    names = [f'{weight:+.2f}*{name}' for weight, name in zip(vectors[-1], names)
             if abs(weight) > 0.1]
    return ('the parameters are not identifiable from these data: the combination '
            f'{" ".join(names)} has (almost) no effect on the output (condition number '
            f'{condition:.1e}); fix one of them, reparameterise the model or use a richer input')


def _structurally_blind(model, theta: np.ndarray, rng: np.random.Generator) -> bool:
    """
    Return True if the transfer function itself ignores a combination of the parameters.

    The map from ``theta`` to the normalised coefficients (``N/d_0``, ``D/d_0`` without its
    leading 1, the dead time) is rank deficient at ``theta`` and at two random points near it:
    no data can separate such parameters (``g/(J s^2 + b s + k)``: only ratios count), so the
    model must change. Where the data alone cannot (time constants that coincide, lags far
    below the sample time acting as dead time, a poorly exciting input) the estimate is
    returned with the weakly determined combination in its warnings instead.
    """
    points = [theta] + [theta * (1.0 + 0.1 * rng.standard_normal(theta.size))
                        for _ in range(2)]
    for point in points:
        try:
            coefficients = model.coefficients(point)
        except ModelError:
            continue
        lead = coefficients.den[0]
        if lead == 0.0:
            continue
        values = np.concatenate([coefficients.num.ravel(), coefficients.den[1:]]) / lead
        lead_gradient = coefficients.den_jacobian[:, 0]
        jacobian = np.hstack([
            coefficients.num_jacobian.reshape(point.size, -1) / lead,
            coefficients.den_jacobian[:, 1:] / lead,
            coefficients.delay_gradient[:, None]])
        jacobian[:, :values.size] -= np.outer(lead_gradient, values) / lead
        # Rows: parameters; scaled by their size, so units do not matter.
        scaled = jacobian * np.maximum(np.abs(point), 1e-12)[:, None]
        singular = np.linalg.svd(scaled, compute_uv=False)
        if singular.size and singular[-1] > 1e-9 * singular[0] and \
                singular.size >= point.size:
            return False
    return True


def _nudged(problem: Problem, state: State, rng: np.random.Generator) -> Optional[State]:
    """Perturb a point where symmetric parameters coincide (e.g. T1 = T2) so they can split."""
    for _ in range(_NUDGES):
        theta = state.theta * (1.0 + 0.05 * rng.standard_normal(state.theta.size))
        theta = np.clip(theta, problem.lower, problem.upper)
        coefficients = problem.admissible(theta)
        if coefficients is not None:
            return problem.state(theta, coefficients)
    return None


@dataclass
class Uncertainty:
    """
    What :func:`covariance` finds at an estimate.

    Attributes
    ----------
    covariance : ndarray
        Parameter covariance valid under coloured residuals, ``model.parameters`` order; rows
        and columns of parameters held at a bound are NaN.
    variance : float
        ``|e|^2 / (N - n)``, the residual variance.
    condition : float
        Condition number of the column-scaled sensitivities of the free parameters.
    weakest : ndarray
        The (unit, scaled) parameter combination the data determine worst, over all
        parameters (zero for held ones).
    noise : NoiseModel
        The autoregressive model of the residual behind the covariance.
    free : ndarray of bool
        Parameters the data determine (not held at a bound).

    """

    covariance: np.ndarray
    variance: float
    condition: float
    weakest: np.ndarray
    noise: NoiseModel
    free: np.ndarray


def covariance(problem: Problem, state: State,
               autocorrelation: Optional[np.ndarray] = None,
               sensitivities: Optional[_Sensitivities] = None) -> Uncertainty:
    """
    Return the parameter covariance at ``state`` and what it rests on.

    The sandwich ``(Psi^T Psi)^-1 Psi^T Sigma Psi (Psi^T Psi)^-1`` of the output-error estimate,
    ``Sigma`` from an autoregressive model of the residual (:mod:`~ctid_ros.estimation.noise`):
    ``sigma^2 (Psi^T Psi)^-1``, ``sigma^2 = |e|^2 / (N - n_theta)``, when the residual is white.
    Only parameters the data determine enter (a parameter held at a bound gets NaN); the
    column-scaled sensitivities give the condition number and the weakest combination
    (``docs/algorithm.md`` section 15). ``autocorrelation``: the residual's, if known;
    ``sensitivities``: the identifiability check's, if it looked at ``state`` too.

    """
    lin = problem.linearize(state.coefficients, regressors=False)
    error = problem.measured - lin.output
    count, params = lin.psi.shape
    variance = float(error @ error) / max(count - params, 1)
    free, psi, norms, svd = (sensitivities or _Sensitivities(problem)).at(state)
    scales = np.where(norms > 0.0, norms, 1.0)
    if lin.delay_jump is not None or svd is None:
        # At a kink of the cost in the dead time (on the sample lattice) the two one-sided
        # sensitivities differ; their mean stands for both.
        psi = lin.psi if lin.delay_jump is None else lin.psi + 0.5 * lin.delay_jump
        psi = psi[:, free]
        scales = column_scales(psi)
        svd = np.linalg.svd(psi / scales, full_matrices=False)
    scaled, model = coloured_covariance(psi / scales, error, int(np.sum(free)), svd,
                                        autocorrelation)
    result = np.full((params, params), np.nan)
    result[np.ix_(free, free)] = scaled / np.outer(scales, scales)
    weakest = np.zeros(params)
    condition = 1.0
    if np.any(free):
        singular, vt = svd[1:]
        condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else np.inf
        weakest[free] = vt[-1] * np.sign(vt[-1][np.argmax(np.abs(vt[-1]))])
    return Uncertainty(result, variance, condition, weakest, model, free)


def estimate(model: Model, data: Data, initial: Initial = 'auto', *,
             bounds: Optional[Bounds] = None, method: str = 'iv', intersample: str = 'zoh',
             max_iterations: int = 100, tolerance: float = 1e-8,
             delay_range: DelayRange = None,
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
    ConfigError
        If an argument has the wrong type or value (:mod:`~ctid_ros.estimation.options`).
    EstimationError
        If the data cannot identify the parameters or no stable starting point is found.
    ModelError
        If initial values or bounds do not match the model.

    """
    (initial, bounds, method, intersample, max_iterations, tolerance, delay_range, transient,
     initial_state, output_offset, integrator_cutoff) = check_options(
        model, data, initial, bounds=bounds, method=method, intersample=intersample,
        max_iterations=max_iterations, tolerance=tolerance, delay_range=delay_range,
        transient=transient, initial_state=initial_state, output_offset=output_offset,
        integrator_cutoff=integrator_cutoff)
    _check_excitation(model, data)
    problem, cutoff = build_problem(model, data, bounds=bounds, intersample=intersample,
                                    initial_state=initial_state, output_offset=output_offset,
                                    integrator_cutoff=integrator_cutoff)
    # The matrices are tiny: threaded BLAS only adds spin-waiting, which dominates under load.
    with warnings.catch_warnings(), _thread_pools().limit(limits=1, user_api='blas'):
        warnings.simplefilter('ignore', RuntimeWarning)
        delay_index = delay_parameter(model)
        profile: List[Tuple[float, float]] = []
        history: List[Iteration] = []
        # A complete guess (a warm start) is iterated first; if that model leaves nothing
        # correlated with the input there is nothing for the global start and search to find.
        start = complete_guess(problem, initial)
        from_initial, settled = False, False
        if start is not None:
            start, history, from_initial, settled = _warm_start(
                problem, _started(problem, start, transient), method, delay_index, delay_range)
        refined = from_initial
        if not from_initial:
            history = []
            start = _started(problem, initial_estimate(problem, initial, delay_range), transient)
            if delay_index is not None:
                search = delay_search(problem, start, delay_index, delay_range)
                start, profile, history = search.state, search.profile, search.history
            nested = _nested_start(problem, initial, delay_range, delay_index, start)
            if nested is not None:
                start, history = nested
            refined = delay_index is not None or nested is not None
        frozen = np.zeros(len(model.parameters), dtype=bool)
        settings = {'method': method, 'frozen': frozen, 'max_iterations': max_iterations,
                    'tolerance': tolerance, 'check_optimality': True}
        if settled:
            # The warm start ended where the next update is negligible: the final iteration's
            # first test, on the same point.
            reason = StopReason.NEGLIGIBLE_UPDATE
            final = IterationResult(start, [], reason, reason.describe(tolerance, max_iterations))
        else:
            # A start refined by iterations needs no least-squares step.
            # A warm start that explained the data is a converged local fit: near its minimum.
            final = iterate(problem, start, first_ls=not refined, near_start=from_initial,
                            **settings)
        history.extend(final.history)
        rng = np.random.default_rng(0)
        final = _from_best_seen(problem, final, history, settings)
        sensitivities = _Sensitivities(problem)
        blind = _blind_combination(problem, final.state, sensitivities)
        for _ in range(_SYMMETRY_RESTARTS):
            if blind is None:
                break
            nudged = _nudged(problem, final.state, rng)
            if nudged is None:
                break
            restarted = iterate(problem, nudged, first_ls=False, **settings)
            history.extend(restarted.history)
            if restarted.state.cost >= final.state.cost:
                # Back where it started, or worse: the data put the minimum at the coincidence.
                break
            final = _from_best_seen(problem, restarted, history, settings)
            blind = _blind_combination(problem, final.state, sensitivities)
        analysis = _residual_analysis(problem, final.state)
        if not from_initial and blind is None:
            final = _elsewhere(problem, final, history, settings, delay_index, analysis)
            if delay_index is not None:
                across = across_the_sample(problem, final.state, delay_index, delay_range)
                if across is not None:
                    again = iterate(problem, across.state, first_ls=False, **settings)
                    history.extend(across.history + again.history)
                    final = _from_best_seen(problem, _lower(final, again), history, settings)
            blind = _blind_combination(problem, final.state, sensitivities)
        if blind is not None and (blind.startswith('the output does not depend') or
                                  _structurally_blind(problem.model, final.state.theta, rng)):
            # A model that explains nothing determines nothing either: that is the news.
            note = _fit_note(fit_percent(problem.measured,
                                         problem.prediction(final.state.coefficients)))
            raise EstimationError(blind if note is None else f'{note}; {blind}')
        residuals = analysis if analysis.state is final.state else \
            _residual_analysis(problem, final.state)
        uncertainty = covariance(problem, final.state, residuals.long_autocorrelation,
                                 sensitivities)
    residuals.noise_order = uncertainty.noise.order
    residuals.noise_power_ratio = uncertainty.noise.variance_ratio
    parameter_covariance = uncertainty.covariance
    variance, condition = uncertainty.variance, uncertainty.condition
    std = np.sqrt(np.abs(np.diag(parameter_covariance)))
    fit = fit_percent(problem.measured, problem.prediction(final.state.coefficients))
    notes = _warnings(problem, final, uncertainty, std, fit, residuals)
    result = Estimate(
        model=model, params=model.as_dict(final.state.theta), std=model.as_dict(std),
        covariance=parameter_covariance, fit=fit, converged=final.converged,
        iterations=len(history), cost=final.state.cost, stop_reason=final.message,
        history=history, noise_variance=variance,
        condition=condition, intersample=intersample, warnings=notes, delay_profile=profile,
        start='initial' if from_initial else 'search', initial_state=initial_state,
        output_offset=output_offset, integrator_cutoff=cutoff, residuals=residuals)
    return with_consistency(result, problem, final.state, uncertainty.noise, uncertainty.free)


def build_problem(model: Model, data: Data, *, bounds: Optional[Bounds] = None,
                  intersample: str = 'zoh', initial_state: str = 'zero',
                  output_offset: bool = False, integrator_cutoff: Optional[float] = None
                  ) -> Tuple[Problem, Optional[float]]:
    """
    Return the :class:`Problem` :func:`estimate` solves, and the integrator cutoff it used.

    The options mean what they mean for :func:`estimate`; an integrating model is replaced by
    its stable reformulation. The problem's cost is the output-error cost every estimate
    reports, so other optimisers can be compared on it (``bench/real_records.py``).
    """
    lower, upper = bound_vectors(model, bounds)
    fitted_model, fitted_data, cutoff = model, data, None
    if model.integrators:
        cutoff = default_cutoff(len(data) * data.ts) if integrator_cutoff is None \
            else float(integrator_cutoff)
        fitted_model = StabilizedModel(model, cutoff)
        fitted_data = Data(data.u, fitted_model.filtered_output(data.y, data.ts), data.ts,
                           data.t0, data.output_skew)
    problem = Problem(fitted_model, fitted_data, lower, upper, intersample,
                      initial_state == 'estimate', output_offset)
    return problem, cutoff


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


def _elsewhere(problem: Problem, final: IterationResult, history: List[Iteration],
               settings: dict, delay_index: Optional[int], verdict: ResidualAnalysis
               ) -> IterationResult:
    """
    Look elsewhere when the residual is not white.

    A residual that is correlated with the input, or coloured (section 11; a coloured input
    makes the two hard to tell apart), can mean the model misses something: a structure that
    cannot do better, or a local minimum. For a non-affine structure, whose equation-error
    start can miss the output-error basin altogether, the random draws of the automatic start
    are then iterated on the output error directly (twenty updates each); a better end is
    iterated to convergence and kept. Automatic searches only; ``docs/algorithm.md`` section 12.
    """
    if problem.model.is_affine or settings['method'] == 'ls' or \
            verdict.white and not verdict.input_correlated:
        return final
    frozen = np.zeros(final.state.theta.size, dtype=bool)
    best = None
    for theta in random_starts(problem, final.state.theta, delay_index):
        coefficients = problem.admissible(theta)
        if coefficients is None:
            continue
        trial = iterate(problem, problem.state(theta, coefficients), method='iv',
                        frozen=frozen, max_iterations=_ELSEWHERE_ITERATIONS, tolerance=1e-6)
        if trial.state.cost < (final.state.cost if best is None else best.state.cost):
            best = trial
    if best is None:
        return final
    again = iterate(problem, best.state, first_ls=False, **settings)
    history.extend(best.history + again.history)
    return _from_best_seen(problem, _lower(final, again), history, settings)


def _lower(first: IterationResult, second: IterationResult) -> IterationResult:
    """Return the result of lower cost (the first on a tie)."""
    return second if second.state.cost < first.state.cost else first


def _from_best_seen(problem: Problem, final: IterationResult, history: List[Iteration],
                    settings: dict) -> IterationResult:
    """
    Continue from the best point evaluated if the iteration ended above it.

    Every start, profile point and line-search candidate is a point of the same cost
    (:attr:`Problem.best`); the estimate may not be worse than any of them, nor than its start
    (``docs/algorithm.md`` section 8). Least-squares projections (``method='ls'``) follow their
    own fixed point and are left where they end.
    """
    for _ in range(2):
        best = problem.best
        if settings['method'] == 'ls' or best is None or best.cost >= final.state.cost:
            return final
        again = iterate(problem, best, first_ls=False, **settings)
        history.extend(again.history)
        final = again if again.state.cost <= final.state.cost else final
    return final


def _warm_start(problem: Problem, start: State, method: str, delay_index: Optional[int],
                delay_range: DelayRange
                ) -> Tuple[State, List[Iteration], bool, bool]:
    """
    Check a complete guess: where it led, the updates, whether the search is skipped, settled.

    Settled: the search is skipped and the iteration stopped because the update from the end
    point is below ``iteration.NEGLIGIBLE_STEP`` standard deviations
    (:attr:`StopReason.NEGLIGIBLE_UPDATE`, the test the final iteration would start with).

    At most :data:`_WARM_START_ITERATIONS` full steps first; if they do not reach a model that
    explains the data, the controlled iteration goes on from there (line search and fallbacks,
    at most :data:`_WARM_START_BUDGET` updates, given up when the cost stops falling far from a
    minimum). The search is skipped if a convergence test stopped it and its residual is
    independent of the input. The full steps are IV projections from the first: consistent
    under noise, and, like the least-squares projection, exact in one step for a noise-free
    affine structure. A dead-time model whose output does not resemble the measured one
    (:func:`resembles_output`: a dead time far off) is tried with the data's own dead-time
    guess instead (:attr:`Problem.delay_guess`, the search's first guess too); if that does not
    resemble it either, it goes to the search at once (``docs/algorithm.md`` section 11).
    """
    if delay_index is not None and not resembles_output(problem, start):
        moved = _with_data_delay(problem, start, delay_index)
        if moved is None:
            # The full steps, linear in the dead time, cannot move it that far either.
            return start, [], False, False
        start = moved
    warm = local_fit(problem, start, method, first_ls=False, full_steps_only=True,
                     iterations=_WARM_START_ITERATIONS)
    state, history = warm.state, warm.history
    if warm.reason is not StopReason.NO_FULL_STEP and \
            explains_data(problem, state, delay_index, delay_range):
        return state, history, True, warm.reason is StopReason.NEGLIGIBLE_UPDATE
    if not resembles_output(problem, state):
        return state, history, False, False
    local = iterate(problem, state, method=method, frozen=np.zeros(state.theta.size, dtype=bool),
                    max_iterations=_WARM_START_BUDGET, tolerance=1e-6, first_ls=not history,
                    check_optimality=True, min_progress=_WARM_START_PROGRESS)
    history = history + local.history
    explained = local.converged and explains_data(problem, local.state, delay_index, delay_range)
    return local.state, history, explained, \
        explained and local.reason is StopReason.NEGLIGIBLE_UPDATE


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


def _started(problem: Problem, start: State, transient: Union[float, str]) -> State:
    """
    Prepare the problem at ``start`` and return the start, moved into the box if need be.

    Anchors the sign of D's leading coefficient, bounds parameters whose zero would drop the
    order of D (:meth:`Problem.limit_reductions`) and leaves out the transient.
    """
    problem.anchor(start.coefficients)
    theta = problem.limit_reductions(start.theta)
    if np.array_equal(theta, start.theta) and not transient:
        return start
    coefficients = problem.admissible(theta)
    if coefficients is None:
        theta, coefficients = start.theta, start.coefficients
    if transient:
        problem.exclude_transient(transient, coefficients)
    return problem.state(theta, coefficients)


def _residual_analysis(problem: Problem, state: State) -> ResidualAnalysis:
    """
    Analyse the residual at ``state`` against the inputs (``docs/algorithm.md`` section 11).

    The lags cover the dead time and twice the slowest time constant, at least the 25 of
    MATLAB's ``resid``, at most 200 or a quarter of the samples. ``state`` is attached (as
    ``analysis.state``) so the analysis is not repeated for the same state.
    """
    data = problem.data
    horizon = max(state.coefficients.delay, 0.0) + 0.4 * settling_time(state.coefficients)
    lags = int(min(max(DEFAULT_LAGS, np.ceil(horizon / data.ts)), _MAX_RESIDUAL_LAGS))
    residual = problem.measured - problem.prediction(state.coefficients)
    inputs = data.u.reshape(len(data), -1)[problem.skip:]
    analysis = analyse_residual(residual, inputs, problem.model.inputs, lags)
    analysis.measured_every = measured_every(problem.measured)
    analysis.state = state
    return analysis


def _combination(weights: np.ndarray, names: Sequence[str]) -> str:
    """Return ``'+0.71*T1 -0.70*T2'`` for the entries above 0.1."""
    return ' '.join(f'{weight:+.2f}*{name}' for weight, name in zip(weights, names)
                    if abs(weight) > 0.1)


def _fit_note(fit: float) -> Optional[str]:
    """Return what a fit below :data:`LOW_FIT` per cent says about the data, else None."""
    if fit < 0.0:
        return (f'fit {fit:.1f} %: the model does not explain these data (its output is '
                'further from the measurements than their mean is)')
    if fit < LOW_FIT:
        return (f'fit {fit:.1f} %: the model explains almost none of the output; check that '
                'input and output are the right signals (not swapped), the dead time and the '
                'structure, or that the input excites the output above its noise')
    return None


def _warnings(problem: Problem, result: IterationResult, uncertainty: Uncertainty,
              std: np.ndarray, fit: float, residuals: ResidualAnalysis) -> List[str]:
    """
    Return what a user should know about the estimate, in words.

    Active bounds (and lags the data would drop), no convergence, a weakly determined
    combination, a negative fit, standard deviations above the value, a residual correlated
    with the input, an output interpolated from a slower measurement (section 15).
    """
    state = result.state
    names = problem.model.parameters
    notes = []
    at_lower, at_upper = on_bounds(state.theta, problem, tolerance=1e-6)
    for index, name in enumerate(names):
        held = '' if uncertainty.free[index] else \
            ' (the fit would go beyond it, so it has no standard deviation)'
        side = 'lower' if at_lower[index] else 'upper' if at_upper[index] else None
        if side is None:
            continue
        bound = problem.lower[index] if side == 'lower' else problem.upper[index]
        if problem.reductions.get(index) == bound:
            notes.append(f'{name} went to {bound:.3g}, where the pole it adds is 1000 times '
                         f'faster than the Nyquist frequency: the data prefer the model without '
                         f'it ({name} = 0, one order lower){held}')
        else:
            notes.append(f'{name} is at its {side} bound {bound:g}{held}')
    if not result.converged:
        notes.append(f'not converged: {result.message}')
    fit_note = _fit_note(fit)
    if fit_note is not None:
        notes.append(fit_note)
    if uncertainty.condition > ILL_CONDITIONED:
        notes.append(f'the data barely determine {_combination(uncertainty.weakest, names)} '
                     f'(condition number {uncertainty.condition:.1e}): these parameters trade '
                     'off against each other; fix one, reparameterise or use a richer input')
    for index, name in enumerate(names):
        if np.isfinite(std[index]) and std[index] > abs(state.theta[index]):
            notes.append(f'the data do not determine {name}: its standard deviation '
                         f'{std[index]:.3g} exceeds its value {state.theta[index]:.3g}')
    if residuals.input_correlated:
        notes.append(f'residual {residuals.verdict}')
    if residuals.measured_every > 1:
        notes.append(f'the output changes only every {residuals.measured_every} samples (held '
                     'or interpolated from a slower measurement): the sample time is finer '
                     'than the data; the standard deviations count the correlated '
                     'interpolated samples, not them as new measurements')
    return notes
