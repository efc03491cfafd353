"""
One estimation problem: data, model and bounds, and what they give at a parameter vector.

:class:`Problem` evaluates the output-error cost of a parameter vector and linearises the model
there (output, regressors ``phi``, instruments ``psi`` on the fitted samples, with an initial
state and an output offset projected out when they are estimated). A :class:`State` is a
parameter vector with its coefficients and cost. The equations are those of ``docs/algorithm.md``
sections 2-4 and 9; the admissible set and the bounds are sections 6 and 7.
"""

from dataclasses import dataclass
from functools import cached_property
from typing import Dict, Mapping, Optional, Tuple, Union
import weakref

from ctid_ros.core.data import Data
from ctid_ros.core.model import Coefficients, Model
from ctid_ros.core.simulation import ContinuousFilter, DiscreteFilter, polynomial_roots
from ctid_ros.errors import ModelError
from ctid_ros.estimation.correlation import prewhitened_delay
from ctid_ros.estimation.integrating import StabilizedModel
from ctid_ros.estimation.regressors import is_stable, Linearization, SignalBank
import numpy as np
from scipy import linalg

__all__ = [
    'Bounds', 'DelayRange', 'FittedModel', 'Problem', 'State', 'bound_vectors', 'delay_parameter',
    'nuisance_columns', 'orthonormal_basis', 'reduction_limits', 'settling_time',
    'with_fitted_nuisance',
]

Bounds = Mapping[str, Tuple[Optional[float], Optional[float]]]
# Where to search a dead time, in seconds (None: from its bounds, else automatic).
DelayRange = Optional[Tuple[float, float]]
# What the estimation fits: the user's model, or its stable reformulation if it integrates.
FittedModel = Union[Model, StabilizedModel]
# The magnitude of an admissible denominator's leading coefficient lies between these, and no
# coefficient is larger: D^2 (the regressors filter through 1/D^2) and its scaling by the
# roots' time scale then stay normal floats. At 1e150 the square's coefficients reached 1e301
# and overflowed there (a two-mass drive's restart, noise-free data).
_REALISABLE = (1e-100, 1e100)


@dataclass
class State:
    """A parameter vector of the iteration, its coefficients and its output-error cost."""

    theta: np.ndarray
    coefficients: Coefficients
    cost: float


def nuisance_columns(den: np.ndarray, count: int, ts: float, initial_state: bool,
                     output_offset: bool, discrete: Optional[DiscreteFilter] = None
                     ) -> Optional[np.ndarray]:
    """
    Return the output components fitted besides ``G u`` as columns, or None.

    ``initial_state``: the free responses of ``1/D`` (a nonzero initial state);
    ``output_offset``: a constant. Their coefficients enter linearly, so they are projected out
    of every residual, regressor and instrument (variable projection, ``docs/algorithm.md``
    section 9). ``discrete``: a discretisation of ``1/D`` at ``ts`` to reuse (any dead time).
    """
    columns = []
    if initial_state:
        if discrete is None:
            discrete = ContinuousFilter(den).discretize(ts)
        columns.append(discrete.free_responses(count))
    if output_offset:
        columns.append(np.ones((count, 1)))
    return np.hstack(columns) if columns else None


