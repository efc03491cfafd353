"""
``ctid record`` and ``ctid echo`` on real DDS over loopback, without launch.

The simulated plant (``ctid_plant``: K=2, T=0.5, tau=0.137 s at 200 Hz, output noise 0.01,
PointStamped messages stamped at the sample instants) and the identification node run in
processes of their own, each test in a namespace of its own. The standard deviations over 6 s
of data are below 0.1 %, so 3 % on K and T and 3 ms on tau are many of them.
"""

import itertools
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time

from ctid_ros.cli.main import main
from ctid_ros.ros.messages import import_message, to_message
from ctid_ros.ros.spinner import Spinner
from ctid_ros.streaming.contract import (diagnostics_message, estimate_messages, NodeTopics,
                                         OK)
from node_harness import wait_for
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

TRUTH = {'K': 2.0, 'T': 0.5, 'tau': 0.137}
_COUNTER = itertools.count()


def namespace() -> str:
    return f'/tools{next(_COUNTER)}_{os.getpid() % 1000}_{int(time.time() * 1000) % 100000}'


def spawn_plant(space: str) -> subprocess.Popen:
    """
    Run ctid_plant publishing ``<space>/u`` and ``<space>/y`` (PointStamped, 200 Hz).

    Stamped at the sample instants, so the estimates do not depend on when the messages
    arrive: on a machine loaded by other test suites, Float64 samples stamped on reception
    moved K by 15 %.
    """
    return subprocess.Popen([sys.executable, '-m', 'ctid_ros.ros.plant_node', '--ros-args',
                             '-r', f'__ns:={space}', '-p', 'message_type:=point_stamped',
                             '--log-level', 'warn'])


def node_params(tmp_path, space: str, **overrides) -> str:
    """Write a params file for ctid_node in ``space`` estimating the plant's model."""
    values = {'input_topic': 'u', 'output_topic': 'y', 'input_field': 'point.x',
              'output_field': 'point.x', 'model': 'K*exp(-tau*s)/(T*s + 1)',
              'parameter_names': ['K', 'T', 'tau'],
              'lower': [0.001, 0.01, 0.0], 'upper': [1000.0, 100.0, 1.0],
              'sample_time': 0.005, 'window': 6.0, 'update_period': 1.0, **overrides}
    path = tmp_path / 'node.yaml'
    # JSON is YAML with every string quoted: rcl would read a bare y as a boolean.
    path.write_text(json.dumps({f'{space}/ctid_node': {'ros__parameters': values}}))
    return str(path)


class LineReader:
    """The lines of a process's output, read by a thread, taken with a deadline."""

    def __init__(self, stream):
        self._lines = queue.Queue()
        threading.Thread(target=lambda: [self._lines.put(line) for line in stream],
                         daemon=True).start()

    def take(self, timeout: float) -> str:
        try:
            return self._lines.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            raise AssertionError(f'no line of output within {timeout:.1f} s') from None


class Listener:
    """Subscribe to a PointStamped topic in a context of its own; the stamps received."""

    def __init__(self, topic: str):
        self.stamps = []
        self._context = Context()
        rclpy.init(context=self._context)
        self._node = rclpy.create_node('listener', context=self._context)
        self._node.create_subscription(
            import_message('geometry_msgs/msg/PointStamped'), topic,
            lambda message: self.stamps.append(message.header.stamp.sec
                                               + 1e-9 * message.header.stamp.nanosec), 1000)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._spinner = Spinner(self._executor, 'listener')
        self._spinner.start()

    def span(self) -> float:
        stamps = list(self.stamps)
        return max(stamps) - min(stamps) if stamps else 0.0

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self._spinner.stop()
        self._executor.shutdown()
        self._node.destroy_node()
        rclpy.try_shutdown(context=self._context)


