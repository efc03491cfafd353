"""Asynchronous samples are admitted, bounded and resampled as documented, live or in batch."""

import math
import threading

from ctid_ros.errors import DataError
from ctid_ros.streaming.buffer import (Admission, capacity_for, Gap, Refusals, resample,
                                       SampleBuffer)
import numpy as np
import pytest

NS = 1_000_000_000


def ns(seconds):
    return int(round(seconds * NS))


def output_signal(t):
    return np.sin(2 * np.pi * 0.7 * t) + 0.3 * np.cos(2 * np.pi * 1.3 * t)


def square_wave(rng, duration):
    """Return change instants (ns) and the held values of an irregular +-1 square wave."""
    changes = np.cumsum(rng.uniform(0.2, 0.6, size=int(duration / 0.2) + 2)) + 0.013
    changes = np.concatenate(([0.0], changes[changes < duration]))
    values = np.where(np.arange(changes.size) % 2 == 0, 1.0, -1.0)
    return np.array([ns(t) for t in changes]), values


def jittered_output(rng, duration, period=0.005, jitter=0.001):
    count = int(duration / period)
    t = np.arange(count) * period + rng.uniform(-jitter, jitter, size=count)
    t = t[t >= 0]
    stamps = np.array([ns(x) for x in t])
    return stamps, output_signal(stamps / NS)


def arrival_order(rng, events, max_delay):
    """Shuffle events (stream, stamp, value) as a network with random latency would."""
    arrival = [stamp + ns(rng.uniform(0, max_delay)) for _, stamp, _ in events]
    return [events[i] for i in np.argsort(arrival, kind='stable')]


def feed(buffer, events):
    add = {'u': buffer.add_input, 'y': buffer.add_output}
    return [add[stream](stamp, value) for stream, stamp, value in events]


def test_known_signals_sampled_asynchronously_are_reproduced_on_the_grid():
    rng = np.random.default_rng(7)
    u_stamps, u_values = square_wave(rng, 6.0)
    y_stamps, y_values = jittered_output(rng, 6.0)
    events = ([('u', s, v) for s, v in zip(u_stamps, u_values)] +
              [('y', s, v) for s, v in zip(y_stamps, y_values)])
    buffer = SampleBuffer(5000, max_gap=0.7, reorder_horizon=0.05)
    verdicts = feed(buffer, arrival_order(rng, events, 0.02))
    assert set(verdicts) == {Admission.ACCEPTED}

    window = buffer.window(4.0, 0.01, ns(5.0))
    data = window.data
    assert window.complete and window.requested == 400 and window.gaps == ()
    assert data.ts == 0.01 and data.t0 == pytest.approx(1.01, abs=1e-12)
    grid = 1.01 + 0.01 * np.arange(400)
    # Input: the value of the last change at or before each instant (exact).
    expected_u = [u_values[max(i for i, c in enumerate(u_stamps) if c <= ns(t))] for t in grid]
    np.testing.assert_array_equal(data.u, expected_u)
    # Output: linear interpolation between samples at most 7 ms apart; the error is bounded by
    # h**2/8 * max|y''| = 0.007**2/8 * 39.4 = 2.4e-4.
    assert np.max(np.abs(data.y - output_signal(grid))) < 2.5e-4

    # Windows are aligned to multiples of the sample time, so successive ones share instants.
    later = buffer.window(4.0, 0.01, ns(5.456)).data
    assert later.t0 == pytest.approx(1.46, abs=1e-12)
    np.testing.assert_array_equal(later.u[:355], data.u[45:])
    np.testing.assert_array_equal(later.y[:355], data.y[45:])


def test_default_end_is_the_settled_coverage():
    buffer = SampleBuffer(1000, max_gap=0.6, reorder_horizon=0.05)
    for k in range(200):
        buffer.add_output(ns(0.01 * k + 0.002), math.sin(k / 10))
    buffer.add_input(ns(0.5), 1.0)
    buffer.add_input(ns(1.0), 2.0)
    # The output ends at 1.992 s, the input is held until 1.0 + max_gap.
    assert buffer.coverage(settled=False) == (ns(0.5), ns(1.6))
    assert buffer.coverage() == (ns(0.5), ns(1.55))
    window = buffer.window(1.0, 0.01)
    # Two input samples are no periodic input: the grid is the multiples of 10 ms. The output
    # is taken at its own samples, 2 ms after them: the last measured by 1.55 s is 1.542 s.
    assert window.complete and window.data.time[-1] == pytest.approx(1.54)
    assert window.data.output_skew == pytest.approx(0.002)
    assert window.data.y[-1] == math.sin(154 / 10)
    assert window.data.u[0] == 1.0 and window.data.u[-1] == 2.0


