"""
Figures of an identification: output fit, estimates over time, Bode plot with uncertainty.

Every function builds a :class:`matplotlib.figure.Figure` on its own Agg canvas (never through
``pyplot``), so it works without a display and does not change the backend or the figures of
anybody else in the process. Pass ``path`` to also write a PNG; the figure is returned either
way, for further editing or embedding (:func:`mark_alarms` adds the change alarms to a
parameters figure). :func:`write_replay_figures` draws the set that ``ctid replay --plot``
writes.
"""

from dataclasses import dataclass
import os
from pathlib import Path
from typing import Callable, List, Mapping, Optional, Sequence, Tuple, Union

from ctid_ros.core.model import Model
from ctid_ros.errors import ModelError
from ctid_ros.estimation.estimate import Estimate
from ctid_ros.streaming.alarm import AlarmStatus
from ctid_ros.streaming.contract import ERROR, NANOSECONDS, WARN
from ctid_ros.streaming.session import Update
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
import numpy as np

__all__ = ['BodeData', 'bode', 'bode_data', 'default_omega', 'fit_figure', 'mark_alarms',
           'parameters_figure', 'replay_figure_paths', 'write_replay_figures']

PathLike = Union[str, os.PathLike]
# A constant truth per parameter, or a function of time (s) returning each parameter's values.
Truth = Union[Mapping[str, float], Callable[[np.ndarray], Mapping[str, np.ndarray]]]


def _new_figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height), layout='constrained')
    FigureCanvasAgg(figure)
    return figure


def _finish(figure: Figure, path: Optional[PathLike]) -> Figure:
    if path is not None:
        figure.savefig(os.fspath(path), dpi=110)
    return figure


def fit_figure(time: Sequence[float], measured: Sequence[float], simulated: Sequence[float], *,
               fit: Optional[float] = None, ylabel: str = 'output y',
               title: str = 'Measured vs. simulated output',
               path: Optional[PathLike] = None) -> Figure:
    """
    Plot the measured output against the identified model's simulated output.

    Parameters
    ----------
    time : sequence of float
        Sample instants in seconds.
    measured, simulated : sequence of float
        Measured output and model output at those instants.
    fit : float, optional
        Normalised fit in percent, shown in the title and legend.
    ylabel, title : str
        Axis label (with unit if known) and figure title.
    path : str or os.PathLike, optional
        Where to write a PNG.

    Returns
    -------
    Figure
        One axes.

    """
    figure = _new_figure(9.0, 4.0)
    axes = figure.add_subplot()
    axes.plot(time, measured, color='0.6', linewidth=2.5, alpha=0.7, label='measured')
    label = 'simulated' if fit is None else f'simulated (fit {fit:.1f} %)'
    axes.plot(time, simulated, color='tab:blue', linewidth=1.0, label=label)
    axes.set_xlabel('time (s)')
    axes.set_ylabel(ylabel)
    axes.set_title(title if fit is None else f'{title}: fit {fit:.1f} %')
    axes.grid(True, alpha=0.3)
    axes.legend(loc='best')
    return _finish(figure, path)


def _truth_values(truth: Optional[Truth], names: Sequence[str], time: np.ndarray
                  ) -> Mapping[str, np.ndarray]:
    """Evaluate the truth of each parameter at ``time`` (parameters without one left out)."""
    if truth is None:
        return {}
    values = truth(time) if callable(truth) else truth
    return {name: np.broadcast_to(np.asarray(values[name], dtype=float), time.shape)
            for name in names if name in values}


