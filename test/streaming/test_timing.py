"""
Lattices fitted to stamps as real publishers produce them, and the grid planned from them.

Stamps are made here: a publisher period (10 ms unless said), a phase within the period, uniform
jitter, dropped messages and a publisher clock running fast or slow; the tolerances follow from
those (a line fitted to thousands of stamps places its instants to well below a microsecond).
"""

from ctid_ros.streaming.timing import assign_instants, fit_lattice, plan_grid, stream_lattice
import numpy as np
import pytest

NS = 1_000_000_000
TS = 10_000_000
T0 = 1_700_000_000 * NS


def stamped(count, phase=0.0, jitter=0.0, drops=0.0, drift=0.0, period=TS, offset=0.0,
            seed=0):
    """Return the stamps and lattice indices of a periodic publisher (offset in periods)."""
    rng = np.random.default_rng(seed)
    index = np.arange(count)
    times = (index + phase + offset) * period * (1 + drift) + \
        rng.uniform(-jitter, jitter, count) * period
    kept = rng.uniform(size=count) >= drops
    return T0 + np.round(times[kept]).astype(np.int64), index[kept]


@pytest.mark.parametrize('phase', [0.0, 0.13, 0.37, 0.61, 0.89])
@pytest.mark.parametrize('drift', [0.0, 1e-3, -5e-4])
def test_lattice_of_a_jittered_lossy_drifting_publisher(phase, drift):
    stamps, index = stamped(3000, phase, jitter=0.005, drops=0.1, drift=drift, seed=7)
    lattice = stream_lattice(stamps)
    assert lattice is not None and lattice.periodic
    assert lattice.period == pytest.approx(TS * (1 + drift), rel=2e-6)
    # The fitted instant of every sample is its true instant to 0.05 % of the period.
    fitted, offsets = lattice.offsets(stamps)
    true = T0 + (index + phase) * TS * (1 + drift)
    instants = lattice.reference + lattice.origin + fitted * lattice.period
    assert np.max(np.abs(instants - true)) < 5e-4 * TS
    assert np.all(np.diff(fitted) == np.diff(index))
    # The jitter is the normal-consistent median absolute deviation: for jitter uniform in
    # +-0.5 % that is 1.4826 * 0.25 % (the standard deviation is 0.29 %).
    assert lattice.jitter == pytest.approx(1.4826 * 0.0025 * TS, rel=0.1)
    assert lattice.inliers == 1.0 and np.max(np.abs(offsets)) < 0.0051 * TS


def test_lattice_with_most_messages_dropped_and_a_few_stray_stamps():
    stamps, _ = stamped(4000, 0.42, jitter=0.002, drops=0.6, seed=3)
    stray = stamps[::50] + TS // 2
    lattice = stream_lattice(np.sort(np.concatenate([stamps, stray])))
    assert lattice is not None and lattice.period == pytest.approx(TS, rel=1e-5)
    assert 0.95 < lattice.inliers < 0.99


@pytest.mark.parametrize('seed', range(20))
@pytest.mark.parametrize('count', [16, 40, 200])
def test_scattered_stamps_follow_no_lattice(seed, count):
    rng = np.random.default_rng(seed)
    # Events at random intervals (a command published when it changes, a bursty source).
    intervals = [rng.uniform(0.2, 0.6, count), rng.exponential(0.01, count) + 1e-5,
                 rng.choice([0.003, 0.011, 0.017], count) + rng.uniform(0, 2e-3, count)]
    for steps in intervals:
        stamps = T0 + np.round(np.cumsum(steps) * NS).astype(np.int64)
        assert stream_lattice(stamps) is None


def test_too_few_stamps_or_a_degenerate_start_give_no_lattice():
    stamps, _ = stamped(15)
    assert stream_lattice(stamps) is None
    assert fit_lattice(stamps, 0.0) is None
    assert stream_lattice(np.full(40, T0)) is None


def plan(input_stamps, output_stamps, sample_time=TS, values=None):
    if values is None:
        values = np.sin(np.arange(input_stamps.size) / 5.0)
    return plan_grid(input_stamps, values, output_stamps, sample_time, ('u', 'y'))


