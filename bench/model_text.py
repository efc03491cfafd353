"""
Model-text benchmark: how long hostile model text takes to be answered (issue #16).

Every text of the seeded fuzz corpus of ``test/model_texts.py`` (the one the fuzz test draws
from, here larger) and the issue's own examples is given to ``Model(text)``,
``Model(text, controller='20 + 10/s')`` and, as a controller, to
``Model('1/(m*s**2 + d*s + k)', controller=text)``. Each call is timed from a cold sympy cache
(a new text on the ROS graph finds nothing cached) until it returns a model or raises a
:class:`~ctid_ros.errors.CtidError`. Reported: calls, accepted and rejected, maximum, 99th
percentile and median answer time, the number of answers over one second (must be 0), the
slowest texts, and any exception that is not a CtidError (must be none).
"""

import argparse
import json
from pathlib import Path
import sys
import time
from typing import List, Optional, Tuple

from ctid_ros import CtidError, Model
import numpy as np
from sympy.core.cache import clear_cache

__all__ = ['LIMIT', 'main', 'run']

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'test'))
from model_texts import CONTROLLER_PLANT, corpus, ISSUE_EXAMPLES  # noqa: E402, I100

LIMIT = 1.0             # seconds: the acceptance bound of issue #16
PI_CONTROLLER = '20 + 10/s'

Call = Tuple[str, Optional[str]]


def calls(seed: int, count: int) -> List[Tuple[str, Call]]:
    """Return ``(kind, (plant, controller))`` of every call of the benchmark."""
    result = [('issue', example) for example in ISSUE_EXAMPLES]
    for kind, text in corpus(seed, count):
        result += [(kind, (text, None)), (kind, (text, PI_CONTROLLER)),
                   (kind + ' as controller', (CONTROLLER_PLANT, text))]
    return result


def run(seed: int = 16, count: int = 1200) -> dict:
    """Time every call; return the summary (times in seconds)."""
    Model('K/(T*s + 1)', controller=PI_CONTROLLER)       # imports and first compilation
    times, slowest, crashes, accepted = [], [], [], 0
    for kind, (plant, controller) in calls(seed, count):
        clear_cache()
        start = time.perf_counter()
        try:
            Model(plant, controller=controller)
            accepted += 1
        except CtidError:
            pass
        except Exception as error:      # reported, not raised: the benchmark sees them all
            crashes.append(f'{kind}: {plant[:60]!r} {controller!r}: {type(error).__name__}')
        elapsed = time.perf_counter() - start
        times.append(elapsed)
        slowest.append((elapsed, kind, plant[:70], controller))
    times = np.array(times)
    slowest.sort(reverse=True)
    return {
        'texts': count + len(ISSUE_EXAMPLES), 'calls': int(times.size), 'accepted': accepted,
        'rejected': int(times.size) - accepted - len(crashes), 'crashes': crashes,
        'max_s': float(times.max()), 'p99_s': float(np.percentile(times, 99)),
        'median_s': float(np.median(times)), 'total_s': float(times.sum()),
        'over_limit': int(np.sum(times > LIMIT)),
        'slowest': [{'seconds': round(t, 4), 'kind': k, 'plant': p, 'controller': c}
                    for t, k, p, c in slowest[:8]],
    }


def main(argv=None) -> dict:
    """Run the benchmark and print its summary."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--seed', type=int, default=16)
    parser.add_argument('--count', type=int, default=1200, help='corpus texts (default 1200)')
    parser.add_argument('--json', default=None, help='also write the summary to this file')
    arguments = parser.parse_args(argv)
    summary = run(arguments.seed, arguments.count)
    print(f"model text: {summary['calls']} calls on {summary['texts']} texts "
          f"({summary['accepted']} accepted, {summary['rejected']} rejected), answer time "
          f"max {summary['max_s']:.3f} s, p99 {summary['p99_s']:.3f} s, median "
          f"{1000 * summary['median_s']:.1f} ms; over {LIMIT:g} s: {summary['over_limit']}; "
          f"not a CtidError: {len(summary['crashes'])}")
    for row in summary['slowest']:
        print(f"  {row['seconds']:.3f} s  {row['kind']:<24} {row['plant']!r} "
              f"controller={row['controller']!r}")
    for crash in summary['crashes']:
        print(f'  NOT A CtidError: {crash}')
    if arguments.json:
        with open(arguments.json, 'w') as handle:
            json.dump(summary, handle, indent=2)
    return summary


if __name__ == '__main__':
    main()