def orthonormal_basis(columns: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """Orthonormal basis of the span of ``columns`` (None stays None)."""
    if columns is None:
        return None
    norms = np.linalg.norm(columns, axis=0)
    return linalg.orth(columns / np.where(norms > 0.0, norms, 1.0))


def with_fitted_nuisance(measured: np.ndarray, output: np.ndarray,
                         basis: Optional[np.ndarray]) -> np.ndarray:
    """Model output plus the part of ``measured - output`` in the span of ``basis``."""
    if basis is None:
        return output
    return output + basis @ (basis.T @ (measured - output))


def _projected_out(columns: Optional[np.ndarray], basis: np.ndarray) -> Optional[np.ndarray]:
    """Return ``columns`` less their part in the span of the orthonormal ``basis``."""
    return None if columns is None else columns - basis @ (basis.T @ columns)


def settling_time(coefficients: Coefficients) -> float:
    """Return five times the slowest time constant of ``D`` plus the dead time (seconds)."""
    roots = polynomial_roots(coefficients.den) if coefficients.den.size > 1 else np.zeros(0)
    # np.max is np.maximum.reduce behind Python wrappers: called directly.
    slowest = float(np.maximum.reduce(-1.0 / roots.real, initial=0.0)) if roots.size else 0.0
    return 5.0 * slowest + max(coefficients.delay, 0.0)


# Nuisance bases kept per problem: a candidate's cost and its linearisation share one, and an
# iteration tries a few candidates before it linearises at the one it accepts.
_REMEMBERED_BASES = 4
# A pole this many times faster than the Nyquist frequency leaves no trace in sampled data.
_NEGLIGIBLE_POLE = 1000.0


def reduction_limits(model: FittedModel, theta: np.ndarray, ts: float) -> Dict[int, float]:
    """
    Parameters whose zero drops the order of ``D``, and the value where that stops mattering.

    For each parameter ``i`` (others at ``theta``) whose value 0 makes ``D``'s leading
    coefficient vanish while the next one stays nonzero, the value (signed like
    ``theta_i``) at which the pole that leaves is ``1000 pi / ts`` rad/s: ``|d_1 / (dd_0 /
    dtheta_i)|`` over that frequency, with ``d_1`` the next coefficient at ``theta_i = 0``.
    """
    limits = {}
    fastest = _NEGLIGIBLE_POLE * np.pi / ts
    for index in range(theta.size):
        if theta[index] == 0.0:
            continue
        reduced = np.array(theta, dtype=float)
        reduced[index] = 0.0
        try:
            coefficients = model.coefficients(reduced)
        except ModelError:
            continue
        den = coefficients.den
        slope = coefficients.den_jacobian[index][0]
        if den.size < 2 or den[0] != 0.0 or den[1] == 0.0 or slope == 0.0 or \
                coefficients.delay_gradient[index] != 0.0:
            continue
        limits[index] = float(np.sign(theta[index]) * abs(den[1] / slope) / fastest)
    return limits


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


def _same_coefficients(first: Coefficients, second: Coefficients) -> bool:
    """Return True if two coefficient sets hold the same values (bit for bit)."""
    if first is second:
        return True             # the iteration asks again with its state's own coefficients
    # The denominator first: a new candidate differs there, and the comparison stops.
    # tobytes reads an array's values in C order whatever its layout (the Jacobians are
    # strided views); the dead time, a float, is compared as its eight bytes.
    return all(one.tobytes() == other.tobytes()
               for one, other in ((first.den, second.den), (first.num, second.num),
                                  (first.den_jacobian, second.den_jacobian),
                                  (first.num_jacobian, second.num_jacobian),
                                  (first.delay_gradient, second.delay_gradient))) and \
        np.float64(first.delay).tobytes() == np.float64(second.delay).tobytes()


# A model's dead-time parameter, found once per model: the stages and checks of every
# estimate ask for it, and each probe evaluates the model's coefficients.
_DELAY_PARAMETERS: 'weakref.WeakKeyDictionary[FittedModel, Optional[int]]' = \
    weakref.WeakKeyDictionary()


def delay_parameter(model: FittedModel) -> Optional[int]:
    """Index of the parameter that is the dead time itself (``exp(-tau*s)``), if any."""
    try:
        return _DELAY_PARAMETERS[model]
    except KeyError:
        index = _DELAY_PARAMETERS[model] = _probed_delay_parameter(model)
        return index


def _probed_delay_parameter(model: FittedModel) -> Optional[int]:
    """:func:`delay_parameter`, from the coefficients' dead-time gradient at all ones."""
    if not model.delay_is_estimated:
        return None
    probe = model.coefficients(np.ones(len(model.parameters)))
    gradient = probe.delay_gradient
    nonzero = np.flatnonzero(gradient)
    if nonzero.size == 1 and gradient[nonzero[0]] == 1.0:
        return int(nonzero[0])
    return None


class Problem:
    """
    Data, model and constraints of one estimation; evaluates costs and linearisations.

    Parameters
    ----------
    model : Model or StabilizedModel
        The model fitted (for an integrating plant, its stable reformulation).
    data : Data
        The data fitted (for an integrating plant, with the high-passed output).
    lower, upper : ndarray
        Bound vectors in parameter order (:func:`bound_vectors`).
    intersample : {'zoh', 'foh'}
        Behaviour of the input between samples.
    initial_state, output_offset : bool
        Whether the response of an unknown initial state and a constant output offset are
        fitted along with the parameters (``docs/algorithm.md`` section 9).

    Attributes
    ----------
    skip : int
        Samples left out of every sum (:meth:`exclude_transient`).
    measured : ndarray
        Output samples that are fitted (after the excluded transient).

    """

    def __init__(self, model: FittedModel, data: Data, lower: np.ndarray, upper: np.ndarray,
                 intersample: str, initial_state: bool = False, output_offset: bool = False):
        self.model = model
        self.data = data
        self.lower = lower
        self.upper = upper
        self.bank = SignalBank(model, data.u, data.y, data.ts, intersample, data.output_skew)
        self.initial_state = initial_state
        self.output_offset = output_offset
        self.evaluations = 0
        self.skip = 0
        # Every cost and linearisation reads it: a view kept, set again with the skip.
        self.measured = data.y
        self.best: Optional[State] = None
        self.reductions: Dict[int, float] = {}
        self._leading_sign = None
        # Nuisance bases of the latest denominators (:meth:`_basis`), oldest first.
        self._bases: Dict[Tuple[bytes, float, int], np.ndarray] = {}
        # The latest linearisation: the coefficients and skip it was for, the bank's own and
        # the fitted samples' one.
        self._latest: Optional[Tuple[Coefficients, int, Linearization, Linearization]] = None

    @cached_property
    def delay_guess(self) -> float:
        """Return the data's own dead-time guess (:func:`prewhitened_delay`), computed once."""
        # The start, the delay bracket, the residual checks and the grid all ask for it.
        return prewhitened_delay(self.data)

    def on_delay_lattice(self, tau: float) -> float:
        """
        Return the dead time nearest ``tau`` at which the delayed input is a whole-sample shift.

        That is where the simulated input delay (``tau`` plus the output skew's extra delay) is
        a multiple of the sample time: ``tau = output_skew + k ts``.
        """
        ts, offset = self.data.ts, self.data.output_skew
        return offset + ts * round((tau - offset) / ts)

    def _basis(self, coefficients: Coefficients) -> Optional[np.ndarray]:
        if not (self.initial_state or self.output_offset):
            return None             # nothing fitted besides G u (every cost asks)
        # A candidate's cost and then its linearisation ask for the same basis: the latest
        # few are kept (they depend on D, the dead time's discretisation and the skip only).
        key = (coefficients.den.tobytes(), float(coefficients.delay), self.skip)
        bases = self._bases
        if key in bases:
            bases[key] = bases.pop(key)                 # the most recent last
            return bases[key]
        # The simulation's own discretisation of 1/D serves the free responses too.
        discrete = self.bank.realized(coefficients.den, coefficients.delay) \
            if self.initial_state else None
        columns = nuisance_columns(coefficients.den, len(self.data), self.data.ts,
                                   self.initial_state, self.output_offset, discrete)
        basis = orthonormal_basis(columns[self.skip:])
        bases[key] = basis
        if len(bases) > _REMEMBERED_BASES:
            del bases[next(iter(bases))]
        return basis

    def prediction(self, coefficients: Coefficients) -> np.ndarray:
        """Model output on the fitted samples, with the fitted initial state and offset."""
        return with_fitted_nuisance(self.measured, self.bank.output(coefficients)[self.skip:],
                                    self._basis(coefficients))

    def linearize(self, coefficients: Coefficients, regressors: bool = True) -> Linearization:
        """
        Output, regressors and instruments on the fitted samples (nuisance projected out).

        The latest result is kept: the final estimate is linearised once for the stopping
        rule, the identifiability check and the covariance. Asked for the regressors where it
        has none, only those are added.

        """
        latest = self._latest
        instruments = None
        if latest is not None and latest[1] == self.skip and \
                _same_coefficients(latest[0], coefficients):
            if latest[3].phi is not None or not regressors:
                return latest[3]
            instruments = latest[2]
        bank_lin, lin = self._linearized(coefficients, regressors, instruments)
        self._latest = (coefficients, self.skip, bank_lin, lin)
        return lin

    def _linearized(self, coefficients: Coefficients, regressors: bool,
                    instruments: Optional[Linearization] = None
                    ) -> Tuple[Linearization, Linearization]:
        """Return the bank's linearisation and the fitted samples' one (nuisance projected)."""
        bank_lin = self.bank.linearize(coefficients, regressors, instruments)
        return bank_lin, self._fitted(coefficients, bank_lin)

    def _fitted(self, coefficients: Coefficients, lin: Linearization) -> Linearization:
        """Return the bank's ``lin`` on the fitted samples, nuisance projected out."""
        skip = self.skip
        output, phi, psi = (lin.output[skip:], None if lin.phi is None else lin.phi[skip:],
                            lin.psi[skip:])
        jump = None if lin.delay_jump is None else lin.delay_jump[skip:]
        basis = self._basis(coefficients)
        if basis is None:
            return Linearization(output, phi, psi, jump, lin.delay_gradient)
        if self.initial_state:
            # The fitted initial-state response moves with D: its derivative at fixed
            # coefficients belongs to every sensitivity (variable projection, section 9).
            motion = self._nuisance_motion(coefficients, self.measured - output)
            psi = psi + motion
            if phi is not None:
                phi = phi + motion
        output = with_fitted_nuisance(self.measured, output, basis)
        return Linearization(output, _projected_out(phi, basis), _projected_out(psi, basis),
                             _projected_out(jump, basis), lin.delay_gradient)

    def _nuisance_motion(self, coefficients: Coefficients, error: np.ndarray) -> np.ndarray:
        """
        Return the derivative of the fitted initial-state response by every parameter.

        The response of an initial state is the impulse response of ``P(s)/D(s)`` with
        ``deg P < deg D``. With ``P`` fitted to ``error`` (together with the offset, if
        estimated) and held fixed, its derivative with respect to ``theta_i`` is the impulse
        response of ``-P D_i / D^2`` (Kaufman's variable-projection Jacobian; the gradient of
        the projected cost is exact with it). Columns in parameter order, fitted samples only.
        """
        den = coefficients.den
        order = den.size - 1
        params = coefficients.den_jacobian.shape[0]
        if order == 0:
            return np.zeros((error.size, params))
        count = len(self.data)
        squared = self.bank.realized(np.convolve(den, den), coefficients.delay)
        single = self.bank.realized(den, coefficients.delay)
        powers = [np.eye(order)[j] for j in range(order)]         # s^(n-1) .. s^0
        columns = [single.impulse_responses(powers, count).T[self.skip:]]
        if self.output_offset:
            columns.append(np.ones((error.size, 1)))
        columns = np.hstack(columns)
        norms = np.linalg.norm(columns, axis=0)
        norms[norms == 0.0] = 1.0
        fitted = np.linalg.lstsq(columns / norms, error, rcond=None)[0] / norms
        polynomial = fitted[:order]
        numerators = [-np.convolve(polynomial, row) for row in coefficients.den_jacobian]
        return squared.impulse_responses(numerators, count).T[self.skip:]

    def exclude_transient(self, seconds: Union[float, str], coefficients: Coefficients
                          ) -> None:
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
        skip = int(min(np.ceil(seconds / self.data.ts), len(self.data) // 2))
        if skip != self.skip:
            # Costs on other samples are not comparable.
            self.best = None
        self.skip = skip
        self.measured = self.data.y[skip:]

    def admissible(self, theta: np.ndarray) -> Optional[Coefficients]:
        """Coefficients at theta if theta is inside the bounds and ``D`` is stable, else None."""
        if any(((theta < self.lower) | (theta > self.upper)).tolist()):
            return None
        try:
            coefficients = self.model.coefficients(theta)
        except ModelError:
            return None
        if coefficients.delay < 0.0 or not is_stable(coefficients.den):
            return None
        # A search drifting along a direction the output hardly sees (a zero cancelling a
        # pole, every coefficient shrinking together) can reach coefficients whose squares
        # underflow: the filters of 1/D could not be built there. Comparisons only: every
        # candidate is checked.
        den = coefficients.den
        leading = den[0]
        small, large = _REALISABLE
        if not (small < leading < large or -large < leading < -small) or \
                not float(np.abs(den).max()) < large:
            return None
        sign = np.sign(coefficients.den[0])
        if self._leading_sign is not None and sign != self._leading_sign:
            return None
        return coefficients

    def limit_reductions(self, theta: np.ndarray) -> np.ndarray:
        """
        Bound every parameter whose zero drops the order of ``D`` where it stops mattering.

        A parameter whose value 0 makes ``D``'s leading coefficient vanish (a lag ``T`` in
        ``T s + 1``, a mass) can approach 0 but never reach it: the model loses an order there.
        It gets a bound on the side of its value in ``theta`` at ``reduction_limit``, where the
        pole it leaves is 1000 times faster than the Nyquist frequency (:attr:`reductions`
        records them; a tighter user bound is kept). Returns ``theta`` moved into the new box.
        Section 7 of ``docs/algorithm.md``.
        """
        for index, value in reduction_limits(self.model, theta, self.data.ts).items():
            if value > 0.0 and self.lower[index] < value < self.upper[index]:
                self.lower[index] = value
            elif value < 0.0 and self.lower[index] < value < self.upper[index]:
                self.upper[index] = value
            else:
                continue
            self.reductions[index] = value
        return np.clip(theta, self.lower, self.upper)

    def anchor(self, coefficients: Coefficients) -> None:
        """Fix the sign of D's leading coefficient: crossing zero would change the order."""
        self._leading_sign = np.sign(coefficients.den[0])
        if self.best is not None and np.sign(self.best.coefficients.den[0]) != \
                self._leading_sign:
            self.best = None

    def cost(self, coefficients: Coefficients) -> float:
        """Return the output-error cost ``0.5 |y - yhat|^2`` on the fitted samples."""
        self.evaluations += 1
        error = self.measured - self.prediction(coefficients)
        return 0.5 * float(error @ error)

    def state(self, theta: np.ndarray, coefficients: Coefficients) -> State:
        """
        Return the state at admissible ``theta``, remembering it if it is the best so far.

        :attr:`best` is the lowest-cost state evaluated since the fitted samples last changed
        (every candidate of every start, search and iteration goes through here), so the
        estimator can return nothing worse than a point it has seen.
        """
        state = State(np.array(theta, dtype=float), coefficients, self.cost(coefficients))
        if self.best is None or state.cost < self.best.cost:
            self.best = state
        return state

    def delay_bracket(self, delay_index: int, delay_range: DelayRange) -> Tuple[float, float]:
        """
        Return the interval the dead time is searched in (``docs/algorithm.md`` section 12).

        ``delay_range`` within the bounds if given; else the bounds, with an infinite upper
        bound replaced by ``max(3 guess, guess + 20 ts, 5 % of the record)`` (at most half the
        record), where ``guess`` is :attr:`delay_guess`.

        """
        data = self.data
        if delay_range is not None:
            low, high = float(delay_range[0]), float(delay_range[1])
            if not (0.0 <= low < high):
                raise ModelError(f'delay range must satisfy 0 <= min < max, got {delay_range}')
            return max(low, self.lower[delay_index]), min(high, self.upper[delay_index])
        low = self.lower[delay_index]
        high = self.upper[delay_index]
        if not np.isfinite(high):
            guess = self.delay_guess
            # The guess can fail (a slowly held or coloured input); a twentieth of the record
            # is searched whatever it says.
            high = min(max(3.0 * guess, guess + 20.0 * data.ts, 0.05 * data.ts * len(data)),
                       0.5 * data.ts * len(data))
        return low, max(high, low + data.ts)
