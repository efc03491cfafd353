"""Tests of ctid_ros.files.csv_file: CSV records with a header line, plain or gzip."""

import gzip
import os
import threading

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
    (['u', 'y'], [(0, 1), (1, 2)], {},
     r"no 't' or '__time' column: give the sample time \(--ts\)"),
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


GOOD = b't,u,y\n' + b''.join(b'%g,%d,%d\n' % (0.1 * k, k % 3, k % 5) for k in range(20))


@pytest.mark.parametrize('name, content, message', [
    ('latin1.csv', b't,u,y\n0,1,\xe92\n', 'not UTF-8 text: byte 0xe9 on line 2; save it as UTF-8'),
    ('nul.csv', GOOD[:30] + b'\x00' + GOOD[30:], 'binary, not CSV text .a NUL byte on line'),
    ('field.csv', b't,u,y\n0,"' + b'1' * 140_000 + b'",1\n', 'line 2: field larger than'),
    ('line.csv', b't,u,y\n' + b'1' * (1 << 20) + b'\n', 'line 2 is longer than the limit'),
    ('cell.csv', GOOD + b'2.0,1,x\n', r"line 22: column 'y' has a missing or non-numeric cell"),
    ('short.csv', GOOD + b'2.0,1\n', r"line 22: column 'y' .* \(nothing\)"),
    ('blank.csv', b't,u,y\n' + b'\n' * 10_001 + b'0,1,2\n', 'more than 10000 blank lines'),
    ('header.csv', b'\n\n', 'needs a header line'),
    ('trunc.csv.gz', gzip.compress(GOOD)[:80], 'truncated or damaged gzip file'),
    ('damaged.csv.gz', gzip.compress(GOOD)[:12] + b'\xff' * 40 + gzip.compress(GOOD)[52:],
     'truncated or damaged gzip file'),
    ('plain.csv.gz', GOOD, 'named .gz but is not gzip-compressed'),
    ('run.csv.xz', b'\xfd7zXZ\x00' + GOOD, 'xz-compressed, not a CSV file'),
    ('run.csv', b'\x89MCAP0\r\n' + GOOD, 'an MCAP file .use ctid replay.'),
])
def test_broken_files_raise_data_errors_naming_the_file(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(DataError, match=message) as error:
        load_csv(path, ts=0.1)
    assert name in str(error.value) and len(str(error.value)) < 400
    assert path.read_bytes() == content


def test_byte_order_mark_and_gzip_by_content(tmp_path):
    bom = tmp_path / 'excel.csv'
    bom.write_bytes(b'\xef\xbb\xbf' + GOOD)
    data = load_csv(bom)
    assert data.ts == pytest.approx(0.1) and len(data) == 20
    unnamed = tmp_path / 'compressed.csv'
    unnamed.write_bytes(gzip.compress(b'\xef\xbb\xbf' + GOOD))
    np.testing.assert_array_equal(load_csv(unnamed).y, data.y)


def test_non_regular_and_large_files_are_refused_before_reading(tmp_path):
    with pytest.raises(DataError, match='/dev/zero is not a regular file'):
        load_csv('/dev/zero')
    with pytest.raises(DataError, match='is a directory'):
        load_csv(tmp_path)
    large = tmp_path / 'large.csv'
    with open(large, 'wb') as stream:
        stream.truncate(300 << 20)                  # sparse: nothing is written
    with pytest.raises(DataError, match='large.csv is 300 MiB, more than the limit of 256 MiB'):
        load_csv(large)


def test_limits_on_decompressed_size_and_rows(tmp_path, monkeypatch):
    from ctid_ros.files import csv_file

    path = tmp_path / 'bomb.csv.gz'
    path.write_bytes(gzip.compress(GOOD + b'0,0,0\n' * 100_000))
    monkeypatch.setattr(csv_file, 'MAX_CSV_BYTES', 10_000)
    with pytest.raises(DataError, match=r'more than the limit of 9.77 KiB \(decompressed\)'):
        load_csv(path)
    monkeypatch.setattr(csv_file, 'MAX_CSV_BYTES', 1 << 30)
    monkeypatch.setattr(csv_file, 'MAX_SAMPLES', 1000)
    with pytest.raises(DataError, match='more than 1000 rows, the record limit'):
        load_csv(path)


def test_a_pipe_is_read(tmp_path):
    fifo = tmp_path / 'pipe.csv'
    os.mkfifo(fifo)
    writer = threading.Thread(target=fifo.write_bytes, args=(GOOD,))
    writer.start()
    try:
        assert len(load_csv(fifo)) == 20
    finally:
        writer.join()


@pytest.mark.parametrize('kwargs, message', [
    ({'ts': '0.1'}, 'sample time must be a positive number'),
    ({'ts': 0.0}, 'sample time must be a positive number'),
    ({'ts': float('nan')}, 'sample time must be a positive number'),
    ({'input_column': ()}, 'input columns must be one or more names'),
    ({'input_column': ['u', 3]}, 'input columns must be one or more names'),
])
def test_bad_arguments(tmp_path, kwargs, message):
    path = tmp_path / 'data.csv'
    path.write_bytes(GOOD)
    with pytest.raises(DataError, match=message):
        load_csv(path, **kwargs)


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
