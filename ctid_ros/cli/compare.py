"""
``ctid compare``: fit candidate models on one record and recommend the simplest adequate one.

Every ``--model`` is fitted on the same record (a CSV file, or a bag read with its params file)
by :func:`ctid_ros.estimation.compare.compare`, scored on the held-out end of the record (or
``--validate``), and ranked. The table says for each candidate its validation fit, AIC, BIC,
consistency over the record and residual, marks the recommended one and says why in one line;
``--json`` is the list, best first, of ``{"model", "params", "std", "fit", "consistent",
"recommended", "why", ...}``; ``--plot`` draws the validation outputs and the Bode plots with
their bands side by side.

Examples
--------
::

    ctid compare dryer.csv --detrend mean --model 'K*exp(-tau*s)/(T*s+1)' \
        --model 'K*exp(-tau*s)/((T1*s+1)*(T2*s+1))'
    ctid compare run1/ --params-file config/open_loop_delay.yaml --model 'K/(T*s+1)' \
        --model 'K*exp(-tau*s)/(T*s+1)' --json --plot

"""

import argparse
import json
import os
from pathlib import Path
import sys
from typing import Optional

from ctid_ros.cli.arguments import DEFAULT_PLOT
from ctid_ros.cli.report import json_default
from ctid_ros.cli.sources import load_record, model_signals, models, plot_path
from ctid_ros.errors import ConfigError
from ctid_ros.estimation.compare import compare, Comparison
import numpy as np

__all__ = ['compare_figure', 'format_comparison', 'run']

# Colours of the candidates, in ranking order (the recommended one first).
_COLOURS = ('tab:blue', 'tab:orange', 'tab:green', 'tab:red', 'tab:purple', 'tab:brown')


def _cell(value: Optional[float], digits: str) -> str:
    return '-' if value is None or not np.isfinite(value) else format(value, digits)


def format_comparison(comparison: Comparison) -> str:
    """Return the table of ``ctid compare``: one row per candidate, best first, then why."""
    where = ('the held-out last part' if comparison.held_out else 'the validation data')
    lines = [f'validation fit on {where} ({len(comparison.validation)} samples); estimated on '
             f'{len(comparison.estimation)} samples',
             f'{"":2}{"#":>2}  {"k":>2} {"fit %":>7} {"AIC":>10} {"BIC":>10} {"consistent":>11}'
             '  model']
    for rank, item in enumerate(comparison.candidates, start=1):
        consistent = {None: 'not checked', True: 'yes', False: 'NO'}[item.consistent]
        mark = '* ' if item.recommended else '  '
        lines.append(f'{mark}{rank:>2}  {item.parameters:>2} {_cell(item.fit, ".2f"):>7} '
                     f'{_cell(item.aic, ".1f"):>10} {_cell(item.bic, ".1f"):>10} '
                     f'{consistent:>11}  {item.model.expression}')
    lines.append('')
    for rank, item in enumerate(comparison.candidates, start=1):
        lines.append(f'{"*" if item.recommended else " "}{rank:>2} {item.why}')
        if item.estimate is not None:
            lines.append('    ' + ', '.join(
                f'{name} = {value:.4g} ± {item.estimate.std.get(name, float("nan")):.2g}'
                for name, value in item.estimate.params.items()))
    return '\n'.join(lines)


