"""
The parameter table documents exactly what a running ctid_node lists, without starting one.

``declared_parameters`` is what a documentation generator reads (no rclpy, no node); here it is
held against ``list_parameters`` and ``describe_parameters`` of a node on real DDS.
"""

import subprocess
import sys

from ctid_ros.ros.parameter_table import declared_parameters, MODEL_NAME_PLACEHOLDER, node_usage
from node_harness import Harness, wait_for
from rcl_interfaces.msg import ParameterType
from rclpy.parameter_client import AsyncParameterClient


def test_the_table_is_importable_without_rclpy():
    code = ('import sys; from ctid_ros.ros.parameter_table import declared_parameters; '
            'table = declared_parameters(); '
            'print(len(table), any(name.split(".")[0] in ("rclpy", "rcl_interfaces") '
            'for name in sys.modules))')
    output = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            check=True).stdout.split()
    assert int(output[0]) > 40 and output[1] == 'False'


def test_the_table_names_every_parameter_once_with_a_description():
    table = declared_parameters()
    names = [entry.name for entry in table]
    assert len(names) == len(set(names))
    assert all(entry.description for entry in table)
    assert f'baseline.{MODEL_NAME_PLACEHOLDER}' in names and 'use_sim_time' in names
    usage = node_usage()
    assert all(f'  {entry.name} (' in usage for entry in table if entry.origin == 'config')


def test_a_running_node_lists_exactly_the_declared_parameters(tmp_path):
    ros = Harness(tmp_path)
    try:
        ros.identifier(input_topic='u', output_topic='y', model='K/(T*s + 1)',
                       sample_time=0.01, window=2.0)
        client = AsyncParameterClient(ros.observer, f'{ros.namespace}/ctid_node')
        assert client.wait_for_services(timeout_sec=30.0)
        future = client.list_parameters()
        wait_for(future.done, 30.0, 'list_parameters')
        listed = sorted(future.result().result.names)
        table = {entry.name: entry for entry in declared_parameters(('K', 'T'))}
        assert listed == sorted(table)
        future = client.describe_parameters(listed)
        wait_for(future.done, 30.0, 'describe_parameters')
        for descriptor in future.result().descriptors:
            entry = table[descriptor.name]
            if entry.kind.startswith('double'):
                # Dynamically typed, so that YAML 5 is accepted for 5.0 (converted on use).
                assert descriptor.dynamic_typing, descriptor.name
            else:
                assert descriptor.type == getattr(ParameterType,
                                                  'PARAMETER_' + entry.kind.upper())
            if entry.origin != 'rclpy':
                assert descriptor.description == entry.description
                assert descriptor.read_only == entry.read_only
    finally:
        ros.close()
