"""
``make demo``: a wheel drive identified live on ROS 2 in closed loop, recorded, replayed, plotted.

The scenario (``config/wheel_demo_plant.yaml``): a mobile robot's wheel drive, torque command
``u`` to wheel speed ``y``, is the grey-box model ``exp(-tau*s)/(J*s + b)`` with inertia ``J``,
viscous friction ``b`` and a dead time ``tau`` of 3.73 samples. A digital PI speed controller
runs at 100 Hz on the measured (noisy) speed and tracks a PRBS reference. Halfway through the
robot picks up a payload: ``J`` jumps from 0.05 to 0.08 kg m².

1. ``ctid_plant`` runs in a process of its own and publishes ``r``, ``u`` and ``y`` as
   ``geometry_msgs/PointStamped`` stamped at the sample instants, on real DDS (a private
   domain, loopback only).
2. ``ctid_node`` runs in another process with ``config/wheel_demo.yaml``: every 2 s it
   identifies the plant from the measured ``u`` to ``y`` on the last 4 s (direct closed-loop
   identification: a dead time cannot be inside a ``controller=`` model).
3. This process records the plant's and the node's topics into an MCAP file
   (:class:`~ctid_ros.ros.recorder.TopicRecorder`) and prints the node's estimates as they
   come.
4. ``ctid replay --sliding --plot --output`` replays the recording offline through the node's
   code path; the demo adds the estimates over time against the truth and a summary of the
   estimates before and after the payload.

The node's params file carries the drive's data-sheet baseline (``baseline: {J: 0.05, ...}``),
so its change alarm (``~/alarm``, merged into ``/diagnostics``) watches the run: the live
table's last column, and a line per alarm raised, live and replayed. The payload raises it
within a few windows, the stationary part none.

Everything goes to ``demo_output/``; ``--docs`` also copies the figures into ``docs/images/``,
where the README shows them. The ROS side (plant process, recorder) is in :mod:`ctid_ros.ros`,
imported only once the DDS environment is set.
"""

import argparse
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, replace
import gc
import math
import multiprocessing
import os
from pathlib import Path
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from typing import Any, Dict, List, Optional, Sequence, TextIO, Tuple

from ctid_ros.cli import main as cli
from ctid_ros.cli.report import format_estimate, series_header, series_row
from ctid_ros.errors import CtidError
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.streaming.alarm import AlarmStatus
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import (DEFAULT_NODE_NAME, DIAGNOSTIC_ARRAY,
                                         DIAGNOSTIC_STATUS, ERROR, FLOAT64_MULTI_ARRAY, LEVELS,
                                         NANOSECONDS, NodeTopics)
from ctid_ros.streaming.params_file import find_config, load_params_file, load_units
import numpy as np
import yaml

__all__ = ['LiveRun', 'LiveTable', 'Scenario', 'Series', 'alarm_summary', 'copy_to_docs', 'main',
           'read_estimates', 'run_live', 'run_replay', 'summary', 'write_figures']

PLANT_CONFIG = 'wheel_demo_plant'
NODE_CONFIG = 'wheel_demo'
# The node runs with its default name in the root namespace.
NODE = NodeTopics.of(DEFAULT_NODE_NAME)
POINT = 'geometry_msgs/msg/PointStamped'
# Figures of the run and the names the README knows them by.
DOC_FIGURES = {'replay.png': 'demo_fit.png', 'parameters.png': 'demo_parameters.png',
               'replay_bode.png': 'demo_bode.png'}
DOCS_DIRECTORY = Path(__file__).resolve().parents[2] / 'docs' / 'images'
# Seconds to wait for the processes to start and discover each other on a loaded machine.
STARTUP_TIMEOUT = 60.0
# Seconds to wait for the last samples in flight after the plant has finished.
DRAIN_TIMEOUT = 3.0
# Set by SIGINT or SIGTERM during main().
_INTERRUPTED = threading.Event()
CELL_WIDTH = 19


