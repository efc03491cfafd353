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

from dataclasses import dataclass
import time
from typing import Any, Dict, Optional, Tuple

from ctid_ros.estimation.estimate import Estimate, estimate
from ctid_ros.estimation.problem import settling_time
from ctid_ros.streaming.buffer import SampleBuffer, Window
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import NANOSECONDS
import numpy as np

__all__ = ['IdentificationSession', 'Update', 'buffer_capacity', 'history_span']


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
        started = time.perf_counter()
        result = estimate(config.compiled_model, window.data, **options)
        elapsed = time.perf_counter() - started
        self._previous = dict(result.params)
        self._settling = settling_time(result.model.coefficients(result.params))
        order = [result.model.parameters[index] for index in config.model_index]
        index = np.asarray(config.model_index, dtype=int)
        data = window.data
        return Update(
            end_ns=window.end_ns, start_ns=window.start_ns,
            names=config.names,
            values=np.array([result.params[name] for name in order]),
            stds=np.array([result.std[name] for name in order]),
            prediction=result.simulate(data), result=result, window=window,
            compute_time=elapsed,
            covariance=np.asarray(result.covariance, dtype=float)[np.ix_(index, index)])
