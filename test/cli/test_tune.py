"""``ctid tune``: the acceptance through the command, its files, a bag, its refusals."""

import json

from ctid_ros.cli import arguments
from ctid_ros.cli.main import main
from ctid_ros.core.reference_systems import two_lags_dead_time
from ctid_ros.design import tune as design
from ctid_ros.design.margins import (closed_loop_step, Gains, integral_absolute_error,
                                     loop_margins, Plant)
from ctid_ros.design.tune import reduce, simc
import pytest
from record_fixtures import write_csv
from replay_fixtures import DELAY, float_records, params_file, simulate, write_bag
import yaml

SOPDT = 'K*exp(-tau*s)/((T1*s+1)*(T2*s+1))'


def test_choices_are_the_designs():
    assert arguments.CONTROLLERS == design.CONTROLLERS
    assert arguments.DESIGN_METHODS == design.METHODS


def test_pi_from_ctid_tune_on_the_true_plant(tmp_path, capsys):
    """Acceptance: the PI of ``ctid tune`` applied to the true SOPDT plant."""
    system = two_lags_dead_time()
    csv = write_csv(tmp_path / 'sopdt.csv', system.data(5))
    assert main(['tune', str(csv), '--model', SOPDT, '--controller', 'PI', '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    gains = Gains(summary['gains']['kp'], summary['gains']['ki'])
    true_plant = Plant.from_model(system.model, system.truth)
    on_truth = loop_margins(true_plant, gains)
    assert on_truth.stable and on_truth.ms <= 2.0
    times, output, _ = closed_loop_step(true_plant, gains, 40.0)
    reference = simc(reduce(true_plant, 'PI'), 'PI')
    _, best, _ = closed_loop_step(true_plant, reference, 40.0)
    assert integral_absolute_error(times, output) <= 1.5 * integral_absolute_error(times, best)
    band = summary['margins']['band']
    for name in ('gain_db', 'phase_deg', 'ms'):
        low, high = band[name]
        assert low <= getattr(on_truth, name) <= high, name
    assert summary['method'].startswith('SIMC PI') and summary['estimate']['converged']


def test_params_out_plot_and_no_overwrite(tmp_path, capsys):
    csv = write_csv(tmp_path / 'sopdt.csv', two_lags_dead_time().data(1))
    params, plot = tmp_path / 'pid.yaml', tmp_path / 'step.png'
    assert main(['tune', str(csv), '--model', SOPDT, '--controller', 'PID', '--joint', 'axis',
                 '--params-out', str(params), '--plot', str(plot), '--draws', '40']) == 0
    out = capsys.readouterr().out
    loaded = yaml.safe_load(params.read_text())['pid_controller']['ros__parameters']
    assert set(loaded['gains']['axis']) == {'p', 'i', 'd'} and loaded['gains']['axis']['d'] > 0
    assert f"p: {loaded['gains']['axis']['p']}" in out
    assert plot.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    before = params.read_bytes()
    assert main(['tune', str(csv), '--model', SOPDT, '--params-out', str(params)]) == 2
    assert 'already exists' in capsys.readouterr().err and params.read_bytes() == before


def test_a_refused_design_writes_nothing(tmp_path, capsys):
    csv = write_csv(tmp_path / 'sopdt.csv', two_lags_dead_time().data(1))
    params, plot = tmp_path / 'pid.yaml', tmp_path / 'step.png'
    code = main(['tune', str(csv), '--model', 'K*exp(-tau*s)/(T*s+1)', '--controller', 'PID',
                 '--method', 'simc', '--params-out', str(params), '--plot', str(plot)])
    assert code == 2
    assert 'second lag' in capsys.readouterr().err
    assert not params.exists() and not plot.exists()
    assert sorted(item.name for item in tmp_path.iterdir()) == ['sopdt.csv']


def test_tune_from_a_bag(tmp_path, capsys):
    u, y = simulate(DELAY, 30.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    params = params_file(tmp_path, DELAY)
    assert main(['tune', str(bag), '--params-file', str(params), '--model', DELAY['model'],
                 '--target', 'tc=0.5', '--json', '--draws', '50']) == 0
    summary = json.loads(capsys.readouterr().out)
    truth = DELAY['truth']
    # SIMC on the truth: Kc = T / (K (tc + tau)), ki = Kc / min(T, 4 (tc + tau)).
    kp = truth['T'] / (truth['K'] * (0.5 + truth['tau']))
    assert summary['gains']['kp'] == pytest.approx(kp, rel=0.03)
    assert summary['gains']['ki'] == pytest.approx(kp / truth['T'], rel=0.03)
    assert summary['target'] == {'tc': 0.5}


def test_a_bag_needs_its_params_file(tmp_path, capsys):
    u, y = simulate(DELAY, 5.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    assert main(['tune', str(bag), '--model', DELAY['model']]) == 2
    assert '--params-file' in capsys.readouterr().err


HOSTILE = [
    ['--target', 'x=1'], ['--target', 'tc=-1'], ['--target', 'ms=0.5'], ['--target', 'tc=nan'],
    ['--target', 'tc=1,ms=2'], ['--draws', '-1'], ['--sample-time', '0'],
    ['--sample-time', 'nan'], ['--controller', 'PD'], ['--method', 'magic'],
    ['--model', 's'], ['--model', 'K/(T*s+1'], ['--model', 'K*exp(-tau*s)/(T*s - 1)'],
    ['--method', 'ms', '--target', 'tc=1'], ['--joint', ''], ['--estimate-range', '1:5'],
]


@pytest.mark.parametrize('options', HOSTILE)
def test_hostile_options_exit_cleanly(tmp_path, capsys, options):
    csv = write_csv(tmp_path / 'sopdt.csv', two_lags_dead_time().data(1))
    before = csv.read_bytes()
    try:
        status = main(['tune', str(csv), '--model', SOPDT, '--draws', '20', *options])
    except SystemExit as exit_:          # argparse
        status = exit_.code
    err = capsys.readouterr().err
    assert status in (0, 2) and 'Traceback' not in err and 'internal error' not in err, err
    if status == 2:
        assert len([line for line in err.splitlines() if ': error: ' in line]) == 1, err
    assert csv.read_bytes() == before


@pytest.mark.parametrize('path', ['missing.csv', '.', 'empty.csv'])
def test_unreadable_records_are_user_errors(tmp_path, capsys, path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / 'empty.csv').write_text('')
    for command in (['tune', path, '--model', SOPDT],
                    ['compare', path, '--model', SOPDT, '--model', 'K/(T*s+1)']):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert err.count(': error: ') == 1 and 'internal error' not in err, err