def stop(*processes: subprocess.Popen) -> None:
    for process in processes:
        if process.poll() is None:
            process.terminate()
    for process in processes:
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@pytest.mark.ros
def test_record_until_ctrl_c_then_replay_recovers_the_plant(tmp_path, capsys):
    space = namespace()
    bag = tmp_path / 'run.mcap'
    plant = spawn_plant(space)
    record = subprocess.Popen([sys.executable, '-m', 'ctid_ros.cli.main', 'record', str(bag),
                               f'{space}/u', f'{space}/y', '--wait', '60'],
                              stderr=subprocess.PIPE, text=True)
    try:
        line = record.stderr.readline()
        assert line.startswith(f'ctid record: waiting for publishers of {space}/u'), line
        line = record.stderr.readline()
        assert line.startswith(f'ctid record: recording {space}/u (geometry_msgs/msg/'
                               f'PointStamped), {space}/y (geometry_msgs/msg/PointStamped) into '
                               f'{bag}'), line
        # 12 s of data at 200 Hz, by the stamps of the plant's messages as they come.
        with Listener(f'{space}/y') as listener:
            wait_for(lambda: listener.span() >= 12.0, 120.0,
                     lambda: f'12 s of {space}/y, got {listener.span():.2f} s')
        record.send_signal(signal.SIGINT)   # Ctrl-C: the file is closed with its index
        rest = record.communicate(timeout=30)[1]
    finally:
        stop(plant, record)
    assert record.returncode == 0, rest
    assert rest.startswith('ctid record: wrote ') and f'{space}/y: ' in rest
    code = main(['replay', str(bag), '--params-file', node_params(tmp_path, space),
                 '--node-name', f'{space}/ctid_node', '--json'])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    result = json.loads(captured.out)
    assert result['params']['K'] == pytest.approx(TRUTH['K'], rel=0.03)
    assert result['params']['T'] == pytest.approx(TRUTH['T'], rel=0.03)
    assert result['params']['tau'] == pytest.approx(TRUTH['tau'], abs=0.003)
    # Without --overwrite the recording is never replaced.
    assert main(['record', str(bag), f'{space}/u']) == 2
    assert 'already exists' in capsys.readouterr().err


@pytest.mark.ros
def test_record_of_a_topic_without_publisher_leaves_no_file(tmp_path, capsys):
    bag = tmp_path / 'none.mcap'
    assert main(['record', str(bag), f'{namespace()}/nobody', '--wait', '1']) == 2
    err = capsys.readouterr().err
    assert 'error: no publisher of' in err and 'after 1 s' in err
    assert not bag.exists()


@pytest.mark.ros
def test_echo_follows_a_running_node(tmp_path, capsys):
    space = namespace()
    plant = spawn_plant(space)
    node = subprocess.Popen([sys.executable, '-m', 'ctid_ros.ros.node', '--ros-args', '-r',
                             f'__ns:={space}', '--params-file', node_params(tmp_path, space),
                             '--log-level', 'warn'])
    echo = subprocess.Popen([sys.executable, '-m', 'ctid_ros.cli.main', 'echo', '--node',
                             f'{space}/ctid_node', '--json'], stdout=subprocess.PIPE, text=True)
    try:
        # JSON lines as the node works: statuses while it warms up, then estimates. The first
        # windows are short (most of their data settle the model's state): take the first
        # estimate a whole window (6 s) after the first one.
        rows = []
        lines = LineReader(echo.stdout)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            # Never blocks past the deadline, even if echo stops writing.
            rows.append(json.loads(lines.take(deadline - time.monotonic())))
            first = next((row['time'] for row in rows if row['params'] and row['time']), None)
            if rows[-1]['params'] and rows[-1]['time'] and rows[-1]['time'] - first >= 6.0:
                break
        row = rows[-1]
        assert row['node'] == f'{space}/ctid_node' and list(row['params']) == ['K', 'T', 'tau']
        assert row['params']['K'] == pytest.approx(TRUTH['K'], rel=0.03)
        assert row['params']['T'] == pytest.approx(TRUTH['T'], rel=0.03)
        assert row['params']['tau'] == pytest.approx(TRUTH['tau'], abs=0.003)
        assert all(0 < value < 0.01 for value in row['std'].values())
        echo.send_signal(signal.SIGINT)
        assert echo.wait(timeout=20) == 0       # Ctrl-C is how the table ends
        # The table, once: the header names the parameters, the row shows value ± std.
        code = main(['echo', '--node', f'{space}/ctid_node', '--once', '--timeout', '90'])
        out = capsys.readouterr().out.splitlines()
        assert code == 0 and out[0].split()[:5] == ['window', 'end', 'K', 'T', 'tau']
        assert len(out) == 2 and out[1].count('±') == 3
    finally:
        stop(echo, node, plant)


