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
    # One parameter vector holds over this simulated record (docs/algorithm.md section 18).
    assert result['consistency']['consistent'] is True
    assert {'max_z', 'blocks', 'verdict'} <= set(result['consistency'])
    assert result['std_noise'] == pytest.approx(result['std'])


def test_table(record, capsys):
    code, out, err = fit(capsys, record, '--model', MODEL)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].split() == ['parameter', 'estimate', 'std', '95%', 'interval']
    rows = {line.split()[0]: float(line.split()[1]) for line in lines[1:4]}
    assert rows == pytest.approx(TRUTH, rel=0.03)       # automatic start
    assert any(line.startswith('consistency: consistent over the record') for line in lines)
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


def plotjuggler_export(record, path):
    """
    Rewrite ``record`` as PlotJuggler's CSV exporter writes it.

    ``__time`` in seconds since the epoch, the columns named by topic and field (sorted), and
    after every tenth sample a row of another series only, empty in u and y.
    """
    rows = [row.split(',') for row in record.read_text().splitlines()[1:]]
    lines = ['__time,/cmd/data,/joint_states/position[0],/rosout/level']
    for index, (t, u, y) in enumerate(rows):
        lines.append(f'{1.7e9 + float(t):.6f},{u},{y},')
        if index % 10 == 0:
            lines.append(f'{1.7e9 + float(t) + 0.003:.6f},,,20')
    path.write_text('\n'.join(lines) + '\n')
    return path


def test_plotjuggler_column_names_and_time(record, tmp_path, capsys):
    export = plotjuggler_export(record, tmp_path / 'export.csv')
    code, out, err = fit(capsys, export, '--model', MODEL, '--input', '/cmd/data', '--output',
                         '/joint_states/position[0]', '--json')
    assert code == 0, err
    result = json.loads(out)
    assert result['params'] == pytest.approx(TRUTH, rel=0.03)
    assert result['warnings'][0] == ('200 rows without a value in /cmd/data, '
                                     '/joint_states/position[0] skipped (first on line 3): rows '
                                     'of other series')
    # An equation names its signals: SIGNAL=COLUMN where the column is no identifier.
    code, out, err = fit(capsys, export, '--model', 'T*s*y + y = K*u', '--input', '/cmd/data',
                         '--output', '/joint_states/position[0]')
    assert code == 2 and 'give this one a name: --input u=/cmd/data' in err
    code, out, err = fit(capsys, export, '--model', 'T*s*q + q = K*v', '--input', 'v=/cmd/data',
                         '--output', 'q=/joint_states/position[0]', '--json')
    assert code == 0, err
    assert set(json.loads(out)['params']) == {'T', 'K'}     # no dead time in an equation


def test_columns_sampled_at_different_instants_are_refused(record, tmp_path, capsys):
    lines = record.read_text().splitlines()
    t, u, y = lines[5].split(',')
    lines[5] = f'{t},{u},'
    path = tmp_path / 'gap.csv'
    path.write_text('\n'.join(lines) + '\n')
    code, out, err = fit(capsys, path, '--model', MODEL)
    assert code == 2 and f"{path} line 6: column 'y' is empty where 'u' has a value" in err
    # Without a time column, a skipped row would shift the samples after it.
    lines = ['u,y'] + [row.split(',', 1)[1] for row in record.read_text().splitlines()[1:]]
    lines[3] = ','
    path.write_text('\n'.join(lines) + '\n')
    code, out, err = fit(capsys, path, '--model', MODEL, '--ts', TS)
    assert code == 2 and 'line 4: no value in u, y; without a time column' in err


def test_fixed_parameter_and_delay_range(record, tmp_path, capsys):
    code, out, err = fit(capsys, record, '--model', MODEL, '--fix', 'K=2', '--delay-range',
                         '0.1:0.4', '--json')
    assert code == 0, err
    result = json.loads(out)
    assert list(result['params']) == ['K', 'tau', 'T'] and result['fixed'] == {'K': 2.0}
    assert result['params'] == pytest.approx(TRUTH, rel=0.01)
    assert result['std']['K'] == 0.0 and 0 < result['std']['T'] < 0.01
    code, out, err = fit(capsys, record, '--model', MODEL, '--fix', 'K=2')
    assert code == 0, err
    row = next(line for line in out.splitlines() if line.startswith('K '))
    assert row.split() == ['K', '2', 'fixed']
    for arguments, message in ((['--fix', 'K=2', '--initial', 'K=1'],
                                'K fixed by --fix cannot also be given in --initial'),
                               (['--fix', 'Q=2'], "'Q' is not a parameter"),
                               (['--fix', 'K=2,T=1,tau=0.2'], 'leaves no parameter')):
        code, out, err = fit(capsys, record, '--model', MODEL, *arguments)
        assert code == 2 and message in err, err
    with pytest.raises(SystemExit) as exit_:
        fit(capsys, record, '--model', MODEL, '--delay-range', '0.3:0.1')
    assert exit_.value.code == 2 and 'need 0 <= MIN < MAX' in capsys.readouterr().err


def test_plot_writes_the_fit_bode_and_residual_figures(record, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = fit(capsys, record, '--model', MODEL, '--plot')
    assert code == 0, err
    written = [tmp_path / 'record_fit.png', tmp_path / 'record_fit_bode.png',
               tmp_path / 'record_fit_residual.png']
    assert all(path.stat().st_size > 10_000 for path in written)
    assert err.splitlines() == [f'ctid fit: wrote {path}' for path in written]
    code, out, err = fit(capsys, record, '--model', MODEL, '--plot', tmp_path / 'no' / 'x.png')
    assert code == 2 and out == '' and 'does not exist' in err