@pytest.mark.parametrize('phase', [0.0, 0.13, 0.37, 0.61, 0.89])
def test_grid_on_the_input_instants_and_the_output_skew(phase):
    u, _ = stamped(2000, phase, jitter=0.005, seed=1)
    y, _ = stamped(2000, phase + 0.03, jitter=0.005, seed=2)
    grid = plan(u, y)
    assert grid.follows_input and grid.warnings == ()
    assert grid.step == pytest.approx(TS, rel=1e-5)
    assert grid.skew == pytest.approx(0.03 * TS, abs=2e-4 * TS)
    assert grid.output_period == pytest.approx(TS, rel=1e-5)
    # The grid instants are the input's: whole periods from the phase.
    instants = grid.instants(-5, 10)
    assert np.max(np.abs(np.remainder(instants - T0 - phase * TS + TS / 2, TS) - TS / 2)) < \
        2e-4 * TS


def test_output_read_before_the_input_of_the_same_cycle():
    u, _ = stamped(2000, 0.2, jitter=0.005, seed=1)
    y, _ = stamped(2000, 0.2 - 0.04, jitter=0.005, seed=2)
    assert plan(u, y).skew == pytest.approx(0.96 * TS, abs=2e-4 * TS)


def test_one_message_for_both_streams_has_no_skew():
    u, _ = stamped(2000, 0.3, jitter=0.005, seed=1)
    grid = plan(u, u.copy())
    assert grid.skew == 0.0 and grid.output_period is not None


