"""The command line alone: every ``--help`` without the heavy libraries, the choices in sync."""

import importlib
import subprocess
import sys

from ctid_ros.cli import arguments
from ctid_ros.cli.main import build_parser, COMMANDS
from ctid_ros.core.simulation import INTERSAMPLE
from ctid_ros.estimation.options import INITIAL_STATES, METHODS
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME
import pytest

HEAVY = ('numpy', 'sympy', 'scipy', 'matplotlib', 'rclpy', 'rosbags', 'mcap', 'tqdm', 'yaml')


def test_choices_are_the_estimators():
    assert arguments.METHODS == METHODS
    assert arguments.INITIAL_STATES == INITIAL_STATES
    assert arguments.INTERSAMPLE == INTERSAMPLE
    assert arguments.DEFAULT_NODE_NAME == DEFAULT_NODE_NAME


@pytest.mark.parametrize('command', [[]] + [[name] for name in COMMANDS])
def test_help_imports_no_heavy_library(command):
    script = (
        'import sys\n'
        'from ctid_ros.cli.main import main\n'
        'try:\n'
        f'    main({command + ["--help"]!r})\n'
        'except SystemExit as exit_:\n'
        '    assert exit_.code == 0, exit_.code\n'
        f'print(sorted({{name.split(".")[0] for name in sys.modules}} & {set(HEAVY)!r}))\n')
    result = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.splitlines()[-1] == '[]', result.stdout


def test_every_command_has_a_module_that_runs_it():
    for name, command in COMMANDS.items():
        assert callable(importlib.import_module(command.module).run), name
        assert name in build_parser().format_help()
