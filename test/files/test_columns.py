"""
The columnar replay gives the streaming replay's numbers on the same bags.

Bags of replay_fixtures (rosbags sqlite3 and mcap directories, mcap_ros2 standalone files) with
Float64 topics (no header) and JointState (header stamps, a shared input/output topic, two
inputs from one message, joints selected by index or by name in lists whose order changes),
stamped from the header or the receive time, one estimate over the span and sliding: every
estimate, standard deviation, window and counter is the same, and joints selected by name take
the columnar path.
"""

from pathlib import Path

from bag_fixtures import MSGDEFS
from ctid_ros.errors import BagError, ConfigError
from ctid_ros.files.bag_reader import BagReader, open_bag
from ctid_ros.files.columns import sample_columns
from ctid_ros.streaming.params_file import load_params_file
from ctid_ros.streaming.replay import replay_columns, replay_messages
from mcap.writer import Writer as McapWriter
import numpy as np
import pytest
from replay_fixtures import (DELAY, float_records, joint_state_records, name_joints, OPEN_LOOP,
                             params_file, simulate, write_bag)
from rosbags.typesys import get_typestore, Stores

KINDS = ['sqlite3', 'mcap', 'mcap-file']


def both(bag_path, params, sliding):
    """Replay a bag through the streaming and the columnar path; return both results."""
    config = load_params_file(params, 'ctid_node')
    with open_bag(bag_path) as bag:
        topics = tuple(bag.topic_name(topic) or topic
                       for topic in (config.input_topic, config.output_topic))
        streaming = replay_messages(bag.messages(sorted(set(topics))), config,
                                    sliding=sliding, topics=topics)
    with open_bag(bag_path) as bag:
        columnar = replay_columns(sample_columns(bag, config, topics), config,
                                  sliding=sliding, topics=topics)
    return streaming, columnar


def assert_same(streaming, columnar):
    assert len(columnar.updates) == len(streaming.updates) > 0
    for ours, theirs in zip(columnar.updates, streaming.updates):
        np.testing.assert_array_equal(ours.values, theirs.values)
        np.testing.assert_array_equal(ours.stds, theirs.stds)
        np.testing.assert_array_equal(ours.window.data.u, theirs.window.data.u)
        np.testing.assert_array_equal(ours.window.data.y, theirs.window.data.y)
        assert (ours.start_ns, ours.end_ns, ours.warnings) == (
            theirs.start_ns, theirs.end_ns, theirs.warnings)
    assert columnar.stats == streaming.stats
    assert columnar.messages == streaming.messages
    assert columnar.skipped == streaming.skipped


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('sliding', [False, True])
def test_float64_topics_without_header(tmp_path, kind, sliding):
    u, y = simulate(DELAY, 16.0)
    path = write_bag(tmp_path, float_records(u, y), kind)
    params = params_file(tmp_path, DELAY, window=6.0, update_period=3.0)
    assert_same(*both(path, params, sliding))


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('stamp_source', ['header', 'receive'])
@pytest.mark.parametrize('sliding', [False, True])
def test_joint_states_on_one_topic(tmp_path, kind, stamp_source, sliding):
    u, y = simulate(OPEN_LOOP, 14.0)
    path = write_bag(tmp_path, joint_state_records(u, y, latency_ns=4_000_000), kind)
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[0]',
                         output_field='position[0]', stamp_source=stamp_source, window=6.0,
                         update_period=4.0)
    assert_same(*both(path, params, sliding))


def one_by_one(monkeypatch):
    """Record the log time of every message the columnar path hands to the streaming decoder."""
    handed = []
    raw_streams = BagReader.raw_streams

    def counted(bag, topics):
        def decode(log_time_ns, data, decoder):
            handed.append(log_time_ns)
            return decoder(log_time_ns, data)

        return {key: stream._replace(decode=lambda time, data, decoder=stream.decode: decode(
            time, data, decoder)) for key, stream in raw_streams(bag, topics).items()}

    monkeypatch.setattr(BagReader, 'raw_streams', counted)
    return handed


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('sliding', [False, True])
def test_joints_selected_by_name_in_a_changing_order(tmp_path, monkeypatch, kind, sliding):
    u, y = simulate(OPEN_LOOP, 14.0)
    records = name_joints(joint_state_records(u, y, latency_ns=4_000_000))
    path = write_bag(tmp_path, records, kind)
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[joint]',
                         output_field='position[joint]', stamp_source='header', window=6.0,
                         update_period=4.0)
    handed = one_by_one(monkeypatch)
    assert_same(*both(path, params, sliding))
    assert handed == []


