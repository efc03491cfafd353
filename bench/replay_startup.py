"""
``ctid replay --json`` of a long bag against a bare rosbags read, both fresh processes (#26).

The 10-minute 500 Hz ``sensor_msgs/JointState`` bag of ``bench/fleet.py`` (300 000 messages,
written once into the work directory) is estimated by ``ctid replay BAG --params-file P
--json`` and read by :mod:`bench.bare_bag_read` (``AnyReader``, ``deserialize`` of every
message, two fields kept), interleaved, several times each. Reported: the median wall time
and the median CPU time (user + system of the child, which a busy machine inflates less) of
each, and their ratios; issue #26 asks for a wall-time ratio of at most 0.5. Both run as an
installed ctid runs for its user (:mod:`bench.fresh_process`): bytecode compiled and the model
stored by the warm-up run.

Run with ``python -m bench replay_startup [--runs N] [--work DIR]``.
"""

import argparse
from pathlib import Path
import sys
import tempfile
from typing import Dict, List, Optional, Tuple

from bench.fresh_process import interleaved_medians, user_environment

__all__ = ['LIMIT', 'main', 'run']

LIMIT = 0.5
_REPOSITORY = Path(__file__).resolve().parent.parent


def run(runs: int, work: Path) -> Dict[str, Tuple[float, float]]:
    """Return the median (wall, CPU) seconds of each command over ``runs`` interleaved runs."""
    sys.path.insert(0, str(_REPOSITORY / 'test'))
    from bench.fleet import _long_bag

    bag, params = _long_bag(work, 10.0)
    ctid = Path(sys.executable).parent / 'ctid'
    ctid_command = [str(ctid)] if ctid.exists() else [sys.executable, '-m', 'ctid_ros.cli.main']
    lines = {
        'ctid replay --json': ctid_command + ['replay', str(bag), '--params-file',
                                              str(params['0']), '--json'],
        'bare rosbags read + deserialise': [sys.executable, '-m', 'bench.bare_bag_read',
                                            str(bag)],
    }
    return interleaved_medians(lines, runs)


def main(argv: Optional[List[str]] = None) -> Dict[str, Tuple[float, float]]:
    """Run the benchmark and print its summary."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--runs', type=int, default=3, help='runs per command (default 3)')
    parser.add_argument('--work', type=Path, default=None,
                        help='directory for the bag (default a temporary one)')
    arguments = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as directory:
        with user_environment(Path(directory)):
            medians = run(arguments.runs, arguments.work or Path(directory))
    print(f'replay of 300 000 JointState messages: median of {arguments.runs} fresh processes')
    for name, (wall, cpu) in medians.items():
        print(f'  {name:<34} wall {wall:6.2f} s   CPU {cpu:6.2f} s')
    (wall, cpu), (bare_wall, bare_cpu) = medians.values()
    verdict = 'ok' if wall / bare_wall <= LIMIT else f'OVER {LIMIT:g}'
    print(f'  ratio ctid / bare: wall {wall / bare_wall:.2f} ({verdict}), CPU '
          f'{cpu / bare_cpu:.2f}')
    return medians


if __name__ == '__main__':
    main()
