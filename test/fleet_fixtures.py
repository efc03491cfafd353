"""
Synthetic fleets of robots for ``ctid fleet``: wheel drives recorded as JointState bags.

Each robot's wheel drive is ``exp(-tau*s)/(J*s + b)`` from the torque command ``effort[0]`` to
the wheel speed ``velocity[0]``, driven by a PRBS, with white speed noise; one robot carries a
heavier payload (a larger inertia J). Bags are rosbag2 directories with MCAP storage written by
rosbags, laid out as ``ROBOT/DATE/run_N/``, stamped at the sample instants (header) and logged
with a small jitter. Shared by test/cli/test_fleet.py and bench/fleet.py (which puts test/
on the path).
"""

from pathlib import Path
import shutil
from typing import Dict, List, Optional, Tuple

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import yaml

__all__ = ['MODEL', 'TRUTH', 'write_fleet', 'write_joint_state_bag', 'write_params']

MODEL = 'exp(-tau*s)/(J*s + b)'
TRUTH = {'J': 0.05, 'b': 0.2, 'tau': 0.0373}
JOINT_STATE = 'sensor_msgs/msg/JointState'
T0_NS = 1_760_000_000_000_000_000
DAY_NS = 86_400 * 10 ** 9


def write_joint_state_bag(path: Path, truth: Dict[str, float], seconds: float, rate_hz: float,
                          seed: int, start_ns: int = T0_NS, topic: str = '/joint_states',
                          noise: float = 0.02,
                          gain_change: Optional[Tuple[float, float]] = None,
                          pause: Optional[Tuple[float, float]] = None) -> Path:
    """
    Write one recording of a wheel drive as a rosbag2 directory (MCAP storage).

    ``gain_change`` ``(seconds, factor)``: from that time on the drive delivers ``factor`` times
    the commanded torque (a weaker motor), so that from the command the wheel behaves as
    ``J / factor`` and ``b / factor`` with the same dead time; the state carries over.
    ``pause`` ``(first, last)``: no message is recorded from ``first`` to ``last`` seconds (the
    recorder was paused; the drive went on).
    """
    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    count = int(round(seconds * rate_hz))
    ts = 1.0 / rate_hz
    rng = np.random.default_rng(seed)
    u = np.resize(prbs(11, max(1, int(round(0.05 * rate_hz)))), count)
    torque = u.copy()
    if gain_change is not None:
        torque[int(round(gain_change[0] * rate_hz)):] *= gain_change[1]
    y = Model(MODEL).simulate(truth, torque, ts) + noise * rng.standard_normal(count)
    step = int(round(ts * 1e9))
    jitter = rng.integers(50_000, 400_000, size=count)
    if path.exists():
        shutil.rmtree(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = ['wheel_left', 'wheel_right']
    zero = np.zeros(2)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(topic, JOINT_STATE, typestore=store)
        header, time = types['std_msgs/msg/Header'], types['builtin_interfaces/msg/Time']
        message = types[JOINT_STATE]
        for k in range(count):
            if pause is not None and pause[0] <= k * ts < pause[1]:
                continue
            stamp = start_ns + k * step
            msg = message(header(time(stamp // 10 ** 9, stamp % 10 ** 9), 'base'), names, zero,
                          np.array([y[k], 0.0]), np.array([u[k], 0.0]))
            writer.write(connection, stamp + int(jitter[k]), store.serialize_cdr(msg, JOINT_STATE))
    return path


def write_params(path: Path, sample_time: float = 0.01, window: float = 10.0,
                 update_period: float = 5.0, joint: str = '0') -> Path:
    """Write the params file of the fleet's identification (``joint``: index or name)."""
    values = {'input_topic': '/joint_states', 'input_field': f'effort[{joint}]',
              'output_topic': '/joint_states', 'output_field': f'velocity[{joint}]',
              'model': MODEL,
              'parameter_names': ['J', 'b', 'tau'], 'lower': [0.001, 0.0, 0.0],
              'upper': [10.0, 10.0, 0.2], 'delay_min': 0.0, 'delay_max': 0.1,
              'sample_time': sample_time, 'window': window, 'update_period': update_period}
    path.write_text(yaml.safe_dump({'ctid_node': {'ros__parameters': values}}))
    return path


def write_fleet(root: Path, robots: int = 5, days: int = 2, runs: int = 5,
                seconds: float = 20.0, rate_hz: float = 100.0, heavy: Optional[str] = 'r2',
                payload: float = 1.2, seed: int = 0) -> List[Path]:
    """
    Write ``robots x days x runs`` bags, plus a corrupt bag and one missing the topic.

    Robot ``heavy`` has its inertia J multiplied by ``payload``. Returns the bags, the two bad
    ones last.
    """
    bags = []
    for r in range(robots):
        robot = f'r{r}'
        truth = dict(TRUTH, J=TRUTH['J'] * (payload if robot == heavy else 1.0))
        for day in range(days):
            date = f'2025-10-{day + 1:02d}'
            for run in range(runs):
                start = T0_NS + day * DAY_NS + run * 3_600 * 10 ** 9
                bags.append(write_joint_state_bag(
                    root / robot / date / f'run_{run}', truth, seconds, rate_hz,
                    seed=seed + 1000 * r + 100 * day + run, start_ns=start))
    corrupt = root / 'r0' / f'2025-10-{days:02d}' / 'run_corrupt'
    write_joint_state_bag(corrupt, TRUTH, 2.0, rate_hz, seed=seed + 7)
    storage = next(corrupt.glob('*.mcap'))
    data = bytearray(storage.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 4096] = bytes(np.random.default_rng(seed).integers(0, 256, 4096,
                                                                            dtype=np.uint8))
    storage.write_bytes(bytes(data))
    missing = write_joint_state_bag(root / 'r1' / f'2025-10-{days:02d}' / 'run_no_topic', TRUTH,
                                    2.0, rate_hz, seed=seed + 8, topic='/other_states')
    return bags + [corrupt, missing]
