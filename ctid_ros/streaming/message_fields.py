"""
Numeric fields of ROS messages addressed by path, without importing ROS.

A field path names one number inside a message::

    data                    std_msgs/Float64
    effort[0]               sensor_msgs/JointState
    position[wheel_left]    sensor_msgs/JointState, the joint named wheel_left
    twist.linear.x          geometry_msgs/TwistStamped
    pose.pose.position.z    nav_msgs/Odometry
    points[3].positions[1]  trajectory_msgs/JointTrajectory

The grammar is identifiers (a letter, then letters, digits and underscores) joined by dots, each
optionally followed by selectors in brackets: a non-negative integer index, or a joint name
(letters, digits and ``_ - . / :``, with at least one letter or underscore). A name selects the
element at the index of that name in the message's ``name`` list, or ``joint_names`` list, the
field next to the array (JointState-like messages): ``position[wheel_left]`` is
``position[i]`` with ``name[i] == 'wheel_left'``, looked up in every message, since publishers
need not keep the order. Nothing else is accepted, in particular no name starting with ``_``,
so a path can never reach private or dunder attributes.

The same compiled :class:`FieldPath` reads messages from every source the package meets, all of
which expose fields as attributes:

* rclpy message classes (field list from ``get_fields_and_field_types()``);
* ``rosbags`` deserialised dataclasses (``dataclasses.fields``, without ``__msgtype__``);
* ``mcap_ros2`` decoded objects (``__slots__``) and other plain objects (``vars``).

Only declared fields are followed, so ``data.real`` or a method name is refused even though
Python would resolve it.
"""

from dataclasses import dataclass, fields, is_dataclass
import functools
import numbers
import re
from typing import Any, Optional, Sequence, Tuple, Union

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.contract import NANOSECONDS
import numpy as np

__all__ = ['FieldPath', 'MissingElementError', 'NAME_FIELDS', 'Step', 'Key', 'extract',
           'extract_values', 'has_header_stamp', 'message_fields', 'message_stamp',
           'parse_field_path', 'sample_stamp', 'sample_stamps']

_NAME = r'[A-Za-z][A-Za-z0-9_]*'
_KEY = r'[A-Za-z0-9_./:-]*[A-Za-z_][A-Za-z0-9_./:-]*'
_SELECTOR = rf'\[(?:[0-9]+|{_KEY})\]'
_SEGMENT = rf'{_NAME}(?:{_SELECTOR})*'
_PATH = re.compile(rf'{_SEGMENT}(?:\.{_SEGMENT})*')
_TOKEN = re.compile(rf'({_NAME})|\[([0-9]+)\]|\[({_KEY})\]|\.')
_GRAMMAR = ('a field path is names joined by dots, each optionally followed by non-negative '
            "integer indices or joint names in brackets, e.g. 'data', 'effort[0]', "
            "'position[wheel_left]', 'twist.linear.x'; a name starts with a letter and contains "
            'only letters, digits and underscores')
# Fields that name the elements of the arrays next to them (sensor_msgs/JointState has name,
# sensor_msgs/MultiDOFJointState and control_msgs types joint_names).
NAME_FIELDS = ('name', 'joint_names')
# Names listed in an error message at most.
_LISTED_NAMES = 20


@dataclass(frozen=True)
class Key:
    """A selector by name: the element whose name in the sibling ``name`` list is :attr:`name`."""

    name: str

    def __str__(self) -> str:
        return self.name


Step = Union[str, int, Key]


@dataclass(frozen=True)
class FieldPath:
    """
    A parsed field path: a sequence of attribute names (str) and indices (int).

    Build it with :func:`parse_field_path`; read a message with :func:`extract`.
    """

    text: str
    steps: Tuple[Step, ...]

    def __str__(self) -> str:
        return self.text


@functools.lru_cache(maxsize=256)
def parse_field_path(text: str) -> FieldPath:
    """
    Parse and check a field path such as ``'pose.pose.position.z'`` or ``'effort[0]'``.

    Parameters
    ----------
    text : str
        The path; surrounding whitespace is ignored.

    Returns
    -------
    FieldPath
        The compiled accessor.

    Raises
    ------
    ConfigError
        If the text does not follow the grammar; the message states the grammar.

    """
    if not isinstance(text, str):
        raise ConfigError(f'a field path must be a string, got {type(text).__name__}')
    stripped = text.strip()
    if not _PATH.fullmatch(stripped):
        raise ConfigError(f'invalid field path {text!r}: {_GRAMMAR}')
    steps = tuple(name if name else int(index) if index else Key(key)
                  for name, index, key in _TOKEN.findall(stripped) if name or index or key)
    return FieldPath(stripped, steps)


