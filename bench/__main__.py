"""``make bench``: every benchmark, each against a baseline measured in the same run."""

import sys

from bench import estimator, stamps


def main() -> int:
    """Run the estimator and stamps benchmarks, then node throughput if it is available."""
    estimator.main(['--runs', '100', '--json', 'bench/results-estimator.json'] + sys.argv[1:])
    # Stamps at five phases, before and after the grid followed the input; the live node part
    # is skipped (with a note) where rclpy is missing.
    stamps.main(['--json', 'bench/results-stamps.json'])
    try:
        from bench import node_throughput
    except ImportError as error:       # rclpy missing: the core benchmark still stands
        print(f'node throughput benchmark skipped: {error}')
        return 0
    node_throughput.main()
    return 0


if __name__ == '__main__':
    sys.exit(main())