@dataclass(frozen=True)
class Scenario:
    """
    The simulated plant as its params file states it: the truth to compare with.

    Attributes
    ----------
    params_file : Path
        The ``ctid_plant`` params file.
    model : str
        Plant transfer function.
    before, after : dict
        Parameter values before and after the drift.
    drift_time : float
        Seconds after the start at which the parameters jump.
    sample_time : float
        Seconds between samples.
    topics : dict
        Reference, command and output topics by role (``r``, ``u``, ``y``).
    pi_gains : (float, float)
        Gains of the digital PI controller.
    noise_std : float
        Standard deviation of the measurement noise.

    """

    params_file: Path
    model: str
    before: Dict[str, float]
    after: Dict[str, float]
    drift_time: float
    sample_time: float
    topics: Dict[str, str]
    pi_gains: Tuple[float, float]
    noise_std: float

    @classmethod
    def load(cls, path: Path) -> 'Scenario':
        """Read the scenario from a ``ctid_plant`` params file."""
        values = yaml.safe_load(path.read_text(encoding='utf-8'))['ctid_plant'][
            'ros__parameters']
        names = values['parameter_names']
        before = dict(zip(names, values['parameter_values']))
        return cls(params_file=path, model=values['model'], before=before,
                   after={**before, **dict(zip(names, values['drift_values']))},
                   drift_time=float(values['drift_time']),
                   sample_time=float(values['sample_time']),
                   topics={'r': values['input_topic'], 'u': values['control_topic'],
                           'y': values['output_topic']},
                   pi_gains=tuple(values['pi_gains']), noise_std=float(values['noise_std']))

    def truth(self, time: np.ndarray) -> Dict[str, np.ndarray]:
        """Return each parameter's true value at ``time`` (seconds from the start)."""
        after = np.asarray(time) >= self.drift_time
        return {name: np.where(after, self.after[name], value)
                for name, value in self.before.items()}

    def drift_text(self) -> str:
        """Describe the drift, e.g. ``J 0.05 -> 0.08``."""
        return ', '.join(f'{name} {value:g} -> {self.after[name]:g}'
                         for name, value in self.before.items() if self.after[name] != value)


@dataclass(frozen=True)
class Series:
    """
    Estimates over time, from the live node or the replay.

    Attributes
    ----------
    times : ndarray
        End of each window in seconds from the plant's start.
    values, stds : ndarray
        Estimates and standard deviations, one row per window, in ``names`` order.
    fits : ndarray
        Fit (%) of each window.
    names : tuple of str
        Parameter names.
    alarms : list of AlarmStatus
        The change alarm after each window (level, parameters, since, window end).

    """

    times: np.ndarray
    values: np.ndarray
    stds: np.ndarray
    fits: np.ndarray
    names: Tuple[str, ...]
    alarms: Tuple[AlarmStatus, ...] = ()

    def last(self, earliest: float = -np.inf, latest: float = np.inf) -> Optional[int]:
        """Return the index of the last window ending in ``[earliest, latest]``, if any."""
        inside = np.flatnonzero((self.times >= earliest - 1e-9) & (self.times <= latest + 1e-9))
        return int(inside[-1]) if inside.size else None


@dataclass(frozen=True)
class LiveRun:
    """
    What the live part of the demo produced.

    Attributes
    ----------
    start_ns : int
        Stamp of the plant's first sample (its start at rest).
    published : int
        Samples the plant published.
    series : Series
        The node's estimates as received.

    """

    start_ns: int
    published: int
    series: Series


