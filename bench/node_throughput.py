"""
Throughput and latency of ctid_node: two 1 kHz streams, a 10 s window, an estimate every second.

The simulated plant (``ctid_plant``, std_msgs/Float64 on ``u`` and ``y``) runs in its own process,
as a real publisher would; ``ctid_node`` runs in this one, spun as :func:`ctid_ros.ros.node.main`
does, with an observer of ``/diagnostics``. Reported: samples published vs received by the node
(drops), the time from each update tick to its published estimate (``publish_latency`` of the
diagnostics), the estimation time, and the CPU use of both processes.

Run with ``.venv/bin/python -m bench.node_throughput [--duration 30]``.
"""

import argparse
import multiprocessing
import os
import random
import resource
import statistics
import threading
import time
from typing import Any, Dict, List, Optional

RATE = 1000.0
PLANT = {'model': 'K*exp(-tau*s)/(T*s + 1)', 'parameter_names': ['K', 'T', 'tau'],
         'parameter_values': [2.0, 0.5, 0.137], 'sample_time': 1.0 / RATE,
         'prbs_clock': 100, 'message_type': 'float64'}
NODE = {'input_topic': 'u', 'output_topic': 'y', 'model': 'K*exp(-tau*s)/(T*s + 1)',
        'parameter_names': ['K', 'T', 'tau'], 'lower': [0.001, 0.01, 0.0],
        'upper': [100.0, 100.0, 1.0], 'window': 10.0, 'update_period': 1.0,
        'qos_reliability': 'reliable', 'qos_depth': 1000}


def _publish(namespace: str, duration: float, ready, go, result) -> None:
    """Run the plant in a child process until ``duration`` seconds of samples are published."""
    import rclpy
    from rclpy.parameter import Parameter
    from ctid_ros.ros.plant_node import PlantNode

    rclpy.init()
    node = PlantNode(namespace=namespace, parameter_overrides=[
        Parameter(name, value=value) for name, value in PLANT.items()])
    # Nothing is published before the subscriber is matched and has cleared its counters.
    while not node.matched():
        time.sleep(0.01)
    ready.set()
    go.wait()
    node.restart()
    end = time.monotonic() + duration
    started = time.process_time()
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.01)
    result.put({'published': node.published, 'cpu': time.process_time() - started})
    node.destroy_node()
    rclpy.shutdown()


def run(duration: float = 30.0, sample_time: float = 0.005) -> Dict[str, Any]:
    """
    Run the benchmark and return its figures.

    Parameters
    ----------
    duration : float
        Seconds of publishing at 1 kHz per stream.
    sample_time : float
        Grid of the estimator (the 1 kHz streams are resampled onto it).

    Returns
    -------
    dict
        ``published``/``received`` per stream, ``dropped``, ``updates``, latency and estimation
        time statistics (s) and CPU use (fraction of one core) of the node and plant processes.

    """
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(101, 200)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from ctid_ros.ros.node import IdentificationNode

    namespace = f'/bench{os.getpid()}'
    spawn = multiprocessing.get_context('spawn')
    ready, go, result = spawn.Event(), spawn.Event(), spawn.Queue()
    plant = spawn.Process(target=_publish, args=(namespace, duration, ready, go, result))
    rclpy.init()
    executor = SingleThreadedExecutor()
    node = IdentificationNode(namespace=namespace, parameter_overrides=[
        Parameter(name, value=value) for name, value in
        {**NODE, 'sample_time': sample_time}.items()])
    observer = rclpy.create_node('bench_observer', namespace=namespace)
    statuses: List[Dict[str, str]] = []
    observer.create_subscription(DiagnosticArray, '/diagnostics', lambda message: statuses.extend(
        {pair.key: pair.value for pair in status.values} for status in message.status
        if status.name.startswith(namespace[1:])), 100)
    executor.add_node(node)
    executor.add_node(observer)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        plant.start()
        if not ready.wait(60.0):
            raise RuntimeError('the plant process found no subscriber within 60 s')
        node.reset()
        go.set()
        started, cpu = time.monotonic(), time.process_time()
        figures = result.get(timeout=duration + 60.0)
        plant.join(timeout=30.0)
        time.sleep(0.5)  # the last samples in flight
        wall, node_cpu = time.monotonic() - started, time.process_time() - cpu
        stats = node.buffer.stats()
    finally:
        executor.shutdown()
        node.destroy_node()
        observer.destroy_node()
        rclpy.try_shutdown()
    estimates = [status for status in statuses if 'publish_latency' in status]
    latency = [float(status['publish_latency']) for status in estimates]
    compute = [float(status['compute_time']) for status in estimates]
    return {
        'duration': duration, 'rate': RATE, 'sample_time': sample_time,
        'published': figures['published'], 'received_input': stats.u.received,
        'received_output': stats.y.received,
        'dropped': 2 * figures['published'] - stats.u.received - stats.y.received,
        'updates': len(estimates),
        'latency_median': statistics.median(latency) if latency else None,
        'latency_max': max(latency, default=None),
        'compute_median': statistics.median(compute) if compute else None,
        'node_cpu': node_cpu / wall, 'plant_cpu': figures['cpu'] / duration,
        'max_rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def format_table(figures: Dict[str, Any]) -> str:
    """Render the figures of :func:`run` as a small table."""
    def seconds(value: Optional[float]) -> str:
        return 'n/a' if value is None else f'{value * 1e3:.0f} ms'

    rows = [
        ('streams', f'u and y at {figures["rate"]:.0f} Hz for {figures["duration"]:g} s, '
                    f'grid {figures["sample_time"] * 1e3:g} ms, window 10 s, update 1 s'),
        ('published per stream', str(figures['published'])),
        ('received u / y', f'{figures["received_input"]} / {figures["received_output"]}'),
        ('dropped', str(figures['dropped'])),
        ('estimates published', str(figures['updates'])),
        ('tick -> estimate, median', seconds(figures['latency_median'])),
        ('tick -> estimate, max', seconds(figures['latency_max'])),
        ('estimation time, median', seconds(figures['compute_median'])),
        ('CPU node process', f'{figures["node_cpu"] * 100:.0f} % of one core'),
        ('CPU plant process', f'{figures["plant_cpu"] * 100:.0f} % of one core'),
        ('max RSS node process', f'{figures["max_rss_mb"]:.0f} MB'),
    ]
    width = max(len(name) for name, _ in rows)
    return '\n'.join(f'{name:<{width}}  {value}' for name, value in rows)


def main(argv: Optional[List[str]] = None) -> int:
    """Run the benchmark and print its table."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--duration', type=float, default=30.0)
    parser.add_argument('--sample-time', type=float, default=0.005)
    arguments = parser.parse_args(argv)
    print(format_table(run(arguments.duration, arguments.sample_time)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
