"""
``ctid replay`` on bags written by independent writers from simulated plants.

The recordings are written here with rosbags (rosbag2 directories, sqlite3 and mcap storage)
and mcap_ros2 (standalone .mcap), from plants with known parameters, sampled at 100 Hz.

Tolerances: the output noise is 1 % of the output's standard deviation (40 dB SNR, seeded); over
a 20-30 s span the reported standard deviations are below 0.1 % of the values, and the 1 ms by
which the output is logged after the input biases the dead time by about 1 ms (0.4 % of tau).
Sliding 10 s windows, of which the automatic transient leaves 5 s to fit, scatter by up to 1-2 %.
So 3 % relative (5 % for the closed loop, seen through the controller, and for the truncated
file) is several times what noise and stamping explain, while a wrong stamp rule, field or
window misses by far more.
"""

import hashlib
import json

from bag_fixtures import _build, MSGDEFS, Record
from ctid_ros import Model
from ctid_ros.cli.main import main
from ctid_ros.core.excitation import prbs
from ctid_ros.errors import ConfigError
from ctid_ros.streaming.buffer import resample
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.message_fields import sample_stamp
from ctid_ros.streaming.replay import Progress, replay_messages, resolve_topic
from ctid_ros.streaming.session import buffer_capacity, IdentificationSession
from mcap_ros2.writer import Writer as McapRos2Writer
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import yaml

T0_NS = 1_700_000_000_000_000_000
TS = 0.01
STEP_NS = 10_000_000
# The measurement is logged 1 ms after the command of the same instant, as a recorder sees it.
Y_LAG_NS = 1_000_000
FLOAT64 = 'std_msgs/msg/Float64'
JOINT_STATE = 'sensor_msgs/msg/JointState'

DELAY = {'model': 'K*exp(-tau*s)/(T*s + 1)', 'truth': {'K': 2.0, 'T': 1.5, 'tau': 0.237},
         'params': {'parameter_names': ['K', 'T', 'tau'], 'lower': [0.01, 0.01, 0.0],
                    'upper': [100.0, 100.0, 2.0], 'delay_min': 0.0, 'delay_max': 1.0}}
OPEN_LOOP = {'model': '1/(m*s**2 + d*s + k)', 'truth': {'m': 0.5, 'd': 1.0, 'k': 50.0},
             'params': {'parameter_names': ['m', 'd', 'k'], 'lower': [0.001, 0.0, 0.0],
                        'upper': [100.0, 100.0, 1000.0]}}
CLOSED_LOOP = {'model': '1/(m*s**2 + d*s + k)', 'controller': '20 + 10/s',
               'truth': {'m': 1.0, 'd': 2.0, 'k': 10.0},
               'params': {'parameter_names': ['m', 'd', 'k'], 'initial': [0.5, 1.0, 5.0],
                          'lower': [0.001, 0.0, 0.0], 'upper': [100.0, 100.0, 1000.0]}}


def simulate(case, seconds, seed=0):
    """Return the input (PRBS, bits of 0.2 s) and the noisy output (40 dB SNR) of a case."""
    u = prbs(10, 20)[:round(seconds / TS)]
    y = Model(case['model'], case.get('controller')).simulate(case['truth'], u, TS)
    noise = np.random.default_rng(seed).standard_normal(y.size)
    return u, y + 0.01 * np.std(y) * noise


def float_records(u, y, input_topic='/plant/u', output_topic='/plant/y'):
    """Return Float64 records in log-time order: input at t_k, output 1 ms later."""
    records = []
    for k, (u_k, y_k) in enumerate(zip(u, y)):
        records.append(Record(input_topic, T0_NS + k * STEP_NS, {'data': float(u_k)}))
        records.append(Record(output_topic, T0_NS + k * STEP_NS + Y_LAG_NS, {'data': float(y_k)}))
    return records


