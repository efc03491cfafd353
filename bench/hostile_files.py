"""
Worst time and peak memory of the file readers over a corpus of hostile and broken files.

The corpus is that of the fuzz tests (``test/hostile_corpus.py``): resource bombs (MCAP chunks
declaring 2 GiB or expanding 30 000 times, frames lying about their size, a YAML billion laughs,
5000 nested brackets, 2 GiB sparse files, ``/dev/zero``), broken files (truncated, zeroed,
random bytes, non-UTF-8, truncated gzip, a wrong schema) and bags whose metadata.yaml disagrees
with their storage, plus the issue's 65 KB MCAP whose chunk really expands to 2 GiB. Each case
is read as ``ctid`` reads it (``load_params_file``, ``load_csv``, ``BagReader`` and every
message of the plant topics) and must be answered, by a result or a one-line error, within
1 s and 64 MiB of Python allocations (tracemalloc); the process's peak RSS is reported too.

Run with ``.venv/bin/python -m bench.hostile_files [--verbose]``.
"""

import argparse
from pathlib import Path
import random
import resource
import sys
import tempfile
import time
import tracemalloc
from typing import Callable, Dict, List, Tuple

TEST = Path(__file__).resolve().parents[1] / 'test'
TIME_LIMIT = 1.0
MEMORY_LIMIT = 64 << 20


def _corpus(root: Path) -> List[Tuple[str, str, Callable[[], object]]]:
    """Return (kind, case, reader call) for every file of the corpus, written under ``root``."""
    sys.path.insert(0, str(TEST))
    import hostile_corpus
    from replay_fixtures import DELAY, float_records, params_file, simulate, write_bag

    from ctid_ros.files.bag_reader import BagReader
    from ctid_ros.files.csv_file import load_csv
    from ctid_ros.streaming.params_file import load_params_file

    rng = random.Random(16)
    u, y = simulate(DELAY, 4.0)
    records = float_records(u, y)
    good_csv = ('t,u,y\n' + ''.join(f'{0.01 * k:.2f},{u_k!r},{y_k!r}\n' for k, (u_k, y_k)
                                    in enumerate(zip(u.tolist(), y.tolist())))).encode()
    (root / 'bag').mkdir()
    good_bag = write_bag(root / 'bag', records, 'sqlite3')
    good_mcap = write_bag(root, records, 'mcap-file')
    good_params_path = params_file(root, DELAY)
    good_params = good_params_path.read_bytes()
    # The readers' one-time costs (sympy's import and the model's derivation on the first
    # valid configuration, the bag plugins) are paid here, not by whichever case comes first.
    load_params_file(good_params_path)

    def read_bag(path: Path) -> int:
        with BagReader(path) as bag:
            topics = [name for name in map(bag.topic_name, ('/plant/u', '/plant/y')) if name]
            return sum(1 for _ in bag.messages(topics)) if topics else 0

    cases = []
    for directory, kind in ((root / 'params', 'params'), (root / 'csv', 'csv'),
                            (root / 'bags', 'bag')):
        directory.mkdir()
    for name, path in hostile_corpus.params_cases(root / 'params', good_params, rng).items():
        cases.append(('params', name, lambda path=path: load_params_file(path)))
    for name, path in hostile_corpus.csv_cases(root / 'csv', good_csv, rng).items():
        cases.append(('csv', name, lambda path=path: load_csv(path)))
    bags = hostile_corpus.bag_cases(root / 'bags', good_bag, good_mcap, rng)
    bags.update(hostile_corpus.mcap_bombs(root / 'bags', heavy=True))
    real = TEST / 'data' / 'bags'
    bags.update({f'rosbag2 {path.name}': path for path in sorted(real.iterdir())})
    for name, path in bags.items():
        cases.append(('bag', name, lambda path=path: read_bag(path)))
    for name, path in hostile_corpus.devices().items():
        cases.append(('params', name, lambda path=path: load_params_file(path)))
        cases.append(('csv', name, lambda path=path: load_csv(path)))
        cases.append(('bag', name, lambda path=path: read_bag(path)))
    return cases


def run(verbose: bool = False) -> Dict[str, object]:
    """Read every case once; return the worst time, the worst memory and the failures."""
    from ctid_ros.errors import CtidError

    rows = []
    with tempfile.TemporaryDirectory() as directory:
        cases = _corpus(Path(directory))
        for kind, name, call in cases:
            tracemalloc.start()
            started = time.perf_counter()
            try:
                result = call()
                answer = f'ok ({type(result).__name__})'
            except CtidError as error:
                answer = f'{type(error).__name__}: {str(error)}'
            except Exception as error:       # a bug: reported as such
                answer = f'UNEXPECTED {type(error).__name__}: {error}'
            elapsed = time.perf_counter() - started
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            rows.append((kind, name, elapsed, peak, answer))
            if verbose:
                print(f'{kind:6} {name[:36]:36} {elapsed:7.3f} s {peak / 2 ** 20:7.1f} MiB  '
                      f'{answer[:110]}')
    failures = [row for row in rows if row[2] > TIME_LIMIT or row[3] > MEMORY_LIMIT
                or row[4].startswith('UNEXPECTED')]
    slowest = max(rows, key=lambda row: row[2])
    largest = max(rows, key=lambda row: row[3])
    return {'cases': len(rows), 'slowest': slowest, 'largest': largest, 'failures': failures,
            'rss': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main(argv=None) -> int:
    """Print the worst case of the corpus; exit 1 if a case exceeds its limits."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--verbose', action='store_true', help='print every case')
    arguments = parser.parse_args(argv)
    summary = run(arguments.verbose)
    kind, name, elapsed, _, answer = summary['slowest']
    print(f'hostile files: {summary["cases"]} cases; slowest {elapsed:.3f} s ({kind} {name}: '
          f'{answer[:80]})')
    kind, name, _, peak, answer = summary['largest']
    print(f'hostile files: largest Python allocation {peak / 2 ** 20:.1f} MiB ({kind} {name}); '
          f'process peak RSS {summary["rss"]:.0f} MiB')
    for kind, name, elapsed, peak, answer in summary['failures']:
        print(f'hostile files: OVER LIMIT {kind} {name}: {elapsed:.3f} s, '
              f'{peak / 2 ** 20:.1f} MiB: {answer[:200]}')
    return 1 if summary['failures'] else 0


if __name__ == '__main__':
    sys.exit(main())