def test_a_command_held_two_periods_published_every_period():
    # Published every 5 ms, changing only on the instants 2 ms + 10 ms * n: sample_time 10 ms.
    u, index = stamped(4000, 0.4, jitter=0.005, period=TS // 2, seed=4)
    values = np.repeat(np.sign(np.sin(np.arange(2000) / 3.0)), 2)[index]
    grid = plan(u, u.copy(), values=values)
    assert grid.step == pytest.approx(TS, rel=1e-5) and grid.warnings == ()
    changes = np.flatnonzero(np.diff(values)) + 1
    offsets = np.remainder(u[changes] - grid.instants(0, 1)[0] + TS // 4, TS) - TS // 4
    assert np.max(np.abs(offsets)) < 0.01 * TS
    # Changing on every instant: the grid cannot hold them all, and says so.
    grid = plan(u, u.copy(), values=np.sign(np.sin(index * 1.7)))
    assert grid.step == pytest.approx(TS, rel=1e-5)
    assert 'changes between the grid instants' in grid.warnings[0]


def test_sample_time_finer_than_the_data_uses_the_data_rate():
    u, _ = stamped(1000, 0.25, jitter=0.005, seed=1)
    y, _ = stamped(1000, 0.28, jitter=0.005, seed=2)
    grid = plan(u, y, sample_time=TS // 4)
    assert grid.step == pytest.approx(TS, rel=1e-5)
    assert grid.skew == pytest.approx(0.03 * TS, abs=2e-4 * TS)
    assert len(grid.warnings) == 1 and "finer than the data's own rate" in grid.warnings[0]


def test_a_faster_output_keeps_a_finer_grid():
    # Input every 10 ms, output every 5 ms, sample_time 5 ms: every instant is measured.
    u, _ = stamped(1000, 0.25, jitter=0.005, seed=1)
    y, _ = stamped(2000, 0.5, jitter=0.005, period=TS // 2, seed=2)
    grid = plan(u, y, sample_time=TS // 2)
    assert grid.step == pytest.approx(TS / 2, rel=1e-5) and grid.warnings == ()
    assert grid.skew == 0.0 and grid.output_period == pytest.approx(TS / 2, rel=1e-5)
    # A faster input than output on a grid as fine as the input: interpolated, and said so.
    u, _ = stamped(4000, 0.25, jitter=0.005, period=TS // 4, seed=1)
    y, _ = stamped(1000, 0.3, jitter=0.005, seed=2)
    grid = plan(u, y, sample_time=TS // 4)
    assert grid.step == pytest.approx(TS / 4, rel=1e-5) and grid.output_period is None
    assert 'standard deviations are too small' in grid.warnings[0]


def test_absolute_grid_without_a_periodic_input_or_with_an_odd_sample_time():
    rng = np.random.default_rng(0)
    u = T0 + np.round(np.cumsum(rng.uniform(0.2, 0.6, 40)) * NS).astype(np.int64)
    y, _ = stamped(2000, 0.3, jitter=0.005, seed=2)
    grid = plan(u, y)
    assert not grid.follows_input and grid.origin == 0.0 and grid.reference % TS == 0
    assert 'is not periodic' in grid.warnings[0]
    # The output is still taken at its own samples, 3 ms after the multiples of 10 ms.
    assert grid.skew == pytest.approx(0.3 * TS, abs=2e-4 * TS)
    u, _ = stamped(2000, 0.3, jitter=0.005, seed=1)
    grid = plan(u, y, sample_time=7_000_000)
    assert not grid.follows_input and 'no whole multiple or fraction' in grid.warnings[0]
    assert grid.output_period is None and 'interpolated' in grid.description


def test_an_irregular_output_is_interpolated():
    u, _ = stamped(2000, 0.3, jitter=0.005, seed=1)
    y, _ = stamped(2000, 0.3, jitter=0.2, seed=2)
    grid = plan(u, y)
    assert grid.output_period is None and grid.skew == 0.0
    assert grid.description.endswith('y interpolated (not periodic)')


def test_bursts_of_late_messages_take_the_free_instants_before_them():
    # Instants 0..9: 2 and 3 published late together with 4; 7 lost; two messages near 9.
    positions = np.array([0.02, 1.01, 3.9, 3.95, 4.0, 5.1, 6.0, 8.0, 8.9, 9.0])
    index, assigned = assign_instants(positions)
    assert index[assigned].tolist() == [0, 1, 2, 3, 4, 5, 6, 8, 9]
    # The earlier of the two near 9 finds 8 taken: it is the one left out.
    assert assigned.tolist() == [True] * 8 + [False, True]
    index, assigned = assign_instants(np.array([]))
    assert index.size == 0 and assigned.size == 0


def late_timer(count, phase, seed, period=TS):
    """
    Return the stamps and instants of a publisher whose timer often fires late.

    Its timer is due every period; a fifth of the times it fires 0.3 to 4 periods late, else
    within 5 %, never before the time it fired last. Each time it sends every sample that
    came due, stamped when sent (DDS source times, 10 us apart).
    """
    rng = np.random.default_rng(seed)
    instants = (np.arange(count) + phase) * period
    lateness = np.where(rng.uniform(size=count) < 0.2, rng.uniform(0.3, 4.0, count),
                        rng.uniform(0, 0.05, count)) * period
    stamps, sent, fired = [], 0, 0.0
    for due, late in zip(instants, lateness):
        fired = max(fired, due + late)
        while sent < count and instants[sent] <= fired:
            stamps.append(fired)
            sent += 1
    stamps = np.array(stamps)
    # Messages of one firing 10 us apart.
    first = np.concatenate(([True], np.diff(stamps) > 0))
    burst = np.cumsum(first) - 1
    position = np.arange(count) - np.flatnonzero(first)[burst]
    stamps = stamps + 10_000 * position
    return T0 + np.round(stamps).astype(np.int64), T0 + np.round(instants).astype(np.int64)


@pytest.mark.parametrize('phase', [0.13, 0.61])
def test_lattice_of_a_publisher_whose_timer_fires_late(phase):
    stamps, instants = late_timer(3000, phase, seed=round(100 * phase))
    assert np.all(np.diff(stamps) > 0)
    lattice = stream_lattice(stamps)
    assert lattice is not None and lattice.periodic and lattice.late > 0.2
    assert lattice.period == pytest.approx(TS, rel=1e-5)
    index, offsets = lattice.offsets(stamps)
    true = np.round((instants - lattice.reference - lattice.origin) / lattice.period)
    # Nearly every sample gets its own instant back (a few of two on one are left out).
    assert np.mean(index == true) > 0.97
    assert np.all(offsets[index == true] > -0.1 * TS)
