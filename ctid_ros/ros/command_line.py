"""
The command line of ``ctid_node`` and ``ctid_plant`` before a node starts: no rclpy, no numpy.

:func:`command_line` answers ``-h``/``--help`` and a wrong argument, and refuses an
environment ROS cannot start in (a ``ROS_DOMAIN_ID`` that is no domain, a log directory that
cannot be written: :func:`~ctid_ros.ros.environment.check_ros_environment`) with one line on
stderr and exit status 2, not a traceback. Used by :mod:`ctid_ros.ros.launcher` (the console
entry point, before anything heavy is imported) and by :func:`ctid_ros.ros.runner.run_node`.
"""

import os
import sys
from typing import Callable, List, Optional

from ctid_ros.errors import ConfigError
from ctid_ros.ros.environment import check_ros_environment

__all__ = ['ROS_ARGUMENTS', 'command_line', 'user_arguments']

ROS_ARGUMENTS = '--ros-args'
# Ends a --ros-args section (rcl's convention).
_END_OF_ROS_ARGUMENTS = '--'


def user_arguments(arguments: List[str]) -> List[str]:
    """
    Return ``arguments`` without the ROS ones, as ``rclpy.utilities.remove_ros_args`` does.

    Every ``--ros-args`` section is left out, up to the ``--`` that ends it or to the end.
    """
    own, inside = [], False
    for argument in arguments:
        if argument == ROS_ARGUMENTS:
            inside = True
        elif inside:
            inside = argument != _END_OF_ROS_ARGUMENTS
        else:
            own.append(argument)
    return own


def command_line(arguments: List[str], name: str,
                 usage: Optional[Callable[[], str]] = None) -> Optional[int]:
    """
    Answer what the command line and the environment settle before a node starts.

    ``-h``/``--help`` outside ``--ros-args`` prints ``usage()`` and gives 0; any other such
    argument, or an environment ROS cannot start in, prints one line on stderr and gives 2.

    Returns
    -------
    int or None
        The exit status, or None if the node is to be started.

    """
    own = user_arguments(arguments)[1:]
    if '-h' in own or '--help' in own:
        print(usage() if usage else f'usage: {name} [--ros-args ...]')
        return 0
    if own:
        print(f'{name}: error: unrecognised argument(s) {" ".join(own)}: ROS arguments go after '
              f'--ros-args (see {name} --help)', file=sys.stderr)
        return 2
    try:
        check_ros_environment(os.environ)
    except ConfigError as error:
        print(f'{name}: error: {error}', file=sys.stderr)
        return 2
    return None
