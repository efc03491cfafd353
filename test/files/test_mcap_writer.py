"""Tests of ctid_ros.files.mcap_writer: files read back with independent readers."""

from bag_fixtures import make_records, SAMPLE_MSG, SAMPLE_TYPE, T0_NS, TOPICS, write_mcap
from ctid_ros.errors import BagError, ConfigError, DataError
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.mcap_writer import EstimateWriter, RecordingWriter
from ctid_ros.streaming.contract import ERROR, OK, WARN
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

NAMES = ['K', 'T', 'tau']


def write_estimates(path, **kwargs):
    """Write three updates with their predictions and a failed one; return what was written."""
    rng = np.random.default_rng(3)
    updates = []
    with EstimateWriter(path, **kwargs) as writer:
        for k in range(3):
            time_ns = T0_NS + (k + 1) * 10**9
            values, stds = rng.normal(size=3), rng.uniform(0.01, 0.1, size=3)
            prediction = np.sin(np.arange(50 + k) / 7)
            diagnostics = {'fit': 91.23456789, 'iterations': 4 + k, 'converged': k != 1,
                           'window_s': 10.0, 'samples': 50 + k,
                           'warnings': ['poorly excited'] if k == 2 else []}
            writer.write_estimate(time_ns, NAMES, values, stds, diagnostics, prediction)
            updates.append((time_ns, values, stds, prediction))
        writer.write_status(T0_NS + 4 * 10**9, ERROR, 'no stable start')
    return updates


def read_with_rosbags(path):
    with AnyReader([path]) as reader:
        types = {name: info.msgtype for name, info in reader.topics.items()}
        return types, [(c.topic, t, reader.deserialize(d, c.msgtype))
                       for c, t, d in reader.messages()]


