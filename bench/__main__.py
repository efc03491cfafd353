"""
``make bench``: every benchmark, each against a baseline measured in the same run.

``python -m bench`` runs them all in the order below; ``python -m bench NAME...`` runs the named
ones (extra arguments such as ``--runs N`` go to the estimator, user-baseline, stage-cost,
cli start-up and replay start-up benchmarks). A benchmark that needs
rclpy is skipped with a message where rclpy is not installed.
"""

import argparse
import importlib
import sys
from typing import Callable, Dict, List, Optional

# name -> (module, arguments of its main); the JSON results land next to the benchmarks.
BENCHMARKS: Dict[str, List[str]] = {
    'cli_startup': [],
    'model_text': ['--json', 'bench/results-model-text.json'],
    'estimator': ['--runs', '100', '--json', 'bench/results-estimator.json'],
    'user_baseline': ['--json', 'bench/results-user-baseline.json'],
    'stage_costs': ['--json', 'bench/results-stage-costs.json'],
    'against_commit': [],
    'stamps': [],
    'coverage': ['--runs', '200', '--json', 'bench/results-coverage.json'],
    'real_records': ['--json', 'bench/results-real-records.json'],
    'real_data': ['--markdown', 'bench/results-real-data.md'],
    'hostile_files': [],
    'node_throughput': [],
    'node_storm': ['--json', 'bench/results-node-storm.json'],
    'fleet': [],
    'replay_startup': [],
    'alarm': ['--json', 'bench/results-alarm.json'],
    'memory': ['--minutes', '20', '--json', 'bench/results-memory.json'],
    'design': ['--runs', '40', '--json', 'bench/results-design.json'],
}


# The benchmarks that take the extra arguments of the command line.
_EXTRA_ARGUMENTS = ('estimator', 'user_baseline', 'stage_costs', 'cli_startup',
                    'replay_startup')


def _runner(name: str) -> Callable[[List[str]], object]:
    return importlib.import_module(f'bench.{name}').main


def main(argv: Optional[List[str]] = None) -> int:
    """Run the selected benchmarks (all by default)."""
    parser = argparse.ArgumentParser(prog='python -m bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('names', nargs='*', metavar='NAME',
                        help=f'subset of: {", ".join(BENCHMARKS)} (default all)')
    arguments, extra = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    unknown = sorted(set(arguments.names) - set(BENCHMARKS))
    if unknown:
        parser.error(f'unknown benchmark(s) {", ".join(unknown)}; choose from '
                     f'{", ".join(BENCHMARKS)}')
    for name in arguments.names or list(BENCHMARKS):
        try:
            run = _runner(name)
        except ImportError as error:       # rclpy missing: the other benchmarks still stand
            print(f'{name} benchmark skipped: {error}')
            continue
        run(BENCHMARKS[name] + (extra if name in _EXTRA_ARGUMENTS else []))
    return 0


if __name__ == '__main__':
    sys.exit(main())
