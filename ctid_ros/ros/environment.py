"""
What ROS needs of the environment, checked before rclpy starts: one line, not a traceback.

Imports no rclpy and no numerical library, so ``ctid_node`` and the ROS commands of ``ctid``
(``record``, ``echo``, ``node``) check the environment first and print a one-line error
with exit status 2 (:func:`check_ros_environment`).
"""

import os
from typing import Mapping

from ctid_ros.errors import ConfigError

__all__ = ['MAX_DOMAIN_ID', 'PATH_HEAD', 'PATH_TAIL', 'SHORT_PATH', 'check_ros_environment',
           'shown_path']

# Fast DDS refuses a domain above 232: its ports would exceed 65535.
MAX_DOMAIN_ID = 232
# A path in an error message keeps its first and last characters; one up to SHORT_PATH
# characters is shown whole.
PATH_HEAD, PATH_TAIL = 60, 40
SHORT_PATH = PATH_HEAD + PATH_TAIL + 20


def check_ros_environment(environment: Mapping[str, str]) -> None:
    """
    Refuse what rcl and DDS would fail on, before anything joins the graph.

    rcl refuses a ``ROS_DOMAIN_ID`` that is not a number only when the context starts, and
    Fast DDS one above 232 (its ports would exceed 65535) when the first node is created, with
    a log line and exit status 1; rcl cannot start either where it cannot create its log
    directory (``ROS_LOG_DIR``, else ``$ROS_HOME/log``, else ``~/.ros/log``), which this
    creates as rcl would.

    Raises
    ------
    ConfigError
        If ``ROS_DOMAIN_ID`` is set and is not an integer from 0 to 232, or the log directory
        cannot be created or written.

    """
    value = environment.get('ROS_DOMAIN_ID', '').strip()
    if value and not (value.isdigit() and int(value) <= MAX_DOMAIN_ID):
        shown = value if len(value) <= 40 else value[:37] + '...'
        raise ConfigError(f'the environment variable ROS_DOMAIN_ID={shown!r} is not a ROS '
                          f'domain: give an integer from 0 to {MAX_DOMAIN_ID} (0 to 101 are '
                          'safe on every platform), or unset it for domain 0')
    if environment.get('ROS_LOG_DIR'):
        variable, directory = 'ROS_LOG_DIR', environment['ROS_LOG_DIR']
    elif environment.get('ROS_HOME'):
        variable, directory = 'ROS_HOME', os.path.join(environment['ROS_HOME'], 'log')
    else:
        variable, directory = 'HOME', os.path.join(os.path.expanduser('~'), '.ros', 'log')
    try:
        os.makedirs(os.path.expanduser(directory), exist_ok=True)
        writable = os.access(os.path.expanduser(directory), os.W_OK)
    except OSError as error:
        problem = error.strerror or str(error)
    else:
        problem = None if writable else 'not writable'
    if problem is not None:
        raise ConfigError(f'ROS cannot write its log files in {shown_path(directory)} ('
                          f'{problem}; from the environment variable {variable}): set '
                          'ROS_LOG_DIR to a writable directory')


def shown_path(name: object) -> str:
    """Return a path for an error message: a long one cut in the middle, with its length."""
    text = os.fsdecode(name) if isinstance(name, (str, bytes, os.PathLike)) else str(name)
    if len(text) <= SHORT_PATH:
        return text
    return f'{text[:PATH_HEAD]}...{text[-PATH_TAIL:]} ({len(text)} characters)'
