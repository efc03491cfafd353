"""
``ctid fit``: estimate a model from a CSV file.

Columns are named as in the file, PlotJuggler's ``/topic/field`` names included; its time
column ``__time`` is found like ``t``. A model equation names its signals after the columns, or
``--input SIGNAL=COLUMN`` when a column name is no identifier.

Examples
--------
::

    ctid fit data.csv --model 'K*exp(-tau*s)/(T*s + 1)' --initial K=1,T=2
    ctid fit data.csv --model '1/(m*s**2 + d*s + k)' --controller '20 + 10/s' --json
    ctid fit dryer.csv --model 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))' --detrend mean \
        --estimate-range 1:500 --validate-range 501:1000
    ctid fit stage.csv --model 'M*s**2*q + Fv*s*q = 35.15*v - Fc*w - off' \
        --input v --input w --output q
    ctid fit export.csv --model 'exp(-tau*s)/(J*s + b)' --input /cmd/data \
        --output '/joint_states/velocity[0]' --fix J=0.05 --delay-range 0:0.1 --plot

"""

import argparse
from dataclasses import replace
import json
from pathlib import Path
import re
import sys
from typing import Dict, List, Optional, Sequence, Tuple

from ctid_ros.cli.arguments import DEFAULT_PLOT
from ctid_ros.cli.report import format_table, json_default
from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import ConfigError, DataError
from ctid_ros.estimation.estimate import Estimate, estimate
from ctid_ros.files.csv_file import load_csv, TIME_COLUMNS
import numpy as np

__all__ = ['Signals', 'default_plot_path', 'fit_figure_paths', 'run', 'select_samples',
           'signals']

_IDENTIFIER = re.compile(r'[A-Za-z_][A-Za-z0-9_]*\Z')


def select_samples(data: Data, samples: Optional[Tuple[int, int]], detrend: str,
                   what: str) -> Data:
    """Return the 1-based inclusive ``samples`` of ``data`` (all if None), detrended."""
    if samples is not None:
        first, last = samples
        if last > len(data):
            raise DataError(f'{what} range {first}:{last} exceeds the {len(data)} samples')
        data = data.segment(first - 1, last)
    return data if detrend == 'none' else data.detrend(detrend)


class Signals:
    """
    The CSV columns of the inputs and the output, and the signal names the model uses.

    Attributes
    ----------
    input_columns, input_names : tuple of str
        Input columns and their signal names, in order.
    output_column, output_name : str
        Output column and its signal name.

    """

    def __init__(self, inputs: Sequence[Tuple[str, str]], output: Tuple[str, str]):
        self.input_names = tuple(name for name, _ in inputs)
        self.input_columns = tuple(column for _, column in inputs)
        self.output_name, self.output_column = output


def _signal(text: str, default: str, equation: bool, option: str) -> Tuple[str, str]:
    """Return ``(signal name, column)`` of ``[SIGNAL=]COLUMN``."""
    name, separator, column = text.partition('=')
    if separator:
        name, column = name.strip(), column.strip()
        if not _IDENTIFIER.match(name) or not column:
            raise ConfigError(f'{option} {text!r}: expected SIGNAL=COLUMN with a signal name '
                              'of letters, digits and underscores')
        return name, column
    column = text.strip()
    if _IDENTIFIER.match(column):
        return column, column
    if equation:
        raise ConfigError(f'{option} {column!r}: a model equation names its signals after the '
                          f'columns; give this one a name: {option} {default}={column}')
    return default, column


def signals(inputs: Optional[List[str]], output: str, equation: bool) -> Signals:
    """
    Read ``--input`` (repeated or comma-separated) and ``--output`` as columns and signals.

    Each is ``COLUMN`` or ``SIGNAL=COLUMN``. A column name that is no identifier (PlotJuggler's
    ``/cmd/data``, ``/joint_states/position[0]``) is fine for a transfer function, whose signals
    are ``u`` and ``y`` whatever the columns; a model equation needs ``SIGNAL=COLUMN`` for it.
    """
    texts = [item for value in (inputs or ['u']) for item in value.split(',') if item.strip()]
    defaults = ['u'] if len(texts) == 1 else [f'u{index + 1}' for index in range(len(texts))]
    pairs = [_signal(text, default, equation, '--input')
             for text, default in zip(texts, defaults)]
    return Signals(pairs, _signal(output, 'y', equation, '--output'))


def default_plot_path(csv: str, directory: Optional[Path] = None) -> Path:
    """Return where ``--plot`` without a value writes: ``<csv name>_fit.png`` (current dir)."""
    name = Path(csv).name
    for suffix in ('.gz', '.csv'):
        name = name[:-len(suffix)] if name.endswith(suffix) else name
    return (directory or Path.cwd()) / f'{name or "data"}_fit.png'


