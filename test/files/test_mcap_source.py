"""Tests of ctid_ros.files.mcap_source: standalone MCAP files, complete, unchunked or damaged."""

import dataclasses
import re
import shutil
import struct
import tracemalloc
import zlib

from bag_fixtures import (assert_fields, make_records, readable_prefix, T0_NS, TOPICS, truncate,
                          write_mcap, write_unchunked_mcap)
from ctid_ros.errors import BagError
from ctid_ros.files import mcap_source
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.mcap_source import chunk_records, McapSource, TopicSchema
import hostile_corpus
import lz4.frame
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.writer import CompressionType, Writer as McapWriter
import pytest
from replay_fixtures import damage_chunk, DELAY, float_records, simulate
from replay_fixtures import write_mcap as write_replay_mcap
import zstandard

RECORDS = make_records(seed=0)


@pytest.fixture(scope='module')
def mcap_file(tmp_path_factory):
    """Write the recording once as a chunked MCAP file; tests that damage it copy it first."""
    path = tmp_path_factory.mktemp('mcap') / 'run.mcap'
    write_mcap(path, RECORDS)
    return path


def assert_records(messages, expected):
    """Assert topics, log times (hence order) and decoded values of messages."""
    assert [(m.topic, m.log_time_ns) for m in messages] == [(r.topic, r.time_ns)
                                                            for r in expected]
    for message, record in zip(messages, expected):
        assert_fields(message.msg, record.fields)


def test_source_indexes_a_complete_file_from_its_summary(mcap_file):
    source = McapSource(mcap_file)
    try:
        assert source.topics == TOPICS and not source.truncated and source.warnings == []
        assert (source.start_ns, source.end_ns) == (RECORDS[0].time_ns, RECORDS[-1].time_ns)
        assert source.schema('/plant/y') == TopicSchema('std_msgs/msg/Float64', 'ros2msg',
                                                        b'float64 data\n', 'cdr')
        records = list(source.records(['/plant/u'], T0_NS, T0_NS + 10**8))
    finally:
        source.close()
    assert_records(records, [r for r in RECORDS
                             if r.topic == '/plant/u' and r.time_ns < T0_NS + 10**8])
    assert all(record.data[:4] == b'\x00\x01\x00\x00' for record in records)   # CDR LE


def test_unchunked_mcap_written_backwards_is_read_in_log_time_order(tmp_path):
    path = tmp_path / 'unchunked.mcap'
    write_unchunked_mcap(path, RECORDS)
    with BagReader(path) as bag:
        assert bag.message_count() == len(RECORDS) and not bag.truncated
        assert_records(list(bag.messages()), RECORDS)
        assert_records(list(bag.messages('/plant/sample', start=1.0)),
                       [r for r in RECORDS
                        if r.topic == '/plant/sample' and r.time_ns >= T0_NS + 10**9])


def test_truncated_mcap_replays_the_readable_prefix(mcap_file, tmp_path):
    path = tmp_path / 'cut.mcap'
    shutil.copy(mcap_file, path)
    truncate(path, 0.6)
    expected = readable_prefix(path, RECORDS)
    assert 0.4 * len(RECORDS) < len(expected) < 0.7 * len(RECORDS)
    with BagReader(path) as bag:
        assert bag.truncated
        assert 'truncated' in bag.warnings[0]
        assert f'{len(expected)} messages' in bag.warnings[0]
        assert bag.message_count() == len(expected)
        messages = list(bag.messages())
        assert_records(messages, expected)
        assert bag.end_time_ns == messages[-1].log_time_ns
        window = list(bag.messages('/plant/u', start=0.2, end=0.4))
        assert_records(window, [r for r in RECORDS if r.topic == '/plant/u'
                                and T0_NS + 2 * 10**8 <= r.time_ns < T0_NS + 4 * 10**8])


