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
import math
from typing import Dict, List, Optional, Sequence, Tuple, Union
import warnings

from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import DataError, EstimationError
from ctid_ros.estimation.consistency import Consistency, CovarianceParts, with_consistency
from ctid_ros.estimation.identifiability import (blind_combination, BlindCombination,
                                                 Sensitivities, structurally_blind)
from ctid_ros.estimation.integrating import default_cutoff, StabilizedModel
from ctid_ros.estimation.iteration import (Iteration, IterationPolicy, IterationResult,
                                           on_bounds, Opening)
from ctid_ros.estimation.linear_algebra import thin_svd
from ctid_ros.estimation.noise import (coloured_covariance, measured_every, noise_model,
                                       NoiseModel)
from ctid_ros.estimation.options import check_options
from ctid_ros.estimation.problem import (bound_vectors, Bounds, delay_parameter, DelayRange,
                                         nuisance_columns, orthonormal_basis, Problem,
                                         settling_time, State, with_fitted_nuisance)
from ctid_ros.estimation.projected_noise import (filtered_twice, low_frequency_level,
                                                 restored_covariance)
from ctid_ros.estimation.residual_analysis import (amplitude_note, analyse_residual, DEFAULT_LAGS,
                                                   ResidualAnalysis)
from ctid_ros.estimation.stages import (against_the_data_basin, against_the_data_guess,
                                        automatic_start, final_iteration, look_elsewhere,
                                        onto_the_sample, other_side_of_the_sample,
                                        symmetry_restarts, warm_start)
from ctid_ros.estimation.starts import Initial
import numpy as np
from threadpoolctl import ThreadpoolController

__all__ = [
    'Estimate', 'ILL_CONDITIONED', 'LOW_FIT', 'SIGNAL_SCALES', 'Uncertainty', 'build_problem',
    'covariance', 'estimate', 'fit_percent',
]

# Above this condition number of the scaled sensitivities a combination is reported as weak.
ILL_CONDITIONED = 1e3
# Below this fit (%) the estimate carries a warning that the model explains almost nothing.
LOW_FIT = 10.0
# The variation of every signal must exceed the first, its values stay below the second.
SIGNAL_SCALES = (1e-60, 1e60)
_MAX_RESIDUAL_LAGS = 200


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
        MATLAB's ``resid``, and whether the residual depends on the amplitude of an input or
        of the model output (``amplitude_dependent``: a static nonlinearity); also the order
        of the residual's noise model behind the covariance and how many samples apart the
        output was measured.
    consistency : Consistency or None
        Whether one parameter vector holds over the whole record (the halves' and quarters'
        estimates against the whole, :mod:`~ctid_ros.estimation.consistency`). If not, ``std``
        covers the scatter of the quarter estimates and ``covariance`` is scaled to match.
    std_noise : dict
        The standard deviations the noise alone implies (equal to ``std`` when consistent).
    std_change : dict
        The standard deviations a change test compares windows by
        (:mod:`~ctid_ros.streaming.alarm`): the noise-only ones before the small-sample t
        factors (a quantile correction of the intervals, not a variance) and before the
        restored projected noise (a correction that grows where the residual is coloured by
        a model that does not hold across the record), both of section 15; the test's robust
        scale calibrates them on the windows themselves (``docs/algorithm.md`` section 17).
        Not reported; empty where not computed.

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
    std_change: Dict[str, float] = field(default_factory=dict)

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
    # np.linalg.norm's arithmetic for a vector, without its dispatch.
    centred, error = y - y.mean(), y - yhat
    spread = math.sqrt(centred.dot(centred))
    if spread == 0.0:
        return float('nan')
    return float(100.0 * (1.0 - math.sqrt(error.dot(error)) / spread))


@lru_cache(maxsize=1)
def _thread_pools() -> ThreadpoolController:
    # Finding the loaded BLAS libraries is slow: once per process, not per estimate.
    return ThreadpoolController()


