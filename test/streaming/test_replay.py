"""
The replay engine: messages through the live node's sampler, buffer and session.

Recordings from replay_fixtures (simulated plants, 40 dB SNR); the ``ctid replay`` command is
tested in test/cli/test_replay.py.
"""

import json

from bag_fixtures import build_message
from ctid_ros.cli.main import main
from ctid_ros.errors import ConfigError
from ctid_ros.streaming.buffer import resample
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import WARN
from ctid_ros.streaming.message_fields import sample_stamp
from ctid_ros.streaming.replay import replay_messages
from ctid_ros.streaming.sampler import WRONG_PATH_MESSAGES
from ctid_ros.streaming.session import buffer_capacity, IdentificationSession
import numpy as np
import pytest
from replay_fixtures import (FLOAT64, float_records, JOINT_STATE, joint_state_records,
                             name_joints, OPEN_LOOP, params_file, simulate, T0_NS, TS, write_bag)
from rosbags.typesys import get_typestore, Stores


def test_wrong_field_path_stops_the_replay_listing_its_fields(tmp_path):
    # Not at the first message: a type that holds the path may come later (a String publisher
    # before the JointState one), as the live node waits for one; after WRONG_PATH_MESSAGES
    # messages without one, it is a wrong path.
    u, y = simulate(OPEN_LOOP, 15.0)
    records = joint_state_records(u, y, latency_ns=0)
    config = IdentificationConfig(input_topic='/joint_states', input_field='effort[0]',
                                  output_topic='/joint_states', output_field='positions[0]',
                                  model=OPEN_LOOP['model'])
    seen = []

    def messages():
        for record in records:
            seen.append(record)
            msg = build_message(get_typestore(Stores.ROS2_JAZZY), JOINT_STATE, record.fields)
            yield record.topic, record.time_ns, msg

    with pytest.raises(ConfigError, match=r"no field 'positions'; available fields: header, "
                                          r'name, position, velocity, effort'):
        replay_messages(messages(), config)
    assert len(seen) == WRONG_PATH_MESSAGES < len(records)


def test_sliding_agrees_with_a_buffer_fed_message_by_message():
    u, y = simulate(OPEN_LOOP, 16.0)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    messages = [(record.topic, record.time_ns, build_message(typestore, FLOAT64, record.fields))
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
    # the window plus the settling transient the session asks for. The output is logged 1 ms
    # after the input: taken at its own samples, 1 ms after the grid instants.
    last = updates[-1].window.data
    assert last.output_skew == pytest.approx(0.001)
    window, _ = resample(*streams(T0_NS + 12 * 10 ** 9), TS,
                         length=updates[-1].window.requested * TS,
                         end_ns=updates[-1].end_ns + 1_000_000, min_length=4.0)
    assert np.array_equal(window.data.y, updates[-1].window.data.y)
    big = replay_messages(messages, config, sliding=True, capacity=100_000).updates
    assert [update.values.tolist() for update in big] == [update.values.tolist()
                                                          for update in updates]
    # The default mode is one estimate over everything, as resample() of the whole recording.
    whole, _ = resample(*streams(T0_NS + 10 ** 12), TS)
    single = replay_messages(messages, config).updates[0]
    assert np.array_equal(IdentificationSession(config).update(whole).values, single.values)


def test_stamp_rule_and_buffer_capacity():
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
    config = IdentificationConfig(model='K/(T*s + 1)', window=10.0, max_gap=0.5,
                                  reorder_horizon=0.05)
    # Window plus an automatic transient of at most one window, gap and horizon, twice over.
    assert buffer_capacity(config, 100.0) == 4110


def test_ticks_without_an_estimate_are_reported_with_their_status_level():
    u, y = simulate(OPEN_LOOP, 9.0)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    messages = [(record.topic, record.time_ns, build_message(typestore, FLOAT64, record.fields))
                for record in float_records(u, y)]
    params = {key: tuple(value) for key, value in OPEN_LOOP['params'].items()}
    config = IdentificationConfig(model=OPEN_LOOP['model'], input_topic='/plant/u',
                                  output_topic='/plant/y', window=8.0, update_period=2.0,
                                  **params)
    replay = replay_messages(messages, config, sliding=True)
    # Ticks at 2 s and 4 s (less than half a window of settled data), 6 s and 8 s.
    assert [tick.time_ns - T0_NS for tick in replay.skipped] == [2 * 10**9, 4 * 10**9]
    for tick in replay.skipped:
        assert tick.level == WARN and tick.reason.startswith('not enough contiguous data')
    assert len(replay.updates) == 2


@pytest.mark.parametrize('kind', ['sqlite3', 'mcap-file'])
def test_joint_names_select_the_joint_in_a_recording(tmp_path, capsys, kind):
    """Select one of three joints by name in JointStates that list them in a changing order."""
    u, y = simulate(OPEN_LOOP, 20.0)
    records = name_joints(joint_state_records(u, y, latency_ns=2_000_000))
    bag = write_bag(tmp_path, records, kind)
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[joint]',
                         output_field='position[joint]', stamp_source='header')
    code = main(['replay', str(bag), '--params-file', str(params), '--json'])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert json.loads(out)['params'] == pytest.approx(OPEN_LOOP['truth'], rel=0.03)
    # A joint that is not there: the names of the first message are listed.
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[joint]',
                         output_field='position[wheel_left]', stamp_source='header')
    code = main(['replay', str(bag), '--params-file', str(params)])
    assert code != 0
    assert "no joint 'wheel_left' in name; names seen: wheel_right, joint, arm" in \
        capsys.readouterr().err


def test_update_covariance_is_in_publishing_order():
    u, y = simulate(OPEN_LOOP, 10.0)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    messages = [(record.topic, record.time_ns, build_message(typestore, FLOAT64, record.fields))
                for record in float_records(u, y)]
    config = IdentificationConfig(model=OPEN_LOOP['model'], input_topic='/plant/u',
                                  output_topic='/plant/y', parameter_names=('k', 'm', 'd'),
                                  lower=(0.0, 0.001, 0.0), upper=(1000.0, 100.0, 100.0))
    (update,) = replay_messages(messages, config).updates
    assert update.names == ('k', 'm', 'd')
    assert update.covariance.shape == (3, 3)
    np.testing.assert_allclose(np.sqrt(np.diag(update.covariance)), update.stds, rtol=1e-12)
    model_order = update.result.model.parameters
    assert update.covariance[0, 1] == update.result.covariance[model_order.index('k'),
                                                               model_order.index('m')]
