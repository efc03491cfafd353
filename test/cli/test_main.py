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
    assert error_text(ConfigError('x' * 5000)) == 'x' * 1997 + '...'
    caret = ModelError("expected ')' at column 9\n  K/(T*s+1\n          ^")
    assert error_text(caret) == str(caret)
    assert error_text(ModelError('one\ntwo')) == 'one two'