def test_exact_duplicates_keep_the_first_sample():
    buffer = SampleBuffer(100, reorder_horizon=0.05)
    for k in range(20):
        buffer.add_input(ns(0.01 * k), 0.0)
        assert buffer.add_output(ns(0.01 * k), float(k)) is Admission.ACCEPTED
    assert buffer.add_output(ns(0.15), 99.0) is Admission.DUPLICATE
    assert buffer.add_output(ns(0.19), 99.0) is Admission.DUPLICATE
    stats = buffer.stats()
    assert (stats.y.received, stats.y.accepted, stats.y.duplicates, stats.y.size) == (
        22, 20, 2, 20)
    y = buffer.window(0.1, 0.01, ns(0.19)).data.y
    np.testing.assert_array_equal(y, np.arange(10.0, 20.0))


def test_reordering_within_the_horizon_gives_the_in_order_result():
    rng = np.random.default_rng(3)
    stamps = np.arange(500) * 10_000_000 + 1_234_567
    values = rng.normal(size=500)
    ordered = SampleBuffer(1000, max_gap=0.1, reorder_horizon=0.05)
    shuffled = SampleBuffer(1000, max_gap=0.1, reorder_horizon=0.05)
    for buffer in (ordered, shuffled):
        for k in range(0, 500, 5):
            buffer.add_input(int(stamps[k]), float(values[k] > 0))
    feed(ordered, [('y', s, v) for s, v in zip(stamps, values)])
    # Blocks of four reversed: every sample arrives at most 30 ms after a newer one.
    order = np.concatenate([np.arange(k, k + 4)[::-1] for k in range(0, 500, 4)])
    verdicts = feed(shuffled, [('y', stamps[i], values[i]) for i in order])
    assert verdicts.count(Admission.ACCEPTED) == 500
    assert shuffled.stats().y.late == 0
    a, b = (buffer.window(4.0, 0.01, ns(4.9)).data for buffer in (ordered, shuffled))
    np.testing.assert_array_equal(a.y, b.y)
    np.testing.assert_array_equal(a.u, b.u)


def test_late_samples_inside_the_horizon_are_used_and_older_ones_counted_and_dropped():
    buffer = SampleBuffer(1000, max_gap=0.1, reorder_horizon=0.05)
    for k in range(101):
        buffer.add_input(ns(0.01 * k), 1.0)
        if k != 97:
            buffer.add_output(ns(0.01 * k), 0.0)
    # 30 ms late, within the horizon: inserted in order and used.
    assert buffer.add_output(ns(0.97), 5.0) is Admission.ACCEPTED
    # 200 ms late: dropped and counted, never seen in the data.
    assert buffer.add_output(ns(0.805), 7.0) is Admission.LATE
    assert buffer.add_input(ns(0.5), 3.0) is Admission.LATE
    stats = buffer.stats()
    assert (stats.y.late, stats.u.late, stats.y.size, stats.u.size) == (1, 1, 101, 101)
    data = buffer.window(1.0, 0.01, ns(1.0)).data
    assert data.y[data.time.round(2).tolist().index(0.97)] == 5.0
    assert np.count_nonzero(data.y) == 1
    np.testing.assert_array_equal(data.u, 1.0)


