"""Validation of sampled input/output data."""

from ctid_ros import CtidError, Data, DataError
import numpy as np
import pytest


def test_valid_data():
    rng = np.random.default_rng(0)
    u = rng.standard_normal(100)
    y = rng.standard_normal(100)
    data = Data(u, y, 0.01, t0=2.0)
    assert len(data) == 100
    assert data.ts == 0.01 and isinstance(data.ts, float)
    assert data.u.dtype == np.float64 and data.y.dtype == np.float64
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)
    np.testing.assert_allclose(data.time, 2.0 + 0.01 * np.arange(100), rtol=1e-15)
    # Lists, integers and numpy scalars are accepted and converted.
    data = Data([1, 2, 3], (4, 5, 6), np.float32(0.5), t0=np.int64(1))
    np.testing.assert_array_equal(data.y, [4.0, 5.0, 6.0])
    assert data.ts == 0.5 and data.t0 == 1.0
    assert Data([1.0], [2.0], 1).ts == 1.0


@pytest.mark.parametrize('u,y,ts,fragment', [
    (np.ones(10), np.ones(11), 0.1, 'same length'),
    (np.ones(0), np.ones(0), 0.1, 'empty'),
    ([], [], 0.1, 'empty'),
    (np.ones(10), np.r_[np.ones(9), np.nan], 0.1, 'non-finite'),
    (np.r_[np.inf, np.ones(9)], np.ones(10), 0.1, 'non-finite'),
    (np.ones(10), np.r_[np.ones(5), -np.inf, np.ones(4)], 0.1, 'first at sample 5'),
    (np.ones(10), np.ones(10), 0.0, 'positive'),
    (np.ones(10), np.ones(10), -0.1, 'positive'),
    (np.ones(10), np.ones(10), np.nan, 'positive'),
    (np.ones(10), np.ones(10), np.inf, 'positive'),
    (np.ones(10), np.ones(10), None, 'number'),
    (np.ones(10), np.ones(10), '0.1', 'number'),
    (np.ones(10), np.ones(10), True, 'number'),
    (np.ones(10), np.ones(10), np.array([0.1]), 'number'),
    (np.ones(10), np.ones(10), 0.1 + 0.1j, 'number'),
    (np.ones((10, 1, 2)), np.ones(10), 0.1, '1-D'),
    (np.ones(10), np.ones((2, 5)), 0.1, '1-D'),
    (1.0, 1.0, 0.1, '1-D'),
    (['a', 'b'], [1.0, 2.0], 0.1, 'numeric'),
    (['1.0', '2.0'], [1.0, 2.0], 0.1, 'numeric'),
    (np.array([1 + 1j, 2.0]), [1.0, 2.0], 0.1, 'numeric'),
    ([1.0, None], [1.0, 2.0], 0.1, 'non-finite'),          # None reads as NaN
    ([[1.0], [2.0, 3.0]], [1.0, 2.0], 0.1, 'numeric'),
])
def test_invalid_data_is_rejected(u, y, ts, fragment):
    with pytest.raises(DataError, match=fragment):
        Data(u, y, ts)


@pytest.mark.parametrize('t0', [np.nan, np.inf, None, 'abc', '1.0'])
def test_invalid_start_time_is_rejected(t0):
    with pytest.raises(DataError, match='t0'):
        Data(np.ones(3), np.ones(3), 0.1, t0=t0)


def test_data_errors_are_ctid_errors():
    with pytest.raises(CtidError):
        Data([1.0, 2.0], [1.0], 0.1)
    assert issubclass(DataError, ValueError)


def test_data_does_not_alias_the_callers_arrays():
    u, y = np.ones(5), np.zeros(5)
    data = Data(u, y, 0.1)
    u[2] = np.nan
    y[0] = 7.0
    assert np.all(np.isfinite(data.u))
    assert data.y[0] == 0.0


def test_data_is_frozen():
    data = Data(np.ones(5), np.ones(5), 0.1)
    with pytest.raises(AttributeError):
        data.ts = 0.2


def test_segment_keeps_times():
    data = Data(np.arange(10.0), 2.0 * np.arange(10.0), 0.5, t0=100.0)
    part = data.segment(2, 5)
    np.testing.assert_array_equal(part.u, [2.0, 3.0, 4.0])
    np.testing.assert_array_equal(part.y, [4.0, 6.0, 8.0])
    assert part.t0 == 101.0 and part.ts == 0.5
    np.testing.assert_array_equal(part.time, [101.0, 101.5, 102.0])
    tail = data.segment(-3)
    np.testing.assert_array_equal(tail.u, [7.0, 8.0, 9.0])
    np.testing.assert_array_equal(tail.time, data.time[-3:])
    np.testing.assert_array_equal(data.segment(-4, -2).time, data.time[-4:-2])
    with pytest.raises(DataError, match='empty'):
        data.segment(5, 5)


def test_detrend_removes_the_operating_point():
    data = Data(np.column_stack([np.arange(4.0), np.ones(4)]), np.array([1.0, 2.0, 3.0, 6.0]),
                0.1)
    np.testing.assert_allclose(data.detrend('mean').y, [-2.0, -1.0, 0.0, 3.0])
    np.testing.assert_allclose(data.detrend('initial').u[:, 0], [0.0, 1.0, 2.0, 3.0])
    with pytest.raises(DataError, match='detrend'):
        data.detrend('linear')


@pytest.mark.parametrize('u,y,ts,t0,fragment', [
    (np.ma.masked_array([1.0, 2.0, 3.0], [0, 1, 0]), np.ones(3), 0.1, 0.0, '1 masked value'),
    (np.ones(3), np.ma.masked_array([1.0, 2.0, 3.0], [1, 1, 0]), 0.1, 0.0, '2 masked value'),
    (np.zeros((3, 0)), np.ones(3), 0.1, 0.0, 'no input columns'),
    ([10 ** 400, 1, 2], np.ones(3), 0.1, 0.0, 'numeric'),
    (np.ones(3), np.ones(3), 10 ** 400, 0.0, 'finite number'),
    (np.ones(3), np.ones(3), 1e308, 0.0, 'overflow'),
    (np.ones(3), np.ones(3), 1e308, 1.7e308, 'overflow'),
])
def test_hostile_arrays_and_times_are_refused(u, y, ts, t0, fragment):
    with pytest.raises(DataError, match=fragment):
        Data(u, y, ts, t0)


def test_segment_indices_must_be_integers():
    data = Data(np.arange(10.0), np.arange(10.0), 0.1)
    assert len(data.segment(np.int64(2), 5)) == 3
    for start, stop in ((1.5, None), ('2', None), (0, 4.0), (True, 3)):
        with pytest.raises(DataError, match='integer sample index'):
            data.segment(start, stop)


def test_output_skew_is_validated_and_kept():
    data = Data(np.arange(10.0), np.arange(10.0), 0.5, t0=1.0, output_skew=0.2)
    assert data.output_skew == 0.2
    assert data.segment(2, 6).output_skew == 0.2
    assert data.detrend('mean').output_skew == 0.2
    assert data.detrend('initial').output_skew == 0.2
    assert Data(np.ones(3), np.ones(3), 0.5).output_skew == 0.0
    for skew in (-0.1, 0.5, 0.7, np.nan, np.inf):
        with pytest.raises(DataError, match='output skew'):
            Data(np.ones(3), np.ones(3), 0.5, output_skew=skew)
    with pytest.raises(DataError, match='output skew'):
        Data(np.ones(3), np.ones(3), 0.5, output_skew='0.1')
