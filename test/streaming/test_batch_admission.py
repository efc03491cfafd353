"""
Whole arrays admitted at once give the buffer that appending one sample at a time gives.

``SampleBuffer.add_inputs``/``add_outputs`` (and so ``resample`` and the columnar replay) store
the samples :meth:`append` would simply store as blocks and hand every other one to it; these
seeded hostile orderings (jitter, reordering within and beyond the horizon, duplicates,
non-finite values, stamps an hour ahead, a stream resuming after a silence, a clock restarted
earlier, zero stamps, slow streams whose steps exceed the horizon, tiny capacities, two inputs
per sample) compare every piece of state and the windows of both.
"""

from ctid_ros.errors import DataError
from ctid_ros.streaming.buffer import SampleBuffer
import numpy as np
import pytest

NS = 1_000_000_000
MS = 1_000_000


def hostile_stream(rng, count, period, trouble=0.45):
    """Return stamps (ns, arrival order) and values of a stream with every kind of trouble."""
    stamps = np.arange(count, dtype=np.int64) * period + 5 * NS
    stamps += rng.integers(-period // 10, period // 10 + 1, size=count)
    values = np.sin(np.arange(count) * 0.1) + rng.normal(0, 0.01, count)
    weights = np.array([0.1, 0.05, 0.05, 0.05, 0.04, 0.04, 0.04, 0.04, 0.04]) / 0.45
    kinds = rng.choice(10, size=count, p=np.concatenate(([1 - trouble], trouble * weights)))
    out_stamps, out_values = [], []
    clock_shift = 0
    for k in range(count):
        stamp, value = int(stamps[k]) + clock_shift, float(values[k])
        kind = kinds[k]
        if kind == 1 and out_stamps:                 # duplicate of a recent stamp
            out_stamps.append(out_stamps[-rng.integers(1, min(5, len(out_stamps)) + 1)])
            out_values.append(42.0)
        elif kind == 2:                              # non-finite
            value = float(rng.choice([np.nan, np.inf, -np.inf]))
        elif kind == 3:                              # late, within or beyond the horizon
            stamp -= int(rng.choice([20 * MS, 60 * MS, 700 * MS, 3 * NS]))
        elif kind == 4:                              # an hour ahead, or zero
            stamp = int(rng.choice([stamp + 3600 * NS, 0]))
        elif kind == 5:                              # a silence: the stream resumes later
            clock_shift += int(rng.choice([80 * MS, 2 * NS]))
            stamp += int(rng.choice([80 * MS, 2 * NS]))
        elif kind == 6 and k > 3:                    # swapped with the previous one
            out_stamps[-1], stamp = stamp, out_stamps[-1]
        elif kind == 7 and rng.random() < 0.2:       # publisher restarted with an earlier clock
            clock_shift -= int(rng.choice([1 * NS, 5 * NS]))
            stamp -= 0
        elif kind == 8:                              # a burst of late messages
            stamp += int(rng.integers(0, 3)) * period
        elif kind == 9:                              # random far stamp
            stamp = int(rng.integers(0, 20 * NS))
        out_stamps.append(stamp)
        out_values.append(value)
    return np.array(out_stamps, dtype=np.int64), np.array(out_values)


def state(stream):
    """Everything a stream holds that can change a window or a count."""
    return (stream.stamps.tolist(), stream.values.tolist(), stream.received, stream.accepted,
            stream.duplicates, stream.late, stream.non_finite, stream.evicted,
            stream.out_of_clock, stream.reanchors, stream.pending,
            [(item[0], np.ravel(item[1]).tolist()) + tuple(item[2:]) for item in stream._run],
            stream._run_forward, [events.tolist() for events in stream.events()])


def buffers(capacity, max_gap, horizon, width=1):
    return [SampleBuffer(capacity, max_gap=max_gap, reorder_horizon=horizon, inputs=width)
            for _ in range(2)]


CASES = [  # (seed, count, period, capacity, max_gap, horizon, trouble)
    (0, 3000, 2 * MS, 100_000, 0.5, 0.05),
    (1, 3000, 10 * MS, 500, 0.5, 0.05),
    (2, 2000, 100 * MS, 100_000, 0.5, 0.05),      # every step beyond the horizon
    (3, 2000, 70 * MS, 40, 0.3, 0.02),
    (4, 2000, 10 * MS, 20, 0.5, 0.05),            # capacity below the 33 stamps of the clock
    (5, 1000, 10 * MS, 2, 0.5, 0.05),             # the smallest buffer
    (6, 3000, 1 * MS, 3000, 0.1, 0.0),            # no reordering allowed at all
    (7, 3000, 25 * MS, 100_000, 2.0, 0.01),
]
# The same with rare trouble: long blocks stored at once between the refusals.
CASES = ([case + (0.45,) for case in CASES] +
         [(10 + case[0],) + case[1:] + (0.03,) for case in CASES])


@pytest.mark.parametrize('seed, count, period, capacity, max_gap, horizon, trouble', CASES)
def test_hostile_streams_admitted_at_once_equal_one_by_one(seed, count, period, capacity,
                                                           max_gap, horizon, trouble):
    rng = np.random.default_rng(seed)
    stamps, values = hostile_stream(rng, count, period, trouble)
    one, batch = buffers(capacity, max_gap, horizon)
    for stamp, value in zip(stamps.tolist(), values.tolist()):
        one.add_output(stamp, value)
    # In pieces of random sizes, as chunks of a bag arrive.
    cuts = np.sort(rng.choice(np.arange(1, count), size=20, replace=False))
    for piece_stamps, piece_values in zip(np.split(stamps, cuts), np.split(values, cuts)):
        batch.add_outputs(piece_stamps, piece_values)
    assert state(batch._output) == state(one._output)
    assert batch.stats() == one.stats()


@pytest.mark.parametrize('seed', range(6))
def test_windows_of_both_agree_on_two_input_rows(seed):
    rng = np.random.default_rng(100 + seed)
    period = int(rng.choice([2 * MS, 10 * MS, 60 * MS]))
    trouble = (0.45, 0.03)[seed % 2]
    u_stamps, u_first = hostile_stream(rng, 1500, period, trouble)
    y_stamps, y_values = hostile_stream(rng, 1500, period, trouble)
    u_values = np.column_stack([u_first, np.cos(np.arange(u_first.size))])
    u_values[rng.choice(u_first.size, 10), 1] = np.nan
    one, batch = buffers(100_000, 0.5, 0.05, width=2)
    for stamp, row in zip(u_stamps.tolist(), u_values):
        one.add_input(stamp, row)
    for stamp, value in zip(y_stamps.tolist(), y_values.tolist()):
        one.add_output(stamp, value)
    batch.add_inputs(u_stamps, u_values)
    batch.add_outputs(y_stamps, y_values)
    assert state(batch._input) == state(one._input)
    assert state(batch._output) == state(one._output)
    try:
        expected = one.window(2.0, period / NS)
    except DataError as error:
        with pytest.raises(DataError) as raised:
            batch.window(2.0, period / NS)
        assert str(raised.value) == str(error)
        return
    window = batch.window(2.0, period / NS)
    np.testing.assert_array_equal(window.data.u, expected.data.u)
    np.testing.assert_array_equal(window.data.y, expected.data.y)
    assert window.warnings == expected.warnings


def test_clean_fast_streams_are_stored_as_blocks_not_one_by_one(monkeypatch):
    stamps = np.arange(200_000, dtype=np.int64) * 2 * MS + 17
    values = np.sin(stamps / NS)
    buffer = SampleBuffer(250_000)
    calls = []
    original = type(buffer._output).append

    def counted(self, stamp, value):
        calls.append(stamp)
        return original(self, stamp, value)

    monkeypatch.setattr(type(buffer._output), 'append', counted)
    buffer.add_outputs(stamps, values)
    # Only the first stamps (too few for the stream's clock yet) are appended one by one.
    assert len(calls) == 33
    np.testing.assert_array_equal(buffer._output.stamps, stamps)


def test_batch_arguments_are_checked():
    buffer = SampleBuffer(10, inputs=2)
    with pytest.raises(DataError, match='integer nanoseconds'):
        buffer.add_inputs([0.5], [[1.0, 2.0]])
    with pytest.raises(DataError, match='needs 2 values'):
        buffer.add_inputs([0], [[1.0, 2.0, 3.0]])
    with pytest.raises(DataError, match='equal length'):
        buffer.add_outputs([0, 1], [1.0])
