"""``make bench``: every benchmark, each against a baseline measured in the same run."""

import sys

from bench import estimator, model_text


def main() -> int:
    """Run the model-text and estimator benchmarks, then the node's, if rclpy is available."""
    model_text.main(['--json', 'bench/results-model-text.json'])
    estimator.main(['--runs', '100', '--json', 'bench/results-estimator.json'] + sys.argv[1:])
    try:
        import rclpy  # noqa: F401 - the node benchmarks import it when they run
        from bench import node_storm, node_throughput
    except ImportError as error:       # rclpy missing: the core benchmark still stands
        print(f'node benchmarks skipped: {error}')
        return 0
    node_throughput.main()
    node_storm.main(['--json', 'bench/results-node-storm.json'])
    return 0


if __name__ == '__main__':
    sys.exit(main())