def _check_excitation(model: Model, data: Data) -> None:
    if data.input_count != len(model.inputs):
        raise DataError(f'the model has {len(model.inputs)} input(s) '
                        f'({", ".join(model.inputs)}), the data have {data.input_count}')
    # np.ptp's reductions, without its dispatch.
    inputs = data.u.reshape(len(data), -1)
    highs, lows = np.maximum.reduce(inputs, axis=0), np.minimum.reduce(inputs, axis=0)
    for name, span in zip(model.inputs, (highs - lows).tolist()):
        if span == 0.0:
            raise EstimationError(f'the input {name} is constant: it does not excite the '
                                  'system, so no dynamic parameter can be identified')
    high, low = np.maximum.reduce(data.y, axis=None), np.minimum.reduce(data.y, axis=None)
    if high - low == 0.0:
        raise EstimationError('the output is constant: the data carry no information about '
                              'the dynamics (is the output topic/column the right one?)')
    if len(data) < 10:
        raise EstimationError(f'only {len(data)} samples: too few to identify a model')
    # The estimator forms sums of squares and products of the signals: beyond these scales
    # they leave the floating-point range (a residual's correlations came out zero at 1e90).
    # Checked on the extremes' Python floats, in one comparison chain per signal.
    small, large = SIGNAL_SCALES
    for name, top, bottom in zip((*model.inputs, model.output), (*highs.tolist(), float(high)),
                                 (*lows.tolist(), float(low))):
        if not (-large <= bottom and top <= large and top - bottom >= small):
            peak = top if top >= -bottom else -bottom
            raise DataError(f'{name} spans {top - bottom:.3g} with values up to {peak:.3g}: '
                            'the estimator squares the signals, so it needs variations above '
                            f'{small:.0e} and values below {large:.0e}; express {name} in '
                            'other units (scale it) before identification')


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
    removed_share : float
        Share of the noise's low-frequency level the fit's projection took out of the residual
        (0 where the noise model was not restored: :mod:`~ctid_ros.estimation.projected_noise`).
    restored_factors : ndarray or None
        Per parameter, the standard deviation with the restored noise model over that with the
        residual's own (1 for held parameters); None where the noise model was not restored.
    parts : CovarianceParts
        The sensitivities, residual, decomposition and noise models behind the covariance,
        which the checks after it use again.

    """

    covariance: np.ndarray
    variance: float
    condition: float
    weakest: np.ndarray
    noise: NoiseModel
    free: np.ndarray
    removed_share: float = 0.0
    restored_factors: Optional[np.ndarray] = None
    parts: Optional[CovarianceParts] = None


def covariance(problem: Problem, state: State,
               autocorrelation: Optional[np.ndarray] = None,
               sensitivities: Optional[Sensitivities] = None) -> Uncertainty:
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
    sensitivities = sensitivities or Sensitivities(problem)
    free, psi, norms, svd = sensitivities.at(state)
    scales = np.where(norms > 0.0, norms, 1.0)
    # The column-scaled sensitivities the identifiability check decomposed, for the sandwich
    # and the checks after it.
    columns = sensitivities.scaled(state)
    if svd is None:
        # A zero column, which the identifiability check's decomposition leaves out (scaled
        # by 1 here). At a kink of the cost in the dead time ``psi`` is already the mean of
        # the two one-sided sensitivities (:class:`Sensitivities`).
        columns = psi / scales
        svd = thin_svd(columns)
    model = noise_model(error, autocorrelation=autocorrelation)
    rows = free.nonzero()[0]
    # The sensitivities' basis filtered once, for the sandwich and the checks after it, and
    # again for the small-sample factors: from one recursion (filtered_twice).
    root = again = None
    if model.order and rows.size:
        root, again = filtered_twice(svd[0], model)
    scaled, model = coloured_covariance(columns, error, rows.size, svd, model=model, root=root)
    # The residual lacks the noise the fit projected off: restore it before the sandwich.
    restored = restored_covariance(columns, error, svd, start=model)
    residual_noise = model
    removed_share = 0.0
    restored_factors = None
    if restored is not None:
        removed_share = max(1.0 - low_frequency_level(model) / low_frequency_level(restored[1]),
                            0.0)
        ratio = np.sqrt(restored[0].diagonal() / scaled.diagonal())
        restored_factors = np.ones(params)
        restored_factors[free] = np.where(np.isfinite(ratio) & (ratio > 0.0), ratio, 1.0)
        scaled, model, root = restored
        again = None
    result = np.full((params, params), np.nan)
    # np.ix_'s indexing and np.outer's product.
    result[rows[:, None], rows] = scaled / (scales[:, None] * scales)
    weakest = np.zeros(params)
    condition = 1.0
    if rows.size:
        singular, vt = svd[1:]
        condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else np.inf
        weakest[free] = vt[-1] * np.sign(vt[-1][np.abs(vt[-1]).argmax()])
    parts = CovarianceParts(columns, scales, error, svd if rows.size else None, residual_noise,
                            root, again)
    return Uncertainty(result, variance, condition, weakest, model, free, removed_share,
                       restored_factors, parts)


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
        slowest time constant of the starting model plus its dead time. At most half of the
        record is left out (a longer given one is cut, with a warning). Default 0: the data
        start at rest.
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
        # The final iteration's settings; every stage after it iterates with them too.
        policy = IterationPolicy(method=method, max_iterations=max_iterations,
                                 tolerance=tolerance, opening=Opening.PROJECTION,
                                 check_optimality=True)
        # A complete guess (a warm start) first: if its model leaves nothing correlated with
        # the input, there is nothing for the automatic start and search to find.
        start = warm_start(problem, initial, transient, method, delay_index, delay_range)
        if start is not None and method != 'ls':
            start = against_the_data_guess(problem, start, delay_index, delay_range)
        if start is None:
            start = automatic_start(problem, initial, transient, delay_index, delay_range)
        fit = final_iteration(problem, start, policy)
        fit, from_initial = against_the_data_basin(problem, fit, start, policy, delay_index,
                                                   delay_range)
        sensitivities = Sensitivities(problem)
        rng = np.random.default_rng(0)
        fit, blind = symmetry_restarts(problem, fit, policy, sensitivities, rng)
        analysis = _residual_analysis(problem, fit.state)
        if not from_initial and blind is None:
            fit = look_elsewhere(problem, fit, policy, delay_index, analysis)
            fit = other_side_of_the_sample(problem, fit, policy, delay_index, delay_range)
            blind = blind_combination(problem, fit.state, sensitivities)
        fit = onto_the_sample(problem, fit, policy, delay_index)
        _refuse_blind(problem, fit.state, blind, rng)
        final, history, profile = fit.result, list(fit.history), list(start.profile)
        residuals = analysis if analysis.state is final.state else \
            _residual_analysis(problem, final.state)
        _test_amplitude(problem, residuals)
        uncertainty = covariance(problem, final.state, residuals.long_autocorrelation,
                                 sensitivities)
    residuals.noise_order = uncertainty.noise.order
    residuals.noise_power_ratio = uncertainty.noise.variance_ratio
    parameter_covariance = uncertainty.covariance
    variance, condition = uncertainty.variance, uncertainty.condition
    std = np.sqrt(np.abs(parameter_covariance.diagonal()))
    fit = fit_percent(problem.measured, problem.prediction(final.state.coefficients))
    notes = _warnings(problem, final, uncertainty, std, fit, residuals)
    if delay_index is not None and delay_range is not None:
        notes.extend(_outside_the_search(problem, final.state, delay_index, delay_range))
    notes.extend(_transient_cut(problem, transient))
    result = Estimate(
        model=model, params=model.as_dict(final.state.theta), std=model.as_dict(std),
        covariance=parameter_covariance, fit=fit, converged=final.converged,
        iterations=len(history), cost=final.state.cost, stop_reason=final.message,
        history=history, noise_variance=variance,
        condition=condition, intersample=intersample, warnings=notes, delay_profile=profile,
        start='initial' if from_initial else 'search', initial_state=initial_state,
        output_offset=output_offset, integrator_cutoff=cutoff, residuals=residuals)
    return with_consistency(result, problem, final.state, uncertainty.noise, uncertainty.free,
                            parts=uncertainty.parts, removed_share=uncertainty.removed_share,
                            restored_factors=uncertainty.restored_factors)


def _refuse_blind(problem: Problem, state: State, blind: Optional[BlindCombination],
                  rng: np.random.Generator) -> None:
    """
    Raise :class:`EstimationError` where no data could determine the parameters at ``state``.

    The output does not depend on a parameter at all, or the model itself ignores a
    combination (:func:`~ctid_ros.estimation.identifiability.structurally_blind`); a
    combination only these data barely see is a warning of the estimate instead
    (``docs/algorithm.md`` section 14). A model that explains nothing determines nothing
    either: that is the news, so the fit's own words lead.
    """
    if blind is None or not (blind.status.always_fatal or
                             structurally_blind(problem.model, state.theta, rng)):
        return
    note = _fit_note(fit_percent(problem.measured, problem.prediction(state.coefficients)))
    raise EstimationError(blind.message if note is None else f'{note}; {blind.message}')


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
    prediction = problem.prediction(state.coefficients)
    residual = problem.measured - prediction
    inputs = data.u.reshape(len(data), -1)[problem.skip:]
    analysis = analyse_residual(residual, inputs, problem.model.inputs, lags)
    analysis.measured_every = measured_every(problem.measured)
    analysis.state = state
    analysis.prediction = prediction
    return analysis


def _test_amplitude(problem: Problem, analysis: ResidualAnalysis) -> None:
    """
    Test the final residual against the amplitude of the inputs and of the model output.

    Once per estimate, on the analysis the user sees (the stages before only ask whether the
    residual is white and independent of the input): ``docs/algorithm.md`` section 11.
    """
    inputs = problem.data.u.reshape(len(problem.data), -1)[problem.skip:]
    analysis.test_amplitude(problem.measured - analysis.prediction, inputs, analysis.prediction)
    # The estimate keeps no copy of the record's length it does not need.
    analysis.prediction = None


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
                'structure, or that the input excites the output above its noise; if they are '
                'right, the estimate may sit in a local minimum: start it near the values '
                'expected')
    return None


def _transient_cut(problem: Problem, transient: Union[float, str]) -> List[str]:
    """
    Say so where a given transient was cut to half the record.

    At most half the record is left out of the fit (:meth:`Problem.exclude_transient`). A
    window of the live node may ask for more while its buffer fills, but a user who gave more
    than half a record (seconds typed as milliseconds) should know which samples were fitted.
    """
    if transient == 'auto' or not transient:
        return []
    ts = problem.data.ts
    if problem.skip >= math.ceil(float(transient) / ts - 1e-9):
        return []
    return [f'transient {float(transient):g} s is more than half the record: only its first '
            f'{problem.skip * ts:g} s ({problem.skip} samples) were left out of the fit, the '
            'second half fitted']


def _outside_the_search(problem: Problem, state: State, delay_index: int,
                        delay_range: DelayRange) -> List[str]:
    """
    Say so where the dead time ended more than half a sample outside the range searched.

    ``delay_range`` (``--delay-range``, the node's ``delay_min``/``delay_max``) is where the
    dead time is searched, not a bound: the final iteration may leave it for a lower cost. A
    user who gave it believed the dead time inside; the estimate says where it went instead.
    """
    low, high = problem.delay_bracket(delay_index, delay_range)
    tau = float(state.theta[delay_index])
    margin = 0.5 * problem.data.ts
    if low - margin <= tau <= high + margin:
        return []
    name = problem.model.parameters[delay_index]
    return [f'{name} went to {tau:.4g} s, outside the dead-time search range {low:g} to '
            f'{high:g} s: the fit is lower there; bound {name} to keep it inside']


def _warnings(problem: Problem, result: IterationResult, uncertainty: Uncertainty,
              std: np.ndarray, fit: float, residuals: ResidualAnalysis) -> List[str]:
    """
    Return what a user should know about the estimate, in words.

    Active bounds (and lags the data would drop), no convergence, a weakly determined
    combination, a negative fit, standard deviations above the value, a residual correlated
    with the input or dependent on its amplitude (section 11), an output interpolated from a
    slower measurement (section 15).
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
            # Only a model that explains the data says what the data prefer: at a low fit the
            # limit may be the edge of a wrong basin, or the output hardly depends on the input.
            verdict = 'the data prefer the model without it' if fit >= LOW_FIT else \
                ('at a fit this low that does not show the data need no such lag (a wrong '
                 'basin, or an output the input hardly moves)')
            notes.append(f'{name} went to {bound:.3g}, where the pole it adds is 1000 times '
                         f'faster than the Nyquist frequency: {verdict} ({name} = 0, one order '
                         f'lower){held}')
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
    elif residuals.amplitude_dependent:
        notes.append(amplitude_note(residuals.amplitude_terms))
    if residuals.measured_every > 1:
        notes.append(f'the output changes only every {residuals.measured_every} samples (held '
                     'or interpolated from a slower measurement): the sample time is finer '
                     'than the data; the standard deviations count the correlated '
                     'interpolated samples, not them as new measurements')
    return notes
