"""``ctid node``: the live node started by the ctid command, as ctid_node."""

import signal
import subprocess
import sys

from ctid_ros.cli.main import main
from node_harness import wait_for
import pytest
import rclpy
from rclpy.context import Context


def test_unknown_configuration_is_one_error_line(capsys):
    assert main(['node', 'no_such_config']) == 2
    err = capsys.readouterr().err
    assert err.startswith("ctid node: error: configuration 'no_such_config.yaml' not found")
    assert err.count('\n') == 1


@pytest.mark.ros
def test_node_runs_from_an_example_configuration_until_sigterm():
    # The root namespace: the example file's section is 'ctid_node:', which rcl matches only
    # there (a namespaced node needs a fully qualified key).
    context = Context()
    rclpy.init(context=context)
    observer = rclpy.create_node('cli_node_observer', context=context)
    process = subprocess.Popen(
        [sys.executable, '-m', 'ctid_ros.cli.main', 'node', 'open_loop_delay', '--ros-args',
         '--log-level', 'warn'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # Configured and active (not exited with a configuration error): its services are on
        # the graph.
        wait_for(lambda: process.poll() is not None or '/ctid_node/estimate_now' in
                 dict(observer.get_service_names_and_types()), 120.0, 'ctid_node services')
        assert process.poll() is None, process.communicate()[0]
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
        observer.destroy_node()
        rclpy.shutdown(context=context)
    assert process.returncode == 0, output