def compare_figure(comparison: Comparison, path: Optional[Path] = None):
    """
    Plot the candidates side by side: validation outputs (left), Bode plots with bands (right).

    The bands are 5-95 % of 100 covariance draws (:func:`ctid_ros.cli.plots.bode_data`).
    Returns the :class:`matplotlib.figure.Figure` (written to ``path`` if given).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ctid_ros.cli.plots import bode_data, default_omega

    figure = Figure(figsize=(13.0, 6.5), layout='constrained')
    FigureCanvasAgg(figure)
    grid = figure.add_gridspec(2, 2)
    outputs = figure.add_subplot(grid[:, 0])
    magnitude = figure.add_subplot(grid[0, 1])
    phase = figure.add_subplot(grid[1, 1], sharex=magnitude)
    validation = comparison.validation
    times = validation.ts * np.arange(len(validation))
    outputs.plot(times, validation.y, color='black', linewidth=0.8, label='measured')
    # One grid for all, up to the Nyquist frequency: the data say nothing above it.
    nyquist = np.pi / validation.ts
    # A Bode plot needs one input and no constant term (a model equation may have more).
    drawn = [item for item in comparison.candidates if item.estimate is not None
             and len(item.model.inputs) == 1 and not item.model.constant_input]
    grids = [default_omega(item.model, item.estimate.params, max_omega=nyquist)
             for item in drawn]
    omega = np.logspace(np.log10(min(grid[0] for grid in grids)), np.log10(nyquist), 300) \
        if grids else None
    nominal = ([], [])
    for colour, item in zip(_COLOURS * 4, comparison.candidates):
        result = item.estimate
        if result is None:
            continue
        simulated = comparison.simulated(item)
        name = ('recommended: ' if item.recommended else '') + item.model.expression
        # The recommended one is drawn thicker and on top.
        style = {'color': colour, 'linewidth': 1.8 if item.recommended else 1.0,
                 'zorder': 3 if item.recommended else 2}
        outputs.plot(times, simulated, label=f'{name} ({_cell(item.fit, ".1f")} %)', **style)
        if item not in drawn:
            continue
        bode = bode_data(result, omega)
        magnitude.semilogx(bode.omega, bode.magnitude_db, **style)
        phase.semilogx(bode.omega, bode.phase_deg, **style)
        nominal[0].extend(bode.magnitude_db)
        nominal[1].extend(bode.phase_deg)
        if bode.magnitude_band is not None:
            magnitude.fill_between(bode.omega, *bode.magnitude_band, color=colour, alpha=0.25,
                                   linewidth=0)
            phase.fill_between(bode.omega, *bode.phase_band, color=colour, alpha=0.25,
                               linewidth=0)
    # The axes follow the models, not a band the data do not bound (an unidentifiable
    # candidate's band may span decades).
    for axes, values, pad in ((magnitude, nominal[0], 10.0), (phase, nominal[1], 45.0)):
        if values:
            axes.set_ylim(min(values) - pad, max(values) + pad)
    outputs.set_xlabel('time in the validation data (s)')
    outputs.set_ylabel('output')
    outputs.set_title('validation: measured and simulated outputs (fit %)', fontsize='medium')
    outputs.legend(loc='best', fontsize='small')
    magnitude.set_ylabel('magnitude (dB)')
    magnitude.set_title('Bode plots, bands: 5-95 % of 100 covariance draws', fontsize='medium')
    phase.set_ylabel('phase (deg)')
    phase.set_xlabel('angular frequency (rad/s)')
    for axes in (outputs, magnitude, phase):
        axes.grid(True, which='both', alpha=0.3)
    if path is not None:
        figure.savefig(os.fspath(path), dpi=110)
    return figure


def _validation(arguments: argparse.Namespace, equation: bool):
    """Return the ``--validate`` record, read with the same columns or topics."""
    if arguments.validate is None:
        return None
    settings = dict(vars(arguments), path=arguments.validate, estimate_range=None, start=None,
                    end=None)
    return load_record(argparse.Namespace(**settings), equation)


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid compare``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    plot = None
    if arguments.plot is not None:
        from ctid_ros.cli.plots import check_figure_paths

        plot = plot_path(arguments.path, 'compare') if arguments.plot is DEFAULT_PLOT \
            else Path(arguments.plot)
        inputs = [Path(item) for item in (arguments.path, arguments.validate,
                                          arguments.params_file) if item]
        check_figure_paths(plot, [plot], inputs)
    equation = model_signals(arguments.model)
    data = load_record(arguments, equation)
    comparison = compare(models(arguments, arguments.model), data,
                         validation=_validation(arguments, equation),
                         holdout=arguments.holdout, initial_state=arguments.initial_state,
                         output_offset=arguments.output_offset)
    if arguments.json:
        print(json.dumps(comparison.to_list(), indent=2, default=json_default))
    else:
        print(format_comparison(comparison))
    if plot is not None:
        try:
            compare_figure(comparison, path=plot)
        except OSError as error:
            raise ConfigError(f'--plot {plot}: cannot write the figure: '
                              f'{error.strerror or error}') from None
        print(f'ctid compare: wrote {plot}', file=sys.stderr)
    return 0
