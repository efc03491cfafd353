"""
Filtered signals of one iteration of the projection method.

At the current estimate ``theta`` with ``G = N/D * exp(-tau s)`` this module computes, from the
sampled input ``u`` and output ``y``, with three state simulations sharing one denominator
(per input channel: a model with several inputs sums the terms of its numerators ``N_j``):

* the model output ``yhat = G u`` (u through ``1/D``, with the dead time);
* the regressors ``phi_i = [dN/dtheta_i e^{-tau s} u - dD/dtheta_i y] / D`` (y through ``1/D``,
  first-order hold), minus ``dtau/dtheta_i * s G u`` for a dead time;
* the instruments ``psi_i = d yhat / d theta_i = (dN_i D - dD_i N)/D^2 e^{-tau s} u - ...``
  (u through ``1/D^2``), which carry no measurement noise. Where ``D`` has uncoupled modes they
  are read off the simulation of ``u`` through ``1/D`` (the double poles' chains of
  :meth:`~ctid_ros.core.simulation.StateResponse.squared_outputs`), so only two state
  simulations are discretised per parameter vector.

``phi`` makes the error decomposition exact (one-step property; on sampled data up to the
first-order hold of ``y``); ``psi`` are the output sensitivities that make the
instrumental-variable iteration consistent (``docs/algorithm.md`` sections 3 and 4).
"""

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Dict, Hashable, List, Optional, TypeVar

from ctid_ros.core.model import Coefficients, Model
from ctid_ros.core.simulation import (all_finite, ContinuousFilter, DiscreteFilter,
                                      polynomial_roots, skew_delay, skew_extended, StateResponse)
from ctid_ros.errors import EstimationError
import numpy as np

__all__ = ['Linearization', 'SignalBank', 'is_stable']

# An iteration evaluates the cost at a candidate, then linearises there if it is accepted, and
# the final estimate is simulated again for its fit: a few recent results serve all of these.
_REMEMBERED = 4
# Outputs are kept up to this many bytes in all, up to _REMEMBERED_OUTPUTS of them (at least
# _REMEMBERED): the data's guess and the restarts evaluate several points between the final
# estimate's linearisation and its residual analysis, which would push a shorter list's out.
_OUTPUT_BYTES = 1 << 23
_REMEMBERED_OUTPUTS = 16
# State trajectories hold (order x samples) values each (on a record of 1e6 samples tens of MB):
# of u through 1/D the latest candidate's (a linearisation follows its candidate's cost), on a
# record of up to _SECOND_RESPONSE_BYTES per signal the one before too; of the others the latest
# linearisation's only (a point that needs its regressors after its instruments takes the
# instruments over: SignalBank.linearize's ``instruments``). The one before is rarely asked for
# again (a few simulations in a hundred); on a longer record its memory, several rows of the
# record's length that the heap gives back after every estimate, costs more than simulating it.
_REMEMBERED_RESPONSES = 2
_SECOND_RESPONSE_BYTES = 1 << 15
Value = TypeVar('Value')
# Realisations shared by every bank (a few tens of small objects).
_SHARED_FILTERS = 32
_TINY = np.finfo(float).tiny
# State trajectories of every input channel through one filter. Named once: a nested function's
# annotation is evaluated at every definition, and typing's subscription is a call.
_Responses = List[StateResponse]


@dataclass
class Linearization:
    """
    Model output and its regressors/instruments at one parameter vector.

    ``psi`` holds the sensitivities for an increasing dead time. Where the dead time is a whole
    number of samples and the held input jumps at the sample instants, the output's derivative
    with respect to the dead time has a different value for a decreasing one:
    ``psi + delay_jump`` (and ``phi + delay_jump``); ``delay_jump`` is None where both sides
    agree. ``delay_gradient`` is ``d tau / d theta`` (``docs/algorithm.md`` section 12).
    """

    output: np.ndarray
    phi: Optional[np.ndarray]
    psi: np.ndarray
    delay_jump: Optional[np.ndarray] = None
    delay_gradient: Optional[np.ndarray] = None


