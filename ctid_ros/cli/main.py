"""
The ``ctid`` command: one subcommand per module of this package.

Each command module (:mod:`~ctid_ros.cli.fit`, :mod:`~ctid_ros.cli.replay`,
:mod:`~ctid_ros.cli.node`) offers ``configure_parser(parser)`` and ``run(arguments) -> int`` and
is imported only when its command runs (the node needs rclpy, replay the bag readers).
"""

import argparse
import importlib
import sys
from typing import List, Optional

from ctid_ros.errors import CtidError

__all__ = ['build_parser', 'main']

_MODULE_COMMANDS = {
    'fit': ('ctid_ros.cli.fit', 'estimate a model from a CSV file'),
    'replay': ('ctid_ros.cli.replay', 'estimate from a rosbag2 directory or an MCAP file'),
    'node': ('ctid_ros.cli.node', 'run the live identification node (same as ctid_node)'),
}


def build_parser(argv: Optional[List[str]] = None) -> argparse.ArgumentParser:
    """Return the ``ctid`` argument parser with its subcommands."""
    parser = argparse.ArgumentParser(
        prog='ctid', description='Continuous-time grey-box identification (ctid_ros).')
    subparsers = parser.add_subparsers(dest='command', required=True)
    for command, (module_name, summary) in _MODULE_COMMANDS.items():
        subparser = subparsers.add_parser(command, help=summary, description=summary)
        if argv and argv[0] == command:
            module = importlib.import_module(module_name)
            module.configure_parser(subparser)
            subparser.set_defaults(run=module.run)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point of the ``ctid`` command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    arguments, unknown = parser.parse_known_args(argv)
    if unknown and arguments.command != 'node':
        parser.error(f'unrecognized arguments: {" ".join(unknown)}')
    arguments.ros_arguments = unknown
    try:
        return arguments.run(arguments)
    except CtidError as error:
        print(f'ctid {arguments.command}: error: {error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
