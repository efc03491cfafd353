"""
Real records: ctid_ros against a multi-start scipy.optimize.least_squares on the same cost.

For every record x model x start ('auto' and crude starts) the estimator's output-error cost
is compared with the best cost found by ``least_squares`` (trust-region reflective, the
model's bounds, finite-difference Jacobian) from many starts on the very same cost: the
:class:`~ctid_ros.estimation.problem.Problem` ``estimate()`` solves (same initial-state,
output-offset and transient options). Reported per case: the estimator's cost over the best
cost found by anyone (target: at most 1.002), over its start's cost (target: at most 1), its
time, and whether it reported convergence. The records are in ``test/data`` (see its README).

Run with ``.venv/bin/python -m bench.real_records [--starts 24] [--cases exchanger ...]``.
"""

import argparse
from dataclasses import dataclass, field
import gzip
import json
from pathlib import Path
import time
from typing import Dict, List, Optional, Tuple, Union
import warnings

from ctid_ros import Data, estimate, EstimationError, Model
from ctid_ros.estimation.estimate import build_problem
from ctid_ros.estimation.problem import delay_parameter, Problem
from ctid_ros.files.csv_file import load_csv
import numpy as np
from scipy import optimize
from threadpoolctl import threadpool_limits

DATA = Path(__file__).resolve().parent.parent / 'test' / 'data'
FOPDT = 'K*exp(-tau*s)/(T*s + 1)'
SOPDT = 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'
SECOND = 'K/((T1*s + 1)*(T2*s + 1))'
Start = Union[str, Dict[str, float]]


def _table(name: str) -> np.ndarray:
    path = DATA / name
    opener = gzip.open if name.endswith('.gz') else open
    with opener(path, 'rt') as handle:
        return np.loadtxt(handle, delimiter=',', skiprows=1)


def record(name: str) -> Data:
    """Return a record of ``test/data`` as the benchmark fits it."""
    if name == 'exchanger':               # DaISy 97-002, first half, means removed
        table = _table('exchanger.csv.gz')[:2000]
        return Data(table[:, 1], table[:, 2], 1.0).detrend('mean')
    if name == 'exchanger-2':             # its second half
        table = _table('exchanger.csv.gz')[2000:]
        return Data(table[:, 1], table[:, 2], 1.0).detrend('mean')
    if name == 'heating':                 # DaISy 99-001, means removed
        return load_csv(DATA / 'heating_system.csv').detrend('mean')
    if name == 'heating-raw':             # DaISy 99-001 as recorded
        return load_csv(DATA / 'heating_system.csv')
    if name == 'dryer':                   # DaISy 96-006, first half, means removed
        return load_csv(DATA / 'dryer_daisy.csv').segment(0, 500).detrend('mean')
    if name == 'ballbeam':                # DaISy 96-004, means removed
        return load_csv(DATA / 'ballbeam.csv').detrend('mean')
    if name == 'tanks':                   # cascaded tanks, estimation record as recorded
        return load_csv(DATA / 'cascaded_tanks_est.csv')
    if name == 'robot_arm':               # DaISy 96-009, time in samples
        table = _table('robot_arm.csv')
        return Data(table[:, 0], table[:, 1], 1.0).detrend('mean')
    if name == 'wall':                    # DaISy 96-011, inside temperature -> heat flow
        table = _table('thermic_res_wall.csv.gz')
        return Data(table[:, 0], table[:, 2], 1.0).detrend('mean')
    if name == 'cd_player':               # DaISy 96-007, u1 -> y1, time in samples
        table = _table('cd_player_arm.csv.gz')
        return Data(table[:, 0], table[:, 2], 1.0).detrend('mean')
    if name == 'winding':                 # DaISy 97-003, u1 -> y1 (tension), Ts = 0.1 s
        table = _table('winding.csv.gz')
        return Data(table[:, 0], table[:, 5], 0.1).detrend('mean')
    if name == 'flutter':                 # DaISy 96-008, time in samples
        table = _table('flutter.csv')
        return Data(table[:, 0], table[:, 1], 1.0).detrend('mean')
    raise KeyError(name)


@dataclass
class Case:
    """One record, one model, the options of the fit and the starts to try."""

    record: str
    model: str
    starts: List[Start]
    options: Dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        """Return a short description."""
        extras = ' '.join(f'{key}={value}' for key, value in self.options.items()
                          if key != 'bounds')
        return f'{self.record} {self.model} {extras}'.strip()