def is_stable(den: np.ndarray, margin: float = 1e-9) -> bool:
    """Return True if every root of ``den`` lies left of ``-margin * max|root|``."""
    if den.size < 2:
        return den.size == 1 and den[0] != 0.0
    # Every candidate parameter vector is checked: by its sum, not elementwise (all_finite).
    if den[0] == 0.0 or not all_finite(den):
        return False
    roots = polynomial_roots(den)
    # Every candidate is checked: the extremes of its few roots by Python's max of their floats
    # (no ufunc set-up for a few values; the roots of finite coefficients hold no NaN).
    scale = max(max(abs(roots).tolist()), _TINY)
    return max(roots.real.tolist()) < -margin * scale


def _remembered(cache: Dict[Hashable, Value], key: Hashable,
                compute: Callable[[], Value], size: int = _REMEMBERED) -> Value:
    """Return ``cache[key]``, computing it if absent; only the latest ``size`` keys are kept."""
    if key in cache:
        value = cache.pop(key)
    else:
        # The oldest goes before the new one is computed: its arrays (a record's length each)
        # are free for the new one's, which then need no more memory than they replace.
        while len(cache) >= size:
            del cache[next(iter(cache))]
        value = compute()
    cache[key] = value
    return value


@lru_cache(maxsize=_SHARED_FILTERS)
def _realization(den: bytes) -> ContinuousFilter:
    """
    Return the realisation of ``1/den`` (coefficients as bytes), shared by every bank.

    The input's and the output's discretisations of one denominator (held and interpolated)
    share its modes; the banks of a record's halves and quarters (the consistency check), of
    the dead-time search and of the structure comparisons evaluate the same parameter vectors,
    and find their discretisations kept by :meth:`ContinuousFilter.discretize`.
    """
    return ContinuousFilter(np.frombuffer(den))


def _pad(poly: np.ndarray, length: int) -> np.ndarray:
    """Return coefficients (highest power first; rows of a 2-D array) with leading zeros."""
    if poly.shape[-1] == length:
        return poly                 # read only here: no copy
    padded = np.zeros(poly.shape[:-1] + (length,))
    padded[..., length - poly.shape[-1]:] = poly
    return padded