class LiveTable:
    """
    Collect the node's estimate, standard deviations and fit; print a row per update.

    The three come on separate topics, one message each per update and in this order, so a row
    is complete when one of each has arrived.
    """

    def __init__(self, scenario: Scenario, names: Sequence[str], stream: TextIO):
        self._scenario = scenario
        self._names = tuple(names)
        self._stream = stream
        self._pending: Dict[str, Any] = {}
        self._rows: List[Tuple[float, List[float], List[float], float, AlarmStatus]] = []
        self._drift_shown = False
        self.start_ns: Optional[int] = None
        self._widths = [max(len(name), CELL_WIDTH) for name in self._names]

    def header(self) -> None:
        """Print the column titles."""
        print(series_header(self._names, self._widths, alarm=True), file=self._stream,
              flush=True)

    def on_estimate(self, message) -> None:
        """Take the estimates of an update."""
        self._add('values', list(message.data))

    def on_std(self, message) -> None:
        """Take the standard deviations of an update."""
        self._add('stds', list(message.data))

    def on_diagnostics(self, message) -> None:
        """Take the fit, window end and change alarm of an update from the node's status."""
        for status in message.status:
            values = {pair.key: pair.value for pair in status.values}
            if status.name == NODE.status_name and 'fit_percent' in values:
                self._add('status', (float(values['window_end']), float(values['fit_percent']),
                                     _alarm_of(values, self.start_ns or 0)))

    def _add(self, key: str, value: Any) -> None:
        self._pending[key] = value
        if len(self._pending) < 3 or self.start_ns is None:
            return
        (end, fit, alarm), values, stds = (self._pending.pop(name)
                                           for name in ('status', 'values', 'stds'))
        time_s = end - self.start_ns / NANOSECONDS
        if time_s >= self._scenario.drift_time and not self._drift_shown:
            self._drift_shown = True
            print(f'{self._scenario.drift_time:>9.2f}  payload picked up: '
                  f'{self._scenario.drift_text()}', file=self._stream, flush=True)
        self._rows.append((time_s, values, stds, fit, alarm))
        cell = alarm.level_name + (f' {",".join(alarm.parameters)}' if alarm.parameters else '')
        print(series_row(time_s, [format_estimate(*pair) for pair in zip(values, stds)], fit,
                         self._widths, cell), file=self._stream, flush=True)

    def series(self) -> Series:
        """Return the rows received so far."""
        count = len(self._names)
        columns = list(zip(*self._rows)) or [(), (), (), (), ()]
        return Series(np.array(columns[0], dtype=float),
                      np.array(columns[1], dtype=float).reshape(-1, count),
                      np.array(columns[2], dtype=float).reshape(-1, count),
                      np.array(columns[3], dtype=float), self._names, tuple(columns[4]))


def _alarm_of(values: Dict[str, str], origin_ns: int) -> AlarmStatus:
    """Return the change alarm carried by a status's values (times after ``origin_ns``)."""
    since = values.get('alarm_since')
    end = values.get('window_end')
    return AlarmStatus(
        LEVELS.get(values.get('alarm', 'OK'), 0),
        tuple(name for name in values.get('alarm_parameters', '').split('; ') if name),
        None if since is None else origin_ns + round(float(since) * NANOSECONDS),
        None if end is None else round(float(end) * NANOSECONDS),
        values.get('alarm_message', '').rsplit(' since t=', 1)[0])


def _isolate_dds() -> None:
    """Keep the demo's DDS traffic on this host, in a domain of its own (before rclpy loads)."""
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


def _wait_event(events: Any, kind: str, timeout: float, node: subprocess.Popen,
                plant: multiprocessing.Process, log: Path) -> Any:
    """Return the payload of the plant's next event, which must be ``kind``."""
    deadline = time.monotonic() + timeout
    while True:
        if node.poll() is not None:
            raise CtidError(f'ctid_node exited with status {node.returncode}; see {log}')
        if not plant.is_alive() and events.empty():
            raise CtidError(f'the plant process exited with status {plant.exitcode}')
        try:
            event, payload = events.get(timeout=0.2)
        except queue.Empty:
            if time.monotonic() > deadline:
                raise CtidError(f'the plant did not report {kind!r} within {timeout:g} s')
            continue
        if event != kind:
            raise CtidError(f'the plant failed: {payload}')
        return payload


