"""
Repeated identification on windows of streaming data.

:class:`IdentificationSession` is the engine shared by the live node and the offline replay:
both resample their messages with :mod:`ctid_ros.streaming.buffer` and hand each
:class:`~ctid_ros.streaming.buffer.Window` to :meth:`IdentificationSession.update`, which estimates
(warm-started from the previous window) and returns an :class:`Update` holding everything that
is published: estimates and standard deviations in ``parameter_names`` order, diagnostics and
the predicted output. Because both front ends go through this one class, the replay of a bag
gives the same numbers as the live node fed the same samples.
"""

import dataclasses
from dataclasses import dataclass
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

from ctid_ros.core.data import Data
from ctid_ros.errors import EstimationError
from ctid_ros.estimation.estimate import Estimate, estimate
from ctid_ros.estimation.problem import settling_time
from ctid_ros.streaming.buffer import SampleBuffer, Window
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import NANOSECONDS
import numpy as np

__all__ = ['IdentificationSession', 'MAX_UNCERTAIN_INPUTS', 'REFINEMENTS', 'SETTLED_INPUT',
           'Update', 'buffer_capacity', 'history_span', 'lost_input_covariance',
           'refine_lost_inputs']

# Input instants estimated at most per window (each is one unknown more; beyond that many
# dropped messages at changes the midpoints stay, and the window's warning says so).
MAX_UNCERTAIN_INPUTS = 64
# Estimates on a completed input at most (each step of the input values is a Gauss-Newton
# step of parameters and values together); another one only if a value still moved by more
# than SETTLED_INPUT of its range.
REFINEMENTS = 3
SETTLED_INPUT = 0.02


@dataclass(frozen=True)
class Update:
    """
    One estimate over one window, in the order of ``parameter_names``.

    Attributes
    ----------
    end_ns, start_ns : int
        Last and first grid instant of the window used (nanoseconds).
    names : tuple of str
        Parameter names in publishing order.
    values, stds : ndarray
        Estimates and their standard deviations.
    prediction : ndarray
        Model output over the window, one value per grid instant.
    result : Estimate
        The full estimator result.
    window : Window
        The window it was computed from.
    compute_time : float
        Wall-clock seconds spent estimating.
    covariance : ndarray or None
        Parameter covariance in the order of :attr:`names`.

    """

    end_ns: int
    start_ns: int
    names: Tuple[str, ...]
    values: np.ndarray
    stds: np.ndarray
    prediction: np.ndarray
    result: Estimate
    window: Window
    compute_time: float
    covariance: Optional[np.ndarray] = None

    @property
    def prediction_times_ns(self) -> np.ndarray:
        """Return the instants of :attr:`prediction` (the outputs' instants) in nanoseconds."""
        data = self.window.data
        offsets = (np.arange(self.prediction.size) * data.ts + data.output_skew) * NANOSECONDS
        return self.start_ns + np.round(offsets).astype(np.int64)

    @property
    def warnings(self) -> Tuple[str, ...]:
        """
        Return what a user should know about this estimate.

        The window's (grid, refused samples, gaps) and the estimator's (bounds, convergence).
        """
        return tuple(self.window.warnings) + tuple(self.result.warnings)

    @property
    def residuals(self) -> Optional[str]:
        """Return the one-line verdict of the estimator on the residuals, if it gave one."""
        residual = self.result.residuals
        return None if residual is None else residual.verdict

    def diagnostics(self) -> Dict[str, Any]:
        """Return the key/value pairs published on ``/diagnostics`` (see its contract)."""
        residual = self.result.residuals
        consistency = self.result.consistency
        return {
            'fit_percent': self.result.fit,
            'iterations': self.result.iterations,
            'converged': self.result.converged,
            'stop_reason': self.result.stop_reason,
            'start': self.result.start,
            'window_start': self.start_ns / NANOSECONDS,
            'window_end': self.end_ns / NANOSECONDS,
            'window_span': (self.end_ns - self.start_ns) / NANOSECONDS,
            'samples': int(self.prediction.size),
            'grid': self.window.plan.description if self.window.plan is not None else '',
            'grid_step': self.window.data.ts,
            'output_skew': self.window.data.output_skew,
            'compute_time': self.compute_time,
            'residual': residual.verdict if residual else '',
            'residual_white': bool(residual.white) if residual else False,
            'residual_input_correlated': bool(residual.input_correlated) if residual else False,
            # A static nonlinearity: the residual depends on the input's or output's amplitude.
            'residual_amplitude_dependent':
                bool(residual.amplitude_dependent) if residual else False,
            # One parameter vector across the window's halves and quarters (issue 24 a).
            'consistent': bool(consistency.consistent) if consistency else True,
            'consistency': consistency.verdict if consistency else 'not checked',
            'consistency_max_z': float(consistency.max_z) if consistency else 0.0,
            'warnings': list(self.warnings),
        }

    def to_dict(self) -> Dict[str, Any]:
        """Return the ``ctid fit --json`` object of this window plus its end time (s)."""
        summary = self.result.to_dict()
        summary['params'] = {name: float(value) for name, value in zip(self.names, self.values)}
        # A parameter held at a bound has no standard deviation: null, as in Estimate.to_dict.
        summary['std'] = {name: float(value) if np.isfinite(value) else None
                          for name, value in zip(self.names, self.stds)}
        summary['warnings'] = list(self.warnings)
        summary['time'] = self.end_ns / NANOSECONDS
        return summary