def fit_figure_paths(path: Path) -> Tuple[Path, Path, Path]:
    """Return the measured-vs-simulated, Bode and residual figure paths of ``--plot path``."""
    suffix = path.suffix or '.png'
    return path, path.with_name(f'{path.stem}_bode{suffix}'), \
        path.with_name(f'{path.stem}_residual{suffix}')


def _fixed(arguments: argparse.Namespace, model: Model) -> Tuple[Model, Dict[str, float]]:
    """Return the model with ``--fix`` applied, and the fixed values."""
    fixed = arguments.fix or {}
    for option in ('initial', 'bounds'):
        both = sorted(set(getattr(arguments, option) or {}) & set(fixed))
        if both:
            raise ConfigError(f'{", ".join(both)} fixed by --fix cannot also be given in '
                              f'--{option}')
    return (model.with_fixed(fixed) if fixed else model), fixed


def _summary(result: Estimate, order: Sequence[str], fixed: Dict[str, float]) -> dict:
    """Return the ``--json`` object: fixed parameters in place, with std 0 and ``fixed``."""
    summary = result.to_dict()
    if fixed:
        summary['params'] = {name: fixed.get(name, summary['params'].get(name))
                             for name in order}
        summary['std'] = {name: 0.0 if name in fixed else summary['std'].get(name)
                          for name in order}
        summary['fixed'] = dict(fixed)
    return summary


def _write_figures(path: Path, result: Estimate, data: Data, units: Dict[str, str]
                   ) -> List[Path]:
    # matplotlib is needed (and loaded) only for figures.
    from ctid_ros.cli.plots import bode, fit_figure, measured_response, residual_figure

    fit_path, bode_path, residual_path = fit_figure_paths(path)
    times = data.ts * np.arange(len(data))      # from the first sample (not epoch seconds)
    output = result.model.output
    fit_figure(times, data.y, result.simulate(data), fit=result.fit, ylabel=f'output {output}',
               unit=units.get(output), path=fit_path)
    bode(result, max_omega=np.pi / data.ts, measured=measured_response(result, data),
         units=units, path=bode_path)
    if result.residuals is None:
        return [fit_path, bode_path]
    residual_figure(result, path=residual_path)
    return [fit_path, bode_path, residual_path]


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid fit``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    plot = None
    if arguments.plot is not None:
        from ctid_ros.cli.plots import check_figure_paths

        plot = default_plot_path(arguments.csv) if arguments.plot is DEFAULT_PLOT \
            else Path(arguments.plot)
        check_figure_paths(plot, fit_figure_paths(plot),
                           [Path(arguments.csv)] + ([Path(arguments.validate)]
                                                    if arguments.validate else []))
    columns = signals(arguments.input, arguments.output, '=' in arguments.model)
    full = Model(arguments.model, controller=arguments.controller, inputs=columns.input_names,
                 output=columns.output_name)
    model, fixed = _fixed(arguments, full)
    times = TIME_COLUMNS if arguments.time is None else arguments.time
    notes: List[str] = []
    data = load_csv(arguments.csv, input_column=columns.input_columns,
                    output_column=columns.output_column, time_column=times, ts=arguments.ts,
                    notes=notes)
    estimation = select_samples(data, arguments.estimate_range, arguments.detrend, 'estimation')
    result = estimate(model, estimation, arguments.initial or 'auto', bounds=arguments.bounds,
                      method=arguments.method, intersample=arguments.intersample,
                      max_iterations=arguments.max_iterations,
                      delay_range=arguments.delay_range,
                      initial_state=arguments.initial_state,
                      output_offset=arguments.output_offset)
    # What the resampling of a jittered time column did comes first among the warnings.
    result = replace(result, warnings=notes + list(result.warnings))
    summary = _summary(result, full.parameters, fixed)
    if arguments.validate or arguments.validate_range:
        source = data if arguments.validate is None else load_csv(
            arguments.validate, input_column=columns.input_columns,
            output_column=columns.output_column, time_column=times, ts=arguments.ts)
        validation = select_samples(source, arguments.validate_range, arguments.detrend,
                                    'validation')
        summary['validation_fit'] = result.compare(validation)
    if arguments.json:
        print(json.dumps(summary, indent=2, default=json_default))
    else:
        print(format_table(result, fixed=fixed))
        if 'validation_fit' in summary:
            print(f'validation fit {summary["validation_fit"]:.2f} % '
                  f'({len(validation)} samples)')
    if plot is not None:
        try:
            written = _write_figures(plot, result, estimation, arguments.units or {})
        except OSError as error:
            raise ConfigError(f'--plot {plot}: cannot write the figures: '
                              f'{error.strerror or error}') from None
        for path in written:
            print(f'ctid fit: wrote {path}', file=sys.stderr)
    return 0
