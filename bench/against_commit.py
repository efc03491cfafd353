"""
The estimator's time per record against an earlier commit, on the same records and starts.

Issue #13 asks that nothing gets slower than at b97b549 by more than 10 %. The in-run ratios of
``bench/estimator.py`` compare with ``least_squares``, which shares the simulator and so moves
with it; this benchmark times ``estimate`` alone in both source trees. The earlier commit is
unpacked with ``git archive`` into a temporary directory (nothing is checked out in this
repository); each tree runs in its own process (``PYTHONPATH`` at the tree), on the 30 seeded
records and ×10 starts per reference system of ``bench/estimator.py`` that both trees know,
each estimate timed in CPU time, best of 3. The trees alternate ``--rounds`` times and the
median of the rounds is reported with the ratio now/then.

Run with ``.venv/bin/python -m bench.against_commit [--commit REV] [--rounds N]``.
"""

import argparse
import json
import os
from pathlib import Path
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Dict, List, Optional

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_COMMIT = 'b97b549'
RECORDS = 30
REPEATS = 3


def child(records: int) -> Dict[str, float]:
    """Time ``estimate`` on every reference system of the tree on ``sys.path``; return ms."""
    import numpy as np

    from bench.estimator import draw_start
    from ctid_ros import estimate
    try:
        from ctid_ros.core import reference_systems
    except ImportError:         # the layout before the subpackages
        from ctid_ros import reference_systems

    medians = {}
    for factory in reference_systems.ALL:
        system = factory()
        rng = np.random.default_rng(1)
        times = []
        for run in range(records):
            data = system.data(seed=1000 + run)
            start = system.model.as_dict(draw_start(system, rng))
            best = float('inf')
            for _ in range(REPEATS):
                began = time.process_time()
                estimate(system.model, data, start, bounds=system.bounds)
                best = min(best, time.process_time() - began)
            times.append(best)
        medians[factory.__name__] = 1e3 * statistics.median(times)
    return medians


def _run_tree(tree: Path, records: int) -> Dict[str, float]:
    environment = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS='1',
                       OMP_NUM_THREADS='1')
    # This file runs as a script, so the earlier tree, which may not have it, is timed too.
    output = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), '--child', '--records', str(records)],
        cwd=tree, env=environment, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def _unpack(commit: str, directory: Path) -> Path:
    # git's own archive of its own commit, unpacked by tar (tarfile's extraction filters,
    # which a trusted archive does not need, are missing from early Python 3.11 releases).
    archive = subprocess.Popen(['git', '-C', str(ROOT), 'archive', '--format=tar',
                                '--prefix=tree/', commit], stdout=subprocess.PIPE)
    subprocess.run(['tar', '-x', '-C', str(directory)], stdin=archive.stdout, check=True)
    archive.stdout.close()
    if archive.wait() != 0:
        raise subprocess.CalledProcessError(archive.returncode, 'git archive')
    return directory / 'tree'


def main(argv: Optional[List[str]] = None) -> Dict[str, object]:
    """Run the comparison; print a table and return the medians."""
    parser = argparse.ArgumentParser(prog='python -m bench.against_commit',
                                     description=__doc__.split('\n\n')[1])
    parser.add_argument('--commit', default=DEFAULT_COMMIT)
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--records', type=int, default=RECORDS)
    parser.add_argument('--child', action='store_true', help=argparse.SUPPRESS)
    arguments = parser.parse_args(argv)
    if arguments.child:
        print(json.dumps(child(arguments.records)))
        return {}
    known = subprocess.run(['git', '-C', str(ROOT), 'cat-file', '-e',
                            f'{arguments.commit}^{{commit}}'], capture_output=True)
    if known.returncode != 0:
        print(f'against_commit: skipped ({arguments.commit} is not a commit of this checkout; '
              'a shallow clone lacks it)')
        return {}
    with tempfile.TemporaryDirectory() as directory:
        then_tree = _unpack(arguments.commit, Path(directory))
        rounds = [(_run_tree(then_tree, arguments.records), _run_tree(ROOT, arguments.records))
                  for _ in range(arguments.rounds)]
    load = os.getloadavg()[0]
    print(f'estimate() CPU ms per record (median of {arguments.records} records, best of '
          f'{REPEATS}; median of {arguments.rounds} alternating rounds; load {load:.1f})')
    print(f'{"system":<26}{arguments.commit:>10}{"now":>10}{"now/then":>10}')
    results: Dict[str, object] = {}
    for name in rounds[0][0]:
        if name not in rounds[0][1]:
            continue
        then = statistics.median(pair[0][name] for pair in rounds)
        now = statistics.median(pair[1][name] for pair in rounds)
        results[name] = {'then_ms': then, 'now_ms': now, 'ratio': now / then}
        print(f'{name:<26}{then:>10.2f}{now:>10.2f}{now / then:>10.2f}')
    return results


if __name__ == '__main__':
    main()
