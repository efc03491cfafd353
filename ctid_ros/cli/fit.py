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
from typing import List, Optional, Tuple

from ctid_ros.cli.report import format_table, json_default
from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import DataError
from ctid_ros.estimation.estimate import estimate
from ctid_ros.files.csv_file import load_csv

__all__ = ['run']


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
