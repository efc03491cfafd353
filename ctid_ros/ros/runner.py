"""
Running a node as a process: ``main()`` of ``ctid_node`` and ``ctid_plant``.

:func:`run_node` reads the command line (``--help``, anything outside ``--ros-args`` is an
error), initialises rclpy, spins the node until Ctrl-C or SIGTERM and shuts everything down in
order: the node before the context, so no callback or publication meets an invalid context.
"""

import signal
import sys
from typing import Any, Callable, List, Optional

from ctid_ros.errors import ConfigError
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

__all__ = ['run_node']


def _interrupt(signal_number: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run_node(factory: Callable[[], Node], name: str, args: Optional[List[str]] = None,
             usage: Optional[Callable[[], str]] = None) -> int:
    """
    Spin the node made by ``factory`` until Ctrl-C or SIGTERM.

    ``-h``/``--help`` before ``--ros-args`` prints ``usage()`` and returns 0 without starting;
    any other argument outside ``--ros-args`` is an error (status 2). Both signals interrupt
    the spinning thread, which then destroys the node before the context goes, so no callback
    or publication meets an invalid context.
    """
    arguments = list(sys.argv if args is None else args)
    own = remove_ros_args(arguments)[1:]
    if '-h' in own or '--help' in own:
        print(usage() if usage else f'usage: {name} [--ros-args ...]')
        return 0
    if own:
        print(f'{name}: error: unrecognised argument(s) {" ".join(own)}: ROS arguments go after '
              f'--ros-args (see {name} --help)', file=sys.stderr)
        return 2
    rclpy.init(args=arguments, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    executor = SingleThreadedExecutor()
    try:
        executor.add_node(factory())
        executor.spin()
    except (ConfigError, ParameterException) as error:
        print(f'{name}: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    finally:
        executor.shutdown()
        for node in executor.get_nodes():
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