def run_live(scenario: Scenario, node_file: Path, bag: Path, duration: float, log: Path,
             stream: Optional[TextIO] = None) -> LiveRun:
    """
    Run plant and node on DDS for ``duration`` seconds, record into ``bag``, print estimates.

    Parameters
    ----------
    scenario : Scenario
        The plant; its drift happens at ``scenario.drift_time``.
    node_file : Path
        Params file of ``ctid_node``.
    bag : Path
        The ``.mcap`` file to record into (created).
    duration : float
        Seconds of plant time.
    log : Path
        Where the node's console output goes.
    stream : text stream, optional
        Where the live table is printed; default standard output.

    Returns
    -------
    LiveRun
        The plant's start and the estimates received.

    """
    _isolate_dds()
    # Imported here, after _isolate_dds() has set the DDS environment.
    from ctid_ros.ros.plant_node import run_samples

    config = load_params_file(node_file)
    # Each plant topic is recorded here; the node subscribes to its input and output too.
    subscribers = {topic: 1 + (topic in (config.input_topic, config.output_topic))
                   for topic in (scenario.topics[role] for role in 'ruy')}
    # Both processes start first: they take seconds to import, in parallel with this one.
    with open(log, 'w', encoding='utf-8') as log_stream:
        node = subprocess.Popen([sys.executable, '-m', 'ctid_ros.ros.node', '--ros-args',
                                 '--params-file', str(node_file)],
                                stdout=log_stream, stderr=subprocess.STDOUT)
    spawn = multiprocessing.get_context('spawn')
    events = spawn.Queue()
    plant = spawn.Process(target=run_samples, args=(
        str(scenario.params_file), {'drift_time': scenario.drift_time},
        round(duration / scenario.sample_time), subscribers, events, STARTUP_TIMEOUT),
        daemon=True)
    plant.start()
    try:
        table = LiveTable(scenario, config.names, stream or sys.stdout)
        published = _record(bag, scenario, table, events, (node, plant, log), duration)
    except BaseException:
        # Interrupted (Ctrl-C, SIGTERM) or failed: the plant has nothing left to publish for.
        plant.terminate()
        raise
    finally:
        _stop(node)
        plant.join(timeout=10.0)
        if plant.is_alive():
            plant.terminate()
    return LiveRun(table.start_ns, published, table.series())


def _record(bag: Path, scenario: Scenario, table: LiveTable, events: Any,
            processes: Tuple[subprocess.Popen, multiprocessing.Process, Path],
            duration: float) -> int:
    """
    Record and tabulate until the plant has finished; return the samples it published.

    ``processes`` are the node, the plant and the node's log, watched while waiting.
    """
    # Imported here, after _isolate_dds() has set the DDS environment.
    from ctid_ros.files.mcap_writer import RecordingWriter
    from ctid_ros.ros.recorder import TopicRecorder

    recorded = {scenario.topics['r']: POINT, scenario.topics['u']: POINT,
                scenario.topics['y']: POINT, NODE.estimate: FLOAT64_MULTI_ARRAY,
                NODE.estimate_std: FLOAT64_MULTI_ARRAY, NODE.diagnostics: DIAGNOSTIC_ARRAY,
                NODE.alarm: DIAGNOSTIC_STATUS}
    with RecordingWriter(bag, overwrite=True) as writer, \
            TopicRecorder(writer, recorded, node_name='ctid_demo_recorder') as recorder:
        for topic, msgtype, callback in (
                (NODE.estimate, FLOAT64_MULTI_ARRAY, table.on_estimate),
                (NODE.estimate_std, FLOAT64_MULTI_ARRAY, table.on_std),
                (NODE.diagnostics, DIAGNOSTIC_ARRAY, table.on_diagnostics)):
            recorder.subscribe(topic, msgtype, callback)
        recorder.start()
        table.start_ns = _wait_event(events, 'started', STARTUP_TIMEOUT, *processes)
        table.header()
        published = _wait_event(events, 'finished', duration + STARTUP_TIMEOUT, *processes)
        # The last samples may still be in flight: let them reach the recording.
        deadline = time.monotonic() + DRAIN_TIMEOUT
        signals = [scenario.topics[name] for name in 'ruy']
        while time.monotonic() < deadline and \
                any(recorder.counts[topic] < published for topic in signals):
            time.sleep(0.01)
        return published


