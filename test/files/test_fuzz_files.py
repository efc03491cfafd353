"""
Fuzzing the file readers with hostile and broken files (seeded, a few seconds).

Params files (``load_params_file``), CSV files (``load_csv``) and bags (``BagReader``: rosbag2
directories and standalone MCAP files) from :mod:`hostile_corpus` plus seeded random mutations
of valid files: truncated, zero bytes, random bytes, a wrong schema, a metadata.yaml that
disagrees with the storage, resource bombs. Each must give a
:class:`~ctid_ros.errors.CtidError` with a short message, or a correct result, within a time
limit, and leave every input file as it was (sha256).
"""

import random
import time

from ctid_ros.errors import bounded_repr, CtidError
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.csv_file import load_csv
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.params_file import load_params_file
import hostile_corpus
import numpy as np
import pytest
from replay_fixtures import DELAY, float_records, params_file, simulate, write_bag

# Seconds one hostile file may take (the benchmark holds them to 1 s on a quiet machine; this
# leaves room for a loaded CI).
TIME_LIMIT = 5.0
TOPICS = ['/plant/u', '/plant/y']


@pytest.fixture(scope='module')
def good(tmp_path_factory):
    """Write valid files: params, CSV, a rosbag2 directory (sqlite3) and a standalone MCAP."""
    root = tmp_path_factory.mktemp('good')
    u, y = simulate(DELAY, 4.0)
    records = float_records(u, y)
    csv = root / 'data.csv'
    rows = zip(u.tolist(), y.tolist())
    csv.write_text('t,u,y\n' + ''.join(f'{0.01 * k:.2f},{u_k!r},{y_k!r}\n'
                                       for k, (u_k, y_k) in enumerate(rows)))
    bag = root / 'bag'
    bag.mkdir()
    return {'params': params_file(root, DELAY), 'csv': csv,
            'bag': write_bag(bag, records, 'sqlite3'),
            'mcap': write_bag(root, records, 'mcap-file')}


def outcome(call, what):
    """Run ``call`` within the time limit: a CtidError with a message, or its result."""
    started = time.perf_counter()
    try:
        result = call()
    except CtidError as error:
        message = str(error)
        assert message and len(message) < 2500, (what, message[:300])
        result = None
    except Exception as error:          # anything else is a bug: report the file
        pytest.fail(f'{what}: {type(error).__name__}: {bounded_repr(str(error), 300)}')
    elapsed = time.perf_counter() - started
    assert elapsed < TIME_LIMIT, f'{what} took {elapsed:.1f} s'
    return result


def mutations(content, rng, count):
    """Yield ``count`` seeded mutations of ``content``: cuts, flips, insertions, zeroing."""
    for index in range(count):
        data = bytearray(content)
        kind = index % 5
        position = rng.randrange(len(data))
        if kind == 0:
            data = data[:position]
        elif kind == 1:
            for _ in range(rng.randrange(1, 8)):
                data[rng.randrange(len(data))] = rng.getrandbits(8)
        elif kind == 2:
            data[position:position] = bytes(rng.getrandbits(8) for _ in range(rng.randrange(64)))
        elif kind == 3:
            end = min(len(data), position + rng.randrange(1, 512))
            data[position:end] = bytes(end - position)
        else:
            data[position:position] = rng.choice([b'\x00', b'\xff\xfe', b'&a [*a]', b'[' * 200,
                                                  b'"', b'\n' * 30, b'\xef\xbb\xbf', b'{{{'])
        yield bytes(data)


def test_params_files(good, tmp_path):
    rng = random.Random(161)
    cases = hostile_corpus.params_cases(tmp_path, good['params'].read_bytes(), rng)
    cases.update(hostile_corpus.devices())
    cases['directory'] = tmp_path
    cases['missing'] = tmp_path / 'missing.yaml'
    for index, content in enumerate(mutations(good['params'].read_bytes(), rng, 60)):
        cases[f'mutation {index}'] = tmp_path / f'mutation_{index}.yaml'
        cases[f'mutation {index}'].write_bytes(content)
    before = hostile_corpus.snapshot([tmp_path])
    loaded = 0
    for name, path in cases.items():
        config = outcome(lambda: load_params_file(path), f'params file {name!r}')
        if config is not None:
            loaded += 1
            assert isinstance(config, IdentificationConfig)
    assert loaded >= 3                   # BOM, harmless mutations
    assert hostile_corpus.snapshot([tmp_path]) == before


def test_csv_files(good, tmp_path):
    rng = random.Random(162)
    content = good['csv'].read_bytes()
    cases = hostile_corpus.csv_cases(tmp_path, content, rng)
    cases.update(hostile_corpus.devices())
    cases['directory'] = tmp_path
    for index, mutated in enumerate(mutations(content, rng, 60)):
        cases[f'mutation {index}'] = tmp_path / f'mutation_{index}.csv'
        cases[f'mutation {index}'].write_bytes(mutated)
    before = hostile_corpus.snapshot([tmp_path])
    loaded = 0
    for name, path in cases.items():
        data = outcome(lambda: load_csv(path), f'CSV file {name!r}')
        if data is not None:
            loaded += 1
            assert np.all(np.isfinite(data.u)) and np.all(np.isfinite(data.y)), name
            assert data.ts > 0 and len(data) >= 2, name
    assert loaded >= 3                   # BOM, harmless mutations
    assert hostile_corpus.snapshot([tmp_path]) == before


def read_bag(path):
    """Open a bag and decode every message of the plant topics (what ctid replay needs)."""
    with BagReader(path) as bag:
        topics = [name for name in (bag.topic_name(topic) for topic in TOPICS) if name]
        if not topics:
            return 0, bag.warnings
        return sum(1 for _ in bag.messages(topics)), bag.warnings


def test_bags(good, tmp_path):
    rng = random.Random(163)
    cases = hostile_corpus.bag_cases(tmp_path, good['bag'], good['mcap'], rng)
    cases.update(hostile_corpus.devices())
    for index, mutated in enumerate(mutations(good['mcap'].read_bytes(), rng, 40)):
        cases[f'mcap mutation {index}'] = tmp_path / f'mutation_{index}.mcap'
        cases[f'mcap mutation {index}'].write_bytes(mutated)
    before = hostile_corpus.snapshot([tmp_path, good['bag'], good['mcap']])
    read = 0
    for name, path in cases.items():
        result = outcome(lambda: read_bag(path), f'bag {name!r}')
        if result is not None:
            count, warnings = result
            # Whatever was readable: never more than was recorded, and a shortfall is explained.
            assert count <= 800, name
            if count < 800:
                assert warnings or count == 0, name
            read += 1
    assert read >= 10
    assert hostile_corpus.snapshot([tmp_path, good['bag'], good['mcap']]) == before
