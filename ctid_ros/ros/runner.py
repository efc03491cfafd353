"""
Running a node as a process: ``main()`` of ``ctid_node`` and ``ctid_plant``.

:func:`run_node` reads the command line (``--help``, anything outside ``--ros-args`` is an
error), initialises rclpy, spins the node until SIGINT (Ctrl-C) or SIGTERM and shuts
everything down in order: the node (its estimator thread with it, unless an estimate outlasts
the node's grace period: it is then abandoned and publishes nothing) before the context, so no
callback or publication meets an invalid context, and the context's handle before the
interpreter's exit, so no DDS thread outlives it; the exit status is 0.

Why not rclpy's own signal handling: it shuts the context down from the signal, under the
node's feet (a publication in progress fails). Why not a Python handler that raises
``KeyboardInterrupt``: Python runs a handler only when the main thread executes bytecode, and
the executor waits in ``rcl_wait`` without a timeout while no timer is due (a managed node
unconfigured or inactive, ``use_sim_time`` without ``/clock``), so the signal was never seen
(issue #25); and an exception raised inside ``take_message`` ended in a RuntimeError. Here the
handler only sets a flag, and the executor waits at most :data:`SIGNAL_LATENCY` at a time, so a
signal ends the node within that period plus the callback in progress, in every state. The
interpreter's final garbage collection is skipped (``gc.freeze``): it was most of the exit.
"""

import gc
import re
import signal
import sys
import threading
from typing import Callable, List, Optional

from ctid_ros.errors import CtidError
from ctid_ros.ros.command_line import command_line
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

__all__ = ['SIGNAL_LATENCY', 'init_problem', 'run_node']

# Longest wait of the executor between two looks at the stop flag (seconds).
SIGNAL_LATENCY = 0.1
_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# Where in rcl's sources an error arose, as rcl appends it to its messages.
_RCL_LOCATION = re.compile(r',? at /\S+:\d+')
_MIXED_LIST = re.compile(r'Sequence should be of same type\..*?line_num (\d+)')


def run_node(factory: Callable[[], Node], name: str, args: Optional[List[str]] = None,
             usage: Optional[Callable[[], str]] = None) -> int:
    """
    Spin the node made by ``factory`` until SIGINT or SIGTERM; return the exit status.

    ``-h``/``--help`` before ``--ros-args`` prints ``usage()`` and returns 0 without starting;
    any other argument outside ``--ros-args`` is an error (status 2), and so are an
    environment ROS cannot start in (:func:`~ctid_ros.ros.command_line.command_line`) and a
    configuration the node refuses to start with (any of the library's errors, a model text
    that does not parse among them: one message, no traceback), and so are ROS arguments rcl
    refuses (a params file it cannot parse: :func:`init_problem`). A signal returns 0 within
    :data:`SIGNAL_LATENCY` plus the callback in progress and the node's own
    ``destroy_node``; the handlers of both signals are restored on return.
    """
    arguments = list(sys.argv if args is None else args)
    status = command_line(arguments, name, usage)
    if status is not None:
        return status
    try:
        rclpy.init(args=arguments, signal_handler_options=SignalHandlerOptions.NO)
    except rclpy_implementation.RCLError as error:
        print(f'{name}: error: {init_problem(str(error))}', file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = {number: signal.signal(number, lambda number, frame: stop.set())
                for number in _SIGNALS}
    try:
        return _spin(factory, name, arguments, stop)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        # The interpreter's last garbage collection walks the whole heap (sympy, scipy): it
        # took 1.7 s of a 1.8 s exit on a loaded machine. Everything is shut down by now, so
        # the objects alive are moved out of the collector's way.
        gc.freeze()


def init_problem(text: str) -> str:
    """
    Say in one line why rcl refused the ROS arguments (a params file it cannot parse).

    rcl types a YAML list by its elements and refuses one that mixes integers and doubles
    (``lower: [0.001, 0, 0]``), which the node itself would accept as doubles: that case
    gets what to write instead.
    """
    text = _RCL_LOCATION.sub('', text).strip()
    text = text.replace('failed to initialize rcl: ', '', 1)
    mixed = _MIXED_LIST.search(text)
    if mixed is not None:
        text += (f' (line {mixed.group(1)}: a list mixes integers and doubles, which ROS 2 '
                 'refuses; write every number of a list of doubles with a decimal point, '
                 '0.0 and not 0)')
    return f'ROS cannot start with these arguments: {text}'


def _spin(factory: Callable[[], Node], name: str, arguments: List[str],
          stop: threading.Event) -> int:
    context = rclpy.get_default_context()
    executor = SingleThreadedExecutor()
    node: Optional[Node] = None
    try:
        node = factory()
        executor.add_node(node)
        while not stop.is_set() and executor.context.ok():
            executor.spin_once(timeout_sec=SIGNAL_LATENCY)
    except (CtidError, ParameterException) as error:
        print(f'{name}: error: {error}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # The node is held here, not taken back from the executor: shutdown() forgets its
        # nodes, and a node left undestroyed kept its threads (the estimator's too) running
        # into the interpreter's exit, which now and then ended in a segmentation fault.
        try:
            if node is not None:
                node.destroy_node()
        finally:
            try:
                executor.shutdown()
                rclpy.try_shutdown()
            finally:
                # The DDS participant and its threads end with the context's handle, here
                # rather than at exit, when the libraries they use are being unloaded.
                context.destroy()
    return 0