def history_span(config: IdentificationConfig) -> float:
    """Return the longest span (s) of data a session asks for (see the config's property)."""
    return config.history_span


def buffer_capacity(config: IdentificationConfig, rate_hz: float) -> int:
    """Size a buffer for :func:`history_span` plus ``max_gap`` and the reorder horizon."""
    return config.buffer_capacity(rate_hz)


def _uncertain_entries(window: Window) -> List[Tuple[int, int]]:
    """Return ``(instant, channel)`` of every input value known only within bounds."""
    instants = window.uncertain_inputs
    if window.input_bounds is None or not 0 < instants.size <= MAX_UNCERTAIN_INPUTS:
        return []
    low, high = (bound.reshape(len(window.data), -1) for bound in window.input_bounds)
    return [(int(k), channel) for k in instants for channel in range(low.shape[1])
            if low[k, channel] != high[k, channel]]


def _skipped(transient: Any, data: Data) -> int:
    """Return the samples at the start of ``data`` that the estimate did not fit."""
    if isinstance(transient, (int, float)) and transient > 0:
        return min(round(transient / data.ts), len(data) - 1)
    return 0


def _lost_input_design(result: Estimate, data: Data, entries: Sequence[Tuple[int, int]]
                       ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the output's sensitivities to the uncertain input values and to the parameters.

    The model is linear in its input: the response to a unit pulse at instant ``k`` is the
    response to one at the first instant, shifted by ``k``. The parameters' sensitivities are
    forward differences, in ``result.model.parameters`` order.
    """
    u = np.asarray(data.u, dtype=float)
    responses = {}
    for channel in {channel for _, channel in entries}:
        pulse = np.zeros_like(u)
        if u.ndim == 2:
            pulse[0, channel] = 1.0
        else:
            pulse[0] = 1.0
        responses[channel] = result.model.simulate(
            result.params, pulse, data.ts, intersample=result.intersample,
            output_skew=data.output_skew)
    inputs = np.zeros((len(data), len(entries)))
    for column, (k, channel) in enumerate(entries):
        inputs[k:, column] = responses[channel][:len(data) - k]
    simulated = result.simulate(data)
    parameters = np.zeros((len(data), len(result.model.parameters)))
    for column, name in enumerate(result.model.parameters):
        value = result.params[name]
        step = 1e-6 * max(abs(value), 1e-3)
        moved = result.model.simulate({**result.params, name: value + step}, data.u, data.ts,
                                      intersample=result.intersample,
                                      output_skew=data.output_skew)
        parameters[:, column] = (moved - simulated) / step
    return inputs, parameters


def refine_lost_inputs(result: Estimate, window: Window, transient: Any = 0.0
                       ) -> Optional[Data]:
    """
    Estimate the input at instants whose message was lost while the input changed.

    A dropped message at a step of a command leaves the instant between the value before
    and the value after, unknown which (the buffer puts the midpoint there and gives the two
    values as :attr:`~ctid_ros.streaming.buffer.Window.input_bounds`). Any fixed guess biases
    the estimate when the change was at that very instant. The model is linear in its input,
    so near ``result`` the output error is linear in those few values and in the parameters:
    one Gauss-Newton step of both, the values kept within their bounds. The refit on the
    completed input then loses one sample's information per such instant, no more (see
    :func:`lost_input_covariance` for its standard deviations).

    Parameters
    ----------
    result : Estimate
        The estimate on ``window.data``.
    window : Window
        The window, with its :attr:`~ctid_ros.streaming.buffer.Window.input_bounds`.
    transient : float or str
        The estimate's transient: seconds at the start that are not fitted ('auto': none).

    Returns
    -------
    Data or None
        The window's data with the estimated input values, or None if there is nothing to
        estimate (no such instant, more than :data:`MAX_UNCERTAIN_INPUTS`, a failed fit) or
        no value moved by more than :data:`SETTLED_INPUT` of its range.

    """
    entries = _uncertain_entries(window)
    if not entries:
        return None
    data = window.data
    skip = _skipped(transient, data)
    inputs, parameters = _lost_input_design(result, data, entries)
    residual = data.y - result.predict(data)
    design = np.hstack((inputs, parameters))[skip:]
    if not (np.all(np.isfinite(design)) and np.all(np.isfinite(residual))):
        return None
    change = np.linalg.lstsq(design, residual[skip:], rcond=None)[0][:len(entries)]
    low, high = (bound.reshape(len(data), -1) for bound in window.input_bounds)
    u = np.array(data.u, dtype=float).reshape(len(data), -1)
    settled = True
    for (k, channel), delta in zip(entries, change):
        value = min(max(u[k, channel] + delta, low[k, channel]), high[k, channel])
        settled &= abs(value - u[k, channel]) <= SETTLED_INPUT * (high[k, channel] -
                                                                  low[k, channel])
        u[k, channel] = value
    if settled:
        return None
    return Data(u if np.ndim(data.u) > 1 else u[:, 0], data.y, data.ts, data.t0,
                data.output_skew)


def lost_input_covariance(result: Estimate, window: Window, transient: Any = 0.0
                          ) -> np.ndarray:
    """
    Return the parameter covariance of ``result`` with the uncertain input values as unknowns.

    The estimate treats the input values of :func:`refine_lost_inputs` as known; they were
    fitted from the same data, so the parameters' covariance grows by what fitting them costs:
    ``s2 ((J' P J)^-1 - (J' J)^-1)`` over the free parameters, with ``J`` the parameters'
    sensitivities, ``P`` the projection away from the sensitivities to those values and
    ``s2`` the residual variance. ``result.covariance`` unchanged if there is none.
    """
    covariance = np.array(result.covariance, dtype=float)
    entries = _uncertain_entries(window)
    if not entries:
        return covariance
    data = window.data
    skip = _skipped(transient, data)
    inputs, parameters = _lost_input_design(result, data, entries)
    free = np.isfinite(np.diag(covariance)) & (np.diag(covariance) > 0)
    inputs, parameters = inputs[skip:], parameters[skip:, free]
    if not (free.any() and np.all(np.isfinite(inputs)) and np.all(np.isfinite(parameters))):
        return covariance
    basis = np.linalg.qr(inputs)[0]
    projected = parameters - basis @ (basis.T @ parameters)
    try:
        growth = np.linalg.inv(projected.T @ projected) - \
            np.linalg.inv(parameters.T @ parameters)
    except np.linalg.LinAlgError:
        return covariance
    index = np.ix_(free, free)
    covariance[index] = covariance[index] + result.noise_variance * growth
    return covariance


class IdentificationSession:
    """
    Estimate a configured model on successive windows, warm-starting each from the last.

    Parameters
    ----------
    config : IdentificationConfig
        Model, bounds, estimator options and publishing order.

    """

    def __init__(self, config: IdentificationConfig):
        self._config = config
        self._previous: Optional[Dict[str, float]] = None
        self._settling: Optional[float] = None

    @property
    def config(self) -> IdentificationConfig:
        """Return the configuration in use."""
        return self._config

    @property
    def previous(self) -> Optional[Dict[str, float]]:
        """Return the last estimate by name (the next warm start), if any."""
        return None if self._previous is None else dict(self._previous)

    def reconfigure(self, config: IdentificationConfig) -> None:
        """Switch configuration; the warm start survives only if the model is unchanged."""
        old = self._config
        same_model = (config.model, config.controller) == (old.model, old.controller)
        self._config = config
        if not same_model:
            self.reset()

    def reset(self) -> None:
        """Forget the warm start: the next estimate starts from the configured initial values."""
        self._previous = None
        self._settling = None

    def window_length(self) -> float:
        """
        Return the seconds of data to take for the next update.

        That is the window plus a settling transient: the configured one, else the settling
        time of the previous estimate (at most one window), else one window.

        """
        config = self._config
        if config.transient >= 0 or self._settling is None:
            return history_span(config)
        return config.window + min(self._settling, config.window)

    def take_window(self, buffer: SampleBuffer, end_ns: Optional[int] = None) -> Window:
        """
        Resample the data for the next update from ``buffer`` (live node and replay alike).

        Asks for :meth:`window_length` seconds and accepts half a window at least, so the first
        estimate comes as soon as that much contiguous data has arrived.

        """
        config = self._config
        length = self.window_length()
        return buffer.window(length, config.sample_time, end_ns,
                             min_length=0.5 * config.window, transient=length - config.window)

    def update(self, window: Window) -> Update:
        """
        Estimate on one window.

        Raises
        ------
        CtidError
            Any :class:`~ctid_ros.errors.EstimationError` or data problem, for the caller to
            report; the session keeps its previous warm start.

        """
        config = self._config
        options = config.estimator_options()
        if config.warm_start and self._previous is not None:
            options['initial'] = self._previous
        record = len(window.data) * window.data.ts
        if config.transient < 0 and self._settling is not None and record > config.window:
            # Everything before the last `window` seconds only settles the model's state, and
            # at least the settling time does (a record barely longer than the window would
            # otherwise be fitted from an unsettled state). Without a previous estimate the
            # estimator's 'auto' transient settles the starting model instead.
            options['transient'] = max(record - config.window, self._settling)
        if options.get('transient', 'auto') != 'auto':
            # The estimator leaves out at most half a record; a window still filling asks for
            # more. Cut here, where that is expected, and not warned about as a user's value.
            options['transient'] = min(options['transient'],
                                       (len(window.data) // 2) * window.data.ts)
        uncertain = window.uncertain_inputs.size
        if uncertain > MAX_UNCERTAIN_INPUTS:
            window = dataclasses.replace(window, notes=window.notes + (
                f'{uncertain} input instants lost their messages while the input changed, '
                f'more than the {MAX_UNCERTAIN_INPUTS} estimated with the model: they keep the '
                'midpoint of their neighbours, which may bias the estimate',))
        started = time.perf_counter()
        result = estimate(config.compiled_model, window.data, **options)
        for _ in range(REFINEMENTS):
            refined = refine_lost_inputs(result, window, options.get('transient', 0.0))
            if refined is None:
                break
            # One more estimate, from the last one, on the input completed by it; if that
            # fails, the last one stands.
            try:
                result = estimate(config.compiled_model, refined,
                                  **{**options, 'initial': dict(result.params)})
            except EstimationError:
                break
            window = dataclasses.replace(window, data=refined)
        # The input values fitted above are unknowns too: their cost in the parameters' spread.
        covariance = lost_input_covariance(result, window, options.get('transient', 0.0))
        elapsed = time.perf_counter() - started
        self._previous = dict(result.params)
        self._settling = settling_time(result.model.coefficients(result.params))
        order = [result.model.parameters[index] for index in config.model_index]
        index = np.asarray(config.model_index, dtype=int)
        stds = np.array([result.std[name] for name in result.model.parameters], dtype=float)
        before = np.diag(np.asarray(result.covariance, dtype=float))
        with np.errstate(divide='ignore', invalid='ignore'):
            grown = np.sqrt(np.diag(covariance) / before)
        stds = np.where(np.isfinite(grown) & (grown > 1.0), stds * grown, stds)
        data = window.data
        return Update(
            end_ns=window.end_ns, start_ns=window.start_ns,
            names=config.names,
            values=np.array([result.params[name] for name in order]),
            stds=stds[index], prediction=result.simulate(data), result=result, window=window,
            compute_time=elapsed, covariance=covariance[np.ix_(index, index)])