def _stop(process: subprocess.Popen) -> None:
    """Stop the node as Ctrl-C would (it exits cleanly on SIGTERM), killing it if it hangs."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def run_replay(bag: Path, node_file: Path, output: Path, report: Path) -> int:
    """
    Run ``ctid replay BAG --sliding --plot --output`` exactly as a user would.

    Its table and messages go to ``report``; the figures are ``output/replay*.png`` and the
    estimates ``output/replay_estimates.mcap``. Returns the command's exit status.
    """
    arguments = ['replay', str(bag), '--params-file', str(node_file), '--sliding',
                 '--plot', str(output / 'replay.png'),
                 '--output', str(output / 'replay_estimates.mcap')]
    (output / 'replay_estimates.mcap').unlink(missing_ok=True)
    with open(report, 'w', encoding='utf-8') as stream, redirect_stdout(stream), \
            redirect_stderr(stream):
        print('ctid ' + ' '.join(arguments))
        return cli.main(arguments)


def read_estimates(path: Path, names: Sequence[str], start_ns: int) -> Series:
    """Read the estimates, standard deviations and fits of an MCAP written by ``--output``."""
    rows: Dict[str, List[Any]] = {NODE.estimate: [], NODE.estimate_std: [],
                                  NODE.diagnostics: []}
    times, alarms = [], []
    with BagReader(path) as bag:
        for topic, log_time_ns, msg in bag.messages(list(rows)):
            if topic == NODE.estimate:
                times.append((log_time_ns - start_ns) / NANOSECONDS)
                if msg.layout.dim[0].label.split(',') != list(names):
                    raise CtidError(f'{path}: estimates of {msg.layout.dim[0].label}, '
                                    f'expected {",".join(names)}')
            if topic == NODE.diagnostics:
                values = {pair.key: pair.value for pair in msg.status[0].values}
                # A tick that gave no estimate has a status but no fit.
                if 'fit_percent' in values:
                    rows[topic].append(float(values['fit_percent']))
                    # The replay counts the alarm's times from the start of the bag.
                    alarms.append(_alarm_of(values, bag.start_time_ns))
            else:
                rows[topic].append(list(msg.data))
    return Series(np.array(times), np.array(rows[NODE.estimate]).reshape(-1, len(names)),
                  np.array(rows[NODE.estimate_std]).reshape(-1, len(names)),
                  np.array(rows[NODE.diagnostics]), tuple(names), tuple(alarms))


def summary(scenario: Scenario, config: IdentificationConfig, replayed: Series,
            live: Series) -> str:
    """
    Compare the estimates with the truth on the last window before the drift and the last one.

    Each block is a window lying entirely on one side of the drift; the replay's estimate is
    shown with its error, the live node's next to it.
    """
    drift = scenario.drift_time
    blocks = (('before the payload', scenario.before, {'latest': drift}),
              ('after the payload', scenario.after, {'earliest': drift + config.window}))
    header = (f'  {"parameter":<10}{"truth":>10}{"ctid replay":>{CELL_WIDTH + 2}}'
              f'{"error":>9}{"live node":>{CELL_WIDTH + 2}}')
    lines = []
    for title, truth, selection in blocks:
        index = replayed.last(**selection)
        if index is None:
            continue
        live_index = live.last(**selection)
        lines += [f'{title} (window ending at {replayed.times[index]:.2f} s, fit '
                  f'{replayed.fits[index]:.1f} %):', header]
        for column, name in enumerate(replayed.names):
            value, std = replayed.values[index, column], replayed.stds[index, column]
            live_cell = '-' if live_index is None else format_estimate(
                live.values[live_index, column], live.stds[live_index, column])
            lines.append(f'  {name:<10}{truth[name]:>10.4g}'
                         f'{format_estimate(value, std):>{CELL_WIDTH + 2}}'
                         f'{100 * (value - truth[name]) / truth[name]:>+8.2f}%'
                         f'{live_cell:>{CELL_WIDTH + 2}}')
    return '\n'.join(lines)


def alarm_summary(scenario: Scenario, live: Series, replayed: Series, start_ns: int) -> str:
    """
    Say what the change alarm did, live and replayed.

    For each: the alarms raised before the payload, and the first one after it with its delay in
    update periods.
    """
    lines = ['change alarm (against the data-sheet baseline of the params file):']
    for label, series in (('live node', live), ('ctid replay', replayed)):
        raised = [(time_s, alarm) for time_s, alarm in zip(series.times, series.alarms)
                  if alarm.level == ERROR]
        before = [time_s for time_s, _ in raised if time_s < scenario.drift_time]
        after = [(time_s, alarm) for time_s, alarm in raised if time_s >= scenario.drift_time]
        period = np.median(np.diff(series.times)) if series.times.size > 1 else math.nan
        text = f'  {label}: {len(before)} alarm(s) before the payload'
        if after:
            time_s, alarm = after[0]
            delay = (time_s - scenario.drift_time) / period
            text += (f'; raised at t={time_s:.2f} s, {delay:.1f} update periods after it: '
                     f'{alarm.summary}')
        else:
            text += '; none after it'
        lines.append(text)
    return '\n'.join(lines)


def write_figures(scenario: Scenario, replayed: Series, output: Path,
                  units: Optional[Dict[str, str]] = None) -> Path:
    """Draw the replay's estimates with ±2σ bands against the drifting truth, and its alarms."""
    # Imported here: the plant process imports this module too and needs no matplotlib.
    from ctid_ros.cli.plots import mark_alarms, parameters_figure

    path = output / 'parameters.png'
    figure = parameters_figure(replayed.times, replayed.names, replayed.values, replayed.stds,
                               truth=scenario.truth, units=units)
    mark_alarms(figure, replayed.times, replayed.names, replayed.alarms, path=path)
    return path


