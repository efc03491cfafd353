"""
Figures of an identification: output fit, estimates over time, Bode plot, residual analysis.

Every function builds a :class:`matplotlib.figure.Figure` on its own Agg canvas (never through
``pyplot``), so it works without a display and does not change the backend or the figures of
anybody else in the process. Pass ``path`` to also write a PNG; the figure is returned either
way, for further editing or embedding (:func:`mark_alarms` adds the change alarms to a
parameters figure). :func:`write_replay_figures` draws the set that ``ctid replay --plot``
writes.

Every axis says what it shows and in which unit: seconds, rad/s, dB, degrees, and for
parameters and signals the units of a ``units`` mapping (``{'J': 'kg m^2', 'u': 'N m', 'y':
'rad/s'}``, from the params file or ``ctid fit --units``); a name without a unit is shown
without one.
"""

from dataclasses import dataclass, replace
import os
from pathlib import Path
from typing import Callable, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

from ctid_ros.core.model import Model
from ctid_ros.core.spectral import spectral_response, SpectralResponse
from ctid_ros.errors import ConfigError, ModelError
from ctid_ros.estimation.estimate import Estimate
from ctid_ros.estimation.problem import settling_time
from ctid_ros.streaming.alarm import AlarmStatus
from ctid_ros.streaming.contract import ERROR, NANOSECONDS, WARN
from ctid_ros.streaming.session import Update
import numpy as np

try:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
except ValueError as error:     # matplotlib checks the MPLBACKEND variable as it loads
    raise ConfigError(f'the environment variable MPLBACKEND={os.environ.get("MPLBACKEND")!r} '
                      f'is not a matplotlib backend ({error}); unset it or set '
                      'MPLBACKEND=agg') from None

__all__ = ['BodeData', 'COHERENT', 'bode', 'bode_data', 'check_figure_paths', 'default_omega',
           'fit_figure', 'label', 'mark_alarms', 'measured_response', 'parameters_figure',
           'replay_figure_paths', 'residual_figure', 'transient_seconds', 'without_hold',
           'write_replay_figures']

PathLike = Union[str, os.PathLike]
# A constant truth per parameter, or a function of time (s) returning each parameter's values.
Truth = Union[Mapping[str, float], Callable[[np.ndarray], Mapping[str, np.ndarray]]]
Units = Optional[Mapping[str, str]]
# Coherence from which the data's frequency response is drawn dark (believable).
COHERENT = 0.5


_FIGURE_SUFFIXES = ('', '.png', '.pdf', '.svg')


def check_figure_paths(path: Path, figures: Iterable[Path], inputs: Iterable[Path]) -> None:
    """
    Check, before anything is estimated, that the figures of ``--plot path`` can be written.

    Raises
    ------
    ConfigError
        If a figure would be written into or over one of the ``inputs`` (a bag directory, the
        params file, a CSV, an ``--output`` file), into a missing or unwritable directory, over
        a directory, or in a format other than PNG, PDF or SVG.

    """
    if path.suffix.lower() not in _FIGURE_SUFFIXES:
        raise ConfigError(f'--plot {path}: give a .png, .pdf or .svg file')
    sources = [Path(item).resolve() for item in inputs]
    for figure in figures:
        target = figure.resolve()
        for source in sources:
            if target == source or source in target.parents:
                raise ConfigError(f'--plot {path} would write {figure} into or over the input '
                                  f'{source}; choose a path outside it')
        if not target.parent.is_dir():
            raise ConfigError(f'--plot {path}: directory {target.parent} does not exist')
        if target.is_dir():
            raise ConfigError(f'--plot {path}: {figure} is a directory')
        if not os.access(target.parent, os.W_OK) or (
                target.exists() and not os.access(target, os.W_OK)):
            raise ConfigError(f'--plot {path}: {figure} cannot be written (permission denied)')


