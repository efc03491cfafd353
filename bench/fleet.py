"""
``python -m bench fleet``: replay throughput and ``ctid fleet`` scaling (issue #18).

1. A 10-minute 500 Hz ``sensor_msgs/JointState`` bag (300 000 messages, rosbag2 directory with
   MCAP storage, written here) replayed through the streaming path (``replay_messages`` over
   decoded messages: the path of the live node and of ``ctid replay`` before) and the columnar
   path (``sample_columns`` + ``replay_columns``), one estimate over the bag and ``--sliding``,
   with the wheel selected by index (``velocity[0]``), then one estimate with the wheel selected
   by name (``velocity[wheel_left]``, the same joint); the largest relative difference of the
   estimates and standard deviations, and of the estimates by name against those by index.
2. A synthetic fleet of 50 bags (5 robots, one with a 20 % heavier payload; 60 s at 500 Hz each)
   plus a corrupt bag and a bag missing the topic, through ``ctid fleet`` with a ``LocalCluster``
   of 1 worker and of every core; then the same run again (every bag skipped).
3. The bag of part 1 through ``ctid fleet --span`` (default 60 s: ten spans) on a
   ``LocalCluster`` of 1 worker and of every core, against the whole bag as one task: the
   clusters are started and their workers have imported ctid_ros before the clock starts, so
   the times are those of the spans' work and its scheduling; then resumed (every span skipped).

Timings are wall-clock on whatever else the machine runs: compare the ratios of one run.
"""

import argparse
import importlib
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time
from typing import Dict, List, Optional, Tuple

import numpy as np

TEST = Path(__file__).resolve().parents[1] / 'test'


def _replay(path: Path, params: Path, sliding: bool, columnar: bool):
    from ctid_ros.files.bag_reader import open_bag
    from ctid_ros.files.columns import sample_columns
    from ctid_ros.streaming.params_file import load_params_file
    from ctid_ros.streaming.replay import replay_columns, replay_messages

    started = time.perf_counter()
    config = load_params_file(params)
    with open_bag(path) as bag:
        topics = (config.input_topic, config.output_topic)
        if columnar:
            replay = replay_columns(sample_columns(bag, config, topics), config,
                                    sliding=sliding, topics=topics)
        else:
            replay = replay_messages(bag.messages(sorted(set(topics))), config,
                                     sliding=sliding, topics=topics)
    return time.perf_counter() - started, replay


def _difference(first, second) -> float:
    worst = 0.0
    for one, other in zip(first.updates, second.updates):
        for a, b in ((one.values, other.values), (one.stds, other.stds)):
            worst = max(worst, float(np.max(np.abs(a / b - 1))))
    return worst


def _long_bag(work: Path, minutes: float) -> Tuple[Path, Dict[str, Path]]:
    """Write the 500 Hz bag and its params files (wheel by index, by name) once; return them."""
    from fleet_fixtures import write_joint_state_bag, write_params

    bag = work / 'js500'
    params = {joint: work / f'js500_{joint}.yaml' for joint in ('0', 'wheel_left')}
    if bag.exists():
        return bag, params
    started = time.perf_counter()
    write_joint_state_bag(bag, {'J': 0.05, 'b': 0.2, 'tau': 0.0373}, minutes * 60, 500.0,
                          seed=1, noise=0.05)
    for joint, path in params.items():
        write_params(path, sample_time=0.002, window=20.0, update_period=10.0, joint=joint)
    size = sum(item.stat().st_size for item in bag.iterdir())
    print(f'bag: {minutes:g} min of JointState at 500 Hz, {round(minutes * 60 * 500)} '
          f'messages, {size / 2**20:.1f} MiB (written in {time.perf_counter() - started:.1f} s)')
    return bag, params


def throughput(work: Path, minutes: float) -> None:
    """Part 1: the 500 Hz bag, streaming against columnar, the wheel by index and by name."""
    bag, params = _long_bag(work, minutes)
    print('| mode | output field | streaming s | columnar s | speed-up | estimates | largest '
          'relative difference |')
    print('|---|---|---|---|---|---|---|')
    replays = {}
    for sliding, joint in ((False, '0'), (True, '0'), (False, 'wheel_left')):
        columnar_time, columnar = _replay(bag, params[joint], sliding, True)
        streaming_time, streaming = _replay(bag, params[joint], sliding, False)
        assert len(columnar.updates) == len(streaming.updates)
        replays[sliding, joint] = columnar
        print(f'| {"sliding" if sliding else "one estimate"} | velocity[{joint}] | '
              f'{streaming_time:.2f} | {columnar_time:.2f} | '
              f'{streaming_time / columnar_time:.1f} | {len(columnar.updates)} | '
              f'{_difference(columnar, streaming):.1e} |')
    print('estimates by name against by index (one estimate): largest relative difference '
          f'{_difference(replays[False, "wheel_left"], replays[False, "0"]):.1e}')
    update = replays[True, '0'].updates[-1]
    print(f'last window: {dict(zip(update.names, np.round(update.values, 6)))}')