def test_non_finite_values_are_rejected_and_counted():
    clean = SampleBuffer(100, max_gap=0.1)
    dirty = SampleBuffer(100, max_gap=0.1)
    for k in range(50):
        for buffer in (clean, dirty):
            buffer.add_pair(ns(0.01 * k), float(k % 7), math.cos(k / 5))
    assert dirty.add_output(ns(0.255), math.nan) is Admission.NON_FINITE
    assert dirty.add_input(ns(0.255), math.inf) is Admission.NON_FINITE
    assert dirty.add_pair(ns(0.5), -math.inf, math.nan) == (Admission.NON_FINITE,
                                                            Admission.NON_FINITE)
    stats = dirty.stats()
    assert (stats.u.non_finite, stats.y.non_finite) == (2, 2)
    assert (stats.u.received, stats.u.accepted) == (52, 50)
    a, b = (buffer.window(0.4, 0.01, ns(0.49)).data for buffer in (clean, dirty))
    np.testing.assert_array_equal(a.y, b.y)
    np.testing.assert_array_equal(a.u, b.u)


def gapped_buffer(output_silence=(), input_silence=(), input_end=6.5):
    """Input and output at 100 Hz (3 ms after the grid) with optional silences."""
    buffer = SampleBuffer(2000, max_gap=0.2, reorder_horizon=0.05)
    for k in range(650):
        t = 0.01 * k + 0.003
        if not (output_silence and output_silence[0] < t < output_silence[1]):
            buffer.add_output(ns(t), output_signal(t))
        if t <= input_end and not (input_silence and input_silence[0] < t < input_silence[1]):
            buffer.add_input(ns(t), math.floor(t))
    return buffer


def test_a_gap_splits_the_window_and_the_latest_long_segment_is_returned():
    buffer = gapped_buffer(output_silence=(3.0, 4.0))
    window = buffer.window(6.0, 0.01, ns(6.0), min_length=1.0)
    # The grid follows the input's instants, 3 ms after the multiples of 10 ms.
    assert window.segments == ((0.003, 2.993), (4.003, 5.993))
    assert window.gaps == (Gap('output', 2.993, 4.003),)
    assert window.gaps[0].duration == pytest.approx(1.01)
    data = window.data
    assert data.t0 == pytest.approx(4.003) and len(data) == 200
    assert window.dropped == 400 and not window.complete
    assert window.warnings == ('400 of 600 samples left out by 1 gap(s) in the data',)
    # Nothing bridged the silence: all values are samples after it.
    np.testing.assert_allclose(data.y, output_signal(data.time), rtol=0, atol=1e-12)

    # The latest segment is too short for 2.5 s: the earlier one is the latest long enough.
    earlier = buffer.window(6.0, 0.01, ns(6.0), min_length=2.5).data
    assert earlier.t0 == pytest.approx(0.003) and earlier.time[-1] == pytest.approx(2.993)
    with pytest.raises(DataError, match=r'3 s of input and output available together in the '
                                        r'6 s window .* need at least 3\.5 s; output missing for '
                                        r'1\.01 s from t=2\.993 s \(max_gap 0\.2 s\)'):
        buffer.window(6.0, 0.01, ns(6.0), min_length=3.5)


def test_the_input_is_never_held_across_a_gap_and_only_max_gap_after_its_end():
    buffer = gapped_buffer(input_silence=(3.0, 4.0), input_end=5.01)
    window = buffer.window(6.0, 0.01, ns(6.0), min_length=1.0)
    # Held 0.2 s after the last input sample at 5.003 s, then missing.
    assert window.segments == ((0.003, 2.993), (4.003, 5.203))
    assert window.gaps == (Gap('input', 2.993, 4.003), Gap('input', 5.003, None))
    np.testing.assert_array_equal(window.data.u, np.floor(window.data.time.round(3)))
    with pytest.raises(DataError, match=r'input silent since t=5\.003 s'):
        buffer.window(6.0, 0.01, ns(6.0), min_length=3.5)


def test_memory_is_bounded_by_the_capacity():
    buffer = SampleBuffer(100, max_gap=0.1)
    for k in range(10_000):
        buffer.add_pair(k * 1_000_000, float(k), float(k))
    stats = buffer.stats()
    assert (stats.u.size, stats.u.evicted, stats.u.accepted) == (100, 9900, 10_000)
    assert stats.y.first == pytest.approx(9.9) and stats.y.last == pytest.approx(9.999)
    assert buffer.capacity == 100
    data = buffer.window(0.09, 0.001, ns(9.999)).data
    np.testing.assert_array_equal(data.y, np.arange(9910.0, 10_000.0))
    with pytest.raises(DataError, match='buffer of 100 samples holds input only since '
                                        r't=9\.900 s: raise its capacity'):
        buffer.window(1.0, 0.001, ns(9.999))