def _new_figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height), layout='constrained')
    FigureCanvasAgg(figure)
    return figure


def _finish(figure: Figure, path: Optional[PathLike]) -> Figure:
    if path is not None:
        figure.savefig(os.fspath(path), dpi=110)
    return figure


def label(name: str, units: Units = None, what: str = '') -> str:
    """Return an axis label, ``'J (kg m^2)'`` or ``'output y (rad/s)'``; without a unit ``'J'``."""
    text = f'{what} {name}'.strip()
    unit = (units or {}).get(name)
    return f'{text} ({unit})' if unit else text


def fit_figure(time: Sequence[float], measured: Sequence[float], simulated: Sequence[float], *,
               fit: Optional[float] = None, ylabel: str = 'output y',
               title: str = 'Measured vs. simulated output', transient: float = 0.0,
               unit: Optional[str] = None, verdict: Optional[str] = None,
               path: Optional[PathLike] = None) -> Figure:
    """
    Plot the measured output against the identified model's, with the residual below.

    Parameters
    ----------
    time : sequence of float
        Sample instants in seconds.
    measured, simulated : sequence of float
        Measured output and model output at those instants.
    fit : float, optional
        Normalised fit in percent, shown in the title and legend.
    ylabel, title : str
        What the output is, and the figure title.
    transient : float
        Seconds at the start that were simulated but not fitted (the settling of a window cut
        from a running plant): shaded in both panels.
    unit : str, optional
        Unit of the output, added to both vertical axes.
    verdict : str, optional
        What the residual analysis says of the residual (whiteness, correlation with the
        input), shown over the residual panel.
    path : str or os.PathLike, optional
        Where to write a PNG.

    Returns
    -------
    Figure
        Two axes sharing the time axis: the outputs above, measured minus simulated below.

    """
    time = np.asarray(time, dtype=float)
    measured = np.asarray(measured, dtype=float)
    simulated = np.asarray(simulated, dtype=float)
    residual = measured - simulated
    figure = _new_figure(9.0, 5.6)
    top, bottom = figure.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [3, 1.6]})
    fitted = time >= time[0] + transient - 1e-12 if time.size else time.astype(bool)
    for axes in (top, bottom):
        if transient > 0 and time.size:
            axes.axvspan(time[0], time[0] + transient, color='0.85', alpha=0.6, linewidth=0,
                         label=f'first {transient:.3g} s simulated, not fitted')
        axes.grid(True, alpha=0.3)
    top.plot(time, measured, color='0.6', linewidth=2.5, alpha=0.7, label='measured')
    label_text = 'simulated' if fit is None else f'simulated (fit {fit:.1f} %)'
    top.plot(time, simulated, color='tab:blue', linewidth=1.0, label=label_text)
    top.set_ylabel(f'{ylabel} ({unit})' if unit else ylabel)
    top.set_title(title if fit is None else f'{title}: fit {fit:.1f} %')
    top.legend(loc='best', fontsize='small')
    rms = float(np.sqrt(np.mean(residual[fitted] ** 2))) if np.any(fitted) else float('nan')
    bottom.plot(time, residual, color='tab:red', linewidth=0.8,
                label=f'measured - simulated (RMS {rms:.3g} where fitted)')
    bottom.axhline(0.0, color='0.4', linewidth=0.6)
    bottom.set_ylabel(f'residual ({unit})' if unit else 'residual')
    bottom.set_xlabel('time (s)')
    bottom.legend(loc='upper right', fontsize='small')
    if verdict:
        bottom.set_title(_wrapped(f'residual: {verdict}', 110), fontsize=9)
    return _finish(figure, path)


def _wrapped(text: str, width: int) -> str:
    """Return ``text`` broken into lines of at most about ``width`` characters."""
    lines = ['']
    for word in text.split():
        if lines[-1] and len(lines[-1]) + len(word) >= width:
            lines.append(word)
        else:
            lines[-1] = f'{lines[-1]} {word}'.strip()
    return '\n'.join(lines)


