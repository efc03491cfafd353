"""
``ctid fit`` end to end on a CSV written here from a plant with known parameters.

A first order plus a fractional dead time, PRBS input, 10 ms samples, output noise of 1 % of
its standard deviation (40 dB SNR, seeded): over 20 s the standard deviations of the estimates
are well below 1 %, so 3 % is several of them, while a wrong sample time, column or dead time
misses by far more.
"""

import json

from ctid_ros import Model
from ctid_ros.cli.main import main
from ctid_ros.core.excitation import prbs
import numpy as np
import pytest

MODEL = 'K*exp(-tau*s)/(T*s + 1)'
TRUTH = {'K': 2.0, 'T': 1.5, 'tau': 0.237}
TS = 0.01


def write_record(path, u, seed):
    """Write t,u,y of the plant driven by ``u`` from rest, with seeded noise, to ``path``."""
    y = Model(MODEL).simulate(TRUTH, u, TS)
    y = y + 0.01 * np.std(y) * np.random.default_rng(seed).standard_normal(y.size)
    rows = '\n'.join(f'{k * TS:.2f},{u_k!r},{y_k!r}'
                     for k, (u_k, y_k) in enumerate(zip(u.tolist(), y.tolist())))
    path.write_text('t,u,y\n' + rows + '\n')
    return path


@pytest.fixture(scope='module')
def record(tmp_path_factory):
    """Return a CSV of 20 s for the estimate."""
    return write_record(tmp_path_factory.mktemp('fit') / 'record.csv', prbs(10, 20)[:2000], 0)


@pytest.fixture(scope='module')
def validation(tmp_path_factory):
    """Return a CSV of 10 s from another input and other noise."""
    u = -prbs(9, 15)[:1000]
    return write_record(tmp_path_factory.mktemp('fit') / 'validation.csv', u, 1)


def fit(capsys, *arguments):
    code = main(['fit', *map(str, arguments)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_json_estimates_within_tolerance_of_the_truth(record, validation, capsys):
    code, out, err = fit(capsys, record, '--model', MODEL, '--initial', 'K=1,T=2',
                         '--bounds', 'T=0.001:,tau=0:1', '--json', '--validate', validation)
    assert code == 0, err
    result = json.loads(out)
    assert {'params', 'std', 'fit', 'converged', 'iterations', 'cost', 'stop_reason',
            'warnings', 'validation_fit'} <= set(result)
    assert result['params'] == pytest.approx(TRUTH, rel=0.03)
    assert all(0 < result['std'][name] < 0.01 * value for name, value in TRUTH.items())
    assert result['converged'] and result['fit'] > 95.0 and result['validation_fit'] > 95.0


def test_table(record, capsys):
    code, out, err = fit(capsys, record, '--model', MODEL)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].split() == ['parameter', 'estimate', 'std', '95%', 'interval']
    rows = {line.split()[0]: float(line.split()[1]) for line in lines[1:4]}
    assert rows == pytest.approx(TRUTH, rel=0.03)       # automatic start
    assert 'converged yes' in out


@pytest.mark.parametrize('arguments, message', [
    (['--model', MODEL, '--output', 'speed'], "has no column 'speed'; its columns are t, u, y"),
    (['--model', MODEL, '--estimate-range', '1:5000'], 'range 1:5000 exceeds the 2000 samples'),
    (['--model', MODEL, '--ts', '0.02'], '--ts 0.02 contradicts the time column'),
])
def test_user_errors_exit_2_with_one_line(record, capsys, arguments, message):
    code, out, err = fit(capsys, record, *arguments)
    assert code == 2 and out == ''
    assert err.startswith('ctid fit: error: ') and message in err
    assert err.count('\n') == 1, err


def test_model_error_points_at_the_column(record, capsys):
    code, out, err = fit(capsys, record, '--model', 'K*exp(-tau*s)/(T*s + 1')
    assert code == 2 and out == ''
    assert err.splitlines() == ["ctid fit: error: expected ')' but found end of expression at "
                                'column 23', '  K*exp(-tau*s)/(T*s + 1', ' ' * 24 + '^']


def test_a_jittered_time_column_is_resampled_as_the_node_does(record, tmp_path, capsys):
    rows = record.read_text().splitlines()
    rng = np.random.default_rng(3)
    # The same samples, stamped 3.7 ms after the hundredths with jitter up to 0.5 % of TS.
    jittered = [rows[0]] + [
        f'{float(t) + 0.0037 + rng.uniform(-0.005, 0.005) * TS!r},{rest}'
        for t, rest in (row.split(',', 1) for row in rows[1:])]
    path = tmp_path / 'jittered.csv'
    path.write_text('\n'.join(jittered) + '\n')
    arguments = ['--model', MODEL, '--initial', 'K=1,T=2', '--bounds', 'T=0.001:,tau=0:1',
                 '--json']
    code, out, err = fit(capsys, path, *arguments)
    assert code == 0, err
    result = json.loads(out)
    assert result['warnings'][0].startswith(f"{path} column 't' jitters")
    # The data are the rows themselves: the estimate is the one of the uniform file.
    code, out, err = fit(capsys, record, *arguments)
    uniform = json.loads(out)
    assert result['params'] == pytest.approx(uniform['params'], rel=1e-4)
    assert result['std'] == pytest.approx(uniform['std'], rel=1e-3)
