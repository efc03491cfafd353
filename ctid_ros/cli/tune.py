"""
``ctid tune``: PI/PID gains from an identified model, verified across its uncertainty.

The model is identified on the record (a CSV file, or a bag with its params file) as ``ctid
fit`` would, then :func:`ctid_ros.design.tune.tune` designs the controller by the stated method
and verifies it on the identified model and on draws from its covariance. The table (or
``--json``) gives the gains, the margins with their 95 % band, the method, and the
ros2_control ``pid_controller`` params (``gains.<joint>.p/i/d``); ``--params-out`` writes them
to a YAML file and ``--plot`` the step response with its band. Files are written only after
everything else succeeded; the params file atomically (never half-written).

Examples
--------
::

    ctid tune dryer.csv --model 'K*exp(-tau*s)/((T1*s+1)*(T2*s+1))' --detrend mean
    ctid tune run1/ --params-file config/open_loop_delay.yaml \
        --model 'K*exp(-tau*s)/(T*s+1)' --controller PI --target tc=0.5 --json
    ctid tune data.csv --model 'K*exp(-tau*s)/(T*s+1)' --params-out pid.yaml --plot

"""

import argparse
import json
import os
from pathlib import Path
import sys
import tempfile
from typing import List, Optional

from ctid_ros.cli.arguments import DEFAULT_PLOT
from ctid_ros.cli.report import json_default
from ctid_ros.cli.sources import load_record, models, plot_path
from ctid_ros.design.margins import Gains, Margins
from ctid_ros.design.tune import step_band, tune, Tuning
from ctid_ros.errors import ConfigError
from ctid_ros.estimation.estimate import Estimate, estimate
import numpy as np

__all__ = ['format_tuning', 'run', 'tune_figure', 'write_atomically']


def _number(value: Optional[float], digits: str = '.3g') -> str:
    return '∞' if value is None or not np.isfinite(value) else format(value, digits)


def format_tuning(tuning: Tuning, result: Estimate) -> str:
    """Return the table of ``ctid tune``: model, gains, margins with band, method, warnings."""
    lines = [f'model {result.model.expression}  (fit {result.fit:.1f} %)']
    lines += [f'  {name} = {value:.5g} ± {result.std.get(name, float("nan")):.2g}'
              for name, value in result.params.items()]
    lines.append(f'{tuning.controller} gains: ' + ', '.join(
        f'{name} = {value:.5g}' for name, value in tuning.gains.to_dict().items()))
    lines.append(f'method: {tuning.method}')
    lines.append(f'on the identified model and 95 % of {tuning.draws} covariance draws:')
    margins = tuning.margins
    for name, value, unit in (('gain_db', margins.gain_db, 'dB'),
                              ('phase_deg', margins.phase_deg, 'deg'),
                              ('ms', margins.ms, ''), ('bandwidth', margins.bandwidth, 'rad/s')):
        low, high = tuning.band.get(name, (None, None))
        band = f'  [{_number(low)}, {_number(high)}]' if tuning.draws else ''
        lines.append(f'  {name:<10} {_number(value):>8} {unit:<5}{band}')
    if tuning.unstable_draws:
        lines.append(f'  unstable in {tuning.unstable_draws} of {tuning.draws} draws')
    lines += [f'warning: {note}' for note in tuning.warnings]
    return '\n'.join(lines)