CRUDE_FOPDT = {'K': 1.0, 'T': 1.0, 'tau': 0.0}
CRUDE_SOPDT = {'K': 1.0, 'T1': 1.0, 'T2': 1.0, 'tau': 0.0}
CRUDE_SECOND = {'K': 1.0, 'T1': 1.0, 'T2': 1.0}
VP = {'initial_state': 'estimate'}
CASES = [
    Case('exchanger', FOPDT, ['auto', CRUDE_FOPDT]),
    Case('exchanger', SOPDT, ['auto', CRUDE_SOPDT]),
    Case('exchanger-2', FOPDT, ['auto', CRUDE_FOPDT]),
    Case('heating', FOPDT, ['auto', CRUDE_FOPDT], VP),
    Case('heating', SOPDT, ['auto', CRUDE_SOPDT], VP),
    Case('heating-raw', SOPDT, ['auto', CRUDE_SOPDT], dict(VP, output_offset=True)),
    Case('dryer', FOPDT, ['auto', CRUDE_FOPDT]),
    Case('dryer', SOPDT, ['auto', CRUDE_SOPDT]),
    Case('tanks', SECOND, ['auto', CRUDE_SECOND, {'K': 1.0, 'T1': 10.0, 'T2': 100.0}],
         dict(VP, output_offset=True)),
    Case('ballbeam', SOPDT, ['auto', CRUDE_SOPDT]),
    Case('robot_arm', '(b1*s + b0)/(s**2 + a1*s + a0)', ['auto']),
    Case('wall', FOPDT, ['auto', CRUDE_FOPDT]),
    Case('wall', SOPDT, ['auto', CRUDE_SOPDT], VP),
    Case('cd_player', 'K*w**2/(s**2 + 2*z*w*s + w**2)', ['auto', {'K': 1.0, 'w': 1.0, 'z': 1.0}]),
    Case('winding', FOPDT, ['auto', CRUDE_FOPDT]),
    Case('flutter', SOPDT, ['auto', CRUDE_SOPDT]),
]


def _residual_function(problem: Problem, penalty: float):
    def residual(theta: np.ndarray) -> np.ndarray:
        coefficients = problem.admissible(theta)
        if coefficients is None:
            return np.full(problem.measured.size, penalty)
        with np.errstate(all='ignore'):
            error = problem.measured - problem.prediction(coefficients)
        return np.where(np.isfinite(error), error, penalty)
    return residual


def _draws(problem: Problem, centre: np.ndarray, count: int, rng: np.random.Generator
           ) -> List[np.ndarray]:
    """Admissible starts: around ``centre`` (x 10^U(-1, 1)), then wide (10^U(-2, 3))."""
    model = problem.model
    delay_index = delay_parameter(model) if isinstance(model, Model) else None
    lower, upper = problem.lower, problem.upper
    starts: List[np.ndarray] = []
    attempts = 0
    while len(starts) < count and attempts < 200 * count:
        attempts += 1
        wide = len(starts) >= count // 2
        if wide:
            sign = np.where(lower < 0.0, rng.choice([-1.0, 1.0], centre.size), 1.0)
            theta = sign * 10.0 ** rng.uniform(-2.0, 3.0, centre.size)
        else:
            theta = centre * 10.0 ** rng.uniform(-1.0, 1.0, centre.size)
        if delay_index is not None:
            low, high = problem.delay_bracket(delay_index, None)
            theta[delay_index] = rng.uniform(low, high)
        theta = np.clip(theta, lower, upper)
        if problem.admissible(theta) is not None:
            starts.append(theta)
    return starts


def reference_fit(problem: Problem, starts: List[np.ndarray]) -> Tuple[np.ndarray, float]:
    """Return the lowest-cost least_squares fit (TRF, bounds, 2-point Jacobian) over starts."""
    penalty = 1e3 * (1.0 + float(np.max(np.abs(problem.measured))))
    residual = _residual_function(problem, penalty)
    margin = 1e-9 * np.maximum(np.abs(np.where(np.isfinite(problem.lower), problem.lower, 0.0)),
                               np.abs(np.where(np.isfinite(problem.upper), problem.upper, 0.0)))
    inside = (problem.lower + np.maximum(margin, 1e-12), problem.upper - np.maximum(margin, 1e-12))
    best_theta, best_cost = None, np.inf
    for start in starts:
        start = np.clip(start, *inside)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            try:
                result = optimize.least_squares(residual, start, method='trf',
                                                bounds=(problem.lower, problem.upper),
                                                x_scale='jac', max_nfev=400)
            except (ValueError, np.linalg.LinAlgError):
                continue
        coefficients = problem.admissible(result.x)
        if coefficients is None:
            continue
        cost = problem.cost(coefficients)
        if cost < best_cost:
            best_theta, best_cost = result.x, cost
    return best_theta, best_cost


