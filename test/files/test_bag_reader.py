"""Tests of ctid_ros.files.bag_reader: bags of every kind from independent writers."""

import hashlib
import os
from pathlib import Path
import shutil
import sqlite3

from bag_fixtures import (assert_fields, DURATION_S, make_records, readable_prefix, SAMPLE_MSG,
                          SAMPLE_TYPE, T0_NS, TOPICS, truncate, write_mcap, write_rosbag2)
from ctid_ros.errors import BagError
from ctid_ros.files.bag_reader import BagReader, open_bag
import hostile_corpus
import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
import zstandard

RECORDS = make_records(seed=0)
KINDS = ['sqlite3', 'mcap_dir', 'mcap_file']


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Write the recording once per storage kind; tests that damage a bag copy it first."""
    root = tmp_path_factory.mktemp('bags')
    write_rosbag2(root / 'sqlite3', RECORDS, 'sqlite3')
    write_rosbag2(root / 'mcap_dir', RECORDS, 'mcap')
    write_mcap(root / 'run.mcap', RECORDS)
    return {'sqlite3': root / 'sqlite3', 'mcap_dir': root / 'mcap_dir',
            'mcap_file': root / 'run.mcap'}


def assert_records(messages, expected):
    """Assert topics, log times (hence order) and decoded values of messages."""
    assert [(m.topic, m.log_time_ns) for m in messages] == [(r.topic, r.time_ns)
                                                            for r in expected]
    for message, record in zip(messages, expected):
        assert_fields(message.msg, record.fields)


@pytest.mark.parametrize('kind', KINDS)
def test_metadata(bags, kind):
    with open_bag(bags[kind]) as bag:
        assert bag.topics() == TOPICS
        counts = {topic: sum(r.topic == topic for r in RECORDS) for topic in TOPICS}
        assert bag.message_counts() == counts
        assert bag.message_count() == len(RECORDS)
        assert bag.message_count(['/plant/u', '/plant/y']) == counts['/plant/u'] * 2
        assert bag.message_count('/joint_states') == counts['/joint_states']
        assert bag.start_time_ns == RECORDS[0].time_ns == T0_NS
        assert bag.end_time_ns == RECORDS[-1].time_ns
        assert bag.duration_s == pytest.approx(DURATION_S, abs=0.01)
        assert not bag.truncated and bag.warnings == []


@pytest.mark.parametrize('kind', KINDS)
def test_all_messages_in_log_time_order_with_values(bags, kind):
    # The standalone MCAP was written with neighbours swapped across small chunks.
    with BagReader(bags[kind]) as bag:
        assert_records(list(bag.messages()), RECORDS)


@pytest.mark.parametrize('kind', KINDS)
def test_topic_and_window_selection(bags, kind):
    topics = ['/plant/u', '/plant/sample']
    lo, hi = T0_NS + 500_000_000, T0_NS + 1_000_000_000
    expected = [r for r in RECORDS if r.topic in topics and lo <= r.time_ns < hi]
    with BagReader(bags[kind]) as bag:
        assert bag.time_range_ns(0.5, 1.0) == (lo, hi)
        assert_records(list(bag.messages(topics, start=0.5, end=1.0)), expected)
        assert_records(list(bag.messages(topics, start_ns=lo, end_ns=hi)), expected)
        tail = list(bag.messages('/plant/y', start=1.5))
        assert_records(tail, [r for r in RECORDS
                              if r.topic == '/plant/y' and r.time_ns >= T0_NS + 1_500_000_000])


def test_custom_type_decoded_from_bag_definition(bags):
    sample = next(r for r in RECORDS if r.topic == '/plant/sample')
    for kind in KINDS:
        with BagReader(bags[kind]) as bag:
            message = next(iter(bag.messages('/plant/sample')))
        assert message.log_time_ns == sample.time_ns
        assert (message.msg.u, message.msg.y) == (sample.fields['u'], sample.fields['y'])
        assert message.msg.header.stamp.sec == sample.time_ns // 10**9


@pytest.mark.parametrize('kind', KINDS)
def test_records_carry_the_serialised_bytes_and_topics_their_schemas(bags, kind):
    typestore = get_typestore(Stores.ROS2_JAZZY)
    typestore.register(get_types_from_msg(SAMPLE_MSG, SAMPLE_TYPE))
    with BagReader(bags[kind]) as bag:
        records = list(bag.records(['/plant/y', '/plant/sample'], end=0.5))
        schemas = {topic: bag.topic_schema(topic) for topic in TOPICS}
        with pytest.raises(BagError, match='/plant/x'):
            bag.topic_schema('/plant/x')
    assert_records(records, [r for r in RECORDS if r.topic in ('/plant/y', '/plant/sample')
                             and r.time_ns < T0_NS + 5 * 10**8])
    for record in records:
        decoded = typestore.deserialize_cdr(record.data, TOPICS[record.topic])
        assert_fields(decoded, next(r.fields for r in RECORDS if r.time_ns == record.log_time_ns))
    for topic, schema in schemas.items():
        assert (schema.msgtype, schema.encoding, schema.message_encoding) == (
            TOPICS[topic], 'ros2msg', 'cdr')
    assert schemas['/plant/y'].definition == b'float64 data\n'
    assert schemas['/plant/sample'].definition.startswith(SAMPLE_MSG.encode())


@pytest.mark.parametrize('kind', ['sqlite3', 'mcap_file'])
def test_missing_topic_lists_existing_topics(bags, kind):
    with BagReader(bags[kind]) as bag:
        with pytest.raises(BagError) as error:
            bag.messages(['/plant/u', '/plant/x'])
    text = str(error.value)
    assert '/plant/x' in text
    for topic, msgtype in TOPICS.items():
        assert f'{topic} ({msgtype}' in text


def test_invalid_windows(bags):
    with BagReader(bags['mcap_file']) as bag:
        for kwargs in ({'start': -1.0}, {'start': 2.0, 'end': 1.0}, {'start': float('nan')},
                       {'start': 100.0}, {'start': 1.0, 'start_ns': T0_NS}):
            with pytest.raises(BagError):
                bag.messages(**kwargs)
        with pytest.raises(BagError, match='no topics'):
            bag.messages([])


def test_nonexistent_path(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        BagReader(tmp_path / 'missing')


def test_directory_that_is_not_a_bag(tmp_path):
    (tmp_path / 'notes.txt').write_text('not a bag')
    with pytest.raises(BagError, match='not a bag'):
        BagReader(tmp_path)


def test_directory_without_metadata_reads_its_single_mcap(bags, tmp_path):
    shutil.copy(bags['mcap_file'], tmp_path / 'run_0.mcap')
    with BagReader(tmp_path) as bag:
        assert 'no metadata.yaml' in bag.warnings[0]
        assert bag.message_count() == len(RECORDS)
    shutil.copy(bags['mcap_file'], tmp_path / 'run_1.mcap')
    with pytest.raises(BagError, match='run_0.mcap, run_1.mcap'):
        BagReader(tmp_path)


def test_garbage_files(tmp_path):
    rng = np.random.default_rng(1)
    (tmp_path / 'garbage.mcap').write_bytes(rng.bytes(5000))
    (tmp_path / 'garbage.bin').write_bytes(rng.bytes(5000))
    (tmp_path / 'empty.mcap').write_bytes(b'')
    with pytest.raises(BagError, match='not an MCAP file'):
        BagReader(tmp_path / 'garbage.mcap')
    with pytest.raises(BagError, match='not an MCAP file'):
        BagReader(tmp_path / 'empty.mcap')
    with pytest.raises(BagError, match='not a bag'):
        BagReader(tmp_path / 'garbage.bin')


def test_truncated_mcap_inside_rosbag2_directory(bags, tmp_path):
    # rosbags writes one 1 MiB chunk, so the recording is taken from the chunked MCAP writer,
    # put in place of the storage file the directory's metadata.yaml names.
    bag = tmp_path / 'bag'
    shutil.copytree(bags['mcap_dir'], bag)
    storage = next(bag.glob('*.mcap'))
    shutil.copy(bags['mcap_file'], storage)
    truncate(storage, 0.6)
    with BagReader(bag) as reader:
        assert reader.truncated
        assert 'rosbags cannot read' in reader.warnings[0]
        assert_records(list(reader.messages()), readable_prefix(storage, RECORDS))


def test_corrupted_sqlite_database(bags, tmp_path):
    rng = np.random.default_rng(2)
    for name, offset in (('header', 0), ('pages', 4096)):
        bag = tmp_path / name
        shutil.copytree(bags['sqlite3'], bag)
        db3 = next(bag.glob('*.db3'))
        data = bytearray(db3.read_bytes())
        data[offset:offset + 8192] = rng.bytes(8192)
        db3.write_bytes(bytes(data))
        with pytest.raises(BagError, match='cannot read|corrupted'):
            with BagReader(bag) as reader:
                list(reader.messages())


def test_single_db3_file(bags):
    db3 = next(bags['sqlite3'].glob('*.db3'))
    with BagReader(db3) as bag:
        assert bag.topics() == TOPICS
        assert_records(list(bag.messages('/plant/y', end=0.1)),
                       [r for r in RECORDS if r.topic == '/plant/y' and r.time_ns < T0_NS + 10**8])


def test_no_file_is_left_open(bags):
    fds = len(os.listdir('/proc/self/fd'))
    for kind in KINDS:
        with BagReader(bags[kind]) as bag:
            list(bag.messages('/plant/u'))
    assert len(os.listdir('/proc/self/fd')) == fds


# Bags written by rosbag2 itself (test/data/bags, from the ros2/rosbag2 test resources).
REAL = Path(__file__).resolve().parents[1] / 'data' / 'bags'


def digest(path):
    return {file.name: hashlib.sha256(file.read_bytes()).hexdigest()
            for file in sorted(path.iterdir())}


@pytest.mark.parametrize('name, storage', [('talker_sqlite3', 'talker.db3'),
                                           ('talker_mcap', 'talker.mcap')])
def test_recorded_talker_with_metadata_version_4_yields_its_messages(name, storage):
    before = digest(REAL / name)
    with BagReader(REAL / name) as bag:
        # Its metadata.yaml (version 4) and storage disagree on the QoS profiles, so rosbags
        # alone would yield none of the 20 messages.
        assert len(bag.warnings) == 1
        assert (f'metadata.yaml (version 4) and {storage} disagree about 2 topic(s) (/rosout: '
                'QoS profiles; /topic: QoS profiles), so rosbags would skip 20 stored message'
                ) in bag.warnings[0]
        assert bag.message_counts() == {'/topic': 10, '/rosout': 10, '/parameter_events': 0}
        messages = list(bag.messages('/topic'))
    assert [message.msg.data for message in messages] == [f'Hello, world! {k}'
                                                          for k in range(10)]
    assert digest(REAL / name) == before


def test_a_stored_definition_that_does_not_match_the_data_is_named():
    with BagReader(REAL / 'talker_sqlite3') as bag:
        # talker.db3 stores a one-field definition of rcl_interfaces/msg/Log.
        with pytest.raises(BagError, match='the message on /rosout at 1585866235112411371 ns '
                           'does not match the definition of rcl_interfaces/msg/Log'):
            list(bag.messages('/rosout'))


@pytest.mark.parametrize('name', ['service_events_sqlite3', 'service_events_mcap'])
def test_service_events_are_named_and_message_topics_still_read(name):
    before = digest(REAL / name)
    with BagReader(REAL / name) as bag:
        assert bag.message_counts()['/test_service1/_service_event'] == 4
        assert [message.msg.string_value_default1
                for message in bag.messages(['/test_topic1', '/test_topic2'])] == [
            'Hello world!'] * 2
        with pytest.raises(BagError, match='/test_service1/_service_event carries service '
                           r'events \(test_msgs/srv/BasicTypes_Event, recorded with `ros2 bag '
                           'record --services`') as error:
            list(bag.messages(['/test_topic1', '/test_service1/_service_event']))
        assert 're-record' not in str(error.value)
    assert digest(REAL / name) == before


def test_topics_stored_without_a_leading_slash_are_found_either_way():
    with BagReader(REAL / 'no_slash_mcap') as bag:
        assert set(bag.topics()) == {'a_empty', 'b_basictypes'}
        assert bag.topic_name('/b_basictypes') == 'b_basictypes'
        assert bag.topic_name('b_basictypes') == 'b_basictypes'
        assert bag.topic_name('/c_strings') is None
        assert len(list(bag.messages('/b_basictypes'))) == 50
        assert bag.message_count(['a_empty', '/b_basictypes']) == 150
    with BagReader(REAL / 'talker_mcap') as bag:
        assert bag.topic_name('topic') == '/topic'


def tampered(bags, tmp_path, edit):
    """Copy the sqlite3 bag and rewrite its metadata.yaml with ``edit``."""
    bag = tmp_path / 'bag'
    shutil.copytree(bags['sqlite3'], bag)
    metadata = bag / 'metadata.yaml'
    metadata.write_text(edit(metadata.read_text()))
    return bag


def test_metadata_disagreeing_with_the_database_is_named_not_called_corrupted(bags, tmp_path):
    def compressed(text):
        return text.replace("compression_format: ''", 'compression_format: zstd').replace(
            "compression_mode: ''", 'compression_mode: message')

    with BagReader(tampered(bags, tmp_path / 'a', compressed)) as bag:
        assert 'says the messages are zstd-compressed (compression_mode: message) but ' \
            'sqlite3.db3 hold(s) uncompressed messages' in bag.warnings[0]
        assert_records(list(bag.messages()), RECORDS)

    def retyped(text):
        return text.replace('type: std_msgs/msg/Float64', 'type: std_msgs/msg/Int32', 1)

    with BagReader(tampered(bags, tmp_path / 'b', retyped)) as bag:
        assert '/plant/u: type std_msgs/msg/Int32 against std_msgs/msg/Float64' in \
            bag.warnings[0]
        assert_records(list(bag.messages()), RECORDS)

    def recounted(text):
        return text.replace(f'message_count: {len(RECORDS)}', 'message_count: 5', 1).replace(
            'message_count: 200', 'message_count: 7', 1)

    with BagReader(tampered(bags, tmp_path / 'c', recounted)) as bag:
        assert any('metadata.yaml counts 7 message(s) on /plant/u, the storage holds 200' in
                   warning for warning in bag.warnings)
        assert bag.message_count('/plant/u') == 200


def test_oversized_metadata_is_refused(bags, tmp_path):
    bag = tmp_path / 'bag'
    shutil.copytree(bags['sqlite3'], bag)
    with open(bag / 'metadata.yaml', 'ab') as stream:
        stream.truncate(5 << 20)
    with pytest.raises(BagError, match='metadata.yaml is 5 MiB, more than the limit of 4 MiB'):
        BagReader(bag)


def test_compressed_storage_files_are_checked_before_rosbags_decompresses_them(bags, tmp_path):
    def file_compressed(text):
        return text.replace("compression_format: ''", 'compression_format: zstd').replace(
            "compression_mode: ''", 'compression_mode: file')

    bag = tampered(bags, tmp_path / 'a', file_compressed)
    with pytest.raises(BagError, match=r'says the storage files are zstd-compressed '
                       r'\(compression_mode: file\) but .*sqlite3.db3 is not'):
        BagReader(bag)
    database = bag / 'sqlite3.db3'
    # A frame that does not state its size is measured, up to the limit (1000 MiB here).
    database.write_bytes(hostile_corpus.zeros_zstd(1 << 30, content_size=False))
    with pytest.raises(BagError, match='decompresses to more than 1000 MiB from 32 KiB .the '
                       'ratio limit is 1000, at least 1000 MiB.: a decompression bomb'):
        BagReader(bag)
    # Damaged zstd data is named as such.
    database.write_bytes(hostile_corpus.zeros_zstd(1 << 20)[:-40] + bytes(40))
    with pytest.raises(BagError, match='is damaged: its zstd data cannot be decompressed'):
        BagReader(bag)


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_file_compressed_bags_are_read_although_their_frames_state_no_size(tmp_path, storage):
    """
    rosbag2 (and rosbags) compress a storage file as a stream: its size is not in the frame.

    Such bags (``ros2 bag record --compression-mode file``) were refused as decompression
    bombs; they are read whole, and left as they were.
    """
    path = tmp_path / 'bag'
    write_rosbag2(path, RECORDS, storage, compression='file')
    (stored,) = path.glob('*.zstd')
    assert zstandard.frame_content_size(stored.read_bytes()[:32]) == -1
    digest = hashlib.sha256(stored.read_bytes()).hexdigest()
    with BagReader(path) as bag:
        assert_records(list(bag.messages()), RECORDS)
        assert bag.warnings == []
    assert hashlib.sha256(stored.read_bytes()).hexdigest() == digest


def _ros1_bag(tmp_path, seconds=1.0):
    from replay_fixtures import DELAY, simulate, write_rosbag1

    u, y = simulate(DELAY, seconds)
    return write_rosbag1(tmp_path / 'run.bag', u, y), u, y


def test_ros1_bag_yields_its_custom_type_as_the_ros2_message(tmp_path):
    from replay_fixtures import COMMAND_TYPE, STEP_NS, T0_NS

    path, u, y = _ros1_bag(tmp_path)
    with BagReader(path) as bag:
        assert bag.topics() == {'/plant/cmd': COMMAND_TYPE, '/plant/y': 'std_msgs/msg/Float64'}
        assert bag.message_counts() == {'/plant/cmd': u.size, '/plant/y': y.size}
        messages = list(bag.messages('/plant/cmd'))
        schema = bag.topic_schema('/plant/cmd')
        # The listing of a missing topic's error, as for every other bag.
        with pytest.raises(BagError, match=r'it has: /plant/cmd \(plant_msgs/msg/Command, 100 '
                                           r'messages\); /plant/y \(std_msgs/msg/Float64'):
            bag.messages('/plant/u')
        records = list(bag.records('/plant/cmd'))
    assert [msg.msg.effort for msg in messages] == pytest.approx(u.tolist())
    first = messages[1].msg
    # The ROS 2 header: stamp and frame_id, without ROS 1's seq.
    assert not hasattr(first.header, 'seq')
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == divmod(T0_NS + STEP_NS,
                                                                          10 ** 9)
    assert schema.encoding == 'ros2msg' and schema.message_encoding == 'cdr'
    assert schema.definition.startswith(b'std_msgs/Header header\nfloat64 effort\n')
    # The copied bytes are CDR that a ROS 2 decoder of that definition reads.
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(schema.definition.decode(), COMMAND_TYPE))
    copy = store.deserialize_cdr(records[1].data, COMMAND_TYPE)
    assert (copy.effort, copy.header.frame_id, copy.source) == (u[1], 'base', 'prbs')


def test_files_that_are_no_bag_are_named(tmp_path):
    path, _, _ = _ros1_bag(tmp_path)
    cut = tmp_path / 'cut.bag'
    cut.write_bytes(path.read_bytes()[:5000])
    with pytest.raises(BagError, match=r'cannot read ROS 1 bag .*cut short before its index'):
        BagReader(cut)
    renamed = tmp_path / 'run.rosbag'
    shutil.copy(path, renamed)
    with pytest.raises(BagError, match=r'is a ROS 1 bag, .*ending in \.bag'):
        BagReader(renamed)
    old = tmp_path / 'old.bag'
    old.write_bytes(b'#ROSBAG V1.2\n' + bytes(100))
    with pytest.raises(BagError, match='ROS 1 bag of format version 1.2'):
        BagReader(old)
    kinds = {'log.csv': (b't,u,y\n0,1,2\n', r"a text file, CSV-like \('t,u,y'"),
             'x.bag': (b'\x1f\x8b\x08\x00' + bytes(40), 'a gzip-compressed file'),
             'empty.bag': (b'', 'an empty file'),
             'notes.txt': (b'hello\n', r"a text file \('hello'\)"),
             'run.db': (b'SQLite format 3\x00' + bytes(100), 'an SQLite database')}
    for name, (content, kind) in kinds.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(BagError, match=f'is not a bag: it is {kind}'):
            BagReader(tmp_path / name)


def test_a_file_cut_inside_its_first_chunk_is_called_truncated(bags, tmp_path):
    content = bags['mcap_file'].read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(content[:300])
    with BagReader(cut) as bag:
        assert bag.truncated and bag.topics() == {}
        with pytest.raises(BagError, match=r'not in the readable part of .*cut.mcap: the file '
                                           r'is truncated or damaged, and nothing is readable'):
            bag.messages('/plant/u')


def _zeros_bag(path, compression, megabytes):
    """Write a ROS 1 bag with one message of ``megabytes`` of zeros, compressed."""
    from rosbags.rosbag1 import Writer as Writer1

    store = get_typestore(Stores.ROS1_NOETIC)
    msgtype = 'std_msgs/msg/UInt8MultiArray'
    layout = store.types['std_msgs/msg/MultiArrayLayout'](dim=[], data_offset=0)
    msg = store.types[msgtype](layout=layout, data=np.zeros(megabytes << 20, dtype=np.uint8))
    writer = Writer1(path)
    writer.set_compression(getattr(Writer1.CompressionFormat, compression.upper()))
    with writer:
        connection = writer.add_connection('/blob', msgtype, typestore=store)
        writer.write(connection, 10 ** 18, store.serialize_ros1(msg, msgtype))
    return path


@pytest.mark.parametrize('compression', ['bz2', 'lz4'])
def test_compressed_ros1_chunks_are_read_within_bounds(tmp_path, compression):
    from replay_fixtures import DELAY, simulate, write_rosbag1

    u, y = simulate(DELAY, 2.0)
    plain = write_rosbag1(tmp_path / 'plain.bag', u, y)
    with BagReader(plain) as bag:
        expected = [(msg.topic, msg.log_time_ns) for msg in bag.messages()]
    # The same messages in compressed chunks (rosbags' writer), read through the bounds.
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer as Writer1

    packed = tmp_path / 'packed.bag'
    writer = Writer1(packed)
    writer.set_compression(getattr(Writer1.CompressionFormat, compression.upper()))
    with AnyReader([plain]) as source, writer:
        connections = {conn.id: writer.add_connection(conn.topic, conn.msgtype,
                                                      msgdef=conn.msgdef.data,
                                                      md5sum=conn.digest)
                       for conn in source.connections}
        for conn, time_ns, data in source.messages():
            writer.write(connections[conn.id], time_ns, data)
    with BagReader(packed) as bag:
        assert [(msg.topic, msg.log_time_ns) for msg in bag.messages()] == expected
    # A chunk that declares less than it holds stops being decompressed there.
    content = bytearray(packed.read_bytes())
    field = content.index(b'\x09\x00\x00\x00size=') + 9
    declared = int.from_bytes(content[field:field + 4], 'little')
    content[field:field + 4] = (declared // 2).to_bytes(4, 'little')
    lying = tmp_path / 'lying.bag'
    lying.write_bytes(bytes(content))
    with BagReader(lying) as bag:
        with pytest.raises(BagError, match=f'a {compression} chunk decompresses to more than '
                                           f'the {declared // 2} bytes it declares'):
            list(bag.messages())


def test_a_ros1_decompression_bomb_is_refused_before_decompressing(tmp_path):
    # 8 MiB of zeros compress more than 1000-fold with bz2 (lz4 cannot exceed 255).
    bomb = _zeros_bag(tmp_path / 'bomb.bag', 'bz2', 8)
    with pytest.raises(BagError, match=r'the chunk at byte \d+ declares 8.* a decompression '
                                       'bomb'):
        BagReader(bomb)


def test_a_bag_without_stored_definitions_is_decoded_with_the_standard_types(bags, tmp_path):
    # Bags from before Iron store no definitions: the standard ROS 2 types decode them.
    path = tmp_path / 'pre_iron'
    shutil.copytree(bags['sqlite3'], path)
    with sqlite3.connect(next(path.glob('*.db3'))) as database:
        database.execute('DELETE FROM message_definitions')
    standard = [topic for topic, msgtype in TOPICS.items() if msgtype != SAMPLE_TYPE]
    with BagReader(path) as bag:
        pairs = [(message, record) for message, record in zip(
            bag.messages(standard), [r for r in RECORDS if r.topic in standard])]
        assert len(pairs) == sum(r.topic in standard for r in RECORDS) > 100
        for message, record in pairs:
            assert (message.topic, message.log_time_ns) == (record.topic, record.time_ns)
            assert_fields(message.msg, record.fields)
        with pytest.raises(BagError, match='not a standard ROS 2 Jazzy type'):
            bag.messages('/plant/sample')


def test_messages_in_an_unmerged_sqlite_log_are_read_and_the_bag_left_alone(bags, tmp_path):
    """
    A database in WAL mode copied while its recorder wrote (or left by a crash).

    rosbags opens it as immutable, which ignores the log: the last half of the recording was
    left out without a word.
    """
    live = tmp_path / 'live'
    shutil.copytree(bags['sqlite3'], live)
    database = live / 'sqlite3.db3'
    half = RECORDS[len(RECORDS) // 2].time_ns
    connection = sqlite3.connect(database)
    try:
        connection.execute('PRAGMA journal_mode=WAL')
        rows = connection.execute('SELECT topic_id, timestamp, data FROM messages WHERE '
                                  'timestamp >= ? ORDER BY id', (half,)).fetchall()
        connection.execute('DELETE FROM messages WHERE timestamp >= ?', (half,))
        connection.commit()
        connection.execute('PRAGMA wal_checkpoint(TRUNCATE)')
        connection.executemany('INSERT INTO messages (topic_id, timestamp, data) VALUES '
                               '(?, ?, ?)', rows)
        connection.commit()
        bag = tmp_path / 'bag'
        bag.mkdir()
        for name in ('metadata.yaml', 'sqlite3.db3', 'sqlite3.db3-wal'):
            shutil.copyfile(live / name, bag / name)
    finally:
        connection.close()
    assert (bag / 'sqlite3.db3-wal').stat().st_size > 0
    digests = {path.name: hashlib.sha256(path.read_bytes()).hexdigest()
               for path in bag.iterdir()}
    with BagReader(bag) as reader:
        assert_records(list(reader.messages()), RECORDS)
        assert reader.warnings[0] == (
            f'{bag}/sqlite3.db3-wal holds messages not merged into sqlite3.db3 (the recorder '
            'did not close the database: a crash, or a copy taken while it was written); they '
            'are read from a merged copy, the bag is left as it is')
        assert reader.message_count() == len(RECORDS)
    assert {path.name: hashlib.sha256(path.read_bytes()).hexdigest()
            for path in bag.iterdir()} == digests
    # The .db3 file alone, too.
    with BagReader(bag / 'sqlite3.db3') as reader:
        assert reader.message_count() == len(RECORDS)