@pytest.mark.ros
def test_echo_started_late_gets_the_latched_estimate(capsys):
    """A node that latches its estimates (transient local): echo started later gets them."""
    topics = NodeTopics.of(f'{namespace()}/ctid_node')
    context = Context()
    rclpy.init(context=context)
    publisher = rclpy.create_node('latched_estimates', context=context)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    try:
        messages = estimate_messages(topics, ['K', 'T'], [2.0, 0.5], [0.01, 0.002])
        messages.append(diagnostics_message(topics, 1_700_000_012_500_000_000, OK, 'fine',
                                            {'fit_percent': 95.5}))
        publishers = {}
        for message in messages:
            kind = import_message(message.msgtype)
            publishers[message.topic] = publisher.create_publisher(kind, message.topic, latched)
            publishers[message.topic].publish(to_message(kind, message.fields))
        # Published before anybody listened: only the history can deliver them.
        code = main(['echo', '--node', topics.node, '--once', '--json', '--timeout', '30'])
        captured = capsys.readouterr()
        assert code == 0, captured.err
        row = json.loads(captured.out)
        assert row['params'] == {'K': 2.0, 'T': 0.5} and row['std'] == {'K': 0.01, 'T': 0.002}
        # /diagnostics, shared by every node, is read without history: the latched estimate
        # comes alone, released after STATUS_WAIT without fit or status.
        assert (row['time'], row['fit'], row['level'], row['status']) == (None,) * 4
    finally:
        publisher.destroy_node()
        rclpy.shutdown(context=context)


@pytest.mark.ros
def test_echo_gives_up_after_its_timeout(capsys):
    node = f'{namespace()}/ctid_node'
    assert main(['echo', '--node', node, '--once', '--timeout', '1']) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith(f'ctid echo: estimates of {node} ') and len(err) == 2
    assert err[1].startswith(f'ctid echo: error: no estimate from {node} within 1 s (no '
                             f'publisher of {node}/estimate, {node}/estimate_std')


def _start_recording(tmp_path, bag, space, *extra):
    """Start ``ctid record`` of the plant's topics; return it once it says it records."""
    record = subprocess.Popen([sys.executable, '-m', 'ctid_ros.cli.main', 'record', str(bag),
                               f'{space}/u', f'{space}/y', '--wait', '60', *extra],
                              stderr=subprocess.PIPE, text=True)
    for expected in ('ctid record: waiting for', 'ctid record: recording'):
        line = record.stderr.readline()
        assert line.startswith(expected), line + record.stderr.read()
    return record


def _flushed_messages(bag, tmp_path):
    """Return the log times of the messages a copy of the file made now holds (plain reader)."""
    from mcap.reader import make_reader

    copy = tmp_path / 'copy.mcap'
    copy.write_bytes(bag.read_bytes())
    with open(copy, 'rb') as stream:
        return [message.log_time for _, _, message in make_reader(stream).iter_messages()]


def _wait_for_flushed(bag, tmp_path, count, timeout=60.0):
    deadline = time.monotonic() + timeout
    while True:
        try:
            times = _flushed_messages(bag, tmp_path) if bag.exists() else []
        except Exception:   # copied in the middle of a flush: the next look sees it whole
            times = []
        if len(times) >= count:
            return times
        assert time.monotonic() < deadline, f'{len(times)} messages flushed after {timeout} s'
        time.sleep(0.05)


@pytest.mark.ros
@pytest.mark.parametrize('first, gap', [(signal.SIGINT, 0.001), (signal.SIGINT, 0.005),
                                        (signal.SIGTERM, 0.010)])