def test_damaged_chunk_in_indexed_mcap_raises_when_reached(mcap_file, tmp_path):
    path = tmp_path / 'damaged.mcap'
    data = bytearray(mcap_file.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(64)
    path.write_bytes(bytes(data))
    with BagReader(path) as bag:
        assert not bag.truncated
        received = []
        with pytest.raises(BagError, match='corrupted'):
            for message in bag.messages():
                received.append(message)
    assert 0 < len(received) < len(RECORDS)
    assert_records(received, RECORDS[:len(received)])


@pytest.mark.parametrize('name, message', [
    ('declares 2 GiB', 'declares 2 GiB uncompressed, more than the limit of 256 MiB per chunk'),
    ('no footer', 'declares 2 GiB uncompressed, more than the limit of 256 MiB per chunk'),
    ('ratio 30000', r'declares 64 MiB uncompressed from 2.\d+ KiB, a ratio of \d+ \(the limit '
                    r'is 1000\): a decompression bomb'),
    ('lying zstd frame', r'holds zstd data of 64 MiB \(as its frame header says\) but declares '
                         '1000 bytes'),
    ('lying lz4 frame', 'holds lz4 data of 16 MiB'),
])
def test_chunk_bombs_are_refused_before_decompressing(tmp_path, name, message):
    path = hostile_corpus.mcap_bombs(tmp_path)[name]
    before = path.read_bytes()
    tracemalloc.start()
    try:
        with pytest.raises(BagError, match=message):
            BagReader(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20 and path.read_bytes() == before
    # The same file as the storage of a rosbag2 directory is refused before rosbags reads it.
    bag = tmp_path / 'bag'
    bag.mkdir(exist_ok=True)
    shutil.copy(path, bag / 'run.mcap')
    (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    with pytest.raises(BagError, match=message):
        BagReader(bag)


@pytest.mark.parametrize('name, message', [
    ('zstd without size', 'chunk decompresses to more than 1001 bytes, not the 1000 bytes it '
                          'declares: damaged'),
    ('zero records', r'chunk holds an invalid record \(opcode 0, 0 bytes\) at byte 0: damaged'),
    ('unknown compression', "chunk compression 'bz2' is not supported"),
])
def test_damaged_chunks_end_the_readable_part(tmp_path, name, message):
    with BagReader(hostile_corpus.mcap_bombs(tmp_path)[name]) as bag:
        assert bag.truncated and re.search(message, bag.warnings[0])
        assert list(bag.messages()) == []


def test_chunk_records_of_a_good_chunk(tmp_path):
    content = b''.join(hostile_corpus.record(0x05, struct.pack('<HIQQ', 1, k, k, k) + b'abc')
                       for k in range(3))
    for compression, data in (('', content), ('zstd', zstandard.compress(content)),
                              ('lz4', lz4.frame.compress(content))):
        records = chunk_records(Chunk(compression=compression, data=data, message_end_time=2,
                                      message_start_time=0, uncompressed_crc=zlib.crc32(content),
                                      uncompressed_size=len(content)))
        assert [(message.sequence, message.data) for message in records] == [
            (0, b'abc'), (1, b'abc'), (2, b'abc')]
    with pytest.raises(BagError, match='CRC mismatch'):
        chunk_records(Chunk(compression='', data=content, message_end_time=2,
                            message_start_time=0, uncompressed_crc=1,
                            uncompressed_size=len(content)))


def _raw_messages(path, topics, start_ns=None, end_ns=None):
    """Return (topic, log time, bytes) of every message ``raw_blocks`` yields, in order."""
    source = McapSource(path)
    try:
        streams = source.raw_streams(topics)
        return [(streams[int(block.topic[row])].topic, int(block.log_time_ns[row]),
                 block.message(row))
                for block in source.raw_blocks(streams, start_ns, end_ns)
                for row in range(len(block))]
    finally:
        source.close()


def _rewrite_message_indexes(path, change):
    """Apply ``change`` to the (log time, offset) pairs of every message index record."""
    data = bytearray(path.read_bytes())
    with open(path, 'rb') as stream:
        indexes = make_reader(stream).get_summary().chunk_indexes
    for index in indexes:
        for offset in index.message_index_offsets.values():
            (size,) = struct.unpack_from('<I', data, offset + 11)
            pairs = [list(struct.unpack_from('<QQ', data, offset + 15 + 16 * k))
                     for k in range(size // 16)]
            change(pairs)
            for k, pair in enumerate(pairs):
                struct.pack_into('<QQ', data, offset + 15 + 16 * k, *pair)
    path.write_bytes(bytes(data))


def _shift_offsets(pairs):
    for pair in pairs:
        pair[1] += 1


def _repeat_an_entry(pairs):
    if len(pairs) > 1:
        pairs[1] = list(pairs[0])


@pytest.mark.parametrize('change', [_shift_offsets, _repeat_an_entry])
def test_raw_blocks_from_the_message_index_match_the_record_walk(tmp_path, monkeypatch,
                                                                 change):
    # The chunks are located by the message index records after them; an index that does not
    # fit the records falls back to walking them, with the same messages in the same order.
    walks = []
    original = mcap_source._message_positions
    monkeypatch.setattr(mcap_source, '_message_positions',
                        lambda *args: walks.append(1) or original(*args))
    # Log times on a 10 ms grid: messages of both topics share times, inside one chunk.
    path = tmp_path / 'ties.mcap'
    write_mcap(path, [dataclasses.replace(record, time_ns=record.time_ns // 10**7 * 10**7)
                      for record in RECORDS])
    damaged = tmp_path / 'damaged_index.mcap'
    shutil.copy(path, damaged)
    _rewrite_message_indexes(damaged, change)
    topics = ['/joint_states', '/plant/y']
    window = (T0_NS + 3 * 10**8, T0_NS + 9 * 10**8)     # times of messages: the end excluded
    for start_ns, end_ns in ((None, None), window):
        walks.clear()
        indexed = _raw_messages(path, topics, start_ns, end_ns)
        assert walks == []
        walked = _raw_messages(damaged, topics, start_ns, end_ns)
        assert len(walks) > 1
        assert indexed == walked
        with BagReader(path) as bag:
            streamed = [(record.topic, record.log_time_ns, record.data) for record in
                        bag.records(topics, start_ns=start_ns, end_ns=end_ns)]
        assert indexed == streamed and len(indexed) > 50
        assert any(one[1] == other[1] for one, other in zip(indexed, indexed[1:]))
        assert end_ns is None or end_ns in {time_ns for _, time_ns, _ in walked} | {
            record.time_ns // 10**7 * 10**7 for record in RECORDS if record.topic in topics}


def test_raw_blocks_of_a_truncated_mcap_use_the_message_indexes_read_by_the_scan(
        mcap_file, tmp_path, monkeypatch):
    # The scan of a file cut short notes each chunk's message index records as well.
    walks = []
    original = mcap_source._message_positions
    monkeypatch.setattr(mcap_source, '_message_positions',
                        lambda *args: walks.append(1) or original(*args))
    path = tmp_path / 'cut.mcap'
    shutil.copy(mcap_file, path)
    truncate(path, 0.6)
    topics = ['/joint_states', '/plant/u']
    indexed = _raw_messages(path, topics)
    with BagReader(path) as bag:
        assert bag.truncated
        streamed = [(record.topic, record.log_time_ns, record.data)
                    for record in bag.records(topics)]
    assert indexed == streamed and len(indexed) > 50
    # Only a chunk whose index the cut left incomplete is walked record by record.
    assert len(walks) <= 1


def test_a_chunk_of_more_messages_than_one_gather_is_located_exactly(tmp_path, monkeypatch):
    # 70 000 messages of two channels and varying sizes in one chunk: more message heads than
    # are gathered at once.
    walks = []
    original = mcap_source._message_positions
    monkeypatch.setattr(mcap_source, '_message_positions',
                        lambda *args: walks.append(1) or original(*args))
    path = tmp_path / 'big_chunk.mcap'
    with open(path, 'wb') as stream:
        writer = McapWriter(stream, chunk_size=64 << 20)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('std_msgs/msg/Float64', 'ros2msg', b'float64 data\n')
        channels = [writer.register_channel(topic, 'cdr', schema) for topic in ('/u', '/y')]
        for k in range(70_000):
            writer.add_message(channels[k % 2], T0_NS + k // 3 * 1000,
                               b'\x00\x01\x00\x00' + struct.pack('<d', k) + bytes(k % 5),
                               T0_NS)
        writer.finish()
    damaged = tmp_path / 'damaged_index.mcap'
    shutil.copy(path, damaged)
    _rewrite_message_indexes(damaged, _shift_offsets)
    window = (T0_NS + 1000, T0_NS + 20_000 * 1000)
    indexed = _raw_messages(path, ['/u', '/y'], *window)
    assert walks == []
    assert indexed == _raw_messages(damaged, ['/u', '/y'], *window) and len(walks) == 1
    assert [(topic, struct.unpack_from('<d', data, 4)[0]) for topic, _, data in indexed] == [
        (('/u', '/y')[k % 2], k) for k in range(3, 60_000)]


def test_a_chunk_failing_its_crc_is_named_with_the_file_and_its_place(tmp_path):
    # The CRC mismatch of an uncompressed chunk said only "chunk CRC mismatch: damaged".
    u, y = simulate(DELAY, 10.0)
    path = write_replay_mcap(tmp_path / 'run.mcap', float_records(u, y),
                             compression=CompressionType.NONE)
    index = damage_chunk(path, 0.5)
    with BagReader(path) as bag, pytest.raises(BagError) as raised:
        for _ in bag.messages():
            pass
    assert str(raised.value) == (f'{path} is corrupted at byte {index.chunk_start_offset} and '
                                 'cannot be read further: chunk CRC mismatch: damaged')


@pytest.mark.parametrize('compression, share', [(CompressionType.NONE, 0.55),
                                                (CompressionType.ZSTD, 0.2),
                                                (CompressionType.LZ4, 0.2)])
def test_a_chunk_cut_short_yields_its_whole_records_before_the_cut(tmp_path, compression,
                                                                   share):
    """
    A recording in one chunk (as rosbags writes a small bag), its file cut at 70 %.

    Nothing was read ("cut before its first complete chunk"); now every whole record of an
    uncompressed chunk before the cut, and the whole blocks of a zstd or lz4 one.
    """
    u, y = simulate(DELAY, 40.0)
    records = float_records(u, y)
    path = write_replay_mcap(tmp_path / 'run.mcap', records, chunk_size=1 << 24,
                             compression=compression)
    with open(path, 'rb') as stream:
        (index,) = make_reader(stream).get_summary().chunk_indexes
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(path.read_bytes()[:index.chunk_start_offset + int(0.7 * index.chunk_length)])
    with BagReader(cut) as bag:
        messages = list(bag.messages())
        assert bag.truncated
        assert f'the file ends in the middle of a chunk, of which {len(messages)} messages are ' \
            'read up to the cut' in bag.warnings[0]
    assert share * len(records) < len(messages) < 0.75 * len(records)
    assert [(m.topic, m.log_time_ns) for m in messages] == \
        [(r.topic, r.time_ns) for r in records[:len(messages)]]
    assert [m.msg.data for m in messages] == [r.fields['data'] for r in records[:len(messages)]]
