"""
From data to a decision, checked against the truth: ``compare`` and ``tune`` over fresh noise.

Monte Carlo runs (seeded, fresh noise each) on reference systems with known parameters:

* ``compare``: FOPDT data (``first_order_dead_time``) with an FOPDT and an SOPDT candidate, and
  two-lag data (``two_lags_dead_time``) with the same candidates: how often the true structure
  is recommended;
* ``tune``: the PI of :func:`ctid_ros.design.tune.tune` from the SOPDT estimate, applied to
  the true plant: how often the true gain margin, phase margin and Ms lie inside the reported
  95 % band, the worst true Ms, and the step IAE against SIMC's PI tuned on the truth.

Run with ``.venv/bin/python -m bench.design [--runs 40]``; the figures of
``docs/compare-and-tune.md`` come from this run.
"""

import argparse
import json
from typing import List, Optional

from ctid_ros.core.reference_systems import first_order_dead_time, two_lags_dead_time
from ctid_ros.design.margins import (closed_loop_step, integral_absolute_error, loop_margins,
                                     Plant)
from ctid_ros.design.tune import reduce, simc, tune
from ctid_ros.estimation.compare import compare
from ctid_ros.estimation.estimate import estimate
import numpy as np

FOPDT = 'K*exp(-tau*s)/(T*s + 1)'
SOPDT = 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'
# Seeds start here, apart from the ones the tests use.
FIRST_SEED = 100
HORIZON = 40.0


def main(argv: Optional[List[str]] = None) -> dict:
    """Run the benchmark and print (and optionally write) its figures."""
    parser = argparse.ArgumentParser(prog='python -m bench.design')
    parser.add_argument('--runs', type=int, default=40)
    parser.add_argument('--json', default=None, help='write the figures to this file')
    arguments = parser.parse_args(argv)
    seeds = range(FIRST_SEED, FIRST_SEED + arguments.runs)
    right = {FOPDT: 0, SOPDT: 0}
    for truth, system in ((FOPDT, first_order_dead_time()), (SOPDT, two_lags_dead_time())):
        for seed in seeds:
            right[truth] += compare([FOPDT, SOPDT], system.data(seed)).recommended.model \
                .expression == truth
    system = two_lags_dead_time()
    plant = Plant.from_model(system.model, system.truth)
    times, best, _ = closed_loop_step(plant, simc(reduce(plant, 'PI'), 'PI'), HORIZON)
    best_iae = integral_absolute_error(times, best)
    inside = {'gain_db': 0, 'phase_deg': 0, 'ms': 0}
    true_ms, ratios = [], []
    for seed in seeds:
        tuning = tune(estimate(system.model, system.data(seed)), 'PI', seed=seed)
        margins = loop_margins(plant, tuning.gains)
        true_ms.append(margins.ms if margins.stable else np.inf)
        for name in inside:
            low, high = tuning.band[name]
            inside[name] += (low is None or low <= getattr(margins, name)) and \
                (high is None or getattr(margins, name) <= high)
        _, output, _ = closed_loop_step(plant, tuning.gains, HORIZON)
        ratios.append(integral_absolute_error(times, output) / best_iae)
    runs = arguments.runs
    figures = {
        'runs': runs,
        'compare_recommends_truth': {'fopdt_data': right[FOPDT] / runs,
                                     'sopdt_data': right[SOPDT] / runs},
        'tune_band_coverage': {name: count / runs for name, count in inside.items()},
        'tune_true_ms_worst': float(np.max(true_ms)),
        'tune_iae_ratio': {'median': float(np.median(ratios)), 'worst': float(np.max(ratios))},
    }
    print(f'design benchmark, {runs} runs (seeds {FIRST_SEED}-{FIRST_SEED + runs - 1}):')
    print(f'  compare recommends the true structure: FOPDT data '
          f'{figures["compare_recommends_truth"]["fopdt_data"]:.0%}, SOPDT data '
          f'{figures["compare_recommends_truth"]["sopdt_data"]:.0%}')
    coverage = ', '.join(f'{name} {value:.1%}'
                         for name, value in figures['tune_band_coverage'].items())
    print(f'  tune: true margins inside the 95 % band: {coverage}')
    print(f'  tune: worst true Ms {figures["tune_true_ms_worst"]:.3f}; IAE / SIMC on the truth '
          f'median {figures["tune_iae_ratio"]["median"]:.3f}, worst '
          f'{figures["tune_iae_ratio"]["worst"]:.3f}')
    if arguments.json:
        with open(arguments.json, 'w', encoding='utf-8') as stream:
            json.dump(figures, stream, indent=2)
    return figures


if __name__ == '__main__':
    main()
