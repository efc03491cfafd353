"""
Where an estimate's time goes: the stages of ``estimate`` on each reference system (issue #26).

For every reference system, ``--runs`` seeded records with the starts of ``bench/estimator.py``
(log-uniform within x10 of the truth, the same draws as ``bench user_baseline``) are fitted
twice: once plainly, for the median CPU time of an estimate, and once under ``cProfile``, for
the share of that time each stage of the pipeline (``docs/algorithm.md`` section 1) takes.
A stage's share is its cumulative profiled time over the estimate's; the milliseconds printed
are that share of the plain median, so the profiler's own overhead (which weighs on small
calls) does not inflate them. A stage that calls another includes it (the final check of a
warm start from afar, stage 3b, iterates again). The user's hand-written fit
(:func:`bench.user_baseline.user_fit`) is timed on the same records for the ratio issue #26
bounds at 0.4. The profiled calls per estimate (Python functions and the C functions they call,
as cProfile counts them) are printed too: unlike times they do not depend on the machine's
load, and an estimate's time follows them closely (issue #26's fourth pass).

Run with ``python -m bench stage_costs --runs N`` or ``python -m bench.stage_costs``.
"""

import cProfile
import pstats
import time
from typing import Dict, List, Optional

from bench.estimator import run_on_reference_systems, timed_fits
from bench.user_baseline import ctid_fit, user_fit
from ctid_ros.core.reference_systems import ReferenceSystem
from ctid_ros.estimation import consistency, estimate, stages
import numpy as np

__all__ = ['STAGES', 'main', 'print_table', 'run_system']

# The stages as the pipeline runs them: (label, module, function name).
STAGES = [
    ('warm start', stages, 'warm_start'),
    ("data's guess", stages, 'against_the_data_guess'),
    ('automatic start', stages, 'automatic_start'),
    ('final iteration', stages, 'final_iteration'),
    ('basin check', stages, 'against_the_data_basin'),
    ('symmetry', stages, 'symmetry_restarts'),
    ('look elsewhere', stages, 'look_elsewhere'),
    ('residual test', estimate, '_residual_analysis'),
    ('amplitude test', estimate, '_test_amplitude'),
    ('covariance', estimate, 'covariance'),
    ('consistency', consistency, 'with_consistency'),
]


def _cumulative(stats: pstats.Stats) -> Dict[tuple, float]:
    """Return the cumulative time of every profiled function by (file, name)."""
    return {(filename, name): entry[3] for (filename, _, name), entry in stats.stats.items()}


def _calls(stats: pstats.Stats) -> int:
    """Return the number of calls profiled (recursive ones included)."""
    return sum(entry[1] for entry in stats.stats.values())


def run_system(system: ReferenceSystem, runs: int, seed: int) -> dict:
    """Time ``runs`` estimates plainly and profiled; return each stage's share and time."""
    profile = cProfile.Profile()

    def profiled(system: ReferenceSystem, data, start: np.ndarray) -> np.ndarray:
        profile.enable()
        try:
            return ctid_fit(system, data, start)
        finally:
            profile.disable()

    # Every record is fitted plainly, by the user's fit and under the profiler, in turn.
    fits = {'ctid_ros': ctid_fit, 'user': user_fit, 'profiled': profiled}
    times: Dict[str, List[float]] = {name: [] for name in fits}
    for name, _, seconds in timed_fits(system, runs, seed, fits, time.process_time):
        times[name].append(seconds)
    median = float(np.median(times['ctid_ros']))
    user = float(np.median(times['user']))
    stats = pstats.Stats(profile)
    cumulative = _cumulative(stats)
    whole = cumulative[(estimate.__file__, 'estimate')]
    shares = {label: cumulative.get((module.__file__, name), 0.0) / whole
              for label, module, name in STAGES}
    return {'system': system.name, 'runs': runs, 'median_time': median,
            'user_median_time': user, 'ratio': median / user, 'shares': shares,
            'calls_per_estimate': _calls(stats) / runs,
            'stage_ms': {label: 1e3 * share * median for label, share in shares.items()}}


def print_table(results: List[dict]) -> None:
    """Print one line per system: estimate and user times, ratio, then ms per stage."""
    labels = [label for label, _, _ in STAGES]
    print(f'{"system":<34} {"ctid ms":>7} {"user ms":>7} {"ratio":>5} {"calls":>6} ' +
          ' '.join(f'{label:>{len(label)}}' for label in labels))
    for result in results:
        print(f'{result["system"][:34]:<34} {1e3 * result["median_time"]:>7.2f} '
              f'{1e3 * result["user_median_time"]:>7.2f} {result["ratio"]:>5.2f} '
              f'{result["calls_per_estimate"]:>6.0f} ' +
              ' '.join(f'{result["stage_ms"][label]:>{len(label)}.2f}' for label in labels))


def main(argv: Optional[List[str]] = None) -> List[dict]:
    """Run the benchmark and print its table."""
    return run_on_reference_systems(argv, __doc__.split('\n\n')[0].strip(), 20, run_system,
                                    print_table)


if __name__ == '__main__':
    main()