@pytest.mark.parametrize('named', [False, True])
def test_two_inputs_from_one_message(tmp_path, monkeypatch, named):
    u, y = simulate(OPEN_LOOP, 12.0)
    records = joint_state_records(u, y, latency_ns=0)
    w = np.repeat(np.random.default_rng(4).choice([-1.0, 1.0], size=len(records) // 20 + 1), 20)
    for record, w_k in zip(records, w):
        record.fields['velocity'] = [float(w_k)]
    joint = '[joint]' if named else '[0]'
    path = write_bag(tmp_path, name_joints(records) if named else records, 'mcap')
    params = params_file(tmp_path, {**OPEN_LOOP, 'model': 'm*s**2*y + d*s*y + k*y = u + c*w',
                                    'params': {}},
                         input_topic='/joint_states', output_topic='/joint_states',
                         input_field=f'effort{joint}', extra_input_fields=[f'velocity{joint}'],
                         input_names=['u', 'w'], output_field=f'position{joint}')
    handed = one_by_one(monkeypatch)
    streaming, columnar = both(path, params, False)
    assert columnar.updates[0].window.data.u.shape[1] == 2
    np.testing.assert_array_equal(np.unique(columnar.updates[0].window.data.u[:, 1]), [-1, 1])
    assert_same(streaming, columnar)
    assert handed == []


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('sliding', [False, True])
def test_messages_without_the_joint_are_skipped_by_both_paths_as_the_node_skips_them(
        tmp_path, monkeypatch, kind, sliding):
    """
    A /joint_states of several drivers: some messages lack the joint, others its effort.

    Both paths skip those messages (the live node counts them as field errors and goes on),
    estimate the same on the rest and say how many they skipped; before, the replay stopped at
    the first such message with no estimate at all.
    """
    u, y = simulate(OPEN_LOOP, 12.0)
    orders = [['joint', 'arm', 'wheel_right']] * 7 + [['arm', 'wheel_right']]
    records = name_joints(joint_state_records(u, y, latency_ns=0), orders)
    for record in records[5::50]:       # and a driver that leaves effort empty at times
        record.fields['effort'] = []
    path = write_bag(tmp_path, records, kind)
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[joint]',
                         output_field='position[joint]', window=8.0, update_period=4.0)
    handed = one_by_one(monkeypatch)
    streaming, columnar = both(path, params, sliding)
    assert_same(streaming, columnar)
    missing = {k for k in range(len(records)) if k % 8 == 7}
    failed = missing | set(range(5, len(records), 50))
    assert streaming.warnings == columnar.warnings == [
        f'input /joint_states (effort[joint]): {len(failed)} of {len(records)} messages '
        "skipped, as the live node skips them: field effort[joint]: index 0 (of 'joint') out "
        'of range for effort, an array of length 0',
        f'output /joint_states (position[joint]): {len(missing)} of {len(records)} messages '
        "skipped, as the live node skips them: field position[joint]: no joint 'joint' in "
        'name; names seen: arm, wheel_right']
    assert sorted(handed) == [records[k].time_ns for k in sorted(failed)]
    assert streaming.stats.u.received == len(records) - len(failed)
    assert streaming.stats.y.received == len(records) - len(missing)
    assert streaming.updates[-1].values == pytest.approx(
        [OPEN_LOOP['truth'][name] for name in streaming.updates[-1].names], rel=0.03)


@pytest.mark.parametrize('kind', KINDS)
def test_a_joint_no_message_has_raises_the_same_error_at_the_end(tmp_path, kind):
    u, y = simulate(OPEN_LOOP, 3.0)
    records = name_joints(joint_state_records(u, y, latency_ns=0), [['arm', 'wheel_right']])
    path = write_bag(tmp_path, records, kind)
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[joint]',
                         output_field='position[joint]')
    config = load_params_file(params, 'ctid_node')
    topics = ('/joint_states', '/joint_states')
    errors = []
    for sliding in (False, True):
        with open_bag(path) as bag, pytest.raises(ConfigError) as raised:
            replay_messages(bag.messages(['/joint_states']), config, topics=topics,
                            sliding=sliding)
        errors.append(str(raised.value))
        with open_bag(path) as bag, pytest.raises(ConfigError) as raised:
            replay_columns(sample_columns(bag, config, topics), config, topics=topics,
                           sliding=sliding)
        errors.append(str(raised.value))
    assert errors == ["field effort[joint]: no joint 'joint' in name; names seen: arm, "
                      'wheel_right'] * 4