def test_concurrent_appends_and_windows():
    buffer = SampleBuffer(2000, max_gap=0.05, reorder_horizon=0.01)
    total = 20_000
    failures, windows = [], []

    def writer():
        for k in range(total):
            stamp = k * 1_000_000
            buffer.add_pair(stamp, stamp / NS, stamp / NS)

    def reader():
        while thread.is_alive() or not windows:
            try:
                data = buffer.window(0.5, 0.01).data
            except DataError:
                continue
            # Output a ramp sampled every ms: interpolation is exact, the hold lags < 1 ms.
            if not (np.allclose(data.y, data.time, atol=1e-9) and
                    np.all((data.time - data.u >= -1e-9) & (data.time - data.u < 1e-3))):
                failures.append(data)
            windows.append(len(data))

    thread = threading.Thread(target=writer)
    consumer = threading.Thread(target=reader)
    thread.start()
    consumer.start()
    thread.join()
    consumer.join()
    assert failures == []
    assert windows and set(windows) == {50}
    stats = buffer.stats()
    for stream in (stats.u, stats.y):
        assert (stream.received, stream.accepted, stream.evicted, stream.size) == (
            total, total, total - 2000, 2000)
        assert stream.duplicates == stream.late == stream.non_finite == 0


def messy_streams(seed):
    """Jittered streams with duplicates, NaNs, reordering and late samples, in arrival order."""
    rng = np.random.default_rng(seed)
    u_stamps, u_values = square_wave(rng, 8.0)
    y_stamps, y_values = jittered_output(rng, 8.0)
    y_values = y_values + 0.01 * rng.normal(size=y_values.size)
    events = ([('u', s, v) for s, v in zip(u_stamps, u_values)] +
              [('y', s, v) for s, v in zip(y_stamps, y_values)])
    events += [('y', y_stamps[i], 42.0) for i in rng.choice(y_stamps.size, 20)]
    events += [('y', y_stamps[i] + 1, math.nan) for i in rng.choice(y_stamps.size, 5)]
    events = arrival_order(rng, events, 0.03)
    late = [('y', stamp - ns(0.5), 9.0) for _, stamp, _ in events[1000:1003]]
    return events[:1000] + late + events[1000:]


def test_batch_resampling_equals_the_live_buffer_fed_the_same_samples():
    events = messy_streams(11)
    live = SampleBuffer(10_000, max_gap=0.7, reorder_horizon=0.04)
    verdicts = feed(live, events)
    assert set(verdicts) == {Admission.ACCEPTED, Admission.DUPLICATE, Admission.LATE,
                             Admission.NON_FINITE}
    end = live.coverage()[1]
    window = live.window(5.0, 0.01, end)

    def column(stream, index):
        return [event[index] for event in events if event[0] == stream]
    batch, stats = resample(np.array(column('u', 1)), column('u', 2), np.array(column('y', 1)),
                            column('y', 2), 0.01, length=5.0, end_ns=end, max_gap=0.7,
                            reorder_horizon=0.04)
    assert stats == live.stats()
    assert stats.y.late == 3 and stats.y.non_finite == 5 and stats.y.duplicates >= 20
    np.testing.assert_array_equal(batch.data.u, window.data.u)
    np.testing.assert_array_equal(batch.data.y, window.data.y)
    assert (batch.data.ts, batch.data.t0, batch.segments, batch.gaps, batch.requested) == (
        window.data.ts, window.data.t0, window.segments, window.gaps, window.requested)
    assert len(batch.data) == 500


def test_batch_defaults_cover_all_complete_data():
    stamps = np.arange(0, 3_000_000_000, 5_000_000) + 2_000_000
    values = np.sin(stamps / NS)
    window, stats = resample(stamps, values > 0, stamps, values, 0.01)
    data = window.data
    assert window.complete
    # Every other input instant (the input never changes: those nearest the multiples of
    # 10 ms), from the first sample to the last; the output at its own samples there.
    assert data.t0 == pytest.approx(0.002) and data.time[-1] == pytest.approx(2.992)
    assert (data.ts, data.output_skew) == (0.01, 0.0)
    assert stats.u.received == stamps.size
    np.testing.assert_array_equal(data.y, values[::2])


