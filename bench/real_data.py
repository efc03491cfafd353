"""
The real-data tables of the user guide: the EMPS positioning stage and the hair dryer.

Fits the two published records the way ``docs/user-guide.md`` shows (EMPS: the model equation
from the measured voltage and the friction sign, crude start; dryer: a second order plus dead
time on samples 1-500, validated on 501-1000, means removed per range) and prints the tables
of estimates with the standard deviations the estimator reports now, as markdown. With
``--markdown FILE`` the tables are also written to that file (``make bench`` writes
``bench/results-real-data.md``), so the figures of the documentation come from a run, not from
a hand copy; ``docs/benchmarks.md`` holds that file's text between markers, which
``test/test_readme.py`` compares. The tables hold no timings (those are printed), so a rerun
on any machine writes the same file unless the estimator changed. The published references
are those of ``test/data/README.md``.

Run with ``.venv/bin/python -m bench.real_data [--markdown bench/results-real-data.md]``.
"""

import argparse
from pathlib import Path
import time
from typing import Dict, List, Optional, Tuple

from ctid_ros import Data, Estimate, estimate, Model
from ctid_ros.files.csv_file import load_csv
import numpy as np
from threadpoolctl import threadpool_limits

__all__ = ['dryer_rows', 'emps_rows', 'main']

DATA = Path(__file__).resolve().parent.parent / 'test' / 'data'
EMPS_MODEL = 'M*s**2*q + Fv*s*q = 35.15065*u - Fc*w - off'
EMPS_START = {'M': 50.0, 'Fv': 100.0, 'Fc': 5.0, 'off': 0.0}
# Janot, Gautier, Brunot (2019), IDIM-LS on the training record.
EMPS_PUBLISHED = {'M': (95.11, 0.11), 'Fv': (203.5, 1.1), 'Fc': (20.39, 0.10),
                  'off': (-3.165, 0.044)}
DRYER_MODEL = 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'
DRYER_START = {'K': 1.0, 'T1': 1.0, 'T2': 1.0, 'tau': 0.0}
# test/data/README.md of the DaISy record: three-sample delay, SOPDT by simulation error.
DRYER_REFERENCE = {'K': 0.926, 'T1': 0.263, 'T2': 0.127, 'tau': 0.158}
COMMAND = 'python -m bench real_data'


def _cell(value: float, std: float, published: Optional[float] = None) -> str:
    text = f'{value:.4g} ± {std:.2g}'
    if published is not None:
        text += f' ({100.0 * (value / published - 1.0):+.1f} %)'
    return text


def emps_data(name: str) -> Data:
    """Return voltage u, friction sign w = sign(dq/dt) of the measured position, position q."""
    record = load_csv(DATA / f'{name}.csv.gz', input_column='u', output_column='y')
    sign = np.sign(np.gradient(record.y, record.ts))
    return Data(np.column_stack([record.u, sign]), record.y, record.ts)


def emps_rows() -> Tuple[List[str], List[str]]:
    """Fit both EMPS records; return the table's lines and notes."""
    model = Model(EMPS_MODEL, inputs=('u', 'w'), output='q')
    lines = ['| | M (kg) | Fv (N·s/m) | Fc (N) | offset (N) | simulated position fit |',
             '|---|---|---|---|---|---|',
             '| published IDIM-LS (train) | ' + ' | '.join(
                 f'{value:.4g} ± {std:.2g}' for value, std in EMPS_PUBLISHED.values())
             + ' | — |']
    notes = []
    for name in ('emps_train', 'emps_pulses'):
        data = emps_data(name)
        started = time.perf_counter()
        result = estimate(model, data, dict(EMPS_START))
        seconds = time.perf_counter() - started
        cells = [_cell(result.params[key], result.std[key],
                       None if key == 'off' else EMPS_PUBLISHED[key][0])
                 for key in ('M', 'Fv', 'Fc', 'off')]
        lines.append(f'| ctid_ros, `{name}` | ' + ' | '.join(cells)
                     + f' | {result.compare(data):.1f} % |')
        print(f'{name}: {seconds:.2f} s')
        notes.append(_notes(name, result))
    return lines, notes


def dryer_rows() -> Tuple[List[str], List[str]]:
    """Fit the dryer with the initial state at rest and estimated; return lines and notes."""
    data = load_csv(DATA / 'dryer_daisy.csv')
    estimation = data.segment(0, 500).detrend('mean')
    validation = data.segment(500, 1000).detrend('mean')
    model = Model(DRYER_MODEL)
    names = ('K', 'T1', 'T2', 'tau')
    lines = ['| | K | T1 (s) | T2 (s) | τ (s) | estimation fit | validation fit |',
             '|---|---|---|---|---|---|---|',
             '| reference (data README: 3-sample delay; SOPDT by simulation error) | '
             + ' | '.join(f'{DRYER_REFERENCE[key]:g}' for key in names)
             + ' | 89.0 % | 90.0 % |']
    notes = []
    for initial_state in ('zero', 'estimate'):
        started = time.perf_counter()
        result = estimate(model, estimation, dict(DRYER_START), initial_state=initial_state)
        seconds = time.perf_counter() - started
        cells = [_cell(result.params[key], result.std[key]) for key in names]
        lines.append(f"| ctid_ros, `initial_state='{initial_state}'` | " + ' | '.join(cells)
                     + f' | {result.fit:.1f} % | {result.compare(validation):.1f} % |')
        print(f"dryer, initial_state='{initial_state}': {seconds:.2f} s")
        notes.append(_notes(f"dryer, initial_state='{initial_state}'", result))
    return lines, notes


def _notes(label: str, result: Estimate) -> str:
    verdict = result.residuals.verdict if result.residuals is not None else 'none'
    warnings = '; '.join(result.warnings) or 'none'
    return (f'- {label}: converged {result.converged}; residual: {verdict}; '
            f'warnings: {warnings}')


def tables() -> Dict[str, Tuple[List[str], List[str]]]:
    """Fit both records; return the lines and notes of their tables, by title."""
    with threadpool_limits(limits=1, user_api='blas'):
        return {'EMPS positioning stage': emps_rows(), 'Hair dryer (DaISy 96-006)': dryer_rows()}


def main(argv: Optional[List[str]] = None) -> Dict[str, Tuple[List[str], List[str]]]:
    """Fit the records, print the tables and optionally write them as markdown."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--markdown', default=None, help='also write the tables to this file')
    arguments = parser.parse_args(argv)
    results = tables()
    text = [f'<!-- written by `{COMMAND}`; do not edit by hand -->', '']
    for title, (lines, notes) in results.items():
        text += [f'### {title}', '', *lines, '', *notes, '']
    output = '\n'.join(text)
    print()
    print(output)
    if arguments.markdown:
        Path(arguments.markdown).write_text(output, encoding='utf-8')
    return results


if __name__ == '__main__':
    main()