class SignalBank:
    """
    Computes outputs and sensitivities of a model on one data record.

    With an ``output_skew`` (outputs measured that long after the input instants) every
    input-driven signal is simulated with ``ts - output_skew`` more dead time on the input
    extended by one sample, and its first sample dropped: exactly the model at the output
    instants (``docs/algorithm.md`` section 2).
    """

    def __init__(self, model: Model, u: np.ndarray, y: np.ndarray, ts: float,
                 intersample: str = 'zoh', output_skew: float = 0.0):
        self.model = model
        self.channels = model.input_channels(u)
        self.y = y
        self.ts = ts
        self.intersample = intersample
        self.output_skew = output_skew
        # What the input-driven simulations run on, and the delay they add (none unskewed).
        self.driving = skew_extended(self.channels, output_skew)
        self.extra_delay = skew_delay(ts, output_skew)
        self.trim = 1 if output_skew else 0
        self._outputs: Dict[Hashable, np.ndarray] = {}
        self._outputs_kept = max(_REMEMBERED, min(_REMEMBERED_OUTPUTS,
                                                  _OUTPUT_BYTES // max(y.nbytes, 1)))
        self._responses_kept = _REMEMBERED_RESPONSES if y.nbytes <= _SECOND_RESPONSE_BYTES \
            else 1
        # State trajectories of the input channels (output and its sensitivities at the same
        # parameters come from one simulation of each filter) and of the output.
        self._responses: Dict[Hashable, _Responses] = {}
        self._sensitivities: Dict[Hashable, _Responses] = {}
        self._output_filtered: Dict[Hashable, StateResponse] = {}

    def _discrete(self, den: np.ndarray, delay: float, intersample: str) -> DiscreteFilter:
        return _realization(den.tobytes()).discretize(self.ts, float(delay), intersample)

    def _channel_responses(self, cache: Dict[Hashable, _Responses], den: np.ndarray,
                           delay: float, size: int) -> _Responses:
        """State trajectories of every input channel through ``1/den`` with ``delay`` (cached)."""
        def simulate() -> _Responses:
            discrete = self._discrete(den, delay, self.intersample)
            return [discrete.response(self.driving[:, j]) for j in range(self.driving.shape[1])]

        return _remembered(cache, (den.tobytes(), float(delay)), simulate, size)

    def realized(self, den: np.ndarray, delay: float) -> DiscreteFilter:
        """
        Discretisation of ``1/den`` for the input with dead time ``delay`` (cached).

        Its transition and realisation do not depend on the dead time: :meth:`linearize`'s
        own filters serve impulse responses too.
        """
        return self._discrete(den, delay + self.extra_delay, self.intersample)

    def pulse_response(self, coefficients: Coefficients, length: int) -> np.ndarray:
        """
        Return the first channel's ``N/D`` response to a unit pulse over ``length`` samples.

        The pulse held over its sample (zero-order hold) with the model's own dead time and
        no output skew: the values ``Model.simulate`` gives for it, from the discretisation
        of ``D`` already made for the state (the process-wide cache ``_realization`` reads)
        rather than a new one.
        """
        pulse = np.zeros(length)
        pulse[0] = 1.0
        discrete = self._discrete(coefficients.den, coefficients.delay, 'zoh')
        return discrete.outputs(pulse, coefficients.num[:1])[0]

    @staticmethod
    def _output_key(coefficients: Coefficients) -> Hashable:
        return coefficients.den.tobytes(), coefficients.num.tobytes(), float(coefficients.delay)

    def output(self, coefficients: Coefficients) -> np.ndarray:
        """Model output ``sum_j N_j/D u_j`` at given coefficients (no sensitivities), read-only."""
        def simulate() -> np.ndarray:
            responses = self._channel_responses(self._responses, coefficients.den,
                                                coefficients.delay + self.extra_delay,
                                                self._responses_kept)
            trim = self.trim
            # One input (the usual case) needs no sum: its output array is new already.
            output = responses[0].outputs(coefficients.num[:1])[0, trim:] \
                if len(responses) == 1 else sum(responses[j].outputs([num])[0][trim:]
                                                for j, num in enumerate(coefficients.num))
            output.setflags(write=False)
            return output

        return _remembered(self._outputs, self._output_key(coefficients), simulate,
                           self._outputs_kept)

    def linearize(self, coefficients: Coefficients, regressors: bool = True,
                  instruments: Optional[Linearization] = None) -> Linearization:
        """
        Return the output, the regressors ``phi`` (if requested) and instruments ``psi``.

        ``phi`` and ``psi`` are equations (3.2)-(3.4) and (4.1) of ``docs/algorithm.md``, one
        column per parameter, computed by the three simulations of its section 4.
        ``instruments``: this bank's linearisation at the same coefficients without the
        regressors, whose output, ``psi`` and ``delay_jump`` are taken over: only ``phi`` is
        computed (the values a whole linearisation gives).
        """
        den = coefficients.den
        order = den.size - 1
        den_jacobian = coefficients.den_jacobian
        params = den_jacobian.shape[0]
        count = self.y.shape[0]
        # Masks and gradients of a few parameters are tested as lists: the builtin any/all
        # of a few Python values costs a fraction of the array methods' reductions.
        delay_used = any(coefficients.delay_gradient.tolist())
        delay = coefficients.delay + self.extra_delay
        # A zero row of a Jacobian (a gain moves no D, a lag no N) maps to a zero regressor:
        # only the parameters that move a polynomial are mapped for phi.
        den_moves = _moving_rows(den_jacobian)
        # Only a dead time's jump reads the discretisation itself.
        bank_u = self._discrete(den, delay, self.intersample) if delay_used else None
        u_responses = self._channel_responses(self._responses, den, delay,
                                              self._responses_kept)
        sensitivity_responses: Optional[_Responses] = None
        # An accepted candidate's output is remembered from its cost: not mapped again.
        key = self._output_key(coefficients)
        known = self._outputs.get(key) if instruments is None else instruments.output
        output = derivative = jump = psi = u_regressors = None
        trim = self.trim
        for j, num in enumerate(coefficients.num):
            signal = self.driving[:, j]
            num_full = _pad(num, order + 1)
            num_jac = _pad(coefficients.num_jacobian[:, j], order + 1)
            num_moves = _moving_rows(num_jac)
            if delay_used and num_full[0] != 0.0:
                raise EstimationError(
                    'cannot estimate the dead time of a biproper model (numerator and '
                    'denominator of equal degree): its output jumps with the held input; fix '
                    'the dead time or use a strictly proper model')
            u_numerators = [] if known is not None else [num_full]
            derivative_row = len(u_numerators)
            if delay_used:
                times_s = np.zeros(order + 1)                       # s N, strictly proper
                times_s[:-1] = num_full[1:]
                u_numerators.append(times_s)
            regressor_row = len(u_numerators)
            if regressors:
                u_numerators.extend(num_jac[num_moves])
            # The rows all have deg D + 1 coefficients: one 2-D array, mapped in one pass.
            u_parts = u_responses[j].outputs(np.array(u_numerators))[:, trim:] \
                if u_numerators else None
            if known is None:
                output = _summed(output, u_parts[0])
            if delay_used:
                derivative = _summed(derivative, u_parts[derivative_row])
                # d yhat / d tau = -s yhat, whose feedthrough of the delayed held input takes
                # the input just before t_k for a growing dead time (its left limit).
                on_lattice = bank_u.feed_left is not None and bank_u.feed_left != bank_u.feed
                feedthrough = bank_u.continuous.output_map(times_s)[1] if on_lattice else 0.0
                if feedthrough != 0.0:
                    jump = _summed(jump, feedthrough * (bank_u.delayed_input(signal, left=True)
                                                        - bank_u.delayed_input(signal))[trim:])
            if regressors and regressor_row < len(u_numerators):
                u_regressors = _summed(u_regressors,
                                       _spread(u_parts[regressor_row:], num_moves))
            if instruments is not None:
                continue
            # Both products have degree 2 deg D: the coefficient arrays align. Every row is
            # mapped, the dead time's zero one too: the rounding of the others depends on how
            # many rows one product maps, and the covariance of a near-singular fit shows it.
            sensitivity_numerators = _row_products(num_jac, den) - \
                _row_products(den_jacobian, num_full)
            # Read off the modes of D where it has uncoupled ones, else simulated through 1/D^2.
            sensitivities = u_responses[j].squared_outputs(sensitivity_numerators)
            if sensitivities is None:
                if sensitivity_responses is None:
                    # np.convolve multiplies polynomials without np.polymul's poly1d overhead.
                    sensitivity_responses = self._channel_responses(
                        self._sensitivities, np.convolve(den, den), delay, 1)
                sensitivities = sensitivity_responses[j].outputs(sensitivity_numerators)
            psi = _summed(psi, sensitivities[:, trim:])
        # Contiguous rows (a complex simulation's real part is strided): every product of an
        # update runs over them.
        if instruments is None:
            psi = np.ascontiguousarray(psi)
        # psi for a growing dead time; a shrinking one gets back the feedthrough's jump.
        delay_jump = None
        # The dead time's term -dtau/dtheta_i s G u, in the rows of the parameters that move it
        # (one, as a rule): the other rows would add zeros.
        delay_terms = []
        if delay_used:
            moved = derivative if jump is None else derivative + jump
            gradient = coefficients.delay_gradient
            for row in gradient.nonzero()[0].tolist():
                term = gradient[row] * moved
                if instruments is None:
                    psi[row] -= term
                delay_terms.append((row, term))
            if instruments is not None:
                delay_jump = instruments.delay_jump
            elif jump is not None and jump.any():
                delay_jump = (gradient[:, None] * jump).T          # np.outer's product
        phi = None
        if regressors:
            phi = u_regressors
            moving = den_moves.tolist()
            bank_y = None if not any(moving) else _remembered(
                self._output_filtered, den.tobytes(),
                lambda: self._discrete(den, 0.0, 'foh').response(self.y), 1)
            if all(moving):
                y_parts = bank_y.outputs(den_jacobian)          # a new array: negated in place
                phi = np.subtract(0.0, y_parts, out=y_parts) if phi is None else \
                    _less(phi, y_parts)
            else:
                if phi is None:
                    phi = np.zeros((params, count))
                if bank_y is not None:
                    # Row by row in place: a masked subtraction would gather the rows into a
                    # copy, subtract into another and scatter them back.
                    y_parts = bank_y.outputs(den_jacobian[den_moves])
                    for part, row in zip(y_parts, den_moves.nonzero()[0].tolist()):
                        phi[row] -= part
            for row, term in delay_terms:
                phi[row] -= term
            phi = phi.T
        if known is None:
            output = np.array(output)       # its own array, not a view of the mapped rows
            output.setflags(write=False)
        output = _remembered(self._outputs, key, lambda: output if known is None else known,
                             self._outputs_kept)
        return Linearization(output, phi, psi.T if instruments is None else instruments.psi,
                             delay_jump, coefficients.delay_gradient)


def _moving_rows(jacobian: np.ndarray) -> np.ndarray:
    """
    Return which rows of a Jacobian hold a nonzero value (``jacobian.any(axis=1)``).

    A handful of rows: Python's any over their floats (a NaN counts, as in numpy), a fraction
    of a ufunc reduction's work.
    """
    return np.array([any(row) for row in jacobian.tolist()], dtype=bool)


# Windows this long or longer are summed by BLAS's unrolled dot kernel (OpenBLAS), in an
# order that depends on where the window starts: _row_products' zero padding then moves bits.
_UNROLLED_DOT = 16


def _row_products(rows: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """
    Return the polynomial products ``np.convolve(row, factor)`` of every row, one row each.

    ``rows`` ``(q, m)`` and ``factor`` ``(m,)``, highest power first. One ``np.correlate`` with
    the reversed factor (convolve's own sums) over the rows laid end to end, each followed by
    ``m - 1`` zeros: every product's window holds its own row and zeros, which add exact zeros
    to the same sums, without a call of numpy's wrappers per row. From
    :data:`_UNROLLED_DOT` coefficients on, BLAS's dot product sums a window in another order
    than a row's own correlate would, so such rows go one at a time.
    """
    count, size = rows.shape
    width = 2 * size - 1
    if not count:
        return np.zeros((0, width))
    if size >= _UNROLLED_DOT:
        return np.array([np.correlate(row, factor[::-1], 'full') for row in rows])
    spaced = np.zeros((count, width))
    spaced[:, :size] = rows
    return np.correlate(spaced.reshape(-1), factor[::-1], 'full')[:count * width] \
        .reshape(count, width)


def _spread(values: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Return ``values``, the signals of the ``rows`` marked, as every row (zeros elsewhere)."""
    if all(rows.tolist()):
        return values
    spread = np.zeros((rows.size, values.shape[1]))
    spread[rows] = values
    return spread


def _less(values: np.ndarray, part: np.ndarray) -> np.ndarray:
    """
    Return ``values - part``: in place where ``values`` holds whole contiguous rows.

    ``values`` is the caller's own array. Rows of a trimmed or strided one are subtracted into
    a new contiguous array, the layout every product of an update reads.
    """
    if values.flags.c_contiguous:
        values -= part
        return values
    return values - part


def _summed(total: Optional[np.ndarray], part: np.ndarray) -> np.ndarray:
    """Return ``total + part`` (a new array), or ``part`` itself for the first input channel."""
    return part if total is None else total + part