def test_missing_data_errors_say_which_stream_and_how_much():
    buffer = SampleBuffer(100)
    with pytest.raises(DataError, match='no samples yet from input: none received; output: '
                                        'none received'):
        buffer.window(1.0, 0.01)
    buffer.add_input(0, 1.0)
    for k in range(3):
        buffer.add_output(k, math.nan)
    with pytest.raises(DataError, match=r'output: 3 received, all refused \(non-finite 3'):
        buffer.coverage()
    for k in range(100):
        buffer.add_pair(ns(0.01 * k), 1.0, 2.0)
    with pytest.raises(DataError, match=r'1 s of input and output .* need at least 5 s; '
                                        r'input starts at t=0\.000 s'):
        buffer.window(10.0, 0.01, ns(0.99))
    with pytest.raises(DataError, match='fewer than the 20 required'):
        buffer.window(0.1, 0.01, min_length=0.2)
    # Seconds passed as a stamp would be misread as nanoseconds.
    with pytest.raises(TypeError):
        buffer.add_input(1.5, 0.0)


def test_batch_input_checks_and_capacity_sizing():
    with pytest.raises(DataError, match='/u data stamps must be integer nanoseconds'):
        resample([0.0, 0.5], [1.0, 2.0], [0, 1], [1.0, 2.0], 0.01, names=('/u data', '/y data'))
    with pytest.raises(DataError, match='no samples yet from /y data: none received'):
        resample([0, 1], [1.0, 2.0], [], [], 0.01, names=('/u data', '/y data'))
    with pytest.raises(DataError, match='equal length'):
        resample([0, 1], [1.0], [0, 1], [1.0, 2.0], 0.01)
    assert capacity_for(10.0, 100.0) == 2000
    assert capacity_for(0.01, 1.0) == 16
    with pytest.raises(DataError, match='rate > 0'):
        capacity_for(10.0, 0.0)


HOUR = 3600 * NS


def steady(buffer, first, count, step=ns(0.01), stream='pair'):
    """Feed ``count`` samples every ``step`` from stamp ``first``; return the verdicts."""
    verdicts = []
    for k in range(first, first + count):
        stamp = k * step
        if stream == 'pair':
            verdicts.extend(buffer.add_pair(stamp, float(k % 7), float(k)))
        else:
            verdicts.append(buffer.add_output(stamp, float(k)))
    return verdicts


def test_a_stamp_an_hour_ahead_does_not_capture_the_stream():
    buffer = SampleBuffer(5000, max_gap=0.5, reorder_horizon=0.05)
    steady(buffer, 1, 300)
    assert buffer.add_output(ns(3.005) + HOUR, 1e6) is Admission.PENDING
    assert buffer.stats().y.pending == 1
    # The next sample of the stream's own clock is admitted and refuses the stray one.
    assert set(steady(buffer, 301, 300)) == {Admission.ACCEPTED}
    stats = buffer.stats().y
    assert (stats.accepted, stats.out_of_clock, stats.late, stats.pending) == (600, 1, 0, 0)
    window = buffer.window(5.0, 0.01, ns(6.0))
    assert window.complete and window.data.y.max() == 600.0
    assert window.refused[1] == Refusals(window.refused[1].stream, out_of_clock=1)
    assert window.warnings == ('output: 1 samples refused in this window (out of clock 1)',)


@pytest.mark.parametrize('stray', ['random', 'zero', 'ahead', 'behind'])
def test_stray_stamps_among_good_ones_are_refused_and_counted(stray):
    rng = np.random.default_rng(4)
    buffer = SampleBuffer(5000, max_gap=0.5, reorder_horizon=0.05)
    refused = 0
    for k in range(1, 1001):
        buffer.add_pair(ns(0.01 * k) + HOUR, float(k % 7), float(k))
        if k % 10 == 5:
            stamp = {'random': int(rng.integers(0, 2 ** 62)), 'zero': 0,
                     'ahead': ns(0.01 * k + 30.0) + HOUR,
                     'behind': ns(0.01 * k - 20.0) + HOUR}[stray]
            verdict = buffer.add_output(stamp, -1.0)
            refused += 1
            assert verdict in (Admission.PENDING, Admission.OUT_OF_CLOCK, Admission.LATE)
    stats = buffer.stats()
    assert stats.y.accepted == 1000 and stats.y.out_of_clock + stats.y.late == refused
    window = buffer.window(9.0, 0.01, ns(10.0) + HOUR)
    assert window.complete and np.all(window.data.y > 0)
    assert window.refused[1].total == 90 and window.refused[0].total == 0


