"""
The ``ctid`` command: one subcommand per module of this package.

The arguments of every command are in :mod:`~ctid_ros.cli.arguments`, which imports nothing
heavy, so ``ctid --help`` and ``ctid <command> --help`` start fast. The module that runs the
chosen command (:mod:`~ctid_ros.cli.fit`, :mod:`~ctid_ros.cli.replay`, ...: ``run(arguments) ->
int``) is imported only once its command line has been parsed; the libraries it needs come
with it (sympy and scipy for an estimate, rclpy for the node, the bag readers for a replay).

Exit status and error output: 0 on success; 2 with one line ``ctid <command>: error: ...`` for
every user error (a :class:`~ctid_ros.errors.CtidError`; a model error adds the model text with
a caret under the column; an optional dependency that is not installed; a system call that
failed on a path or environment the user gave: a name too long, a full disk, no permission) and
for a wrong command line (argparse); 1 with one line ``ctid <command>: internal error: <type>:
...`` for anything else, which is a bug of ctid_ros: its traceback is printed only with ``ctid
--debug`` or ``CTID_DEBUG=1`` in the environment. 130 on Ctrl-C.
The commands that run until stopped (``ctid record``, ``ctid echo``) end with status 0 on
SIGINT and SIGTERM (:func:`ctid_ros.ros.spinner.stop_on_signals`).
"""

import argparse
import errno
import gc
import importlib
import os
import re
import sys
from typing import Callable, Dict, List, NamedTuple, Optional

from ctid_ros.cli import arguments as command_lines
from ctid_ros.errors import CtidError, ModelError
from ctid_ros.ros.environment import check_ros_environment, SHORT_PATH, shown_path

__all__ = ['COMMANDS', 'Command', 'DEBUG_VARIABLE', 'build_parser', 'check_ros_environment',
           'error_text', 'main', 'os_error_text']

# Set to 1 (or use ctid --debug) to get the traceback of an internal error.
DEBUG_VARIABLE = 'CTID_DEBUG'
# Characters of an error message printed (a message may quote a long value or listing).
_MESSAGE_LIMIT = 2000
# errno values of failures that a path or the environment given by the user causes: what the
# system says is the whole message.
_USER_ERRNOS = frozenset((errno.ENAMETOOLONG, errno.ENOENT, errno.ENOTDIR, errno.EISDIR,
                          errno.ELOOP, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC,
                          errno.EDQUOT, errno.EFBIG, errno.EEXIST, errno.ENXIO, errno.ETXTBSY))
# Characters of a path quoted in an error, from its start and from its end.
# A word of an error message that shown_path shortens.
_LONG_WORD = re.compile(r'[^\s,;:]{%d,}' % (SHORT_PATH + 1))
# The largest domain id for which DDS's port numbers fit (with the default port base).


class Command(NamedTuple):
    """
    One subcommand of ``ctid``.

    Attributes
    ----------
    summary : str
        One line for ``ctid --help``.
    configure : callable
        Adds the command's arguments to its parser (:mod:`~ctid_ros.cli.arguments`).
    module : str
        The module whose ``run(arguments) -> int`` runs the command, imported only then.
    ros_arguments : bool
        Whether arguments the parser does not know pass through to ROS (``--ros-args ...``).
    uses_ros : bool
        Whether the command joins the ROS graph (its environment is checked first).

    """

    summary: str
    configure: Callable[[argparse.ArgumentParser], None]
    module: str
    ros_arguments: bool = False
    uses_ros: bool = False


COMMANDS: Dict[str, Command] = {
    'fit': Command('estimate a model from a CSV file', command_lines.configure_fit,
                   'ctid_ros.cli.fit'),
    'replay': Command('estimate from a rosbag2 directory, an MCAP file or a ROS 1 bag',
                      command_lines.configure_replay, 'ctid_ros.cli.replay'),
    'node': Command('run the live identification node (same as ctid_node)',
                    command_lines.configure_node, 'ctid_ros.cli.node', ros_arguments=True,
                    uses_ros=True),
    'echo': Command("print a running node's estimates as a live table (ros2 topic echo)",
                    command_lines.configure_echo, 'ctid_ros.cli.echo', uses_ros=True),
    'record': Command('record live topics into an MCAP file (ros2 bag record)',
                      command_lines.configure_record, 'ctid_ros.cli.record', uses_ros=True),
    'fleet': Command('estimate on every bag of a fleet with Dask; Parquet results and a fleet '
                     'report', command_lines.configure_fleet, 'ctid_ros.cli.fleet'),
    'compare': Command('fit candidate models on one record and recommend the simplest adequate',
                       command_lines.configure_compare, 'ctid_ros.cli.compare'),
    'tune': Command('PI/PID gains from an identified model, verified across its uncertainty',
                    command_lines.configure_tune, 'ctid_ros.cli.tune'),
}

# The pip extra that provides each optional dependency, for the message when it is missing.
_EXTRAS = {'rclpy': 'ros', 'rosbags': 'bag', 'mcap': 'bag', 'mcap_ros2': 'bag', 'tqdm': 'bag',
           'matplotlib': 'plot', 'dask': 'fleet', 'distributed': 'fleet', 'pyarrow': 'fleet'}