def transient_seconds(result: Estimate, samples: int, ts: float, transient: float) -> float:
    """
    Return the seconds at the start of a record that ``result`` simulated but did not fit.

    ``transient`` is what the estimate was asked for: seconds, or negative for automatic (five
    slowest time constants plus the dead time of the estimate, at most half the record).
    """
    if transient >= 0:
        seconds = transient
    else:
        seconds = settling_time(result.model.coefficients(result.params))
    return float(min(np.ceil(seconds / ts - 1e-9), samples // 2) * ts)


def _truth_values(truth: Optional[Truth], names: Sequence[str], time: np.ndarray
                  ) -> Mapping[str, np.ndarray]:
    """Evaluate the truth of each parameter at ``time`` (parameters without one left out)."""
    if truth is None:
        return {}
    values = truth(time) if callable(truth) else truth
    return {name: np.broadcast_to(np.asarray(values[name], dtype=float), time.shape)
            for name in names if name in values}


def parameters_figure(times: Sequence[float], names: Sequence[str], values: np.ndarray,
                      stds: np.ndarray, *, truth: Optional[Truth] = None, units: Units = None,
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
    units : mapping, optional
        Unit of each parameter, on its axis.
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
        axes.set_ylabel(label(name, units))
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
    """
    Return magnitude (dB) and phase (degrees) of the model at ``omega``.

    The phase of the rational part is unwrapped from the lowest frequency, on the branch of its
    low-frequency asymptote (0 or -180 degrees for a gain, -90 per integrator, +90 per zero at
    the origin), and the dead
    time's phase ``-omega tau`` is added exactly: a steadily falling line however far it goes,
    never wrapped into saw-teeth.
    """
    num, den, delay = model.transfer_function(params)
    s = 1j * omega
    rational = np.polyval(num, s) / np.polyval(den, s)
    phase = np.unwrap(np.angle(rational))
    if phase.size:
        phase = phase - 2 * np.pi * np.round((phase[0] - _low_frequency_phase(num, den)) /
                                             (2 * np.pi))
    return 20 * np.log10(np.abs(rational)), np.degrees(phase - omega * delay)


def _low_frequency_phase(num: np.ndarray, den: np.ndarray) -> float:
    """Return the phase (rad) of ``num/den`` as omega goes to 0: of ``c s^k`` (zeros - poles)."""
    def trailing(coefficients: np.ndarray) -> Tuple[int, float]:
        nonzero = np.flatnonzero(np.asarray(coefficients) != 0)
        last = nonzero[-1] if nonzero.size else 0
        return len(coefficients) - 1 - last, float(coefficients[last]) if nonzero.size else 1.0

    zeros, num_low = trailing(num)
    poles, den_low = trailing(den)
    # A negative gain lags by half a turn (as a phase margin is read), not leads.
    return float((-np.pi if num_low / den_low < 0 else 0.0) + (zeros - poles) * np.pi / 2)


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
         measured: Optional[SpectralResponse] = None, units: Units = None,
         path: Optional[PathLike] = None) -> Figure:
    """
    Plot the Bode diagram of an identified model with its uncertainty band.

    The arguments are those of :func:`bode_data`; ``measured`` adds the frequency response seen
    in the data alone (:func:`~ctid_ros.core.spectral.spectral_response`, as MATLAB's ``spa``),
    dark where its coherence is at least :data:`COHERENT`; ``units`` (of the model's input and
    output) label the magnitude; ``path`` writes a PNG.

    Returns
    -------
    Figure
        Two axes: magnitude (dB) above phase (degrees), over rad/s.

    """
    if omega is None and measured is not None and measured.omega.size:
        model = _plotted_model(result, closed_loop)
        default = default_omega(model, result.params, max_omega=max_omega)
        omega = np.logspace(np.log10(min(default[0], measured.omega[0])),
                            np.log10(max(default[-1], measured.omega[-1])), default.size)
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
    if measured is not None and measured.omega.size:
        _measured(top, bottom, measured, data.phase_deg, data.omega)
    output, source = model.output, model.inputs[0] if not model.controller else 'r'
    ratio = [(units or {}).get(name) for name in (output, source)]
    if all(ratio):
        top.set_ylabel(f'magnitude (dB of {output}/{source} in {ratio[0]} per {ratio[1]})')
    for axes in (top, bottom):
        axes.legend(loc='best', fontsize='small')
    bottom.set_xlabel('angular frequency (rad/s)')
    which = 'closed loop r → y' if model.controller else 'plant'
    top.set_title(f'Bode plot of the identified {which}: {model.expression}')
    return _finish(figure, path)


def residual_figure(result: Estimate, path: Optional[PathLike] = None) -> Figure:
    """
    Plot the residual analysis of an estimate, as MATLAB's ``resid``.

    The autocorrelation of the residual (lags ``0..M``) and its cross-correlation with every
    input (lags ``-M..M``; negative lags: the input reacting to the output), each with its 99 %
    band under independence; the verdict is the title.

    Raises
    ------
    ValueError
        If the estimate carries no residual analysis.

    """
    analysis = result.residuals
    if analysis is None:
        raise ValueError('the estimate has no residual analysis')
    inputs = analysis.inputs
    figure = _new_figure(9.0, 1.2 + 2.3 * (1 + len(inputs)))
    panels = figure.subplots(1 + len(inputs), 1, squeeze=False)[:, 0]
    series = [(np.arange(analysis.lags + 1), analysis.autocorrelation, analysis.auto_bound,
               'autocorrelation of the residual')]
    series += [(np.arange(-analysis.lags, analysis.lags + 1), analysis.cross_correlation[:, j],
                analysis.cross_bounds[j], f'cross-correlation of the residual with {name}')
               for j, name in enumerate(inputs)]
    for axes, (lags, values, bound, label) in zip(panels, series):
        axes.axhspan(-bound, bound, color='tab:blue', alpha=0.15, label='99 % band')
        axes.vlines(lags, 0.0, values, color='0.2', linewidth=1.0)
        axes.plot(lags, values, '.', color='0.2', markersize=3)
        axes.axhline(0.0, color='0.5', linewidth=0.5)
        axes.set_ylabel('correlation')
        axes.set_title(label, fontsize=10)
        axes.grid(True, alpha=0.3)
        axes.legend(loc='upper right', fontsize=8)
    panels[-1].set_xlabel('lag (samples)')
    # The verdict can be long: wrapped at the figure's width.
    words, lines = f'Residual: {analysis.verdict}'.split(), ['']
    for word in words:
        lines[-1:] = [f'{lines[-1]} {word}'.strip()] if len(lines[-1]) + len(word) < 95 \
            else [lines[-1], word]
    figure.suptitle('\n'.join(lines), fontsize=10)
    return _finish(figure, path)


def _measured(top, bottom, measured: SpectralResponse, model_phase: np.ndarray,
              model_omega: np.ndarray) -> None:
    """Draw the data's frequency response: dark where coherent, light where not."""
    start = float(np.interp(measured.omega[0], model_omega, model_phase))
    phase = measured.phase_deg(start=start)
    coherent = measured.coherence >= COHERENT
    for axes, values in ((top, measured.magnitude_db), (bottom, phase)):
        axes.semilogx(measured.omega[~coherent], values[~coherent], '.', color='0.75',
                      markersize=3, label=f'data, coherence < {COHERENT:g}')
        axes.semilogx(measured.omega[coherent], values[coherent], '.', color='0.25',
                      markersize=3.5,
                      label=f'data (Welch, {measured.segment}-sample segments, hold removed)')


def replay_figure_paths(path: Path, sliding: bool
                        ) -> Tuple[Path, Optional[Path], Path, Path]:
    """Return the fit, parameters (sliding only), Bode and residual figure paths."""
    def sibling(suffix: str) -> Path:
        return path.with_name(f'{path.stem}_{suffix}{path.suffix or ".png"}')

    return path, sibling('params') if sliding else None, sibling('bode'), sibling('residual')


def measured_response(result: Estimate, data) -> Optional[SpectralResponse]:
    """
    Return the frequency response from the data alone, or None where it would mislead.

    Only for a model with one input and no controller: with a controller the data run from the
    reference while the Bode plot shows the plant; a model equation has several inputs.
    """
    model = result.model
    if model.controller is not None or len(model.inputs) != 1 or model.constant_input:
        return None
    try:
        measured = spectral_response(data.u, data.y, data.ts)
    except ValueError:
        return None
    return without_hold(measured, data.ts, result.intersample)


def without_hold(measured: SpectralResponse, ts: float, intersample: str) -> SpectralResponse:
    """
    Take the input's hold out of a response measured from samples, to compare with ``G(s)``.

    A held input (``zoh``) reaches the plant through ``sinc(omega ts / 2 pi) exp(-j omega ts /
    2)``: half a sample of delay and a gain falling to 2/pi at the Nyquist frequency; a linear
    one (``foh``) through ``sinc^2``. Dividing them out leaves the continuous plant (up to the
    aliasing of what it passes above the Nyquist frequency).
    """
    argument = measured.omega * ts / (2 * np.pi)
    hold = np.sinc(argument) * np.exp(-0.5j * measured.omega * ts) if intersample == 'zoh' \
        else np.sinc(argument) ** 2
    return replace(measured, response=measured.response / hold)


def write_replay_figures(path: Path, updates: Sequence[Update], origin_ns: int, sliding: bool,
                         truth: Optional[Truth] = None, units: Units = None,
                         transient: float = -1.0,
                         alarms: Optional[Sequence[AlarmStatus]] = None) -> List[Path]:
    """
    Write the replay's figures as PNG files and return their paths.

    ``path`` gets measured vs. simulated output of the last window, its residual below (the
    settling stretch, ``transient`` seconds or automatic when negative, shaded);
    ``<stem>_bode.png`` the Bode plot of the last estimate up to the Nyquist frequency of the
    data, over the response seen in the window's data; ``<stem>_residual.png`` the residual
    analysis of the last estimate (:func:`residual_figure`); with ``sliding`` also
    ``<stem>_params.png``, the estimates over time with their ±2σ bands (against ``truth`` if
    given) and the change ``alarms`` of the windows marked (:func:`mark_alarms`). ``units``
    label the axes.
    """
    fit_path, params_path, bode_path, residual_path = replay_figure_paths(path, sliding)
    last = updates[-1]
    data = last.window.data
    times = (last.prediction_times_ns - origin_ns) / NANOSECONDS
    output = last.result.model.output
    fit_figure(times, data.y, last.prediction, fit=last.result.fit,
               ylabel=f'output {output}', unit=(units or {}).get(output),
               transient=transient_seconds(last.result, len(data), data.ts, transient),
               path=fit_path)
    written = [fit_path]
    if params_path is not None:
        times = np.array([(update.end_ns - origin_ns) / NANOSECONDS for update in updates])
        figure = parameters_figure(times, last.names,
                                   np.array([update.values for update in updates]),
                                   np.array([update.stds for update in updates]), truth=truth,
                                   units=units)
        mark_alarms(figure, times, last.names, alarms or (), path=params_path)
        written.append(params_path)
    bode(last.result, max_omega=np.pi / data.ts, measured=measured_response(last.result, data),
         units=units, path=bode_path)
    written.append(bode_path)
    if last.result.residuals is not None:
        residual_figure(last.result, path=residual_path)
        written.append(residual_path)
    return written
