"""
Warnings only for what happened: start-up, window changes, buffer turnover, time origin.

Issue 25 item 4: a window that is short only because the data have not arrived yet (after a
start or a window change) is no gap; a buffer's normal turnover is no loss; the messages of a
sliding replay count time from one origin and name the configured window.
"""

from types import SimpleNamespace

from ctid_ros.errors import DataError
from ctid_ros.streaming.buffer import SampleBuffer
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import count_change
from ctid_ros.streaming.replay import replay_messages
from ctid_ros.streaming.sampler import MessageSampler
from ctid_ros.streaming.session import IdentificationSession
import numpy as np
import pytest
from replay_fixtures import DELAY, float_records, simulate, T0_NS

STEP_NS = 10_000_000


def delay_config(**overrides):
    params = {key: tuple(value) if isinstance(value, list) else value
              for key, value in DELAY['params'].items()}
    return IdentificationConfig(model=DELAY['model'], input_topic='/plant/u',
                                output_topic='/plant/y', **{**params, **overrides})


def messages(seconds):
    u, y = simulate(DELAY, seconds)
    return [(record.topic, record.time_ns, SimpleNamespace(data=record.fields['data']))
            for record in float_records(u, y)]


def test_start_up_windows_are_short_without_a_left_out_warning():
    replay = replay_messages(messages(40.0), delay_config(window=10.0, update_period=2.0),
                             sliding=True)
    # The first estimates (from 6 s on) have less than the 10 s window and 10 s transient.
    assert len(replay.updates) == 17
    short = [update for update in replay.updates if update.window.dropped]
    assert len(short) >= 5
    for update in replay.updates:
        assert not [note for note in update.warnings if 'left out' in note], update.warnings
        assert update.window.dropped == update.window.unreceived
    # A real gap is still reported: the input silent for 1 s in the middle.
    silent = [message for message in messages(40.0) if not (
        message[0] == '/plant/u' and T0_NS + 25 * 10 ** 9 < message[1] < T0_NS + 26 * 10 ** 9)]
    gapped = replay_messages(silent, delay_config(window=10.0, update_period=2.0),
                             sliding=True)
    notes = [note for update in gapped.updates for note in update.warnings
             if 'left out by 1 gap(s)' in note]
    assert notes


def test_skipped_ticks_count_from_one_origin_and_name_the_configured_window():
    config = delay_config(window=20.0, update_period=2.0)
    replay = replay_messages(messages(30.0), config, sliding=True)
    first = replay.skipped[0]
    assert first.time_ns == T0_NS + 2 * 10 ** 9
    # Seconds since the first message, as the replay's own lines count them (t=2.00 s).
    assert 'in the 20 s window (plus 20 s settling transient) ending at t=1.940 s' in \
        first.reason
    assert 'need at least 10 s' in first.reason
    assert '1700000' not in first.reason
    # The caller's origin (e.g. the bag's start) is used when given.
    shifted = replay_messages(messages(30.0), config, sliding=True,
                              origin_ns=T0_NS - 10 ** 9).skipped[0]
    assert 'ending at t=2.940 s' in shifted.reason


def fill(buffer, first, count):
    """Input and output at 100 Hz, output 1 ms after the input; a slow square wave input."""
    stamps = T0_NS + np.arange(first, first + count, dtype=np.int64) * STEP_NS
    buffer.add_inputs(stamps, np.floor(np.arange(first, first + count) / 150) % 2)
    buffer.add_outputs(stamps + 1_000_000, np.sin(np.arange(first, first + count) / 30.0))


def test_a_window_change_keeps_the_data_that_still_fits():
    old_config = delay_config(window=10.0)
    sampler = MessageSampler(old_config, ('/plant/u', '/plant/y'))
    old = sampler.buffer(old_config.buffer_capacity(100.0), old_config)
    fill(old, 0, 3000)
    before = old.stats()
    # A shorter window: the newest samples that fit the smaller buffer are kept.
    short = delay_config(window=5.0)
    smaller = sampler.buffer(short.buffer_capacity(100.0), short, previous=old)
    stats = smaller.stats()
    assert stats.u.size == short.buffer_capacity(100.0) < before.u.size
    assert stats.u.last == before.u.last and stats.y.last == before.y.last
    assert stats.u.received == 3000 and stats.u.evicted == 0
    window = IdentificationSession(short).take_window(smaller)
    assert window.complete and window.warnings == ()
    # A longer window: everything is kept, the first windows are short but not warned about.
    long = delay_config(window=20.0)
    larger = sampler.buffer(long.buffer_capacity(100.0), long, previous=old)
    assert larger.stats().u.size == before.u.size
    window = IdentificationSession(long).take_window(larger)
    assert window.dropped == window.unreceived > 0 and window.warnings == ()
    assert len(window.data) * 0.01 == pytest.approx(29.95, abs=0.02)
    # Another input topic: its samples are another signal, not kept; the output is.
    other = MessageSampler(old_config, ('/plant/other', '/plant/y'))
    moved = other.buffer(old_config.buffer_capacity(100.0), old_config, previous=old)
    assert (moved.stats().u.size, moved.stats().y.size) == (0, before.y.size)