def copy_to_docs(output: Path, directory: Path = DOCS_DIRECTORY) -> List[Path]:
    """Copy the figures the README shows into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    return [Path(shutil.copyfile(output / source, directory / target))
            for source, target in DOC_FIGURES.items()]


def _introduction(scenario: Scenario, config: IdentificationConfig, node_file: str,
                  bag: Path, log: Path) -> str:
    truth = ', '.join(f'{name} = {value:g}' for name, value in scenario.before.items())
    delay = scenario.before.get('tau')
    samples = '' if delay is None else f' (dead time {delay / scenario.sample_time:.2f} samples)'
    kp, ki = scenario.pi_gains
    return '\n'.join([
        'ctid_ros demo: a wheel drive identified in closed loop, live on ROS 2, then replayed',
        '',
        f'plant      {scenario.model} from torque command u to wheel speed y, '
        f'{1 / scenario.sample_time:g} Hz',
        f'truth      {truth}{samples}',
        f'drift      at t = {scenario.drift_time:g} s a payload is picked up: '
        f'{scenario.drift_text()}',
        f'loop       digital PI (kp {kp:g}, ki {ki:g}) on the measured speed (noise std '
        f'{scenario.noise_std:g}), PRBS speed reference',
        f'node       ctid_node --ros-args --params-file {node_file} (window {config.window:g} s, '
        f'every {config.update_period:g} s; log {log})',
        f'recording  {bag} (ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID")}, loopback only)',
        '',
        'live estimates of ctid_node (end of window, estimate ± std, fit of the window):'])


def _shown(path: Path) -> str:
    """Return ``path`` relative to the working directory when it is below it."""
    try:
        return str(path.resolve().relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def main(argv: Optional[List[str]] = None) -> int:
    """Run the demonstration; return the exit status."""
    parser = argparse.ArgumentParser(
        prog='python -m ctid_ros.demo',
        description='Identify a wheel drive in closed loop live on ROS 2, record it, replay it '
        'with ctid replay and plot the results.')
    parser.add_argument('--output', type=Path, default=Path('demo_output'),
                        help='directory for the recording, figures and reports '
                        '(default demo_output)')
    parser.add_argument('--duration', type=float, default=None,
                        help='seconds of live run; the payload is picked up halfway '
                        '(default: twice the drift_time of the plant params file)')
    parser.add_argument('--params-file', type=Path, default=None,
                        help=f'params file of ctid_node (default config/{NODE_CONFIG}.yaml)')
    parser.add_argument('--docs', action='store_true',
                        help=f'also copy the figures to {DOCS_DIRECTORY} for the README')
    arguments = parser.parse_args(argv)
    # SIGTERM ends the demo as Ctrl-C does: the node and the plant are stopped on the way out.
    # Ctrl-C reaches the node too, which may exit first: its exit is then no error.
    _INTERRUPTED.clear()
    previous = {number: signal.signal(number, _interrupt)
                for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(arguments)
    except KeyboardInterrupt:
        print('\ndemo: interrupted; the node and the plant are stopped', file=sys.stderr)
        # Skip the interpreter's last garbage collection over the whole heap (seconds).
        gc.freeze()
        return 0
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _interrupt(signal_number: int, frame: Any) -> None:
    _INTERRUPTED.set()
    raise KeyboardInterrupt


def _run(arguments: argparse.Namespace) -> int:
    """Run the demonstration with the parsed command line; return the exit status."""
    started = time.monotonic()
    scenario = Scenario.load(find_config(PLANT_CONFIG))
    duration = arguments.duration or 2 * scenario.drift_time
    scenario = replace(scenario, drift_time=duration / 2)
    node_file = arguments.params_file or find_config(NODE_CONFIG)
    output = arguments.output
    output.mkdir(parents=True, exist_ok=True)
    bag, log, report = output / 'wheel.mcap', output / 'node.log', output / 'replay.txt'
    try:
        config = load_params_file(node_file)
        _isolate_dds()
        print(_introduction(scenario, config, _shown(node_file), bag, log), flush=True)
        live = run_live(scenario, node_file, bag, duration, log)
        live_done = time.monotonic()
        print(f'\nrecorded {live.published} samples per signal; replaying offline: ctid replay '
              f'{bag} --params-file {_shown(node_file)} --sliding --plot ... (output in '
              f'{report})', flush=True)
        status = run_replay(bag, node_file, output, report)
        if status:
            print(f'demo: ctid replay failed (status {status}); see {report}', file=sys.stderr)
            return status
        replayed = read_estimates(output / 'replay_estimates.mcap', config.names,
                                  live.start_ns)
    except CtidError as error:
        if _INTERRUPTED.is_set():
            raise KeyboardInterrupt from None
        print(f'demo: error: {error}', file=sys.stderr)
        return 1
    figures = [output / name for name in DOC_FIGURES if name != 'parameters.png']
    figures.insert(1, write_figures(scenario, replayed, output, load_units(node_file)))
    print(f'replayed {replayed.times.size} windows in {time.monotonic() - live_done:.1f} s\n')
    print(summary(scenario, config, replayed, live.series))
    print(alarm_summary(scenario, live.series, replayed, live.start_ns))
    print('\nfigures: ' + ', '.join(str(path) for path in figures))
    if arguments.docs:
        print('copied to ' + ', '.join(_shown(path) for path in copy_to_docs(output)))
    print(f'demo finished in {time.monotonic() - started:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