def test_a_stream_resuming_after_a_silence_or_losing_most_messages_loses_nothing():
    buffer = SampleBuffer(5000, max_gap=0.5, reorder_horizon=0.05)
    steady(buffer, 1, 200)
    verdicts = steady(buffer, 1200, 200)
    # The first two samples after 10 s of silence wait for a third to confirm the new clock.
    assert verdicts[:6] == [Admission.PENDING] * 4 + [Admission.ACCEPTED] * 2
    stats = buffer.stats()
    assert stats.u.accepted == stats.y.accepted == 400 and stats.y.out_of_clock == 0
    lossy = SampleBuffer(5000, max_gap=0.5, reorder_horizon=0.01)
    rng = np.random.default_rng(2)
    kept = np.flatnonzero(rng.uniform(size=3000) < 0.3)
    for k in kept:
        lossy.add_output(ns(0.005 * k), float(k))
    stats = lossy.stats().y
    assert stats.accepted == kept.size and stats.out_of_clock == stats.pending == 0


def test_a_publisher_restarted_on_an_earlier_clock_re_anchors_the_stream():
    buffer = SampleBuffer(5000, max_gap=0.5, reorder_horizon=0.05)
    # The first sample is stamped an hour ahead: every later one is behind it.
    buffer.add_pair(HOUR, 0.0, 0.0)
    verdicts = steady(buffer, 1, 100)
    stats = buffer.stats()
    assert stats.y.reanchors == 1 and stats.y.first == pytest.approx(0.01)
    # Refused until the stamps behind the clock spanned max_gap, then admitted after all.
    assert verdicts[:2] == [Admission.OUT_OF_CLOCK] * 2 and verdicts[-1] is Admission.ACCEPTED
    assert stats.y.accepted == 101 and stats.y.size == 100 and stats.y.out_of_clock == 0
    # A simulated clock restarting from zero.
    steady(buffer, 10_000, 300)
    verdicts = steady(buffer, 1, 300)
    assert buffer.stats().y.reanchors == 2 and buffer.stats().y.last == pytest.approx(3.0)
    window = buffer.window(2.0, 0.01, ns(3.0))
    assert window.complete and window.data.y[-1] == 300.0


def test_refused_samples_of_the_window_are_reported():
    # Issue 16: 1 in 11 input samples and 1 in 7 output samples non-finite.
    buffer = SampleBuffer(5000, max_gap=0.5, reorder_horizon=0.05)
    for k in range(1, 1001):
        u = math.nan if k % 11 == 0 else float(k % 5)
        y = math.nan if k % 7 == 0 else float(k)
        buffer.add_pair(ns(0.01 * k), u, y)
    window = buffer.window(5.0, 0.01, ns(10.0))
    assert [refusals.non_finite for refusals in window.refused] == [45, 71]
    assert window.warnings[:2] == (
        'input: 45 samples refused in this window (non-finite 45)',
        'output: 71 samples refused in this window (non-finite 71)')
    assert window.missing == (45, 71)
    assert 'input: 45 of 500 instants without a sample of their own' in window.warnings[2]
    # The lost outputs are interpolated between their neighbours (a ramp: exactly).
    np.testing.assert_allclose(window.data.y, np.arange(501.0, 1001.0), rtol=0, atol=1e-9)


def test_a_window_with_no_sample_in_its_range_says_so():
    # Just after a reset: a few samples, all newer than the settled end of the window.
    buffer = SampleBuffer(100, max_gap=0.5, reorder_horizon=0.05)
    for k in range(3):
        buffer.add_pair(ns(5.0 + 0.01 * k), 1.0, 2.0)
    with pytest.raises(DataError, match='not enough contiguous data'):
        buffer.window(4.0, 0.01)
