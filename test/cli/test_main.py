"""The ``ctid`` command's exit statuses and one-line errors, whatever goes wrong."""

from ctid_ros.cli import fit as fit_command
from ctid_ros.cli.main import DEBUG_VARIABLE, error_text, main
from ctid_ros.errors import ConfigError, ModelError
import pytest


def run(capsys, *arguments):
    code = main(list(map(str, arguments)))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture
def broken_fit(monkeypatch):
    """Make ``ctid fit`` fail as a bug would (a TypeError deep inside)."""
    def fail(arguments):
        raise TypeError('unsupported operand type(s)\nfor +: int and str')

    monkeypatch.setattr(fit_command, 'run', fail)
    monkeypatch.delenv(DEBUG_VARIABLE, raising=False)


def test_internal_error_is_one_line_with_exit_1(broken_fit, capsys):
    code, out, err = run(capsys, 'fit', 'data.csv', '--model', 'K/(T*s + 1)')
    assert code == 1 and out == ''
    assert err.startswith('ctid fit: internal error: TypeError: unsupported operand type(s) for '
                          '+: int and str (a bug in ctid_ros; run with ctid --debug or '
                          'CTID_DEBUG=1')
    assert err.count('\n') == 1 and 'Traceback' not in err


def test_debug_shows_the_traceback(broken_fit, capsys, monkeypatch):
    with pytest.raises(TypeError):
        main(['--debug', 'fit', 'data.csv', '--model', 'K/(T*s + 1)'])
    monkeypatch.setenv(DEBUG_VARIABLE, '1')
    with pytest.raises(TypeError):
        main(['fit', 'data.csv', '--model', 'K/(T*s + 1)'])
    monkeypatch.setenv(DEBUG_VARIABLE, '0')
    assert main(['fit', 'data.csv', '--model', 'K/(T*s + 1)']) == 1


def test_interrupt_exits_130(capsys, monkeypatch):
    def interrupt(arguments):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_command, 'run', interrupt)
    code, _, err = run(capsys, 'fit', 'data.csv', '--model', 'K/(T*s + 1)')
    assert code == 130 and err == 'ctid fit: interrupted\n'


def test_command_line_errors_exit_2(capsys):
    for arguments in (['fit'], ['fit', 'x.csv', '--max-iterations', 'many'], ['nothing'], [],
                      ['replay', 'bag', '--params-file', 'p.yaml', '--bogus']):
        with pytest.raises(SystemExit) as exit_:
            main(arguments)
        assert exit_.value.code == 2
        assert 'Traceback' not in capsys.readouterr().err


def test_error_text_is_one_line_but_keeps_a_model_caret():
    assert error_text(ConfigError('a\n  b\tc')) == 'a b c'
    assert error_text(ConfigError('xy ' * 1000)) == ('xy ' * 666)[:1997] + '...'
    # A word longer than any path is cut in the middle, so that what follows it shows.
    assert error_text(ConfigError('cannot read ' + 'x' * 5000 + ': File name too long')) == (
        'cannot read ' + 'x' * 60 + '...' + 'x' * 40 + ' (5000 characters): File name too long')
    caret = ModelError("expected ')' at column 9\n  K/(T*s+1\n          ^")
    assert error_text(caret) == str(caret)
    assert error_text(ModelError('one\ntwo')) == 'one two'


def _one_line_error(code, out, err, command):
    assert code == 2 and out == '' and err.count('\n') == 1, err
    assert err.startswith(f'ctid {command}: error: ') and 'internal error' not in err


def test_paths_too_long_are_one_line_user_errors(tmp_path, capsys):
    from replay_fixtures import DELAY, params_file

    params = params_file(tmp_path, DELAY)
    name = 'a' * 300
    deep = tmp_path.joinpath(*['d' * 250] * 20)
    cases = [('replay', f'{name}.bag', '--params-file', params),
             ('replay', deep, '--params-file', params),
             ('replay', tmp_path, '--params-file', params, '--output', f'{name}.mcap'),
             ('replay', tmp_path, '--params-file', params, '--output', f'{deep}.mcap'),
             ('record', tmp_path / f'{name}.mcap', '/u'),
             ('record', f'{deep}.mcap', '/u'),
             ('fit', f'{deep}.csv', '--model', 'K/(T*s + 1)')]
    for arguments in cases:
        code, out, err = run(capsys, *arguments)
        _one_line_error(code, out, err, arguments[0])
        assert 'too long' in err
        assert len(err) < 400       # the path cut in the middle, with its length
    assert not list(tmp_path.glob('*.mcap'))


@pytest.mark.parametrize('value', ['abc', '500', '-1'])
def test_a_domain_id_dds_cannot_use_is_refused_first(tmp_path, capsys, monkeypatch, value):
    monkeypatch.setenv('ROS_DOMAIN_ID', value)
    output = tmp_path / 'run.mcap'
    code, out, err = run(capsys, 'record', output, '/u', '--wait', '1')
    _one_line_error(code, out, err, 'record')
    assert f"ROS_DOMAIN_ID='{value}' is not a ROS domain" in err
    assert not output.exists()
    code, out, err = run(capsys, 'echo', '--timeout', '1')
    _one_line_error(code, out, err, 'echo')


def test_a_bogus_matplotlib_backend_is_named(tmp_path):
    import os
    import subprocess
    import sys

    from replay_fixtures import DELAY, float_records, params_file, simulate, write_bag

    u, y = simulate(DELAY, 5.0)
    bag = write_bag(tmp_path, float_records(u, y), 'mcap-file')
    # matplotlib reads MPLBACKEND when it loads: a process of its own.
    done = subprocess.run([sys.executable, '-m', 'ctid_ros.cli.main', 'replay', str(bag),
                           '--params-file', str(params_file(tmp_path, DELAY)), '--plot',
                           str(tmp_path / 'fit.png')], capture_output=True, text=True,
                          env={**os.environ, 'MPLBACKEND': 'bogus'}, timeout=120)
    _one_line_error(done.returncode, done.stdout, done.stderr, 'replay')
    assert "MPLBACKEND='bogus' is not a matplotlib backend" in done.stderr
    assert not list(tmp_path.glob('*.png'))


def test_a_log_directory_ros_cannot_create_is_named(tmp_path, capsys, monkeypatch):
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    monkeypatch.setenv('ROS_LOG_DIR', str(blocker / 'log'))
    output = tmp_path / 'run.mcap'
    code, out, err = run(capsys, 'record', output, '/u', '--wait', '1')
    _one_line_error(code, out, err, 'record')
    assert f'ROS cannot write its log files in {blocker}/log (Not a directory; from the ' \
           'environment variable ROS_LOG_DIR)' in err
    assert not output.exists()