def parameters_figure(times: Sequence[float], names: Sequence[str], values: np.ndarray,
                      stds: np.ndarray, *, truth: Optional[Truth] = None,
                      path: Optional[PathLike] = None) -> Figure:
    """
    Plot each parameter estimate over time with its ±2σ confidence band.

    Parameters
    ----------
    times : sequence of float
        Time of each estimate (end of its window) in seconds.
    names : sequence of str
        Parameter names, one panel each.
    values, stds : ndarray
        Estimates and standard deviations, shape ``(len(times), len(names))``; NaN standard
        deviations draw no band.
    truth : mapping or callable, optional
        ``{name: value}``, or a function of a time array returning ``{name: values}`` (for a
        parameter that drifts); drawn dashed.
    path : str or os.PathLike, optional
        Where to write a PNG.

    Returns
    -------
    Figure
        One axes per parameter, sharing the time axis.

    """
    times = np.asarray(times, dtype=float)
    values, stds = np.atleast_2d(values), np.atleast_2d(stds)
    figure = _new_figure(9.0, 1.0 + 2.0 * len(names))
    panels = figure.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    dense = np.linspace(times.min(), times.max(), 400) if times.size else times
    truths = _truth_values(truth, names, dense)
    for index, (axes, name) in enumerate(zip(panels, names)):
        axes.fill_between(times, values[:, index] - 2 * stds[:, index],
                          values[:, index] + 2 * stds[:, index], color='tab:blue', alpha=0.2,
                          linewidth=0, label='±2σ')
        axes.plot(times, values[:, index], 'o-', color='tab:blue', markersize=3,
                  label='estimate')
        if name in truths:
            axes.plot(dense, truths[name], '--', color='black', linewidth=1.2, label='truth')
        axes.set_ylabel(name)
        axes.grid(True, alpha=0.3)
        axes.legend(loc='best', fontsize='small')
    panels[0].set_title('Parameter estimates with ±2σ confidence bands')
    panels[-1].set_xlabel('time (s), end of each window')
    return _finish(figure, path)


def mark_alarms(figure: Figure, times: Sequence[float], names: Sequence[str],
                alarms: Sequence[AlarmStatus], path: Optional[PathLike] = None) -> Figure:
    """
    Mark the change alarms on a :func:`parameters_figure` (one panel per name, in order).

    A window whose alarm is raised for a parameter is shaded red on that parameter's panel
    from the previous window's end to its own, and the first one of each alarm gets a red
    line at its estimated start (``since``); windows whose model no longer explains the data
    (WARN) are shaded orange on every panel.

    Parameters
    ----------
    figure : Figure
        The parameters figure.
    times : sequence of float
        End of each window (s), as plotted.
    names : sequence of str
        The panels' parameters.
    alarms : sequence of AlarmStatus
        The alarm after each window.
    path : str or os.PathLike, optional
        Where to write a PNG.

    """
    times = np.asarray(times, dtype=float)
    if times.size == 0 or not alarms:
        return _finish(figure, path)
    # The plotted time base: seconds from some origin, recovered from the first window's end.
    offset = times[0] - (alarms[0].time_ns or 0) / NANOSECONDS
    starts = np.concatenate([[times[0] - (times[1] - times[0] if times.size > 1 else 0.0)],
                             times[:-1]])
    panels = figure.axes[:len(names)]
    for axes, name in zip(panels, names):
        labelled = set()
        for index, status in enumerate(alarms):
            raised = status.level == ERROR and name in status.parameters
            failing = status.level == WARN and not status.parameters
            if not (raised or failing):
                continue
            colour, label = ('tab:red', 'alarm') if raised else ('tab:orange', 'model fails')
            axes.axvspan(starts[index], times[index], color=colour, alpha=0.15, linewidth=0,
                         label=None if label in labelled else label)
            labelled.add(label)
            begins = index == 0 or name not in alarms[index - 1].parameters
            if raised and begins and status.since_ns is not None:
                axes.axvline(status.since_ns / NANOSECONDS + offset, color='tab:red',
                             linewidth=1.0, linestyle=':')
        if labelled:
            axes.legend(loc='best', fontsize='small')
    return _finish(figure, path)


@dataclass(frozen=True)
class BodeData:
    """
    Frequency response of an estimate and its Monte Carlo uncertainty band.

    Attributes
    ----------
    omega : ndarray
        Angular frequencies in rad/s.
    magnitude_db, phase_deg : ndarray
        Response at the estimate.
    magnitude_band, phase_band : ndarray or None
        Lower and upper percentile (shape ``(2, len(omega))``) over the draws; None when the
        covariance is unknown.
    draws : int
        Number of parameter draws that gave a valid response.

    """

    omega: np.ndarray
    magnitude_db: np.ndarray
    phase_deg: np.ndarray
    magnitude_band: Optional[np.ndarray]
    phase_band: Optional[np.ndarray]
    draws: int


