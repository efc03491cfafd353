"""Tests of ctid_ros.files.csv_file: CSV records with a header line, plain or gzip."""

import gzip

from ctid_ros.errors import DataError
from ctid_ros.files.csv_file import load_csv, timed_data, uniform_sample_time
import numpy as np
import pytest


def write(path, header, rows):
    text = ','.join(header) + '\n' + ''.join(','.join(map(str, row)) + '\n' for row in rows)
    if path.suffix == '.gz':
        with gzip.open(path, 'wt') as stream:
            stream.write(text)
    else:
        path.write_text(text)
    return path


@pytest.mark.parametrize('name', ['data.csv', 'data.csv.gz'])
def test_time_column_gives_sample_time_and_start(tmp_path, name):
    t = 2.5 + 0.1 * np.arange(20)
    u, y = np.sin(t), np.cos(t)
    path = write(tmp_path / name, ['t', 'u', 'y'], zip(t, u, y))
    data = load_csv(path)
    assert data.ts == pytest.approx(0.1) and data.t0 == pytest.approx(2.5)
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)


def test_named_columns_several_inputs_and_no_time_column(tmp_path):
    rows = [(k, 2 * k, 3 * k, -k) for k in range(10)]
    path = write(tmp_path / 'stage.csv', [' q', 'v ', 'w', 'other'], [
        (q, v, w, o) for v, w, q, o in rows])
    data = load_csv(path, input_column=('v', 'w'), output_column='q', ts=0.001)
    assert data.u.shape == (10, 2) and data.ts == 0.001 and data.t0 == 0.0
    np.testing.assert_array_equal(data.u[:, 1], [row[1] for row in rows])
    np.testing.assert_array_equal(data.y, [row[2] for row in rows])
    # --ts may repeat the time column, within 0.1 %.
    path = write(tmp_path / 'timed.csv', ['t', 'u', 'y'], [(0.01 * k, k, k) for k in range(5)])
    assert load_csv(path, ts=0.010005).ts == pytest.approx(0.01)


@pytest.mark.parametrize('header, rows, kwargs, message', [
    (['t', 'u'], [(0, 1), (1, 2)], {}, r"no column 'y'; its columns are t, u"),
    (['u', 'y'], [(0, 1), (1, 2)], {}, r"no 't' column: give the sample time \(--ts\)"),
    (['t', 'u', 'y'], [(0, 1, 'x'), (1, 2, 3)], {}, "column 'y' has a missing or non-numeric"),
    (['t', 'u', 'y'], [(0, 1, 2), (1, 2)], {}, "column 'y' has a missing or non-numeric"),
    (['t', 'u', 'y'], [(0, 1, 2)], {}, 'a single sample'),
    (['t', 'u', 'y'], [], {}, 'needs a header line and at least one row'),
    (['t', 'u', 'y'], [(0, 1, 2), (1, 1, 2), (3, 1, 2)], {}, 'not uniformly sampled'),
    (['t', 'u', 'y'], [(0, 1, 2), (1, 1, 2), (1, 1, 2)], {}, 'not increasing at row 2'),
    (['t', 'u', 'y'], [(0, 1, 2), (1, 1, 2)], {'ts': 0.5}, '--ts 0.5 contradicts'),
])
def test_errors_say_what_is_wrong(tmp_path, header, rows, kwargs, message):
    with pytest.raises(DataError, match=message):
        load_csv(write(tmp_path / 'bad.csv', header, rows), **kwargs)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match='cannot read .*absent.csv'):
        load_csv(tmp_path / 'absent.csv')


def test_uniform_sample_time_tolerates_jitter_below_a_thousandth():
    t = 0.01 * np.arange(100)
    t[50] += 5e-6
    assert uniform_sample_time(t) == pytest.approx(0.01)
    t[50] += 1e-4
    with pytest.raises(DataError, match='step .* at row 50'):
        uniform_sample_time(t)


def test_a_jittered_time_column_is_resampled_on_its_own_instants():
    rng = np.random.default_rng(5)
    k = np.arange(400)
    # Rows every 10 ms, 3.7 ms after the whole hundredths, stamps jittered by up to 50 us.
    t = 12.0037 + 0.01 * k + rng.uniform(-5e-5, 5e-5, k.size)
    u, y = np.sign(np.sin(k / 7.0)), np.cos(k / 11.0)
    data, notes = timed_data(t, u, y, 'column t')
    # Every row is its own sample: nothing is held over or interpolated between rows.
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)
    assert data.ts == pytest.approx(0.01, rel=1e-5) and data.output_skew == 0.0
    assert data.t0 == pytest.approx(12.0037, abs=1e-5)
    assert notes[0].startswith('column t jitters') and len(notes) == 1
    # A lost row: its input is held (the same value on both sides), its output interpolated.
    lost = np.delete(np.arange(k.size), 200)
    data, notes = timed_data(t[lost], u[lost], y[lost], 'column t')
    assert len(data) == 400 and data.u[200] == u[199] == u[201]
    # Interpolated between the stamps of its neighbours, which jitter by up to 0.5 %.
    assert data.y[200] == pytest.approx((y[199] + y[201]) / 2, abs=2e-4)
    assert 'input: 1 of 400 instants without a sample of their own' in notes[1]
    assert 'output: 1 of 400 instants without a sample of their own' in notes[2]


@pytest.mark.parametrize('time, message', [
    (np.r_[0.0:1.0:0.01, 1.5:2.0:0.01], r'a gap of 0\.51 s at row 100'),
    (np.cumsum(np.random.default_rng(1).uniform(0.005, 0.015, 100)), 'follow no period'),
])
def test_gaps_and_irregular_time_columns_are_refused(time, message):
    with pytest.raises(DataError, match=message):
        timed_data(time, np.ones(time.size), np.ones(time.size), 'column t')


def test_uniform_time_columns_are_taken_as_they_are():
    t = 2.5 + 0.1 * np.arange(20)
    t[7] += 5e-5
    data, notes = timed_data(t, np.sin(t), np.cos(t))
    assert (data.ts, data.t0, notes) == (pytest.approx(0.1), 2.5, ())