def read_with_mcap(path):
    with open(path, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        types, messages = {}, []
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            types[channel.topic] = schema.name
            messages.append((channel.topic, message.log_time, decoded))
        return types, messages


@pytest.mark.parametrize('read', [read_with_rosbags, read_with_mcap])
def test_estimate_writer_output_reads_back(tmp_path, read):
    path = tmp_path / 'estimates.mcap'
    updates = write_estimates(path)
    types, messages = read(path)
    array, scalar = 'std_msgs/msg/Float64MultiArray', 'std_msgs/msg/Float64'
    assert types == {'/ctid_node/estimate': array, '/ctid_node/estimate_std': array,
                     '/ctid_node/prediction': array,
                     '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
                     **{f'/ctid_node/params/{name}': scalar for name in NAMES}}
    by_topic = {}
    for topic, time_ns, msg in messages:
        by_topic.setdefault(topic, []).append((time_ns, msg))
    assert len(by_topic['/ctid_node/prediction']) == 3    # one array per update
    assert len(by_topic['/diagnostics']) == 4
    for index, (time_ns, values, stds, prediction) in enumerate(updates):
        for topic, label, array in (('/ctid_node/estimate', 'K,T,tau', values),
                                    ('/ctid_node/estimate_std', 'K,T,tau', stds),
                                    ('/ctid_node/prediction', 'prediction', prediction)):
            stamp, msg = by_topic[topic][index]
            assert stamp == time_ns
            assert list(msg.data) == list(array)
            assert msg.layout.dim[0].label == label
            assert msg.layout.dim[0].size == msg.layout.dim[0].stride == len(array)
        for name, value in zip(NAMES, values):
            stamp, msg = by_topic[f'/ctid_node/params/{name}'][index]
            assert (stamp, msg.data) == (time_ns, value)
        stamp, msg = by_topic['/diagnostics'][index]
        status = msg.status[0]
        assert msg.header.stamp.sec == time_ns // 10**9
        assert (status.name, status.hardware_id) == ('ctid_node: estimate', 'ctid_node')
        pairs = {kv.key: kv.value for kv in status.values}
        assert pairs['fit'] == '91.23456789' and pairs['iterations'] == str(4 + index)
        assert pairs['converged'] == ('false' if index == 1 else 'true')
        assert status.level == (OK, WARN, WARN)[index]
        summary = ', '.join(f'{name}={value:.6g} (std {std:.3g})'
                            for name, value, std in zip(NAMES, values, stds))
        assert status.message == (summary, 'not converged', 'poorly excited')[index]
    _, failed = by_topic['/diagnostics'][3]
    assert (failed.status[0].level, failed.status[0].message) == (ERROR, 'no stable start')
    assert list(failed.status[0].values) == []


def test_estimate_writer_namespace_and_param_topics(tmp_path):
    path = tmp_path / 'ns.mcap'
    with EstimateWriter(path, namespace='/plant1/', node_name='ident') as writer:
        writer.write_estimate(T0_NS, ['K'], [2.0])
        assert writer.node.param('K') == '/plant1/ident/params/K'
    with BagReader(path) as bag:
        assert bag.topics() == {'/plant1/ident/estimate': 'std_msgs/msg/Float64MultiArray',
                                '/plant1/ident/params/K': 'std_msgs/msg/Float64'}
        (message,) = bag.messages('/plant1/ident/params/K')
        assert message.msg.data == 2.0
    with EstimateWriter(tmp_path / 'qualified.mcap', node_name='/lab/ident') as writer:
        assert writer.node.estimate == '/lab/ident/estimate'
    with pytest.raises(ConfigError):
        EstimateWriter(tmp_path / 'bad.mcap', namespace='plant-1')


def test_estimate_writer_protects_inputs_and_existing_files(tmp_path):
    bag = tmp_path / 'run.mcap'
    write_mcap(bag, make_records())
    original = bag.read_bytes()
    with pytest.raises(BagError, match='input bag'):
        EstimateWriter(bag, inputs=[bag], overwrite=True)
    with pytest.raises(BagError, match='input bag'):
        EstimateWriter(tmp_path / 'estimates.mcap', inputs=[tmp_path])
    assert bag.read_bytes() == original
    assert not (tmp_path / 'estimates.mcap').exists()

    existing = tmp_path / 'old.mcap'
    existing.write_bytes(b'keep me')
    with pytest.raises(BagError, match='already exists'):
        EstimateWriter(existing)
    assert existing.read_bytes() == b'keep me'
    with EstimateWriter(existing, overwrite=True) as writer:
        writer.write_status(T0_NS, WARN, 'waiting')
    with BagReader(existing) as reader:
        assert reader.message_count() == 1

    with pytest.raises(BagError, match='.mcap'):
        EstimateWriter(tmp_path / 'estimates.db3')
    with pytest.raises(BagError, match='does not exist'):
        EstimateWriter(tmp_path / 'nowhere' / 'estimates.mcap')


def test_estimate_writer_rejects_inconsistent_data(tmp_path):
    with EstimateWriter(tmp_path / 'e.mcap') as writer:
        with pytest.raises(DataError):
            writer.write_estimate(T0_NS, ['K', 'T'], [1.0])
        with pytest.raises(DataError):
            writer.write_estimate(T0_NS, ['K', 'T'], [1.0, 2.0], [0.1])
        with pytest.raises(DataError):
            writer.write_estimate(T0_NS, ['K', 'K'], [1.0, 2.0])
        with pytest.raises(DataError):
            writer.write_estimate(T0_NS, ['a.b'], [1.0])
        with pytest.raises(DataError):
            writer.write_estimate(1.5e18, ['K'], [1.0])
        with pytest.raises(DataError):
            writer.write_status(-1, OK, 'negative time')
    with pytest.raises(BagError, match='closed'):
        writer.write_status(T0_NS, OK, 'closed')


def test_recording_writer_output_reads_back_with_both_readers(tmp_path):
    typestore = get_typestore(Stores.ROS2_JAZZY)
    point = typestore.types['geometry_msgs/msg/PointStamped']
    header = typestore.types['std_msgs/msg/Header']
    stamp = typestore.types['builtin_interfaces/msg/Time']
    vector = typestore.types['geometry_msgs/msg/Point']
    path = tmp_path / 'run.mcap'
    with RecordingWriter(path) as writer:
        writer.add_topic('/wheel/y', 'geometry_msgs/msg/PointStamped')
        with pytest.raises(BagError, match='not a standard'):
            writer.add_topic('/x', 'my_pkg/msg/Unknown')
        with pytest.raises(BagError, match='already recorded'):
            writer.add_topic('/wheel/y', 'geometry_msgs/msg/PointStamped')
        for k in range(5):
            msg = point(header(stamp(100, 10_000_000 * k), 'base'), vector(0.5 * k, 0.0, 0.0))
            writer.write('/wheel/y', 1_000 + k, typestore.serialize_cdr(
                msg, 'geometry_msgs/msg/PointStamped'))
        with pytest.raises(BagError, match='not declared'):
            writer.write('/wheel/u', 2_000, b'')
    with pytest.raises(BagError, match='closed'):
        writer.write('/wheel/y', 3_000, b'')
    with BagReader(path) as bag:
        assert bag.topics() == {'/wheel/y': 'geometry_msgs/msg/PointStamped'}
        messages = list(bag.messages())
    assert [message.log_time_ns for message in messages] == [1_000 + k for k in range(5)]
    assert [message.msg.point.x for message in messages] == [0.5 * k for k in range(5)]
    assert messages[3].msg.header.stamp.nanosec == 30_000_000
    with AnyReader([path]) as reader:
        decoded = [reader.deserialize(data, connection.msgtype)
                   for connection, _, data in reader.messages()]
    assert [msg.point.x for msg in decoded] == [0.5 * k for k in range(5)]


def test_recorded_topics_are_copied_with_their_own_schemas(tmp_path):
    """A custom type, unknown to any type store, is copied byte for byte with its definition."""
    source = tmp_path / 'run.mcap'
    records = make_records()
    write_mcap(source, records)
    output = tmp_path / 'estimates.mcap'
    topics = ['/plant/sample', '/plant/u']
    with BagReader(source) as bag, EstimateWriter(output, inputs=[source]) as writer:
        for topic in topics:
            writer.add_topic(topic, TOPICS[topic], bag.topic_schema(topic))
        for record in bag.records(topics):
            writer.write(record.topic, record.log_time_ns, record.data)
        writer.write_estimate(T0_NS + 10**9, ['K'], [1.5], [0.1])
    expected = [record for record in records if record.topic in topics]
    types, messages = read_with_mcap(output)
    assert types['/plant/sample'] == SAMPLE_TYPE and types['/plant/u'] == TOPICS['/plant/u']
    copied = [(topic, time_ns, msg) for topic, time_ns, msg in messages if topic in topics]
    assert [(topic, time_ns) for topic, time_ns, _ in copied] == [
        (record.topic, record.time_ns) for record in expected]
    for (_, _, msg), record in zip(copied, expected):
        for name in ('u', 'y', 'data'):
            if name in record.fields:
                assert getattr(msg, name) == record.fields[name]
    with BagReader(output) as bag:
        schema = bag.topic_schema('/plant/sample')
        assert schema.msgtype == SAMPLE_TYPE and schema.definition.startswith(SAMPLE_MSG.encode())
        assert bag.message_count('/ctid_node/estimate') == 1


_JAZZY = get_typestore(Stores.ROS2_JAZZY)


def _float64(value):
    return bytes(_JAZZY.serialize_cdr(_JAZZY.types['std_msgs/msg/Float64'](data=value),
                                      'std_msgs/msg/Float64'))


def _plain_count(path):
    """Read a file with the plain mcap reader; return its message count."""
    with open(path, 'rb') as stream:
        return sum(1 for _ in make_reader(stream).iter_messages())


def test_a_recording_is_a_valid_file_after_every_flush(tmp_path):
    path = tmp_path / 'run.mcap'
    snapshots = []
    with RecordingWriter(path, flush_interval=3600.0) as writer:
        writer.add_topic('/u', 'std_msgs/msg/Float64')
        snapshots.append(path.read_bytes())         # what a kill right now would leave
        for k in range(10):
            writer.write('/u', T0_NS + k, _float64(float(k)))
            if k in (3, 6):
                writer.flush(force=True)
                snapshots.append(path.read_bytes())
        snapshots.append(path.read_bytes())         # 3 messages after the last flush
    # A flush writes its chunk and a new end past the old end's first bytes, then those: a
    # kill between the two writes leaves the file as it was before, with bytes after its end.
    torn = [before + after[len(before):] for before, after in zip(snapshots, snapshots[1:])]
    for index, (content, expected) in enumerate(zip(snapshots + torn, [0, 4, 7, 7, 0, 4, 7])):
        copy = tmp_path / f'killed{index}.mcap'
        copy.write_bytes(content)
        assert _plain_count(copy) == expected
        with BagReader(copy) as bag:
            assert not bag.truncated
            assert [msg.msg.data for msg in bag.messages()] == list(map(float, range(expected)))
    assert _plain_count(path) == 10


def test_messages_are_flushed_once_the_interval_has_passed(tmp_path):
    path = tmp_path / 'run.mcap'
    with RecordingWriter(path, flush_interval=0.0) as writer:
        writer.add_topic('/u', 'std_msgs/msg/Float64')
        for k in range(5):
            writer.write('/u', T0_NS + k, _float64(float(k)))
            assert _plain_count(path) == k + 1


def test_a_full_disk_fails_once_with_its_cause_and_keeps_a_readable_file(tmp_path):
    from disk_fixtures import small_disk

    with small_disk(tmp_path / 'disk', 64) as disk:
        path = disk / 'run.mcap'
        writer = RecordingWriter(path, flush_interval=0.0)
        writer.add_topic('/u', 'std_msgs/msg/Float64')
        written = 0
        with pytest.raises(BagError, match=f'cannot write {path}: No space left on device'):
            for k in range(100_000):
                writer.write('/u', T0_NS + k, _float64(float(k)))
                written += 1
        assert 500 < written < 100_000
        with pytest.raises(BagError, match='No space left on device'):
            writer.write('/u', T0_NS, _float64(0.0))
        writer.close()
        # Every message written before the failure, in a file the plain reader reads.
        assert _plain_count(path) == written
        with BagReader(path) as bag:
            assert bag.message_count() == written and not bag.truncated


def test_no_writing_into_pipes_or_devices(tmp_path):
    import os

    fifo = tmp_path / 'pipe.mcap'
    os.mkfifo(fifo)
    with pytest.raises(BagError, match=r'pipe.mcap: it is a named pipe \(FIFO\), not a regular'):
        RecordingWriter(fifo, overwrite=True)      # would block until someone reads it
    full = tmp_path / 'full.mcap'
    full.symlink_to('/dev/full')
    with pytest.raises(BagError, match=r'it is a character device \(/dev/full\)'):
        RecordingWriter(full, overwrite=True)


def test_a_recording_named_otherwise_than_mcap_is_refused_as_such(tmp_path):
    # `ctid record run /u` said "estimate output run must end in .mcap": no estimate there.
    with pytest.raises(BagError) as raised:
        RecordingWriter(tmp_path / 'run', overwrite=True)
    assert str(raised.value) == (f'cannot write {tmp_path / "run"}: the name must end in .mcap '
                                 '(an MCAP file is written)')
    assert not (tmp_path / 'run').exists()


def test_an_atomic_file_is_complete_or_absent(tmp_path):
    path = tmp_path / 'est.mcap'
    partial = tmp_path / 'est.partial.mcap'
    path.write_bytes(b'the previous results')
    writer = EstimateWriter(path, overwrite=True, atomic=True)
    writer.write_status(T0_NS, OK, 'one')
    assert partial.exists() and path.read_bytes() == b'the previous results'
    writer.discard()
    assert not partial.exists() and path.read_bytes() == b'the previous results'
    partial.write_bytes(b'left by a killed replay')
    with EstimateWriter(path, overwrite=True, atomic=True) as writer:
        writer.write_status(T0_NS, OK, 'two')
    assert not partial.exists()
    with BagReader(path) as bag:
        assert [msg.msg.status[0].message for msg in bag.messages()] == ['two']


def test_an_atomic_file_that_fails_leaves_nothing(tmp_path):
    from disk_fixtures import small_disk

    rng = np.random.default_rng(5)
    with small_disk(tmp_path / 'disk', 64) as disk:
        path = disk / 'est.mcap'
        writer = EstimateWriter(path, atomic=True)
        writer.add_topic('/u', 'std_msgs/msg/Float64')
        for k in range(20_000):         # 0.5 MB that zstd cannot shrink, held until the end
            writer.write('/u', T0_NS + k, _float64(rng.normal()))
        with pytest.raises(BagError, match=f'cannot write {path}: No space left on device'):
            writer.close()
        assert list(disk.iterdir()) == []
        writer.close()      # closed already: nothing more to say