def _plotted_model(result: Estimate, closed_loop: bool) -> Model:
    model = result.model
    if model.controller is None or closed_loop:
        return model
    return Model(model.expression)


def default_omega(model: Model, params: Mapping[str, float], points: int = 300,
                  max_omega: Optional[float] = None) -> np.ndarray:
    """
    Return frequencies two decades around the model's poles, zeros and dead time (rad/s).

    ``max_omega`` caps the range, e.g. at the Nyquist frequency ``pi/Ts`` of the data: sampled
    data say nothing about the response above it.
    """
    num, den, delay = model.transfer_function(params)
    corners = np.abs(np.concatenate([np.roots(num), np.roots(den)]))
    corners = list(corners[corners > 0])
    if delay > 0:
        corners.append(1.0 / delay)
    low, high = (min(corners), max(corners)) if corners else (1.0, 1.0)
    top = np.ceil(np.log10(high)) + 1
    if max_omega is not None:
        top = min(top, np.log10(max_omega))
    return np.logspace(np.floor(np.log10(low)) - 1, top, points)


def _response(model: Model, params: Mapping[str, float], omega: np.ndarray
              ) -> Tuple[np.ndarray, np.ndarray]:
    response = model.frequency_response(params, omega)
    return 20 * np.log10(np.abs(response)), np.degrees(np.unwrap(np.angle(response)))


def bode_data(result: Estimate, omega: Optional[np.ndarray] = None, *, draws: int = 100,
              seed: int = 0, percentiles: Tuple[float, float] = (5.0, 95.0),
              closed_loop: bool = False, max_omega: Optional[float] = None) -> BodeData:
    """
    Compute the Bode response of an estimate and its band over covariance draws.

    Parameter vectors are drawn from the normal distribution with the estimate's covariance
    (seeded, so figures are reproducible); draws where the model is undefined are skipped.
    Each draw's phase is shifted by whole turns to start next to the estimate's.

    Parameters
    ----------
    result : Estimate
        The identified model.
    omega : ndarray, optional
        Angular frequencies (rad/s); default :func:`default_omega` up to ``max_omega``.
    draws : int
        Number of Monte Carlo draws.
    seed : int
        Random seed of the draws.
    percentiles : (float, float)
        Band limits in percent.
    closed_loop : bool
        For a closed-loop estimate: the closed loop r -> y instead of the plant P(s).
    max_omega : float, optional
        Highest default frequency (rad/s), e.g. the Nyquist frequency of the data.

    Returns
    -------
    BodeData
        Magnitude (dB) and phase (degrees) with their bands.

    """
    model = _plotted_model(result, closed_loop)
    if omega is None:
        omega = default_omega(model, result.params, max_omega=max_omega)
    omega = np.asarray(omega, dtype=float)
    magnitude, phase = _response(model, result.params, omega)
    covariance = np.asarray(result.covariance, dtype=float)
    if draws < 1 or not np.all(np.isfinite(covariance)):
        return BodeData(omega, magnitude, phase, None, None, 0)
    rng = np.random.default_rng(seed)
    thetas = rng.multivariate_normal(result.theta, covariance, size=draws, method='eigh')
    magnitudes, phases = [], []
    for theta in thetas:
        try:
            draw_magnitude, draw_phase = _response(model, result.model.as_dict(theta), omega)
        except ModelError:
            continue
        if np.all(np.isfinite(draw_magnitude)) and np.all(np.isfinite(draw_phase)):
            magnitudes.append(draw_magnitude)
            phases.append(draw_phase - 360.0 * np.round((draw_phase[0] - phase[0]) / 360.0))
    if not magnitudes:
        return BodeData(omega, magnitude, phase, None, None, 0)
    return BodeData(omega, magnitude, phase, np.percentile(magnitudes, percentiles, axis=0),
                    np.percentile(phases, percentiles, axis=0), len(magnitudes))