def test_a_wrong_field_path_raises_the_same_error(tmp_path):
    u, y = simulate(OPEN_LOOP, 3.0)
    path = write_bag(tmp_path, joint_state_records(u, y, latency_ns=0), 'mcap-file')
    for field in ('positions[0]', 'position[3]', 'header.frame_id'):
        params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                             output_topic='/joint_states', input_field='effort[0]',
                             output_field=field)
        errors = []
        for use_columns in (False, True):
            config = load_params_file(params, 'ctid_node')
            with open_bag(path) as bag, pytest.raises(ConfigError) as raised:
                topics = ('/joint_states', '/joint_states')
                if use_columns:
                    replay_columns(sample_columns(bag, config, topics), config, topics=topics)
                else:
                    replay_messages(bag.messages(['/joint_states']), config, topics=topics)
            errors.append(str(raised.value))
        assert errors[0] == errors[1], field


def test_a_damaged_message_ends_the_blocks_where_the_streaming_reader_stops(tmp_path):
    """A message whose bytes do not fit its definition: same messages before, same error."""
    u, y = simulate(DELAY, 4.0)
    store = get_typestore(Stores.ROS2_JAZZY)
    float64 = store.types['std_msgs/msg/Float64']
    path = tmp_path / 'damaged.mcap'
    with open(path, 'wb') as stream:
        writer = McapWriter(stream, chunk_size=2048)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('std_msgs/msg/Float64', 'ros2msg',
                                        MSGDEFS['std_msgs/msg/Float64'].encode())
        channels = [writer.register_channel(topic, 'cdr', schema)
                    for topic in ('/plant/u', '/plant/y')]
        for k, (u_k, y_k) in enumerate(zip(u, y)):
            for channel, value, lag in zip(channels, (u_k, y_k), (0, 1_000_000)):
                data = bytes(store.serialize_cdr(float64(float(value)), 'std_msgs/msg/Float64'))
                if k == 250 and lag:
                    data = data[:7]         # cut inside the float
                writer.add_message(channel, 10**18 + k * 10_000_000 + lag, data,
                                   10**18 + k * 10_000_000 + lag)
        writer.finish()
    config = load_params_file(params_file(tmp_path, DELAY), 'ctid_node')
    topics = ('/plant/u', '/plant/y')
    seen = {False: [], True: []}
    for use_columns in (False, True):
        with open_bag(path) as bag, pytest.raises(BagError) as raised:
            if use_columns:
                for block in sample_columns(bag, config, topics):
                    seen[True].extend(block.log_time_ns.tolist())
            else:
                for message in bag.messages(list(topics)):
                    seen[False].append(message.log_time_ns)
        seen[use_columns].append(str(raised.value))
    assert seen[True] == seen[False]
    assert 'at 1000000002501000000 ns' in seen[True][-1]
    assert len(seen[True]) == 2 * 250 + 1 + 1


def test_blocks_of_a_long_bag_stay_small(tmp_path):
    u, y = simulate(DELAY, 30.0)
    path = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    config = load_params_file(params_file(tmp_path, DELAY), 'ctid_node')
    with open_bag(path) as bag:
        sizes = [block.log_time_ns.size
                 for block in sample_columns(bag, config, ('/plant/u', '/plant/y'))]
    assert sum(sizes) == 2 * u.size and max(sizes) < 2000
    assert Path(path).exists()


@pytest.mark.parametrize('kind', KINDS)
def test_unset_header_stamps_are_counted_by_both_paths(tmp_path, kind):
    """
    A driver that leaves header.stamp zero now and then: filed under the log time, and said.

    The live node counts them (zero_stamps on /diagnostics); the replay said nothing.
    """
    u, y = simulate(OPEN_LOOP, 6.0)
    records = joint_state_records(u, y, latency_ns=2_000_000)
    for record in records[3::10]:
        record.fields['header']['stamp'] = {'sec': 0, 'nanosec': 0}
    path = write_bag(tmp_path, records, kind)
    params = params_file(tmp_path, OPEN_LOOP, input_topic='/joint_states',
                         output_topic='/joint_states', input_field='effort[0]',
                         output_field='position[0]')
    streaming, columnar = both(path, params, False)
    assert_same(streaming, columnar)
    unset = len(records[3::10])
    assert streaming.warnings == columnar.warnings == [
        f'{role} /joint_states ({field}): header.stamp unset (zero) in {unset} messages, filed '
        'under their log time (when the recorder received them), as the live node files them '
        'under the receive time; a dead time then includes the delay to the recorder'
        for role, field in (('input', 'effort[0]'), ('output', 'position[0]'))]