def test_a_second_ctrl_c_right_after_the_first_keeps_the_recording(tmp_path, first, gap):
    space = namespace()
    bag = tmp_path / 'run.mcap'
    plant = spawn_plant(space)
    try:
        record = _start_recording(tmp_path, bag, space)
        flushed = len(_wait_for_flushed(bag, tmp_path, 400))
        # Ctrl-C under a parent that forwards it too (as launch does): two signals.
        record.send_signal(first)
        time.sleep(gap)
        record.send_signal(signal.SIGINT)
        rest = record.communicate(timeout=30)[1]
    finally:
        stop(plant, record)
    assert record.returncode == 0, rest
    assert rest.startswith('ctid record: wrote ') and 'Traceback' not in rest, rest
    from ctid_ros.files.bag_reader import BagReader

    with BagReader(bag) as reader:
        assert not reader.truncated and reader.message_count() >= flushed


@pytest.mark.ros
def test_a_killed_recorder_loses_about_the_last_second(tmp_path):
    space = namespace()
    bag = tmp_path / 'run.mcap'
    plant = spawn_plant(space)
    try:
        record = _start_recording(tmp_path, bag, space)
        _wait_for_flushed(bag, tmp_path, 1200)     # 3 s at 2 x 200 Hz
        killed_ns = time.time_ns()
        record.kill()
        record.wait(timeout=30)
    finally:
        stop(plant, record)
    times = _flushed_messages(bag, tmp_path)       # the plain mcap reader reads the file
    lost = (killed_ns - max(times)) / 1e9
    # Flushed every second plus a tick of 0.1 s; the rest is margin for a busy machine.
    assert lost < 2.0, f'{lost:.2f} s lost'
    code = main(['replay', str(bag), '--params-file', node_params(tmp_path, space),
                 '--node-name', f'{space}/ctid_node', '--json'])
    assert code == 0


@pytest.mark.ros
def test_a_full_disk_stops_the_recording_with_one_line_and_a_readable_file(tmp_path):
    from disk_fixtures import small_disk

    space = namespace()
    plant = spawn_plant(space)
    record = None
    try:
        with small_disk(tmp_path / 'disk', 128) as disk:
            bag = disk / 'run.mcap'
            record = _start_recording(tmp_path, bag, space)
            rest = record.communicate(timeout=120)[1]
            times = _flushed_messages(bag, tmp_path)
    finally:
        stop(plant, *([record] if record else []))
    assert record.returncode == 2 and rest.count('\n') == 1, rest
    assert rest.startswith(f'ctid record: error: cannot write {bag}: No space left on device; '
                           'recording stopped after '), rest
    assert len(times) > 500


@pytest.mark.ros
@pytest.mark.parametrize('number', [signal.SIGINT, signal.SIGTERM])
def test_echo_ends_on_ctrl_c_and_sigterm_with_status_0(number):
    echo = subprocess.Popen([sys.executable, '-m', 'ctid_ros.cli.main', 'echo', '--node',
                             f'{namespace()}/ctid_node', '--timeout', '300'],
                            stderr=subprocess.PIPE, text=True)
    try:
        line = echo.stderr.readline()
        assert line.startswith('ctid echo: estimates of '), line
        signalled = time.monotonic()
        echo.send_signal(number)
        rest = echo.communicate(timeout=30)[1]
        took = time.monotonic() - signalled
    finally:
        stop(echo)
    assert echo.returncode == 0 and rest == '', rest
    # 0.3 s on a quiet machine; the margin is for a busy one.
    assert took < 2.0, f'{took:.2f} s'


@pytest.mark.ros
@pytest.mark.parametrize('number', [signal.SIGINT, signal.SIGTERM])
def test_record_stopped_while_waiting_ends_with_status_0_and_no_file(tmp_path, number):
    bag = tmp_path / 'none.mcap'
    record = subprocess.Popen([sys.executable, '-m', 'ctid_ros.cli.main', 'record', str(bag),
                               f'{namespace()}/nobody', '--wait', '300'],
                              stderr=subprocess.PIPE, text=True)
    try:
        line = record.stderr.readline()
        assert line.startswith('ctid record: waiting for publishers of '), line
        record.send_signal(number)
        rest = record.communicate(timeout=30)[1]
    finally:
        stop(record)
    assert record.returncode == 0, rest
    assert rest == 'ctid record: stopped while waiting for publishers; nothing recorded\n'
    assert not bag.exists()