def bode(result: Estimate, omega: Optional[np.ndarray] = None, *, draws: int = 100,
         seed: int = 0, percentiles: Tuple[float, float] = (5.0, 95.0),
         closed_loop: bool = False, max_omega: Optional[float] = None,
         path: Optional[PathLike] = None) -> Figure:
    """
    Plot the Bode diagram of an identified model with its uncertainty band.

    The arguments are those of :func:`bode_data`; ``path`` writes a PNG.

    Returns
    -------
    Figure
        Two axes: magnitude (dB) above phase (degrees), over rad/s.

    """
    data = bode_data(result, omega, draws=draws, seed=seed, percentiles=percentiles,
                     closed_loop=closed_loop, max_omega=max_omega)
    model = _plotted_model(result, closed_loop)
    figure = _new_figure(8.0, 6.0)
    top, bottom = figure.subplots(2, 1, sharex=True)
    band_label = f'{percentiles[0]:g}–{percentiles[1]:g} % of {data.draws} covariance draws'
    for axes, nominal, band, unit, short in ((top, data.magnitude_db, data.magnitude_band,
                                              'magnitude (dB)', ' dB'),
                                             (bottom, data.phase_deg, data.phase_band,
                                              'phase (deg)', '°')):
        if band is not None:
            # A precise estimate's band is thinner than the line: its width says it exists.
            width = float(np.max(band[1] - band[0]))
            axes.fill_between(data.omega, band[0], band[1], color='tab:orange', alpha=0.3,
                              linewidth=0, label=f'{band_label}, at most {width:.2g}{short} wide')
        axes.semilogx(data.omega, nominal, color='tab:blue', label='estimate')
        axes.set_ylabel(unit)
        axes.grid(True, which='both', alpha=0.3)
        axes.legend(loc='best', fontsize='small')
    bottom.set_xlabel('angular frequency (rad/s)')
    which = 'closed loop r → y' if model.controller else 'plant'
    top.set_title(f'Bode plot of the identified {which}: {model.expression}')
    return _finish(figure, path)


def replay_figure_paths(path: Path, sliding: bool) -> Tuple[Path, Optional[Path], Path]:
    """Return the measured-vs-simulated, parameters (sliding only) and Bode figure paths."""
    def sibling(suffix: str) -> Path:
        return path.with_name(f'{path.stem}_{suffix}{path.suffix or ".png"}')

    return path, sibling('params') if sliding else None, sibling('bode')


def write_replay_figures(path: Path, updates: Sequence[Update], origin_ns: int, sliding: bool,
                         truth: Optional[Truth] = None,
                         alarms: Optional[Sequence[AlarmStatus]] = None) -> List[Path]:
    """
    Write the replay's figures as PNG files and return their paths.

    ``path`` gets measured vs. simulated output of the last window; ``<stem>_bode.png`` the Bode
    plot of the last estimate up to the Nyquist frequency of the data; with ``sliding`` also
    ``<stem>_params.png``, the estimates over time with their ±2σ bands (against ``truth`` if
    given) and the change ``alarms`` of the windows marked (:func:`mark_alarms`).
    """
    fit_path, params_path, bode_path = replay_figure_paths(path, sliding)
    last = updates[-1]
    times = (last.prediction_times_ns - origin_ns) / NANOSECONDS
    fit_figure(times, last.window.data.y, last.prediction, fit=last.result.fit, path=fit_path)
    written = [fit_path]
    if params_path is not None:
        times = np.array([(update.end_ns - origin_ns) / NANOSECONDS for update in updates])
        figure = parameters_figure(times, last.names,
                                   np.array([update.values for update in updates]),
                                   np.array([update.stds for update in updates]), truth=truth)
        mark_alarms(figure, times, last.names, alarms or (), path=params_path)
        written.append(params_path)
    bode(last.result, max_omega=np.pi / last.window.data.ts, path=bode_path)
    written.append(bode_path)
    return written
