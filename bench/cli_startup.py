"""
Start-up time of the ``ctid`` command: ``ctid --help`` and ``ctid fit --help``.

Each command runs in a fresh process (the installed ``ctid`` script next to this interpreter,
else ``python -m ctid_ros.cli.main``) several times, interleaved with the baseline ``python -c
pass`` measured in the same run; the medians are reported, and the help is expected within
0.5 s. For comparison the imports a real ``ctid fit`` needs (its module: sympy, scipy, the
estimator) are timed the same way: that is what ``--help`` used to cost.

Run with ``.venv/bin/python -m bench.cli_startup [--runs N]``.
"""

import argparse
from pathlib import Path
import statistics
import subprocess
import sys
import time
from typing import Dict, List, Optional

LIMIT = 0.5


def _ctid() -> List[str]:
    script = Path(sys.executable).parent / 'ctid'
    return [str(script)] if script.exists() else [sys.executable, '-m', 'ctid_ros.cli.main']


def commands() -> Dict[str, List[str]]:
    """Return the command lines timed, by name; the first is the baseline."""
    return {
        'python -c pass (baseline)': [sys.executable, '-c', 'pass'],
        'ctid --help': _ctid() + ['--help'],
        'ctid fit --help': _ctid() + ['fit', '--help'],
        'import ctid_ros.cli.fit (what fit --help used to load)': [
            sys.executable, '-c', 'import ctid_ros.cli.fit'],
    }


def _once(command: List[str]) -> float:
    started = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - started


def run(runs: int) -> Dict[str, float]:
    """Return the median wall time (s) of each command over ``runs`` interleaved runs."""
    lines = commands()
    for command in lines.values():     # warm the file cache and the bytecode once
        _once(command)
    times: Dict[str, List[float]] = {name: [] for name in lines}
    for _ in range(runs):
        for name, command in lines.items():
            times[name].append(_once(command))
    return {name: statistics.median(values) for name, values in times.items()}


def main(argv: Optional[List[str]] = None) -> Dict[str, float]:
    """Run the benchmark and print its summary."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--runs', type=int, default=9, help='runs per command (default 9)')
    arguments = parser.parse_args(argv)
    medians = run(arguments.runs)
    baseline = next(iter(medians.values()))
    print(f'cli start-up: median of {arguments.runs} runs each, interleaved')
    for name, seconds in medians.items():
        verdict = ''
        if name.endswith('--help'):
            verdict = '  ok' if seconds <= LIMIT else f'  OVER {LIMIT:g} s'
        print(f'  {name:<56} {seconds:6.3f} s  ({seconds - baseline:+.3f} s over the '
              f'baseline){verdict}')
    return medians


if __name__ == '__main__':
    main()
