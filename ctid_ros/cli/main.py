"""
The ``ctid`` command: one subcommand per module of this package.

Each command module (:mod:`~ctid_ros.cli.fit`, :mod:`~ctid_ros.cli.replay`,
:mod:`~ctid_ros.cli.node`) offers ``configure_parser(parser)`` and ``run(arguments) -> int`` and
is imported only when its command runs (the node needs rclpy, replay the bag readers).

Exit status and error output: 0 on success; 2 with one line ``ctid <command>: error: ...`` for
every user error (a :class:`~ctid_ros.errors.CtidError`; a model error adds the model text with
a caret under the column) and for a wrong command line (argparse); 1 with one line ``ctid
<command>: internal error: <type>: ...`` for anything else, which is a bug of ctid_ros: its
traceback is printed only with ``ctid --debug`` or ``CTID_DEBUG=1`` in the environment. 130 on
Ctrl-C.
"""

import argparse
import importlib
import os
import sys
from typing import List, Optional

from ctid_ros.errors import CtidError, ModelError

__all__ = ['DEBUG_VARIABLE', 'build_parser', 'error_text', 'main']

# Set to 1 (or use ctid --debug) to get the traceback of an internal error.
DEBUG_VARIABLE = 'CTID_DEBUG'
# Characters of an error message printed (a message may quote a long value or listing).
_MESSAGE_LIMIT = 2000

_MODULE_COMMANDS = {
    'fit': ('ctid_ros.cli.fit', 'estimate a model from a CSV file'),
    'replay': ('ctid_ros.cli.replay', 'estimate from a rosbag2 directory or an MCAP file'),
    'node': ('ctid_ros.cli.node', 'run the live identification node (same as ctid_node)'),
    'fleet': ('ctid_ros.cli.fleet', 'estimate on every bag of a fleet with Dask; Parquet '
              'results and a fleet report'),
}


def build_parser(argv: Optional[List[str]] = None) -> argparse.ArgumentParser:
    """Return the ``ctid`` argument parser with its subcommands."""
    parser = argparse.ArgumentParser(
        prog='ctid', description='Continuous-time grey-box identification (ctid_ros).',
        epilog=f'Exit status: 0 success, 2 user error (one line), 1 internal error (a bug; its '
        f'traceback with --debug or {DEBUG_VARIABLE}=1).')
    parser.add_argument('--debug', action='store_true',
                        help='print the traceback of an internal error')
    subparsers = parser.add_subparsers(dest='command', required=True)
    command = next((item for item in argv or [] if not item.startswith('-')), None)
    for name, (module_name, summary) in _MODULE_COMMANDS.items():
        subparser = subparsers.add_parser(name, help=summary, description=summary)
        if command == name:
            module = importlib.import_module(module_name)
            module.configure_parser(subparser)
            subparser.set_defaults(run=module.run)
    return parser


def error_text(error: BaseException) -> str:
    """
    Return the message of ``error`` for the terminal: one line, at most 2000 characters.

    A :class:`~ctid_ros.errors.ModelError` keeps the model text and the caret under the column
    that its message shows on the lines after the first.
    """
    lines = str(error).splitlines() or ['']
    if isinstance(error, ModelError) and len(lines) == 3 and lines[2].strip() == '^':
        first, context = lines[0], lines[1:]
    else:
        first, context = ' '.join(' '.join(lines).split()), []
    if len(first) > _MESSAGE_LIMIT:
        first = first[:_MESSAGE_LIMIT - 3] + '...'
    return '\n'.join([first] + [line[:_MESSAGE_LIMIT] for line in context])


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point of the ``ctid`` command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    arguments, unknown = parser.parse_known_args(argv)
    if unknown and arguments.command != 'node':
        parser.error(f'unrecognized arguments: {" ".join(unknown)}')
    arguments.ros_arguments = unknown
    prefix = f'ctid {arguments.command}'
    try:
        return arguments.run(arguments)
    except CtidError as error:
        print(f'{prefix}: error: {error_text(error)}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'{prefix}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of the output went away (ctid fit ... | head): nothing left to say.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except Exception as error:  # the last resort: a bug, reported on one line
        if arguments.debug or os.environ.get(DEBUG_VARIABLE, '') not in ('', '0'):
            raise
        name = type(error).__name__
        print(f'{prefix}: internal error: {name}: {error_text(error)} (a bug in ctid_ros; '
              f'run with ctid --debug or {DEBUG_VARIABLE}=1 for the traceback, and report it)',
              file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
