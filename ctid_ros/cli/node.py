"""
``ctid node``: run the live identification node, as ``ctid_node`` does.

``ctid node open_loop_delay`` is ``ctid_node --ros-args --params-file
<share>/config/open_loop_delay.yaml``; further ROS arguments (``--ros-args -r __ns:=/plant1``)
pass through. This module (and with it rclpy) is imported only when the command runs.
"""

import argparse

from ctid_ros.ros.node import main
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME
from ctid_ros.streaming.params_file import find_config

__all__ = ['run']


def run(arguments: argparse.Namespace) -> int:
    """Run the node for ``ctid node``."""
    ros_arguments = list(getattr(arguments, 'ros_arguments', None) or [])
    if arguments.config:
        ros_arguments = ['--ros-args', '--params-file', str(find_config(arguments.config)),
                         *ros_arguments]
    return main([DEFAULT_NODE_NAME, *ros_arguments])
