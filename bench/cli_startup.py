"""
Start-up and whole-command time of ``ctid`` against what a user would run instead (issue #26).

Every command runs as a fresh process, several times, interleaved with its baseline in the same
run; the medians of wall and CPU time (user + system of the child, which a busy machine inflates
less) and their ratios are reported, the limits apply to wall time:

* ``ctid --help`` and ``ctid_node --help`` against ``python -c "import numpy"`` (limit 2x);
* ``ctid fit`` of a 2000-sample CSV (first order plus dead time, seeded noise) against the
  hand-written scipy script :mod:`bench.user_fit_script` on the same file (limit 0.7x);
* for reference ``python -c pass``, ``ctid fit --help`` and ``ctid fit`` with the model store
  switched off (``CTID_CACHE_DIR=''``: the model derived with sympy, as on the first run of a
  model).

The processes run as an installed ctid runs for its user (:mod:`bench.fresh_process`): bytecode
compiled and the model stored by the warm-up run.

The installed ``ctid`` and ``ctid_node`` scripts next to this interpreter are used, else
``python -m``. Run with ``python -m bench cli_startup [--runs N]``.
"""

import argparse
from pathlib import Path
import sys
import tempfile
from typing import Dict, List, Optional, Tuple

from bench.fresh_process import interleaved_medians, MODEL_STORE, user_environment

__all__ = ['LIMITS', 'commands', 'main', 'run', 'write_record']

MODEL = 'K*exp(-tau*s)/(T*s + 1)'
# (command, baseline, largest ratio command / baseline) that issue #26 accepts.
LIMITS: List[Tuple[str, str, float]] = [
    ('ctid --help', 'python -c "import numpy"', 2.0),
    ('ctid_node --help', 'python -c "import numpy"', 2.0),
    ('ctid fit (2000 samples)', 'hand-written scipy fit script', 0.7),
]


def _script(name: str, module: str) -> List[str]:
    script = Path(sys.executable).parent / name
    return [str(script)] if script.exists() else [sys.executable, '-m', module]


def write_record(path: Path, samples: int = 2000) -> None:
    """Write ``t,u,y`` of the first-order model with dead time, 10 % output noise, seeded."""
    import numpy as np
    from ctid_ros.core.excitation import prbs
    from ctid_ros.core.model import Model

    ts = 0.1
    u = np.resize(prbs(8, 10), samples)
    y = Model(MODEL).simulate({'K': 2.0, 'T': 5.0, 'tau': 1.234}, u, ts)
    y = y + 0.1 * np.std(y) * np.random.default_rng(0).standard_normal(samples)
    np.savetxt(path, np.column_stack([ts * np.arange(samples), u, y]), delimiter=',',
               header='t,u,y', comments='')


def commands(csv: Path) -> Dict[str, List[str]]:
    """Return the command lines timed, by name."""
    ctid = _script('ctid', 'ctid_ros.cli.main')
    return {
        'python -c pass': [sys.executable, '-c', 'pass'],
        'python -c "import numpy"': [sys.executable, '-c', 'import numpy'],
        'ctid --help': ctid + ['--help'],
        'ctid fit --help': ctid + ['fit', '--help'],
        'ctid_node --help': _script('ctid_node', 'ctid_ros.ros.launcher') + ['--help'],
        'ctid fit (2000 samples)': ctid + ['fit', str(csv), '--model', MODEL, '--time', 't',
                                           '--input', 'u', '--output', 'y'],
        'ctid fit, model not stored': ['env', f'{MODEL_STORE}='] + ctid + [
            'fit', str(csv), '--model', MODEL, '--time', 't', '--input', 'u', '--output', 'y'],
        'hand-written scipy fit script': [
            sys.executable, '-m', 'bench.user_fit_script', str(csv), '1', '1', '0.5'],
    }


def run(runs: int, csv: Path) -> Dict[str, Tuple[float, float]]:
    """Return the median (wall, CPU) seconds of each command over ``runs`` interleaved runs."""
    lines = commands(csv)
    return interleaved_medians(lines, runs)


def main(argv: Optional[List[str]] = None) -> Dict[str, float]:
    """Run the benchmark, print its summary and return the median wall times."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--runs', type=int, default=7, help='runs per command (default 7)')
    arguments = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as directory:
        csv = Path(directory) / 'first_order_dead_time.csv'
        with user_environment(Path(directory)):
            write_record(csv)
            medians = run(arguments.runs, csv)
    print(f'cli start-up: median wall (and CPU) time of {arguments.runs} fresh processes each, '
          'interleaved')
    for name, (wall, cpu) in medians.items():
        print(f'  {name:<32} {wall:6.3f} s  (CPU {cpu:6.3f} s)')
    first = 'ctid fit, model not stored'
    for name, baseline, limit in LIMITS + [(first, 'hand-written scipy fit script', None)]:
        ratio = medians[name][0] / medians[baseline][0]
        verdict = '(first run of a model)' if limit is None else \
            'ok' if ratio <= limit else f'OVER {limit:g}x'
        print(f'  {name:<32} / {baseline:<30} {ratio:5.2f}  {verdict}  '
              f'(CPU {medians[name][1] / medians[baseline][1]:5.2f})')
    return {name: wall for name, (wall, _) in medians.items()}


if __name__ == '__main__':
    main()
