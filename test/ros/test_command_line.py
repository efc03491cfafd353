"""
The command line of ``ctid_node`` before the node starts.

``--help`` without the numerical stack; one-line errors, exit status 2, for arguments and
environments ROS cannot start in.
"""

import os
import subprocess
import sys

from ctid_ros.ros.command_line import user_arguments
import pytest
from rclpy.utilities import remove_ros_args

HEAVY = ('numpy', 'sympy', 'scipy', 'matplotlib', 'rclpy', 'rosbags', 'mcap', 'yaml')
# The console entry point of ctid_node (setup.py), and the node's own module.
ENTRY_POINTS = ('ctid_ros.ros.launcher', 'ctid_ros.ros.node')


def test_help_imports_no_heavy_library():
    script = (
        'import sys\n'
        'from ctid_ros.ros.launcher import main\n'
        "assert main(['ctid_node', '--help']) == 0\n"
        f'print(sorted({{name.split(".")[0] for name in sys.modules}} & {set(HEAVY)!r}))\n')
    result = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                            timeout=60, check=True)
    lines = result.stdout.splitlines()
    assert lines[0].startswith('usage: ctid_node')
    assert any(line.startswith('  tune.controller (string') for line in lines)
    assert lines[-1] == '[]', result.stdout


@pytest.mark.parametrize('arguments', [
    ['ctid_node'], ['ctid_node', '--help'], ['ctid_node', '--ros-args', '-p', 'a:=1'],
    ['ctid_node', '--ros-args', '-p', 'a:=1', '--', '-h', '--ros-args', '-r', 'x:=y'],
    ['ctid_node', 'extra', '--ros-args', '-r', '__ns:=/a', '--', 'more']])
def test_user_arguments_are_those_rclpy_leaves(arguments):
    assert user_arguments(arguments) == remove_ros_args(arguments)


def _run(module, environment, *arguments):
    return subprocess.run([sys.executable, '-m', module, *arguments, '--ros-args', '-p',
                           'model:=K/(T*s + 1)'], capture_output=True, text=True, timeout=60,
                          env={**os.environ, **environment})


@pytest.mark.parametrize('module', ENTRY_POINTS)
@pytest.mark.parametrize('value', ['abc', '500'])
def test_a_domain_id_dds_cannot_use_is_one_line_and_status_2(module, value):
    done = _run(module, {'ROS_DOMAIN_ID': value})
    assert done.returncode == 2, done.stderr
    assert done.stderr.count('\n') == 1 and 'Traceback' not in done.stderr
    assert done.stderr.startswith('ctid_node: error: the environment variable '
                                  f"ROS_DOMAIN_ID='{value}' is not a ROS domain")


@pytest.mark.parametrize('module', ENTRY_POINTS)
def test_a_log_directory_ros_cannot_create_is_one_line_and_status_2(module, tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    done = _run(module, {'ROS_LOG_DIR': str(blocker / 'log')})
    assert done.returncode == 2, done.stderr
    assert done.stderr.count('\n') == 1 and 'Traceback' not in done.stderr
    assert f'ROS cannot write its log files in {blocker}/log (Not a directory' in done.stderr


def test_the_plant_checks_the_environment_too():
    done = _run('ctid_ros.ros.plant_node', {'ROS_DOMAIN_ID': 'abc'})
    assert done.returncode == 2 and 'Traceback' not in done.stderr
    assert done.stderr.startswith('ctid_plant: error: the environment variable ROS_DOMAIN_ID=')
