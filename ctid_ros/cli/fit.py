"""
``ctid fit``: estimate a model from a CSV file.

Examples
--------
::

    ctid fit data.csv --model 'K*exp(-tau*s)/(T*s + 1)' --initial K=1,T=2
    ctid fit data.csv --model '1/(m*s**2 + d*s + k)' --controller '20 + 10/s' --json
    ctid fit dryer.csv --model 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))' --detrend mean \
        --estimate-range 1:500 --validate-range 501:1000
    ctid fit stage.csv --model 'M*s**2*q + Fv*s*q = 35.15*v - Fc*w - off' \
        --input v --input w --output q

"""

import argparse
from dataclasses import replace
import json
from typing import Dict, List, Optional, Tuple

from ctid_ros.cli.report import format_table, json_default
from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.core.simulation import INTERSAMPLE
from ctid_ros.errors import DataError
from ctid_ros.estimation.estimate import estimate, INITIAL_STATES, METHODS
from ctid_ros.files.csv_file import load_csv

__all__ = ['configure_parser', 'parse_bounds', 'parse_initial', 'parse_range', 'run']


def _assignments(text: str, option: str) -> Dict[str, str]:
    pairs = {}
    for item in filter(None, (part.strip() for part in text.split(','))):
        name, separator, value = item.partition('=')
        if not separator or not name.strip():
            raise argparse.ArgumentTypeError(f'{option} expects NAME=VALUE[,NAME=VALUE...], '
                                             f'got {item!r}')
        pairs[name.strip()] = value.strip()
    return pairs


def parse_initial(text: str) -> Dict[str, float]:
    """Parse ``K=1,T=2`` into ``{'K': 1.0, 'T': 2.0}``."""
    try:
        return {name: float(value) for name, value in _assignments(text, '--initial').items()}
    except ValueError as error:
        raise argparse.ArgumentTypeError(f'--initial: {error}') from None


def parse_bounds(text: str) -> Dict[str, Tuple[Optional[float], Optional[float]]]:
    """Parse ``T=0:10,tau=0:`` into ``{'T': (0, 10), 'tau': (0, None)}``."""
    bounds = {}
    for name, value in _assignments(text, '--bounds').items():
        low, separator, high = value.partition(':')
        if not separator:
            raise argparse.ArgumentTypeError(f'--bounds expects NAME=LOW:HIGH, got {value!r}')
        try:
            bounds[name] = (float(low) if low else None, float(high) if high else None)
        except ValueError as error:
            raise argparse.ArgumentTypeError(f'--bounds: {error}') from None
    return bounds


def parse_range(text: str) -> Tuple[int, int]:
    """Parse ``FIRST:LAST``, 1-based inclusive sample numbers (as MATLAB's ``z(1:500)``)."""
    try:
        first, last = (int(part) for part in text.split(':'))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected FIRST:LAST sample numbers, got {text!r}'
                                         ) from None
    if not 1 <= first <= last:
        raise argparse.ArgumentTypeError(f'need 1 <= FIRST <= LAST, got {text!r}')
    return first, last


def _select(data: Data, samples: Optional[Tuple[int, int]], detrend: str, what: str) -> Data:
    if samples is not None:
        first, last = samples
        if last > len(data):
            raise DataError(f'{what} range {first}:{last} exceeds the {len(data)} samples')
        data = data.segment(first - 1, last)
    return data if detrend == 'none' else data.detrend(detrend)


def _input_names(values: Optional[List[str]]) -> Tuple[str, ...]:
    names = [name.strip() for value in (values or ['u']) for name in value.split(',')]
    return tuple(name for name in names if name)


def configure_parser(fit: argparse.ArgumentParser) -> None:
    """Add the ``ctid fit`` arguments to ``fit``."""
    fit.description = ('Estimate grey-box parameters from a CSV file with columns t,u,y (or '
                       'u,y with --ts).')
    fit.add_argument('csv', help='CSV file with a header line')
    fit.add_argument('--model', required=True, help="plant transfer function, e.g. 'K/(T*s+1)'")
    fit.add_argument('--controller', default=None,
                     help='known controller for closed-loop data (u is then the reference r)')
    fit.add_argument('--initial', type=parse_initial, default=None,
                     help='initial values NAME=VALUE,...; missing ones are found automatically')
    fit.add_argument('--bounds', type=parse_bounds, default=None,
                     help='bounds NAME=LOW:HIGH,... (either side may be empty)')
    fit.add_argument('--ts', type=float, default=None, help='sample time if there is no t column')
    fit.add_argument('--input', action='append', default=None,
                     help='input column name (default u); repeat (or separate by commas) for '
                     'the inputs of a model equation, which uses these names')
    fit.add_argument('--output', default='y', help='output column name (default y)')
    fit.add_argument('--estimate-range', type=parse_range, default=None, metavar='FIRST:LAST',
                     help='estimate on these samples only (1-based, inclusive)')
    fit.add_argument('--validate', default=None, metavar='CSV',
                     help='report the fit on this validation file (same columns)')
    fit.add_argument('--validate-range', type=parse_range, default=None, metavar='FIRST:LAST',
                     help='validation samples (of --validate, else of the estimation file)')
    fit.add_argument('--detrend', choices=('none', 'mean', 'initial'), default='none',
                     help='remove the operating point of every range: its means, or its first '
                     'samples (default none: the columns are deviations already)')
    fit.add_argument('--initial-state', choices=INITIAL_STATES, default='zero',
                     help='zero: data start at rest (default); estimate: fit the initial state')
    fit.add_argument('--output-offset', action='store_true',
                     help='estimate a constant offset of the output')
    fit.add_argument('--method', choices=METHODS, default='iv')
    fit.add_argument('--intersample', choices=INTERSAMPLE, default='zoh')
    fit.add_argument('--max-iterations', type=int, default=100)
    fit.add_argument('--json', action='store_true', help='print a JSON object instead of a table')


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid fit``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    inputs = _input_names(arguments.input)
    model = Model(arguments.model, controller=arguments.controller, inputs=inputs,
                  output=arguments.output)
    notes = []
    data = load_csv(arguments.csv, input_column=inputs, output_column=arguments.output,
                    ts=arguments.ts, notes=notes)
    estimation = _select(data, arguments.estimate_range, arguments.detrend, 'estimation')
    result = estimate(model, estimation, arguments.initial or 'auto', bounds=arguments.bounds,
                      method=arguments.method, intersample=arguments.intersample,
                      max_iterations=arguments.max_iterations,
                      initial_state=arguments.initial_state,
                      output_offset=arguments.output_offset)
    # What the resampling of a jittered time column did comes first among the warnings.
    result = replace(result, warnings=notes + list(result.warnings))
    summary = result.to_dict()
    if arguments.validate or arguments.validate_range:
        source = data if arguments.validate is None else load_csv(
            arguments.validate, input_column=inputs, output_column=arguments.output,
            ts=arguments.ts)
        validation = _select(source, arguments.validate_range, arguments.detrend, 'validation')
        summary['validation_fit'] = result.compare(validation)
    if arguments.json:
        print(json.dumps(summary, indent=2, default=json_default))
    else:
        print(format_table(result))
        if 'validation_fit' in summary:
            print(f'validation fit {summary["validation_fit"]:.2f} % '
                  f'({len(validation)} samples)')
    return 0
