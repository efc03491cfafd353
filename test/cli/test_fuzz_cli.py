"""
``ctid fit`` and ``ctid replay`` end to end with hostile files and options (seeded, ~10 s).

Every run must exit 0, or 2 with one line ``ctid <command>: error: ...`` (argparse: its usage
and one error line), never print a traceback or report an internal error, and leave every
input file as it was (sha256). A few runs go through the installed ``ctid`` executable in a
subprocess, to see exactly what a user sees.
"""

from pathlib import Path
import random
import subprocess
import sys

from ctid_ros.cli.main import main
import hostile_corpus
import pytest
from replay_fixtures import DELAY, float_records, params_file, simulate, write_bag

MODEL = 'K*exp(-tau*s)/(T*s + 1)'
# Bags written by rosbag2 itself (see test/data/README.md).
REAL_BAGS = Path(__file__).resolve().parents[1] / 'data' / 'bags'


@pytest.fixture(scope='module')
def good(tmp_path_factory):
    """Write valid inputs: a 4 s CSV, params, a rosbag2 directory (sqlite3), a standalone MCAP."""
    root = tmp_path_factory.mktemp('good')
    u, y = simulate(DELAY, 4.0)
    rows = zip(u.tolist(), y.tolist())
    csv = root / 'data.csv'
    csv.write_text('t,u,y\n' + ''.join(f'{0.01 * k:.2f},{u_k!r},{y_k!r}\n'
                                       for k, (u_k, y_k) in enumerate(rows)))
    (root / 'bag').mkdir()
    records = float_records(u, y)
    return {'csv': csv, 'params': params_file(root, DELAY),
            'bag': write_bag(root / 'bag', records, 'sqlite3'),
            'mcap': write_bag(root, records, 'mcap-file')}


def run_ctid(capsys, arguments):
    """Run ``ctid`` in this process; return (status, stdout, stderr)."""
    try:
        status = main([str(argument) for argument in arguments])
    except SystemExit as exit_:          # argparse
        status = exit_.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def assert_clean(status, err, arguments):
    """Exit 0, or 2 with a one-line error (argparse: usage plus one line); no traceback."""
    what = ' '.join(map(str, arguments))[:300]
    assert status in (0, 2), f'{what}: exit {status}: {err[-500:]}'
    assert 'Traceback' not in err and 'internal error' not in err, f'{what}: {err[-500:]}'
    if status == 2:
        lines = [line for line in err.splitlines() if not line.startswith('ctid replay: warning')]
        errors = [line for line in lines if ': error: ' in line]
        assert len(errors) == 1, f'{what}: {err[-500:]}'
        if lines[0].startswith('usage:'):
            return
        # One line; a model error adds the model text and a caret under the column.
        assert len(lines) == 1 or (len(lines) == 3 and lines[2].strip() == '^'), f'{what}: {err}'


def test_fit_on_hostile_files(good, tmp_path, capsys):
    rng = random.Random(31)
    cases = hostile_corpus.csv_cases(tmp_path, good['csv'].read_bytes(), rng)
    cases.update(hostile_corpus.devices())
    cases['directory'] = tmp_path
    cases['missing'] = tmp_path / 'missing.csv'
    before = hostile_corpus.snapshot([tmp_path, good['csv']])
    for name, path in cases.items():
        arguments = ['fit', path, '--model', MODEL]
        assert_clean(*run_ctid(capsys, arguments)[::2], arguments)
        arguments = ['fit', good['csv'], '--model', MODEL, '--validate', path]
        assert_clean(*run_ctid(capsys, arguments)[::2], arguments)
    assert hostile_corpus.snapshot([tmp_path, good['csv']]) == before


FIT_OPTIONS = [
    ['--max-iterations', '0'], ['--max-iterations', '-3'], ['--max-iterations', '2.5'],
    ['--max-iterations', 'many'], ['--max-iterations', '1'], ['--initial', 'K=nan'],
    ['--initial', 'K='], ['--initial', '=1'], ['--initial', 'x=1'], ['--initial', 'K=1e999'],
    ['--initial', 'K=1,T=1,tau=0'], ['--bounds', 'T=5:1'], ['--bounds', 'T=a:b'],
    ['--bounds', 'T=:'], ['--bounds', 'tau=:-1'], ['--bounds', 'T=nan:1'], ['--bounds', 'T=1'],
    ['--bounds', 'T=0.01:'], ['--ts', '0'], ['--ts', '-1'], ['--ts', 'nan'], ['--ts', 'inf'],
    ['--ts', 'abc'], ['--ts', '0.02'], ['--estimate-range', '0:5'],
    ['--estimate-range', '5:1'], ['--estimate-range', '1:99999'], ['--estimate-range', 'a:b'],
    ['--estimate-range', '1:5'], ['--validate-range', '1:0'], ['--validate-range', '300:400'],
    ['--detrend', 'bogus'], ['--detrend', 'mean'], ['--method', 'magic'], ['--method', 'gn'],
    ['--intersample', 'cubic'], ['--input', ''], ['--input', 't'], ['--input', 'u,u'],
    ['--output', 'nonexistent'], ['--output', 't'], ['--initial-state', 'random'],
    ['--initial-state', 'estimate'], ['--output-offset'], ['--controller', '1/s'],
    ['--controller', 'x'], ['--model', 'K/(T*s+1'], ['--model', ''], ['--model', 's'],
    ['--model', 'K*exp(-tau*s)/(T*s + 1)'], ['--json'], ['--bogus'],
]


