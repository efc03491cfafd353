"""
The console entry point of ``ctid_node``: the command line first, the node only then.

``ctid_node --help`` and a wrong argument or environment are answered by
:func:`~ctid_ros.ros.command_line.command_line` without rclpy or the numerical stack (issue
#26: ``--help`` at most twice ``python -c "import numpy"``); only then is the node's module
imported and run (:func:`ctid_ros.ros.node.main`, which is the same command after its
imports).
"""

import importlib
import sys
from typing import List, Optional

from ctid_ros.ros.command_line import command_line
from ctid_ros.ros.parameter_table import node_usage
from ctid_ros.streaming.parameter_specs import DEFAULT_NODE_NAME

__all__ = ['main']


def main(args: Optional[List[str]] = None) -> int:
    """Run ``ctid_node``: answer ``--help`` and bad arguments at once, else start the node."""
    arguments = list(sys.argv if args is None else args)
    status = command_line(arguments, DEFAULT_NODE_NAME, node_usage)
    if status is not None:
        return status
    # Imported by name once the node is to run: rclpy, numpy and sympy load only here.
    return importlib.import_module('ctid_ros.ros.node').main(arguments)


if __name__ == '__main__':
    sys.exit(main())