def joint_state_records(u, y, latency_ns):
    """Return JointStates stamped at t_k but logged ``latency_ns`` (plus jitter) later."""
    jitter = np.random.default_rng(1).integers(0, 3_000_000, size=len(u))
    records = []
    for k, (u_k, y_k) in enumerate(zip(u, y)):
        stamp_ns = T0_NS + k * STEP_NS
        records.append(Record('/joint_states', stamp_ns + latency_ns + int(jitter[k]), {
            'header': {'stamp': {'sec': stamp_ns // 10 ** 9, 'nanosec': stamp_ns % 10 ** 9},
                       'frame_id': 'base'},
            'name': ['joint'], 'position': [float(y_k)], 'velocity': [0.0],
            'effort': [float(u_k)]}))
    return sorted(records, key=lambda record: record.time_ns)


def types_of(records):
    return {record.topic: JOINT_STATE if 'header' in record.fields else FLOAT64
            for record in records}


def write_rosbag2(path, records, storage):
    """Write a rosbag2 directory with rosbags (sqlite3 or mcap storage)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.SQLITE3 if storage == 'sqlite3' else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        connections = {topic: (writer.add_connection(topic, msgtype, typestore=typestore),
                               msgtype) for topic, msgtype in types_of(records).items()}
        for record in records:
            connection, msgtype = connections[record.topic]
            msg = _build(typestore, msgtype, record.fields)
            writer.write(connection, record.time_ns, typestore.serialize_cdr(msg, msgtype))
    return path


def write_mcap(path, records, chunk_size=16384):
    """Write a standalone .mcap with mcap_ros2."""
    with open(path, 'wb') as stream, McapRos2Writer(stream, chunk_size=chunk_size) as writer:
        schemas = {msgtype: writer.register_msgdef(msgtype, MSGDEFS[msgtype])
                   for msgtype in set(types_of(records).values())}
        types = types_of(records)
        for record in records:
            writer.write_message(record.topic, schemas[types[record.topic]], record.fields,
                                 log_time=record.time_ns, publish_time=record.time_ns)
    return path


def write_bag(tmp_path, records, kind):
    if kind == 'mcap-file':
        return write_mcap(tmp_path / 'run.mcap', records)
    return write_rosbag2(tmp_path / 'run', records, kind)


def params_file(tmp_path, case, node='ctid_node', **overrides):
    """Write a params YAML in the format of config/*.yaml and return its path."""
    values = {'input_topic': '/plant/u', 'input_field': 'data', 'output_topic': '/plant/y',
              'output_field': 'data', 'model': case['model'],
              'controller': case.get('controller', ''), 'sample_time': TS, 'window': 10.0,
              'update_period': 5.0, 'max_gap': 0.5, 'reorder_horizon': 0.05,
              **case['params'], **overrides}
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump({node: {'ros__parameters': values}}))
    return path


def replay(capsys, *arguments):
    """Run ``ctid replay`` and return (exit code, stdout, stderr)."""
    code = main(['replay', *map(str, arguments)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def digest(path):
    files = sorted(path.rglob('*')) if path.is_dir() else [path]
    return hashlib.sha256(b''.join(file.read_bytes() for file in files if file.is_file())
                          ).hexdigest()


@pytest.mark.parametrize('kind', ['sqlite3', 'mcap', 'mcap-file'])
def test_fractional_delay_recovered_from_every_storage(tmp_path, capsys, kind):
    u, y = simulate(DELAY, 30.0)
    bag = write_bag(tmp_path, float_records(u, y), kind)
    code, out, _ = replay(capsys, bag, '--params-file', params_file(tmp_path, DELAY), '--json')
    assert code == 0
    result = json.loads(out)
    assert set(result) >= {'params', 'std', 'fit', 'converged', 'warnings', 'time'}
    assert result['params'] == pytest.approx(DELAY['truth'], rel=0.03)
    assert result['fit'] > 95.0
    # One estimate over the whole span, not the configured 10 s window.
    assert result['time'] == pytest.approx((T0_NS + (u.size - 1) * STEP_NS) / 1e9, abs=0.02)


def test_open_loop_second_order_table(tmp_path, capsys):
    u, y = simulate(OPEN_LOOP, 20.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap')
    code, out, err = replay(capsys, bag, '--params-file', params_file(tmp_path, OPEN_LOOP))
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].split()[:3] == ['parameter', 'estimate', 'std']
    rows = {line.split()[0]: float(line.split()[1]) for line in lines[1:4]}
    assert list(rows) == ['m', 'd', 'k']
    assert rows == pytest.approx(OPEN_LOOP['truth'], rel=0.03)
    assert 'converged yes' in out
    assert '/plant/u: 2000 samples used of 2000 (non-finite 0' in out


def test_closed_loop_reference_and_output(tmp_path, capsys):
    r, y = simulate(CLOSED_LOOP, 30.0)
    bag = write_bag(tmp_path, float_records(r, y, input_topic='/plant/r'), 'sqlite3')
    params = params_file(tmp_path, CLOSED_LOOP, input_topic='/plant/r')
    code, out, err = replay(capsys, bag, '--params-file', params, '--json')
    assert code == 0, err
    assert json.loads(out)['params'] == pytest.approx(CLOSED_LOOP['truth'], rel=0.05)


def test_truncated_mcap_replays_the_readable_part(tmp_path, capsys):
    u, y = simulate(DELAY, 40.0)
    whole = write_mcap(tmp_path / 'whole.mcap', float_records(u, y))
    cut = tmp_path / 'cut.mcap'
    data = whole.read_bytes()
    cut.write_bytes(data[:int(0.6 * len(data))])
    code, out, err = replay(capsys, cut, '--params-file', params_file(tmp_path, DELAY), '--json')
    assert code == 0
    assert 'truncated' in err and 'warning' in err
    result = json.loads(out)
    assert result['params'] == pytest.approx(DELAY['truth'], rel=0.05)
    # Roughly the first 60 % of the 40 s survive.
    assert 18.0 < result['time'] - T0_NS / 1e9 < 25.0


def test_missing_topic_lists_the_topics_of_the_bag(tmp_path, capsys):
    u, y = simulate(DELAY, 5.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    params = params_file(tmp_path, DELAY, input_topic='/plant/command')
    output = tmp_path / 'estimates.mcap'
    code, out, err = replay(capsys, bag, '--params-file', params, '--output', output)
    assert code == 2 and out == ''
    assert not output.exists()      # no half-written output is left behind
    assert err.startswith('ctid replay: error: topic(s) /plant/command not in')
    assert '/plant/u (std_msgs/msg/Float64, 500 messages)' in err
    assert '/plant/y' in err


def test_wrong_field_path_stops_at_the_first_message_listing_its_fields(tmp_path):
    u, y = simulate(OPEN_LOOP, 5.0)
    records = joint_state_records(u, y, latency_ns=0)
    config = IdentificationConfig(input_topic='/joint_states', input_field='effort[0]',
                                  output_topic='/joint_states', output_field='positions[0]',
                                  model=OPEN_LOOP['model'])
    seen = []

    def messages():
        for record in records:
            seen.append(record)
            yield record.topic, record.time_ns, _build(get_typestore(Stores.ROS2_JAZZY),
                                                       JOINT_STATE, record.fields)

    with pytest.raises(ConfigError, match=r"no field 'positions'; available fields: header, "
                                          r'name, position, velocity, effort'):
        replay_messages(messages(), config)
    assert len(seen) == 1


def test_header_stamps_are_used_when_configured(tmp_path, capsys):
    u, y = simulate(OPEN_LOOP, 20.0)
    latency_ns = 300_000_000
    bag = write_bag(tmp_path, joint_state_records(u, y, latency_ns), 'mcap-file')
    common = {'input_topic': '/joint_states', 'input_field': 'effort[0]',
              'output_topic': '/joint_states', 'output_field': 'position[0]'}
    last_stamp = (T0_NS + (u.size - 1) * STEP_NS) / 1e9
    code, out, _ = replay(capsys, bag, '--params-file',
                          params_file(tmp_path, OPEN_LOOP, stamp_source='header', **common),
                          '--json')
    assert code == 0
    header = json.loads(out)
    assert header['time'] == pytest.approx(last_stamp, abs=1e-6)
    assert header['params'] == pytest.approx(OPEN_LOOP['truth'], rel=0.03)
    code, out, _ = replay(capsys, bag, '--params-file',
                          params_file(tmp_path, OPEN_LOOP, stamp_source='receive', **common),
                          '--json')
    assert code == 0
    # Receive (log) times: later by the latency, and jittered, which the fit shows.
    assert json.loads(out)['time'] > last_stamp + 0.29
    assert json.loads(out)['fit'] < header['fit']


def test_sliding_gives_one_estimate_per_update_period(tmp_path, capsys):
    u, y = simulate(DELAY, 21.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    params = params_file(tmp_path, DELAY)
    code, out, err = replay(capsys, bag, '--params-file', params, '--sliding', '--json')
    assert code == 0
    results = json.loads(out)
    # Ticks 5, 10, 15 and 20 s after the first message (the bag ends before 25 s); at 5 s less
    # than half a window is buffered, so no estimate and a note on stderr.
    times = np.array([result['time'] for result in results]) - T0_NS / 1e9
    assert times == pytest.approx([10, 15, 20], abs=0.1)
    assert np.diff(times) == pytest.approx(5.0, abs=1e-9)
    assert 'no estimate at t=5.00 s: not enough contiguous data' in err
    for result in results:
        assert result['params'] == pytest.approx(DELAY['truth'], rel=0.03)
    code, out, _ = replay(capsys, bag, '--params-file', params, '--sliding', '--end', '16')
    assert code == 0
    header, *rows = out.split('\n\n')[0].splitlines()
    assert header.split() == ['time', 's', 'K', 'T', 'tau', 'fit', '%']
    # Window ends: the tick less the reorder horizon (settled data), on the sample grid.
    assert [row.split()[0] for row in rows] == ['9.94', '14.94']


def test_sliding_agrees_with_a_buffer_fed_message_by_message():
    u, y = simulate(OPEN_LOOP, 16.0)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    messages = [(record.topic, record.time_ns, _build(typestore, FLOAT64, record.fields))
                for record in float_records(u, y)]
    params = {key: tuple(value) for key, value in OPEN_LOOP['params'].items()}
    config = IdentificationConfig(model=OPEN_LOOP['model'], input_topic='/plant/u',
                                  output_topic='/plant/y', window=8.0, update_period=4.0,
                                  **params)
    updates = replay_messages(messages, config, sliding=True).updates
    assert len(updates) == 2    # ticks at 4 s (too little data), 8 s and 12 s

    def streams(until_ns):
        return [value for topic in ('/plant/u', '/plant/y') for value in zip(*[
            (stamp, msg.data) for name, stamp, msg in messages
            if name == topic and stamp <= until_ns])]

    # A tick at T estimates on what was logged up to T, whatever the buffer size; the span is
    # the window plus the settling transient the session asks for.
    window, _ = resample(*streams(T0_NS + 12 * 10 ** 9), TS,
                         length=updates[-1].window.requested * TS, end_ns=updates[-1].end_ns,
                         min_length=4.0)
    assert np.array_equal(window.data.y, updates[-1].window.data.y)
    big = replay_messages(messages, config, sliding=True, capacity=100_000).updates
    assert [update.values.tolist() for update in big] == [update.values.tolist()
                                                          for update in updates]
    # The default mode is one estimate over everything, as resample() of the whole recording.
    whole, _ = resample(*streams(T0_NS + 10 ** 12), TS)
    single = replay_messages(messages, config).updates[0]
    assert np.array_equal(IdentificationSession(config).update(whole).values, single.values)


def test_output_mcap_has_the_node_topics_and_the_input_is_unchanged(tmp_path, capsys):
    u, y = simulate(OPEN_LOOP, 20.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap')
    before = digest(bag)
    output = tmp_path / 'estimates.mcap'
    params = params_file(tmp_path, OPEN_LOOP, node='/lab/ctid_node')
    code, _, err = replay(capsys, bag, '--params-file', params, '--sliding', '--output', output,
                          '--node-name', '/lab/ctid_node')
    assert code == 0, err
    assert digest(bag) == before
    with AnyReader([output]) as reader:
        counts = {name: info.msgcount for name, info in reader.topics.items()}
        estimates = [reader.deserialize(data, conn.msgtype) for conn, _, data in
                     reader.messages([c for c in reader.connections
                                      if c.topic == '/lab/ctid_node/estimate'])]
    assert counts['/lab/ctid_node/estimate'] == counts['/lab/ctid_node/estimate_std'] == 2
    assert counts['/lab/ctid_node/params/k'] == counts['/diagnostics'] == 2
    # As the live node: one prediction array per update.
    assert counts['/lab/ctid_node/prediction'] == 2
    assert estimates[0].layout.dim[0].label == 'm,d,k'
    assert estimates[-1].data == pytest.approx([0.5, 1.0, 50.0], rel=0.03)
    code, _, err = replay(capsys, bag, '--params-file', params, '--node-name',
                          '/lab/ctid_node', '--output', bag / 'inside.mcap')
    assert code == 2 and 'refusing' in err
    assert digest(bag) == before


def test_no_samples_in_the_selected_span(tmp_path, capsys):
    u, y = simulate(DELAY, 10.0)
    records = [record for record in float_records(u, y)
               if record.topic == '/plant/u' or record.time_ns < T0_NS + 4 * 10 ** 9]
    bag = write_bag(tmp_path, records, 'mcap-file')
    params = params_file(tmp_path, DELAY)
    code, _, err = replay(capsys, bag, '--params-file', params, '--start', '6')
    assert code == 2
    assert 'no messages of the output /plant/y (data) in the selected span' in err
    code, _, err = replay(capsys, bag, '--params-file', params, '--start', '60')
    assert code == 2 and 'start 60.0 s is after the last message' in err


def test_plot_files(tmp_path, capsys):
    u, y = simulate(OPEN_LOOP, 20.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    params = params_file(tmp_path, OPEN_LOOP)
    code, _, err = replay(capsys, bag, '--params-file', params, '--plot', tmp_path / 'fit.png')
    assert code == 0, err
    assert sorted(path.name for path in tmp_path.glob('*.png')) == ['fit.png', 'fit_bode.png']
    code, _, err = replay(capsys, bag, '--params-file', params, '--sliding', '--end', '16',
                          '--plot', tmp_path / 'slide.png')
    assert code == 0, err
    for name in ('slide.png', 'slide_params.png', 'slide_bode.png'):
        assert (tmp_path / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_nan_samples_are_counted(tmp_path, capsys):
    u, y = simulate(DELAY, 20.0)
    y[::50] = np.nan
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    code, out, _ = replay(capsys, bag, '--params-file', params_file(tmp_path, DELAY))
    assert code == 0
    assert '/plant/y: 1960 samples used of 2000 (non-finite 40, duplicates 0, late 0)' in out


def test_stamp_rule_and_topic_resolution():
    class Stamp:
        __slots__ = ('sec', 'nanosec')

        def __init__(self, sec, nanosec):
            self.sec, self.nanosec = sec, nanosec

    class Header:
        __slots__ = ('stamp',)

        def __init__(self, stamp):
            self.stamp = stamp

    class Stamped:
        __slots__ = ('header', 'data')

        def __init__(self, sec, nanosec):
            self.header, self.data = Header(Stamp(sec, nanosec)), 1.0

    assert sample_stamp(Stamped(3, 5), 99, 'header') == 3_000_000_005
    assert sample_stamp(Stamped(3, 5), 99, 'receive') == 99
    assert sample_stamp(Stamped(0, 0), 99, 'header') == 99   # unset header: receive time
    assert resolve_topic('/plant/u', '/lab/ctid_node') == '/plant/u'
    assert resolve_topic('u', 'ctid_node') == '/u'
    assert resolve_topic('u', '/lab/ctid_node') == '/lab/u'
    assert resolve_topic('~/u', '/lab/ctid_node') == '/lab/ctid_node/u'
    config = IdentificationConfig(model='K/(T*s + 1)', window=10.0, max_gap=0.5,
                                  reorder_horizon=0.05)
    # Window plus an automatic transient of at most one window, gap and horizon, twice over.
    assert buffer_capacity(config, 100.0) == 4110


def test_progress_bar_only_on_a_terminal():
    class Terminal:
        def __init__(self, tty):
            self.tty, self.text = tty, ''

        def isatty(self):
            return self.tty

        def write(self, text):
            self.text += text

        def flush(self):
            pass

    items = [('/u', T0_NS + k * 10 ** 8, None) for k in range(11)]
    terminal = Terminal(True)
    assert list(Progress(terminal, T0_NS, T0_NS + 10 ** 9).track(items)) == items
    assert '\rreplaying [' in terminal.text and '100 %' in terminal.text
    assert terminal.text.endswith('\r')
    pipe = Terminal(False)
    assert list(Progress(pipe, T0_NS, T0_NS + 10 ** 9).track(items)) == items
    assert pipe.text == ''


def test_absent_bag(tmp_path, capsys):
    code, _, err = replay(capsys, tmp_path / 'absent', '--params-file',
                          params_file(tmp_path, DELAY))
    assert code == 2 and 'does not exist' in err


def test_two_inputs_from_one_joint_state(tmp_path, capsys):
    """A model equation whose second input is effort[1] of the same JointState."""
    model = Model('T*s*q + q = K1*v + K2*w', inputs=('v', 'w'), output='q')
    truth = {'T': 0.5, 'K1': 2.0, 'K2': -1.0}
    rng = np.random.default_rng(4)
    u = np.column_stack([prbs(10, 10)[:2500], np.repeat(rng.standard_normal(250), 10)])
    clean = model.simulate(truth, u, TS)
    y = clean + 0.01 * np.std(clean) * rng.standard_normal(clean.size)
    records = joint_state_records(u[:, 0], y, 2_000_000)
    # The jitter (< 3 ms) is below the 10 ms step, so log order is stamp order.
    for record, second in zip(records, u[:, 1]):
        record.fields['effort'].append(float(second))
    bag = write_bag(tmp_path, records, 'mcap-file')
    params = params_file(
        tmp_path, {'model': 'T*s*q + q = K1*v + K2*w', 'params': {}},
        input_topic='/joint_states', output_topic='/joint_states', input_field='effort[0]',
        output_field='position[0]', extra_input_fields=['effort[1]'], input_names=['v', 'w'],
        output_name='q', stamp_source='header')
    code, out, err = replay(capsys, bag, '--params-file', params, '--json')
    assert code == 0, err
    assert json.loads(out)['params'] == pytest.approx(truth, rel=0.03)