def run_case(case: Case, reference_starts: int, seed: int) -> dict:
    """Fit every start with ctid_ros, then least_squares from many starts, and compare."""
    data = record(case.record)
    model = Model(case.model)
    options = dict(case.options)
    outcomes = []
    centre = None
    for start in case.starts:
        problem, _ = build_problem(model, data, **{
            key: value for key, value in options.items() if key != 'transient'})
        start_cost = np.nan
        if isinstance(start, dict):
            coefficients = problem.admissible(model.vector(start))
            start_cost = np.inf if coefficients is None else problem.cost(coefficients)
        began = time.perf_counter()
        try:
            result = estimate(model, data, start, **options)
        except EstimationError as error:
            outcomes.append({'start': str(start), 'error': str(error)})
            continue
        elapsed = time.perf_counter() - began
        theta = model.vector(result.params)
        centre = theta if centre is None else centre
        outcomes.append({'start': 'auto' if start == 'auto' else 'crude' if start in (
            CRUDE_FOPDT, CRUDE_SOPDT, CRUDE_SECOND) else str(start),
            'cost': result.cost, 'start_cost': start_cost, 'time': elapsed,
            'verdict': result.residuals.verdict if result.residuals else '',
            'converged': result.converged, 'stop_reason': result.stop_reason,
            'params': result.params, 'warnings': result.warnings})
    problem, _ = build_problem(model, data, **options)
    rng = np.random.default_rng(seed)
    if centre is None:
        centre = np.ones(len(model.parameters))
    crude = [model.vector(start) for start in case.starts if isinstance(start, dict)]
    own = [model.vector(outcome['params']) for outcome in outcomes if 'params' in outcome]
    starts = crude + own + _draws(problem, centre, reference_starts, rng)
    began = time.perf_counter()
    theta, cost = reference_fit(problem, starts)
    reference_time = time.perf_counter() - began
    best = min([cost] + [outcome.get('cost', np.inf) for outcome in outcomes])
    for outcome in outcomes:
        if 'cost' in outcome:
            outcome['ratio_to_best'] = outcome['cost'] / best
            outcome['ratio_to_start'] = outcome['cost'] / outcome['start_cost'] \
                if np.isfinite(outcome['start_cost']) else None
    return {'case': case.label, 'parameters': list(model.parameters),
            'least_squares': {'cost': cost, 'ratio_to_best': cost / best,
                              'params': None if theta is None else model.as_dict(theta),
                              'time': reference_time, 'starts': len(starts)},
            'ctid': outcomes}


def print_results(results: List[dict]) -> None:
    """Print one line per case and start."""
    print(f'{"case":<62} {"start":<8} {"cost/best":>10} {"cost/start":>10} '
          f'{"time s":>7} {"conv":>5}  stop reason')
    for result in results:
        for outcome in result['ctid']:
            if 'error' in outcome:
                print(f'{result["case"]:<62} {outcome["start"]:<8} error: {outcome["error"]}')
                continue
            to_start = outcome['ratio_to_start']
            print(f'{result["case"]:<62} {outcome["start"]:<8} '
                  f'{outcome["ratio_to_best"]:>10.5f} '
                  f'{"" if to_start is None else f"{to_start:.4f}":>10} '
                  f'{outcome["time"]:>7.2f} {"yes" if outcome["converged"] else "no":>5}  '
                  f'{outcome["stop_reason"]}')
        reference = result['least_squares']
        print(f'{result["case"]:<62} {"l-sq":<8} {reference["ratio_to_best"]:>10.5f} '
              f'{"":>10} {reference["time"]:>7.2f}        ({reference["starts"]} starts)')


def main(argv: Optional[List[str]] = None) -> List[dict]:
    """Run the real-record comparison and print its table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--starts', type=int, default=24,
                        help='random least_squares starts per case (default 24)')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--cases', nargs='*', default=None,
                        help='records to run (default: all of ' + ', '.join(
                            sorted({case.record for case in CASES})) + ')')
    parser.add_argument('--json', default=None, help='also write the results to this file')
    arguments = parser.parse_args(argv)
    results = []
    with threadpool_limits(limits=1, user_api='blas'):
        for case in CASES:
            if arguments.cases and case.record not in arguments.cases:
                continue
            results.append(run_case(case, arguments.starts, arguments.seed))
            print_results(results[-1:])
    print()
    print_results(results)
    if arguments.json:
        with open(arguments.json, 'w') as handle:
            json.dump(results, handle, indent=2, default=float)
    return results


if __name__ == '__main__':
    main()
