"""``make bench``: every benchmark, each against a baseline measured in the same run."""

import sys

from bench import estimator, hostile_files


def main() -> int:
    """Run the estimator and hostile-files benchmarks, then the node throughput benchmark."""
    estimator.main(['--runs', '100', '--json', 'bench/results-estimator.json'] + sys.argv[1:])
    hostile_files.main([])
    try:
        from bench import node_throughput
    except ImportError as error:       # rclpy missing: the core benchmark still stands
        print(f'node throughput benchmark skipped: {error}')
        return 0
    node_throughput.main()
    return 0


if __name__ == '__main__':
    sys.exit(main())