def test_normal_turnover_is_not_counted_as_evicted():
    config = delay_config(window=2.0)
    sampler = MessageSampler(config, ('/plant/u', '/plant/y'))
    buffer = sampler.buffer(config.buffer_capacity(100.0), config)
    for first in range(0, 20_000, 500):
        fill(buffer, first, 500)
    stats = buffer.stats()
    assert stats.u.received == 20_000 and stats.u.size == buffer.capacity
    assert (stats.u.evicted, stats.y.evicted) == (0, 0)
    # A buffer too small for the span its windows need: what it pushes out is counted, and
    # the short window says why.
    small = SampleBuffer(300, history=config.history_span + config.max_gap +
                         config.reorder_horizon)
    small.origin_ns = T0_NS
    for first in range(0, 2000, 100):
        fill(small, first, 100)
    stats = small.stats()
    assert stats.u.evicted == pytest.approx(2000 - 300 - 0, abs=20) and stats.u.evicted > 0
    window = small.window(4.0, 0.01, min_length=1.0)
    assert window.unreceived > 0
    assert any('the buffer of 300 samples holds input only since t=17.000 s' in note
               for note in window.warnings), window.warnings
    with pytest.raises(DataError, match=r'holds input only since t=17\.000 s: raise its '
                                        'capacity'):
        small.window(8.0, 0.01, min_length=4.0)


def test_counters_are_python_ints_that_only_grow_by_what_happened():
    # A batch far larger than the buffer (a huge message's worth): received and accepted count
    # it whole, the turnover is no eviction, and no counter is a fixed-width integer.
    buffer = SampleBuffer(1000, history=0.5)
    count = 2_000_000
    stamps = np.arange(count, dtype=np.int64) * 1_000_000
    buffer.add_inputs(stamps, np.zeros(count))
    buffer.add_outputs(stamps, np.ones(count))
    stats = buffer.stats().u
    assert (stats.received, stats.accepted, stats.evicted, stats.size) == (
        count, count, 0, 1000)
    assert all(type(value) is int for value in (stats.received, stats.accepted, stats.evicted,
                                                stats.late, stats.duplicates))
    # The middleware's size_t increments: a negative one read as unsigned counts as nothing.
    assert [count_change(value) for value in (
        3, 0, 18446744071562067969, 2 ** 64 - 1, -5, None, float('nan'), np.uint64(7))] == [
        3, 0, 0, 0, 0, 0, 0, 7]


@pytest.mark.parametrize('output_rate', [20, 100])
def test_a_jittered_command_without_drops_has_no_missing_samples(output_rate):
    # A command stamped by a free-running 20 Hz timer (every interval 49.85-50.16 ms, so its
    # clock wanders by milliseconds) against a steadily sampled output: no message is lost.
    rng = np.random.default_rng(1)
    count = 800
    u_stamps = T0_NS + np.concatenate(([0], np.cumsum(rng.uniform(49.85e6, 50.16e6,
                                                                  count - 1)))).astype(np.int64)
    outputs = count * output_rate // 20
    y_stamps = (T0_NS + 3_000_000 + np.arange(outputs) * (10 ** 9 // output_rate) +
                rng.uniform(0, 300_000, outputs)).astype(np.int64)
    u = (np.arange(count) // 37 % 2).astype(float)
    y = np.sin(np.arange(outputs) / 50.0)
    buffer = SampleBuffer(5000)
    buffer.add_inputs(u_stamps, u)
    buffer.add_outputs(y_stamps, y)
    ends = u_stamps[[400, 600, 799]]
    for end in ends:
        window = buffer.window(16.2, 0.05, int(end), min_length=8.0)
        assert window.missing == (0, 0), window.warnings
        assert window.warnings == ()
    # A message really lost is still counted: one output sample and one input sample.
    lost = SampleBuffer(5000)
    lost.add_inputs(np.delete(u_stamps, 500), np.delete(u, 500))
    drop = int(np.searchsorted(y_stamps, u_stamps[520]))
    lost.add_outputs(np.delete(y_stamps, drop), np.delete(y, drop))
    window = lost.window(16.2, 0.05, int(ends[1]), min_length=8.0)
    assert window.missing == (1, 1)
    assert [note.split(':')[0] for note in window.warnings] == ['input', 'output']


def test_the_first_sample_of_a_message_sets_the_buffer_time_origin():
    # The live node's path: its messages count from its first sample, not from the epoch.
    settings = delay_config(window=10.0)
    sampler = MessageSampler(settings, ('/plant/u', '/plant/y'))
    buffer = sampler.buffer(settings.buffer_capacity(100.0), settings)
    for topic, stamp, message in messages(3.0):
        sampler(topic, stamp, message).add_to(buffer)
    assert buffer.origin_ns == T0_NS
    with pytest.raises(DataError, match=r'in the 10 s window \(plus 10 s settling transient\) '
                                        r'ending at t=2\.940 s'):
        IdentificationSession(settings).take_window(buffer)
    # A window change keeps the origin with the data.
    longer = delay_config(window=20.0)
    assert sampler.buffer(longer.buffer_capacity(100.0), longer,
                          previous=buffer).origin_ns == T0_NS