@functools.lru_cache(maxsize=256)
def _declared_fields(cls: type) -> Optional[Tuple[str, ...]]:
    """Return the field names a message class declares, or None if only instances know them."""
    introspect = getattr(cls, 'get_fields_and_field_types', None)
    if callable(introspect):
        return tuple(introspect())
    if is_dataclass(cls):
        return tuple(item.name for item in fields(cls) if not item.name.startswith('_'))
    slots = [name for klass in cls.__mro__ for name in vars(klass).get('__slots__', ())]
    if slots:
        return tuple(name for name in slots if not name.startswith('_'))
    return None


def message_fields(message) -> Tuple[str, ...]:
    """
    List the public fields of a message (rclpy, rosbags dataclass or mcap_ros2 object).

    Returns
    -------
    tuple of str
        Field names in declaration order; empty for a primitive value.

    """
    if isinstance(message, (numbers.Number, str, bytes, np.ndarray)):
        return ()
    declared = _declared_fields(type(message))
    if declared is not None:
        return declared
    try:
        return tuple(name for name in vars(message) if not name.startswith('_'))
    except TypeError:
        return ()


def extract_values(message, paths: Sequence[Union[FieldPath, str]]) -> Union[float, np.ndarray]:
    """Read one number per path (see :func:`extract`): a float for one path, else an array."""
    if len(paths) == 1:
        return extract(message, paths[0])
    return np.array([extract(message, path) for path in paths])


def _type_name(value) -> str:
    return type(value).__name__


def _describe(value) -> str:
    names = message_fields(value)
    if names:
        return f'available fields: {", ".join(names)}'
    if _is_array(value):
        return f'it is an array of length {len(value)}'
    return f'it is a {_type_name(value)}, which has no fields'


def _is_array(value) -> bool:
    return not isinstance(value, (str, bytes)) and (
        isinstance(value, (Sequence, np.ndarray)) or hasattr(value, 'typecode'))


def _location(path: FieldPath, depth: int) -> str:
    """Render the part of the path already followed, for error messages."""
    text = ''
    for step in path.steps[:depth]:
        text += f'[{step}]' if not isinstance(step, str) else (f'.{step}' if text else step)
    return text or 'the message'


def _listed(names: Sequence[str]) -> str:
    shown = ', '.join(str(name) for name in names[:_LISTED_NAMES])
    more = len(names) - _LISTED_NAMES
    return (shown + (f' and {more} more' if more > 0 else '')) if names else 'none (empty)'


class MissingElementError(ConfigError):
    """
    A message lacks the element a field path selects (a joint, an index).

    The joint is not in its names, or the index is past the end of its array. Another
    message of the same topic may have it (``/joint_states`` of several drivers, an ``effort``
    array a driver leaves empty at times), so the replay skips and counts such a message, as
    the live node does, where a path the message type cannot have raises its
    :class:`ConfigError` at once.
    """


def _named_index(path: FieldPath, depth: int, parent, key: Key) -> int:
    """Return the index of ``key`` in the name list next to the array at ``depth``."""
    where = _location(path, depth)
    available = message_fields(parent) if parent is not None else ()
    field = next((name for name in NAME_FIELDS if name in available), None)
    if field is None:
        raise ConfigError(f'field {path}: selecting [{key}] by name needs a list of names '
                          f'({" or ".join(NAME_FIELDS)}) next to {where}; '
                          f'{_describe(parent)}')
    names = getattr(parent, field)
    # A list or tuple is searched in place: a message of millions of joints is not copied.
    if not isinstance(names, (list, tuple)):
        names = list(names)
    try:
        return names.index(key.name)
    except ValueError:
        raise MissingElementError(f'field {path}: no joint {key.name!r} in {field}; names '
                                  f'seen: {_listed(names)}') from None


