"""``ctid node``: the live node started by the ctid command, as ctid_node."""

import signal
import subprocess
import sys
import time

from ctid_ros.cli.main import main
import pytest


def test_unknown_configuration_is_one_error_line(capsys):
    assert main(['node', 'no_such_config']) == 2
    err = capsys.readouterr().err
    assert err.startswith("ctid node: error: configuration 'no_such_config.yaml' not found")
    assert err.count('\n') == 1


@pytest.mark.ros
def test_node_runs_from_an_example_configuration_until_sigterm():
    # The root namespace: the example file's section is 'ctid_node:', which rcl matches only
    # there (a namespaced node needs a fully qualified key).
    process = subprocess.Popen(
        [sys.executable, '-m', 'ctid_ros.cli.main', 'node', 'open_loop_delay', '--ros-args',
         '--log-level', 'warn'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # Running (not exited with a configuration error) after its start-up.
        time.sleep(4.0)
        assert process.poll() is None, process.communicate()[0]
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, output