def tune_figure(tuning: Tuning, path: Optional[Path] = None):
    """
    Plot the unit step response of the loop on the identified model with its 95 % band.

    Top: the output against the reference; bottom: the controller output. Returns the
    :class:`matplotlib.figure.Figure` (written to ``path`` if given).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    times, nominal, band, command = step_band(tuning)
    figure = Figure(figsize=(8.0, 6.0), layout='constrained')
    FigureCanvasAgg(figure)
    top, bottom = figure.subplots(2, 1, sharex=True)
    if band is not None:
        top.fill_between(times, band[0], band[1], color='tab:orange', alpha=0.3, linewidth=0,
                         label='95 % of covariance draws')
    top.plot(times, nominal, color='tab:blue', label='identified model')
    top.axhline(1.0, color='black', linewidth=0.8, linestyle='--', label='reference')
    top.set_ylabel(f'output {tuning.model.output} (unit step)')
    margins = tuning.margins
    top.set_title(f'{tuning.controller} {_gains_text(tuning.gains)}: '
                  f'{_margins_text(margins)}', fontsize='medium')
    top.legend(loc='lower right', fontsize='small')
    bottom.plot(times, command, color='tab:green')
    bottom.set_ylabel(f'command {tuning.model.inputs[0]}')
    bottom.set_xlabel('time (s)')
    for axes in (top, bottom):
        axes.grid(True, alpha=0.3)
    if path is not None:
        figure.savefig(os.fspath(path), dpi=110)
    return figure


def _gains_text(gains: Gains) -> str:
    return ', '.join(f'{name} {value:.3g}' for name, value in gains.to_dict().items())


def _margins_text(margins: Margins) -> str:
    return (f'GM {_number(margins.gain_db, ".1f")} dB, PM {_number(margins.phase_deg, ".0f")}°, '
            f'Ms {margins.ms:.2f}')


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in its directory and a rename."""
    handle, temporary = tempfile.mkstemp(dir=path.resolve().parent, prefix=f'.{path.name}.')
    try:
        with os.fdopen(handle, 'w', encoding='utf-8') as stream:
            stream.write(text)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _check_outputs(arguments: argparse.Namespace) -> Optional[Path]:
    """Check ``--params-out`` and ``--plot`` before anything is computed; return the plot path."""
    inputs = [Path(arguments.path)] + ([Path(arguments.params_file)]
                                       if arguments.params_file else [])
    target = arguments.params_out
    if target is not None:
        if target.exists() and not arguments.overwrite:
            raise ConfigError(f'--params-out {target} already exists; choose another file or '
                              'pass --overwrite to replace it')
        if any(target.resolve() == item.resolve() or item.resolve() in target.resolve().parents
               for item in inputs):
            raise ConfigError(f'--params-out {target} would write into or over an input')
        if not target.resolve().parent.is_dir():
            raise ConfigError(f'--params-out {target}: directory {target.parent} does not exist')
    if arguments.plot is None:
        return None
    from ctid_ros.cli.plots import check_figure_paths

    plot = plot_path(arguments.path, 'tune') if arguments.plot is DEFAULT_PLOT \
        else Path(arguments.plot)
    check_figure_paths(plot, [plot], inputs + ([target] if target is not None else []))
    return plot


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid tune``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    plot = _check_outputs(arguments)
    if arguments.draws < 0:
        raise ConfigError(f'--draws must be 0 or more, got {arguments.draws}')
    data = load_record(arguments)
    model, = models(arguments, [arguments.model])
    result = estimate(model, data, arguments.initial or 'auto', bounds=arguments.bounds,
                      delay_range=arguments.delay_range,
                      initial_state=arguments.initial_state,
                      output_offset=arguments.output_offset)
    tuning = tune(result, arguments.controller, arguments.method, arguments.target,
                  sample_time=arguments.sample_time, draws=arguments.draws)
    if arguments.json:
        summary = {**tuning.to_dict(arguments.joint), 'model': model.expression,
                   'estimate': result.to_dict()}
        text = json.dumps(summary, indent=2, default=json_default)
    else:
        text = (format_tuning(tuning, result) + '\n\nros2_control params:\n'
                + tuning.ros2_control_yaml(arguments.joint).rstrip('\n'))
    written: List[Path] = []
    if plot is not None:
        try:
            tune_figure(tuning, path=plot)
        except OSError as error:
            raise ConfigError(f'--plot {plot}: cannot write the figure: '
                              f'{error.strerror or error}') from None
        written.append(plot)
    if arguments.params_out is not None:
        try:
            write_atomically(arguments.params_out, tuning.ros2_control_yaml(arguments.joint))
        except OSError as error:
            raise ConfigError(f'--params-out {arguments.params_out}: cannot write: '
                              f'{error.strerror or error}') from None
        written.append(arguments.params_out)
    print(text)
    for path in written:
        print(f'ctid tune: wrote {path}', file=sys.stderr)
    return 0