def extract(message, path: Union[FieldPath, str]) -> float:
    """
    Read one number from a message.

    Parameters
    ----------
    message : object
        An rclpy message, a ``rosbags`` dataclass or an ``mcap_ros2`` decoded object.
    path : FieldPath or str
        The field to read; a string is parsed (and cached).

    Returns
    -------
    float
        The value, converted to float (integers and booleans included). NaN and infinity are
        returned as they are: the sample buffer rejects and counts them.

    Raises
    ------
    ConfigError
        If a field does not exist (the message lists the fields available at that level), an
        index is applied to a non-array, or the value reached is not a number.
    MissingElementError
        If an index is out of range (the message gives the array length) or a joint is not in
        the message's names (the message lists them).

    """
    if not isinstance(path, FieldPath):
        path = parse_field_path(path)
    value = message
    # The message holding the current field: its name list resolves a Key.
    parent = None
    for depth, step in enumerate(path.steps):
        where = _location(path, depth)
        if isinstance(step, str):
            if step not in message_fields(value):
                raise ConfigError(f'field {path}: {where} ({_type_name(value)}) has no field '
                                  f'{step!r}; {_describe(value)}')
            parent, value = value, getattr(value, step)
            continue
        if not _is_array(value):
            raise ConfigError(f'field {path}: {where} is not an array, cannot take '
                              f'[{step}]; {_describe(value)}')
        index = step if isinstance(step, int) else _named_index(path, depth, parent, step)
        if index >= len(value):
            named = '' if isinstance(step, int) else f' (of {str(step)!r})'
            raise MissingElementError(f'field {path}: index {index}{named} out of range for '
                                      f'{where}, an array of length {len(value)}')
        parent, value = None, value[index]
    # numpy's bool is no numbers.Real: the elements of a bool[] that rosbags decodes.
    if isinstance(value, (numbers.Real, np.bool_)):
        return float(value)
    hint = f'; {_describe(value)}' if message_fields(value) or _is_array(value) else ''
    raise ConfigError(f'field {path} is not a number: it is a {_type_name(value)}{hint}')


def message_stamp(message) -> Optional[int]:
    """
    Return ``header.stamp`` in integer nanoseconds, or None if the message has no usable stamp.

    A message without a ``header`` field (``std_msgs/Float64``), or whose stamp lacks
    ``sec``/``nanosec``, gives None. So does an all-zero stamp: it means the publisher left the
    header unset, and the caller should fall back to the receive time rather than put every
    sample at the epoch.
    """
    if 'header' not in message_fields(message):
        return None
    header = message.header
    if 'stamp' not in message_fields(header):
        return None
    stamp = header.stamp
    if not {'sec', 'nanosec'} <= set(message_fields(stamp)):
        return None
    nanoseconds = int(stamp.sec) * NANOSECONDS + int(stamp.nanosec)
    return nanoseconds or None


def sample_stamps(header_ns: Optional[np.ndarray], receive_ns: np.ndarray,
                  stamp_source: str) -> np.ndarray:
    """
    Return the stamps (ns) of many messages' samples: :func:`sample_stamp`'s rule on arrays.

    ``header_ns`` holds each message's ``header.stamp`` (0 where it is zero), or is None for a
    type without one; ``receive_ns`` the receive (log) times.
    """
    receive_ns = np.asarray(receive_ns, dtype=np.int64)
    if stamp_source == 'header' and header_ns is not None:
        return np.where(header_ns != 0, header_ns, receive_ns)
    return receive_ns


def has_header_stamp(message) -> bool:
    """Return True if the message has a ``header.stamp`` (zero or not)."""
    if 'header' not in message_fields(message):
        return False
    header = message.header
    return 'stamp' in message_fields(header) and \
        {'sec', 'nanosec'} <= set(message_fields(header.stamp))


def sample_stamp(msg: Any, receive_ns: int, stamp_source: str) -> int:
    """
    Return the stamp (ns) a message's samples are filed under (live node and replay alike).

    ``header.stamp`` when ``stamp_source`` is ``'header'`` and the message has a non-zero one,
    otherwise ``receive_ns``: the source/receive time live, the recorder's log time in a bag.
    """
    if stamp_source == 'header':
        stamp = message_stamp(msg)
        if stamp is not None:
            return stamp
    return int(receive_ns)