def test_fit_with_hostile_options(good, capsys):
    rng = random.Random(32)
    before = hostile_corpus.snapshot([good['csv']])
    for _ in range(45):
        options = [item for chosen in rng.sample(FIT_OPTIONS, rng.randrange(1, 4))
                   for item in chosen]
        if '--model' not in options:
            options += ['--model', MODEL]
        arguments = ['fit', good['csv'], *options]
        assert_clean(*run_ctid(capsys, arguments)[::2], arguments)
    assert hostile_corpus.snapshot([good['csv']]) == before


def test_replay_on_hostile_bags_and_params(good, tmp_path, capsys):
    rng = random.Random(33)
    (tmp_path / 'bags').mkdir()
    bags = hostile_corpus.bag_cases(tmp_path / 'bags', good['bag'], good['mcap'], rng)
    bags.update(hostile_corpus.devices())
    bags.update({f'rosbag2 {path.name}': path for path in sorted(REAL_BAGS.iterdir())})
    (tmp_path / 'params').mkdir()
    params = hostile_corpus.params_cases(tmp_path / 'params', good['params'].read_bytes(), rng)
    inputs = [tmp_path, good['bag'], good['mcap'], good['params'], REAL_BAGS]
    before = hostile_corpus.snapshot(inputs)
    for name, path in bags.items():
        arguments = ['replay', path, '--params-file', good['params']]
        assert_clean(*run_ctid(capsys, arguments)[::2], arguments)
    for name, path in params.items():
        arguments = ['replay', good['mcap'], '--params-file', path]
        assert_clean(*run_ctid(capsys, arguments)[::2], arguments)
    assert hostile_corpus.snapshot(inputs) == before


def test_replay_with_hostile_options(good, tmp_path, capsys):
    rng = random.Random(34)
    options = [
        ['--start', 'nan'], ['--start', '-1'], ['--start', 'inf'], ['--start', '1e300'],
        ['--start', '3', '--end', '2'], ['--end', '0'], ['--end', '1e-12'], ['--start', '1'],
        ['--node-name', ''], ['--node-name', '/'], ['--node-name', '//x'],
        ['--node-name', 'a b'], ['--node-name', '/other/ctid_node'], ['--sliding'], ['--json'],
        ['--plot', tmp_path / 'missing' / 'fit.png'], ['--plot', 'BAG/fit.png'], ['--plot'],
        ['--plot', tmp_path / 'fit.txt'], ['--plot', good['params']],
        ['--output', tmp_path / 'missing' / 'out.mcap'], ['--output', 'BAG/x.mcap'],
        ['--output', 'BAG'], ['--output', tmp_path / 'out.txt'], ['--bogus'],
    ]
    inputs = [good['bag'], good['mcap'], good['params']]
    before = hostile_corpus.snapshot(inputs)
    for index in range(30):
        bag = rng.choice([good['bag'], good['mcap']])
        chosen = [str(item).replace('BAG', str(bag))
                  for option in rng.sample(options, rng.randrange(1, 3)) for item in option]
        arguments = ['replay', bag, '--params-file', good['params'], *chosen]
        assert_clean(*run_ctid(capsys, arguments)[::2], arguments)
        for created in [*tmp_path.glob('*.mcap'), *good['bag'].parent.glob('*.png'),
                        *good['mcap'].parent.glob('*.png')]:
            created.unlink()
    assert hostile_corpus.snapshot(inputs) == before


@pytest.mark.parametrize('arguments', [
    ['fit', '/dev/zero', '--model', MODEL],
    ['replay', 'BOMB', '--params-file', 'PARAMS'],
])
def test_the_executable_prints_one_line(good, tmp_path, arguments):
    bomb = hostile_corpus.mcap_bombs(tmp_path)['declares 2 GiB']
    arguments = [str(good['params']) if item == 'PARAMS' else str(bomb) if item == 'BOMB'
                 else item for item in arguments]
    completed = subprocess.run([sys.executable, '-m', 'ctid_ros.cli.main', *arguments],
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 2 and completed.stdout == ''
    assert completed.stderr.count('\n') == 1 and ': error: ' in completed.stderr
