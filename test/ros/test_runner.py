"""run_node: the node it made and its context end with the run, and their threads with them."""

import os
from pathlib import Path
import signal
import threading

from ctid_ros.ros.node import IdentificationNode
from ctid_ros.ros.plant_node import PlantNode
from ctid_ros.ros.runner import run_node
from node_harness import wait_for
import pytest
from rclpy.parameter import Parameter

PARAMETERS = {'input_topic': 'runner_u', 'output_topic': 'runner_y',
              'input_field': 'point.x', 'output_field': 'point.x', 'model': 'K/(T*s + 1)',
              'parameter_names': ['K', 'T'], 'initial': [1.0, 1.0], 'sample_time': 0.005,
              'window': 2.0, 'update_period': 0.1}


def dds_threads() -> int:
    """Count this process's DDS threads (Fast DDS names them dds.*; its static watchdog aside)."""
    names = [(task / 'comm').read_text().strip() for task in Path('/proc/self/task').iterdir()]
    return sum(name.startswith('dds.') and name != 'dds.shm.wdog' for name in names)


class RecordedNode(IdentificationNode):
    """The live node, remembering whether it was destroyed."""

    destroyed = False

    def destroy_node(self) -> None:
        type(self).destroyed = True
        super().destroy_node()


@pytest.mark.ros
def test_a_signal_destroys_the_node_and_ends_its_estimator_thread():
    # executor.shutdown() forgets its nodes: run_node once took them back from it after the
    # shutdown, found none, and left the estimator thread running into the interpreter's
    # exit (a segmentation fault now and then, in CI).
    made = []
    returned = threading.Event()
    before = set(threading.enumerate())
    participants = dds_threads()

    def factory():
        node = RecordedNode(parameter_overrides=[Parameter(name, value=value)
                                                 for name, value in PARAMETERS.items()])
        made.append(node)
        return node

    def stop_when_made():
        wait_for(lambda: made or returned.is_set(), 120.0, 'the node')
        if not returned.is_set():       # a node that failed to start has ended the run
            os.kill(os.getpid(), signal.SIGTERM)

    stopper = threading.Thread(target=stop_when_made, daemon=True)
    stopper.start()
    try:
        status = run_node(factory, 'ctid_node', ['ctid_node'])
    finally:
        returned.set()
    stopper.join()
    assert status == 0
    assert RecordedNode.destroyed
    left = [thread.name for thread in threading.enumerate()
            if thread not in before and thread is not stopper and thread.is_alive()]
    assert left == []
    # The run's DDS participant has ended (another test's may end meanwhile, none starts).
    assert dds_threads() <= participants


@pytest.mark.ros
def test_a_node_that_refuses_its_configuration_ends_with_its_context():
    # The node's constructor raises: run_node never holds it, so the node destroys itself
    # before raising, or its handles would keep the context and its DDS threads alive.
    participants = dds_threads()
    before = set(threading.enumerate())

    def factory():
        return RecordedNode(parameter_overrides=[
            Parameter(name, value=value)
            for name, value in {**PARAMETERS, 'update_period': 0.05}.items()])

    assert run_node(factory, 'ctid_node', ['ctid_node']) == 2
    assert dds_threads() <= participants
    assert [thread for thread in threading.enumerate() if thread not in before] == []


@pytest.mark.ros
@pytest.mark.parametrize('name, value', [('message_type', 'no_such_type'),
                                         ('model', 'K/(T*s+')])
def test_a_plant_that_refuses_its_configuration_says_why_and_ends(name, value, capsys):
    # A model text that does not parse raised ModelError through run_node: a traceback and
    # status 1 instead of one message and status 2.
    participants = dds_threads()

    def factory():
        return PlantNode(parameter_overrides=[Parameter(name, value=value)])

    assert run_node(factory, 'ctid_plant', ['ctid_plant']) == 2
    assert capsys.readouterr().err.startswith('ctid_plant: error: ')
    assert dds_threads() <= participants


@pytest.mark.parametrize('text, reason', [
    ('ctid_node:\n  ros__parameters:\n    lower: [0.001, 0, 0]\n',
     "Value type 'integer' do not belong at line_num 3 (line 3: a list mixes integers and "
     'doubles, which ROS 2 refuses; write every number of a list of doubles with a decimal '
     'point, 0.0 and not 0)'),
    ('ctid_node:\n  ros__parameters:\n    model: [a\n', 'Error parsing a event near line 3')],
    ids=['mixed list', 'broken YAML'])
def test_a_params_file_rcl_cannot_parse_is_one_line_and_status_2(tmp_path, capsys, text,
                                                                 reason):
    # rclpy.init raised RCLError through run_node: a traceback and status 1 (`ctid node`:
    # "internal error ... a bug in ctid_ros") for a list as natural as [0.001, 0, 0].
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    arguments = ['ctid_node', '--ros-args', '--params-file', str(path)]
    assert run_node(IdentificationNode, 'ctid_node', arguments) == 2
    err = capsys.readouterr().err
    assert err.startswith("ctid_node: error: ROS cannot start with these arguments: Couldn't "
                          f"parse params file: '--params-file {path}'. Error: ")
    assert err.rstrip().endswith(reason) and err.count('\n') == 1, err