def fleet(work: Path, bags_per_robot: int, seconds: float, workers: List[int]) -> None:
    """Part 2: the synthetic fleet with 1 worker and all cores, then resumed."""
    from ctid_ros.cli.fleet import run_fleet
    from fleet_fixtures import write_fleet, write_params

    started = time.perf_counter()
    root = work / 'fleet'
    bags = write_fleet(root, robots=5, days=2, runs=bags_per_robot // 2, seconds=seconds,
                       rate_hz=500.0, heavy='r2')
    params = write_params(work / 'fleet.yaml', sample_time=0.002, window=20.0,
                          update_period=10.0)
    print(f'\nfleet: {len(bags)} bags ({len(bags) - 2} of {seconds:g} s at 500 Hz, a corrupt '
          f'one, one without the topic), written in {time.perf_counter() - started:.1f} s')
    print('| run | workers | wall s | analysed | skipped | errors | flagged |')
    print('|---|---|---|---|---|---|---|')
    times = {}
    for count in workers:
        results = work / f'results_{count}'
        started = time.perf_counter()
        summary = run_fleet([str(root)], params, results, robot_from='{robot}/{date}/*',
                            workers=count, plots=False)
        times[count] = time.perf_counter() - started
        print(f'| fresh | {count} | {times[count]:.1f} | {summary["computed"]} | '
              f'{summary["skipped"]} | {summary["errors"]} | {summary["flagged"]} of '
              f'{summary["robots"]} |')
    started = time.perf_counter()
    summary = run_fleet([str(root)], params, work / f'results_{workers[-1]}',
                        robot_from='{robot}/{date}/*', workers=workers[-1])
    print(f'| resumed (+ report, figures) | {workers[-1]} | {time.perf_counter() - started:.1f} '
          f'| {summary["computed"]} | {summary["skipped"]} | {summary["errors"]} | '
          f'{summary["flagged"]} of {summary["robots"]} |')
    speed_up = times[workers[0]] / times[workers[-1]]
    print(f'speed-up from 1 to {workers[-1]} workers: {speed_up:.2f} (load average before: '
          f'{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)')
    import pyarrow.parquet as pq
    for row in pq.read_table(work / f'results_{workers[-1]}' / 'robots.parquet').to_pylist():
        if row['flagged']:
            print(f'flagged {row["robot"]}: {row["flag_reason"]}')


def spans(work: Path, minutes: float, span: float, workers: List[int]) -> None:
    """Part 3: one long bag cut into spans, on 1 worker and on every core."""
    from ctid_ros.cli.fleet import run_fleet
    from distributed import Client, LocalCluster
    import pyarrow.parquet as pq

    bag, params = _long_bag(work, minutes)
    print(f'\none {minutes:g}-minute bag, --span {span:g}')
    print('| run | workers | tasks | wall s | analysed | skipped | errors |')
    print('|---|---|---|---|---|---|---|')
    times = {}
    for count, spanned in [(workers[0], False)] + [(count, True) for count in workers]:
        results = work / f'spans_{count}_{spanned}'
        with LocalCluster(n_workers=count, threads_per_worker=1, dashboard_address=':0'
                          ) as cluster, Client(cluster) as client:
            # The workers' first task would import sympy and scipy: done before the clock.
            client.run(importlib.import_module, 'ctid_ros.files.fleet')
            runs = ['fresh', 'resumed'] if spanned and count == workers[-1] else ['fresh']
            for run in runs:
                started = time.perf_counter()
                summary = run_fleet([str(bag)], params['0'], results, client=client, plots=False,
                                    span=span if spanned else None)
                elapsed = time.perf_counter() - started
                if run == 'fresh':
                    times[count, spanned] = elapsed
                what = f'--span {span:g}' if spanned else 'whole bag'
                print(f'| {what}, {run} | {count} | {summary.get("spans", 1)} | {elapsed:.2f} | '
                      f'{summary["computed"]} | {summary["skipped"]} | {summary["errors"]} |')
    one, many = times[workers[0], True], times[workers[-1], True]
    print(f'speed-up of --span from {workers[0]} to {workers[-1]} workers: {one / many:.2f}; '
          f'against the whole bag as one task: {times[workers[0], False] / many:.2f} (load '
          f'average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)')
    rows = pq.read_table(work / f'spans_{workers[-1]}_True' / 'bags.parquet').to_pylist()
    values = np.array([row['J'] for row in rows])
    print(f'J per span: {values.min():.6f} to {values.max():.6f} (truth 0.05)')


def main(argv: Optional[List[str]] = None) -> int:
    """Run the benchmark."""
    parser = argparse.ArgumentParser(prog='python -m bench.fleet', description=__doc__)
    parser.add_argument('--minutes', type=float, default=10.0,
                        help='length of the 500 Hz bag (default 10)')
    parser.add_argument('--bags-per-robot', type=int, default=10)
    parser.add_argument('--seconds', type=float, default=60.0, help='length of a fleet bag')
    parser.add_argument('--skip-throughput', action='store_true')
    parser.add_argument('--skip-fleet', action='store_true')
    parser.add_argument('--span', type=float, default=60.0,
                        help='span of the long bag in part 3 (default 60 s)')
    parser.add_argument('--skip-spans', action='store_true')
    arguments = parser.parse_args(argv)
    sys.path.insert(0, str(TEST))
    work = Path(tempfile.mkdtemp(prefix='ctid-bench-fleet-'))
    try:
        if not arguments.skip_throughput:
            throughput(work, arguments.minutes)
        if not arguments.skip_fleet:
            fleet(work, arguments.bags_per_robot, arguments.seconds,
                  sorted({1, os.cpu_count() or 1}))
        if not arguments.skip_spans:
            spans(work, arguments.minutes, arguments.span, sorted({1, os.cpu_count() or 1}))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
