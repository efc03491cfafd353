"""Tests of ctid_ros.files.mcap_source: standalone MCAP files, complete, unchunked or damaged."""

import shutil

from bag_fixtures import (assert_fields, make_records, readable_prefix, T0_NS, TOPICS, truncate,
                          write_mcap, write_unchunked_mcap)
from ctid_ros.errors import BagError
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.mcap_source import McapSource, TopicSchema
import pytest

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