def build_parser() -> argparse.ArgumentParser:
    """Return the ``ctid`` argument parser with the arguments of every subcommand."""
    parser = argparse.ArgumentParser(
        prog='ctid', description='Continuous-time grey-box identification (ctid_ros).',
        epilog=f'Exit status: 0 success, 2 user error (one line), 1 internal error (a bug; its '
        f'traceback with --debug or {DEBUG_VARIABLE}=1).')
    parser.add_argument('--debug', action='store_true',
                        help='print the traceback of an internal error')
    subparsers = parser.add_subparsers(dest='command', required=True)
    for name, command in COMMANDS.items():
        command.configure(subparsers.add_parser(name, help=command.summary,
                                                description=command.summary))
    return parser


def _missing_dependency(error: ImportError) -> str:
    """Return what to install for an optional dependency that could not be imported."""
    module = (error.name or '').split('.')[0]
    extra = _EXTRAS.get(module)
    if extra is None:
        return f'cannot import {module or error}: {error}'
    hint = ' or source a ROS 2 installation' if extra == 'ros' else ''
    return (f'this command needs {module}, which is not installed: pip install '
            f"'ctid_ros[{extra}]'{hint}")


def os_error_text(error: OSError) -> str:
    """
    Return one line for a system call that failed on a user's path: what failed, and where.

    A name too long says the limits (255 bytes per name, PATH_MAX for a whole path).
    """
    text = error.strerror or str(error)
    if error.filename is not None:
        text += f': {shown_path(error.filename)}'
    if error.filename2 is not None:
        text += f' -> {shown_path(error.filename2)}'
    if error.errno == errno.ENAMETOOLONG:
        text += (f' (the system allows {os.pathconf("/", "PC_NAME_MAX")} bytes per name and '
                 f'{os.pathconf("/", "PC_PATH_MAX")} per path)')
    return text


def error_text(error: BaseException) -> str:
    """
    Return the message of ``error`` for the terminal: one line, at most 2000 characters.

    A :class:`~ctid_ros.errors.ModelError` keeps the model text and the caret under the column
    that its message shows on the lines after the first. A word longer than a path should be
    (a name past the system's limits) is cut in the middle, so that the cause after it shows.
    """
    lines = str(error).splitlines() or ['']
    if isinstance(error, ModelError) and len(lines) == 3 and lines[2].strip() == '^':
        first, context = lines[0], lines[1:]
    else:
        first = ' '.join(' '.join(lines).split())
        first, context = _LONG_WORD.sub(lambda match: shown_path(match.group()), first), []
    if len(first) > _MESSAGE_LIMIT:
        first = first[:_MESSAGE_LIMIT - 3] + '...'
    return '\n'.join([first] + [line[:_MESSAGE_LIMIT] for line in context])


def main(argv: Optional[List[str]] = None) -> int:
    """
    Entry point of the ``ctid`` command.

    Called without ``argv`` (as the process's command) it leaves the objects it made out of
    the interpreter's last garbage collections: those walk every object sympy and scipy
    created, up to a second after the command ended (Ctrl-C of ``ctid echo`` took 1.3 s to
    exit, 0.4 s without them). Everything that must be closed is closed before.
    """
    try:
        return _run(sys.argv[1:] if argv is None else list(argv))
    finally:
        if argv is None:
            gc.freeze()


def _run(argv: List[str]) -> int:
    """Parse ``argv``, run the command, turn its errors into messages and exit statuses."""
    parser = build_parser()
    arguments, unknown = parser.parse_known_args(argv)
    command = COMMANDS[arguments.command]
    if unknown and not command.ros_arguments:
        parser.error(f'unrecognized arguments: {" ".join(unknown)}')
    arguments.ros_arguments = unknown
    prefix = f'ctid {arguments.command}'
    try:
        if command.uses_ros:
            check_ros_environment(os.environ)
        return importlib.import_module(command.module).run(arguments)
    except ImportError as error:
        if (error.name or '').split('.')[0] not in _EXTRAS:
            return _internal_error(prefix, arguments, error)
        print(f'{prefix}: error: {_missing_dependency(error)}', file=sys.stderr)
        return 2
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
    except OSError as error:
        if error.errno not in _USER_ERRNOS:
            return _internal_error(prefix, arguments, error)
        print(f'{prefix}: error: {os_error_text(error)}', file=sys.stderr)
        return 2
    except Exception as error:  # the last resort: a bug, reported on one line
        return _internal_error(prefix, arguments, error)


def _internal_error(prefix: str, arguments: argparse.Namespace, error: Exception) -> int:
    """Report a bug on one line and return 1, or raise it again for ``--debug``."""
    if arguments.debug or os.environ.get(DEBUG_VARIABLE, '') not in ('', '0'):
        raise error
    name = type(error).__name__
    print(f'{prefix}: internal error: {name}: {error_text(error)} (a bug in ctid_ros; '
          f'run with ctid --debug or {DEBUG_VARIABLE}=1 for the traceback, and report it)',
          file=sys.stderr)
    return 1


if __name__ == '__main__':
    sys.exit(main())
